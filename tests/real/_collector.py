"""A deterministic fake collector that the kill test runs in a subprocess and SIGKILLs.

``python _collector.py DIR SYNC CHUNK_SIZE`` continues the dataset in DIR forever, printing
``start <episode id>`` once the writer is open and then, after every ``add`` has returned, the
number of completed ``add`` calls (flushed, so the count the test reads is never ahead of the
dataset).

Every transition is a pure function of (episode id, step), so the test can check each recorded
transition's content without talking to the collector. Only numpy and the dataset package (loaded
from its files) are imported: importing the ``twinrl`` package would import jax, and twenty
start-ups of that would dominate the test.
"""

from __future__ import annotations

import importlib
import sys
import time
import types
from pathlib import Path
from typing import Any

import numpy as np

OBS_SHAPE = (3,)
ACTION_SHAPE = (2,)
IMAGE_SHAPES = {"rgb": (4, 4, 3), "depth": (4, 4), "segmentation": (4, 4)}
ENDINGS = ("terminated", "truncated", "end_episode")
# A collector the test failed to kill stops on its own rather than running forever.
MAX_SECONDS = 60.0


def episode_plan(ep: int) -> tuple[int, str]:
    """(length, how it ends) of episode ``ep``."""
    return 3 + (ep * 5) % 9, ENDINGS[ep % 3]


def transition(ep: int, t: int) -> dict[str, Any]:
    """The arguments of ``DatasetWriter.add`` for step ``t`` of episode ``ep``."""
    length, ending = episode_plan(ep)
    last = t == length - 1
    k = np.arange(16)
    return {
        "obs": np.array([ep, t, np.sin(ep + 0.1 * t)]),
        "action": np.array([0.5 * t, -float(ep)]),
        "reward": ep + t / 7,
        "next_obs": np.array([ep, t + 1, np.sin(ep + 0.1 * (t + 1))]),
        "terminated": last and ending == "terminated",
        "truncated": last and ending == "truncated",
        "info": {"ep": np.int64(ep), "t": t, "tag": f"e{ep}s{t}", "gain": np.float32(0.25) * t},
        "images": {
            "rgb": ((ep * 31 + t * 7 + np.arange(48)) % 256).astype(np.uint8).reshape(4, 4, 3),
            "depth": (ep + t + k / 16).astype(np.float32).reshape(4, 4),
            "segmentation": ((k + t) % 5).astype(np.int32).reshape(4, 4),
        },
    }


def _load_dataset_module():
    # ``twinrl`` and ``twinrl.real`` stand in as bare packages pointing at their directories, so
    # importing the dataset package runs its own modules and not the ``twinrl`` package's
    # ``__init__`` (which imports jax).
    root = Path(__file__).resolve().parents[2] / "twinrl"
    for name, path in (("twinrl", root), ("twinrl.real", root / "real")):
        package = types.ModuleType(name)
        package.__path__ = [str(path)]
        sys.modules[name] = package
    return importlib.import_module("twinrl.real.dataset")


def main(argv: list[str]) -> None:
    root, sync, chunk_size = argv[0], argv[1], int(argv[2])
    dataset = _load_dataset_module()
    deadline = time.monotonic() + MAX_SECONDS
    with dataset.DatasetWriter(
        root,
        env="fake",
        obs_shape=OBS_SHAPE,
        action_shape=ACTION_SHAPE,
        image_shapes=IMAGE_SHAPES,
        metadata={"collector": "tests/real/_collector.py"},
        chunk_size=chunk_size,
        sync=sync,
    ) as writer:
        print(f"start {writer.episode_id}", flush=True)
        count = 0
        while time.monotonic() < deadline:
            ep = writer.episode_id
            length, ending = episode_plan(ep)
            for t in range(length):
                writer.add(**transition(ep, t))
                count += 1
                print(count, flush=True)
            if ending == "end_episode":
                writer.end_episode()


if __name__ == "__main__":
    main(sys.argv[1:])
