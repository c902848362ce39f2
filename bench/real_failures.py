"""Where a loop's real failures come from: its actor, its identified twin, or the real physics.

For each ``--run TASK=DIR`` (a finished ``twinrl run``: its last round's image actor and
identified twin; its real twin's hidden perturbation from ``DIR/eval/twin.json``, for evaluation
only), on ``--episodes`` real starts ``reset(seed=1000 * twin + first + i)`` (the sensing
bench's), per start:

- ``real``: the image actor deployed in the real twin as ``bench/sensing.py`` deploys it (with
  the run's residual policy where its gate accepted one), with the loop's camera (``--camera``:
  the run's deployed camera unless given); its actions are recorded, and where the true tool
  ends against the target (peg: the tip's horizontal offset from the hole's axis and its height
  above the hole's top, mm);
- ``sim actor``: the same actor (without a residual) in the identified twin from the same
  start (``reset_key``), the camera where the real episode's first choice put it -- does the twin
  reproduce the failure? -- and, for an actor that reads a fitted pose, ``sim truth``: the actor
  fed the true state where it reads that pose (its cloning without its view);
- ``replay``: the real episode's actions replayed open loop in the identified twin -- does the
  twin predict the real outcome of the real actions (its physics, its grasp)? -- and again in
  the twin holding the tool at the real twin's hidden grasp (``replay_grasp``): how much of a
  disagreement the fit of the grasp makes;
- ``plan`` (``--plan``): trajectory optimisation in the identified twin, as the loop's plan stage
  runs it, from each start the actor failed on in the real twin and as many it solved (the
  controls); each plan replayed open loop in the real twin -- can the expert the actor imitates
  solve that start, in the twin and in the real physics?

Prints a table per run (failed starts against solved ones) and writes ``DIR/real_failures.json``
(``--out DIR``), every start's figures in it.

    python bench/real_failures.py --run peg_insertion=runs/peg --episodes 50 --plan --out DIR
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, jaxconfig)
import jax
import jax.numpy as jnp
import numpy as np

from twinrl.report import print_table
from q_rank import _pct, evaluate_runs, load_run  # noqa: E402  (bench/q_rank.py: a run's round)


class Recorder:
    """A real twin that records, per episode, the start state, the actions sent, and at the end
    (``success``: the deployer's last call of an episode) the true state and tool."""

    def __init__(self, twin):
        self.twin, self.episodes = twin, []

    def __getattr__(self, name):
        return getattr(self.twin, name)

    def reset(self, **kw):
        out = self.twin.reset(**kw)
        self.episodes.append({"qpos0": self.twin.oracle().qpos, "actions": []})
        return out

    def step(self, action):
        self.episodes[-1]["actions"].append(np.asarray(action, np.float32))
        return self.twin.step(action)

    def success(self):
        ok = self.twin.success()
        o = self.twin.oracle()
        self.episodes[-1].update(qpos=o.qpos, qvel=o.qvel, tool=self.twin.true_tool(), ok=ok)
        return ok


def offsets(env, qpos, tip=None) -> dict | None:
    """The tool tip against the target, mm, for a task with ``tip_and_hole`` (peg): ``xy`` the
    tip's distance from the hole's axis, ``z`` its height above the hole's top (negative: in).
    ``tip``: the true tip (a real twin's); default the twin's own (its identified grasp)."""
    if not hasattr(env, "tip_and_hole"):
        return None
    t, hole = (np.asarray(x, np.float64) for x in env.tip_and_hole(jnp.asarray(qpos, jnp.float32)))
    t = t if tip is None else np.asarray(tip, np.float64)
    d = 1e3 * (t - hole)
    return {"xy": float(np.hypot(d[0], d[1])), "z": float(d[2])}


def _padded(actions: list, T: int, m: int) -> np.ndarray:
    a = np.zeros((T, m), np.float32)
    if actions:
        a[:len(actions)] = np.stack(actions)[:T]
    return a


def real_episodes(task, run, env, actor, ap, q, qp, cfg, args, summary):
    """The actor's real episodes on the run's twin: ``(episodes, result, twin)``, per start its
    success and, recorded, its start, actions and end; the deployment's result
    (``Deployer.run``'s); the twin (open, for the plans' replays)."""
    from twinrl.learn.camera_choice import image_size
    from twinrl.real.remote import hidden_perturbation
    from twinrl.real.twin import RealTwin
    from twinrl.sim2real import active

    seed = int(summary["seed"])
    hidden = hidden_perturbation(task, seed, run / "eval" / "twin.json")
    twin = RealTwin(task, seed=seed, perturbation=hidden,
                    width=image_size(env, actor), height=image_size(env, actor))
    rec = Recorder(twin)
    correction = None
    if summary["final"].get("residual_accepted"):  # deployed as the loop deploys it
        from twinrl.learn.checkpoint import load_policy

        rdir = run / f"round{summary['final']['round']}"
        correction = active.residual_correction(*load_policy(rdir / "residual")[:2])
    dep = active.Deployer(env, actor, ap, q=q, q_params=qp, sensing=cfg, residual=correction)
    camera = args.camera or summary["final"].get("deployed_camera") or "default"
    twin.move_camera(env.mount.default)
    res = dep.run(rec, active.DeployConfig(camera=camera, episodes=args.first + args.episodes),
                  seed=1000 * seed, start=args.first)
    res["camera"], res["hidden"] = camera, hidden
    return rec.episodes, res, twin


def sim_side(env, actor, ap, keys, coords, real_actions) -> dict:
    """The actor in the identified twin from the real starts (``keys``), the camera at
    ``coords``; the actor fed the true pose (a pose actor); the real actions replayed."""
    from twinrl.learn.camera_choice import image_size, observer
    from twinrl.learn.common import held_episodes

    act = lambda o: actor.apply(ap, o)  # noqa: E731
    observe = observer(env, image_size(env, actor), keys=tuple(actor.obs_spec))

    def true_observe(s, c):  # the fitted pose replaced by the truth it estimates
        return {"estimate": env.observe(*env.state_from_obs(s.obs), nominal=False)}

    out = {"sim_actor": np.asarray(jax.jit(
        lambda: held_episodes(env, observe, act, keys, coords=coords).success)())}
    if "estimate" in actor.obs_spec:
        out["sim_truth"] = np.asarray(jax.jit(
            lambda: held_episodes(env, true_observe, act, keys, coords=coords).success)())

    ok, qend = replay(env, keys, real_actions)
    out["replay"], out["replay_qpos"] = ok, qend
    return out


def replay(env, keys, actions) -> tuple[np.ndarray, np.ndarray]:
    """``actions`` (N, T, m) open loop in ``env`` from ``reset(keys)``: success, final qpos."""
    def one(k, a):
        final, _ = env.unroll(env.reset(k), a)
        q, v = final.pipeline_state.qpos, final.pipeline_state.qvel
        return env.success(q, v), q

    ok, q = jax.jit(jax.vmap(one))(keys, actions)
    return np.asarray(ok), np.asarray(q)


def true_grasp_env(run: Path, hidden):
    """The run's identified twin holding its tool at the real twin's hidden grasp (evaluation
    only): what the twin's replay of the real actions would be with the grasp fitted exactly."""
    import dataclasses

    from twinrl.envs.system import System, ToolGrasp
    from twinrl.loop.arm import run_env

    summary = json.loads((run / "summary.json").read_text())
    system = System.load(run / f"round{summary['final']['round']}" / "system.json")
    grasp = ToolGrasp(hidden.tool_pos_offset, hidden.tool_rot_offset)
    return run_env(run, dataclasses.replace(system, tool=grasp))


def plan_side(env, twin, keys, seeds, config: dict) -> dict:
    """Plans from ``keys`` in the identified twin (the loop's plan stage's settings), each
    replayed open loop in the real twin from its start (``seeds``): success in both. ``twin``
    is the deployment's, its controller already calibrated by ``Deployer.run``."""
    from twinrl.learn import plans
    from twinrl.loop.arm_config import ArmLoopConfig

    c = ArmLoopConfig()
    res = plans.plan(env, len(keys), int(config.get("trajopt_iterations", c.trajopt_iterations)),
                     min(10, len(keys)),
                     restarts=int(config.get("trajopt_restarts", c.trajopt_restarts)), keys=keys,
                     say=lambda s: print(f"[bench] {s}", flush=True))
    real, ends = [], []
    for s, a in zip(seeds, res["plans"]):
        twin.reset(seed=int(s))
        for x in a:
            if twin.step(x)[2]:
                break
        real.append(twin.success())
        ends.append(offsets(env, twin.oracle().qpos, (twin.true_tool() or (None,))[0]))
    return {"plan_sim": np.asarray(res["success"]), "plan_real": np.asarray(real),
            "plan_real_end": ends, "plan_seconds_per_solved": res["seconds_per_solved"]}


def evaluate(task: str, run: Path, args) -> dict:
    from twinrl.real.twin import reset_key

    t0 = time.perf_counter()
    summary, env, actor, ap, q, qp, cfg = load_run(task, run)
    episodes, res, twin = real_episodes(task, run, env, actor, ap, q, qp, cfg, args, summary)
    seeds = [1000 * int(summary["seed"]) + args.first + i for i in range(args.episodes)]
    keys = jnp.stack([reset_key(s) for s in seeds])
    T, m = env.episode_length, env.action_size
    acts = jnp.asarray(np.stack([_padded(e["actions"], T, m) for e in episodes]))
    coords = jnp.asarray([c if c is not None else env.mount.default for c in res["coords"]],
                         jnp.float32)
    q0 = np.asarray(jax.vmap(env.reset)(keys).pipeline_state.qpos)
    start_gap = float(np.max(np.abs(q0 - np.stack([e["qpos0"] for e in episodes]))))
    if start_gap > 1e-4:
        raise SystemExit(f"{task}: the simulator's starts miss the real ones by {start_gap:.1e}")
    sim = sim_side(env, actor, ap, keys, coords, acts)
    if any(res["hidden"].tool_pos_offset) or any(res["hidden"].tool_rot_offset):
        sim["replay_grasp"] = replay(true_grasp_env(run, res["hidden"]), keys, acts)[0]
    real_ok = np.asarray([e["ok"] for e in episodes], float)
    starts = []
    for i, e in enumerate(episodes):
        row = {"start": args.first + i, "seed": seeds[i], "real": bool(e["ok"]),
               "real_end": offsets(env, e["qpos"], (e["tool"] or (None,))[0]),
               "sim_actor": bool(sim["sim_actor"][i]), "replay": bool(sim["replay"][i]),
               "replay_end": offsets(env, sim["replay_qpos"][i]),
               "return": float(res["return"][i])}
        for k in ("sim_truth", "replay_grasp"):
            if k in sim:
                row[k] = bool(sim[k][i])
        starts.append(row)
    if args.plan:
        failed = np.flatnonzero(real_ok == 0)
        controls = np.flatnonzero(real_ok > 0)[:max(len(failed), 1)]
        pick = np.concatenate([failed, controls]).astype(int)
        config = json.loads((run / "loop.json").read_text()).get("config") or {}
        p = plan_side(env, twin, keys[pick], [seeds[i] for i in pick], config)
        for j, i in enumerate(pick):
            starts[i].update(plan_sim=bool(p["plan_sim"][j]), plan_real=bool(p["plan_real"][j]),
                             plan_real_end=p["plan_real_end"][j])
    twin.close()
    out = {"task": task, "run": str(run), "twin_seed": summary.get("seed"),
           "camera": res["camera"], "episodes": args.episodes, "first_start": args.first,
           "real_success": float(real_ok.mean()), "start_gap": start_gap,
           "groups": groups(starts), "starts": starts, "wall_s": time.perf_counter() - t0}
    print(f"[bench] {task} {run.name}: real {out['real_success']:.2f} "
          f"({out['wall_s']:.0f} s)", flush=True)
    return out


def groups(starts: list[dict]) -> list[dict]:
    """The figures of the starts the actor failed in the real twin and of those it solved."""
    out = []
    for name, real in (("failed", False), ("solved", True)):
        rows = [s for s in starts if s["real"] == real]
        g = {"group": name, "starts": len(rows)}
        for k in ("sim_actor", "sim_truth", "replay", "replay_grasp", "plan_sim", "plan_real"):
            vals = [s[k] for s in rows if k in s]
            g[k] = float(np.mean(vals)) if vals else None
            g[k + "_n"] = len(vals)
        for k in ("real_end", "replay_end"):
            ends = [s[k] for s in rows if s.get(k)]
            if ends:
                g[k + "_xy_mm"] = float(np.median([e["xy"] for e in ends]))
                g[k + "_z_mm"] = float(np.median([e["z"] for e in ends]))
        out.append(g)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", nargs="+", required=True, help="TASK=DIR twinrl run directories")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--first", type=int, default=0, help="the first start (the sensing bench's 0)")
    p.add_argument("--camera", choices=("default", "selected", "random"), default=None,
                   help="the real episodes' camera (default: the run's deployed camera)")
    p.add_argument("--plan", action="store_true",
                   help="plan from the failed starts and as many solved ones; replay in real")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    if args.episodes < 1 or args.first < 0:
        raise SystemExit("--episodes must be >= 1 and --first >= 0")
    rows = evaluate_runs(args, evaluate, "real_failures.json")
    for r in rows:
        print_table(f"{r['task']} twin {r['twin_seed']}: the starts the actor failed in the real "
                    f"twin against those it solved ({r['camera']} camera)",
                    ["starts", "n", "sim actor", "sim, true pose", "real actions in the twin",
                     "... at the true grasp", "plan in the twin", "plan in real",
                     "real end xy / z (mm)"],
                    [[g["group"], g["starts"], _pct(g["sim_actor"]), _pct(g["sim_truth"]),
                      _pct(g["replay"]), _pct(g["replay_grasp"]), _pct(g["plan_sim"]),
                      _pct(g["plan_real"]),
                      f"{g['real_end_xy_mm']:.1f} / {g['real_end_z_mm']:.1f}"
                      if "real_end_xy_mm" in g else "-"] for g in r["groups"]])
    print(f"wrote {args.out / 'real_failures.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
