"""``DatasetWriter``: appends transitions to a dataset directory, each durable when ``add`` returns.

One writer holds a dataset at a time (``flock`` on ``.lock``, released by the kernel when the
holder dies); a writer on an existing dataset continues it in a new session of chunk files.
"""

from __future__ import annotations

import datetime
import fcntl
import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from twinrl.real.dataset._checks import (
    DatasetError,
    DatasetMismatch,
    check_array,
    check_finite_scalar,
    check_flag,
    check_image_shapes,
    check_real_dtype,
    check_shape,
    json_safe,
    read_meta,
)
from twinrl.real.dataset._format import (
    FILE_MAGIC,
    FORMAT,
    IMAGE_DTYPES,
    LOCK_FILE,
    META_FILE,
    META_KEYS,
    VERSION,
    encode_record,
    list_chunks,
    scan_chunk,
)

Sync = Literal["transition", "episode", "none"]
"""When a writer ``fsync``s: every transition, at episode ends and close, or never."""
_SYNC_MODES = ("transition", "episode", "none")


class DatasetWriter:
    """Appends transitions to a dataset directory, each one durable when ``add`` returns.

    Args:
        path: dataset directory. Created if absent; an existing dataset there is continued (a new
            writer session: new chunk files, episode ids continue after the largest recorded).
        env: name of the environment the transitions come from (stored in ``meta.json``).
        obs_shape, action_shape: shapes of one observation / one action.
        image_shapes: image streams every transition carries, e.g. ``{"rgb": (64, 64, 3),
            "depth": (64, 64), "segmentation": (64, 64)}``; keys are ``rgb``/``depth``/
            ``segmentation``, optionally ``kind/camera`` (``"rgb/wrist"``). Stored dtypes are
            ``IMAGE_DTYPES``: uint8 RGB, float32 depth, int32 segmentation.
        metadata: free-form JSON-serialisable dict stored in ``meta.json`` (numpy scalars are
            converted).
            Written once; continuing a dataset with different metadata is an error (pass None).
        obs_dtype, action_dtype: stored dtypes (float64 default: the MuJoCo engine's precision,
            which sysid on real data wants to keep).
        chunk_size: transitions per chunk file before a new one is started.
        sync: when to ``fsync``: ``"transition"`` (every ``add``; survives power loss),
            ``"episode"`` (at episode ends and close), ``"none"`` (never). Every mode survives the
            process being killed.

    Continuing a dataset requires the same ``env``, shapes, dtypes and ``image_shapes``.
    Only one writer may hold a dataset at a time (``DatasetError`` otherwise).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        env: str,
        obs_shape: int | Sequence[int],
        action_shape: int | Sequence[int],
        image_shapes: Mapping[str, Sequence[int]] | None = None,
        metadata: Mapping[str, Any] | None = None,
        obs_dtype: Any = np.float64,
        action_dtype: Any = np.float64,
        chunk_size: int = 1000,
        sync: Sync = "transition",
    ):
        if sync not in _SYNC_MODES:
            raise ValueError(f"sync={sync!r}; expected one of {', '.join(_SYNC_MODES)}")
        if (
            isinstance(chunk_size, bool)
            or not isinstance(chunk_size, (int, np.integer))
            or chunk_size < 1
        ):
            raise ValueError(f"chunk_size={chunk_size!r}; expected an integer >= 1")
        if not isinstance(env, str) or not env:
            raise ValueError(f"env={env!r}; expected a non-empty environment name")
        wanted = {
            "env": env,
            "obs_shape": list(check_shape("obs_shape", obs_shape)),
            "obs_dtype": check_real_dtype("obs_dtype", obs_dtype).str,
            "action_shape": list(check_shape("action_shape", action_shape)),
            "action_dtype": check_real_dtype("action_dtype", action_dtype).str,
            "image_shapes": check_image_shapes(image_shapes or {}),
        }
        if metadata is not None and not isinstance(metadata, Mapping):
            raise ValueError(
                f"metadata has type {type(metadata).__name__}; expected a dict or None"
            )
        user_meta = None if metadata is None else json_safe(dict(metadata), "metadata")

        self.path = Path(path)
        self.sync: Sync = sync
        self.chunk_size = int(chunk_size)
        # Checked before the lock file is created, which would litter someone else's directory.
        _refuse_foreign_directory(self.path)
        self.path.mkdir(parents=True, exist_ok=True)
        self._lock_fd: int | None = _lock(self.path)
        try:
            self.meta: dict[str, Any] = _open_or_create_meta(self.path, wanted, user_meta)
            self.session, self._episode = _resume_point(self.path)
        except BaseException:
            os.close(self._lock_fd)
            self._lock_fd = None
            raise
        self._obs_shape = tuple(self.meta["obs_shape"])
        self._action_shape = tuple(self.meta["action_shape"])
        self._obs_dtype = np.dtype(self.meta["obs_dtype"])
        self._action_dtype = np.dtype(self.meta["action_dtype"])
        self._image_shapes = {k: tuple(v) for k, v in self.meta["image_shapes"].items()}
        self._fd: int | None = None
        self._chunk_path: Path | None = None
        self._chunk_index = 0
        self._chunk_steps = 0
        self._chunk_records = 0
        self._offset = 0
        self._step = 0
        self.num_added = 0
        """Transitions recorded by this writer (this session)."""

    @property
    def episode_id(self) -> int:
        """Id of the episode the next ``add`` belongs to."""
        return self._episode

    @property
    def closed(self) -> bool:
        """Whether ``close`` was called."""
        return self._lock_fd is None

    def add(
        self,
        obs: Any,
        action: Any,
        reward: Any,
        next_obs: Any,
        terminated: Any,
        truncated: Any,
        info: Mapping[str, Any] | None = None,
        images: Mapping[str, Any] | None = None,
    ) -> None:
        """Records one transition; when this returns it is on disk (fsync'd per ``sync``).

        ``terminated`` or ``truncated`` ends the episode: the next ``add`` starts a new one.
        Raises ``ValueError`` naming the field for a wrong shape or dtype, NaN/inf in obs, action,
        next_obs or reward, non-boolean flags, non-JSON ``info`` or missing/extra images; nothing is
        written then, and what was recorded before stays.
        """
        self._check_open()
        obs_a = check_array("obs", obs, self._obs_shape, self._obs_dtype, "same_kind", finite=True)
        action_a = check_array(
            "action", action, self._action_shape, self._action_dtype, "same_kind", finite=True
        )
        next_a = check_array(
            "next_obs", next_obs, self._obs_shape, self._obs_dtype, "same_kind", finite=True
        )
        reward_f = check_finite_scalar("reward", reward)
        term = check_flag("terminated", terminated)
        trunc = check_flag("truncated", truncated)
        if info is not None and not isinstance(info, Mapping):
            raise ValueError(f"info has type {type(info).__name__}; expected a dict or None")
        info_j = json_safe(dict(info or {}), "info")
        arrays = [("obs", obs_a), ("action", action_a), ("next_obs", next_a)]
        arrays += [(f"images/{k}", v) for k, v in self._images(images).items()]
        header = {
            "kind": "step",
            "episode": self._episode,
            "step": self._step,
            "time": time.time(),
            "reward": reward_f,
            "terminated": term,
            "truncated": trunc,
            "info": info_j,
        }
        record = encode_record(header, arrays)

        if self._fd is None or self._chunk_steps >= self.chunk_size:
            self._start_chunk()
        self._write(record)
        self._chunk_steps += 1
        self._chunk_records += 1
        self.num_added += 1
        self._step += 1
        ends = term or trunc
        if self.sync == "transition" or (ends and self.sync == "episode"):
            os.fsync(self._fd)
        if ends:
            self._episode += 1
            self._step = 0

    def end_episode(self) -> None:
        """Ends the current episode without terminated/truncated (e.g. the operator stopped it).

        A no-op when the episode has no transitions yet (also right after a terminal ``add``).
        """
        self._check_open()
        if self._step == 0:
            return
        self._write(
            encode_record({"kind": "end", "episode": self._episode, "steps": self._step}, [])
        )
        self._chunk_records += 1
        if self.sync != "none":
            os.fsync(self._fd)
        self._episode += 1
        self._step = 0

    def close(self) -> None:
        """Writes the chunk footer, renames the chunk closed and releases the dataset.

        An episode still open is *not* ended: it reads back incomplete (call ``end_episode`` first
        if it was finished). Idempotent.
        """
        if self._lock_fd is None:
            return
        try:
            if self._fd is not None:
                self._close_chunk()
        finally:
            os.close(self._lock_fd)
            self._lock_fd = None

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self.closed else f"session {self.session}, episode {self._episode}"
        return f"DatasetWriter({str(self.path)!r}, {state}, {self.num_added} added)"

    # -- internals ---------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._lock_fd is None:
            raise ValueError(f"DatasetWriter for {self.path} is closed")

    def _images(self, images: Mapping[str, Any] | None) -> dict[str, np.ndarray]:
        given = dict(images or {})
        if set(given) != set(self._image_shapes):
            raise ValueError(
                f"images has keys {sorted(given)}; this dataset records "
                f"{sorted(self._image_shapes)} "
                f"(image_shapes in {self.path / META_FILE})"
            )
        out = {}
        for key in sorted(given):
            kind = key.split("/", 1)[0]
            # RGB must already be uint8: silently casting float images in [0, 1] would store zeros.
            casting = "safe" if kind == "rgb" else "same_kind"
            out[key] = check_array(
                f"images[{key!r}]", given[key], self._image_shapes[key], IMAGE_DTYPES[kind], casting
            )
        return out

    def _start_chunk(self) -> None:
        if self._fd is not None:
            self._close_chunk()
        name = f"chunk-{self.session:05d}-{self._chunk_index:05d}.twr.open"
        self._chunk_path = self.path / name
        # O_APPEND: after a failed write is cut off by ftruncate, the next one lands at the new end.
        self._fd = os.open(
            self._chunk_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o644
        )
        self._offset = 0
        self._chunk_steps = 0
        self._chunk_records = 0
        self._chunk_index += 1
        self._write(FILE_MAGIC)
        if self.sync != "none":
            os.fsync(self._fd)
            _fsync_dir(self.path)

    def _close_chunk(self) -> None:
        assert self._fd is not None and self._chunk_path is not None
        self._write(encode_record({"kind": "footer", "records": self._chunk_records}, []))
        if self.sync != "none":
            os.fsync(self._fd)
        os.close(self._fd)
        self._fd = None
        closed = self._chunk_path.with_name(self._chunk_path.name[: -len(".open")])
        os.replace(self._chunk_path, closed)
        if self.sync != "none":
            _fsync_dir(self.path)

    def _write(self, data: bytes) -> None:
        assert self._fd is not None
        view = memoryview(data)
        try:
            while view:
                view = view[os.write(self._fd, view) :]
        except BaseException:
            # A half-written record (disk full, interrupt) would read as damage in the middle of the
            # chunk once later records follow it; cut it off so the chunk stays a clean sequence.
            try:
                os.ftruncate(self._fd, self._offset)
            except OSError:
                pass
            raise
        self._offset += len(data)


def _lock(root: Path) -> int:
    fd = os.open(root / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        # The kernel releases flock when the holder dies, so a killed writer never blocks --resume.
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        os.close(fd)
        raise DatasetError(
            f"{root} is being written by another DatasetWriter ({root / LOCK_FILE} is locked)"
        ) from e
    return fd


def _open_or_create_meta(
    root: Path, wanted: dict[str, Any], user_meta: dict[str, Any] | None
) -> dict[str, Any]:
    meta_path = root / META_FILE
    if meta_path.exists():
        meta = read_meta(root)
        for key in META_KEYS:
            if meta[key] != wanted[key]:
                raise DatasetMismatch(
                    f"{key}={wanted[key]!r} does not match {meta[key]!r} recorded in {meta_path}; "
                    "continue a dataset with the same settings, or write to a new directory", key
                )
        if user_meta is not None and meta["metadata"] != user_meta:
            raise ValueError(
                f"metadata={user_meta!r} differs from the metadata in {meta_path} (written once); "
                "pass metadata=None to continue this dataset"
            )
        return meta
    _refuse_foreign_directory(root)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        **wanted,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "metadata": user_meta or {},
    }
    _write_json_atomic(meta_path, meta)
    return meta


def _refuse_foreign_directory(root: Path) -> None:
    if not root.is_dir() or (root / META_FILE).exists():
        return
    ours = {LOCK_FILE, META_FILE + ".tmp"}  # leftovers of a writer killed before meta.json existed
    foreign = sorted(p.name for p in root.iterdir() if p.name not in ours)
    if foreign:
        raise ValueError(
            f"{root} is not empty and has no {META_FILE}, so it is not a twinrl dataset "
            f"(found {', '.join(foreign[:5])}); choose a new or empty directory"
        )


def _resume_point(root: Path) -> tuple[int, int]:
    """Next session number and next episode id for a writer continuing the dataset at ``root``."""
    chunks = list_chunks(root)
    session = max((s for s, _, _, _ in chunks), default=-1) + 1
    # Episode ids grow with (session, chunk), so the newest chunk with a readable record holds the
    # largest; reading backwards avoids scanning a whole (possibly huge) dataset on --resume.
    for _, _, is_open, file in reversed(chunks):
        try:
            data = file.read_bytes()
        except OSError:
            continue
        ids = [
            h["episode"]
            for _, h, _ in scan_chunk(file, data, not is_open, [])
            if isinstance(h.get("episode"), int)
        ]
        if ids:
            return session, max(ids) + 1
    return session, 0


def _write_json_atomic(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=2)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
    # The directory entry of a new or renamed file is durable only once the directory is fsync'd.
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
