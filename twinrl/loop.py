"""The whole loop, Real2Sim -> Learn@Sim -> Sim2Real, in rounds, resumable: ``twinrl run``.

What a user comes for: hand twinrl a system it cannot see inside (a task's real twin), let it watch
a few episodes, get back a policy that works on that system. Round 0 records ``K`` episodes with a
safe exciting open-loop policy (``twinrl.real2sim.sysid.excitation_actions``). Every round ``r >= 1``:

1. **sysid** on every real transition recorded so far -> ``PhysParams`` and action latency
   (``twinrl.real2sim.sysid``);
2. **hybrid refit**: the residual dynamics on top of the identified simulator
   (``twinrl.sim2real.hybrid``);
3. **learn in sim**, in the identified simulator: Brax PPO by default (see ``LoopConfig.algo`` for
   the measurements behind that choice), or any trainer of ``twinrl.learn.runner.ALGORITHMS``;
   with ``algo="hds"``, HDS with a fraction of rollouts through the hybrid model;
4. **deploy with residual adaptation**: the residual policy (zero at first, so the first deployment
   is exactly the simulator's policy) is trained through the hybrid model from recorded real states
   (``twinrl.sim2real.residual``) and kept only if it does not lower the full-episode return through
   that model (``residual.accept``; else pi_sim is deployed), then ``K`` real episodes are run and
   recorded.

Bookkeeping per round: real steps used so far, identified-parameter errors, sim return, real return
and the oracle's return. The **oracle** (evaluation only, never fed back) is a policy trained the
same way in a simulator given the twin's *true* parameters, evaluated on the real twin; the
parameter errors likewise read the twin's hidden truth. Both happen in evaluation functions
(``twinrl.eval``, the only module
outside ``twinrl/real`` allowed to read the twin's oracle) that the learning stages never call.

The real twin is served in another process (``twinrl.real.remote.TwinClient``): the loop holds a
``gymnasium.Env`` client with no model or perturbation in it, whose hidden perturbation is seeded
by the public seed and a secret salt. Everything evaluation writes (the salt, ``twin.json``; the
oracle's training, ``oracle/``; the per-round evaluation records, ``evaluation.json``) goes to
``OUT/eval/``, a directory the stages never read; ``summary.json`` and the report merge it in at
the end.

Resume: every stage writes its outputs, then marks itself done in ``progress.json`` (atomically).
Real episodes go to ``dataset/`` as they happen (``twinrl.real.dataset``), so a run killed at any
moment loses nothing recorded; ``resume=True`` skips the finished stages, counts the episodes the
dataset already holds for the interrupted collection stage, and resumes training from its last
saved epoch (``twinrl.learn.runner``).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from twinrl import eval as evaluation
from twinrl import report

__all__ = ["LoopConfig", "run", "LoopError"]


class LoopError(Exception):
    """Bad loop settings or a mismatched resume."""


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Settings of ``twinrl run``."""

    rounds: int = 1
    """Rounds of sysid -> hybrid -> learn -> deploy after the round-0 collection (1 by default:
    the default cartpole loop takes ~7 min 50 s on 2 cores with a cold compilation cache, of the
    10 minutes ``make run`` has; ``summary.json`` gives each stage's seconds)."""
    episodes_per_round: int = 2
    """Real episodes recorded per round (round 0: exciting open-loop actions)."""
    algo: str = "ppo"
    """Learner in sim (``twinrl.learn.runner.ALGORITHMS``). Brax PPO by default, for measured
    reasons (2 cores, ``cartpole_swingup``, seed 0): with SHAC the loop's sim policy stalled at 88
    (balanced, but the cart drifting 5-16 m out, where the ``centered`` reward term is flat and
    gives no gradient back), 68 % of the oracle; SHAC alone ends at 135-189 over 3 seeds, HDS at
    165-198 (``bench/learn.py``, one core, ~160 s against PPO's 108 s). With PPO (3.5 M
    simulated steps, ~3.5 min beside the oracle's) the default loop reaches 99.5-101.7 % of the
    oracle on cartpole real twins 0-2 (entropy cost 0.03, ``learn.tuned.TUNED``). The
    differentiable simulator still does the sysid and the residual adaptation; ``hds`` is the
    learner that mixes the hybrid model into learning (``model_fraction``)."""
    epochs: int | None = None
    """Training epochs per round (None: the algorithm's tuned value for the task)."""
    model_fraction: float = 0.25
    """HDS's beta: fraction of rollouts through the hybrid model (0 disables the hybrid in
    learning; used with ``algo="hds"`` only)."""
    hybrid: bool = True
    """Fit the hybrid residual dynamics each round (needed for the residual policy)."""
    residual: bool = True
    """Adapt with a residual policy trained through the hybrid model before each deployment."""
    sysid_window: int | None = None
    """Multiple-shooting window length (steps) of sysid (None: ``SysidConfig``'s default)."""
    checkpoint_every: int = 10
    """Save the learner's train state every this many epochs (a killed round resumes from the
    last save; saving every epoch costs SHAC on cartpole about a second an epoch)."""
    oracle: bool = True
    """Train and evaluate the oracle policy (evaluation only)."""
    oracle_in_background: bool = True
    """Train the oracle in a lower-priority child process from the start, while the loop's stages
    run: it needs nothing the loop records, and it takes the CPU the stages leave idle."""
    eval_episodes: int = 3
    """Evaluation-only real episodes of the oracle and of the sim policy without adaptation (not
    recorded, not counted as real steps)."""
    video: bool = True
    """Write final.mp4: the final real episode beside the simulator's."""

    def __post_init__(self):
        for name in ("rounds", "episodes_per_round", "eval_episodes", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise LoopError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.model_fraction < 1.0:
            raise LoopError(f"model_fraction must be in [0, 1), got {self.model_fraction}")
        if self.model_fraction > 0 and not self.hybrid:
            raise LoopError("model_fraction > 0 needs the hybrid model (hybrid=True)")
        if self.residual and not self.hybrid:
            raise LoopError("the residual policy is trained through the hybrid model: "
                            "residual=True needs hybrid=True")


# ------------------------------------------------------------------------------ bookkeeping
class _Progress:
    """``progress.json``: the finished stages and the per-round records, written atomically."""

    def __init__(self, path: Path):
        self.path = path
        self.doc = json.loads(path.read_text()) if path.exists() else {"done": [], "rounds": {}}

    def done(self, stage: str) -> bool:
        return stage in self.doc["done"]

    def mark(self, stage: str, **record: Any) -> None:
        if record:
            r = stage.split("/")[0]
            self.doc["rounds"].setdefault(r, {}).update(report.to_jsonable(record))
        if stage not in self.doc["done"]:
            self.doc["done"].append(stage)
        report.write_json(self.path, self.doc)

    def record(self, r: int) -> dict[str, Any]:
        return self.doc["rounds"].get(f"round{r}", {})


def _oracle_child(conn, env_name, seed, out, config, perturbation, nice, parent, secret=None):
    """The oracle's process: lower priority, dies with its parent, sends back the return or the
    error's text."""
    import os
    import signal
    import traceback

    try:  # Linux: SIGKILL when the parent dies, so a killed loop leaves no orphan training
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    # A spawned child gets here after seconds of imports; a parent killed before the prctl sent
    # no signal, so check it is still the parent.
    if os.getppid() != parent:
        os._exit(1)
    os.nice(nice)
    try:
        conn.send(("ok", evaluation.oracle_return(env_name, seed, out, config, False,
                                                  perturbation, secret)))
    except BaseException:  # noqa: BLE001  (sent to the parent, which raises it)
        conn.send(("error", traceback.format_exc()))
    conn.close()


class _OracleProcess:
    """The oracle trained in a child process at a lower CPU priority (``nice``) while the loop's
    stages run: it needs nothing the loop records, and the scheduler gives it the CPU the stages
    leave idle (on 2 cores: sysid's and the residual's single-threaded compiles) instead of
    halving the stages' share, as a thread in this process did. The child dies with this process
    (a killed loop leaves no orphan); the oracle resumes from its own checkpoints."""

    def __init__(self, env_name, seed, out, config, perturbation, nice: int = 10, secret=None):
        import multiprocessing as mp
        import os

        ctx = mp.get_context("spawn")  # a fresh interpreter: JAX is not fork-safe
        self._conn, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_oracle_child, name="twinrl-oracle", daemon=True,
                                 args=(child, env_name, seed, Path(out), config, perturbation,
                                       nice, os.getpid(), secret))
        self._proc.start()
        child.close()

    def running(self) -> bool:
        return self._proc.is_alive() and not self._conn.poll()

    def result(self) -> float:
        try:
            status, value = self._conn.recv()
        except EOFError:
            self._proc.join()
            raise LoopError(f"the oracle's process died (exit code {self._proc.exitcode}) "
                            f"before reporting") from None
        self._proc.join()
        if status == "error":
            raise LoopError(f"the oracle's training failed:\n{value}")
        return value


def _identified_system(rdir: Path):
    """The ``System`` (parameters + action latency) the round's sysid wrote to ``sysid.json``."""
    from twinrl.envs.system import System

    return System.from_json(json.loads((rdir / "sysid.json").read_text())["system"])


# ------------------------------------------------------------------------------ the stages
def _collect(twin, writer, episodes: int, policy, seed: int, rng: np.random.Generator,
             bar=None) -> list[float]:
    """Run ``policy(obs, t) -> action`` for ``episodes`` real episodes, recording every
    transition; returns the episode returns."""
    from twinrl.real.twin import record_episode

    returns = []
    for ep in range(episodes):
        obs, _ = twin.reset(seed=int(rng.integers(0, 2**31 - 1)))
        ret, _ = record_episode(twin, writer, policy, obs)
        returns.append(ret)
        if bar is not None:
            bar(f"episode {ep + 1}/{episodes} return {ret:.1f}")
    return returns


def _episodes_in(dataset_dir: Path) -> int:
    from twinrl.real import dataset as ds

    if not (dataset_dir / "meta.json").exists():
        return 0
    data = ds.read(dataset_dir, strict=False)  # damage is reported where the rounds read it
    return int(np.sum(data.episode_complete))


def run(env_name: str, out: str | Path, config: LoopConfig = LoopConfig(), *, seed: int = 0,
        resume: bool = False, progress: bool = True, perturbation=None) -> dict[str, Any]:
    """Run the loop on ``env_name``'s real twin (hidden perturbation drawn from ``seed``) into
    ``out``; returns the summary (also ``out/summary.json``).

    ``perturbation`` (a ``twinrl.real.perturbation.Perturbation``) replaces the drawn one: a
    benchmark's custom real twin, e.g. one with an effect the simulator cannot model. Like the drawn
    one it is applied by the twin and never shown to the learning stages."""
    from twinrl import envs
    from twinrl.learn.runner import algorithm
    from twinrl.real.dataset import DatasetWriter
    from twinrl.real2sim import sysid

    if env_name not in envs.names():
        raise LoopError(f"unknown task {env_name!r}; registered: {', '.join(envs.names())}")
    algorithm(config.algo)
    out = Path(out)
    # The perturbation (a custom twin's) is not a setting the loop may read back: the twin's
    # server keeps it with the salt in eval/twin.json and refuses a resume with another one.
    settings = {"env": env_name, "seed": int(seed), "config": report.to_jsonable(config)}
    settings_file = out / "loop.json"
    if settings_file.exists():
        previous = json.loads(settings_file.read_text())
        if not resume:
            raise LoopError(f"{out} already holds a loop run; pass --resume to continue it or "
                            f"choose a new --out")
        if previous != report.to_jsonable(settings):
            raise LoopError(f"--resume: {settings_file} was started with other settings "
                            f"({previous}); resume with the same ones")
        # the dataset is made after the twin's server has written its secret: data without a
        # secret came from a twin that cannot be rebuilt (a new salt would be another twin)
        if (out / "dataset").exists() and not (out / "eval" / "twin.json").exists():
            raise LoopError(f"--resume: {out} has no eval/twin.json (the real twin's secret; "
                            f"the run predates it or it was removed): start a new --out")
    out.mkdir(parents=True, exist_ok=True)
    report.write_json(settings_file, settings)
    prog = _Progress(out / "progress.json")
    say = report.console.print if progress else (lambda *a, **k: None)
    t_start = time.perf_counter()

    # Evaluation only, never read by the stages: the twin's secret, the oracle, the records.
    ev_dir = out / "eval"
    secret = ev_dir / "twin.json"
    ev = _Progress(ev_dir / "evaluation.json")
    # The twin's server first: it creates the secret the oracle's process then reads.
    from twinrl.real.remote import TwinClient

    twin = TwinClient(env_name, seed=seed, secret=secret, perturbation=perturbation)
    oracle_job = None
    if config.oracle and config.oracle_in_background:
        say("training the oracle (evaluation only) in the background")
        oracle_job = _OracleProcess(env_name, seed, ev_dir / "oracle", config, perturbation,
                                    secret=secret)
    nominal_env = envs.make(env_name)
    K, T = config.episodes_per_round, nominal_env.episode_length
    rng = np.random.default_rng(seed)
    obs0, _ = twin.reset(seed=seed)
    writer = DatasetWriter(out / "dataset", env=env_name, obs_shape=obs0.shape,
                           action_shape=twin.action_space.shape, obs_dtype=np.float32,
                           action_dtype=np.float32)
    rounds: list[dict[str, Any]] = []
    try:
        # ---------------------------------------------------------------- round 0: excitation
        if not prog.done("round0/collect"):
            have = _episodes_in(out / "dataset")
            need = K - have
            say(f"[bold]round 0[/]: recording {need} exciting episodes on the real twin"
                f"{f' ({have} already recorded)' if have else ''}")
            acts = [sysid.excitation_actions(np.random.default_rng([seed, e]), T,
                                             nominal_env.action_size) for e in range(K)]
            t0 = time.perf_counter()
            for e in range(have, K):
                _collect(twin, writer, 1, lambda o, t, a=acts[e]: a[min(t, T - 1)], seed,
                         np.random.default_rng([seed, e, 1]))
            prog.mark("round0/collect", real_steps=_real_steps(out), real_return=None,
                      seconds={"collect": time.perf_counter() - t0})
        rounds.append(_round_record(prog, 0))

        policy_dir = None
        for r in range(1, config.rounds + 1):
            tag = f"round{r}"
            rdir = out / tag
            rdir.mkdir(exist_ok=True)
            say(f"[bold]round {r}[/] ({time.perf_counter() - t_start:.0f} s)")
            data = _read(out / "dataset", say)

            # 1. sysid --------------------------------------------------------------------
            if not prog.done(f"{tag}/sysid"):
                say(f"  sysid on {len(data)} real transitions ...")
                t0 = time.perf_counter()
                res = sysid.fit(nominal_env, data, sysid.SysidConfig(
                    **({"window": config.sysid_window} if config.sysid_window else {})))
                report.write_json(rdir / "sysid.json", {
                    "latency": res.latency, "system": res.system.to_json(),
                    "table": res.table, "loss": res.loss, "sim_rollouts": res.sim_rollouts,
                    "seconds": res.seconds})
                ev.mark(f"{tag}/sysid", param_rel_error=evaluation.param_errors(
                    env_name, seed, res, perturbation, secret))
                prog.mark(f"{tag}/sysid", latency=res.latency,
                          sysid_rollouts=res.sim_rollouts,
                          seconds=_seconds(prog, r, sysid=time.perf_counter() - t0))
            # the identified twin, latency included, is what every later stage simulates
            system = _identified_system(rdir)
            latency = system.latency
            env = envs.make(env_name, system=system)

            # 2. hybrid -------------------------------------------------------------------
            hyb = None
            if config.hybrid:
                hyb = _hybrid_stage(prog, r, rdir, env, data, latency, seed + r, say)

            # 3. learn in sim -------------------------------------------------------------
            policy_dir = rdir / "train"
            if not prog.done(f"{tag}/learn"):
                say(f"  learning with {config.algo} in the identified simulator ...")
                kwargs = {}
                overrides = {}
                if config.algo == "hds" and config.model_fraction > 0 and hyb is not None:
                    from twinrl.sim2real.hybrid import make_dynamics

                    kwargs["dynamics"] = make_dynamics(env, hyb)
                    overrides["model_fraction"] = config.model_fraction
                from twinrl.learn.runner import continue_run

                t0 = time.perf_counter()
                s = continue_run(env_name, config.algo, policy_dir, seed=seed + r,
                                 epochs=config.epochs, overrides=overrides, progress=progress,
                                 env=env, train_kwargs=kwargs,
                                 checkpoint_every=config.checkpoint_every)
                prog.mark(f"{tag}/learn", sim_return=s["final"].get("return"),
                          train_epochs=s["epochs"],
                          seconds=_seconds(prog, r, learn=time.perf_counter() - t0))

            # 4. residual + deploy ---------------------------------------------------------
            if not prog.done(f"{tag}/deploy"):
                t0 = time.perf_counter()
                act = _deployed_policy(config, env, hyb, data, policy_dir, rdir, seed + r, say)
                have = _episodes_in(out / "dataset") - _episodes_before(prog, r, K)
                say(f"  deploying on the real twin ({K - have} episodes) ...")
                rets = list(prog.record(r).get("deploy_returns_partial", []))
                for e in range(max(0, have), K):
                    rets += _collect(twin, writer, 1, lambda o, t: act(o), seed,
                                     np.random.default_rng([seed, r, e]))
                    prog.mark(f"{tag}/deploy_partial", deploy_returns_partial=rets)
                t_eval = time.perf_counter()
                # evaluation only: pi_sim alone and the deployed policy on the same unrecorded
                # episodes (same start states), a like-for-like before/after of the adaptation;
                # without an accepted residual the deployed policy is pi_sim (scored once)
                no_adapt = evaluation.real_return(env_name, seed, policy_dir,
                                                   config.eval_episodes, perturbation, secret)
                gate = _residual_gate(rdir)
                adapted = (evaluation.policy_real_return(env_name, seed, act,
                                                         config.eval_episodes, perturbation,
                                                         secret)
                           if gate["residual_accepted"] else no_adapt)
                ev.mark(f"{tag}/deploy", sim_policy_real_return=no_adapt,
                        adapted_real_return=adapted)
                prog.mark(f"{tag}/deploy", real_return=float(np.mean(rets)) if rets else None,
                          real_returns=rets, real_steps=_real_steps(out),
                          seconds=_seconds(prog, r, deploy=t_eval - t0,
                                           evaluation=time.perf_counter() - t_eval), **gate)
            rounds.append(_round_record(prog, r))
    finally:
        writer.close()
        twin.close()

    # ------------------------------------------------------------------------- oracle
    oracle_return = None
    t_wait = time.perf_counter()
    if oracle_job is not None:
        if oracle_job.running():
            say("waiting for the oracle's training ...")
        oracle_return = oracle_job.result()
    elif config.oracle:
        oracle_return = evaluation.oracle_return(env_name, seed, ev_dir / "oracle", config,
                                                 progress, perturbation, secret)
    for rec in rounds:  # the evaluation records merged in, now that the stages are done
        rec.update({k: v for k, v in ev.record(rec["round"]).items()})
        rec["oracle_return"] = oracle_return
    final = dict(rounds[-1]) if rounds else {}
    if oracle_return:
        final["fraction_of_oracle"] = (final.get("real_return") or 0.0) / oracle_return
    summary = {"env": env_name, "seed": int(seed), "config": report.to_jsonable(config),
               "rounds": rounds, "final": final,
               "oracle_wait_s": time.perf_counter() - t_wait,
               "wall_s_this_process": time.perf_counter() - t_start}
    if config.video and policy_dir is not None:
        t0 = time.perf_counter()
        summary["video"] = str(_final_video(out, env_name, seed, config, perturbation, secret))
        summary["video_s"] = time.perf_counter() - t0
        summary["wall_s_this_process"] = time.perf_counter() - t_start
    _write_outputs(out, summary, config, env_name, seed, policy_dir)
    return summary


def _final_video(out: Path, env_name: str, seed: int, config: LoopConfig, perturbation=None,
                 secret=None, size: tuple[int, int] = (320, 240)) -> Path:
    """``final.mp4``: an episode of the final deployed policy on the real twin (left, its true
    camera) beside the identified simulator's episode from the same recorded start (right).
    Neither episode is recorded in the dataset."""
    import mujoco

    from twinrl import envs
    from twinrl.real.twin import CameraRenderer

    r = config.rounds
    rdir = out / f"round{r}"
    env = envs.make(env_name, system=_identified_system(rdir))
    hyb = _load_hybrid(rdir) if config.hybrid else None
    act = _deployed_policy(config, env, hyb, None, rdir / "train", rdir, seed + r,
                           lambda *a, **k: None)
    # Both sides without shadows: in software OpenGL (no GPU) shadow mapping is ~90 % of a frame
    # (cartpole 320x240: 80 ms -> 6 ms), and the video is for looking at, not for fitting.
    from twinrl.real.remote import TwinClient

    twin = TwinClient(env_name, seed=seed, secret=secret, perturbation=perturbation,
                      width=size[0], height=size[1], shadows=False)
    renderer = CameraRenderer(env.sim.mj_model, *size, shadows=False)
    frames = []
    try:
        obs, _ = twin.reset(seed=20_000 + seed)
        qpos, qvel = env.state_from_obs(jnp.asarray(obs))
        state = env.reset(jax.random.key(0))
        state = state.replace(pipeline_state=env.sim.init(qpos, qvel), obs=env.observe(qpos, qvel))
        # committed to the device like step's outputs, so step compiles once, not twice
        state = jax.device_put(state, jax.devices()[0])
        step = jax.jit(env.step)
        d = mujoco.MjData(env.sim.mj_model)
        done = False
        while not done:
            obs, _, term, trunc, _ = twin.step(act(obs))
            state = step(state, jnp.asarray(act(np.asarray(state.obs))))
            d.qpos[:] = np.asarray(state.pipeline_state.qpos)
            mujoco.mj_forward(env.sim.mj_model, d)
            real_img = twin.render_images(twin.camera, ("rgb",))["rgb"]
            sim_img = renderer.images(d, env.cameras[0], ("rgb",))["rgb"]
            frames.append(np.concatenate([real_img, sim_img], axis=1))
            done = term or trunc
    finally:
        renderer.close()
        twin.close()
    frames = report.label_frames(frames, ["real twin", "identified simulator"])
    return report.write_video(out / "final.mp4", frames, fps=1.0 / env.dt)


def _read(path: Path, say=None):
    """Every intact transition of the dataset. Damage (a flipped byte, a truncated closed chunk)
    costs the records it hit, not the run: ``say`` gets one line saying what was dropped, and the
    loop goes on with the rest (a strict read would stop ``--resume`` for good)."""
    from twinrl.real import dataset as ds

    data = ds.read(path, strict=False)
    if data.problems and say is not None:
        more = f" (and {len(data.problems) - 1} more)" if len(data.problems) > 1 else ""
        say(f"  [yellow]dataset damaged, continuing with its {len(data)} intact transitions:[/] "
            f"{data.problems[0]}{more}", markup=True, highlight=False, soft_wrap=True)
    return data


def _real_steps(out: Path) -> int:
    return int(len(_read(out / "dataset")))


def _episodes_before(prog: _Progress, r: int, K: int) -> int:
    """Complete episodes recorded before round ``r``'s deployment: K per earlier stage."""
    return K * r


def _seconds(prog: _Progress, r: int, **stages: float) -> dict[str, float]:
    """Round ``r``'s wall-clock seconds per stage so far, with ``stages`` added (a resumed
    stage counts only this process's part)."""
    return {**prog.record(r).get("seconds", {}), **stages}


def _round_record(prog: _Progress, r: int) -> dict[str, Any]:
    rec = prog.record(r)
    return {"round": r, "real_steps": rec.get("real_steps"), "real_return": rec.get("real_return"),
            "real_returns": rec.get("real_returns"), "sim_return": rec.get("sim_return"),
            "oracle_return": None,
            "param_rel_error": rec.get("param_rel_error", {}),
            "sim_policy_real_return": rec.get("sim_policy_real_return"),
            "adapted_real_return": rec.get("adapted_real_return"),
            "residual_accepted": rec.get("residual_accepted"),
            "latency": rec.get("latency"), "seconds": rec.get("seconds", {})}


def _hybrid_stage(prog, r, rdir, env, data, latency, seed, say):
    from twinrl.learn.checkpoint import save_policy
    from twinrl.sim2real import hybrid

    tag = f"round{r}"
    if not prog.done(f"{tag}/hybrid"):
        say("  fitting the hybrid residual dynamics ...")
        t0 = time.perf_counter()
        fit = hybrid.fit(env, data, latency=latency, rng=jax.random.key(seed))
        m = fit.model
        save_policy(rdir / "hybrid", m.network, m.params, kind="hybrid_residual",
                    in_mean=m.in_mean, in_std=m.in_std, out_scale=m.out_scale,
                    latency=m.latency, metrics=fit.metrics)
        prog.mark(f"{tag}/hybrid", hybrid_sim_rmse=fit.metrics["sim_val_rmse"],
                  hybrid_rmse=fit.metrics["hybrid_val_rmse"],
                  seconds=_seconds(prog, r, hybrid=time.perf_counter() - t0))
    return _load_hybrid(rdir)


def _load_hybrid(rdir: Path):
    from twinrl.learn.checkpoint import load_policy
    from twinrl.sim2real import hybrid

    net, params, meta = load_policy(rdir / "hybrid")
    f32 = lambda k: jnp.asarray(np.asarray(meta[k]), jnp.float32)  # noqa: E731
    return hybrid.HybridModel(net, params, f32("in_mean"), f32("in_std"), f32("out_scale"),
                              int(meta["latency"]))


def _residual_gate(rdir: Path) -> dict[str, Any]:
    """The residual's acceptance (``residual.accept``) as recorded in its checkpoint."""
    f = rdir / "residual" / "checkpoint.json"
    m = json.loads(f.read_text()).get("metrics", {}) if f.exists() else {}
    return {"residual_accepted": bool(m["accepted"]) if "accepted" in m else None,
            "residual_model_return": [m.get("model_return_before"), m.get("model_return_after")]}


def _deployed_policy(config, env, hyb, data, policy_dir, rdir, seed, say):
    """The deployed ``obs -> action``: pi_sim, plus the residual trained through the hybrid."""
    from twinrl.learn.checkpoint import load_policy, save_policy
    from twinrl.sim2real import hybrid, residual

    base, base_params, _ = load_policy(policy_dir)
    if not config.residual or hyb is None:
        f = jax.jit(base.apply)
        return lambda o: np.asarray(f(base_params, o))
    pol = residual.make_residual(base, base_params)
    if not (rdir / "residual" / "checkpoint.json").exists():
        if data is None:
            raise LoopError(f"{rdir}: residual policy missing")
        say("  training the residual policy through the hybrid model ...")
        dynamics = hybrid.make_dynamics(env, hyb)
        res_params, metrics = residual.train(env, dynamics, pol, data.obs,
                                             rng=jax.random.key(seed))
        ok, before, after = residual.accept(env, dynamics, pol, res_params,
                                            jax.random.key(seed + 1))
        say(f"  residual {'accepted' if ok else 'rejected (deploying pi_sim)'}: full-episode "
            f"return through the hybrid model {before:.1f} -> {after:.1f}")
        if not ok:  # the exact pi_sim: an all-zero delta outputs tanh(0) = 0
            res_params = jax.tree_util.tree_map(jnp.zeros_like, res_params)
        metrics = {k: v[-1] for k, v in metrics.items()}
        metrics.update(accepted=float(ok), model_return_before=before, model_return_after=after)
        save_policy(rdir / "residual", pol.delta, res_params, kind="residual", metrics=metrics)
    _, res_params, _ = load_policy(rdir / "residual")
    f = jax.jit(pol.act)
    return lambda o: np.asarray(f(res_params, o))


# ------------------------------------------------------------------------------ outputs
def _write_outputs(out: Path, summary, config, env_name, seed, policy_dir) -> None:
    rounds = summary["rounds"]
    for rec in rounds:  # what the report draws: each round's learning curve and fit
        _add_round_details(out, rec)
    rows = [[r["round"], r["real_steps"], r["sim_return"], r["real_return"],
             r["sim_policy_real_return"], r.get("adapted_real_return"), r["oracle_return"],
             max(r["param_rel_error"].values()) if r["param_rel_error"] else None]
            for r in rounds]
    cols = ["round", "real steps", "sim return", "real return", "no-adapt real", "adapted real",
            "oracle", "max param err"]
    report.print_table(f"twinrl run {env_name} (seed {seed})", cols, rows)
    report.write_json(out / "summary.json", summary)
    report.loop_report(out, summary, _model_free_runs(env_name, seed))


def _add_round_details(out: Path, rec: dict[str, Any]) -> None:
    """Round ``rec["round"]``'s learning curve in its identified simulator (``env_steps``,
    ``return`` of its ``train/metrics.csv``) and its sysid table (value, sd, status per
    parameter), for the report."""
    import csv

    rdir = out / f"round{rec['round']}"
    f = rdir / "train" / "metrics.csv"
    if f.exists():
        rows = list(csv.DictReader(open(f)))
        pick = lambda k: [float(r[k]) for r in rows if r.get(k) not in (None, "")]  # noqa: E731
        rec["learning_curve"] = {"env_steps": pick("env_steps"), "return": pick("return")}
    f = rdir / "sysid.json"
    if f.exists():
        rec["identified"] = json.loads(f.read_text()).get("table", [])


def _model_free_runs(env_name: str, seed: int) -> list[dict]:
    """``bench/sim2real.py``'s model-free runs on this task and twin seed, when its results file
    exists (in the working directory's or the source tree's ``bench/results/``)."""
    for base in (Path.cwd(), Path(__file__).resolve().parents[1]):
        f = base / "bench" / "results" / "sim2real.json"
        if f.exists():
            try:
                runs = json.loads(f.read_text()).get("runs", [])
            except (OSError, json.JSONDecodeError):
                return []
            return [r for r in runs if r.get("task") == env_name and r.get("seed") == seed]
    return []
