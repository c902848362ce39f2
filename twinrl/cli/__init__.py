"""The ``twinrl`` command.

Each sub-command has ``--help``, ``--seed`` and ``--out DIR``; those that produce results write
``DIR/summary.json`` beside their human outputs and print a table. Bad input (a missing or
malformed MJCF, an unknown scene) gets one clear line on stderr and exit status 2; a check that
runs and fails exits 1.

One module per command (``envs``, ``collect``, ``export``, ``render``, ``gradcheck``, ``run``,
``sysid``, ``train``, ``eval``, ``sense``), each with its parser (``add_parser``) and a thin ``cmd(args)``
that checks the arguments, calls the library and prints; ``common`` holds what they share.
"""

from __future__ import annotations

import argparse
import sys

from twinrl.cli import collect, envs, eval, export, gradcheck, render, run, sense, sysid, train
from twinrl.cli.common import UsageError, one_line_warnings
from twinrl.cli.gradcheck import unjudged_line

__all__ = ["main", "build_parser", "UsageError", "unjudged_line", "one_line_warnings"]

COMMANDS = (envs, collect, export, render, gradcheck, run, sysid, train, eval, sense)
"""The command modules, in the order ``twinrl --help`` lists them."""


def build_parser() -> argparse.ArgumentParser:
    """The ``twinrl`` parser with every sub-command's (the CLI reference is generated from it)."""
    parser = argparse.ArgumentParser(
        prog="twinrl",
        description="Robot learning through differentiable digital twins "
                    "(Real2Sim -> Learn@Sim -> Sim2Real).")
    parser.add_argument("--verbose", "-v", action="store_true",
                        help="show the XLA/absl runtime log (warnings and errors, e.g. about "
                             "executables loaded from the compilation cache), hidden by default")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``twinrl ARGV`` (default ``sys.argv[1:]``); returns the exit status: 0, 1 for a check
    that ran and failed, 2 for bad input (one line on stderr), 130 when interrupted."""
    args = build_parser().parse_args(argv)
    from twinrl.learn.distributed import DistributedError

    try:  # a command's setup that must come before any JAX backend starts (jax.distributed)
        if getattr(args, "before_jax", None) is not None:
            args.before_jax(args)
    except UsageError as e:
        print(f"twinrl {args.command}: error: {e}", file=sys.stderr)
        return 2
    except DistributedError as e:
        print(f"twinrl {args.command}: error: {e}", file=sys.stderr)
        return 1
    from twinrl import jaxconfig
    from twinrl.learn.checkpoint import CheckpointError
    from twinrl.learn.imitation import DemonstrationError
    from twinrl.learn.runner import RunError
    from twinrl.learn.sensing import SensingError
    from twinrl.physics import MJCFError, PhysParamsError
    from twinrl.real.dataset import DatasetError

    if args.verbose:
        jaxconfig.set_verbose()
    one_line_warnings(f"twinrl {args.command}")
    try:
        return args.func(args)
    except (UsageError, MJCFError, PhysParamsError, DatasetError, FileNotFoundError, RunError,
            CheckpointError, DemonstrationError, SensingError) as e:
        print(f"twinrl {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"twinrl {args.command}: interrupted", file=sys.stderr)
        return 130
