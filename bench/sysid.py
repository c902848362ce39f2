"""Benchmark: sysid (multiple shooting + Levenberg-Marquardt) against CMA-ES on the real twins.

Per task and seed: record ``--episodes`` episodes of excitation actions on the default real twin
(``twinrl.real.make_real(task, seed=s)``), then

1. **acceptance fit** -- ``sysid.fit`` with the default parameter set, start states estimated,
   latency chosen from 0..1, and the first body's mass *known* (weighed: here read from the twin's
   truth, standing in for a scale). Without a known mass the overall scale of masses, gains,
   damping and friction is a flat direction (trajectories cannot tell a heavy robot with a strong
   motor from a light one with a weak motor); ``sysid`` reports it, and the unanchored fit is
   also run and compared after aligning that one scale (``aligned`` columns).
   Each parameter: truth, identified, sd, relative error, covered (|err| <= 3 sd).
2. **rollouts to the same loss / parameter error** -- sysid and CMA-ES on the *same* objective
   (recorded start states, the latency found in 1., the identifiable parameters, same known mass),
   counting simulated window rollouts (forward, gradient and Jacobian passes all counted):
   rollouts each needs to reach the loss and the worst relative parameter error sysid ends at.

Prints tables (``twinrl.report.print_table``) and writes ``OUT/sysid.json`` (``--out OUT``, default ``bench/results``).
Run: ``.venv/bin/python bench/sysid.py [--tasks cartpole_swingup pendulum_swingup] [--seeds 0 1 2]``
(``--no-cma``: only part 1, the acceptance tables; part 2 costs minutes per seed).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import twinrl  # noqa: F401  (compilation cache)
from twinrl import envs, real, report
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)
from twinrl.real2sim import baselines, sysid
from twinrl.real2sim.sysid.config import parse_param
from twinrl.real2sim.sysid.problem import param_value

RESULTS = Path(__file__).resolve().parent / "results"
# Parameters compared between sysid and CMA-ES (identifiable once the first mass is known).
COMPARE = {
    "cartpole_swingup": ("mass/pole", "damping/slider", "damping/hinge", "frictionloss/slider",
                         "gain/push"),
    "pendulum_swingup": ("damping/hinge", "frictionloss/hinge", "gain/torque"),
}


def max_rel_err(names, values, truth_rows_by_name):
    return float(max(abs(v - truth_rows_by_name[n]) / abs(truth_rows_by_name[n])
                     for n, v in zip(names, values) if truth_rows_by_name[n] != 0))


def first_reaching(history, key, target):
    for h in history:
        if h[key] <= target:
            return int(h["rollouts"])
    return None


def run(task: str, seed: int, episodes: int, cma_evals: int | None) -> dict:
    twin = real.make_real(task, seed=seed)
    data = sysid.collect(twin, episodes=episodes, seed=seed)
    truth = twin.oracle()  # evaluation only
    env = envs.make(task)
    body0 = sysid.param_names(env, ("mass",))[0]
    true_of = lambda name: param_value(truth.params.as_dict(), *parse_param(env, name))  # noqa
    known = ((body0, true_of(body0)),)
    out = {"task": task, "seed": seed, "episodes": episodes,
           "true_latency": truth.perturbation.latency_steps,
           "obs_noise_std": truth.perturbation.obs_noise_std}

    # 1. acceptance fit (anchored) and the unanchored fit
    t = time.perf_counter()
    res = sysid.fit(env, data, sysid.SysidConfig(known=known))
    rows = sysid.compare_to_truth(res, truth.params, truth.perturbation.latency_steps)
    out["anchored"] = dict(rows=rows, loss=res.loss, rollouts=res.sim_rollouts,
                           seconds=time.perf_counter() - t, residual_sd=res.residual_sd,
                           flat=res.flat_directions, loss_by_latency=res.loss_by_latency)
    res_u = sysid.fit(env, data, sysid.SysidConfig())
    rows_u = sysid.compare_to_truth(res_u, truth.params, truth.perturbation.latency_steps)
    out["unanchored"] = dict(rows=rows_u, loss=res_u.loss, rollouts=res_u.sim_rollouts,
                             flat=res_u.flat_directions)

    if cma_evals is None:
        return out
    # 2. same objective for both: recorded starts, the found latency, identifiable parameters
    cfg = sysid.SysidConfig(params=COMPARE[task], known=known, estimate_start=False,
                            latency=res.latency)
    truth_by = {n: true_of(n) for n in COMPARE[task]}
    t = time.perf_counter()
    g = sysid.fit(env, data, cfg)
    g_sec = time.perf_counter() - t
    c = baselines.cmaes_fit(env, data, cfg, baselines.CmaesConfig(max_evals=cma_evals), seed=seed)
    for h in g.history + c.history:
        h["err"] = max_rel_err(COMPARE[task], [v for v in h["values"]][:len(COMPARE[task])],
                               truth_by)
    g_err = max_rel_err(COMPARE[task], g.values[:len(COMPARE[task])], truth_by)
    target_loss = g.loss * (1 + 1e-3)
    cmp = dict(
        sysid_loss=g.loss, sysid_err=g_err, sysid_rollouts=g.sim_rollouts, sysid_seconds=g_sec,
        sysid_rollouts_to_loss=first_reaching(g.history, "loss", target_loss),
        sysid_rollouts_to_err=first_reaching(g.history, "err", g_err * 1.001),
        cma_loss=c.loss, cma_err=max_rel_err(COMPARE[task], c.values[:len(COMPARE[task])],
                                             truth_by),
        cma_rollouts=c.sim_rollouts, cma_seconds=c.seconds,
        cma_rollouts_to_loss=first_reaching(c.history, "loss", target_loss),
        cma_rollouts_to_err=first_reaching(c.history, "err", g_err * 1.001),
        windows=g.n_windows)
    out["compare"] = cmp
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="+", default=["cartpole_swingup", "pendulum_swingup"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--cma-evals", type=int, default=2000)
    ap.add_argument("--no-cma", action="store_true", help="skip part 2 (sysid vs CMA-ES)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    results = []
    for task in args.tasks:
        for seed in args.seeds:
            t = time.perf_counter()
            r = run(task, seed, args.episodes, None if args.no_cma else args.cma_evals)
            r["seconds"] = time.perf_counter() - t
            results.append(r)
            write_result(args.out / "sysid.json", {"results": results}, args)  # after every seed
            rows = [[row["parameter"], row["truth"], row["identified"], row["sd"], row["rel_err"],
                     "yes" if row["covered"] else "NO", row["status"]]
                    for row in r["anchored"]["rows"]]
            report.print_table(f"{task} seed {seed}: sysid, first mass known",
                               ["parameter", "truth", "identified", "sd", "rel err", "covered",
                                "status"], rows)
            rows = [[row["parameter"], row["truth"], row["identified"], row.get("aligned", "-"),
                     row.get("aligned_rel_err", row["rel_err"]),
                     "yes" if row.get("aligned_covered", row["covered"]) else "NO", row["status"]]
                    for row in r["unanchored"]["rows"]]
            report.print_table(f"{task} seed {seed}: sysid, nothing known (scale aligned)",
                               ["parameter", "truth", "identified", "aligned", "rel err",
                                "covered", "status"], rows)
    cols = ["task", "seed", "sysid loss", "sysid err", "sysid rollouts", "to loss", "to err",
            "cma loss", "cma err", "cma rollouts", "to loss", "to err", "ratio (err)"]
    rows = []
    for r in (r for r in results if "compare" in r):
        c = r["compare"]
        ratio = (c["cma_rollouts_to_err"] / c["sysid_rollouts_to_err"]
                 if c["cma_rollouts_to_err"] and c["sysid_rollouts_to_err"] else
                 f"> {c['cma_rollouts'] / max(c['sysid_rollouts_to_err'] or 1, 1):.0f}")
        rows.append([r["task"], r["seed"], c["sysid_loss"], c["sysid_err"], c["sysid_rollouts"],
                     c["sysid_rollouts_to_loss"], c["sysid_rollouts_to_err"], c["cma_loss"],
                     c["cma_err"], c["cma_rollouts"], c["cma_rollouts_to_loss"] or "never",
                     c["cma_rollouts_to_err"] or "never", ratio])
    if rows:
        report.print_table("sysid vs CMA-ES: window rollouts to the same loss / parameter error",
                           cols, rows)
    write_result(args.out / "sysid.json", {"results": results}, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
