"""``twinrl eval``: episodes of a policy in sim or on the real twin -- a state policy
(``twinrl.learn.runner.eval_run``) or an arm task's image actor deployed as the SAM-RL loop
deploys it (``twinrl.loop.actor_eval``)."""

from __future__ import annotations

from pathlib import Path

from twinrl.cli.common import UsageError, add_common, at_least_one, check_size


def add_parser(sub) -> None:
    """The ``eval`` sub-command's parser."""
    p = sub.add_parser(
        "eval", help="evaluate a policy checkpoint in sim or in the real twin",
        description="Deterministic episodes of a trained policy; writes summary.json (returns; "
                    "for an arm task's actor also the success rate and its 95%% interval) and a "
                    "video of the first episode (an actor's: the view it saw beside the scene). "
                    "--checkpoint takes a policy, a `twinrl train` run, or a `twinrl run` "
                    "(its last round) or one of its rounds (that round's deployed policy).")
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="a policy checkpoint, a `twinrl train` --out, a `twinrl run` --out or "
                        "its round<r>/ (or round<r>/actor)")
    p.add_argument("--real", action="store_true",
                   help="run on the real twin (a run's actor: that run's twin; else MuJoCo C "
                        "with the hidden perturbation of --seed)")
    p.add_argument("--episodes", type=int, default=5, help="episodes (default 5)")
    p.add_argument("--camera", choices=("chosen", "default", "random"), default=None,
                   help="an arm task's actor: the mount camera's pose -- chosen by the "
                        "sensing-aware Q (default when one is at hand: the round's q/ or --q), "
                        "the fixed default pose, or random per episode")
    p.add_argument("--q", type=Path, default=None,
                   help="the sensing-aware Q for --camera chosen (default: the round's q/)")
    p.add_argument("--no-residual", action="store_true",
                   help="a run's round: leave out the round's accepted residual policy")
    p.add_argument("--no-video", action="store_true", help="skip the video")
    p.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"),
                   help="video size of a state policy (default 320 240); an actor's video is "
                        "its view (3x) beside the scene")
    add_common(p, "runs/eval")
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    """Evaluate ``--checkpoint``."""
    from twinrl import report
    from twinrl.learn.runner import eval_run
    from twinrl.loop.checkpoints import TAKES, arm_run, require, round_of, round_q

    if not args.checkpoint.exists():
        raise UsageError(f"checkpoint {args.checkpoint} does not exist")
    at_least_one(args, "episodes")
    check_size(args.size)
    found = require(args.checkpoint, "eval", TAKES["eval"])
    actor = found.kind == "image_actor" or (found.kind in ("run", "round") and arm_run(found))
    if actor:
        from twinrl.loop.actor_eval import eval_actor

        has_q = args.q is not None or round_q(found) is not None
        camera = args.camera or ("chosen" if has_q else "default")
        eval_actor(found, args.out, real=args.real, episodes=args.episodes, seed=args.seed,
                   camera=camera, q=args.q, residual=not args.no_residual,
                   video=not args.no_video, say=report.console.print)
        return 0
    given = [f for f, on in (("--camera", args.camera), ("--q", args.q),
                             ("--no-residual", args.no_residual and found.kind not in (
                                 "run", "round"))) if on]
    if given:
        raise UsageError(f"{', '.join(given)}: for an arm task's image actor; {found.path} is "
                         f"{found.describe()}")
    checkpoint, policy = found.path, None
    if found.kind in ("run", "round"):  # the cartpole family: the round's deployed policy
        rdir = round_of(found)
        if rdir is None:
            raise UsageError(f"{found.path}: the run has no round with a trained policy yet")
        checkpoint = rdir.train
        policy = _with_residual(rdir) if not args.no_residual else None
    eval_run(checkpoint, args.out, real=args.real, episodes=args.episodes, seed=args.seed,
             video=not args.no_video, size=tuple(args.size), policy=policy,
             residual=policy is not None)
    return 0


def _with_residual(rdir):
    """A cartpole-family round's deployed policy, pi_sim plus its accepted residual, as
    ``(apply, params)``; None where the round has none or its gate rejected it."""
    from twinrl.learn.checkpoint import load_policy
    from twinrl.sim2real.residual import ResidualPolicy

    metrics = rdir.residual_metrics()
    if not (metrics and metrics.get("accepted")):
        return None
    base, base_params, _ = load_policy(rdir.train)
    delta, res_params, _ = load_policy(rdir.residual)
    return ResidualPolicy(base, base_params, delta).act, res_params

