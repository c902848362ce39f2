"""The real twin behind a process boundary, as a robot would be: ``TwinClient``.

Learning code talks to a robot through an interface (observations, actions, camera frames), never
to the physics behind it. ``TwinClient`` is that interface for the real twin: a ``gymnasium.Env``
whose ``RealTwin`` (MuJoCo model, hidden ``Perturbation``, renderer) lives in a server process
started with the ``spawn`` context and reached over a pipe (messages ``reset``, ``step``,
``render``, ``render_images``, ``move_camera``, ``success``, ``close``, and reads of the mount's
``camera_steps`` and ``mount_coords``; nothing else). The client holds the observation and action
spaces, the task's name, time step and episode length, the camera names and image size: what a
robot's driver publishes. It holds no model, perturbation or renderer, so ``client._model`` and
its like raise ``AttributeError`` and nothing reachable from the client is one
(``tests/real/test_remote.py``).

The hidden perturbation is drawn from the public seed *and a secret salt* (128 bits) the server
keeps in ``secret`` (a JSON file in the run's evaluation directory, which the learning stages
never read), created on first use and read back on a resume, so ``Perturbation.sample(task,
seed)`` (the public seed alone) draws a different twin. By default the salt is a keyed hash of
``(task, seed)`` with a key private to this module, so a run is reproducible: the same ``--seed``
meets the same twin on every machine (the README's figures rely on it). ``TWINRL_TWIN_SALT=random``
draws a fresh random salt instead (a twin nobody's code can have seen). Evaluation
(``twinrl.eval``) rebuilds the same twin in-process from that file (``hidden_perturbation``).
``secret=None`` serves the public-seed twin (``make_real(task, seed=seed)``), for tests and
commands that evaluate against a twin named by its seed alone.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import traceback
from pathlib import Path
from typing import Any, Sequence

import gymnasium as gym
import numpy as np

__all__ = ["TwinClient", "TwinServerError", "hidden_perturbation", "secret_file"]


def secret_file(out: str | os.PathLike, task: str, seed: int) -> Path:
    """Where ``twinrl collect --out OUT`` keeps the secret of twin ``(task, seed)``: in
    ``OUT/eval/`` (beside ``OUT/dataset/``, which learning reads)."""
    return Path(out) / "eval" / f"twin-{task}-seed{int(seed)}.json"


class TwinServerError(RuntimeError):
    """The real twin's server failed (its traceback's last line) or died."""


_KEY = b"twinrl real-twin salt: evaluation and the twin server only"


def _salt(task: str, seed: int) -> str:
    """A new twin's salt: keyed hash of (task, seed), or random with TWINRL_TWIN_SALT=random."""
    mode = os.environ.get("TWINRL_TWIN_SALT", "seeded")
    if mode == "random":
        return secrets.token_hex(16)
    if mode != "seeded":
        raise ValueError(f"TWINRL_TWIN_SALT must be 'seeded' (default) or 'random', got {mode!r}")
    return hmac.new(_KEY, f"{task}:{int(seed)}".encode(), hashlib.sha256).hexdigest()[:32]


def _secret_doc(path: Path, task: str, seed: int, perturbation=None) -> dict[str, Any]:
    """The secret file's contents, created (atomically) when missing. A given ``perturbation``
    (a benchmark's custom twin) is stored with it, so a resume with another one is refused."""
    from twinrl.report import to_jsonable, write_json

    given = to_jsonable(perturbation) if perturbation is not None else None
    if path.exists():
        doc = json.loads(path.read_text())
        if (doc.get("task"), doc.get("seed")) != (task, int(seed)) or doc.get(
                "perturbation") != given:
            raise ValueError(f"{path} holds the twin of task {doc.get('task')!r} seed "
                             f"{doc.get('seed')} (perturbation "
                             f"{'given' if doc.get('perturbation') else 'drawn'}), not this one")
        return doc
    doc = {"task": task, "seed": int(seed), "salt": _salt(task, seed), "perturbation": given}
    write_json(path, doc)
    return doc


def hidden_perturbation(task: str, seed: int, secret: str | os.PathLike, perturbation=None):
    """The ``Perturbation`` of the twin ``(task, seed)`` whose salt is in ``secret`` (created if
    missing): ``perturbation`` itself when given (a custom twin), else a draw from the task's
    spec seeded by ``(seed, salt)``. Server and evaluation only."""
    from twinrl.real.perturbation import Perturbation

    doc = _secret_doc(Path(secret), task, seed, perturbation)
    if perturbation is not None:
        return perturbation
    seq = np.random.SeedSequence([int(seed), int(doc["salt"], 16)])
    return Perturbation.sample(task, np.random.default_rng(seq))


# ---------------------------------------------------------------------- the server process
def _serve(conn, parent: int) -> None:
    """The server: receives ``("open", kwargs)``, then requests, until ``close`` or EOF."""
    import signal

    try:  # Linux: die with the client's process (no orphan holding the twin)
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:
        os._exit(1)
    twin = None
    try:
        _, kw = conn.recv()
        from twinrl.real.twin import RealTwin

        secret = kw.pop("secret")
        if secret is not None:
            kw["perturbation"] = hidden_perturbation(kw["task"], kw["seed"], secret,
                                                     kw.get("perturbation"))
        twin = RealTwin(kw.pop("task"), **kw)
        conn.send(("ok", {
            "observation_space": twin.observation_space, "action_space": twin.action_space,
            "metadata": twin.metadata, "dt": float(twin.dt),
            "episode_length": int(twin.task.episode_length),
            "cameras": list(twin.task.cameras), "camera": twin.camera,
            "width": twin.width, "height": twin.height}))
    except BaseException:  # noqa: BLE001 - sent to the client, which raises it
        conn.send(("error", traceback.format_exc()))
        return
    try:
        while True:
            try:
                op, args, kwargs = conn.recv()
            except EOFError:
                return
            if op == "close":
                conn.send(("ok", None))
                return
            try:
                if op == "attr" and args and args[0] in _ATTRS:  # what a robot's driver reports
                    conn.send(("ok", getattr(twin, args[0])))
                elif op in _OPS:
                    conn.send(("ok", getattr(twin, op)(*args, **kwargs)))
                else:
                    raise ValueError(f"the real twin has no operation {op!r}")
            except Exception:  # noqa: BLE001 - a bad request fails that call, not the server
                conn.send(("error", traceback.format_exc()))
    finally:
        twin.close()


_OPS = ("reset", "step", "render", "render_images", "move_camera", "success",
        "calibrate_controller")
"""The requests the server answers (and ``close``); anything else is refused."""
_ATTRS = ("camera_steps", "mount_coords", "joint_speed")
"""The twin's attributes a client may read (``op == "attr"``): the camera mount's odometry."""


class TwinClient(gym.Env):
    """A ``gymnasium.Env`` client of a real twin served in another process.

    Args:
      task: registered task name.
      seed: the twin's public seed (default episode seed; with ``secret``, half of the hidden
        perturbation's seed).
      secret: path of the secret-salt file (see the module docstring); None: the public-seed twin.
      perturbation: a custom ``Perturbation`` applied instead of the drawn one (benchmarks);
        recorded in ``secret`` so a resume with another is refused.
      **twin_kwargs: ``RealTwin``'s (``width``, ``height``, ``shadows``, ``render_mode``, ...).

    Everything else a ``RealTwin`` holds stays in the server: ``reset``/``step``/``render``/
    ``render_images`` are forwarded; an error there raises ``ValueError`` (bad input) or
    ``TwinServerError`` here with the server's message.
    """

    def __init__(self, task: str, *, seed: int = 0, secret: str | os.PathLike | None = None,
                 perturbation=None, **twin_kwargs: Any):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # a fresh interpreter: no fork after JAX's threads
        self.__conn, child = ctx.Pipe()
        self.__proc = ctx.Process(target=_serve, name=f"twinrl-twin-{task}", daemon=True,
                                  args=(child, os.getpid()))
        self.__proc.start()
        child.close()
        # Sent over the pipe, not as Process args: the Process object keeps its args.
        self.__conn.send(("open", {"task": task, "seed": int(seed),
                                   "secret": None if secret is None else str(secret),
                                   "perturbation": perturbation, **twin_kwargs}))
        info = self.__reply()
        self.task_name = task
        self.seed = int(seed)
        self.observation_space = info["observation_space"]
        self.action_space = info["action_space"]
        self.metadata = info["metadata"]
        self.render_mode = twin_kwargs.get("render_mode")
        self.dt = info["dt"]
        self.episode_length = info["episode_length"]
        self.cameras: tuple[str, ...] = tuple(info["cameras"])
        self.camera: str = info["camera"]
        self.width, self.height = info["width"], info["height"]

    def __reply(self):
        try:
            status, value = self.__conn.recv()
        except (EOFError, OSError):
            self.__proc.join(timeout=5)
            raise TwinServerError(f"the real twin's server died (exit code "
                                  f"{self.__proc.exitcode})") from None
        if status == "error":
            last = value.strip().splitlines()[-1]
            if last.startswith("ValueError: "):
                raise ValueError(last[len("ValueError: "):])
            raise TwinServerError(f"the real twin's server failed: {last}")
        return value

    def __call(self, op: str, *args, **kwargs):
        if self.__proc is None:
            raise TwinServerError("the real twin's client is closed")
        self.__conn.send((op, args, kwargs))
        return self.__reply()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        return self.__call("reset", seed=seed, options=options)

    def step(self, action):
        return self.__call("step", np.asarray(action, np.float32))

    def render(self):
        return self.__call("render")

    def render_images(self, camera: str | None = None,
                      kinds: Sequence[str] = ("rgb", "depth", "segmentation")):
        """Camera frames from the twin's (true, unknown) camera pose, as ``RealTwin``'s."""
        return self.__call("render_images", camera, tuple(kinds))

    def move_camera(self, coords) -> int:
        """Move the camera mount (arm tasks), as ``RealTwin.move_camera``; returns the steps."""
        return self.__call("move_camera", np.asarray(coords, np.float64))

    def calibrate_controller(self, joint_speed=None) -> None:
        """Configure the arm's Cartesian controller, as ``RealTwin.calibrate_controller``."""
        self.__call("calibrate_controller",
                    None if joint_speed is None else np.asarray(joint_speed, np.float64))

    @property
    def joint_speed(self):
        """The controller's calibration (None: nominal), as ``RealTwin.joint_speed``."""
        return self.__call("attr", "joint_speed")

    def success(self) -> float:
        """The task's success of the episode's current state, as ``RealTwin.success`` (an
        operator's verdict: evaluation and bookkeeping, never a learning signal)."""
        return float(self.__call("success"))

    @property
    def camera_steps(self) -> int:
        """Control steps the camera mount has spent moving since the last reset."""
        return int(self.__call("attr", "camera_steps"))

    @property
    def mount_coords(self):
        """The commanded camera-mount coordinates (None before the first move)."""
        return self.__call("attr", "mount_coords")

    def close(self) -> None:
        proc = self.__proc
        if proc is None:
            return
        try:
            self.__call("close")
        except (TwinServerError, OSError, BrokenPipeError):
            pass
        self.__proc = None
        self.__conn.close()
        proc.join(timeout=10)
        if proc.is_alive():
            proc.kill()
            proc.join()

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

    def __repr__(self) -> str:
        return f"TwinClient({self.task_name!r}, seed={self.seed})"
