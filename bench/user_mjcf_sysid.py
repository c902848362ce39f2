"""Real2Sim on a robot that is not a twinrl task: any MJCF, its own logs (``envs.from_mjcf``).

The "robot" is MuJoCo C running ``--mjcf`` (default: twinrl's Panda, ``envs/arm/panda.xml``:
seven position servos, nine bodies) with every body's mass (and inertia with it) scaled by a
factor drawn in [0.85, 1.2] and every joint's damping by one in [0.6, 1.6] (``--seed``). Each of
``--episodes`` episodes starts at the MJCF's first keyframe (else ``qpos0``) and holds random
controls (within 40 % of each actuator's half-range around the start, for 10 samples at a time)
for ``--steps`` samples of ``--frame-skip`` physics steps; ``qpos``, ``qvel`` (plus Gaussian
``--noise``) and ``ctrl`` are logged as a robot's logger would give them. Then
``sysid.fit(env, env.transitions(...))`` fits every mass and damping from the nominal MJCF
(``--window``-step shooting windows, latency 0) and the table gives each parameter's relative
error against the hidden value (``sysid.compare_to_truth``), with sysid's
own verdict (a body welded to the world, like the Panda's base, moves nothing and is reported
not identifiable). The identified MJCF is written to ``OUT/identified.xml``.

Prints the table and writes ``OUT/user_mjcf_sysid.json``.

    python bench/user_mjcf_sysid.py --out B                       # the Panda, ~1 min on 2 cores
    python bench/user_mjcf_sysid.py --mjcf my_robot.xml --frame-skip 1 --out B
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import twinrl  # noqa: F401  (before jax: compilation cache, quiet XLA)
from twinrl import envs, report
from twinrl.physics import PhysParams
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)

PANDA = Path(twinrl.__file__).parent / "envs" / "arm" / "panda.xml"


def robot_logs(path: str, seed: int, episodes: int, steps: int, frame_skip: int):
    """MuJoCo C on ``path`` with hidden scales: ``(qpos, qvel, ctrl, truth)``, ``truth`` the
    robot's ``PhysParams`` (evaluation only)."""
    import mujoco

    m = mujoco.MjModel.from_xml_path(path)
    rng = np.random.default_rng(seed)
    mass_scale = rng.uniform(0.85, 1.2, m.nbody - 1)
    damping_scale = rng.uniform(0.6, 1.6, m.nv)
    m.body_inertia[1:] *= mass_scale[:, None]
    m.body_mass[1:] *= mass_scale
    m.dof_damping[:] *= damping_scale
    d = mujoco.MjData(m)
    mujoco.mj_setConst(m, d)
    lo, hi = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
    qp, qv, cs = [], [], []
    for _ in range(episodes):
        mujoco.mj_resetData(m, d)
        if m.nkey:
            mujoco.mj_resetDataKeyframe(m, d, 0)
        mujoco.mj_forward(m, d)
        centre = np.clip(d.actuator_length.copy(), lo, hi) if m.nu else np.zeros(0)
        held = centre + rng.uniform(-0.4, 0.4, (-(-steps // 10), m.nu)) * (hi - lo) / 2
        ctrl = np.clip(np.repeat(held, 10, axis=0)[:steps], lo, hi)
        q, v = [d.qpos.copy()], [d.qvel.copy()]
        for c in ctrl:
            d.ctrl[:] = c
            for _ in range(frame_skip):
                mujoco.mj_step(m, d)
            q.append(d.qpos.copy())
            v.append(d.qvel.copy())
        qp.append(q)
        qv.append(v)
        cs.append(ctrl)
    return np.array(qp), np.array(qv), np.array(cs), PhysParams.from_model(m)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mjcf", default=str(PANDA), help="the robot's MJCF (default: the Panda)")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--steps", type=int, default=100, help="logged samples per episode")
    p.add_argument("--frame-skip", type=int, default=4,
                   help="physics steps per logged sample (default 4: the Panda's 2 ms timestep "
                        "logged at 125 Hz)")
    p.add_argument("--window", type=int, default=10, help="shooting window, samples")
    p.add_argument("--seed", type=int, default=0, help="draws the hidden scales and controls")
    p.add_argument("--noise", type=float, nargs=2, default=(0.0, 0.0), metavar=("QPOS", "QVEL"),
                   help="sd of Gaussian sensor noise added to the logged qpos and qvel (default "
                        "0 0; e.g. 0.001 0.01: 1 mrad encoders, 0.01 rad/s velocities)")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    for flag in ("episodes", "steps", "frame_skip", "window"):
        if getattr(args, flag) < 1:
            raise SystemExit(f"--{flag.replace('_', '-')} must be >= 1")
    if min(args.noise) < 0:
        raise SystemExit(f"--noise must be >= 0, got {args.noise}")
    from twinrl.envs.mjcf import save_mjcf
    from twinrl.real2sim import sysid

    env = envs.from_mjcf(args.mjcf, frame_skip=args.frame_skip)
    qpos, qvel, ctrl, truth = robot_logs(args.mjcf, args.seed, args.episodes, args.steps,
                                         args.frame_skip)
    noise = np.random.default_rng([args.seed, 1])
    qpos = qpos + args.noise[0] * noise.standard_normal(qpos.shape)
    qvel = qvel + args.noise[1] * noise.standard_normal(qvel.shape)
    names = [n for n in sysid.param_names(env) if n.split("/")[0] in ("mass", "damping")]
    t0 = time.perf_counter()
    res = sysid.fit(env, env.transitions(qpos, qvel, ctrl),
                    sysid.SysidConfig(params=tuple(names), max_latency=0, window=args.window))
    fit_s = time.perf_counter() - t0
    initial = {r["parameter"]: r["initial"] for r in res.table}
    rows = [{"parameter": r["parameter"], "nominal": initial[r["parameter"]], "truth": r["truth"],
             "identified": r["identified"], "rel_err": r["identified"] / r["truth"] - 1,
             "nominal_rel_err": initial[r["parameter"]] / r["truth"] - 1, "status": r["status"]}
            for r in sysid.compare_to_truth(res, truth)]
    ok = [abs(r["rel_err"]) for r in rows if r["status"] == "identified"]
    xml = save_mjcf(env, res.params, args.out / "identified.xml")
    out = {"mjcf": args.mjcf, "samples": int(np.prod(ctrl.shape[:2])),
           "noise": list(args.noise),
           "fit_s": fit_s, "rows": rows, "identified_max_rel_err": max(ok) if ok else None,
           "identified_xml": str(xml)}
    write_result(args.out / "user_mjcf_sysid.json", out, args)
    report.print_table(
        f"sysid of {Path(args.mjcf).name} from {out['samples']} logged samples of MuJoCo C, "
        f"noise sd {args.noise[0]:g} / {args.noise[1]:g} ({fit_s:.0f} s)",
        ["parameter", "truth", "nominal err", "identified err", "sysid says"],
        [[r["parameter"], f"{r['truth']:.4g}", f"{100 * r['nominal_rel_err']:+.1f} %",
          f"{100 * r['rel_err']:+.3f} %", r["status"]] for r in rows])
    print(f"wrote {args.out / 'user_mjcf_sysid.json'} and {xml}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
