"""Minari datasets both ways: a twinrl dataset written as a Minari dataset, and a Minari dataset,
twinrl's own or anyone's, read back as a twinrl ``Dataset``.

Minari (Farama's format for offline-RL data) is an optional extra, imported only when one of these
functions runs: ``pip install 'twinrl[minari]'`` (minari and h5py, its HDF5 storage).

Where Minari keeps datasets
---------------------------
A dataset id is ``(namespace/)name-vN``; the dataset lives in ``ROOT/<id>/data``. ``ROOT`` is the
``root`` argument, else ``$MINARI_DATASETS_PATH``, else ``~/.minari/datasets`` (Minari's own
default). An id given without ``-vN`` means ``-v0`` when writing and the highest local version
when reading.

A twinrl dataset in Minari's terms (``to_minari``)
--------------------------------------------------
* Each twinrl episode is one Minari episode: ``observations`` are its ``obs`` followed by the last
  ``next_obs`` (T+1 rows, Minari's convention), ``actions``, ``rewards``, ``terminations`` and
  ``truncations`` its T transitions', in their recorded dtypes (the spaces are ``Box``es of the
  recorded dtypes; actions of a registered task in its twin's ``[-1, 1]``). Where an episode's
  ``next_obs`` is not the next transition's ``obs`` (records lost to damage), it is cut there into
  several Minari episodes, each a consistent sequence; the reader joins them again.
* Per step, in ``infos`` (T+1 rows, row ``t + 1`` belonging to transition ``t``, row 0 to the
  reset, which twinrl does not record: filled with -1, NaN, ``""`` and zeros):
  ``infos["twinrl"]`` holds ``episode`` and ``step`` (the twinrl ids), ``time`` (wall clock) and
  ``info`` (each transition's info dict as JSON); ``infos["images"]`` the recorded RGB, depth and
  segmentation frames (``rgb/wrist`` stored as ``rgb:wrist``), raw, never JPEG-encoded.
* The dataset's metadata ``twinrl`` holds the task, the real twin's *public* seed(s) (what
  ``twinrl collect --seed`` was given: never its hidden perturbation), the original ``meta.json``
  and each episode's completeness.

Reading a Minari dataset (``read_minari``)
------------------------------------------
A dataset twinrl wrote reads back exactly as it was recorded (values, dtypes, episode ids, steps,
times, infos, images, completeness, ``meta``). Anyone else's is read where its spaces fit a task:
one ``Box`` observation the size of the task's observation (or of its full state, recorded then as
``metadata["observation"] = "state"``, what ``twinrl sysid`` needs where the task's observation
does not determine the state), a ``Box`` action of the task's shape in ``[-1, 1]``; each Minari
episode is one twinrl episode (id = its Minari id, steps from 0, time NaN, scalar infos kept per
transition), complete when its last step terminated or truncated. Anything else is refused with
``DatasetMismatch`` naming what does not fit.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from twinrl.real.dataset._checks import DatasetError, DatasetMismatch, check_real_dtype
from twinrl.real.dataset._format import FORMAT, IMAGE_DTYPES, META_FILE, VERSION
from twinrl.real.dataset.reader import Dataset, read

__all__ = ["MinariUnavailable", "PREFIX", "minari_root", "dataset_id", "find_dataset",
           "to_minari", "read_minari", "fit_task", "import_minari", "export_metadata"]

PREFIX = "minari:"
"""How the command line names a Minari dataset where it also takes a directory:
``--from minari:NAME``."""

_EXTRA = "Minari datasets need the `minari` extra: pip install 'twinrl[minari]' (minari, h5py)"
_ID_RE = re.compile(r"^(?:(?P<ns>[-_\w][-_\w/]*[-_\w]+)/)?(?P<name>[-_\w]+?)(?:-v(?P<v>\d+))?$")


class MinariUnavailable(DatasetError, ImportError):
    """The ``minari`` extra is not installed; the message says what to install."""


def _minari():
    try:
        import minari
    except ImportError:
        raise MinariUnavailable(_EXTRA) from None
    return minari


def minari_root(root: str | os.PathLike[str] | None = None) -> Path:
    """Where Minari datasets live: ``root``, else ``$MINARI_DATASETS_PATH``, else
    ``~/.minari/datasets`` (Minari's default)."""
    if root is not None:
        return Path(root).expanduser()
    env = os.environ.get("MINARI_DATASETS_PATH")
    return Path(env) if env else Path.home() / ".minari" / "datasets"


@contextlib.contextmanager
def _datasets_path(root: Path) -> Iterator[None]:
    # Minari finds its datasets through this variable alone (read at every call).
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def dataset_id(name: str) -> str:
    """``name`` as a full Minari id (``-v0`` added when it has no version); ``DatasetError``
    for a name Minari would not accept."""
    name = str(name).removeprefix(PREFIX)
    m = _ID_RE.fullmatch(name)
    if not m:
        raise DatasetError(f"{name!r} is not a Minari dataset id: expected (namespace/)name-vN "
                           f"of letters, digits, '-' and '_'")
    return name if m["v"] is not None else f"{name}-v0"


def _local_ids(root: Path) -> list[str]:
    if not root.is_dir():
        return []
    return sorted(p.parent.parent.relative_to(root).as_posix()
                  for p in root.rglob("data/metadata.json"))


def find_dataset(name: str, root: str | os.PathLike[str] | None = None) -> tuple[str, Path]:
    """``(id, data directory)`` of the local Minari dataset ``name`` (without ``-vN``: its highest
    version); ``DatasetError`` listing the local datasets when there is none."""
    base = minari_root(root)
    name = str(name).removeprefix(PREFIX)
    full = dataset_id(name)
    if _ID_RE.fullmatch(name)["v"] is None:
        versions = {int(m[1]): i for i in _local_ids(base)
                    if (m := re.fullmatch(rf"{re.escape(name)}-v(\d+)", i))}
        if versions:
            full = versions[max(versions)]
    data = base / full / "data"
    if not (data / "metadata.json").is_file():
        have = _local_ids(base)
        listing = ", ".join(have[:8]) + (" ..." if len(have) > 8 else "") if have else "none"
        raise DatasetError(f"no Minari dataset {full!r} in {base} (local datasets: {listing}; "
                           f"set MINARI_DATASETS_PATH or --minari-root for another place)")
    return full, data


def export_metadata(name: str, root: str | os.PathLike[str] | None = None) -> dict | None:
    """The ``twinrl`` metadata of the local Minari dataset ``name`` when twinrl wrote it (``task``,
    ``twin_seed``, ``twin_seeds``, the original ``meta``), else None."""
    _, path = find_dataset(name, root)
    try:
        ours = json.loads((path / "metadata.json").read_text(encoding="utf-8")).get("twinrl")
    except (OSError, ValueError, AttributeError) as e:
        raise DatasetError(f"{path / 'metadata.json'} is unreadable: {e}") from None
    return ours if isinstance(ours, dict) and ours.get("format") == FORMAT else None


# -- twinrl -> Minari --------------------------------------------------------------------------

def _box(shape: Sequence[int], dtype: np.dtype, bound: float | None):
    import gymnasium as gym

    if dtype.kind == "b":
        return gym.spaces.Box(False, True, tuple(shape), dtype)
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        return gym.spaces.Box(info.min, info.max, tuple(shape), dtype)
    b = np.inf if bound is None else bound
    return gym.spaces.Box(-b, b, tuple(shape), dtype)


def _chains(data: Dataset, a: int, b: int) -> list[tuple[int, int]]:
    """``[a, b)`` cut where a transition's ``next_obs`` is not (bit for bit) the next one's
    ``obs``: Minari stores one observation sequence per episode."""
    if b - a < 2:
        return [(a, b)]
    n = b - a - 1
    nxt = np.ascontiguousarray(data.next_obs[a:b - 1]).reshape(n, -1).view(np.uint8)
    obs = np.ascontiguousarray(data.obs[a + 1:b]).reshape(n, -1).view(np.uint8)
    cuts = (a + 1 + np.flatnonzero((nxt != obs).any(axis=1))).tolist()
    edges = [a, *cuts, b]
    return list(zip(edges[:-1], edges[1:]))


def _with_reset_row(x: np.ndarray, fill) -> np.ndarray:
    return np.concatenate([np.full((1, *x.shape[1:]), fill, x.dtype), x])


def _buffers(data: Dataset):
    from minari.data_collector import EpisodeBuffer

    out = []
    for a0, b0 in zip(data.episode_starts.tolist(), data.episode_ends.tolist()):
        for a, b in _chains(data, a0, b0):
            infos: dict[str, Any] = {"twinrl": {
                "episode": _with_reset_row(data.episode_id[a:b], data.episode_id[a]),
                "step": _with_reset_row(data.step[a:b], -1),
                "time": _with_reset_row(data.time[a:b], np.nan),
                "info": ["", *(json.dumps(i, separators=(",", ":")) for i in data.info[a:b])],
            }}
            if data.images:
                infos["images"] = {k.replace("/", ":"): _with_reset_row(v[a:b], 0)
                                   for k, v in data.images.items()}
            out.append(EpisodeBuffer(
                observations=np.concatenate([data.obs[a:b], data.next_obs[b - 1:b]]),
                actions=data.action[a:b], rewards=data.reward[a:b],
                terminations=data.terminated[a:b], truncations=data.truncated[a:b],
                infos=infos))
    return out


def to_minari(data: Dataset | str | os.PathLike[str], name: str, *,
              root: str | os.PathLike[str] | None = None,
              twin_seeds: Sequence[int] = (), description: str | None = None) -> Path:
    """Writes ``data`` (a ``Dataset``, or a dataset directory, read strictly) as the Minari
    dataset ``name``; returns its data directory.

    ``twin_seeds``: the public seed(s) of the real twin(s) the data was recorded on (``twinrl
    collect --seed``), stored in the metadata for whoever reads it back. Refuses (``DatasetError``)
    a name that exists, and removes what it wrote when writing fails.
    """
    minari = _minari()
    if not isinstance(data, Dataset):
        data = read(data)
    if not len(data):
        raise DatasetError(f"{data.path} holds no transitions: nothing to export")
    full = dataset_id(name)
    base = minari_root(root)
    target = base / full
    if target.exists():
        raise DatasetError(f"Minari dataset {full!r} already exists in {base}; choose another "
                           f"name or version (-vN), or delete it (minari delete {full})")
    meta = data.meta
    from twinrl.envs import names

    task = meta["env"]
    bound = 1.0 if task in names() else None  # a task's real twin acts in [-1, 1]
    seeds = sorted({int(s) for s in twin_seeds})
    complete = dict(zip(data.episode_id[data.episode_starts].tolist(),
                        data.episode_complete.tolist()))
    info = {"format": FORMAT, "version": VERSION, "task": task,
            "twin_seed": seeds[0] if len(seeds) == 1 else None, "twin_seeds": seeds,
            "meta": meta,
            "episodes": {"id": list(complete), "complete": list(complete.values())}}
    about = description or (f"twinrl dataset of task {task}: {len(data)} transitions in "
                            f"{data.num_episodes} episodes recorded on its real twin"
                            + (f" (seed {', '.join(map(str, seeds))})" if seeds else ""))
    try:
        obs_space = _box(meta["obs_shape"], data.obs.dtype, None)
        act_space = _box(meta["action_shape"], data.action.dtype, bound)
        buffers = _buffers(data)
        with _datasets_path(base), warnings.catch_warnings():
            # Minari warns of every optional field left out (author, code permalink, ...).
            warnings.simplefilter("ignore", UserWarning)
            out = minari.create_dataset_from_buffers(
                full, buffers, observation_space=obs_space, action_space=act_space,
                algorithm_name="twinrl", description=about, data_format="hdf5",
                jpeg_encoding=False)
            out.storage.update_metadata({"twinrl": info})
    except BaseException:
        shutil.rmtree(target, ignore_errors=True)
        raise
    return Path(out.storage.data_path)


# -- Minari -> twinrl --------------------------------------------------------------------------

def fit_task(task: str, observation_space, action_space, where: str = "the Minari dataset") -> str:
    """Which observation of ``task`` the spaces fit: ``"task"`` (the task's observation) or
    ``"state"`` (its full qpos and qvel); ``DatasetMismatch`` naming what does not fit."""
    import gymnasium as gym

    from twinrl import envs

    if task not in envs.names():
        raise DatasetMismatch(f"unknown task {task!r}; registered tasks are "
                              f"{', '.join(envs.names())}", "env")
    for kind, space in (("observation", observation_space), ("action", action_space)):
        if not isinstance(space, gym.spaces.Box):
            raise DatasetMismatch(
                f"{where}'s {kind} space is {type(space).__name__} ({space}); twinrl datasets "
                f"hold one Box {kind} (flatten it first, e.g. gymnasium.wrappers.Flatten"
                f"{'Observation' if kind == 'observation' else ''})", f"{kind}_space")
    env = envs.make(task)
    shapes = {"task": (env.observation_size,)}
    with contextlib.suppress(TypeError, ValueError):
        shapes["state"] = (envs.make(task, observation="state").observation_size,)
    fits = [k for k, s in shapes.items() if s == tuple(observation_space.shape)]
    if not fits:
        state = f" nor its full state {shapes['state']}" if "state" in shapes else ""
        raise DatasetMismatch(
            f"{where}'s observation shape {tuple(observation_space.shape)} fits neither "
            f"{task}'s observation {shapes['task']}{state}", "obs_shape")
    if tuple(action_space.shape) != (env.action_size,):
        raise DatasetMismatch(f"{where}'s action shape {tuple(action_space.shape)} is not "
                              f"{task}'s ({env.action_size},)", "action_shape")
    if not (np.all(action_space.low == -1.0) and np.all(action_space.high == 1.0)):
        raise DatasetMismatch(
            f"{where}'s action bounds [{np.min(action_space.low):g}, "
            f"{np.max(action_space.high):g}] are not {task}'s [-1, 1] (actions normalised to "
            f"the actuators' ranges)", "action_space")
    return fits[0]


def _twinrl_rows(ep, T: int, where: str) -> dict[str, Any] | None:
    """The twinrl per-step columns of a Minari episode twinrl wrote (reset row dropped)."""
    rows = (ep.infos or {}).get("twinrl")
    if rows is None:
        return None
    try:
        out = {k: np.asarray(rows[k])[1:] for k in ("episode", "step", "time", "info")}
        if any(len(v) != T for v in out.values()):
            raise ValueError(f"{T + 1} rows expected")
        out["info"] = [json.loads(s.decode() if isinstance(s, bytes) else s) for s in out["info"]]
    except (KeyError, ValueError, TypeError) as e:
        raise DatasetError(f"{where}: malformed infos['twinrl'] ({e})") from None
    return out


def _scalar_infos(infos: dict | None, T: int) -> list[dict[str, Any]]:
    """Per transition, the foreign infos that are one number per step (row ``t + 1``)."""
    cols = {k: v for k, v in (infos or {}).items()
            if isinstance(v, np.ndarray) and v.shape == (T + 1,) and v.dtype.kind in "biuf"}
    return [{k: v[t + 1].item() for k, v in cols.items()} for t in range(T)]


def read_minari(name: str, *, root: str | os.PathLike[str] | None = None,
                task: str | None = None) -> Dataset:
    """The local Minari dataset ``name`` as a twinrl ``Dataset`` (see the module docstring).

    ``task``: the twinrl task it must be of (twinrl's own export: default the one it recorded)
    or fit (anyone else's: required); a dataset twinrl wrote for another task, or spaces that do
    not fit, raise ``DatasetMismatch`` with a one-line reason; a missing dataset
    ``DatasetError`` listing the local ones.
    """
    minari = _minari()
    full, path = find_dataset(name, root)
    where = f"Minari dataset {full}"
    try:
        mds = minari.MinariDataset(path)
    except (ValueError, KeyError, OSError, AssertionError) as e:
        raise DatasetError(f"{where} cannot be read by Minari: {e}") from None
    ours = mds.storage.metadata.get("twinrl")
    ours = ours if isinstance(ours, dict) and ours.get("format") == FORMAT else None
    recorded = ours["task"] if ours else None
    if task is not None and recorded is not None and task != recorded:
        raise DatasetMismatch(f"{where} was recorded on {recorded!r}, not {task!r}", "env")
    if ours is None and task is None:
        raise DatasetMismatch(f"{where} was not written by twinrl, so it names no twinrl task: "
                              f"give the task it fits (--env)", "env")
    # twinrl's own export says what it holds (any env, even one no task registers); anyone
    # else's must fit the task
    kind = None if ours else fit_task(task, mds.observation_space, mds.action_space, where)
    obs_dtype = check_real_dtype("observation dtype", mds.observation_space.dtype)
    act_dtype = check_real_dtype("action dtype", mds.action_space.dtype)
    if ours:
        meta = ours["meta"]
        image_keys = list(meta["image_shapes"])
        done = dict(zip(ours["episodes"]["id"], ours["episodes"]["complete"]))
    else:
        meta = {"format": FORMAT, "version": VERSION, "env": task,
                "obs_shape": list(mds.observation_space.shape), "obs_dtype": obs_dtype.str,
                "action_shape": list(mds.action_space.shape), "action_dtype": act_dtype.str,
                "image_shapes": {}, "created": None,
                "metadata": {"source": f"{PREFIX}{full}",
                             **({"observation": "state"} if kind == "state" else {})}}
        image_keys, done = [], {}

    cols: dict[str, list] = {k: [] for k in ("obs", "action", "reward", "next_obs", "terminated",
                                             "truncated", "episode_id", "step", "time")}
    infos: list[dict[str, Any]] = []
    images: dict[str, list] = {k: [] for k in image_keys}
    for ep in mds.iterate_episodes():
        here = f"{where}, episode {ep.id}"
        T = len(ep.rewards)
        obs = np.asarray(ep.observations)
        if obs.shape[0] != T + 1:
            raise DatasetError(f"{here}: {obs.shape[0]} observations for {T} steps; Minari "
                               f"episodes hold T+1 (the last next observation included)")
        rows = _twinrl_rows(ep, T, here) if ours else None
        cols["obs"].append(obs[:-1])
        cols["next_obs"].append(obs[1:])
        cols["action"].append(np.asarray(ep.actions).reshape(T, *mds.action_space.shape))
        cols["reward"].append(np.asarray(ep.rewards, np.float64).reshape(T))
        cols["terminated"].append(np.asarray(ep.terminations, bool).reshape(T))
        cols["truncated"].append(np.asarray(ep.truncations, bool).reshape(T))
        if rows is not None:
            cols["episode_id"].append(rows["episode"].astype(np.int64))
            cols["step"].append(rows["step"].astype(np.int64))
            cols["time"].append(rows["time"].astype(np.float64))
            infos += rows["info"]
            for k in image_keys:
                try:
                    frames = np.asarray(ep.infos["images"][k.replace("/", ":")])[1:]
                except KeyError:
                    raise DatasetError(f"{here}: the {k!r} images are missing") from None
                images[k].append(frames.astype(IMAGE_DTYPES[k.split("/", 1)[0]], copy=False))
        else:
            cols["episode_id"].append(np.full(T, ep.id, np.int64))
            cols["step"].append(np.arange(T, dtype=np.int64))
            cols["time"].append(np.full(T, np.nan))
            infos += _scalar_infos(ep.infos, T)

    def cat(parts: list, shape, dtype) -> np.ndarray:
        return np.concatenate(parts) if parts else np.empty((0, *shape), dtype)

    arrays = {k: cat(v, (), np.float64) for k, v in cols.items()}
    for k, shape, dtype in (("obs", meta["obs_shape"], obs_dtype),
                            ("next_obs", meta["obs_shape"], obs_dtype),
                            ("action", meta["action_shape"], act_dtype)):
        arrays[k] = cat(cols[k], shape, dtype).astype(dtype, copy=False)
    ids = arrays["episode_id"]
    # Minari episodes of one twinrl episode (cut where records were lost) are adjacent: join them.
    edges = np.flatnonzero(np.diff(ids) != 0) + 1 if len(ids) else np.empty(0, np.int64)
    starts = np.concatenate([[0], edges]).astype(np.int64) if len(ids) else edges
    ends = np.concatenate([edges, [len(ids)]]).astype(np.int64) if len(ids) else edges

    def complete(a: int, b: int) -> bool:
        eid = int(ids[a])
        if eid in done:
            return bool(done[eid])
        steps = arrays["step"][a:b]
        return bool(np.array_equal(steps, np.arange(b - a))
                    and (arrays["terminated"][b - 1] or arrays["truncated"][b - 1]))

    return Dataset(
        path=path, meta=meta, obs=arrays["obs"], action=arrays["action"],
        reward=arrays["reward"].astype(np.float64), next_obs=arrays["next_obs"],
        terminated=arrays["terminated"].astype(bool), truncated=arrays["truncated"].astype(bool),
        episode_id=ids.astype(np.int64), step=arrays["step"].astype(np.int64),
        time=arrays["time"].astype(np.float64), info=infos,
        images={k: cat(v, meta["image_shapes"][k], IMAGE_DTYPES[k.split("/", 1)[0]])
                for k, v in images.items()},
        episode_starts=starts, episode_ends=ends,
        episode_complete=np.array([complete(a, b) for a, b in zip(starts.tolist(),
                                                                     ends.tolist())], bool),
        problems=[])


def import_minari(name: str, path: str | os.PathLike[str], *, task: str,
                  root: str | os.PathLike[str] | None = None, data: Dataset | None = None
                  ) -> Dataset:
    """Writes the Minari dataset ``name`` (read as ``read_minari`` reads it, or ``data`` when
    already read) into a new twinrl dataset directory ``path`` with ``DatasetWriter``, its
    metadata naming the source (``metadata["source"] = "minari:ID"``); returns what it read.

    Values, dtypes, infos, images and episode boundaries are kept; times are the import's (the
    writer stamps each transition), and an episode that was not complete is ended. ``path`` must
    not hold a dataset yet.
    """
    from twinrl.real.dataset.writer import DatasetWriter

    if (Path(path) / META_FILE).exists():
        raise DatasetError(f"{path} already holds a dataset; import into a new directory")
    data = data if data is not None else read_minari(name, root=root, task=task)
    full, _ = find_dataset(name, root)
    meta = data.meta
    with DatasetWriter(path, env=task, obs_shape=meta["obs_shape"],
                       action_shape=meta["action_shape"], image_shapes=meta["image_shapes"],
                       obs_dtype=meta["obs_dtype"], action_dtype=meta["action_dtype"],
                       metadata={**meta["metadata"], "source": f"{PREFIX}{full}"},
                       sync="episode") as writer:
        for ep in data.episodes():
            for t in range(len(ep)):
                writer.add(ep.obs[t], ep.action[t], ep.reward[t], ep.next_obs[t],
                           ep.terminated[t], ep.truncated[t], info=ep.info[t],
                           images={k: v[t] for k, v in ep.images.items()})
            writer.end_episode()  # a no-op after a terminal step
    return data
