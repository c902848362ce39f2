"""The manipulation loop's sysid, judged by what it is for: does the identified twin move the arm
like the real twin?

Per task and twin seed: record ``--episodes`` episodes of the loop's round-0 excitation (open-loop
``sysid.excitation_actions``, the mount at its default pose) on ``make_real(task, seed=s)``, fit
the loop's parameters (``twinrl.loop.arm.sysid_config``: latency 0-1, the 7 joints' servo
stiffness and damping), then

1. each parameter's relative error against the twin's hidden truth, beside the nominal's
   (evaluation only);
2. the tool point's gap to the real twin, open loop: the scripted expert's actions recorded on the
   unperturbed twin (``--starts`` episodes of 25 steps) replayed from the same start state on the
   real twin and in the simulator with the nominal, the identified and the true parameters. The
   gap after 5, 10 and 25 control steps (cm, mean over starts).

Prints the tables and writes ``OUT/arm_sysid.json``. 3-7 minutes per twin on 2 cores (the fit).
``--estimate-start`` fits every window's start state too (sysid's default; far slower).
``--prior-sd`` sets the parameters' prior (the loop keeps sysid's weak default, 3; a datasheet's
20 % is ``0.2``).

    python bench/arm_sysid.py --out B
    python bench/arm_sysid.py --tasks spatula_flipping --seeds 0 1 2 --out B
    python bench/arm_sysid.py --tasks spatula_flipping --seeds 0 --estimate-start --out B
    python bench/arm_sysid.py --tasks spatula_flipping --seeds 0 1 2 --prior-sd 0.2 --out B
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import twinrl  # noqa: F401  (compilation cache)
from twinrl import envs, report
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)
from twinrl.loop.arm import sysid_config
from twinrl.real import make_real
from twinrl.real.perturbation import Perturbation
from twinrl.real2sim import sysid

TASKS = ("peg_insertion", "spatula_flipping", "needle_threading")
STEPS = (5, 10, 25)


def tool_gaps(name: str, twin, systems: dict, starts: int) -> dict[str, list[float]]:
    """Mean tool-point gap (m) to ``twin`` after each of ``STEPS`` control steps, per system."""
    import jax
    import jax.numpy as jnp

    env = envs.make(name)
    sims = {k: envs.make(name, system=s) for k, s in systems.items()}
    steps = {k: jax.jit(e.step) for k, e in sims.items()}
    tool = lambda q: np.asarray(env.tool_point(jnp.asarray(q, jnp.float32)))
    exact = make_real(name, perturbation=Perturbation.none())
    gaps = {k: [] for k in sims}
    for e in range(starts):
        obs, _ = exact.reset(seed=100 + e)
        start = exact.oracle()  # the true state (evaluation only)
        q0, v0 = start.qpos, start.qvel
        acts = []
        for _ in range(max(STEPS)):
            acts.append(env.scripted_action(obs))
            obs, *_ = exact.step(acts[-1])
        twin.reset(seed=1, options={"qpos": q0, "qvel": v0})
        real = []
        for a in acts:
            twin.step(a)
            real.append(tool(twin.oracle().qpos))  # the true joints (evaluation only)
        real = np.array(real)
        for k, sim in sims.items():
            s = sim.reset(jax.random.PRNGKey(0))
            s = s.replace(pipeline_state=sim.sim.init(jnp.asarray(q0, jnp.float32),
                                                      jnp.asarray(v0, jnp.float32)))
            path = []
            for a in acts:
                s = steps[k](s, jnp.asarray(a))
                path.append(tool(s.pipeline_state.qpos))
            d = np.linalg.norm(np.array(path) - real, axis=1)
            gaps[k].append([float(d[t - 1]) for t in STEPS])
    exact.close()
    return {k: np.mean(v, axis=0).tolist() for k, v in gaps.items()}


def one(name: str, seed: int, episodes: int, starts: int, estimate_start: bool = False,
        prior_sd: float | None = None) -> dict:
    import dataclasses

    from twinrl.envs.system import System

    twin = make_real(name, seed=seed)
    truth = twin.oracle()  # evaluation only
    data = sysid.collect(twin, episodes, seed=3, policy="open_loop")
    t0 = time.perf_counter()
    config = dataclasses.replace(sysid_config(), estimate_start=estimate_start)
    if prior_sd is not None:
        config = dataclasses.replace(config, prior_sd=prior_sd)
    res = sysid.fit(envs.make(name), data, config)
    seconds = time.perf_counter() - t0
    rows = sysid.compare_to_truth(res, truth.params, truth.perturbation.latency_steps)
    nominal = {r["parameter"]: float(r["initial"]) for r in res.table}
    params = {r["parameter"]: {"truth": float(r["truth"]), "identified": float(r["identified"]),
                               "nominal": nominal[r["parameter"]], "rel_err": float(r["rel_err"]),
                               "nominal_rel_err": abs(nominal[r["parameter"]] / float(r["truth"])
                                                      - 1.0)}
              for r in rows if r["parameter"] in nominal}
    lat = truth.perturbation.latency_steps
    systems = {"nominal": System.nominal(name), "identified": res.system,
               "truth": System(params=truth.params, latency=lat, task=name)}
    gaps = tool_gaps(name, twin, systems, starts)
    twin.close()
    return {"task": name, "seed": seed, "estimate_start": estimate_start,
            "prior_sd": config.prior_sd,
            "fit_seconds": seconds, "latency": res.latency,
            "true_latency": lat, "params": params, "tool_gap_m": gaps, "steps": list(STEPS)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="+", choices=TASKS, default=list(TASKS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--episodes", type=int, default=5,
                    help="real excitation episodes (the loop's K)")
    ap.add_argument("--starts", type=int, default=6, help="expert starts replayed open loop")
    ap.add_argument("--estimate-start", action="store_true",
                    help="estimate every window's start state with the parameters (sysid's "
                         "default; the loop starts windows from the recorded joints)")
    ap.add_argument("--prior-sd", type=float, default=None,
                    help="the parameters' prior sd (unconstrained units, about relative; default "
                         "the loop's: sysid's weak 3)")
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)
    if args.prior_sd is not None and not 0 < args.prior_sd < float("inf"):
        ap.error(f"--prior-sd must be a finite number > 0, got {args.prior_sd}")
    runs = []
    for name in args.tasks:
        for seed in args.seeds:
            r = one(name, seed, args.episodes, args.starts, args.estimate_start, args.prior_sd)
            runs.append(r)
            errs = np.array([[p["nominal_rel_err"], p["rel_err"]] for p in r["params"].values()])
            print(f"{name} twin {seed}: fit {r['fit_seconds']:.0f} s, latency {r['latency']} "
                  f"(truth {r['true_latency']}); relative error median nominal "
                  f"{np.median(errs[:, 0]):.3f} -> identified {np.median(errs[:, 1]):.3f}, "
                  f"max {errs[:, 0].max():.3f} -> {errs[:, 1].max():.3f}", flush=True)
    report.print_table(
        "tool-point gap to the real twin, open loop (cm after " + ", ".join(map(str, STEPS))
        + " steps)", ("task", "twin", "nominal", "identified", "truth"),
        [(r["task"], r["seed"], *(" / ".join(f"{100 * x:.2f}" for x in r["tool_gap_m"][k])
                                  for k in ("nominal", "identified", "truth"))) for r in runs])
    print(f"wrote {write_result(args.out / 'arm_sysid.json', {'runs': runs}, args)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
