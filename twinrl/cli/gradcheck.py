"""``twinrl gradcheck``: reverse-mode gradients of a rollout against finite differences
(``twinrl.physics.gradcheck``) on bundled scenes, tasks' scenes (``twinrl.envs.gradcheck``) or
your MJCF, a table per scene and ``OUT/summary.json``."""

from __future__ import annotations

import time

from twinrl.cli.common import ProgressLines, UsageError, add_common, at_least_one


def add_parser(sub) -> None:
    """The ``gradcheck`` sub-command's parser."""
    p = sub.add_parser(
        "gradcheck", help="check reverse-mode gradients of a rollout against finite differences",
        description="Reverse-mode gradients of a rollout loss w.r.t. actions, initial state and "
                    "every PhysParams field, against central finite differences. Exits 1 if a "
                    "relative error exceeds the tolerance or a gradient is non-finite.")
    p.add_argument("targets", nargs="*", default=["all"], metavar="SCENE|TASK|MJCF-PATH",
                   help="bundled scene name, a manipulation task's name (peg_insertion, "
                        "spatula_flipping, needle_threading: its scene through the scripted "
                        "expert's tool-object contacts), path to your MJCF, or 'all' (default: "
                        "the bundled scenes)")
    p.add_argument("--horizon", "-T", type=int, default=None,
                   help="rollout steps (default: 100; 50 for peg_in_hole)")
    p.add_argument("--x64", action="store_true",
                   help="float64 (needed for a meaningful check; float32 differences are noise)")
    p.add_argument("--rtol", type=float, default=None,
                   help="relative tolerance (default 1e-4 with --x64, 2e-2 without)")
    p.add_argument("--iterations", type=int, default=None,
                   help="constraint-solver iterations (default: the MJCF's option)")
    p.add_argument("--scenario", default=None, metavar="NAME",
                   help="initial state and actions: 'wave' (smooth random actions from the "
                        "model's qpos0 at rest; the default for your MJCF), 'zero' (no actuation: "
                        "a dropped object), or a bundled scene's name for its own scenario "
                        "(cartpole, pendulum, push, peg_in_hole; the default for that scene)")
    p.add_argument("--tolerance", type=float, default=None,
                   help="constraint-solver tolerance during the check (default 1e-12 with --x64 "
                        "so differences see the solution, not the stopping rule; else the MJCF's)")
    p.add_argument("--gradient", default="implicit", choices=("implicit", "unrolled"),
                   help="derivative of the constraint solve: of its converged solution (implicit "
                        "function theorem, default) or of its fixed iterations")
    p.add_argument("--contacts", default="mjx", choices=("mjx", "mujoco"),
                   help="collision rules: stock MJX's (default) or MuJoCo C's box on a plane "
                        "(every lower corner touches; MJX keeps those within 1 mm of the deepest)")
    p.add_argument("--max-geom-pairs", type=int, default=None, metavar="K",
                   help="keep, of each collision function's geom pairs (planes and height "
                        "fields excepted), the K nearest by bounding sphere (MJX's own "
                        "max_geom_pairs; MJX has no broad phase and otherwise evaluates every "
                        "candidate pair every step); default: the MJCF's <numeric>, else all")
    p.add_argument("--max-contact-points", type=int, default=None, metavar="P",
                   help="keep the P deepest contacts of each contact dimension (MJX's own "
                        "max_contact_points); default: the MJCF's <numeric>, else all")
    p.add_argument("--settle", type=int, default=0, metavar="N",
                   help="run N physics steps (MuJoCo C, no actuation) before the check, so it "
                        "starts where the model has come to rest, e.g. a walker on the ground")
    p.add_argument("--strict", action="store_true",
                   help="also exit 1 when an input group has no resolved entry (nothing judged "
                        "through it) and is not inert")
    p.add_argument("--step", type=float, default=None, metavar="H",
                   help="finite-difference step, relative to max(1, |x|) (default 1e-6 with "
                        "--x64, else 1e-3); a larger one resolves smaller gradients (rounding "
                        "noise ~ eps |L| / H) at the risk of more kinks in the window")
    p.add_argument("--entries", type=int, default=None, metavar="K",
                   help="difference at most K entries per input group (a seeded random subset; "
                        "each costs 4 rollouts): a large model's check at a fraction of the cost")
    add_common(p, "runs/gradcheck")
    p.set_defaults(func=cmd)


def unjudged_line(r) -> str:
    """The line naming a gradcheck's unjudged groups, and why where the forward's own roughness
    explains it (``GradcheckResult.unjudged_by_roughness``)."""
    from twinrl.physics.gradcheck import JITTER

    why = (f"; moving every input by {JITTER:g} of itself moved the loss by "
           f"{r.loss_jitter:.1e} beyond its gradient, so differences at --step {r.step:g} "
           f"resolve no derivative below ~{r.resolution_floor:.1e} (a body resting flat, a "
           f"contact that switches on rounding: a scenario that moves it, or a larger --step)"
           if r.unjudged_by_roughness else "")
    return f"not judged (no resolved entry): {', '.join(r.unjudged)}{why}"


def cmd(args) -> int:
    """Check every target; exit 1 when one fails."""
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from twinrl import report
    from twinrl.envs.gradcheck import load_target
    from twinrl.physics import SCENES
    from twinrl.physics.gradcheck import combine_summaries, gradcheck

    targets = list(SCENES) if args.targets == ["all"] else args.targets
    at_least_one(args, "horizon", "iterations", "entries")
    rtol = args.rtol if args.rtol is not None else (1e-4 if args.x64 else 2e-2)
    if not rtol > 0:
        raise UsageError(f"--rtol must be > 0, got {args.rtol}")
    tolerance = args.tolerance if args.tolerance is not None else (1e-12 if args.x64 else None)
    if tolerance is not None and not tolerance >= 0:
        raise UsageError(f"--tolerance must be >= 0, got {args.tolerance}")
    h = args.step if args.step is not None else (1e-6 if args.x64 else 1e-3)
    if not h > 0:
        raise UsageError(f"--step must be > 0, got {args.step}")
    # fail fast on bad input: every target loads before the first check runs
    at_least_one(args, "max_geom_pairs", "max_contact_points")
    loaded = [load_target(t, horizon=args.horizon, seed=args.seed,
                          scenario=args.scenario is None, iterations=args.iterations,
                          gradient=args.gradient, contacts=args.contacts,
                          max_geom_pairs=args.max_geom_pairs,
                          max_contact_points=args.max_contact_points) for t in targets]
    if not args.x64:
        report.console.print("[yellow]float32: finite differences are coarse; use --x64 for the "
                             "real check[/yellow]")
    results = []
    for sim, scenario in loaded:
        t0 = time.perf_counter()
        progress = ProgressLines(sim.name)
        try:
            r = gradcheck(sim, horizon=args.horizon, h=h, rtol=rtol, seed=args.seed,
                          scenario=args.scenario if scenario is None else scenario,
                          tolerance=tolerance, settle=args.settle, entries=args.entries,
                          progress=progress)
        except ValueError as e:
            raise UsageError(f"{sim.name}: {e}") from None
        finally:
            progress.close()
        secs = time.perf_counter() - t0
        _print_result(r, sim.name, rtol, secs, args.strict)
        summ = r.summary() | {"seconds": secs, "passed": r.passed_strict if args.strict
                              else r.passed}
        results.append(summ)
        if len(loaded) > 1:
            report.write_json(args.out / sim.name / "summary.json", summ)

    if len(results) == 1:
        summary = results[0]
    else:
        summary = combine_summaries(results)
        report.print_table("gradcheck summary", ["scene", "max rel err", "non-finite", "pass"],
                           [[s["scene"], s["max_rel_error"], s["nan_count"],
                             "yes" if s["passed"] else "NO"] for s in results])
    path = report.write_json(args.out / "summary.json", summary)
    report.console.print(f"wrote {path}")
    return 0 if all(s["passed"] for s in results) else 1


def _print_result(r, name: str, rtol: float, secs: float, strict: bool) -> None:
    """One scene's table of input groups, its verdict line and its unjudged groups."""
    from twinrl import report

    report.print_table(
        f"gradcheck {name}  T={r.horizon}  {r.dtype}  scenario {r.scenario}  "
        f"(constrained steps {r.constrained_steps}, free {r.free_steps})",
        ["input", "n", "resolved", "noise-lim", "kinks", "max |grad|", "max rel err",
         "max abs err", "fail", "judged"],
        [[g["group"], g["entries"] if g["entries"] == g["entries_total"]
          else f'{g["entries"]} of {g["entries_total"]}', g["resolved"],
          g["noise_limited"], g["kinks"],
          g["max_abs_grad"], g["max_rel_err"], g["max_abs_err"], g["failures"],
          "yes" if g["resolved"] else ("inert" if g["inert"] else "NO")]
         for g in r.groups])
    ok = r.passed_strict if strict else r.passed
    verdict = "[green]PASS[/green]" if ok else "[red]FAIL[/red]"
    report.console.print(f"{verdict} {name}: max rel error {r.max_rel_error:.2e} "
                         f"(tol {rtol:g}) over {r.count('resolved')} resolved entries, "
                         f"non-finite {r.nan_count}, failures {len(r.failures)}, "
                         f"{secs:.0f} s")
    if r.count("outside"):
        names = ", ".join(f'{x["group"]}[{x["index"]}]' for x in r.rows
                          if x["status"] == "outside")
        report.console.print(f"[yellow]not judged (differences leave the model's valid range "
                             f"even at a 10^10 times smaller step): {names}[/yellow]")
    if r.unjudged:
        report.console.print(f"[yellow]{unjudged_line(r)}[/yellow]"
                             + ("" if strict else " (--strict fails on this)"))
    report.console.print("")
