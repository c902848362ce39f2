"""DreamerV3 (danijar/dreamerv3) from pixels on a real twin: the Dreamer row of ``bench/sensing.py``.

DreamerV3 pins ``jax==0.4.33`` (its requirements.txt), twinrl ``jax==0.9.2``: the two cannot share
an environment. So the twin runs here, in twinrl's environment, and Dreamer runs in its own
Python (``--dreamer-python``, or ``$TWINRL_DREAMER_PYTHON``) as a subprocess of this file in
``--worker`` mode, which imports no twinrl and talks to the twin over a local
``multiprocessing.connection`` (pickled numpy arrays, an auth key per run). Each real step sends
an action and gets back the default camera's RGB frame (the task's ``image_size``, 64 pixels for
the arm tasks), the reward and the episode flags.

The separate environment. PyPI has no installable DreamerV3: ``pip install dreamer`` (3.3.1,
danijar's current release) fails building its sdist, whose setup.py reads a requirements.txt
the sdist does not ship (``FileNotFoundError: [Errno 2] No such file or directory:
'requirements.txt'``), and ``pip install dreamerv3`` (1.5.0, the 2023 version) fails on its
``gym==0.19.0`` pin (``error in gym setup command: 'extras_require' must be a dictionary whose
values are strings or lists of strings containing valid project/version requirement
specifiers.``). So the code comes from the source (github.com/danijar/dreamerv3, setup.py
version 3.3.1; used here at commit e3f02248693a) and its requirements.txt from PyPI, less the
Atari, CUDA and debugger ones; pip resolves jax 0.4.33, numpy 1.26.4, ml-dtypes 0.5.4,
optax 0.2.5, chex 0.1.90, elements 3.22.4, ninjax 3.6.3, portal 3.8.3 (Python 3.11)::

    python3 -m venv /tmp/dreamer-venv
    /tmp/dreamer-venv/bin/pip install "jax==0.4.33" "jaxlib==0.4.33" chex einops \\
        "elements>=3.19.1" "granular>=0.20.3" jaxtyping "ninjax>=3.5.1" "numpy<2" optax \\
        "portal>=3.5.0" "scope>=0.4.4" tqdm av colored_traceback
    git clone https://github.com/danijar/dreamerv3 DIR
    export TWINRL_DREAMER_PYTHON=/tmp/dreamer-venv/bin/python DREAMERV3_SRC=DIR
    PYTHONPATH=DIR $TWINRL_DREAMER_PYTHON bench/dreamer_baseline.py --probe  # dreamerv3 with jax 0.4.33

Dreamer's settings: its ``size1m`` model (687k parameters), float32 on the CPU, one
environment, train ratio 32 (replayed steps per real step), the rest its defaults; training
starts once the replay holds one batch (16 x 64 steps).

Success is the twin's ``success()`` at the end of each training episode (the stochastic training
policy, reset seeds ``20,000 + episode``), reported as the mean of the last 10 episodes; the
real steps to the target are those at which that mean first reached it. Dreamer's step budget
counts each episode's first observation as a step, so it applies about one action in 50 fewer
(needle: 1,960 real steps for 2,000).

On 2 shared CPU cores, needle, 2,000 steps: 13 minutes in all (2 of them compiling); about 14
real steps/s while it collects its first batch, 1-3 once it trains; 0 % success at the end.
"""

from __future__ import annotations

import argparse
import os
import secrets
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

WINDOW = 10  # episodes the success rate is taken over
RESET_SEED = 20_000


def dreamer_python(path: str | None = None) -> tuple[str | None, str | None]:
    """The separate environment's interpreter and, when it cannot run DreamerV3, why not."""
    path = path or os.environ.get("TWINRL_DREAMER_PYTHON")
    if not path:
        return None, ("no Dreamer environment: give --dreamer-python or $TWINRL_DREAMER_PYTHON "
                      "(bench/dreamer_baseline.py's docstring says how it is built)")
    exe = shutil.which(path)
    if exe is None:
        return None, f"no Dreamer environment: {path} is not an executable"
    try:
        probe = subprocess.run([exe, __file__, "--probe"], capture_output=True, text=True,
                               env=_worker_env(), timeout=300)
    except subprocess.TimeoutExpired:
        return None, f"DreamerV3 did not import in {exe} within 300 s"
    if probe.returncode != 0:
        last = (probe.stderr.strip().splitlines() or ["(no output)"])[-1]
        return None, f"DreamerV3 does not import in {exe}: {last}"
    return exe, None


def _worker_env() -> dict:
    env = dict(os.environ)
    src = env.get("DREAMERV3_SRC")
    if src:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (src, env.get("PYTHONPATH")) if p)
    return env


def train_dreamer(task: str, steps: int, target: float, seed: int, secret=None,
                  python: str | None = None, logdir: Path | None = None,
                  train_ratio: float = 32.0, size: str = "size1m") -> dict:
    """DreamerV3 on the real twin of ``task`` (twin seed ``seed``, the run's secret salt when
    given) for ``steps`` real steps from its default camera's images. Returns the bench row, or
    one with ``absent`` (the reason) when the Dreamer environment is missing or fails."""
    from multiprocessing.connection import Listener

    from twinrl.real.remote import hidden_perturbation
    from twinrl.real.twin import RealTwin

    row = {"task": task, "algo": "dreamer", "observation": "pixels (default camera RGB)",
           "twin_seed": seed, "secret": secret is not None, "target": target}
    exe, why = dreamer_python(python)
    if exe is None:
        return {**row, "absent": why}
    hidden = None if secret is None else hidden_perturbation(task, seed, secret)
    twin = RealTwin(task, seed=seed, perturbation=hidden, render_mode="rgb_array")
    size_px = int(getattr(twin.task.config, "image_size", 64))
    twin.width = twin.height = size_px
    logdir = Path(logdir or f"/tmp/twinrl-dreamer-{task}-{seed}-{os.getpid()}")
    key = secrets.token_bytes(16)
    episodes, n, t0 = [], 0, time.perf_counter()
    with Listener(("127.0.0.1", 0), authkey=key) as listener:
        cmd = [exe, __file__, "--worker", "--port", str(listener.address[1]), "--steps",
               str(steps), "--logdir", str(logdir), "--train-ratio", str(train_ratio),
               "--size", size]
        env = {**_worker_env(), "TWINRL_DREAMER_KEY": key.hex()}
        log = open(logdir.with_suffix(".log"), "w")
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            conn = _accept(listener, proc)
            conn.send({"image": (size_px, size_px, 3), "nu": int(twin.action_space.shape[0])})
            while True:
                msg = conn.recv()
                if msg[0] == "done":
                    break
                if msg[0] == "reset":
                    twin.reset(seed=RESET_SEED + len(episodes))
                    r, first, last, term = 0.0, True, False, False
                else:
                    _, r, term, trunc, _ = twin.step(np.asarray(msg[1], np.float32))
                    n, first, last = n + 1, False, bool(term or trunc)
                    if last:
                        episodes.append({"real_steps": n, "success": float(twin.success()),
                                         "wall_s": time.perf_counter() - t0})
                        recent = [e["success"] for e in episodes[-WINDOW:]]
                        print(f"[bench] {task} dreamer: {n} real steps, episode {len(episodes)}"
                              f" success {episodes[-1]['success']:.0f}, last {len(recent)}: "
                              f"{np.mean(recent):.2f} (target {target:.2f})", flush=True)
                conn.send({"image": twin.render(), "reward": np.float32(r),
                           "is_first": first, "is_last": last, "is_terminal": bool(term)})
        except (EOFError, ConnectionError, TimeoutError) as e:
            proc.wait(timeout=60)
            tail = logdir.with_suffix(".log").read_text().strip().splitlines()[-3:]
            return {**row, "absent": f"the Dreamer worker stopped ({e!r}, exit "
                                     f"{proc.returncode}): {' | '.join(tail)}",
                    "real_steps_trained": n, "log": str(logdir.with_suffix(".log"))}
        finally:
            if proc.poll() is None:
                proc.wait(timeout=120)
            log.close()
            twin.close()
    wall = time.perf_counter() - t0
    rolling = [float(np.mean([e["success"] for e in episodes[max(0, i + 1 - WINDOW):i + 1]]))
               for i in range(len(episodes))]
    reached = next((e["real_steps"] for i, (e, s) in enumerate(zip(episodes, rolling))
                    if i + 1 >= WINDOW and s >= target), None)
    return {**row, "steps_to_target": reached,
            "best_success": max(rolling[WINDOW - 1:], default=max(rolling, default=0.0)),
            "final_success": rolling[-1] if rolling else 0.0, "real_steps_trained": n,
            "curve": [{**e, "success_last10": s} for e, s in zip(episodes, rolling)],
            "wall_s": wall, "real_steps_per_s": n / wall if wall > 0 else None,
            "hyperparameters": {"size": size, "train_ratio": train_ratio,
                                "image_size": size_px, "compute_dtype": "float32"},
            "log": str(logdir.with_suffix(".log"))}


def _accept(listener, proc, timeout: float = 600.0):
    """The worker's connection, or TimeoutError/ConnectionError if it dies or never calls."""
    import threading

    box: list = []
    waiter = threading.Thread(target=lambda: box.append(listener.accept()), daemon=True)
    waiter.start()
    deadline = time.time() + timeout
    while not box and time.time() < deadline:
        if proc.poll() is not None:
            raise ConnectionError("the worker exited before connecting")
        waiter.join(1.0)
    if not box:
        raise TimeoutError(f"no connection from the worker in {timeout:.0f} s")
    return box[0]


# ----- the worker: runs in the Dreamer environment, imports no twinrl -----

def _worker(a) -> int:
    from multiprocessing.connection import Client

    conn = Client(("127.0.0.1", a.port), authkey=bytes.fromhex(os.environ["TWINRL_DREAMER_KEY"]))
    spec = conn.recv()
    import elements
    import embodied
    from dreamerv3 import main as dm

    class TwinEnv(embodied.Env):
        """The real twin behind the connection, as an embodied environment."""

        def __init__(self):
            self.done = True

        @property
        def obs_space(self):
            return {"image": elements.Space(np.uint8, tuple(spec["image"])),
                    "reward": elements.Space(np.float32), "is_first": elements.Space(bool),
                    "is_last": elements.Space(bool), "is_terminal": elements.Space(bool)}

        @property
        def act_space(self):
            return {"reset": elements.Space(bool),
                    "action": elements.Space(np.float32, (spec["nu"],), -1.0, 1.0)}

        def step(self, action):
            if action["reset"] or self.done:
                conn.send(("reset",))
            else:
                conn.send(("step", np.asarray(action["action"], np.float32)))
            obs = conn.recv()
            self.done = obs["is_last"]
            return obs

        def close(self):
            pass  # make_agent builds one to read the spaces and closes it; the link stays

    dm.make_env = lambda config, index, **kw: dm.wrap_env(TwinEnv(), config)
    dm.main(["--configs", a.size, "--task", "twin_real", "--logdir", a.logdir,
             "--run.steps", str(a.steps), "--run.envs", "1", "--run.eval_envs", "0",
             "--run.debug", "True", "--run.train_ratio", str(a.train_ratio),
             "--run.save_every", "1e9", "--run.log_every", "60", "--run.report_every", "1e9",
             "--jax.platform", "cpu", "--jax.compute_dtype", "float32", "--jax.prealloc",
             "False", "--logger.outputs", "jsonl", "--replay.size", "1e5",
             "--run.usage.nvsmi", "False"])
    conn.send(("done",))
    conn.close()
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--probe", action="store_true", help="check that DreamerV3 imports")
    p.add_argument("--worker", action="store_true")
    p.add_argument("--port", type=int)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--logdir", default="/tmp/twinrl-dreamer")
    p.add_argument("--train-ratio", type=float, default=32.0)
    p.add_argument("--size", default="size1m")
    a = p.parse_args(argv)
    if a.probe:
        import dreamerv3.agent  # noqa: F401
        import jax

        print(f"dreamerv3 with jax {jax.__version__}")
        return 0
    if a.worker:
        return _worker(a)
    p.error("run by bench/sensing.py --dreamer-steps (or --probe / --worker)")
    return 2


if __name__ == "__main__":
    sys.exit(main())
