"""``twinrl train``: learn a policy in the simulator (``twinrl.learn.runner.train_run``), on a
registered task or on your MJCF with your reward (``twinrl.envs.mjcf``)."""

from __future__ import annotations

import math
from pathlib import Path

from twinrl.cli.common import UsageError, add_common, at_least_one, check_task


def add_parser(sub) -> None:
    """The ``train`` sub-command's parser."""
    from twinrl.learn.runner import ALGORITHMS

    p = sub.add_parser(
        "train", help="learn a policy in the simulator (PODS, HDS, SHAC; Brax PPO/APG baselines)",
        description="Train a policy in the differentiable simulator. Writes metrics.csv, "
                    "TensorBoard events (tb/), curve.png, the policy checkpoint (policy/: orbax "
                    "params + checkpoint.json) and summary.json; the training state is saved "
                    "every epoch so --resume continues a killed run to the same result.")
    p.add_argument("--env", required=True,
                   help="task name (see `twinrl envs`), or your MJCF file with --reward")
    p.add_argument("--algo", required=True, choices=list(ALGORITHMS),
                   help="pods, pods2 (second order), hds, shac, imitation (an actor from "
                        "trajopt demonstrations), sensing (the camera-scoring Q of an image "
                        "actor), or the baselines ppo, apg")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--epochs", type=int, default=None,
                        help="epochs (pods/pods2/hds/shac; default: the tuned value)")
    length.add_argument("--steps", type=int, default=None,
                        help="environment steps (ppo/apg; default: the tuned value)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="override a config field (JSON value; dotted for nested fields), "
                        "repeatable, e.g. --set lr=3e-4 --set trajopt.order=2")
    p.add_argument("--resume", action="store_true",
                   help="continue the killed run in --out from its last saved epoch")
    mjcf = p.add_argument_group("your MJCF (--env FILE.xml; envs.from_mjcf)")
    mjcf.add_argument("--reward", metavar="FILE.py:FUNCTION",
                      help="the reward: a function (qpos, qvel, action) -> scalar or dict of "
                           "terms, in jax.numpy (or module:FUNCTION)")
    mjcf.add_argument("--reset-noise", type=float, default=0.0,
                      help="uniform +- noise on every qpos and qvel entry at reset (default 0)")
    mjcf.add_argument("--episode-length", type=int, default=None,
                      help="control steps per episode (default 1000)")
    mjcf.add_argument("--frame-skip", type=int, default=None,
                      help="physics steps per control step (default 1)")
    add_distributed(p)
    add_common(p, "runs/train")
    p.set_defaults(func=cmd, before_jax=join)


TRAIN_PROCESSES = ("Start the same command once per process, with the same --out on a shared "
                   "file system: the batch is split over every process's devices and process 0 "
                   "alone writes.")


def add_distributed(p, what: str = TRAIN_PROCESSES) -> None:
    """The flags that join several processes (``--coordinator``, ``--num-processes``,
    ``--process-id``, ``--peer-timeout``; ``join`` reads them), in a group whose description
    starts with ``what``: ``twinrl train``'s and ``twinrl run``'s."""
    dist = p.add_argument_group(
        "several processes (jax.distributed; docs: Scaling out)",
        f"{what} Under SLURM (srun, several tasks) or Open MPI (mpirun) the three settings come "
        f"from the environment.")
    dist.add_argument("--coordinator", metavar="HOST:PORT",
                      help="address of process 0, where the others join (any free port)")
    dist.add_argument("--num-processes", type=int, metavar="N", help="processes in the run")
    dist.add_argument("--process-id", type=int, metavar="I", help="this process, 0 .. N-1")
    dist.add_argument("--peer-timeout", type=int, default=120, metavar="S",
                      help="seconds to wait for every process to join, and after which a "
                           "process that stopped answering is declared dead, ending the others "
                           "with an error (default 120)")


def join(args) -> None:
    """Join JAX's multi-process runtime when the flags or the environment (SLURM, Open MPI) ask
    for it; ``twinrl`` calls it before anything starts a JAX backend."""
    from twinrl.learn import distributed

    given = [args.coordinator, args.num_processes, args.process_id]
    if None in given and any(x is not None for x in given) and not distributed.requested():
        raise UsageError("--coordinator, --num-processes and --process-id go together (outside "
                         "a SLURM or Open MPI launch, which sets them)")
    if args.peer_timeout < 1:
        raise UsageError(f"--peer-timeout must be >= 1 s, got {args.peer_timeout}")
    distributed.initialize(args.coordinator, args.num_processes, args.process_id,
                           timeout_s=args.peer_timeout, heartbeat_s=args.peer_timeout)


def _mjcf_task(args):
    """``twinrl train --env FILE.xml --reward ...``'s task and its spec (``envs.mjcf``), or
    (None, None) for a registered task name (where the MJCF options are refused)."""
    from twinrl import envs
    from twinrl.envs.mjcf import load_reward, task_spec

    own = ("reward", "episode_length", "frame_skip")
    if not str(args.env).lower().endswith(".xml"):
        given = [f"--{k.replace('_', '-')}" for k in own if getattr(args, k) is not None]
        if args.reset_noise:
            given.append("--reset-noise")
        if given:
            raise UsageError(f"{', '.join(given)}: for your MJCF (--env FILE.xml); task "
                             f"{args.env!r} has its own")
        return None, None
    if not Path(args.env).is_file():
        raise UsageError(f"--env {args.env}: no such MJCF file")
    if args.reward is None:
        raise UsageError(f"--env {args.env}: an MJCF has no reward; give --reward "
                         f"FILE.py:FUNCTION (a function (qpos, qvel, action) -> reward)")
    at_least_one(args, "episode_length", "frame_skip")
    if not (args.reset_noise >= 0 and math.isfinite(args.reset_noise)):
        raise UsageError(f"--reset-noise must be a finite value >= 0, got {args.reset_noise}")
    config = {k: getattr(args, k) for k in ("episode_length", "frame_skip")
              if getattr(args, k) is not None}
    try:
        env = envs.from_mjcf(args.env, reward=load_reward(args.reward),
                             reset_noise=args.reset_noise, **config)
    except (ValueError, TypeError) as e:
        raise UsageError(str(e).splitlines()[0]) from None
    return env, task_spec(env, args.reward)


def cmd(args) -> int:
    """Train ``--algo`` on ``--env``."""
    from twinrl import report
    from twinrl.learn import distributed
    from twinrl.learn.runner import parse_overrides, train_run

    with distributed.guard(f"twinrl {args.command}"):  # a lost peer: one line, exit 1
        s = _train(args, train_run, parse_overrides)
    if distributed.is_writer():
        f = s["final"]
        report.print_table(f"trained {args.algo} on {args.env}",
                           ["epochs", "env steps", "final return", "best return", "wall s"],
                           [[s["epochs"], f.get("env_steps"), f.get("return"), s["best_return"],
                             f.get("wall_s")]])
    return 0


def _train(args, train_run, parse_overrides) -> dict:
    env, spec = _mjcf_task(args)
    if env is None:
        check_task(args.env)
    at_least_one(args, "epochs", "steps")
    s = train_run(env.name if env is not None else args.env, args.algo, args.out,
                  seed=args.seed, epochs=args.epochs, steps=args.steps,
                  overrides=parse_overrides(args.set), resume=args.resume, env=env,
                  env_spec=spec)
    return s
