"""``twinrl run``: the whole loop on a registered task's real twin, the cartpole family's
(``twinrl.loop.cartpole``) or, on a manipulation task, the SAM-RL loop (``twinrl.loop.arm``).

Every import of the loops is in ``_loops`` below."""

from __future__ import annotations

from twinrl.cli.common import UsageError, add_common, check_task
from twinrl.cli.train import add_distributed, join

MJCF_RUN_HINT = ("the loop is for the registered tasks: identify your MJCF with `twinrl sysid "
                 "--env PATH --from LOG.npz`, learn in it with `twinrl train --env PATH "
                 "--reward FILE.py:FUNCTION`")


def add_parser(sub) -> None:
    """The ``run`` sub-command's parser."""
    p = sub.add_parser(
        "run", help="the whole loop: Real2Sim -> Learn@Sim -> Sim2Real on a task's real twin",
        description="Round 0 records exciting episodes on the real twin; each round then "
                    "identifies the simulator (sysid), refits the hybrid dynamics, learns in sim "
                    "(--algo), and deploys with residual adaptation, recording the real episodes. "
                    "Writes summary.json, report.md, returns.png, params.png and final.mp4; "
                    "--resume continues a killed run without losing recorded data. On a "
                    "manipulation task (peg_insertion, needle_threading, spatula_flipping) it "
                    "runs the SAM-RL loop instead: round 0 records episodes with images; each "
                    "round calibrates the camera mount from them, plans demonstrations in the "
                    "identified twin, clones an image actor, learns the sensing-aware Q and "
                    "deploys with the camera Q chooses (summary.json, success.png, final.mp4).")
    p.add_argument("--env", default="cartpole_swingup",
                   help="task name (default cartpole_swingup)")
    p.add_argument("--rounds", type=int, default=None, help="rounds after round 0 (default 1)")
    p.add_argument("--episodes-per-round", type=int, default=None,
                   help="real episodes recorded per round (default 2)")
    p.add_argument("--algo", default=None,
                   help="learner in sim (default ppo; shac and hds learn through the "
                        "simulator's gradients, hds mixes in the hybrid model)")
    p.add_argument("--epochs", type=int, default=None,
                   help="training epochs per round (default: tuned per task)")
    p.add_argument("--compare", default=None, metavar="ALGO",
                   help="also train ALGO (e.g. ppo) on each round's identified simulator, for "
                        "the report's learning wall clock beside the deployed learner's; never "
                        "deployed (costs its training time)")
    p.add_argument("--no-oracle", action="store_true",
                   help="skip the oracle policy (evaluation only; saves a training run)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="manipulation tasks: a setting of the SAM-RL loop (twinrl.loop.arm."
                        "ArmLoopConfig), repeatable, e.g. --set demonstrations=16 --set "
                        "imitation.fit_steps=1000 --set camera=default")
    p.add_argument("--resume", action="store_true", help="continue a killed run in --out")
    add_distributed(p, "Process 0 runs the loop (the real twin, every file); the others follow "
                       "it and learn with it (the learning stages are data-parallel over every "
                       "process's devices). Start the same command once per process, with the "
                       "same --out on a shared file system.")
    add_common(p, "runs/loop")
    p.set_defaults(func=cmd, before_jax=join)


def _loops():
    """``(twinrl.loop, twinrl.loop.arm)``: the loops this command runs (every import of them is
    here; imported when the command runs, not when the parser is built)."""
    from twinrl import loop
    from twinrl.loop import arm as loop_arm

    return loop, loop_arm


def cmd(args) -> int:
    """Run the loop for ``--env``: the SAM-RL loop on a manipulation task, else the cartpole
    family's (on several processes: each process's part, ``twinrl.loop.engine``)."""
    from twinrl.learn import distributed

    with distributed.guard(f"twinrl {args.command}"):  # a lost peer: one line, exit 1
        return _run(args)


def _run(args) -> int:
    loop, loop_arm = _loops()
    check_task(args.env, MJCF_RUN_HINT)
    if loop_arm.is_arm_task(args.env):
        return _run_arm(args)
    if args.set:
        raise UsageError("--set configures the manipulation loop (peg_insertion, "
                         "needle_threading, spatula_flipping); use --rounds, --algo, ... here")
    overrides = {k: v for k, v in (("rounds", args.rounds),
                                   ("episodes_per_round", args.episodes_per_round),
                                   ("algo", args.algo), ("epochs", args.epochs),
                                   ("compare", args.compare)) if v is not None}
    if args.no_oracle:
        overrides["oracle"] = False
    try:
        config = loop.LoopConfig(**overrides)
        loop.run(args.env, args.out, config, seed=args.seed, resume=args.resume)
    except loop.LoopError as e:
        raise UsageError(str(e)) from None
    return 0


def _run_arm(args) -> int:
    """``twinrl run`` on a manipulation task: the SAM-RL loop."""
    from twinrl.learn.runner import RunError, parse_overrides

    loop, loop_arm = _loops()
    for flag, value in (("--algo", args.algo), ("--epochs", args.epochs),
                        ("--compare", args.compare)):
        if value is not None:
            raise UsageError(f"{flag} is the state-based loop's; the manipulation loop learns an "
                             f"image actor by imitation (see --set imitation.FIELD=VALUE)")
    try:
        overrides = parse_overrides(args.set)
        for k, v in (("rounds", args.rounds), ("episodes_per_round", args.episodes_per_round)):
            if v is not None:
                overrides[k] = v
        if args.no_oracle:
            overrides["eval_episodes"] = 0
        config = loop_arm.make_config(overrides)
        loop_arm.run(args.env, args.out, config, seed=args.seed, resume=args.resume)
    except (loop.LoopError, RunError) as e:
        raise UsageError(str(e)) from None
    return 0
