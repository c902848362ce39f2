"""Push identification, taken apart: box mass and friction from the push real twin, by case.

Records ``--episodes`` episodes of push's closed-loop excitation from a real twin observed in full
states (``observation="state"``), then fits box mass, box friction, pusher friction, the
motor gains and the pusher damping (pusher mass known -- weighed --, floor friction held at 0.05 so
the box's coefficient is the contact's; the box's tilt and rocking left out of the residuals).
The twin is twin ``--twin-seed``'s hidden perturbation, or only some of its parts
(``--only mass_scale friction_scale ...``: the others nominal), so each cause can be looked at
alone. ``--start truth`` starts the fit at the hidden truth (evaluation only), to tell an
objective whose minimum is elsewhere from a fit that stops short. ``--contacts``,
``--iterations`` and ``--loss`` choose the simulator and the objective. ``--staged`` fits the
pusher first, on the windows where it keeps clear of the box, then the box from planar positions
(``staged``). The box friction's truth is the box-floor contact's coefficient, the larger of the
twin's box and floor values (the fit holds its floor's at 0.05).

Prints a table (truth, identified, sd, relative error per parameter) and writes
``OUT/push_sysid.json``. About 2-3 minutes per case on 2 cores.

    python bench/push_sysid.py --out B                                   # stock simulator
    python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --out B
    python bench/push_sysid.py --contacts mujoco --iterations 12 --only friction_scale --out B
    python bench/push_sysid.py --contacts mujoco --iterations 12 --start truth --out B
    python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --staged --out B
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

import twinrl  # noqa: F401  (compilation cache)
from twinrl import envs, real, report
from twinrl.physics.collision import CONTACTS
from twinrl.real.perturbation import Perturbation
from twinrl.real2sim import sysid
from twinrl.real2sim.sysid.config import LOSSES, parse_param
from twinrl.real2sim.sysid.problem import param_value

PARAMS = ("mass/box", "friction/box", "friction/pusher", "gain/fx", "gain/fy", "damping/px",
          "damping/py")
PARTS = ("mass_scale", "friction_scale", "gain_scale", "damping_scale", "latency_steps",
         "obs_noise_std")
FLOOR_FRICTION = 0.05  # below the box's: the box-floor contact's coefficient is the box's
# [qpos (9): pusher x y, box x y z, quaternion; qvel (8): pusher, box linear, angular]
WEIGHTS = tuple(0.0 if i in (4, 5, 6, 7, 13, 14, 15, 16) else 1.0 for i in range(17))
PUSHER = ("gain/fx", "gain/fy", "damping/px", "damping/py")
PUSHER_WEIGHTS = tuple(1.0 if i in (0, 1, 9, 10) else 0.0 for i in range(17))
POSITION_WEIGHTS = tuple(1.0 if i in (0, 1, 2, 3, 8) else 0.0 for i in range(17))
CLEAR_WINDOW = 5  # steps per stage-1 window: short, so that some keep clear of the box


def box_contact_truth(env, params):
    """The twin's ``params`` with the box's friction replaced by the box-floor contact's
    coefficient, the larger of the two geoms' (MuJoCo's rule): with the floor held at
    ``FLOOR_FRICTION`` the fit's box value stands for the contact's, so that is its truth (the
    floor's value on twins whose floor is the rougher)."""
    floor, box = (env.sim.mj_model.geom(g).id for g in ("floor", "box"))
    friction = np.array(params.friction)
    friction[box] = max(friction[box], friction[floor])
    return params.replace(friction=friction)


def floor_held(env, friction):
    """``friction`` with the floor's coefficient at ``FLOOR_FRICTION``."""
    friction = np.array(friction)
    friction[env.sim.mj_model.geom("floor").id] = FLOOR_FRICTION
    return friction


def staged(env, data, known, loss):
    """Two stages: (1) the pusher's gains and damping, and the latency, on the short windows
    where the pusher stays clear of the box (``Push.pusher_clear``), from its own states only;
    (2) box mass, box friction and pusher friction on all windows, the pusher's values known,
    from planar positions only (the box's velocities chatter with its rocking; positions
    integrate it away). Returns both results and the number of stage-1 windows."""
    c1 = sysid.SysidConfig(params=PUSHER, known=known, observation_weights=PUSHER_WEIGHTS,
                           loss=loss, window=CLEAR_WINDOW)
    w = sysid.windows_from_dataset(env, data, c1.window, max_latency=c1.max_latency)
    states = np.concatenate([w.obs0[:, None], w.targets], axis=1)
    clear = env.pusher_clear(states).all(axis=1)
    first = sysid.fit(env, w.select(clear), c1)
    pusher = tuple((n, float(v)) for n, v in zip(first.names, first.values) if n in PUSHER)
    c2 = sysid.SysidConfig(params=("mass/box", "friction/box", "friction/pusher"),
                           known=known + pusher, observation_weights=POSITION_WEIGHTS,
                           loss=loss, latency=first.latency)
    return first, sysid.fit(env, data, c2), int(clear.sum())


def run(args) -> dict:
    config = {"observation": "state"}
    hidden = real.make_real("push", seed=args.twin_seed, config=config).oracle().perturbation
    pert = hidden if args.only is None else dataclasses.replace(
        Perturbation.none(), **{k: getattr(hidden, k) for k in args.only})
    twin = real.make_real("push", seed=args.twin_seed, perturbation=pert, config=config)
    truth = twin.oracle()  # evaluation only
    data = sysid.collect(twin, episodes=args.episodes, seed=args.seed)
    sim_config = dict(contacts=args.contacts, solver_iterations=args.iterations, **config)
    env = envs.make("push", **sim_config)
    true_of = lambda n: float(param_value(truth.params.as_dict(), *parse_param(env, n)))  # noqa
    contact_truth = box_contact_truth(env, truth.params)
    if args.start == "truth":
        env = envs.make("push", params=contact_truth.replace(
            friction=floor_held(env, contact_truth.friction)), **sim_config)
    known = (("mass/pusher", true_of("mass/pusher")), ("friction/floor", FLOOR_FRICTION))
    t = time.perf_counter()
    if args.staged:
        first, res, n_clear = staged(env, data, known, args.loss)
        rows = ([r for r in sysid.compare_to_truth(first, contact_truth, pert.latency_steps)
                 if r["parameter"] in PUSHER]
                + [r for r in sysid.compare_to_truth(res, contact_truth, pert.latency_steps)
                   if r["parameter"] not in PUSHER + ("friction/floor",)])
    else:
        cfg = sysid.SysidConfig(params=PARAMS, known=known, observation_weights=WEIGHTS,
                                loss=args.loss)
        res = sysid.fit(env, data, cfg)
        rows = [r for r in sysid.compare_to_truth(res, contact_truth, pert.latency_steps)
                if r["parameter"] != "friction/floor"]
        n_clear = None
    return dict(twin_seed=args.twin_seed, only=args.only, episodes=args.episodes,
                contacts=args.contacts, iterations=args.iterations, loss=args.loss,
                start=args.start, staged=args.staged, clear_windows=n_clear,
                latency=res.latency, true_latency=pert.latency_steps,
                obs_noise_std=pert.obs_noise_std, loss_value=res.loss,
                seconds=time.perf_counter() - t, rows=rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--twin-seed", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0, help="excitation seed")
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--only", nargs="+", choices=PARTS, default=None,
                    help="perturb only these parts of the twin's hidden perturbation")
    ap.add_argument("--contacts", choices=CONTACTS, default="mjx")
    ap.add_argument("--iterations", type=int, default=None,
                    help="solver iterations of the fitting simulator (default: push.xml's 6)")
    ap.add_argument("--loss", choices=LOSSES, default="huber")
    ap.add_argument("--start", choices=("nominal", "truth"), default="nominal")
    ap.add_argument("--staged", action="store_true",
                    help="pusher first on windows clear of the box, then the box from positions")
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)
    if args.episodes < 1 or (args.iterations is not None and args.iterations < 1):
        ap.error("--episodes and --iterations must be >= 1")
    r = run(args)
    report.print_table(
        f"push twin {args.twin_seed} ({'only ' + ', '.join(args.only) if args.only else 'all'}), "
        f"{args.contacts} contacts, {args.loss}, from {args.start}"
        f"{', staged (%d clear windows)' % r['clear_windows'] if args.staged else ''}: "
        f"loss {r['loss_value']:.3g}",
        ["parameter", "truth", "identified", "sd", "rel err", "status"],
        [[x["parameter"], x["truth"], x["identified"], x["sd"], x["rel_err"], x["status"]]
         for x in r["rows"]])
    print(f"wrote {report.write_json(args.out / 'push_sysid.json', r)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
