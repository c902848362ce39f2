"""``twinrl collect``: record episodes of a task's real twin into a durable dataset
(``twinrl.real.dataset``), appending to the one already in ``--out``."""

from __future__ import annotations

from twinrl.cli.common import UsageError, add_common, at_least_one, check_task
from twinrl.cli.export import add_minari_root


def add_parser(sub) -> None:
    """The ``collect`` sub-command's parser."""
    p = sub.add_parser(
        "collect", help="record episodes of a real twin into a durable dataset",
        description="Run a policy on a task's real twin and record every transition as it "
                    "happens (a killed run keeps everything but the transition in flight; run "
                    "again on the same --out to append more episodes).")
    p.add_argument("--env", required=True, help="task name (see `twinrl envs`)")
    p.add_argument("--episodes", type=int, required=True, help="episodes to record")
    p.add_argument("--policy", default="excite", choices=("excite", "random", "zero"),
                   help="'excite' (default: random levels, each held 3-15 steps, as sysid's "
                        "excitation: the system travels, so its trajectories and images show it "
                        "in many states; with --observation state the task's closed-loop "
                        "excitation where it has one, as push's strokes), 'random' (uniform in "
                        "the action box every step: it jitters in place) or 'zero'")
    p.add_argument("--images", action="store_true",
                   help="also record RGB, depth and segmentation of the default camera")
    p.add_argument("--size", type=int, nargs=2, default=(64, 64), metavar=("W", "H"),
                   help="image size with --images (default 64 64)")
    p.add_argument("--observation", default="task", choices=("task", "state"),
                   help="what each transition records: 'task' (default: the task's observation, "
                        "what a policy sees) or 'state' (the full qpos and qvel, as a motion-"
                        "capture rig gives them): what `twinrl sysid` needs where the task's "
                        "observation does not determine the state (push)")
    p.add_argument("--from", dest="source", default=None, metavar="minari:NAME",
                   help="start --out's dataset from a Minari dataset (`twinrl export` writes one; "
                        "anyone else's whose spaces fit --env): its episodes are imported first "
                        "and --episodes more recorded after them (0: import only); run again "
                        "with the same --from to continue it (the import is kept). A dataset "
                        "twinrl exported is continued on its own real twin: --seed must be its")
    add_minari_root(p)
    add_common(p, "runs/collect")
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    """Record ``--episodes`` episodes of ``--policy`` on the real twin of ``--env``."""
    import numpy as np
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from twinrl import envs, report
    from twinrl.real import dataset as ds
    from twinrl.real.dataset import DatasetWriter
    from twinrl.real.record import episode_seeds, record_episodes
    from twinrl.real2sim.sysid import excitation_actions

    check_task(args.env)
    if args.source is None:
        at_least_one(args, "episodes")
    elif args.episodes < 0:
        raise UsageError(f"--episodes must be >= 0, got {args.episodes}")
    w, h = args.size
    imported = _from_minari(args) if args.source is not None else None
    if imported is not None and args.episodes == 0:  # import only: no twin started
        report.write_json(args.out / "summary.json", {
            "env": args.env, "seed": args.seed, "episodes": 0, "returns": [],
            "dataset": str(args.out / "dataset"), "imported": imported})
        what = ("kept, imported by a run before" if imported["kept"] else
                f"{imported['episodes']} episodes, {imported['steps']} steps imported")
        report.console.print(f"{args.out / 'dataset'} from {imported['from']}: {what}")
        return 0
    # The real twin runs in its own process, as a robot would (twinrl.real.remote); its hidden
    # perturbation's seed includes a secret salt kept in OUT/eval/, beside the dataset, for
    # evaluation only (`twinrl sysid --visual --twin-seed` reads it).
    from twinrl.real.remote import TwinClient, secret_file

    fresh_out = not args.out.exists()
    full = args.observation == "state"
    twin = TwinClient(args.env, seed=args.seed, secret=secret_file(args.out, args.env, args.seed),
                      width=w, height=h, **({"config": {"observation": "state"}} if full else {}))
    obs, _ = twin.reset(seed=args.seed)
    act_shape = twin.action_space.shape
    image_shapes = None
    if args.images:
        # Rendered once before the dataset is touched, so a size the renderer refuses fails here
        # instead of after meta.json has been written claiming that size.
        from twinrl.real.twin import IMAGE_KINDS

        try:
            twin.render_images(twin.camera, IMAGE_KINDS)
        except ValueError as e:
            twin.close()
            if fresh_out:  # nothing recorded: leave no directory behind (the twin's secret)
                import shutil

                shutil.rmtree(args.out, ignore_errors=True)
            raise UsageError(f"--size {w} {h}: {e}") from None
        image_shapes = {"rgb": (h, w, 3), "depth": (h, w), "segmentation": (h, w)}
    dataset_dir = args.out / "dataset"
    try:
        writer = DatasetWriter(dataset_dir, env=args.env, obs_shape=obs.shape,
                               action_shape=act_shape, image_shapes=image_shapes,
                               obs_dtype=imported["obs_dtype"] if imported else np.float32,
                               action_dtype=imported["action_dtype"] if imported else np.float32,
                               metadata=None if imported or not full else {"observation": "state"})
    except (ValueError, OSError, ds.DatasetError) as e:  # another env, a live writer, ...
        raise UsageError(f"--out {args.out}: {e}") from None
    # full states are for sysid: the task's own closed-loop excitation where it has one (push:
    # held random levels rarely touch the box), as sysid.collect's policy="auto"
    task_excitation = getattr(envs.make(args.env, observation="state"), "excitation_policy",
                              None) if full else None
    returns, steps = [], 0
    first_episode = writer.episode_id
    columns = [TextColumn("[bold]collect"), BarColumn(), MofNCompleteColumn(),
               TextColumn("episodes  return {task.fields[ret]}"), TimeElapsedColumn()]
    def policy(e):
        # Each episode's randomness is a function of (--seed, its id in the dataset): re-running
        # on the same --out appends new episodes, not copies of the first ones.
        _, rng = episode_seeds(args.seed, first_episode + e)
        if args.policy == "excite" and task_excitation is not None:
            return task_excitation(rng)
        if args.policy == "excite":
            levels = excitation_actions(rng, twin.episode_length, int(np.prod(act_shape)))
            return lambda o, t: levels[min(t, len(levels) - 1)].reshape(act_shape)
        if args.policy == "random":
            return lambda o, t: rng.uniform(-1, 1, act_shape)
        return lambda o, t: np.zeros(act_shape)

    try:
        with writer, Progress(*columns, console=report.console) as bar:
            task = bar.add_task("collect", total=args.episodes, ret="-")

            def done(rec):
                nonlocal steps
                returns.append(rec.ret)
                steps += rec.steps
                bar.update(task, advance=1, ret=f"{rec.ret:.2f}")

            record_episodes(twin, range(args.episodes), policy,
                            lambda e: episode_seeds(args.seed, first_episode + e)[0],
                            writer=writer, images=args.images, on_episode=done)
    except OSError as e:  # disk full, quota, I/O error: what was recorded before stays readable
        raise UsageError(f"writing {dataset_dir} failed after {len(returns)} complete "
                         f"episode(s) of this run: {e.strerror or e}; the dataset keeps every "
                         f"transition recorded before") from None
    twin.close()
    summary = {"env": args.env, "policy": args.policy, "seed": args.seed,
               "episodes": args.episodes, "first_episode_id": first_episode, "steps": steps,
               "returns": returns, "mean_return": float(np.mean(returns)),
               "dataset": str(args.out / "dataset"),
               **({"imported": imported} if imported is not None else {})}
    report.print_table(f"collected {args.env}", ["episodes", "steps", "mean return", "min", "max"],
                       [[args.episodes, steps, float(np.mean(returns)), float(np.min(returns)),
                         float(np.max(returns))]])
    report.write_json(args.out / "summary.json", summary)
    return 0


def _from_minari(args) -> dict:
    """``--from minari:NAME``: ``--out``'s dataset started from the Minari dataset (imported unless
    a run before did). When this run records episodes, checks first that they continue it: the
    same task, observation, images and, for a dataset twinrl exported, real twin. Returns what
    was imported and the dtypes to continue with."""
    import json

    from twinrl.real import dataset as ds
    from twinrl.real.dataset.minari import (PREFIX, export_metadata, find_dataset,
                                            import_minari, read_minari)

    if not str(args.source).startswith(PREFIX):
        raise UsageError(f"--from {args.source}: --from takes minari:NAME (a Minari dataset; "
                         f"`twinrl export` writes one)")
    dataset_dir = args.out / "dataset"
    data = None
    try:
        full, _ = find_dataset(args.source, args.minari_root)
        source = f"{PREFIX}{full}"
        if (dataset_dir / "meta.json").exists():  # a run before imported it, or another dataset
            meta = json.loads((dataset_dir / "meta.json").read_text(encoding="utf-8"))
            if (meta.get("metadata") or {}).get("source") != source:
                raise UsageError(f"--out {args.out} holds a dataset not imported from {source}; "
                                 f"import into a new --out")
        else:
            data = read_minari(args.source, root=args.minari_root, task=args.env)
            meta = data.meta
        ours = export_metadata(args.source, args.minari_root) or {}
    except (ds.DatasetError, ValueError, KeyError) as e:  # missing, unreadable, does not fit
        raise UsageError(f"--from {args.source}: {e}") from None
    if args.episodes > 0:
        _check_continues(args, source, meta, ours.get("twin_seeds") or [])
    out = {"from": source, "kept": data is None, "obs_dtype": meta["obs_dtype"],
           "action_dtype": meta["action_dtype"]}
    if data is not None:
        try:
            import_minari(args.source, dataset_dir, task=args.env, root=args.minari_root,
                          data=data)
        except (ds.DatasetError, ValueError, OSError) as e:
            raise UsageError(f"--out {args.out}: {e}") from None
        out |= {"episodes": data.num_episodes, "steps": len(data)}
    return out


def _check_continues(args, source: str, meta: dict, seeds: list[int]) -> None:
    """One line where the episodes this run would record do not continue the imported dataset
    (``meta``: its meta.json): another real twin, observation or set of images."""
    if seeds and args.seed not in seeds:
        raise UsageError(f"--from {source} was recorded on real twin seed "
                         f"{', '.join(map(str, seeds))}; continue it on the same twin: "
                         f"--seed {seeds[0]}")
    kind = (meta.get("metadata") or {}).get("observation", "task")
    if kind != args.observation:
        raise UsageError(f"--from {source} records the {kind} observation; collect with "
                         f"--observation {kind}")
    w, h = args.size
    wanted = {"rgb": [h, w, 3], "depth": [h, w], "segmentation": [h, w]} if args.images else {}
    have = meta["image_shapes"]
    if have != wanted:
        if not have:
            why = "holds no images: collect without --images"
        elif not args.images:
            why = f"holds images {have}: collect with --images and the --size W H of them"
        else:
            why = f"holds images {have}, not {wanted}: collect with the --size that matches"
        raise UsageError(f"--from {source} {why}")
