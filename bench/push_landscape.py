"""Push identification's objective, looked at: the box's loss along a scan of one parameter
around the hidden truth, and the gradient the Jacobian gives there.

``bench/push_sysid.py`` fits box mass and friction on twins whose data pin their product; even on
noise-free data with every other parameter at its truth the fits stop percents off. This tells why:
it builds the box's objective of ``push_sysid``'s second stage (planar positions, pusher values
known) on a twin's recorded episodes, with every parameter but ``--param`` at the twin's truth
(evaluation only), and evaluates, at ``--points`` values of ``--param`` spread over +-``--span``
(log) around its truth, the mean loss per residual and its derivative from the Jacobian LM uses
(``J^T r / n`` of the loss ``sum r^2 / 2n``, recorded start states). A smooth objective has a
parabola there and a slope whose descent heads for the truth from either side; a rough one has a
cusp at the truth and slopes that send descent away from it. Beside each slope, the loss's central
difference (``--fd-step``): where the two agree the simulator's gradient is right and the function
itself is rough; where they do not, the gradient is wrong. ``--noise`` keeps the twin's observation
noise (default off: the objective's own shape).

Prints a table and writes ``OUT/push_landscape.json``. ~1-2 min on 2 cores.

    python bench/push_landscape.py --twin-seed 2 --out B
    python bench/push_landscape.py --twin-seed 2 --param mass/box --window 20 --out B
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: compilation cache, quiet console)
import jax
import numpy as np

from twinrl import envs, real, report
from twinrl.real.perturbation import Perturbation
from twinrl.real2sim import sysid
from twinrl.real2sim.sysid.config import parse_param
from twinrl.real2sim.sysid.problem import build_problem, param_value

sys.path.insert(0, str(Path(__file__).resolve().parent))
import push_sysid  # noqa: E402  (its weights, truth and floor rule)

BOX = ("mass/box", "friction/box", "friction/pusher")
PUSHER = ("mass/pusher", "gain/fx", "gain/fy", "damping/px", "damping/py")


def run(args) -> dict:
    config = {"observation": "state"}
    hidden = real.make_real("push", seed=args.twin_seed, config=config).oracle().perturbation
    pert = hidden if args.noise else dataclasses.replace(hidden, obs_noise_std=0.0)
    twin = real.make_real("push", seed=args.twin_seed, perturbation=pert, config=config)
    truth = twin.oracle()  # evaluation only
    data = sysid.collect(twin, episodes=args.episodes, seed=args.seed)
    env = envs.make("push", contacts=args.contacts, solver_iterations=args.iterations, **config)
    ct = push_sysid.box_contact_truth(env, truth.params).as_dict()
    value = {n: float(param_value(ct, *parse_param(env, n))) for n in BOX + PUSHER}
    known = tuple((n, v) for n, v in value.items() if n != args.param)
    known += (("friction/floor", push_sysid.FLOOR_FRICTION),)
    cfg = sysid.SysidConfig(params=(args.param,), known=known, loss="l2",
                            observation_weights=push_sysid.POSITION_WEIGHTS,
                            latency=pert.latency_steps, window=args.window)
    rows = []
    with jax.enable_x64(True):
        prob = build_problem(env, data, cfg)
        j = prob.names.index(args.param)
        k = args.points // 2  # the truth's row is exactly 0: linspace's middle can miss it
        for d in args.span * np.arange(-k, k + 1) / k:
            theta = prob.theta0.copy()
            theta[j] = np.log(value[args.param]) + d
            r, J = prob.jacobian(theta, pert.latency_steps)
            side = []
            for h in (args.fd_step, -args.fd_step):
                th = theta.copy()
                th[j] += h
                rh = prob.residuals(th, pert.latency_steps)
                side.append(prob.data_loss(rh) / rh.size)
            rows.append(dict(dlog=float(d), value=float(np.exp(theta[j])),
                             loss=prob.data_loss(r) / r.size,
                             grad=float(np.sum(r * J[..., j]) / r.size),
                             fd=float((side[0] - side[1]) / (2.0 * args.fd_step))))
    for row in rows:  # does descent along the Jacobian's slope head for the truth?
        row["toward"] = None if row["dlog"] == 0.0 else bool(
            np.sign(row["grad"]) == np.sign(row["dlog"]))
    return dict(twin_seed=args.twin_seed, param=args.param, truth=value[args.param],
                window=args.window, noise=bool(args.noise), obs_noise_std=pert.obs_noise_std,
                episodes=args.episodes, windows=prob.n_windows, rows=rows,
                away=sum(r["toward"] is False for r in rows),
                truth_lowest=bool(min(rows, key=lambda r: r["loss"])["dlog"] == 0.0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--twin-seed", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0, help="excitation seed")
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--param", choices=BOX, default="friction/box")
    ap.add_argument("--span", type=float, default=0.04, help="half-width of the scan (log)")
    ap.add_argument("--points", type=int, default=17, help="odd: the truth is the middle one")
    ap.add_argument("--window", type=int, default=5)
    ap.add_argument("--fd-step", type=float, default=1e-6,
                    help="log step of the loss's central difference beside the Jacobian's slope")
    ap.add_argument("--noise", action="store_true", help="keep the twin's observation noise")
    ap.add_argument("--contacts", default="mujoco")
    ap.add_argument("--iterations", type=int, default=12)
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)
    if (args.episodes < 1 or args.points < 3 or args.points % 2 == 0 or args.window < 1
            or not args.span > 0 or not args.fd_step > 0):
        ap.error("--episodes and --window must be >= 1, --points odd and >= 3 (the truth in "
                 "the middle), --span and --fd-step > 0")
    t = time.perf_counter()
    r = run(args)
    r["seconds"] = time.perf_counter() - t
    report.print_table(
        f"push twin {args.twin_seed}, {args.param} around its truth {r['truth']:.4g} "
        f"({'noisy' if args.noise else 'noise-free'}, window {args.window}, "
        f"{r['windows']} windows): descent heads away from the truth at {r['away']} of "
        f"{len(r['rows']) - 1} points; the truth's loss is {'' if r['truth_lowest'] else 'not '}"
        f"the scan's lowest",
        ["dlog", "value", "loss / residual", "J'r slope", "central diff.", "descent toward truth"],
        [[x["dlog"], x["value"], x["loss"], x["grad"], x["fd"], x["toward"]] for x in r["rows"]])
    print(f"wrote {report.write_json(args.out / 'push_landscape.json', r)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
