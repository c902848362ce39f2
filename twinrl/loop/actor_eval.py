"""``twinrl eval`` of an arm task's image actor, deployed as the SAM-RL loop deploys it.

The actor acts on what it is trained to see (the mount image, the pose estimate fitted to it,
or the target's cloud, as its ``obs_spec`` says), in the task built with its ``System`` (the
round's identified one for an actor inside a ``twinrl run``: camera mount and hand-eye
calibration, tool grasp, controller calibration, latency), with the camera

- ``default``: the mount's fixed default pose;
- ``random``: a pose drawn uniformly over the mount's workspace per episode;
- ``chosen``: the pose the sensing-aware Q chooses by gradient ascent through the renderer
  (the round's ``q/``, or ``--q``), as the loop deploys it;

and the round's residual policy when its gate accepted it. In the simulator the episodes are the
identified twin's (``twinrl.learn.common.held_episodes``: the camera held at its pose, the image
drawn by the differentiable renderer); with ``real`` they run on the real twin through
``twinrl.sim2real.active.Deployer``, the loop's own deployment: for an actor of a ``twinrl run``
the run's real twin (the same hidden perturbation: its ``eval/twin.json``), else the public
twin ``make_real(task, seed)``. Episode ``i`` starts from reset seed ``seed + i``.

The summary gives the success rate with its 95 % Wilson interval beside the returns, and the
video shows the view the actor saw beside the scene.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn.checkpoint import CheckpointError
from twinrl.loop.checkpoints import Found, round_of, round_q
from twinrl.report import wilson_interval

__all__ = ["CAMERAS", "eval_actor", "wilson_interval"]

CAMERAS = ("default", "chosen", "random")
_DEPLOY = {"default": "default", "chosen": "selected", "random": "random"}


def _actor_dir(found: Found) -> tuple[Path, Any]:
    """The actor's checkpoint and its round (None outside a ``twinrl run``)."""
    rdir = round_of(found)
    if found.kind == "run":
        if rdir is None:
            raise CheckpointError(f"{found.path}: the run has no round with a trained actor yet")
    if found.kind in ("run", "round"):
        return rdir.actor, rdir
    return found.path, rdir


def eval_actor(found: Found, out: str | Path, *, real: bool = False, episodes: int = 5,
               seed: int = 0, camera: str = "chosen", q: str | Path | None = None,
               residual: bool = True, video: bool = True, say: Callable[[str], None] = print
               ) -> dict[str, Any]:
    """Evaluate the image actor ``found`` (``twinrl.loop.checkpoints.describe`` of an actor, a
    training run of one, a round or a run) on ``episodes`` episodes (module docstring); write
    ``out/summary.json`` and ``out/{sim,real}.mp4``. Returns the summary."""
    from twinrl import report
    from twinrl.envs.system import system_of
    from twinrl.learn.checkpoint import load_system
    from twinrl.learn.runner import env_from_meta
    from twinrl.learn.sensing import SensingConfig, load_actor
    from twinrl.sense import load_q

    if camera not in CAMERAS:
        raise ValueError(f"camera {camera!r}: one of {', '.join(CAMERAS)}")
    actor_dir, rdir = _actor_dir(found)
    actor, actor_params, meta = load_actor(actor_dir)
    system = rdir.identified_system(meta["env"]) if rdir is not None and rdir.system.exists() \
        else load_system(actor_dir)
    env = env_from_meta(meta, system)
    q_dir = Path(q) if q is not None else round_q(found)
    q_net = q_params = sensing = None
    if camera == "chosen":
        if q_dir is None or not q_dir.exists():
            raise CheckpointError(f"--camera chosen needs a sensing-aware Q: {actor_dir} has no "
                                  f"round's q/ beside it; give --q DIR (a `twinrl train --algo "
                                  f"sensing` run) or --camera default")
        q_net, q_params, q_meta = load_q(q_dir)
        if q_meta.get("env") != meta["env"]:
            raise CheckpointError(f"--q {q_dir}: trained on {q_meta.get('env')!r}, the actor on "
                                  f"{meta['env']!r}")
        sensing = SensingConfig.from_dict(q_meta.get("config") or {})
    metrics = rdir.residual_metrics() if rdir is not None and residual else None
    correction = None  # (obs, action) -> delta, in JAX
    if metrics and metrics.get("accepted"):
        from twinrl.learn.checkpoint import load_policy

        delta, res_params, _ = load_policy(rdir.residual)
        correction = (lambda o, a: delta.apply(  # noqa: E731
            res_params, jnp.concatenate([o, a], -1)))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    where = "real twin" if real else "sim"
    say(f"evaluating the actor ({camera} camera{', with its residual' if correction else ''}) "
        f"on {episodes} episodes in the {'real twin' if real else 'identified simulator'} ...")
    if real:
        rows, frames, twin_doc = _real(found, env, actor, actor_params, q_net, q_params,
                                       sensing, correction, camera, episodes, seed, video, say)
    else:
        rows, frames = _sim(env, actor, actor_params, q_net, q_params, sensing, correction,
                            camera, episodes, seed, video, say)
        twin_doc = None
    k, n = int(np.sum(rows["success"])), len(rows["success"])
    lo, hi = wilson_interval(k, n)
    files = {}
    if video and frames:
        view = {"chosen": "chosen view", "default": "default view"}.get(camera, "random view")
        files["video"] = str(report.write_video(
            out / f"{'real' if real else 'sim'}.mp4",
            report.label_frames(frames, [view, "scene"]), fps=1.0 / env.dt))
    summary = {"kind": "eval", "checkpoint": str(actor_dir), "env": meta["env"],
               "algo": meta.get("algo"), "where": where, "camera": camera, "seed": int(seed),
               "episodes": n, "residual": correction is not None,
               "successes": [bool(s) for s in rows["success"]], "success_rate": k / n,
               "success_interval_95": [lo, hi],
               "returns": [float(r) for r in rows["return"]],
               "mean_return": float(np.mean(rows["return"])),
               "std_return": float(np.std(rows["return"])),
               "camera_coords": rows["coords"], "twin": twin_doc,
               "system": {"from": "round" if rdir is not None and rdir.system.exists() else
                          "checkpoint" if system is not None else "nominal (none saved)",
                          **system_of(env).to_json()},
               "wall_s": time.perf_counter() - t0, "files": files}
    report.print_table(f"eval {meta.get('algo')} actor on {meta['env']} ({where}, {camera} "
                       f"camera)", ["episodes", "success", "95% interval", "mean return",
                                    "std"],
                       [[n, f"{k}/{n}", f"[{lo:.2f}, {hi:.2f}]", summary["mean_return"],
                         summary["std_return"]]])
    report.write_json(out / "summary.json", summary)
    return summary


def _sim(env, actor, actor_params, q, q_params, sensing, correction, camera, episodes, seed,
         video, say):
    """Episodes of the identified simulator, the camera held at the episode's pose."""
    from twinrl.learn.camera_choice import image_size, observer, select_camera, uniform_coords
    from twinrl.learn.common import held_episodes

    keys = jax.random.split(jax.random.key(int(seed)), episodes)
    if camera == "default":
        coords = jnp.broadcast_to(jnp.asarray(env.mount.default, jnp.float32), (episodes, 3))
    elif camera == "random":
        coords = uniform_coords(env.mount, jax.random.key(int(seed) + 1), (episodes,))
    else:
        choose = jax.jit(lambda k, c: select_camera(env, q, q_params, actor, actor_params,
                                                    env.reset(k), c, sensing).coords)
        picks = []
        for i, k in enumerate(keys):
            picks.append(choose(k, jax.random.fold_in(jax.random.key(int(seed) + 1), i)))
            say(f"  camera chosen for episode {i + 1}/{episodes}")
        coords = jnp.stack(picks)
    n = image_size(env, actor)
    see = observer(env, n, keys=tuple(actor.obs_spec))

    def observe(s, c):
        return {"actor": see(s, c), "state": s.obs}

    def act(o):
        a = actor.apply(actor_params, o["actor"])
        if correction is not None:
            a = jnp.clip(a + correction(o["state"], a), -1.0, 1.0)
        return a

    ep = jax.jit(lambda k, c: held_episodes(env, observe, act, k, coords=c))(keys, coords)
    rows = {"success": np.asarray(ep.success) > 0.5,
            "return": np.asarray(ep.rewards).sum(axis=1),
            "coords": np.asarray(coords).tolist()}
    frames = _sim_frames(env, ep.states, coords[0], n) if video else []
    return rows, frames


def _sim_frames(env, states, coords, n) -> list[np.ndarray]:
    """Episode 0 drawn: the mount's view at ``coords`` (the differentiable renderer's, what a
    pixel actor sees) beside the scene's ``overview`` camera (MuJoCo's renderer)."""
    import mujoco

    from twinrl.render.opengl import CameraRenderer

    m = env.sim.mj_model
    d = mujoco.MjData(m)
    view = jax.jit(lambda s: env.image_observation(s, coords, size=n,
                                                   keys=("pixels/mount",))["pixels/mount"])
    has = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, "overview") >= 0
    scene = "overview" if has else env.default_camera
    qpos = np.asarray(states.pipeline_state.qpos[0])
    renderer = CameraRenderer(m, 3 * n, 3 * n)
    frames = []
    try:
        for t in range(qpos.shape[0]):
            s = jax.tree.map(lambda x: x[0, t], states)
            px = np.asarray(view(s))[..., :3]
            mount = (np.clip(px, 0, 1) * 255).astype(np.uint8).repeat(3, 0).repeat(3, 1)
            d.qpos[:] = qpos[t]
            mujoco.mj_forward(m, d)
            frames.append(np.concatenate([mount, renderer.images(d, scene, ("rgb",))["rgb"]], 1))
    finally:
        renderer.close()
    return frames


def _real(found, env, actor, actor_params, q, q_params, sensing, correction, camera, episodes,
          seed, video, say):
    """Episodes on the real twin through the loop's ``Deployer``."""
    from twinrl.loop.arm import FilmedTwin
    from twinrl.sim2real.active import DeployConfig, Deployer
    from twinrl.learn.camera_choice import image_size

    n = image_size(env, actor)
    if correction is not None:  # jitted, on numpy arrays
        f = jax.jit(correction)
        correction = lambda o, a: np.asarray(f(jnp.asarray(o, jnp.float32),  # noqa: E731
                                               jnp.asarray(a, jnp.float32)))
    dep = Deployer(env, actor, actor_params, q=q, q_params=q_params, sensing=sensing,
                   residual=correction)
    run = found.run
    if run is not None and run.secret.exists():
        import json

        from twinrl.real.remote import TwinClient

        doc = json.loads(run.settings.read_text())
        twin_seed = int(doc["seed"])
        try:
            twin = TwinClient(doc["env"], seed=twin_seed, secret=run.secret, width=n, height=n)
        except ValueError as e:  # a custom twin's secret (a benchmark's)
            raise CheckpointError(f"{run.out}: its real twin cannot be rebuilt ({e})") from None
        twin_doc = {"from": "the run's real twin", "run": str(run.out), "seed": twin_seed}
    else:
        from twinrl.real.twin import make_real

        twin = make_real(env.name, seed=int(seed), width=n, height=n)
        twin_doc = {"from": "make_real", "seed": int(seed)}
    filmed = FilmedTwin(twin, film=video)

    def on_episode(row):
        filmed.film = False  # the first episode only
        say(f"  episode {row['episode'] + 1}/{episodes}: "
            f"{'success' if row['success'] else 'failure'}, return {row['return']:.1f}")

    try:
        res = dep.run(filmed, DeployConfig(camera=_DEPLOY[camera], episodes=episodes),
                      seed=int(seed), on_episode=on_episode)
    finally:
        filmed.close()
    rows = {"success": np.asarray(res["success"]) > 0.5, "return": np.asarray(res["return"]),
            "coords": res["coords"]}
    return rows, filmed.frames, twin_doc
