"""``twinrl export``: a recorded dataset written in another format: a Minari dataset
(``twinrl.real.dataset.minari``) that offline-RL code reads with ``minari.load_dataset``.

Also the ``--minari-root`` option that ``sysid`` and ``collect`` take with ``--from minari:NAME``.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from twinrl.cli.common import UsageError, add_common

MINARI_ROOT_HELP = ("where Minari datasets live (default: $MINARI_DATASETS_PATH, else "
                    "~/.minari/datasets, Minari's own default)")


def add_minari_root(p) -> None:
    """The ``--minari-root DIR`` option of a command that reads or writes Minari datasets."""
    p.add_argument("--minari-root", type=Path, default=None, metavar="DIR", help=MINARI_ROOT_HELP)


def add_parser(sub) -> None:
    """The ``export`` sub-command's parser."""
    p = sub.add_parser(
        "export", help="write a recorded dataset as a Minari dataset",
        description="Write a dataset recorded by `twinrl collect` or `twinrl run` as a Minari "
                    "dataset (Farama's format for offline RL; needs the `minari` extra: pip "
                    "install 'twinrl[minari]'): states, actions, rewards, terminations and "
                    "truncations per episode, the recorded images and infos, the task and the "
                    "real twin's public seed in its metadata (never the twin's hidden "
                    "perturbation). Read it back with `--from minari:NAME` (sysid, collect) or "
                    "minari.load_dataset(NAME).")
    p.add_argument("source", metavar="DIR", type=Path,
                   help="the dataset directory, or the --out of `twinrl collect` or `twinrl "
                        "run` (DIR/dataset)")
    p.add_argument("--to", nargs=2, required=True, metavar=("FORMAT", "NAME"),
                   help="the format, 'minari', and the dataset's Minari id, "
                        "(namespace/)name(-vN), e.g. twinrl/pendulum/excite-v0 (-v0 when no "
                        "version is given); an existing id is refused")
    p.add_argument("--twin-seed", type=int, default=None,
                   help="the real twin's public seed recorded in the metadata (default: the "
                        "seed `twinrl collect --seed` or `twinrl run --seed` used, read from "
                        "DIR's eval/ file names or loop.json)")
    add_minari_root(p)
    add_common(p, "runs/export")
    p.set_defaults(func=cmd)


def twin_seeds(out: Path, task: str) -> list[int]:
    """The public seeds of the real twins a `collect` or `run` output directory ``out`` recorded
    on: `collect` names each twin's secret ``eval/twin-TASK-seedN.json`` (only the name is read),
    `run` keeps its seed in ``loop.json``."""
    pattern = re.compile(rf"^twin-{re.escape(task)}-seed(\d+)\.json$")
    eval_dir = out / "eval"
    seeds = sorted(int(m[1]) for p in (eval_dir.iterdir() if eval_dir.is_dir() else ())
                   if (m := pattern.match(p.name)))
    if not seeds and (out / "loop.json").is_file():
        try:
            seed = json.loads((out / "loop.json").read_text(encoding="utf-8")).get("seed")
        except (OSError, ValueError, AttributeError):
            seed = None
        if isinstance(seed, int) and not isinstance(seed, bool):
            seeds = [seed]
    return seeds


def cmd(args) -> int:
    """Write the dataset in ``DIR`` as the Minari dataset ``NAME``."""
    from twinrl import report
    from twinrl.real import dataset as ds
    from twinrl.real.dataset.minari import dataset_id, to_minari

    fmt, name = args.to
    if fmt != "minari":
        raise UsageError(f"--to {fmt}: unknown format; the formats are: minari")
    source = args.source
    if not (source / "meta.json").exists() and (source / "dataset" / "meta.json").exists():
        source = source / "dataset"
    full = dataset_id(name)  # a malformed name fails before the dataset is read
    data = ds.read(source, strict=False)
    if data.problems:  # damage costs the records it hit; the export keeps every intact one
        more = f" (and {len(data.problems) - 1} more)" if len(data.problems) > 1 else ""
        print(f"twinrl export: warning: dataset damaged, exporting its {len(data)} intact "
              f"transitions: {data.problems[0]}{more}", file=sys.stderr)
    task = data.meta["env"]
    seeds = [args.twin_seed] if args.twin_seed is not None else twin_seeds(source.parent, task)
    path = to_minari(data, full, root=args.minari_root, twin_seeds=seeds)
    summary = {"source": str(source), "env": task, "format": "minari", "dataset_id": full,
               "path": str(path.parent), "episodes": data.num_episodes,
               "transitions": len(data), "images": sorted(data.images), "twin_seeds": seeds}
    report.print_table(f"exported {task} to Minari", ["dataset id", "episodes", "transitions",
                                                      "twin seed", "path"],
                       [[full, data.num_episodes, len(data),
                         ", ".join(map(str, seeds)) or "-", str(path.parent)]])
    report.write_json(args.out / "summary.json", summary)
    return 0
