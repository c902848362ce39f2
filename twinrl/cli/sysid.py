"""``twinrl sysid``: Real2Sim from recorded data (``twinrl.real2sim.sysid``): a task's
simulator from a ``twinrl collect`` dataset (``--visual``: its camera and object from the
images, ``twinrl.real2sim.visual``), or your MJCF from a qpos/qvel/ctrl log, written back as
``OUT/identified.xml``."""

from __future__ import annotations

import sys
from pathlib import Path

from twinrl.cli.common import (ProgressLines, UsageError, add_common, at_least_one, check_task,
                               is_mjcf)
from twinrl.cli.export import add_minari_root


def add_parser(sub) -> None:
    """The ``sysid`` sub-command's parser."""
    p = sub.add_parser(
        "sysid", help="Real2Sim: identify the simulator from a recorded dataset",
        description="From transitions recorded by `twinrl collect`, fit PhysParams and the action "
                    "latency by multiple shooting through the simulator (report table with "
                    "uncertainty and identifiability); with --visual, fit the camera and the "
                    "task's object to the recorded RGB-D + segmentation frames instead. With "
                    "--env ROBOT.xml, fit your own MJCF to your qpos/qvel/ctrl log (.npz) and "
                    "write OUT/identified.xml.")
    p.add_argument("--env", required=True,
                   help="task name (see `twinrl envs`), or the path of your robot's MJCF "
                        "(`twinrl.envs.from_mjcf`: its full state observed; --from then takes "
                        "an .npz log)")
    p.add_argument("--from", dest="source", required=True, type=Path,
                   help="dataset directory (`twinrl collect --out DIR` writes DIR/dataset), or "
                        "minari:NAME, a Minari dataset (`twinrl export` writes one; anyone "
                        "else's whose spaces fit --env; see --minari-root); with "
                        "an MJCF, an .npz with qpos (E, T+1, nq), qvel (E, T+1, nv) and the "
                        "controls sent between them ctrl (E, T, nu), in the actuators' units, "
                        "sampled every --frame-skip physics steps")
    p.add_argument("--param", action="append", default=[], metavar="NAME",
                   help="a parameter to fit, repeatable (default: every mass, damping, friction "
                        "loss and gain), e.g. --param mass/upper; an unknown name lists them")
    p.add_argument("--max-latency", type=int, default=None,
                   help="largest action latency tried, in samples (default: SysidConfig's, 1)")
    p.add_argument("--frame-skip", type=int, default=None,
                   help="with an MJCF: physics steps of its timestep per logged sample "
                        "(default 1)")
    p.add_argument("--visual", action="store_true",
                   help="visual Real2Sim from the dataset's images (needs `collect --images`)")
    p.add_argument("--known", action="append", default=[], metavar="PARAM=VALUE",
                   help="a parameter known from elsewhere, e.g. --known mass/cart=1.05 (fixes the "
                        "common scale that trajectories cannot)")
    p.add_argument("--window", type=int, default=None,
                   help="shooting window, steps (default: SysidConfig's, 20)")
    p.add_argument("--frames", type=int, default=12,
                   help="frames used with --visual, evenly spread over the dataset (default 12: the "
                        "camera's yaw and sideways position are fixed only by where the moving "
                        "objects appear, so they need views of them in many places)")
    p.add_argument("--twin-seed", type=int, default=None,
                   help="evaluation only, with --visual: the seed of the real twin the dataset "
                        "was recorded on (`collect --seed`); adds the errors against its hidden "
                        "camera and object to summary.json")
    add_minari_root(p)
    add_common(p, "runs/sysid")
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    """Identify ``--env`` from ``--from``: a task from its dataset, an MJCF from its log."""
    from twinrl import envs

    if is_mjcf(args.env):
        return _sysid_mjcf(args)
    check_task(args.env)
    if args.frame_skip is not None:
        raise UsageError("--frame-skip is for an MJCF's log; a task's dataset is sampled at the "
                         "task's own control period")
    if str(args.source).startswith("minari:"):
        data, source = _read_minari(args)
    else:
        data, source = _read_dataset(args)
    if data.meta.get("env") not in (None, args.env):
        raise UsageError(f"--from {source} was recorded on {data.meta.get('env')!r}, "
                         f"not {args.env!r}")
    if args.twin_seed is not None and not args.visual:
        raise UsageError("--twin-seed evaluates a visual fit: use it with --visual")
    if args.visual:
        return _sysid_visual(args, data, source)
    recorded = (data.meta.get("metadata") or {}).get("observation", "task")
    env = envs.make(args.env, **({"observation": "state"} if recorded == "state" else {}))
    if not env.observes_state:
        raise UsageError(f"--from {source}: {args.env}'s observation does not determine its "
                         f"state, so sysid cannot start a simulated window from it; record full "
                         f"states: twinrl collect --env {args.env} --observation state ...")
    _fit_and_report(args, env, data, len(data), source)
    return 0


def _read_minari(args):
    """``--from minari:NAME``: the Minari dataset as a twinrl ``Dataset``, and where it is."""
    from twinrl.real import dataset as ds
    from twinrl.real.dataset.minari import read_minari

    try:
        data = read_minari(str(args.source), root=args.minari_root, task=args.env)
    except (ds.DatasetError, ValueError) as e:  # missing, unreadable, spaces that do not fit
        raise UsageError(f"--from {args.source}: {e}") from None
    return data, data.path


def _read_dataset(args):
    """``--from DIR``: the dataset in DIR (or DIR/dataset), read past damage with a warning."""
    from twinrl.real import dataset as ds

    source = args.source
    if not (source / "meta.json").exists() and (source / "dataset" / "meta.json").exists():
        source = source / "dataset"
    if not (source / "meta.json").exists():
        if source.is_dir():  # a checkpoint or another output: say what it is, who takes it
            from twinrl.learn.checkpoint import CheckpointError
            from twinrl.loop.checkpoints import TAKES, require

            try:
                require(source, "sysid --from", TAKES["sysid --from"])
            except CheckpointError as e:
                raise UsageError(str(e)) from None
        raise UsageError(f"--from {args.source}: no dataset there (no meta.json)")
    try:
        data = ds.read(source, strict=False)
    except ds.DatasetError as e:  # no dataset there, or its meta.json is unreadable
        raise UsageError(f"--from {source}: {e}") from None
    if data.problems:  # damage costs the records it hit; the fit uses every intact one
        more = f" (and {len(data.problems) - 1} more)" if len(data.problems) > 1 else ""
        print(f"twinrl sysid: warning: dataset damaged, using its {len(data)} intact "
              f"transitions: {data.problems[0]}{more}", file=sys.stderr)
    return data, source


def _sysid_visual(args, data, source) -> int:
    """``twinrl sysid --visual``: the camera and the task's object fitted to the dataset's images
    (``twinrl.real2sim.visual``); with ``--twin-seed``, their errors against the real twin's
    hidden ones (evaluation only)."""
    from twinrl import report
    from twinrl.real2sim.visual import visual_sysid

    if not data.images:
        raise UsageError(f"--from {source} holds no images: record with "
                         f"`twinrl collect --images`")
    summary = visual_sysid(args.env, data, args.out, seed=args.seed, n_frames=args.frames)
    if args.twin_seed is not None:
        from twinrl.eval import visual_errors
        from twinrl.real.remote import secret_file

        # `twinrl collect` keeps the twin's secret beside the dataset (evaluation only)
        secret = secret_file(source.parent, args.env, args.twin_seed)
        summary["evaluation"] = {"twin_seed": args.twin_seed, **visual_errors(
            args.env, args.twin_seed, summary, secret if secret.exists() else None)}
        report.print_table(f"evaluation only: errors against real twin seed {args.twin_seed}",
                           ["error", "value"],
                           [[k, v] for k, v in summary["evaluation"].items()
                            if k != "twin_seed"])
        report.write_json(args.out / "summary.json", summary)
    return 0


def _sysid_config(args):
    """``SysidConfig`` from ``--known``, ``--window``, ``--max-latency`` and ``--param``."""
    from twinrl.real2sim import sysid

    known = []
    for item in args.known:
        name, _, value = item.partition("=")
        try:
            known.append((name.strip(), float(value)))
        except ValueError:
            raise UsageError(f"--known {item!r} must look like PARAM=NUMBER") from None
    at_least_one(args, "window")
    if args.max_latency is not None and args.max_latency < 0:
        raise UsageError(f"--max-latency must be >= 0, got {args.max_latency}")
    over = {k: v for k, v in (("window", args.window), ("max_latency", args.max_latency))
            if v is not None}
    if args.param:
        over["params"] = tuple(args.param)
    return sysid.SysidConfig(known=tuple(known), **over)


def _sysid_mjcf(args) -> int:
    """``twinrl sysid --env ROBOT.xml --from LOG.npz``: Real2Sim on a user's MJCF and logs."""
    import numpy as np

    from twinrl import envs, report
    from twinrl.envs.mjcf import read_log, save_mjcf

    if args.visual or args.twin_seed is not None:
        raise UsageError("--visual and --twin-seed fit a registered task's camera and object; "
                         "an MJCF's sysid takes its qpos/qvel/ctrl log")
    at_least_one(args, "frame_skip")
    try:  # an MJCF MJX cannot simulate, an actuator without a ctrlrange
        env = envs.from_mjcf(args.env, frame_skip=args.frame_skip or 1)
    except ValueError as e:
        raise UsageError(str(e)) from None
    if not args.source.is_file():
        raise UsageError(f"--from {args.source}: no such file (an MJCF's sysid takes an .npz "
                         f"with qpos, qvel and ctrl)")
    try:
        data = env.transitions(*read_log(args.source))
    except ValueError as e:  # an array missing, not an .npz, shapes that do not fit the model
        raise UsageError(f"--from {args.source}: {e}") from None
    summary, res = _fit_and_report(args, env, data, int(np.prod(data["action"].shape[:2])),
                                   args.source)
    summary["mjcf"] = str(save_mjcf(env, res.params, args.out / "identified.xml"))
    report.write_json(args.out / "summary.json", summary)
    report.console.print(f"identified MJCF: {summary['mjcf']}")
    return 0


def _fit_and_report(args, env, data, transitions: int, source):
    """sysid's fit, its table and ``OUT/summary.json``: ``(summary, result)``."""
    from twinrl import report
    from twinrl.real2sim import sysid

    lines = ProgressLines(f"sysid {env.name}")
    try:
        config = _sysid_config(args)
        lines(f"fitting {transitions} transitions: compiling the windows' rollouts and their "
              f"Jacobian (the first iteration)")
        res = sysid.fit(env, data, config, progress_fn=lambda it, m: lines.tick(
            f"iteration {it}: loss {m['loss']:.4g}, latency {m['latency']}, "
            f"{m['rollouts']} window rollouts"))
    except ValueError as e:
        raise UsageError(str(e)) from None
    finally:
        lines.close()
    sysid.print_result(res, title=f"sysid {env.name}")
    summary = {"env": args.env, "dataset": str(source), "transitions": transitions,
               **res.summary()}
    report.write_json(args.out / "summary.json", summary)
    return summary, res
