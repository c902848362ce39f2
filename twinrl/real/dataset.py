"""Durable, append-only recording of real-robot transitions, and the reader that gives them back.

What it is for
--------------
Everything the loop learns about the real system comes from transitions recorded on it: sysid
fits ``PhysParams`` to them, visual real2sim fits cameras and objects to their images, sim2real
trains the residual policy and refits the hybrid dynamics on them (ARCHITECTURE.md, "The loop, as
data"). Real rollouts are the expensive resource, and a collection run can die at any moment
(e-stop, OOM killer, a pre-empted job, SIGKILL). So every transition is made durable *as it
happens*: a process killed mid-episode leaves a readable dataset that has lost at most the
transition being written, and ``DatasetWriter`` on the same directory continues it
(``twinrl collect --resume``).

Format, and why
---------------
A dataset is a directory::

    meta.json                     written once, atomically (tmp file, fsync, os.replace)
    chunk-SSSSS-CCCCC.twr         closed chunk C of writer session S
    chunk-SSSSS-CCCCC.twr.open    chunk being written, or left behind by a killed writer
    .lock                         flock(2) held by the one live writer

A chunk is an 8-byte file magic followed by self-delimiting records::

    prefix, 28 bytes little-endian: b"TRec" | header length u32 | body length u64
                                    | header crc32 | body crc32 | crc32 of these 24 bytes
    header: UTF-8 JSON (kind, episode, step, time, reward, flags, info, array names/dtypes/shapes)
    body:   raw little-endian bytes of the arrays (obs, action, next_obs, images), in header order

Why this rather than the alternatives:

* **One record, one write, nothing rewritten.** ``add`` builds a whole record and hands it to the
  kernel with ``os.write`` on an unbuffered descriptor before returning, so a completed ``add``
  survives SIGKILL in every ``sync`` mode; ``sync`` only decides when ``os.fsync`` also makes it
  survive power loss (every transition, every episode end, or never). Bytes once written are never
  touched again, so a crash can only leave a torn tail.
* **Self-delimiting and checksummed.** The prefix's own CRC makes the lengths trustworthy; the
  header and body CRCs catch torn or flipped bytes. A torn tail is recognised and dropped; a
  damaged record in the middle is skipped and the reader resynchronises on the next valid prefix,
  so every intact transition is still returned.
* **"Closed" and "killed" are told apart.** A chunk is renamed from ``.twr.open`` to ``.twr`` only
  after its footer (its record count) is written. A torn tail in an ``.open`` chunk is the expected
  trace of a killed writer and is not an error; a ``.twr`` chunk without its footer, or whose count
  disagrees, was damaged afterwards and is reported, naming the file.
* **Chunks** bound the memory a reader needs per file and what one bad file can cost; every writer
  session starts a new chunk, so a resumed run never appends behind a torn tail.
* **No new dependency, no pickle.** JSON plus raw arrays, readable from any language. HDF5 (h5py,
  and Minari's default storage) updates its metadata in place, so a writer killed mid-flush can
  leave the whole file unreadable; ``.npz`` is a zip whose directory is written last, at close.

Episodes: an ``add`` with ``terminated`` or ``truncated`` ends the episode, ``end_episode()`` ends
it without either (an ``end`` marker record). An episode is *complete* when its steps run 0..n-1
without a gap and it was ended; the episode a killed or closed writer left open is returned,
flagged incomplete.
"""

from __future__ import annotations

import dataclasses
import datetime
import fcntl
import json
import math
import os
import re
import struct
import time
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

__all__ = ["Dataset", "DatasetError", "DatasetMismatch", "DatasetWriter", "Episode", "read",
           "IMAGE_DTYPES", "VERSION"]

FORMAT = "twinrl.real.dataset"
VERSION = 1
META_FILE = "meta.json"
LOCK_FILE = ".lock"
FILE_MAGIC = b"TWRLDS\x00\x01"
RECORD_MAGIC = b"TRec"
_PREFIX = struct.Struct("<4sIQII")  # magic, header length, body length, header crc, body crc
_PREFIX_CRC = struct.Struct("<I")
PREFIX_SIZE = _PREFIX.size + _PREFIX_CRC.size
# A header this long is damage that happens to pass the prefix CRC check, not a real header.
_MAX_HEADER = 1 << 24
_CHUNK_RE = re.compile(r"^chunk-(\d{5,})-(\d{5,})\.twr(\.open)?$")

IMAGE_DTYPES: dict[str, np.dtype] = {
    "rgb": np.dtype(np.uint8),
    "depth": np.dtype("<f4"),
    "segmentation": np.dtype("<i4"),
}
"""Image kinds and their stored dtypes; an image key is a kind, optionally ``kind/camera``."""

Sync = Literal["transition", "episode", "none"]
_SYNC_MODES = ("transition", "episode", "none")
_META_KEYS = ("env", "obs_shape", "obs_dtype", "action_shape", "action_dtype", "image_shapes")


class DatasetError(Exception):
    """A dataset directory is missing, corrupt, truncated or busy; the message names the file.

    ``problems`` lists every problem found (each naming its file), when there were several.
    """

    def __init__(self, message: str, problems: Sequence[str] = ()):
        super().__init__(message)
        self.problems = list(problems) or [message]


class DatasetMismatch(ValueError):
    """Continuing a dataset with other settings than it was recorded with; ``key`` names the
    setting (``"image_shapes"``, ``"obs_shape"``, ...), the message both values and the file."""

    def __init__(self, message: str, key: str):
        super().__init__(message)
        self.key = key


# --------------------------------------------------------------------------------------------------
# Writing


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
            "obs_shape": list(_shape("obs_shape", obs_shape)),
            "obs_dtype": _real_dtype("obs_dtype", obs_dtype).str,
            "action_shape": list(_shape("action_shape", action_shape)),
            "action_dtype": _real_dtype("action_dtype", action_dtype).str,
            "image_shapes": _image_shapes(image_shapes or {}),
        }
        if metadata is not None and not isinstance(metadata, Mapping):
            raise ValueError(
                f"metadata has type {type(metadata).__name__}; expected a dict or None"
            )
        user_meta = None if metadata is None else _json_safe(dict(metadata), "metadata")

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
        obs_a = _array("obs", obs, self._obs_shape, self._obs_dtype, "same_kind", finite=True)
        action_a = _array(
            "action", action, self._action_shape, self._action_dtype, "same_kind", finite=True
        )
        next_a = _array(
            "next_obs", next_obs, self._obs_shape, self._obs_dtype, "same_kind", finite=True
        )
        reward_f = _finite_scalar("reward", reward)
        term = _flag("terminated", terminated)
        trunc = _flag("truncated", truncated)
        if info is not None and not isinstance(info, Mapping):
            raise ValueError(f"info has type {type(info).__name__}; expected a dict or None")
        info_j = _json_safe(dict(info or {}), "info")
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
        record = _encode_record(header, arrays)

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
            _encode_record({"kind": "end", "episode": self._episode, "steps": self._step}, [])
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
            out[key] = _array(
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
        self._write(_encode_record({"kind": "footer", "records": self._chunk_records}, []))
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
        meta = _read_meta(root)
        for key in _META_KEYS:
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
    chunks = _list_chunks(root)
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
            for _, h, _ in _scan_chunk(file, data, not is_open, [])
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


def _encode_record(header: dict[str, Any], arrays: list[tuple[str, np.ndarray]]) -> bytes:
    if arrays:
        header = {**header, "arrays": [[name, a.dtype.str, list(a.shape)] for name, a in arrays]}
    hbytes = json.dumps(header, separators=(",", ":")).encode("utf-8")
    body = b"".join(a.tobytes() for _, a in arrays)
    prefix = _PREFIX.pack(
        RECORD_MAGIC, len(hbytes), len(body), zlib.crc32(hbytes), zlib.crc32(body)
    )
    return prefix + _PREFIX_CRC.pack(zlib.crc32(prefix)) + hbytes + body


# --------------------------------------------------------------------------------------------------
# Input validation (errors name the field and what is allowed)


def _shape(name: str, value: Any) -> tuple[int, ...]:
    dims = (value,) if isinstance(value, (int, np.integer)) else value
    try:
        out = tuple(int(d) for d in dims)
        ok = all(not isinstance(d, bool) and int(d) == d and int(d) >= 0 for d in dims)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{name}={value!r}; expected a tuple of non-negative integers")
    return out


def _real_dtype(name: str, value: Any) -> np.dtype:
    try:
        dtype = np.dtype(value)
    except TypeError as e:
        raise ValueError(f"{name}={value!r} is not a numpy dtype") from e
    if dtype.kind not in "fiub":
        raise ValueError(f"{name}={dtype}; expected a float, integer or bool dtype")
    return dtype.newbyteorder("<")


def _image_shapes(image_shapes: Mapping[str, Sequence[int]]) -> dict[str, list[int]]:
    out = {}
    for key, shape in image_shapes.items():
        kind = key.split("/", 1)[0] if isinstance(key, str) else None
        if kind not in IMAGE_DTYPES or (isinstance(key, str) and key.endswith("/")):
            raise ValueError(
                f"image_shapes key {key!r}; expected one of {', '.join(IMAGE_DTYPES)}, optionally "
                "followed by /camera (e.g. 'rgb/wrist')"
            )
        dims = _shape(f"image_shapes[{key!r}]", shape)
        rank_ok = len(dims) == 3 and dims[2] == 3 if kind == "rgb" else len(dims) == 2
        if not rank_ok:
            want = "(H, W, 3)" if kind == "rgb" else "(H, W)"
            raise ValueError(f"image_shapes[{key!r}]={dims}; {kind} images have shape {want}")
        out[key] = list(dims)
    return out


def _array(
    name: str,
    value: Any,
    shape: tuple[int, ...],
    dtype: np.dtype,
    casting: str,
    finite: bool = False,
) -> np.ndarray:
    try:
        a = np.asarray(value)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} is not an array: {e}") from e
    if a.shape != shape:
        raise ValueError(f"{name} has shape {a.shape}; expected {shape}")
    if not np.can_cast(a.dtype, dtype, casting=casting):
        raise ValueError(
            f"{name} has dtype {a.dtype}; expected {dtype} (or a dtype that converts {casting})"
        )
    a = np.asarray(a, dtype=dtype, order="C")  # not ascontiguousarray: it makes 0-d arrays 1-d
    if finite and a.dtype.kind == "f" and not np.isfinite(a).all():
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(
            f"{name} is not finite at index {bad} (value {a[bad]}); NaN and inf are not recorded"
        )
    return a


def _finite_scalar(name: str, value: Any) -> float:
    a = np.asarray(value)
    if a.shape != () or a.dtype.kind not in "fiub":
        raise ValueError(f"{name}={value!r}; expected a real scalar")
    out = float(a)
    if not math.isfinite(out):
        raise ValueError(f"{name}={out}; expected a finite number")
    return out


def _flag(name: str, value: Any) -> bool:
    a = np.asarray(value)
    if a.shape == () and a.dtype.kind in "biu" and a.item() in (0, 1):
        return bool(a.item())
    raise ValueError(f"{name}={value!r}; expected a bool")


def _json_safe(value: Any, where: str) -> Any:
    """``value`` with numpy scalars/arrays turned into JSON types; ValueError naming ``where``."""
    if value is None or isinstance(value, (str, bool, int, float)):
        return value
    if isinstance(value, np.ndarray):
        return _json_safe(value.tolist(), where)
    if isinstance(value, np.generic):
        return _json_safe(value.item(), where)
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                # json.dumps would turn the key into a string, so it would not read back as written.
                raise ValueError(
                    f"{where} has key {k!r} of type {type(k).__name__}; keys must be str"
                )
            out[k] = _json_safe(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [_json_safe(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise ValueError(
        f"{where} has type {type(value).__name__}, which is not JSON-serialisable; use str, int, "
        "float, bool, None and lists/dicts of them (numpy scalars and arrays are converted)"
    )


# --------------------------------------------------------------------------------------------------
# Reading


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
    meta = _read_meta(root)
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
    chunks = _list_chunks(root)
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
        for offset, header, body in _scan_chunk(file, data, not is_open, problems):
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


def _read_meta(root: Path) -> dict[str, Any]:
    meta_path = root / META_FILE
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DatasetError(f"no dataset at {root}: {meta_path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(f"{meta_path} is unreadable: {e}") from e
    found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
    if found != FORMAT:
        raise DatasetError(f"{meta_path} is not a {FORMAT} meta file (format={found!r})")
    if meta.get("version") != VERSION:
        raise DatasetError(
            f"{meta_path} has format version {meta.get('version')!r}; "
            f"this reader knows version {VERSION}"
        )
    missing = [k for k in (*_META_KEYS, "metadata") if k not in meta]
    if missing:
        raise DatasetError(f"{meta_path} lacks {', '.join(missing)}")
    try:
        _shape("obs_shape", meta["obs_shape"])
        _shape("action_shape", meta["action_shape"])
        _real_dtype("obs_dtype", meta["obs_dtype"])
        _real_dtype("action_dtype", meta["action_dtype"])
        _image_shapes(meta["image_shapes"])
    except (ValueError, AttributeError) as e:
        raise DatasetError(f"{meta_path}: {e}") from e
    return meta


def _list_chunks(root: Path) -> list[tuple[int, int, bool, Path]]:
    """(session, index, is_open, path) of every chunk file, in recording order."""
    out = []
    for p in root.iterdir():
        m = _CHUNK_RE.match(p.name)
        if m:
            out.append((int(m[1]), int(m[2]), m[3] is not None, p))
    return sorted(out)


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


def _read_prefix(data: bytes, pos: int) -> tuple[int, int, int, int] | None:
    if len(data) - pos < PREFIX_SIZE:
        return None
    magic, hlen, blen, hcrc, bcrc = _PREFIX.unpack_from(data, pos)
    if magic != RECORD_MAGIC or hlen > _MAX_HEADER:
        return None
    (pcrc,) = _PREFIX_CRC.unpack_from(data, pos + _PREFIX.size)
    if pcrc != zlib.crc32(data[pos : pos + _PREFIX.size]):
        return None
    return hlen, blen, hcrc, bcrc


def _resync(data: bytes, start: int) -> int:
    """Offset of the next valid record prefix at or after ``start`` (``len(data)`` if none)."""
    while True:
        i = data.find(RECORD_MAGIC, start)
        if i < 0:
            return len(data)
        if _read_prefix(data, i) is not None:
            return i
        start = i + 1


def _scan_chunk(
    file: Path, data: bytes, closed: bool, problems: list[str]
) -> list[tuple[int, dict[str, Any], memoryview]]:
    """(offset, header, body) of every intact non-footer record; damage is appended to ``problems``.

    ``closed``: the file has the ``.twr`` name, so it must end with a footer; an ``.open`` chunk may
    end in a torn record (a killed writer), which is dropped without a problem.
    """
    view = memoryview(data)
    records: list[tuple[int, dict[str, Any], memoryview]] = []
    footer: dict[str, Any] | None = None
    if data[: len(FILE_MAGIC)] == FILE_MAGIC:
        pos = len(FILE_MAGIC)
    elif not closed and FILE_MAGIC.startswith(data):
        return records  # killed while creating the chunk
    else:
        problems.append(f"{file}: bad file magic (not a twinrl chunk, or its start is damaged)")
        pos = _resync(data, 0)

    def torn(pos: int, why: str) -> None:
        if closed:
            problems.append(f"{file}: truncated: {why}")

    def zero_filled_tail(pos: int) -> bool:
        # Power loss after unsynced appends leaves the file at its new length with the unwritten
        # blocks read back as zeros: an unreadable record at ``pos`` with no record after it, in a
        # file that ends in zero bytes. In an ``.open`` chunk that is a torn tail, not damage.
        return not closed and data[-1:] == b"\0" and _resync(data, pos + 1) == len(data)

    while pos < len(data):
        if footer is not None:
            problems.append(
                f"{file}: {len(data) - pos} unexpected bytes after the footer at offset {pos}"
            )
            break
        remaining = len(data) - pos
        if remaining < PREFIX_SIZE and RECORD_MAGIC.startswith(
            data[pos : pos + min(remaining, len(RECORD_MAGIC))]
        ):
            torn(pos, f"the file ends {remaining} bytes into the record header at offset {pos}")
            break
        prefix = _read_prefix(data, pos)
        if prefix is None and zero_filled_tail(pos):
            break
        if prefix is None:
            nxt = _resync(data, pos + 1)
            problems.append(
                f"{file}: damaged record header at offset {pos}; skipped {nxt - pos} bytes"
            )
            pos = nxt
            continue
        hlen, blen, hcrc, bcrc = prefix
        start = pos + PREFIX_SIZE
        end = start + hlen + blen
        if end > len(data):
            torn(
                pos,
                f"the record at offset {pos} needs {end - pos} bytes, "
                f"the file ends after {remaining}",
            )
            break
        hbytes = data[start : start + hlen]
        body = view[start + hlen : end]
        if zlib.crc32(hbytes) != hcrc or zlib.crc32(body) != bcrc:
            if zero_filled_tail(pos):
                break
            part = "header" if zlib.crc32(hbytes) != hcrc else "body"
            problems.append(
                f"{file}: record at offset {pos} fails its {part} checksum (damaged); skipped"
            )
            pos = end
            continue
        try:
            header = json.loads(hbytes)
            if not isinstance(header, dict):
                raise ValueError("header is not a JSON object")
        except (UnicodeDecodeError, ValueError) as e:
            problems.append(
                f"{file}: record at offset {pos} has an unreadable header ({e}); skipped"
            )
            pos = end
            continue
        if header.get("kind") == "footer":
            footer = header
        else:
            records.append((pos, header, body))
        pos = end

    if footer is None:
        if closed:
            problems.append(f"{file}: no footer: the closed chunk was truncated")
    elif footer.get("records") != len(records):
        problems.append(
            f"{file}: footer counts {footer.get('records')!r} records, {len(records)} are intact"
        )
    return records


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
