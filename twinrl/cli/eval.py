"""``twinrl eval``: deterministic episodes of a policy checkpoint in sim or on the real twin
(``twinrl.learn.runner.eval_run``)."""

from __future__ import annotations

from pathlib import Path

from twinrl.cli.common import UsageError, add_common, at_least_one, check_size


def add_parser(sub) -> None:
    """The ``eval`` sub-command's parser."""
    p = sub.add_parser("eval", help="evaluate a policy checkpoint in sim or in the real twin",
                       description="Deterministic episodes of a trained policy; writes "
                                   "summary.json (returns) and a video of the first episode.")
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="a policy checkpoint (or the --out of `twinrl train`)")
    p.add_argument("--real", action="store_true",
                   help="run on the task's real twin (MuJoCo C, hidden perturbation for --seed)")
    p.add_argument("--episodes", type=int, default=5, help="episodes (default 5)")
    p.add_argument("--no-video", action="store_true", help="skip the video")
    p.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"),
                   help="video size (default 320 240)")
    add_common(p, "runs/eval")
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    """Evaluate ``--checkpoint``."""
    from twinrl.learn.runner import eval_run

    if not args.checkpoint.exists():
        raise UsageError(f"checkpoint {args.checkpoint} does not exist")
    at_least_one(args, "episodes")
    check_size(args.size)
    eval_run(args.checkpoint, args.out, real=args.real, episodes=args.episodes, seed=args.seed,
             video=not args.no_video, size=tuple(args.size))
    return 0
