"""Why push's box friction resists identification: the box chatters, in MuJoCo C itself.

Drives push's closed-loop excitation (``Push.excitation_policy``) on MuJoCo C -- the real twin's
engine -- for ``--episodes`` episodes, then from every recorded state steps one control period
twice, with the box's friction as it is and 1 % higher, and compares the box's planar velocity.
A smooth system moves it by ~1e-3 m/s; where the box rocks on its corners (contacts switching
between physics steps) the same 1 % moves it by far more. Reported per scene variant: the box's
roll/pitch rate (p50, p90), and over the steps where the box moves, the velocity change from 1 %
of friction (p50, p90) and the fraction above 5 mm/s. Variants: push.xml as shipped, softer
contacts (solref 0.04), half the timestep, elliptic friction cones, a low-friction pusher.

``--scan`` also evaluates sysid's objective (one-step windows, full states, L2) along the box
friction on a noise-free twin whose only perturbation is friction, through MJX with
``contacts="mujoco"`` and 12 iterations: zero at the truth, jagged and V-shaped around it (not the
quadratic bowl Gauss-Newton assumes), because the simulator reproduces the chatter exactly.

Prints a table and writes ``OUT/push_chatter.json``. Seconds (``--scan``: about two minutes).

    python bench/push_chatter.py --out B
    python bench/push_chatter.py --scan --out B
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import mujoco
import numpy as np

from twinrl import envs, report
from twinrl.physics.scenes import scene_path

VARIANTS = {
    "push.xml": lambda x: x,
    "solref 0.04": lambda x: x.replace("<option ", '<default><geom solref="0.04 1"/></default>\n'
                                                   "  <option "),
    "timestep 0.005": lambda x: x.replace('timestep="0.01"', 'timestep="0.005"'),
    "elliptic cones": lambda x: x.replace("<option ", '<option cone="elliptic" '),
    "pusher friction 0.1": lambda x: x.replace(
        'size="0.03" mass="0.2"', 'size="0.03" mass="0.2" priority="1" friction="0.1 0.005 1e-4"'),
}


def chatter(xml: str, episodes: int, seed: int, dv_floor: float = 5e-3) -> dict:
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    substeps = int(round(0.05 / m.opt.timestep))  # push's control period
    box = m.geom("box").id
    mu = float(m.geom_friction[box, 0])
    env = envs.make("push", observation="state")
    rng = np.random.default_rng(seed)
    states, actions = [], []
    for _ in range(episodes):
        mujoco.mj_resetData(m, d)
        d.qpos[:2] = rng.uniform(-0.05, 0.05, 2)
        d.qpos[2:4] += rng.uniform(-0.04, 0.04, 2)
        mujoco.mj_forward(m, d)
        policy = env.excitation_policy(rng)
        for t in range(env.config.episode_length):
            s = np.concatenate([d.qpos, d.qvel])
            a = policy(s, t)
            states.append(s)
            actions.append(a)
            d.ctrl[:] = a
            for _ in range(substeps):
                mujoco.mj_step(m, d)

    def box_velocity(s, a, scale):
        m.geom_friction[box, 0] = mu * scale
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:], d.ctrl[:] = s[:9], s[9:], a
        for _ in range(substeps):
            mujoco.mj_step(m, d)
        m.geom_friction[box, 0] = mu
        return d.qvel[2:4].copy()

    states = np.asarray(states)
    dv = np.array([np.abs(box_velocity(s, a, 1.01) - box_velocity(s, a, 1.0)).max()
                   for s, a in zip(states, actions)])
    moving = np.linalg.norm(states[:, 11:13], axis=1) > 0.02
    rate = np.abs(states[:, 13:15]).max(axis=1)
    return dict(steps=len(states), moving=float(moving.mean()),
                rate_p50=float(np.median(rate)), rate_p90=float(np.percentile(rate, 90)),
                dv_p50=float(np.median(dv[moving])), dv_p90=float(np.percentile(dv[moving], 90)),
                dv_over=float((dv[moving] > dv_floor).mean()))


def scan(factors=(0.95, 0.98, 0.99, 0.995, 1.0, 1.005, 1.01, 1.02, 1.05)) -> list[dict]:
    import jax

    from twinrl import real
    from twinrl.real.perturbation import Perturbation
    from twinrl.real2sim import sysid
    from twinrl.real2sim.sysid.problem import build_problem

    from push_sysid import WEIGHTS, box_contact_truth, floor_held  # this script's neighbour

    config = {"observation": "state", "contacts": "mujoco", "solver_iterations": 12}
    twin_config = {"observation": "state"}
    hidden = real.make_real("push", seed=0, config=twin_config).oracle().perturbation
    pert = dataclasses.replace(Perturbation.none(), friction_scale=hidden.friction_scale)
    twin = real.make_real("push", seed=0, perturbation=pert, config=twin_config)
    data = sysid.collect(twin, episodes=5, seed=0)
    env = envs.make("push", **config)
    truth = box_contact_truth(env, twin.oracle().params)  # evaluation only
    env = envs.make("push", params=truth.replace(friction=floor_held(env, truth.friction)),
                    **config)
    cfg = sysid.SysidConfig(params=("friction/box",), observation_weights=WEIGHTS, loss="l2",
                            window=1, latency=0)
    rows = []
    with jax.enable_x64(True):
        prob = build_problem(env, data, cfg)
        for f in factors:
            theta = prob.theta0.copy()
            theta[0] += np.log(f)
            rows.append(dict(factor=f, loss=prob.data_loss(prob.residuals(theta, 0))))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scan", action="store_true", help="also scan sysid's objective (MJX)")
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error("--episodes must be >= 1")
    xml = scene_path("push").read_text()
    out = {name: chatter(edit(xml), args.episodes, args.seed) for name, edit in VARIANTS.items()}
    report.print_table(
        f"push's box under its excitation, MuJoCo C ({args.episodes} episodes): box velocity "
        "change in one control step from +1 % box friction, over the steps where it moves",
        ["scene", "roll/pitch rate p50", "p90", "dv p50 (m/s)", "dv p90", "share > 5 mm/s"],
        [[k, v["rate_p50"], v["rate_p90"], v["dv_p50"], v["dv_p90"], v["dv_over"]]
         for k, v in out.items()])
    result = dict(episodes=args.episodes, seed=args.seed, variants=out)
    if args.scan:
        result["scan"] = scan()
        report.print_table("sysid objective along box friction (noise-free, 1-step windows)",
                           ["friction / truth", "loss"],
                           [[r["factor"], r["loss"]] for r in result["scan"]])
    print(f"wrote {report.write_json(args.out / 'push_chatter.json', result)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
