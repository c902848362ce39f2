"""Training and evaluation runs on disk: what ``twinrl train`` / ``twinrl eval`` (and the loop) do.

A **training run** directory holds::

    run.json          "kind": "train", algo, env, seed and the full trainer config (what
                      --resume must match)
    metrics.csv       one row per epoch (flushed as it goes); tb/ TensorBoard events
    train_state/      orbax steps of the whole trainer state (resumable trainers only)
    policy/           the returned policy's checkpoint (``twinrl.learn.checkpoint``)
    curve.png         return vs epoch, env steps and wall clock
    summary.json      final figures: the returned policy's epoch (the last, or the one the
                      trainer's metrics mark ``kept``: imitation keeps its best round)

``train_run`` resumes a killed run (``resume=True``) from the last complete ``train_state`` step;
because trainers draw every random number from the key in their state, the resumed run ends
with the same parameters and metrics as an uninterrupted one.

Under ``jax.distributed`` (``twinrl.learn.distributed``) every process calls ``train_run`` with
the same arguments and ``out`` (a shared file system); process 0 alone writes the directory
(the others check it, train their share and return the same summary), and any process count,
one included, resumes from it.

The algorithm registry maps the CLI's names to trainers: ``pods`` and ``pods2`` (PODS, first and
second order), ``hds``, ``shac`` and the Brax baselines ``ppo`` and ``apg``. Per-task tuned
defaults are one table, ``twinrl.learn.tuned.TUNED[algo][env_name]`` (MuJoCo Playground's
habit of keeping RL configs apart from task configs), applied before the user's overrides.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from twinrl.learn import distributed, tuned

__all__ = ["ALGORITHMS", "Algorithm", "algorithm", "make_config", "parse_overrides", "train_run",
           "continue_run", "eval_run", "policy_video", "RunError", "progress_figures",
           "env_from_meta"]


class RunError(Exception):
    """Bad arguments to a run (unknown algorithm, config field, mismatched resume)."""


class Algorithm(NamedTuple):
    module: str
    train: str
    config: str
    overrides: dict[str, Any]
    resumable: bool


ALGORITHMS: dict[str, Algorithm] = {
    "pods": Algorithm("twinrl.learn.pods", "train", "PODSConfig", {}, True),
    "pods2": Algorithm("twinrl.learn.pods", "train", "PODSConfig", {"order": 2}, True),
    "hds": Algorithm("twinrl.learn.hds", "train", "HDSConfig", {}, True),
    "shac": Algorithm("twinrl.learn.shac", "train", "SHACConfig", {}, True),
    "ppo": Algorithm("twinrl.learn.baselines", "ppo_train", "PPOConfig", {}, False),
    "apg": Algorithm("twinrl.learn.baselines", "apg_train", "APGConfig", {}, False),
    "imitation": Algorithm("twinrl.learn.imitation", "train", "ImitationConfig", {}, False),
    "sensing": Algorithm("twinrl.learn.sensing", "train", "SensingConfig", {}, False),
}


def algorithm(name: str) -> tuple[Algorithm, Callable, type]:
    """``(entry, train_fn, ConfigClass)`` of a registered algorithm."""
    if name not in ALGORITHMS:
        raise RunError(f"unknown algorithm {name!r}; choose one of {', '.join(ALGORITHMS)}")
    entry = ALGORITHMS[name]
    module = importlib.import_module(entry.module)
    return entry, getattr(module, entry.train), getattr(module, entry.config)


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``["lr=1e-3", "hidden=[64,64]"]`` -> dict; values parsed as JSON, else kept as strings."""
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise RunError(f"override {item!r} must look like field=value")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = json.loads(v)
        except json.JSONDecodeError:
            out[k.strip()] = v
    return out


def _replace(config, overrides: dict[str, Any], what: str):
    """``dataclasses.replace`` with dotted keys into nested dataclass fields."""
    names = {f.name: f for f in dataclasses.fields(config)}
    flat, nested = {}, {}
    for k, v in overrides.items():
        head, _, rest = k.partition(".")
        if head not in names:
            raise RunError(f"{type(config).__name__} has no field {head!r} ({what}); fields: "
                           f"{', '.join(names)}")
        if rest:
            nested.setdefault(head, {})[rest] = v
        else:
            cur = getattr(config, head)
            if dataclasses.is_dataclass(cur) and isinstance(v, dict):
                nested.setdefault(head, {}).update(v)
            else:
                flat[head] = tuple(v) if isinstance(v, list) else v
    for head, sub in nested.items():
        flat[head] = _replace(getattr(config, head), sub, what)
    try:
        return dataclasses.replace(config, **flat)
    except (TypeError, ValueError) as e:
        raise RunError(f"invalid {type(config).__name__} ({what}): {e}") from None


def make_config(algo: str, env_name: str, overrides: dict[str, Any] | None = None):
    """The algorithm's config for a task: class defaults, then the task's tuned values, then the
    algorithm entry's (``pods2``: order 2), then the user's ``overrides``."""
    entry, _, cls = algorithm(algo)
    config = cls()
    config = _replace(config, tuned.overrides(algo, env_name), f"tuned for {env_name}")
    config = _replace(config, entry.overrides, f"algorithm {algo}")
    return _replace(config, overrides or {}, "override")


def _length_overrides(config, epochs: int | None, steps: int | None) -> dict[str, Any]:
    fields = {f.name for f in dataclasses.fields(config)}
    out = {}
    if epochs is not None:
        if "epochs" not in fields:
            raise RunError(f"--epochs does not apply to {type(config).__name__}; use --steps")
        out["epochs"] = int(epochs)
    if steps is not None:
        key = next((k for k in ("num_timesteps", "env_steps", "steps") if k in fields), None)
        if key is None:
            raise RunError(f"--steps does not apply to {type(config).__name__}; use --epochs")
        out[key] = int(steps)
    return out


def train_run(env_name: str, algo: str, out: str | Path, *, seed: int = 0,
              epochs: int | None = None, steps: int | None = None,
              overrides: dict[str, Any] | None = None, resume: bool = False,
              progress: bool = True, env=None, train_kwargs: dict[str, Any] | None = None,
              checkpoint_every: int = 1, env_spec: dict[str, Any] | None = None
              ) -> dict[str, Any]:
    """Train ``algo`` on ``env_name`` into ``out`` (see the module docstring); returns the summary.

    ``env`` may be given to train in a specific simulator (``envs.make(name, system=...)``: an
    identified system, the loop); the policy checkpoint keeps that system (``system.json``), so
    ``eval_run`` rebuilds it. ``train_kwargs`` are passed to the trainer (HDS's ``dynamics``).
    ``env_spec``: a user's MJCF task (``envs.mjcf.task_spec``, with ``env`` built from it), kept
    in ``run.json`` and the checkpoint so ``--resume`` and ``eval_run`` rebuild that task.
    """
    from twinrl import envs, report
    from twinrl.envs.system import system_of
    from twinrl.learn.checkpoint import TrainStateCheckpointer, save_policy

    entry, train_fn, _ = algorithm(algo)
    config = make_config(algo, env_name, overrides)
    config = _replace(config, _length_overrides(config, epochs, steps), "length")
    env = env if env is not None else envs.make(env_name)
    if hasattr(config, "lengths"):  # a config that does not fit the task: one line, before files
        try:
            config.lengths(env)
        except ValueError as e:
            raise RunError(f"{type(config).__name__} on {env_name}: {e} (episode length "
                           f"{env.episode_length}; --set horizon=... or rollout_length=...)"
                           ) from None
    out = Path(out)
    run_doc = {"kind": "train", "algo": algo, "env": env_name, "seed": int(seed),
               "config": report.to_jsonable(config), "config_class": type(config).__name__}
    if env_spec is not None:
        run_doc["mjcf"] = env_spec
    run_file = out / "run.json"
    state_dir = out / "train_state"
    restore = None
    ckpt = None
    if run_file.exists():
        previous = json.loads(run_file.read_text())
        if not resume:
            raise RunError(f"{out} already holds a training run ({previous.get('algo')} on "
                           f"{previous.get('env')}); pass --resume to continue it or choose a new "
                           f"--out")
        now = report.to_jsonable(run_doc)
        # "kind" says what the directory is; a run started before it was recorded resumes
        diff = sorted(k for k in (set(previous) | set(now)) - {"kind"}
                      if previous.get(k) != now.get(k))
        if diff:
            raise RunError(f"--resume: {run_file} was started with different settings "
                           f"({', '.join(diff)}); resume with the same --algo/--env/--seed/--set")
    elif resume and (out / "policy").exists():
        raise RunError(f"--resume: {out} has no run.json")
    if entry.resumable:
        ckpt = TrainStateCheckpointer(state_dir, every=checkpoint_every)
        if resume and ckpt.latest_epoch() is not None:
            restore = ckpt.restore
    elif resume:
        raise RunError(f"{algo} (a trainer without saved state) cannot resume; run it again "
                       f"without --resume")
    distributed.barrier("twinrl-train-run-checked")  # every process read run.json before it changes
    own = distributed.is_writer()
    if own:
        report.write_json(run_file, run_doc)

    writer = report.MetricsWriter(out) if own else _NoMetrics(out)
    total = int(getattr(config, "epochs", 0) or 0)
    title = f"train {algo} on {env_name}"
    bar, task = _progress_bar(title, total, enabled=progress and own)
    lines = _progress_lines(title, enabled=progress and own and bar is None)

    finished = [0]                     # epochs done (trainers number epochs from 0 or 1)

    def on_restore(template):
        state, history = restore(template)
        writer.rewrite(history)
        finished[0] = len(history.get("epoch", []))
        if bar is not None:
            bar.update(task, completed=finished[0])
        return state, history

    def progress_fn(epoch, row):
        writer.write(epoch, row)
        finished[0] += 1
        if bar is not None:
            bar.update(task, completed=finished[0], figures=progress_figures(row))
        if lines is not None:
            lines.tick(f"epoch {finished[0]}{f'/{total}' if total else ''}  "
                       f"{progress_figures(row)}")

    kwargs = dict(train_kwargs or {})
    kwargs["progress_fn"] = progress_fn
    if entry.resumable:
        kwargs["checkpoint_fn"] = ckpt
        kwargs["restore"] = on_restore if restore is not None else None
    rng = jax.random.key(int(seed))
    t0 = time.perf_counter()
    try:
        if bar is not None:
            bar.start()
        if lines is not None:
            lines("tracing and compiling the first epoch ...")
        policy, params, metrics = train_fn(env, config, rng, **kwargs)
    finally:
        if bar is not None:
            bar.stop()
        if lines is not None:
            lines.close()
        writer.close()
        if ckpt is not None:
            ckpt.close()
    wall = time.perf_counter() - t0
    writer.rewrite(metrics)
    # the returned policy's row: the last, or the one a trainer marks ``kept`` (imitation's best)
    kept = metrics.get("kept") or []
    at = kept.index(1.0) if 1.0 in kept else -1
    final = {k: (v[at] if v else None) for k, v in metrics.items()}
    summary = {"algo": algo, "env": env_name, "seed": int(seed), "final": final,
               "best_return": float(np.nanmax(metrics["return"])) if metrics.get("return") else None,
               "epochs": len(metrics.get("epoch", [])), "wall_s_this_process": wall,
               "policy": str(out / "policy"), "curve": str(out / "curve.png"),
               "metrics_csv": str(writer.path), "resumed": restore is not None}
    if distributed.is_distributed():
        params = distributed.to_host(params)
    if not own:
        return summary
    save_policy(out / "policy", policy, params, system=system_of(env), algo=algo, env=env_name,
                env_config=_env_config(env), config=config, seed=int(seed),
                metrics={k: v for k, v in final.items() if v is not None},
                **({"mjcf": env_spec} if env_spec is not None else {}))
    summary["curve"] = str(_plot_training(out / "curve.png", metrics, f"{algo} on {env_name}"))
    report.write_json(out / "summary.json", summary)
    return summary


class _NoMetrics:
    """``report.MetricsWriter``'s interface writing nothing: a process other than the writer."""

    def __init__(self, directory):
        self.path = Path(directory) / "metrics.csv"

    def write(self, step, row) -> None:
        pass

    def rewrite(self, history) -> None:
        pass

    def close(self) -> None:
        pass


def continue_run(env_name: str, algo: str, out: str | Path, **kwargs) -> dict[str, Any]:
    """``train_run`` into ``out`` that survives being killed: a resumable trainer continues from
    its last saved step; a Brax trainer (which keeps no state between its own evaluations) starts
    again from scratch, its partial directory removed. What the loop and the oracle call."""
    import shutil

    entry, _, _ = algorithm(algo)
    out = Path(out)
    if not entry.resumable and out.exists() and distributed.is_writer():
        shutil.rmtree(out)
    distributed.barrier("twinrl-continue-run")  # every process sees what process 0 left
    return train_run(env_name, algo, out, resume=entry.resumable, **kwargs)


def _env_config(env) -> dict[str, Any]:
    from twinrl import report

    return report.to_jsonable(env.config)


def _progress_bar(title: str, total: int, enabled: bool):
    """A live rich bar on a terminal; (None, None) elsewhere (a log shows nothing of it)."""
    from twinrl import report

    if not enabled or not report.console.is_terminal:
        return None, None
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                               TimeElapsedColumn, TimeRemainingColumn)

    bar = Progress(TextColumn(f"[bold]{title}"), BarColumn(), MofNCompleteColumn(),
                   TextColumn("{task.fields[figures]}"),
                   TimeElapsedColumn(), TimeRemainingColumn(), console=report.console,
                   auto_refresh=True)
    task = bar.add_task("train", total=total or None, figures="")
    return bar, task


def _progress_lines(title: str, enabled: bool):
    """Where no live bar can show (a log, a pipe): a dim line a while (``twinrl.progress``), the
    first while the first epoch traces and compiles."""
    if not enabled:
        return None
    from twinrl.progress import ProgressLines

    return ProgressLines(title)


def progress_figures(row) -> str:
    """The progress bar's figures: only those the trainer reported and that are finite (PPO
    reports no gradient norm: the bar showed 'grad nan')."""
    out = []
    for key, label, fmt in (("return", "return", ".2f"), ("grad_norm", "grad", ".2e")):
        v = row.get(key)
        if v is not None and np.isfinite(v):
            out.append(f"{label} {v:{fmt}}")
    return "  ".join(out)


def _plot_training(path: Path, metrics: dict[str, list[float]], title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ret = np.asarray(metrics.get("return", []), float)
    # one panel per x the trainer reports (imitation and sensing count no env steps)
    panels = [(k, lab) for k, lab in (("epoch", "epoch"), ("env_steps", "simulated env steps"),
                                      ("wall_s", "wall clock (s)"))
              if k in metrics or k == "epoch"]
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.4), dpi=110,
                             squeeze=False)
    axes = axes[0]
    for ax, (key, label) in zip(axes, panels):
        x = np.asarray(metrics.get(key, np.arange(len(ret))), float)[:len(ret)]
        ax.plot(x, ret[:len(x)], marker=".")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("evaluation return")
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------------ eval
def env_from_meta(meta: dict[str, Any], system=None):
    """The simulator a checkpoint's policy was trained in: its task and config, built from the
    ``system`` it saved (None, for checkpoints without one: the task's nominal simulator)."""
    from twinrl import envs

    name = meta.get("env")
    if meta.get("mjcf"):  # a user's MJCF task: its file and reward, as trained
        from twinrl.envs.mjcf import from_spec

        try:
            return from_spec(meta["mjcf"])
        except (ValueError, TypeError, OSError) as e:
            raise RunError(f"checkpoint's MJCF task cannot be rebuilt: {e}") from None
    if name not in envs.names():
        raise RunError(f"checkpoint's env {name!r} is not a registered task")
    cfg = meta.get("env_config") or {}
    default = dataclasses.asdict(envs.default_config(name))
    overrides = {k: v for k, v in cfg.items() if k in default and default[k] != v}
    try:
        return envs.make(name, system=system, **overrides)
    except ValueError as e:       # a system of another task
        raise RunError(f"checkpoint's system cannot build {name!r}: {e}") from None


def eval_run(checkpoint: str | Path, out: str | Path, *, real: bool = False, episodes: int = 5,
             seed: int = 0, video: bool = True, size: tuple[int, int] = (320, 240),
             progress: bool = True, policy: tuple[Callable, Any] | None = None,
             residual: bool = False) -> dict[str, Any]:
    """Evaluate a policy checkpoint in the simulator or (``real``) its real twin; write
    ``summary.json`` and an MP4 of the first episode. Returns the summary. ``policy``: an
    ``(apply, params)`` acting in the checkpoint's stead on its task and system (e.g. the policy
    plus a residual correction: ``residual`` says so in the summary)."""
    from twinrl import report
    from twinrl.envs.system import system_of
    from twinrl.learn.checkpoint import load_policy, load_system

    if episodes < 1:
        raise RunError(f"--episodes must be >= 1, got {episodes}")
    network, params, meta = load_policy(checkpoint)
    saved = load_system(checkpoint)
    env = env_from_meta(meta, saved)
    out = Path(out)
    apply, params = policy if policy is not None else (network.apply, params)
    act = jax.jit(apply)
    frames: list[np.ndarray] = []
    if real:
        returns = _eval_real(env, env if meta.get("mjcf") else meta["env"], act, params,
                             episodes, seed, frames if video else None, size, progress)
    else:
        from twinrl.learn.common import make_evaluator

        returns = np.asarray(make_evaluator(env, apply, episodes)(
            params, jax.random.key(seed)), float).tolist()
        if video:
            frames = _sim_frames(env, act, params,
                                 jax.random.split(jax.random.key(seed), episodes)[0], size)
    files = {}
    if video and frames:
        files["video"] = str(report.write_video(out / f"{'real' if real else 'sim'}.mp4", frames,
                                                fps=1.0 / env.dt))
    summary = {"kind": "eval", "checkpoint": str(checkpoint), "env": meta["env"],
               "algo": meta.get("algo"),
               "where": "real twin" if real else "sim", "seed": int(seed),
               "episodes": int(episodes), "residual": bool(residual), "returns": returns,
               "mean_return": float(np.mean(returns)), "std_return": float(np.std(returns)),
               "system": {"from": "checkpoint" if saved is not None else "nominal (none saved)",
                          **system_of(env).to_json()},
               "files": files}
    report.print_table(f"eval {meta.get('algo')} on {meta['env']} ({summary['where']})",
                       ["episodes", "mean return", "std", "min", "max"],
                       [[episodes, summary["mean_return"], summary["std_return"],
                         float(np.min(returns)), float(np.max(returns))]])
    report.write_json(out / "summary.json", summary)
    return summary


def _eval_real(env, name, act, params, episodes, seed, frames, size, progress):
    from twinrl.real.twin import make_real

    twin = make_real(name, seed=seed, width=size[0], height=size[1])
    returns = []
    try:
        for ep in range(episodes):
            obs, _ = twin.reset(seed=seed + ep)
            ret, done = 0.0, False
            while not done:
                a = np.asarray(act(params, obs), np.float32)
                obs, r, term, trunc, _ = twin.step(a)
                ret += float(r)
                done = term or trunc
                if frames is not None and ep == 0:
                    frames.append(twin.render_images(twin.camera, ("rgb",))["rgb"])
            returns.append(ret)
    finally:
        twin.close()
    return returns


def policy_video(env, policy, params, path, *, seed: int = 0, size: tuple[int, int] = (320, 240),
                 camera: str | int | None = None, steps: int | None = None) -> Path:
    """One deterministic episode of ``policy`` (a ``Network``, or any ``apply(params, obs)``)
    in ``env``'s simulator from reset key ``seed``, drawn by MuJoCo's renderer and written to
    ``path`` (MP4 at the control rate; ``report.write_video``). The states are MJX's, only the
    pixels come from OpenGL. ``camera``: a camera of the MJCF (name or id); default the task's
    first camera, else the MJCF's first, else where MuJoCo's viewer opens (the free camera), so
    a user's MJCF without cameras (``envs.from_mjcf``) gets a video too. ``steps``: default the
    episode length. Returns the path written (``.gif`` without ffmpeg)."""
    from twinrl import report

    apply = getattr(policy, "apply", policy)
    frames = _sim_frames(env, jax.jit(apply), params, jax.random.key(int(seed)), size, camera,
                         steps)
    return report.write_video(path, frames, fps=1.0 / env.dt)


def _sim_frames(env, act, params, key, size, camera=None, steps=None) -> list[np.ndarray]:
    """An episode of the simulator from reset ``key``, drawn by MuJoCo's renderer
    (``policy_video``)."""
    import mujoco

    from twinrl.render.opengl import CameraRenderer

    m = env.sim.mj_model
    camera = env.default_camera if camera is None else camera
    T = int(steps or env.episode_length)
    if T < 1:
        raise ValueError(f"steps must be >= 1, got {T}")
    state = jax.jit(env.reset)(key)
    step = jax.jit(env.step)
    d = mujoco.MjData(m)
    renderer = CameraRenderer(m, *size)
    frames = []
    try:
        for _ in range(T):
            state = step(state, act(params, state.obs))
            d.qpos[:] = np.asarray(state.pipeline_state.qpos)
            mujoco.mj_forward(m, d)
            frames.append(renderer.images(d, camera, ("rgb",))["rgb"])
    finally:
        renderer.close()
    return frames
