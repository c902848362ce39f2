"""How much a real twin's servos bend the arm's Cartesian commands: the tool point's motion for
one command in a twin's hidden dynamics against the nominal twin's, for the arm's controller as
it is, calibrated to the servos, and for an integrating variant.

``CartesianController`` sets each step's joint targets from the *measured* joints (``q + dq``):
the servo then closes only part of ``dq`` within the 0.04 s step, and how much depends on its
gain over its damping (and the link's inertia), joint by joint, so a twin's +-15 % gains and
damping bend the commanded direction. Rows per controller:

- ``measured``: the nominal controller (what round 0 records with);
- ``calibrated (true)``: calibrated to the twin's true servo speeds (``ArmTask.servo_speed`` of
  the hidden parameters; evaluation only: the best calibration can do);
- ``calibrated (identified)``: with ``--run``, the speeds the run identified (its
  ``round1/system.json``), as the loop deploys;
- ``integrating``: ``dq`` added to the previous step's targets instead (evaluated here only;
  not in ``twinrl``), as a robot's Cartesian position interface does, so the servos settle on
  the commanded pose whatever their gains. (No drop-in: swapped into the spatula as is, the
  nominal twin's planner solves 1/8 starts, not 7/8; README, stop 60.)

For each twin (``--seeds``: the public ``make_real(task, seed)``; ``--run DIR``: the hidden twin
of a ``twinrl run`` output, ``DIR/eval/twin.json``; evaluation only) and each command (+x push,
+z lift, +y sideways, half the speed limit for ``--steps`` steps, then as many of zero command):
the displacement's length against the nominal twin's (ratio), the angle between them (deg) and
the gap (mm), after the commands and after the still steps. Latency 0, the hidden grasp left
out: the servos' part alone. Prints a table, writes ``OUT/arm_controller.json``. A minute per
twin on 2 cores.

    python bench/arm_controller.py --tasks spatula_flipping --seeds 0 1 2 --out B
    python bench/arm_controller.py --tasks spatula_flipping --run runs/spatula2 --out B
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, _jaxconfig)
import jax
import jax.numpy as jnp
import numpy as np

from twinrl import envs
from twinrl.envs.arm.kinematics import N_JOINTS
from twinrl.report import print_table, run_meta, write_json

TASKS = ("peg_insertion", "spatula_flipping", "needle_threading")
COMMANDS = {"+x": (1.0, 0.0, 0.0), "+z": (0.0, 0.0, 1.0), "+y": (0.0, 1.0, 0.0)}


def _stepper(env, integrate: bool):
    def step(data, a):
        if not integrate:  # the task's own step (its controller as calibrated)
            return env.sim_step(data, a, env.params)
        # the task's targets, moved from the measured joints onto the previous targets (set to
        # the start posture at reset)
        ctrl = env.control(data.qpos, data.qvel, a)
        ctrl = ctrl.at[:N_JOINTS].add(data.ctrl[:N_JOINTS] - data.qpos[:N_JOINTS])
        return env.sim.step(data, ctrl, env.params)
    return jax.jit(step)


def displacements(env, steps: int, speeds: dict | None = None) -> dict:
    """Per controller and command: the tool point's displacement (m) after the commands and
    after as many still steps, from the task's start for key 0. ``speeds``: more rows, the
    controller calibrated to each named set of servo speeds."""
    size = env.action_size
    out = {}
    kinds = [("measured", False, None), ("integrating", True, None)]
    kinds += [(name, False, js) for name, js in (speeds or {}).items()]
    for label, integrate, js in kinds:
        env.calibrate_controller(js)
        step = _stepper(env, integrate)
        for name, cmd in COMMANDS.items():
            a = jnp.zeros(size, jnp.float32).at[:3].set(0.5 * jnp.asarray(cmd, jnp.float32))
            d = env.reset(jax.random.PRNGKey(0)).pipeline_state
            d = d.replace(ctrl=d.ctrl.at[:N_JOINTS].set(d.qpos[:N_JOINTS]))
            p0 = np.asarray(env.tool_point(d.qpos), np.float64)
            for _ in range(steps):
                d = step(d, a)
            moved = np.asarray(env.tool_point(d.qpos), np.float64) - p0
            for _ in range(steps):
                d = step(d, jnp.zeros(size, jnp.float32))
            still = np.asarray(env.tool_point(d.qpos), np.float64) - p0
            out[(label, name)] = (moved, still)
    env.calibrate_controller(None)
    return out


def compare(u: np.ndarray, v: np.ndarray) -> dict:
    cos = float(np.dot(u, v) / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12))
    return {"length_ratio": float(np.linalg.norm(v) / max(np.linalg.norm(u), 1e-12)),
            "angle_deg": float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))),
            "gap_mm": float(1000 * np.linalg.norm(v - u)),
            "nominal_mm": float(1000 * np.linalg.norm(u))}


def twins(args):
    """(label, task, seed, perturbation or None) of each twin asked for."""
    from twinrl.real.remote import hidden_perturbation

    for task in args.tasks:
        for s in args.seeds:
            yield f"{task} twin {s}", task, s, None, None
    for run in args.run:
        secret = Path(run) / "eval" / "twin.json"
        if not secret.is_file():
            _bad(f"--run {run}: no eval/twin.json there (a twinrl run's output)")
        doc = json.loads(secret.read_text())
        task, seed = doc.get("task"), doc.get("seed")
        if task not in TASKS:
            _bad(f"--run {run}: its twin is {task!r}, not a manipulation task")
        yield (f"{task} run {run}", task, int(seed), hidden_perturbation(task, seed, secret),
               Path(run) / "round1" / "system.json")


def _bad(message: str):
    print(f"bench/arm_controller.py: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def main(argv=None) -> int:
    from twinrl.envs.system import System
    from twinrl.real import make_real

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="*", default=["spatula_flipping"], choices=TASKS)
    p.add_argument("--seeds", nargs="*", type=int, default=[0, 1, 2])
    p.add_argument("--run", nargs="*", default=[], help="twinrl run outputs (their hidden twin)")
    p.add_argument("--steps", type=int, default=5, help="command steps (then as many still)")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    if args.steps < 1:
        _bad(f"--steps must be >= 1, got {args.steps}")
    nominal, rows, table = {}, [], []
    for label, task, seed, pert, identified in list(twins(args)):  # bad --run: before any work
        if task not in nominal:
            nominal[task] = displacements(envs.make(task), args.steps)
        twin = make_real(task, seed=seed, perturbation=pert)
        truth = twin.oracle()  # evaluation only
        twin.close()
        system = System(params=truth.params, latency=0, task=task)
        env = envs.make(task, system=system)
        speeds = {"calibrated (true)": env.servo_speed(truth.params)}
        if identified is not None and identified.is_file():
            speeds["calibrated (identified)"] = env.servo_speed(System.load(identified).params)
        moved = displacements(env, args.steps, speeds)
        for (ctl, cmd), (m, s) in moved.items():
            n_m, n_s = nominal[task]["measured" if ctl.startswith("calibrated") else ctl, cmd]
            row = {"twin": label, "controller": ctl, "command": cmd,
                   "after_commands": compare(n_m, m), "after_still": compare(n_s, s)}
            rows.append(row)
            a, b = row["after_commands"], row["after_still"]
            table.append([label, ctl, cmd, f"{a['nominal_mm']:.1f}", f"{a['length_ratio']:.2f}",
                          f"{a['angle_deg']:.1f}", f"{b['nominal_mm']:.1f}",
                          f"{b['length_ratio']:.2f}", f"{b['angle_deg']:.1f}",
                          f"{b['gap_mm']:.1f}"])
    print_table(f"tool point moved by {args.steps} commands at half speed, then {args.steps} "
                "still: twin against nominal",
                ["twin", "controller", "command", "nominal mm", "ratio", "angle deg",
                 "still: nominal mm", "ratio", "angle deg", "gap mm"], table)
    path = write_json(args.out / "arm_controller.json", {"meta": run_meta(args), "rows": rows})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
