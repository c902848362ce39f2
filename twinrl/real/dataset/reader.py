"""``read``: a dataset directory back as a ``Dataset`` of numpy arrays, damage reported per file.

``Dataset`` holds every transition in recording order with its episode boundaries; ``Episode`` is
one episode's views into it.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from twinrl.real.dataset._checks import DatasetError, read_meta
from twinrl.real.dataset._format import IMAGE_DTYPES, list_chunks, scan_chunk


@dataclasses.dataclass(frozen=True, eq=False)
class Episode:
    """One episode of a ``Dataset``: views (no copies) of its transitions."""

    id: int
    """Episode id (unique in the dataset, increasing in recording order)."""
    complete: bool
    """Steps 0..n-1 all present and the episode ended (terminated, truncated or ``end_episode``)."""
    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    step: np.ndarray
    """Index of each transition within the episode (0, 1, ... unless records were lost)."""
    time: np.ndarray
    """Wall-clock time (``time.time()``) at which each transition was recorded."""
    info: list[dict[str, Any]]
    images: dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.reward)


_PER_TRANSITION = ("obs", "action", "reward", "next_obs", "terminated", "truncated",
                   "episode_id", "step", "time", "info")


@dataclasses.dataclass(frozen=True, eq=False)
class Dataset:
    """Transitions read back from a dataset directory, in recording order, as numpy arrays.

    Transitions of one episode are contiguous: episode ``i`` is
    ``episode_starts[i]:episode_ends[i]``.
    """

    path: Path
    meta: dict[str, Any]
    """Contents of ``meta.json``: format, version, env, shapes, dtypes, image_shapes, metadata."""
    obs: np.ndarray
    """Shape (N, *obs_shape)."""
    action: np.ndarray
    """Shape (N, *action_shape)."""
    reward: np.ndarray
    """Shape (N,), float64."""
    next_obs: np.ndarray
    """Shape (N, *obs_shape)."""
    terminated: np.ndarray
    """Shape (N,), bool."""
    truncated: np.ndarray
    """Shape (N,), bool."""
    episode_id: np.ndarray
    """Shape (N,), int64: episode of each transition."""
    step: np.ndarray
    """Shape (N,), int64: index of each transition within its episode."""
    time: np.ndarray
    """Shape (N,), float64: wall-clock time each transition was recorded."""
    info: list[dict[str, Any]]
    """One dict per transition."""
    images: dict[str, np.ndarray]
    """Per ``image_shapes`` key, shape (N, *image_shape); empty when no images were recorded."""
    episode_starts: np.ndarray
    """Shape (E,), int64: index of each episode's first transition."""
    episode_ends: np.ndarray
    """Shape (E,), int64: one past each episode's last transition."""
    episode_complete: np.ndarray
    """Shape (E,), bool: see ``Episode.complete``; the episode a killed writer left is False."""
    problems: list[str]
    """Damage found by a non-strict read, each naming its file; empty for an intact dataset."""

    def __len__(self) -> int:
        return len(self.reward)

    @property
    def num_episodes(self) -> int:
        """Number of episodes (complete or not)."""
        return len(self.episode_starts)

    def episodes(self) -> Iterator[Episode]:
        """Yields each episode as views into this dataset's arrays."""
        for i, (a, b) in enumerate(
            zip(self.episode_starts.tolist(), self.episode_ends.tolist(), strict=True)
        ):
            yield Episode(
                id=int(self.episode_id[a]),
                complete=bool(self.episode_complete[i]),
                obs=self.obs[a:b],
                action=self.action[a:b],
                reward=self.reward[a:b],
                next_obs=self.next_obs[a:b],
                terminated=self.terminated[a:b],
                truncated=self.truncated[a:b],
                step=self.step[a:b],
                time=self.time[a:b],
                info=self.info[a:b],
                images={k: v[a:b] for k, v in self.images.items()},
            )

    def first_episodes(self, n: int) -> "Dataset":
        """The dataset's first ``n`` episodes (in recording order; all of them if it has fewer)
        as a ``Dataset`` of views: e.g. the episodes one phase of a run recorded."""
        n = max(0, min(int(n), self.num_episodes))
        end = int(self.episode_ends[n - 1]) if n else 0
        cut = {name: getattr(self, name)[:end] for name in _PER_TRANSITION}
        return dataclasses.replace(
            self, **cut, images={k: v[:end] for k, v in self.images.items()},
            episode_starts=self.episode_starts[:n], episode_ends=self.episode_ends[:n],
            episode_complete=self.episode_complete[:n])


def read(path: str | os.PathLike[str], strict: bool = True) -> Dataset:
    """Reads every transition of the dataset at ``path``.

    A torn tail left by a killed writer (in a ``.twr.open`` chunk) is dropped silently: that is the
    transition in flight, and its episode reads back incomplete. So is the zero-filled tail that a
    power loss leaves after appends that were not yet fsync'd (unreadable records followed only by
    zeros to the end of an ``.open`` chunk). Any other damage (flipped bytes, a
    truncated closed chunk, a missing chunk, a record that disagrees with ``meta.json``) raises
    ``DatasetError`` naming the file when ``strict``; with ``strict=False`` every intact transition
    is returned and the damage is listed in ``Dataset.problems``. A missing directory or an
    unreadable ``meta.json`` raises ``DatasetError`` in both modes.
    """
    root = Path(path)
    if not root.is_dir():
        what = "is not a directory" if root.exists() else "does not exist"
        raise DatasetError(f"no dataset at {root}: the path {what}")
    meta = read_meta(root)
    obs_shape, action_shape = tuple(meta["obs_shape"]), tuple(meta["action_shape"])
    obs_dtype, action_dtype = np.dtype(meta["obs_dtype"]), np.dtype(meta["action_dtype"])
    image_shapes = {k: tuple(v) for k, v in meta["image_shapes"].items()}
    expected = {
        "obs": (obs_dtype, obs_shape),
        "action": (action_dtype, action_shape),
        "next_obs": (obs_dtype, obs_shape),
    }
    expected |= {
        f"images/{k}": (IMAGE_DTYPES[k.split("/", 1)[0]], s) for k, s in image_shapes.items()
    }

    problems: list[str] = []
    chunks = list_chunks(root)
    _check_chunk_sequence(root, chunks, problems)
    headers: list[dict[str, Any]] = []
    arrays: list[dict[str, np.ndarray]] = []
    ended: set[int] = set()
    for _, _, is_open, file in chunks:
        try:
            try:
                data = file.read_bytes()
            except FileNotFoundError:
                if not is_open:
                    raise
                # A live writer closed this chunk after we listed the directory: read it closed.
                file, is_open = file.with_name(file.name[: -len(".open")]), False
                data = file.read_bytes()
        except OSError as e:
            problems.append(f"{file}: cannot be read ({e})")
            continue
        for offset, header, body in scan_chunk(file, data, not is_open, problems):
            where = f"{file}: record at offset {offset}"
            kind = header.get("kind")
            if kind == "end":
                if isinstance(header.get("episode"), int) and not isinstance(
                    header["episode"], bool
                ):
                    ended.add(header["episode"])
                else:
                    problems.append(f"{where}: end marker without an episode id; skipped")
            elif kind == "step":
                try:
                    _check_step_header(header)
                    arrays.append(_decode_arrays(header, body, expected))
                except ValueError as e:
                    problems.append(f"{where}: {e}; skipped")
                    continue
                headers.append(header)
            else:
                problems.append(f"{where}: unknown record kind {kind!r}; skipped")

    starts, ends, complete = _episodes(root, headers, ended, problems)
    if problems and strict:
        more = f" (and {len(problems) - 1} more problems)" if len(problems) > 1 else ""
        raise DatasetError(
            f"{problems[0]}{more}; read(..., strict=False) returns the intact transitions", problems
        )

    def stack(name: str) -> np.ndarray:
        dtype, shape = expected[name]
        if not arrays:
            return np.empty((0, *shape), dtype)
        return np.stack([a[name] for a in arrays])

    return Dataset(
        path=root,
        meta=meta,
        obs=stack("obs"),
        action=stack("action"),
        reward=np.array([h["reward"] for h in headers], np.float64),
        next_obs=stack("next_obs"),
        terminated=np.array([h["terminated"] for h in headers], bool),
        truncated=np.array([h["truncated"] for h in headers], bool),
        episode_id=np.array([h["episode"] for h in headers], np.int64),
        step=np.array([h["step"] for h in headers], np.int64),
        time=np.array([h["time"] for h in headers], np.float64),
        info=[h["info"] for h in headers],
        images={k: stack(f"images/{k}") for k in image_shapes},
        episode_starts=np.array(starts, np.int64),
        episode_ends=np.array(ends, np.int64),
        episode_complete=np.array(complete, bool),
        problems=problems,
    )


def _check_chunk_sequence(
    root: Path, chunks: list[tuple[int, int, bool, Path]], problems: list[str]
) -> None:
    # A writer numbers its chunks 0, 1, 2, ...; a gap means a chunk file was deleted or renamed.
    by_session: dict[int, list[int]] = {}
    for session, index, _, _ in chunks:
        by_session.setdefault(session, []).append(index)
    for session, indices in by_session.items():
        missing = sorted(set(range(max(indices) + 1)) - set(indices))
        if missing:
            names = ", ".join(f"chunk-{session:05d}-{i:05d}.twr" for i in missing[:3])
            problems.append(f"{root}: missing chunk file(s) {names}")


def _check_step_header(h: dict[str, Any]) -> None:
    for key, types in (
        ("episode", int),
        ("step", int),
        ("time", (int, float)),
        ("reward", (int, float)),
        ("terminated", bool),
        ("truncated", bool),
        ("info", dict),
        ("arrays", list),
    ):
        if not isinstance(h.get(key), types) or (types is int and isinstance(h[key], bool)):
            raise ValueError(f"field {key!r} is missing or malformed ({h.get(key)!r})")


def _decode_arrays(
    header: dict[str, Any], body: memoryview, expected: dict[str, tuple[np.dtype, tuple[int, ...]]]
) -> dict[str, np.ndarray]:
    out = {}
    offset = 0
    for entry in header["arrays"]:
        try:
            name, dtype_str, shape = entry
            dtype, shape = np.dtype(dtype_str), tuple(shape)
        except (TypeError, ValueError) as e:
            raise ValueError(f"malformed array entry {entry!r}") from e
        if name not in expected or expected[name] != (dtype, shape):
            want = expected.get(name)
            raise ValueError(
                f"array {name!r} {dtype_str}{list(shape)} does not match meta.json ({want})"
            )
        count = math.prod(shape)
        if offset + count * dtype.itemsize > len(body):
            raise ValueError(f"array {name!r} runs past the end of the record")
        out[name] = np.frombuffer(body, dtype, count, offset).reshape(shape)
        offset += count * dtype.itemsize
    if set(out) != set(expected):
        raise ValueError(f"arrays {sorted(set(expected) - set(out))} missing")
    if offset != len(body):
        raise ValueError(
            f"{len(body) - offset} bytes of the record body are not described by its header"
        )
    return out


def _episodes(
    root: Path, headers: list[dict[str, Any]], ended: set[int], problems: list[str]
) -> tuple[list[int], list[int], list[bool]]:
    starts, ends, complete = [], [], []
    seen: set[int] = set()
    i = 0
    while i < len(headers):
        ep = headers[i]["episode"]
        j = i
        while j < len(headers) and headers[j]["episode"] == ep:
            j += 1
        if ep in seen:
            problems.append(f"{root}: episode {ep} is recorded in two separate places")
        seen.add(ep)
        steps = [h["step"] for h in headers[i:j]]
        last = headers[j - 1]
        finished = last["terminated"] or last["truncated"] or ep in ended
        starts.append(i)
        ends.append(j)
        complete.append(steps == list(range(j - i)) and finished)
        i = j
    return starts, ends, complete
