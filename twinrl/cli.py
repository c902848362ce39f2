"""The ``twinrl`` command.

Each sub-command has ``--help``, ``--seed`` and ``--out DIR``; those that produce results write
``DIR/summary.json`` beside their human outputs and print a table. Bad input (a missing or
malformed MJCF, an unknown scene) gets one clear line on stderr and exit status 2; a check that
runs and fails exits 1.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

__all__ = ["main"]


class UsageError(Exception):
    """Bad input named in one line, no traceback."""


def _common(p: argparse.ArgumentParser, out_default: str) -> None:
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", type=Path, default=Path(out_default),
                   help=f"output directory (default {out_default})")


# ---------------------------------------------------------------------------------- gradcheck
def _gradcheck_parser(sub) -> None:
    p = sub.add_parser(
        "gradcheck", help="check reverse-mode gradients of a rollout against finite differences",
        description="Reverse-mode gradients of a rollout loss w.r.t. actions, initial state and "
                    "every PhysParams field, against central finite differences. Exits 1 if a "
                    "relative error exceeds the tolerance or a gradient is non-finite.")
    p.add_argument("targets", nargs="*", default=["all"], metavar="SCENE|MJCF-PATH",
                   help="bundled scene name, path to your MJCF, or 'all' (default)")
    p.add_argument("--horizon", "-T", type=int, default=None,
                   help="rollout steps (default: 100; 50 for peg_in_hole)")
    p.add_argument("--x64", action="store_true",
                   help="float64 (needed for a meaningful check; float32 differences are noise)")
    p.add_argument("--rtol", type=float, default=None,
                   help="relative tolerance (default 1e-4 with --x64, 2e-2 without)")
    p.add_argument("--iterations", type=int, default=None,
                   help="constraint-solver iterations (default: the MJCF's option)")
    _common(p, "runs/gradcheck")
    p.set_defaults(func=_cmd_gradcheck)


def _cmd_gradcheck(args) -> int:
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from twinrl import report
    from twinrl.physics import SCENES, Sim
    from twinrl.physics.gradcheck import gradcheck

    targets = list(SCENES) if args.targets == ["all"] else args.targets
    if args.horizon is not None and args.horizon < 1:
        raise UsageError(f"--horizon must be >= 1, got {args.horizon}")
    rtol = args.rtol or (1e-4 if args.x64 else 2e-2)
    h = 1e-6 if args.x64 else 1e-3
    sims = [Sim.load(t, iterations=args.iterations) for t in targets]  # fail fast on bad input
    if not args.x64:
        report.console.print("[yellow]float32: finite differences are coarse; use --x64 for the "
                             "real check[/yellow]")
    results = []
    for sim in sims:
        t0 = time.perf_counter()
        with report.console.status(f"{sim.name}: compiling and differencing the rollout..."):
            r = gradcheck(sim, horizon=args.horizon, h=h, rtol=rtol, seed=args.seed)
        secs = time.perf_counter() - t0
        report.print_table(
            f"gradcheck {sim.name}  T={r.horizon}  {r.dtype}  "
            f"(constrained steps {r.constrained_steps}, free {r.free_steps})",
            ["input", "n", "resolved", "noise-lim", "kinks", "max |grad|", "max rel err",
             "max abs err", "fail"],
            [[g["group"], g["entries"], g["resolved"], g["noise_limited"], g["kinks"],
              g["max_abs_grad"], g["max_rel_err"], g["max_abs_err"], g["failures"]]
             for g in r.groups])
        verdict = "[green]PASS[/green]" if r.passed else "[red]FAIL[/red]"
        report.console.print(f"{verdict} {sim.name}: max rel error {r.max_rel_error:.2e} "
                             f"(tol {rtol:g}) over {r.count('resolved')} resolved entries, "
                             f"non-finite {r.nan_count}, failures {len(r.failures)}, "
                             f"{secs:.0f} s\n")
        summ = r.summary() | {"seconds": secs}
        results.append(summ)
        if len(sims) > 1:
            report.write_json(args.out / sim.name / "summary.json", summ)

    if len(results) == 1:
        summary = results[0]
    else:
        summary = {"scenes": [{k: v for k, v in s.items() if k != "rows"} for s in results],
                   "max_rel_error": max(s["max_rel_error"] for s in results),
                   "nan_count": sum(s["nan_count"] for s in results),
                   "passed": all(s["passed"] for s in results),
                   "rows": [dict(row, scene=s["scene"]) for s in results for row in s["rows"]]}
        report.print_table("gradcheck summary", ["scene", "max rel err", "non-finite", "pass"],
                           [[s["scene"], s["max_rel_error"], s["nan_count"],
                             "yes" if s["passed"] else "NO"] for s in results])
    path = report.write_json(args.out / "summary.json", summary)
    report.console.print(f"wrote {path}")
    return 0 if all(s["passed"] for s in results) else 1


# ---------------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twinrl",
        description="Robot learning through differentiable digital twins "
                    "(Real2Sim -> Learn@Sim -> Sim2Real).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _gradcheck_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from twinrl.physics import MJCFError

    try:
        return args.func(args)
    except (UsageError, MJCFError) as e:
        print(f"twinrl {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"twinrl {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
