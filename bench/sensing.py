"""Active sensing on the real twins: success of the image actor with (a) the camera the
sensing-aware Q selects, (b) the default fixed camera, (c) a random reachable camera, against
(d) the state-based oracle policy, and model-free SAC/TD3 trained on the real twin
(``twinrl.sim2real.active``; SAM-RL, Lv et al. RSS 2023, Table I's comparison).

Per task and twin seed (``--seeds``: each a hidden perturbation, hand-eye offset included),
``--episodes`` real episodes per camera mode from the same start states (reset seeds
``1000 * seed + first + i``, ``first`` = ``--first-start``, 0 by default: another set of
starts). Checkpoints per task, ``TASK=DIR`` (``twinrl train`` run directories):
``--actor`` the image actor (``--algo imitation --set observation=pixels`` or ``=target``),
``--q`` its sensing-aware Q (``--algo sensing``), ``--state-actor`` the state actor
(``--algo imitation``) for (d). Modes whose checkpoint is missing are left out. Real steps
count the steps acting and, separately, the steps the camera mount spends moving.

``--residual TASK=DIR`` adds a residual policy's correction (``twinrl.sim2real.residual``; the
loop's ``roundR/residual``) to the image actor's actions on the real twin (not in ``--where
sim``).

``--run TASK=DIR`` takes all of these from a ``twinrl run`` (the SAM-RL loop) output directory:
its last round's actor, Q, identified ``System`` (``--system``: the calibrated mount) and
residual policy if the loop accepted one (``--no-residual``: leave it out), and
the loop's hidden twin: the run's seed and its secret salt (``DIR/eval/twin.json``; ``--secret``).
The loop's twin is drawn from the seed *and* that salt (``twinrl.real.remote``), so it is not
the public-seed twin ``--seeds`` names alone: a mount calibrated on one and deployed on the other
is off by the difference of their hand-eye offsets (centimetres), so ``--system`` without
``--secret`` is refused.

``--model-free-steps N`` (needs the ``bench`` extra: sbx-rl) also trains sbx SAC and TD3 on the
state observation of each task's first ``--seeds`` twin (the run's own with ``--run``) for N
real steps, evaluating success every ``--eval-every`` steps, and reports the real steps each
needed to reach the selected camera's success, or ``--model-free-target`` (or that it did not
within N).

``--dreamer-steps N`` adds DreamerV3 (danijar/dreamerv3) from pixels -- the default camera's RGB
frames -- on the same twin for N real steps: SAM-RL's third baseline. It needs its own
environment (DreamerV3 pins jax 0.4.33; ``--dreamer-python`` or ``$TWINRL_DREAMER_PYTHON``, built
as ``bench/dreamer_baseline.py``'s docstring says), where it runs as a subprocess talking to the
twin here. Its success is the mean of its last 10 training episodes. Without that environment
the row is kept, marked ``absent`` with the reason.

``--where sim`` (with or instead of ``real``) runs the image actor's camera modes in the
simulator as well -- the run's identified twin with ``--run``/``--system``, else the nominal task
-- from ``--episodes`` start states ``reset(PRNGKey(1000 * seed + i))``: the success in sim of
the actor as it is deployed, with its chosen camera (``camera_choice.view_outcomes``; the choice
from the true simulated state, where the real deployment chooses from the state it measures).

The selected camera is also compared with the default one episode by episode (``paired``: the
same start states; the difference with a bootstrap 95 % interval and a sign test), which is the
spread that one twin seed has. Prints the tables and writes ``DIR/sensing.json`` and
``DIR/sensing.png`` (``--out DIR``).

    python bench/sensing.py --tasks peg_insertion --actor peg_insertion=runs/ia \\
        --q peg_insertion=runs/sq --state-actor peg_insertion=runs/sa --out bench/results
    twinrl run --env needle_threading --out runs/needle
    python bench/sensing.py --tasks needle_threading --run needle_threading=runs/needle \\
        --episodes 50 --modes selected default random --out bench/results
    TWINRL_DREAMER_PYTHON=/tmp/dreamer-venv/bin/python DREAMERV3_SRC=DIR python bench/sensing.py \\
        --tasks needle_threading --run needle_threading=runs/needle --dreamer-steps 20000
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from twinrl import envs
from twinrl.report import print_table
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)

TASKS = ("peg_insertion", "spatula_flipping", "needle_threading")
MODES = ("selected", "default", "random", "oracle")
"""Camera modes a run measures."""
REPORTED = (*MODES, "loop")
"""Modes the tables and plot report: ``--merge`` adds ``"loop"`` (``loop_camera_rows``)."""


def _per_task(pairs: list[str], flag: str) -> dict[str, Path]:
    out = {}
    for p in pairs or []:
        task, sep, path = p.partition("=")
        if not sep or task not in TASKS:
            raise SystemExit(f"{flag} takes TASK=DIR with TASK one of {', '.join(TASKS)}; "
                             f"got {p!r}")
        out[task] = Path(path)
    return out


def _from_runs(runs: dict[str, Path], args) -> None:
    """Fill the per-task checkpoints, System, secret and seed from ``--run TASK=DIR``."""
    import json

    for task, d in runs.items():
        try:
            summary = json.loads((d / "summary.json").read_text())
        except (OSError, ValueError) as e:
            raise SystemExit(f"--run {task}={d}: no finished twinrl run there ({e})") from None
        if summary.get("env") != task:
            raise SystemExit(f"--run {task}={d}: that run is on {summary.get('env')!r}")
        r = summary["final"]["round"]
        rdir = d / f"round{r}"
        accepted = summary["final"].get("residual_accepted") and not args.no_residual
        for flag, key, path in (("--actor", "actor", rdir / "actor"), ("--q", "q", rdir / "q"),
                                ("--system", "system", rdir / "system.json"),
                                ("--secret", "secret", d / "eval" / "twin.json"),
                                ("--residual", "residual", rdir / "residual")):
            if key == "q" and not path.exists():
                continue  # a camera=default loop learns no Q
            if key == "residual" and not accepted:
                continue
            if not path.exists():
                raise SystemExit(f"--run {task}={d}: {path} is missing")
            getattr(args, key).append(f"{task}={path}")
        if args.seeds != [int(summary["seed"])]:
            print(f"[bench] --run {task}: twin seed {summary['seed']} (the run's)", flush=True)
        args.seeds = [int(summary["seed"])]
        args.run_dirs[task] = d  # the task's settings the run ran with (its image size)
        args.q_ranks[task] = _run_gate(summary, rdir)  # the loop's camera gate


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="*", default=list(TASKS), choices=TASKS)
    p.add_argument("--actor", nargs="*", default=[], help="TASK=DIR image actor checkpoints")
    p.add_argument("--q", nargs="*", default=[], help="TASK=DIR sensing-aware Q checkpoints")
    p.add_argument("--state-actor", nargs="*", default=[], help="TASK=DIR state actors (oracle)")
    p.add_argument("--system", nargs="*", default=[],
                   help="TASK=FILE identified System (a loop round's system.json: its calibrated "
                        "mount camera); default: the nominal task; needs --secret")
    p.add_argument("--secret", nargs="*", default=[],
                   help="TASK=FILE a run's twin secret (DIR/eval/twin.json): deploy on that "
                        "run's hidden twin instead of the public-seed twin")
    p.add_argument("--residual", nargs="*", default=[],
                   help="TASK=DIR a residual policy checkpoint added to the image actor")
    p.add_argument("--no-residual", action="store_true",
                   help="with --run: leave out the residual policy the loop accepted")
    p.add_argument("--run", nargs="*", default=[],
                   help="TASK=DIR a `twinrl run` loop directory: its last round's actor, Q, "
                        "System, its twin's secret and seed")
    p.add_argument("--seeds", nargs="*", type=int, default=[0, 1, 2])
    p.add_argument("--where", nargs="+", default=["real"], choices=("real", "sim"),
                   help="deploy on the real twin, in the simulator (the identified twin), or both")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--first-start", type=int, default=0,
                   help="real episodes reset with seeds 1000 * seed + first-start + i (another "
                        "set of starts than the default 0)")
    p.add_argument("--modes", nargs="*", default=list(MODES), choices=MODES)
    p.add_argument("--restarts", type=int, default=None, help="ascents per choice (default: Q's)")
    p.add_argument("--ascent-steps", type=int, default=None)
    p.add_argument("--smooth-samples", type=int, default=None,
                   help="poses around each leading candidate the choice averages Q over (0: "
                        "the pose alone; default: the Q checkpoint's SensingConfig)")
    p.add_argument("--reselect-every", type=int, default=0,
                   help="choose the camera again every N steps (DeployConfig.reselect_every; "
                        "0: once per episode)")
    p.add_argument("--pose-memory", choices=("none", "best"), default="none",
                   help="a pose actor's target pose on the real twin: each frame's fit, or the "
                        "best-seen one (DeployConfig.pose_memory)")
    p.add_argument("--model-free-steps", type=int, default=0)
    p.add_argument("--model-free-target", type=float, default=None,
                   help="success SAC/TD3 must reach (default: the selected camera's here)")
    p.add_argument("--eval-every", type=int, default=5000)
    p.add_argument("--dreamer-steps", type=int, default=0,
                   help="real steps of DreamerV3 from pixels per task (bench/dreamer_baseline.py;"
                        " its own environment: --dreamer-python)")
    p.add_argument("--dreamer-python", default=None,
                   help="the Dreamer environment's interpreter (default: $TWINRL_DREAMER_PYTHON)")
    p.add_argument("--merge", nargs="*", type=Path, default=[],
                   help="sensing.json files of earlier invocations (e.g. one per loop run with "
                        "--run): their episodes analysed together into --out; nothing is run. A "
                        "later file's twins replace those twins' rows from earlier files")
    p.add_argument("--camera-min-rank", type=float, default=None,
                   help="with --merge: the loop's camera gate (ArmLoopConfig.camera_min_rank, "
                        "default the loop's): a twin's 'loop' row is its selected camera where "
                        "the run's Q ranks at least this, else its default camera")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    if args.merge:
        return merge(args)
    args.run_dirs, args.q_ranks = {}, {}
    _from_runs(_per_task(args.run, "--run"), args)
    if args.episodes < 1 or not args.seeds:
        raise SystemExit("--episodes must be >= 1 and --seeds must name at least one seed")
    if args.first_start < 0:
        raise SystemExit(f"--first-start must be >= 0, got {args.first_start}")
    actors, qs = _per_task(args.actor, "--actor"), _per_task(args.q, "--q")
    states = _per_task(args.state_actor, "--state-actor")
    residuals = _per_task(args.residual, "--residual")
    systems = _per_task(args.system, "--system")
    secrets = _per_task(args.secret, "--secret")
    for flag, files in (("--system", systems), ("--secret", secrets)):
        for task, path in files.items():
            if not path.is_file():
                raise SystemExit(f"{flag} {task}={path}: no such file")
    for task in systems:
        if task not in secrets:
            raise SystemExit(f"--system {task}=...: give that run's --secret {task}=FILE too "
                             "(or --run): its calibration belongs to the run's hidden twin")
    rows, model_free, sim_rows = [], [], []
    for name in args.tasks:
        if "sim" in args.where:
            sim_rows += run_sim(name, actors.get(name), qs.get(name), args, systems.get(name))
        if "real" in args.where:
            rows += run_task(name, actors.get(name), qs.get(name), states.get(name), args,
                             systems.get(name), secrets.get(name), residuals.get(name))
        write_result(args.out / "sensing.json", _result(args, rows, model_free, sim_rows), args)
        if args.model_free_steps > 0:
            sel = [r["success"] for r in rows if r["task"] == name and r["mode"] == "selected"]
            target = (args.model_free_target if args.model_free_target is not None
                      else float(np.mean(sel)) if sel else 0.8)
            for algo in ("td3", "sac"):
                model_free.append(train_model_free(algo, name, target, args,
                                                   secrets.get(name)))
                write_result(args.out / "sensing.json", _result(args, rows, model_free, sim_rows), args)
        if args.dreamer_steps > 0:
            from dreamer_baseline import train_dreamer

            sel = [r["success"] for r in rows if r["task"] == name and r["mode"] == "selected"]
            target = (args.model_free_target if args.model_free_target is not None
                      else float(np.mean(sel)) if sel else 0.8)
            model_free.append(train_dreamer(name, args.dreamer_steps, target, int(args.seeds[0]),
                                            secrets.get(name), python=args.dreamer_python))
            write_result(args.out / "sensing.json", _result(args, rows, model_free, sim_rows), args)
    table = summarise(rows)
    cols = ["task", "mode", "success", "spread (sd over seeds)", "return", "real steps",
            "camera steps", "wall s"]
    if table:
        print_table(f"real-twin success ({args.episodes} episodes x {len(args.seeds)} seeds)",
                    cols, [[t[c] for c in ("task", "mode", "success", "sd", "return",
                                           "real_steps", "camera_steps", "wall_s")]
                           for t in table])
    if sim_rows:
        print_table(f"in the simulator (identified twin, {args.episodes} episodes x "
                    f"{len(args.seeds)} seeds)", ["task", "mode", "success",
                                                  "spread (sd over seeds)", "return", "wall s"],
                    [[t[c] for c in ("task", "mode", "success", "sd", "return", "wall_s")]
                     for t in summarise(sim_rows)])
    for where, pairs in (("real twin", paired(rows)), ("simulator", paired(sim_rows))):
        if not pairs:
            continue
        print_table(f"selected against default camera, paired episodes ({where}, same starts)",
                    ["task", "episodes", "difference", "95 % interval", "only selected solved",
                     "only default solved", "sign test p"],
                    [[x["task"], x["episodes"], f"{100 * x['difference']:+.0f} points",
                      f"{100 * x['ci95'][0]:+.0f} .. {100 * x['ci95'][1]:+.0f}", x["only_a"],
                      x["only_b"], f"{x['sign_test_p']:.3f}"] for x in pairs])
    if model_free:
        print_table("model-free on the real twin",
                    ["task", "algo", "observation", "target success", "steps to target",
                     "best success", "real steps"],
                    [[m["task"], m["algo"], m.get("observation", "state"), m["target"],
                      f"absent: {m['absent']}" if "absent" in m
                      else m["steps_to_target"] or "not reached",
                      m.get("best_success", "-"), m.get("real_steps_trained", 0)]
                     for m in model_free])
    path = write_result(args.out / "sensing.json", _result(args, rows, model_free, sim_rows), args)
    _plot(args.out / "sensing.png", table, summarise(sim_rows))
    print(f"wrote {path} and {args.out / 'sensing.png'}")
    return 0


def _env(name, system, args):
    """The task in ``system`` (a ``system.json``; None: nominal), as ``--run``'s loop ran it."""
    from twinrl.envs.system import System
    from twinrl.loop.arm import run_env

    system = None if system is None else System.load(system)
    run = getattr(args, "run_dirs", {}).get(name)
    return envs.make(name, system=system) if run is None else run_env(run, system)


def run_task(name, actor_dir, q_dir, state_dir, args, system=None, secret=None,
             residual=None) -> list[dict]:
    from twinrl.learn.camera_choice import image_size
    from twinrl.learn.checkpoint import load_policy
    from twinrl.learn.sensing import SensingConfig, load_actor
    from twinrl.real.remote import hidden_perturbation
    from twinrl.real.twin import RealTwin
    from twinrl.sense import load_q
    from twinrl.sim2real import active

    env = _env(name, system, args)
    deployers, size = {}, None
    if actor_dir is not None:
        actor, actor_params, _ = load_actor(actor_dir)
        size = image_size(env, actor)
        q = q_params = sensing = None
        if q_dir is not None:
            q, q_params, meta = load_q(q_dir)
            sensing = SensingConfig.from_dict(meta.get("config") or {})
        correction = None
        if residual is not None:
            correction = active.residual_correction(*load_policy(residual)[:2])
            print(f"[bench] {name}: the image actor plus the residual policy {residual}",
                  flush=True)
        dep = active.Deployer(env, actor, actor_params, q=q, q_params=q_params, sensing=sensing,
                              residual=correction)
        for mode in ("selected", "default", "random"):
            if mode in args.modes and (mode != "selected" or q is not None):
                deployers[mode] = dep
    if state_dir is not None and "oracle" in args.modes:
        net, params, _ = load_policy(state_dir)
        deployers["oracle"] = active.Deployer(env, net, params)
    if not deployers:
        print(f"[bench] {name}: no checkpoints given; skipped", flush=True)
        return []
    rows = []
    q_ranks = getattr(args, "q_ranks", {})  # with --run: the loop's Q rank, its camera gate
    q_rank = q_ranks.get(name, {})
    for seed in args.seeds:
        hidden = None if secret is None else hidden_perturbation(name, seed, secret)
        twin = RealTwin(name, seed=seed, perturbation=hidden, width=size or 64,
                        height=size or 64)
        for mode, dep in deployers.items():
            cfg = active.DeployConfig(camera=mode, episodes=args.episodes,
                                      restarts=args.restarts, ascent_steps=args.ascent_steps,
                                      pose_memory=args.pose_memory,
                                      reselect_every=args.reselect_every,
                                      smooth_samples=args.smooth_samples)
            twin.move_camera(env.mount.default)
            t0 = time.perf_counter()
            res = dep.run(twin, cfg, seed=1000 * seed + args.first_start)
            print(f"[bench] {name} seed {seed} {mode:>8}: success {res['success_rate']:.2f}, "
                  f"return {res['mean_return']:.1f}, camera steps {res['real_camera_steps']} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
            rows.append({"task": name, "seed": seed, "mode": mode,
                         "success": res["success_rate"], "return": res["mean_return"],
                         "real_steps": res["real_steps"],
                         "camera_steps": res["real_camera_steps"], "wall_s": res["wall_s"],
                         "episodes": res, **q_rank})
        twin.close()
    return rows


def run_sim(name, actor_dir, q_dir, args, system=None) -> list[dict]:
    """The image actor's camera modes (``--modes`` but the oracle) in the simulator: per
    ``--seeds`` seed, ``--episodes`` starts ``reset(PRNGKey(1000 * seed + i))``, the same for
    every mode; "selected" is ``select_camera`` from each true start state."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from twinrl.learn.camera_choice import select_camera, uniform_coords, view_outcomes
    from twinrl.learn.sensing import SensingConfig, load_actor
    from twinrl.sense import load_q

    if actor_dir is None:
        return []
    env = _env(name, system, args)
    actor, ap, _ = load_actor(actor_dir)
    run = jax.jit(lambda k, c: view_outcomes(env, actor, ap, k, c))
    choose = None
    if q_dir is not None and "selected" in args.modes:
        q, qp, meta = load_q(q_dir)
        cfg = SensingConfig.from_dict(meta.get("config") or {})
        cfg = dataclasses.replace(cfg, restarts=args.restarts or cfg.restarts,
                                  ascent_steps=args.ascent_steps or cfg.ascent_steps)
        if args.smooth_samples is not None:
            cfg = dataclasses.replace(cfg, smooth_samples=args.smooth_samples)
        choose = jax.jit(lambda k, kc: select_camera(env, q, qp, actor, ap, env.reset(k), kc,
                                                     cfg).coords)
    rows, n = [], int(args.episodes)
    for seed in args.seeds:
        keys = jnp.stack([jax.random.PRNGKey(1000 * seed + i) for i in range(n)])
        for mode in ("selected", "default", "random"):
            if mode not in args.modes or (mode == "selected" and choose is None):
                continue
            t0 = time.perf_counter()
            if mode == "selected":
                coords = jnp.stack([choose(k, jax.random.fold_in(k, 1)) for k in keys])
            elif mode == "default":
                coords = jnp.tile(jnp.asarray(env.mount.default, jnp.float32), (n, 1))
            else:
                coords = uniform_coords(env.mount, jax.random.PRNGKey(1000 * seed + n), (n,))
            ret, ok = (np.asarray(x, np.float64) for x in run(keys, coords))
            wall = time.perf_counter() - t0
            print(f"[bench] {name} seed {seed} {mode:>8} (sim): success {ok.mean():.2f}, "
                  f"return {ret.mean():.1f} ({wall:.0f} s)", flush=True)
            rows.append({"task": name, "seed": seed, "mode": mode, "where": "sim",
                         "success": float(ok.mean()), "return": float(ret.mean()),
                         "real_steps": 0, "camera_steps": 0, "wall_s": wall,
                         "episodes": {"seed": 1000 * seed, "success": ok.tolist(),
                                      "return": ret.tolist(),
                                      "coords": np.asarray(coords).tolist()}})
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    out = []
    for task in dict.fromkeys(r["task"] for r in rows):
        for mode in REPORTED:
            sel = [r for r in rows if r["task"] == task and r["mode"] == mode]
            if not sel:
                continue
            s = np.array([r["success"] for r in sel])
            out.append({"task": task, "mode": mode, "success": float(s.mean()),
                        "sd": float(s.std(ddof=1)) if len(s) > 1 else 0.0,
                        "per_seed": s.tolist(),
                        "return": float(np.mean([r["return"] for r in sel])),
                        "real_steps": int(sum(r["real_steps"] for r in sel)),
                        "camera_steps": int(sum(r["camera_steps"] for r in sel)),
                        "wall_s": float(sum(r["wall_s"] for r in sel))})
    return out


def paired(rows: list[dict], a: str = "selected", b: str = "default", n_boot: int = 10_000,
           seed: int = 0) -> list[dict]:
    """Per task, mode ``a`` against ``b`` on the same start states (same twin seed, same reset
    seed): the success difference, its 95 % interval by a bootstrap over the paired episodes,
    the episodes only ``a`` / only ``b`` solved, and the exact sign test's two-sided p on
    those (McNemar's)."""
    from scipy.stats import binomtest

    out = []
    for task in dict.fromkeys(r["task"] for r in rows):
        pairs = []
        for ra in (r for r in rows if r["task"] == task and r["mode"] == a):
            rb = next((r for r in rows if r["task"] == task and r["mode"] == b
                       and r["seed"] == ra["seed"]), None)
            if rb is None:
                continue
            # episode i of either mode reset with seed ``episodes["seed"] + i``
            ea, eb = ra["episodes"], rb["episodes"]
            if ea["seed"] == eb["seed"]:
                pairs += [(float(x), float(y)) for x, y in zip(ea["success"], eb["success"])]
        if not pairs:
            continue
        d = np.array([x - y for x, y in pairs])
        boot = np.random.default_rng(seed).choice(d, (n_boot, d.size)).mean(axis=1)
        wins, losses = int(np.sum(d > 0)), int(np.sum(d < 0))
        out.append({"task": task, "a": a, "b": b, "episodes": int(d.size),
                    "difference": float(d.mean()),
                    "ci95": [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))],
                    "only_a": wins, "only_b": losses,
                    "sign_test_p": float(binomtest(wins, wins + losses).pvalue)
                    if wins + losses else 1.0})
    return out


def train_model_free(algo: str, task: str, target: float, args, secret=None) -> dict:
    """sbx ``algo`` on the real twin's state observation for ``--model-free-steps``: the first
    ``--seeds``' twin, with the run's secret salt when given (``--run``/``--secret``: the twin the
    loop learned on); the real steps at which its deterministic policy first reached ``target``
    success (10 episodes from reset seeds 10,000+)."""
    from sim2real import LEARNING_STARTS, TD3_NOISE_SD, import_sbx
    from twinrl.real.remote import hidden_perturbation
    from twinrl.real.twin import RealTwin

    sbx, BaseCallback, NormalActionNoise = import_sbx()
    seed = int(args.seeds[0])
    hidden = None if secret is None else hidden_perturbation(task, seed, secret)
    twin = RealTwin(task, seed=seed, perturbation=hidden)
    nu = twin.action_space.shape[0]
    kw = ({"action_noise": NormalActionNoise(np.zeros(nu), TD3_NOISE_SD * np.ones(nu))}
          if algo == "td3" else {})
    model = getattr(sbx, algo.upper())("MlpPolicy", twin, learning_starts=LEARNING_STARTS,
                                       seed=0, **kw)
    env, curve, t0 = twin.task, [], time.perf_counter()
    evaluator = RealTwin(task, seed=seed, perturbation=hidden)

    def success_rate() -> float:
        wins = 0.0
        for i in range(10):
            obs, _ = evaluator.reset(seed=10_000 + i)
            for _ in range(env.episode_length):
                obs, _, term, _, _ = evaluator.step(model.predict(obs, deterministic=True)[0])
                if term:
                    break
            wins += evaluator.success()
        return wins / 10

    class Eval(BaseCallback):
        def _on_step(self) -> bool:
            n = self.num_timesteps
            if n % args.eval_every == 0 or n >= args.model_free_steps:
                s = success_rate()
                curve.append({"real_steps": n, "success": s, "wall_s": time.perf_counter() - t0})
                print(f"[bench] {task} {algo}: {n} real steps, success {s:.2f} (target "
                      f"{target:.2f})", flush=True)
                return s < target
            return True

    model.learn(total_timesteps=args.model_free_steps, callback=Eval())
    twin.close()
    evaluator.close()
    reached = next((c["real_steps"] for c in curve if c["success"] >= target), None)
    return {"task": task, "algo": algo, "twin_seed": seed, "secret": secret is not None,
            "target": target, "steps_to_target": reached,
            "best_success": max((c["success"] for c in curve), default=0.0),
            "real_steps_trained": int(model.num_timesteps), "curve": curve,
            "wall_s": time.perf_counter() - t0}


def _plot(path: Path, table: list[dict], sim_table: list[dict] = ()) -> None:
    """Success per task and camera mode: the real twin, and beside it the identified twin
    (``--where sim``) when measured."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(where, t) for where, t in (("real twin", table),
                                          ("identified twin (sim)", list(sim_table))) if t]
    if not panels:
        return
    tasks = list(dict.fromkeys(t["task"] for _, tab in panels for t in tab))
    fig, axes = plt.subplots(1, len(panels), figsize=(len(panels) * (2.2 + 2.4 * len(tasks)),
                                                      3.4), squeeze=False, sharey=True)
    for ax, (where, tab) in zip(axes[0], panels):
        modes = [m for m in REPORTED if any(t["mode"] == m for t in tab)]
        width = 0.8 / len(modes)
        for j, mode in enumerate(modes):
            xs, ys, es = [], [], []
            for i, task in enumerate(tasks):
                t = next((t for t in tab if t["task"] == task and t["mode"] == mode), None)
                if t is not None:
                    xs.append(i + (j - (len(modes) - 1) / 2) * width)
                    ys.append(100 * t["success"])
                    es.append(100 * t["sd"])
            if xs:
                ax.bar(xs, ys, width, yerr=es, capsize=3, label=mode)
        ax.set_xticks(range(len(tasks)), tasks)
        ax.set_ylim(0, 105)
        ax.set_title(f"{where}\n(bars: mean over twin seeds; lines: sd)", fontsize=9)
        ax.legend(fontsize=8, title="camera", title_fontsize=8)
    axes[0][0].set_ylabel("success (%)")
    fig.suptitle("image actor by camera, and the state oracle", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def per_twin(rows: list[dict]) -> list[dict]:
    """Per task, twin seed and mode: the successes over its episodes with their 95 % Wilson
    interval; and per task and twin, the selected camera against the default one (``paired`` on
    that twin's episodes alone)."""
    from twinrl.report import wilson_interval

    out = []
    for r in rows:
        ok = [float(x) for x in r["episodes"]["success"]]
        lo, hi = wilson_interval(int(round(sum(ok))), len(ok))
        out.append({"task": r["task"], "seed": r["seed"], "mode": r["mode"],
                    "episodes": len(ok), "success": float(np.mean(ok)), "ci95": [lo, hi]})
    for task, seed in dict.fromkeys((r["task"], r["seed"]) for r in rows):
        for x in paired([r for r in rows if r["task"] == task and r["seed"] == seed]):
            out.append({**x, "seed": seed, "mode": "selected - default"})
    return out


def merge(args) -> int:
    """``--merge``: the rows of several ``sensing.json`` files as one result (pooled tables, the
    pooled sign test, per-twin figures). A later file's twin (task, seed) replaces that twin's
    rows from earlier files, so ``--merge bench/results/sensing.json NEW/sensing.json`` updates
    one twin; each row keeps the command that measured it (``command``), and
    ``meta.merged`` lists those of the rows kept. The loop's camera rows are derived anew."""
    by_twin: dict[tuple, list[dict]] = {}  # (task, seed) -> rows; a replaced twin keeps its place
    sim_by_twin: dict[tuple, list[dict]] = {}
    model_free: dict[tuple, dict] = {}  # (task, algo, twin) -> row; a later file's replaces
    for path in args.merge:
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise SystemExit(f"--merge {path}: not a sensing.json ({e})") from None
        command = doc.get("meta", {}).get("command")
        new = [{**r, "command": r.get("command") or command} for r in _with_run_gate(doc)
               if r["mode"] != "loop"]
        new_sim = [{**r, "command": r.get("command") or command}
                   for r in doc.get("sim_rows", [])]
        for twin in dict.fromkeys((r["task"], r["seed"]) for r in new + new_sim):
            by_twin[twin] = [r for r in new if (r["task"], r["seed"]) == twin]
            sim_by_twin[twin] = [r for r in new_sim if (r["task"], r["seed"]) == twin]
        for r in doc.get("model_free", []):
            model_free[(r.get("task"), r.get("algo"), r.get("twin_seed"))] = r
    model_free = list(model_free.values())
    rows = [r for twin in by_twin.values() for r in twin]
    sim_rows = [r for twin in sim_by_twin.values() for r in twin]
    commands = list(dict.fromkeys(r["command"] for r in rows + sim_rows if r.get("command")))
    gate = args.camera_min_rank
    if gate is None:
        from twinrl.loop.arm_config import ArmLoopConfig

        gate = ArmLoopConfig.camera_min_rank
    rows += loop_camera_rows(rows, gate)
    result = _result(args, rows, model_free, sim_rows)
    write_result(args.out / "sensing.json", {"meta": {"merged": commands},
                                             "camera_min_rank": gate, **result}, args)
    for x in result["per_twin"]:
        ci = f"{100 * x['ci95'][0]:.0f}-{100 * x['ci95'][1]:.0f} %"
        what = (f"{100 * x['difference']:+.0f} points, sign test p {x['sign_test_p']:.3g}"
                if "difference" in x else f"{100 * x['success']:.0f} % ({ci})")
        print(f"{x['task']} twin {x['seed']} {x['mode']}: {what}")
    for x in result["paired"]:
        print(f"{x['task']} pooled selected - default: {100 * x['difference']:+.0f} points over "
              f"{x['episodes']} episodes, sign test p {x['sign_test_p']:.3g}")
    print(f"wrote {args.out / 'sensing.json'}")
    return 0


def _with_run_gate(doc: dict) -> list[dict]:
    """A sensing.json's rows, each with what its loop run's camera gate read (``_run_gate``: Q's
    rank, the camera check's choice): the row's own, else the run's if the file was written
    with ``--run`` and the run is still there."""
    import ast

    rows = [dict(r) for r in doc.get("rows", [])]
    try:
        runs = _per_task(ast.literal_eval(doc["meta"]["settings"]["run"]), "--run")
    except (KeyError, ValueError, SyntaxError, SystemExit):
        runs = {}
    for r in rows:
        if r["task"] not in runs:
            continue
        try:
            summary = json.loads((runs[r["task"]] / "summary.json").read_text())
        except (OSError, ValueError):
            continue
        if int(summary.get("seed", -1)) == int(r["seed"]):
            rdir = runs[r["task"]] / f"round{summary['final']['round']}"
            r.update({k: v for k, v in _run_gate(summary, rdir).items() if k not in r})
    return rows


def _run_gate(summary: dict, rdir: Path) -> dict:
    """What a loop run's camera gate read: its Q's held-out rank (``q_rank_corr``) and, where
    the run has its ``camera_check`` stage's record, the camera it chose (``deploy_camera``)."""
    out = {"q_rank_corr": summary["final"].get("q_rank_corr")}
    try:
        out["deploy_camera"] = json.loads((rdir / "camera_check.json").read_text())["camera"]
    except (OSError, ValueError, KeyError):
        pass
    return out


def loop_camera_rows(rows: list[dict], gate: float) -> list[dict]:
    """Per task and twin, the camera the loop deploys (mode ``"loop"``): its ``default`` row
    where the run's Q ranks below ``gate`` (``ArmLoopConfig.camera_min_rank``); else the camera
    the run's ``camera_check`` stage chose where it recorded one (``deploy_camera``: Q's choice
    against the default camera in the identified twin), its ``selected`` row where not -- the
    same episodes, relabelled (``deployed_from``). Twins without a Q rank or without both rows
    get none."""
    out = []
    for task, seed in dict.fromkeys((r["task"], r["seed"]) for r in rows):
        by = {r["mode"]: r for r in rows if r["task"] == task and r["seed"] == seed}
        q = by.get("selected", {}).get("q_rank_corr")
        if q is None or "default" not in by or "loop" in by:
            continue
        src = "default" if q < gate else by["selected"].get("deploy_camera") or "selected"
        out.append({**by[src], "mode": "loop", "deployed_from": src, "q_rank_corr": q,
                    "camera_min_rank": gate})
    return out


def _result(args, rows, model_free, sim_rows=()) -> dict:
    return {"table": summarise(rows), "paired": paired(rows), "per_twin": per_twin(rows),
            "rows": rows, "model_free": model_free, "sim_table": summarise(list(sim_rows)),
            "sim_paired": paired(list(sim_rows)), "sim_rows": list(sim_rows)}



if __name__ == "__main__":
    sys.exit(main())
