"""Checkpoints: a trained policy (orbax params + JSON config) and a resumable training state.

**Policy checkpoint** (``save_policy`` / ``load_policy``), a directory::

    checkpoint.json   format, what it is (``kind``, one of ``KINDS``), network (kind, in/out
                      sizes, NetworkConfig, and the observation spec when it is a dict of keys
                      to shapes), algo, env name and its config overrides, the trainer's
                      config, final metrics
    system.json       the ``twinrl.envs.System`` the policy was trained in (parameters, action
                      latency, ...): evaluation rebuilds exactly that simulator (``load_system``)
    params/           orbax StandardCheckpointer tree of the network parameters

``load_policy(dir)`` rebuilds the network from the JSON alone (Brax's habit: params + a JSON
network config), so a policy can be evaluated, deployed on the real twin, or used as the base of a
residual policy without the training code. Brax PPO's and APG's normalised policies are rebuilt by
``twinrl.learn.baselines.NETWORK_KINDS`` (imported on first use); other kinds register a builder
with ``register_network_kind``.

**Training state** (``TrainStateCheckpointer``): the trainer's whole state (params, optimiser state,
rng, counters; ``twinrl.learn.common``) and its metric history, saved together by an orbax
``CheckpointManager`` after every epoch (or every ``every`` epochs). Orbax writes each step into a
temporary directory and renames it when complete, so a run killed at any moment leaves the last
complete step; ``restore(template)`` continues from it. PRNG key arrays are stored as their raw key
data and re-wrapped with the template's key implementation.

**Several processes** (``twinrl.learn.distributed``): every process calls the checkpointer (the
state is gathered to NumPy first, a collective), process 0 alone writes, and every process
restores from the same directory (a file system they share); orbax runs on one process at a
time (``MultiprocessingOptions(active_processes={this one})``), so no process waits for another
at a save. What is written is the one-process format: a single process resumes from it.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from twinrl.learn import distributed
from twinrl.learn.networks import Network, NetworkConfig, make_network
from twinrl.report import to_jsonable

__all__ = ["save_policy", "load_policy", "load_system", "register_network_kind",
           "TrainStateCheckpointer", "CheckpointError", "FORMAT", "KINDS", "checkpoint_kind",
           "read_meta"]

FORMAT = "twinrl-policy-1"
SYSTEM_FILE = "system.json"

_BUILDERS: dict[str, Callable[[dict[str, Any]], Network]] = {}

KINDS = {
    "policy": "a policy on the task's observation vector (twinrl train: pods, hds, shac, ppo, "
              "apg, or imitation with observation=state)",
    "image_actor": "an arm task's actor that sees the mount camera (twinrl train --algo "
                   "imitation, or a run's round<r>/actor)",
    "sensing_q": "a sensing-aware Q that scores camera poses (twinrl train --algo sensing, or a "
                 "run's round<r>/q)",
    "residual": "a residual policy: a correction of another policy's action (a run's "
                "round<r>/residual)",
    "hybrid_residual": "a learned residual dynamics model (a run's round<r>/hybrid)",
}
"""What a policy checkpoint holds (``checkpoint.json``'s ``kind``), described in words."""


class CheckpointError(Exception):
    """A checkpoint directory that is missing, incomplete or of an unknown format."""


def register_network_kind(kind: str, builder: Callable[[dict[str, Any]], Network]) -> None:
    """Teach ``load_policy`` to rebuild networks whose JSON says ``"kind": kind``."""
    _BUILDERS[kind] = builder


def _mlp_builder(spec: dict[str, Any]) -> Network:
    # a dict observation spec (camera encoder + MLP) is saved as "obs_spec"; a flat one as in_size
    obs = spec.get("obs_spec")
    obs = int(spec["in_size"]) if obs is None else {k: tuple(v) for k, v in obs.items()}
    return make_network(obs, int(spec["out_size"]), NetworkConfig.from_dict(spec["config"]))


register_network_kind("mlp", _mlp_builder)


def network_spec(policy: Network) -> dict[str, Any]:
    spec = getattr(policy, "spec", None)
    if spec is not None:
        return dict(spec)
    out = {"kind": "mlp", "in_size": policy.in_size, "out_size": policy.out_size,
           "config": policy.config.to_dict()}
    if isinstance(policy.obs_spec, dict):
        out["obs_spec"] = {k: list(shape) for k, shape in policy.obs_spec.items()}
    return out


def save_policy(path: str | Path, policy: Network, params: Any, *, system: Any = None,
                **meta: Any) -> Path:
    """Write a policy checkpoint to ``path`` (created; an existing checkpoint is replaced).

    ``meta`` (algo, env, env_config, config, metrics, ...) goes into ``checkpoint.json`` after
    conversion to JSON (dataclasses become dicts, arrays lists, non-finite floats null);
    ``system`` (a ``twinrl.envs.System``) into ``system.json``, exactly. ``kind`` (one of
    ``KINDS``) says what the checkpoint holds; without it, ``checkpoint_kind`` tells from the
    algorithm and the network's observation.
    """
    import orbax.checkpoint as ocp

    path = Path(path).absolute()
    path.mkdir(parents=True, exist_ok=True)
    leaves = jax.tree.leaves(params)
    if not all(np.all(np.isfinite(np.asarray(x))) for x in leaves):
        raise ValueError("refusing to save a policy with non-finite parameters")
    if distributed.is_distributed():
        params = distributed.to_host(params)
    ckptr = ocp.StandardCheckpointer(**_this_process_only(ocp))
    ckptr.save(path / "params", params, force=True)
    ckptr.wait_until_finished()
    if system is not None:
        system.save(path / SYSTEM_FILE)
    elif (path / SYSTEM_FILE).exists():
        (path / SYSTEM_FILE).unlink()      # a replaced checkpoint keeps no stale system
    doc = {"format": FORMAT, "network": network_spec(policy), **to_jsonable(meta)}
    doc["kind"] = checkpoint_kind(doc)
    tmp = path / "checkpoint.json.tmp"
    tmp.write_text(json.dumps(doc, indent=2, allow_nan=False))
    tmp.replace(path / "checkpoint.json")
    return path


def load_policy(path: str | Path) -> tuple[Network, Any, dict[str, Any]]:
    """``(network, params, meta)`` from a policy checkpoint written by ``save_policy``."""
    import orbax.checkpoint as ocp

    path, meta = read_meta(path)  # a training run's directory holds it under policy/
    meta_file = path / "checkpoint.json"
    spec = meta.get("network")
    if not isinstance(spec, dict):
        raise CheckpointError(f"{meta_file}: no 'network' object (kind, in/out sizes, config); "
                              f"found {spec!r}: the network cannot be rebuilt")
    kind = spec.get("kind", "mlp")
    if not isinstance(kind, str):
        raise CheckpointError(f"{meta_file}: network kind {kind!r} is not a string")
    if kind not in _BUILDERS and kind.startswith("brax"):
        from twinrl.learn.baselines import NETWORK_KINDS  # Brax's imports only when needed
        _BUILDERS.update({k: b for k, b in NETWORK_KINDS.items() if k not in _BUILDERS})
    if kind not in _BUILDERS:
        raise CheckpointError(f"{meta_file}: unknown network kind {kind!r}; "
                              f"known: {sorted(_BUILDERS)}")
    try:
        network = _BUILDERS[kind](spec)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{meta_file}: network {kind!r} cannot be rebuilt from its JSON "
                              f"({type(e).__name__}: {e})") from None
    if not (path / "params").exists():
        raise CheckpointError(f"{path}: params/ missing (checkpoint incomplete)")
    template = jax.eval_shape(network.init, jax.random.key(0))
    # on this process alone: one process of several reads a policy without the others (the loop
    # deploys it from process 0), where orbax's default would wait for every process
    params = ocp.StandardCheckpointer(**_this_process_only(ocp)).restore(path / "params",
                                                                         template)
    return network, params, meta


def checkpoint_kind(meta: dict[str, Any]) -> str:
    """What a policy checkpoint holds, one of ``KINDS``, from its ``checkpoint.json``: its
    ``kind`` when it names one, else (a checkpoint written before kinds were recorded) its
    algorithm's: ``sensing`` a Q, a network that reads a dict observation an image actor, any
    other a policy."""
    kind = meta.get("kind")
    if kind is not None:
        if kind not in KINDS:
            raise CheckpointError(f"checkpoint kind {kind!r} is not one of {', '.join(KINDS)}")
        return kind
    if meta.get("algo") == "sensing":
        return "sensing_q"
    network = meta.get("network")
    if isinstance(network, dict) and network.get("obs_spec") is not None:
        return "image_actor"
    return "policy"


def read_meta(path: str | Path) -> tuple[Path, dict[str, Any]]:
    """``(directory, checkpoint.json)`` of the policy checkpoint at ``path`` (or a training
    run's directory holding it under ``policy/``), its ``kind`` filled in (``checkpoint_kind``),
    without restoring its parameters; a ``CheckpointError`` in one line if there is none."""
    path = _policy_dir(path)
    meta_file = path / "checkpoint.json"
    if not meta_file.exists():
        raise CheckpointError(f"{path}: no checkpoint.json (not a twinrl policy checkpoint)")
    try:
        meta = json.loads(meta_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{meta_file}: not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise CheckpointError(f"{meta_file}: holds a JSON {type(meta).__name__}, expected an "
                              f"object with format, network, env, ...")
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{meta_file}: format {meta.get('format')!r}, expected {FORMAT!r}")
    try:
        meta["kind"] = checkpoint_kind(meta)
    except CheckpointError as e:
        raise CheckpointError(f"{meta_file}: {e}") from None
    return path, meta


def _policy_dir(path: str | Path) -> Path:
    path = Path(path).absolute()
    if not (path / "checkpoint.json").exists() and (path / "policy" / "checkpoint.json").exists():
        path = path / "policy"
    return path


def load_system(path: str | Path):
    """The ``twinrl.envs.System`` a policy checkpoint (or a training run's directory) was trained
    in, or None for a checkpoint written without one (its task's nominal simulator)."""
    from twinrl.envs.system import System, SystemFormatError

    f = _policy_dir(path) / SYSTEM_FILE
    if not f.exists():
        return None
    try:
        return System.load(f)
    except (SystemFormatError, ValueError) as e:
        raise CheckpointError(f"{f}: {e}") from None


def _is_key(x) -> bool:
    return isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _flat(tree) -> dict[str, Any]:
    """The non-empty leaves of ``tree`` by position, PRNG keys as raw key data. Orbax cannot store
    zero-size arrays (an ``mjx.Data`` carries several), and positions keep the saved layout free of
    the trainer's NamedTuple classes."""
    leaves = jax.tree.leaves(tree)
    return {f"{i:05d}": (jax.random.key_data(x) if _is_key(x) else x)
            for i, x in enumerate(leaves) if np.size(x) > 0}


def _unflat(saved: dict[str, Any], template):
    leaves, treedef = jax.tree.flatten(template)
    out = []
    for i, t in enumerate(leaves):
        k = f"{i:05d}"
        if np.size(t) == 0:
            out.append(t)
        elif _is_key(t):
            out.append(jax.random.wrap_key_data(saved[k], impl=jax.random.key_impl(t)))
        else:
            out.append(saved[k])
    return jax.tree.unflatten(treedef, out)


def _this_process_only(ocp) -> dict[str, Any]:
    """Orbax options for a checkpointer that runs on this process alone (``{}`` when not
    distributed: orbax's defaults, unchanged)."""
    if not distributed.is_distributed():
        return {}
    me = jax.process_index()
    return {"multiprocessing_options": ocp.options.MultiprocessingOptions(
        primary_host=me, active_processes={me})}


class _NoSaveWaits(logging.Filter):
    """Drops orbax's "Waiting for previous save to complete took N seconds" warning. A train-state
    save is asynchronous and the next one waits for it: on busy cores that is expected, and it
    printed a line every few saves of a training (the loop's oracle process among them)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Waiting for previous save to complete")


_NO_SAVE_WAITS = _NoSaveWaits()


class _ReaderNotices(logging.Filter):
    """Drops orbax's notices that a directory is read only ("Given directory is read only",
    "... is read only, save will be skipped", "... delete will be skipped") for the directories
    of this process's reading checkpointers: under ``jax.distributed`` every process but the
    writer opens the training state read only on purpose, and orbax warned about it on each of
    them. The same notice about any other directory still shows."""

    NOTICES = ("Given directory is read only=%s", "%s is read only, save will be skipped",
               "%s is read only, delete will be skipped")

    def __init__(self):
        super().__init__()
        self.directories: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args if isinstance(record.args, tuple) else ()
        return not (record.msg in self.NOTICES and len(args) == 1
                    and str(args[0]) in self.directories)


_READER_NOTICES = _ReaderNotices()


class TrainStateCheckpointer:
    """Saves a trainer's state + metrics every ``every`` epochs into ``directory``; restores it.

    Use as the trainer's ``checkpoint_fn`` and (``if ckpt.latest_epoch() is not None``) its
    ``restore``. Keeps the last ``keep`` steps.
    """

    def __init__(self, directory: str | Path, every: int = 1, keep: int = 2):
        import orbax.checkpoint as ocp

        if every < 1:
            raise ValueError(f"every must be >= 1 epoch, got {every}")
        logging.getLogger("absl").addFilter(_NO_SAVE_WAITS)  # addFilter keeps a single copy
        self.directory = Path(directory).absolute()
        self.every = int(every)
        self._ocp = ocp
        self._writer = distributed.is_writer()
        alone = _this_process_only(ocp)
        if not self._writer:
            _READER_NOTICES.directories.add(str(self.directory))
            logging.getLogger("absl").addFilter(_READER_NOTICES)
        if alone and self._writer:  # orbax creates no directory for a subset of processes
            self.directory.mkdir(parents=True, exist_ok=True)
        self._manager = ocp.CheckpointManager(
            self.directory, options=ocp.CheckpointManagerOptions(
                max_to_keep=keep if self._writer else None, create=not alone,
                read_only=not self._writer, **({} if self._writer else {"save_interval_steps": 0}),
                **alone),
            item_names=("state", "metrics"))

    def latest_epoch(self) -> int | None:
        return self._manager.latest_step()

    def __call__(self, epoch: int, state: Any, metrics: dict[str, list[float]],
                 force: bool = False) -> None:
        if not force and (epoch + 1) % self.every:
            return
        ocp = self._ocp
        if distributed.is_distributed():
            state = distributed.to_host(state)  # every process: the gather is a collective
            if not self._writer:
                return
        self._manager.save(int(epoch), args=ocp.args.Composite(
            state=ocp.args.StandardSave(_flat(state)),
            metrics=ocp.args.JsonSave(to_jsonable(metrics))), force=True)
        self._manager.wait_until_finished()

    def restore(self, template: Any) -> tuple[Any, dict[str, list[float]]]:
        step = self.latest_epoch()
        if step is None:
            raise CheckpointError(f"{self.directory}: no saved training state to resume from")
        ocp = self._ocp
        if distributed.is_distributed():  # NumPy on each process; the trainer places it
            abstract = {k: np.zeros(np.shape(v), v.dtype) for k, v in _flat(template).items()}
        else:
            abstract = {k: jax.ShapeDtypeStruct(np.shape(v), v.dtype)
                        for k, v in _flat(template).items()}
        got = self._manager.restore(step, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract), metrics=ocp.args.JsonRestore()))
        return _unflat(got.state, template), dict(got.metrics)

    def close(self) -> None:
        self._manager.close()
