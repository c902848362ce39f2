"""``twinrl sense``: the camera pose the sensing-aware Q chooses for a start state, Q's landscape
over the mount's workspace, and the views from the default and the chosen pose.

The choice itself is ``twinrl.learn.camera_choice.select_camera``; Q and its training are
``twinrl.learn.sensing``.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn.camera_choice import image_size, landscape, observer, select_camera
from twinrl.learn.networks import Network
from twinrl.learn.sensing import SensingConfig, SensingError, load_actor

__all__ = ["load_q", "sense"]


def load_q(path) -> tuple[Network, object, dict]:
    """Q ``(network, params, meta)`` from a ``twinrl train --algo sensing`` run (or its
    ``policy/``); a one-line error for any other checkpoint."""
    from twinrl.learn.checkpoint import KINDS, load_policy, read_meta

    where, meta = read_meta(path)
    if meta["kind"] != "sensing_q":
        raise SensingError(f"{where} is {KINDS[meta['kind']]}, not a sensing-aware Q; train one "
                           f"with twinrl train --algo sensing --set actor=DIR")
    net, params, meta = load_policy(path)
    if meta.get("algo") != "sensing" or not isinstance(net.obs_spec, dict) \
            or "action" not in net.obs_spec:
        raise SensingError(f"{path}: not a sensing Q checkpoint (algo {meta.get('algo')!r}); "
                           f"train one with twinrl train --algo sensing --set actor=DIR")
    return net, params, meta


def sense(env_name: str, checkpoint, out, *, seed: int = 0, restarts: int | None = None,
          steps: int | None = None, grid: tuple[int, int] = (15, 9), progress=None) -> dict:
    """``twinrl sense``: the camera pose Q chooses for the start state ``reset(seed)`` of
    ``env_name``; writes ``out/sense.png`` (Q over the workspace at the chosen distance, with the
    default, the ascents and the choice marked; the views from the default and the chosen pose
    side by side, RGB and the target mask), ``out/views.png`` (the two 64 x 64 images the actor
    would see) and ``out/summary.json``. Returns the summary."""
    from twinrl import envs, report
    from twinrl.learn.checkpoint import load_system

    out = Path(out)
    q, q_params, meta = load_q(checkpoint)
    if meta.get("env") != env_name:
        raise SensingError(f"{checkpoint}: Q was trained on {meta.get('env')!r}, not "
                           f"{env_name!r}")
    cfg = SensingConfig.from_dict(meta.get("config") or {})
    over = {k: v for k, v in (("restarts", restarts), ("ascent_steps", steps)) if v is not None}
    cfg = dataclasses.replace(cfg, **over)
    actor, actor_params, _ = load_actor(cfg.actor)
    system = load_system(checkpoint)  # the (identified) simulator Q was trained in, if any
    env = envs.make(env_name) if system is None else envs.make(env_name, system=system)
    say = progress or (lambda s: None)
    state = jax.jit(env.reset)(jax.random.PRNGKey(int(seed)))
    say("choosing the camera pose (gradient ascent of Q through the renderer) ...")
    choose = jax.jit(lambda s, k: select_camera(env, q, q_params, actor, actor_params, s, k, cfg))
    sel = jax.block_until_ready(choose(state, jax.random.PRNGKey(int(seed) + 1)))
    say("Q over the workspace ...")
    az, el, vals = landscape(env, q, q_params, actor, actor_params, state,
                             float(sel.coords[2]), grid)
    mount = env.mount
    chosen = np.asarray(sel.coords, np.float64)
    default = np.asarray(mount.default, np.float64)
    sph = functools.partial(_spherical, mount)
    big = jax.jit(lambda c: env.image_observation(state, c, size=160,
                                                  keys=("pixels/mount",))["pixels/mount"])
    images = {}
    for name, c in (("default", default), ("chosen", chosen)):
        px = np.asarray(big(jnp.asarray(c, jnp.float32)))
        images[name] = (px[..., :3], px[..., 4] > 0.5)  # RGB, the target's (hard) mask
    pixels = {k: int(v[1].sum()) for k, v in images.items()}
    out.mkdir(parents=True, exist_ok=True)
    _plot_sense(out / "sense.png", env, az, el, vals, sel, images, env_name,
                around=int(cfg.smooth_samples) > 0)
    observe = jax.jit(observer(env, image_size(env, actor), keys=("pixels/mount",)))
    small = [np.asarray(observe(state, jnp.asarray(c, jnp.float32))["pixels/mount"][..., :3])
             for c in (default, chosen)]
    import imageio.v3 as iio

    gap = np.ones((small[0].shape[0], 4, 3))
    iio.imwrite(out / "views.png", (np.concatenate([small[0], gap, small[1]], axis=1)
                                    * 255).clip(0, 255).astype(np.uint8))
    summary = {
        "kind": "sense", "env": env_name, "seed": int(seed), "checkpoint": str(checkpoint),
        "chosen_coords": chosen.tolist(),
        "chosen_pose": dict(zip(("azimuth_rad", "elevation_rad", "distance_m"),
                                sph(chosen).tolist())),
        "default_pose": dict(zip(("azimuth_rad", "elevation_rad", "distance_m"),
                                 sph(default).tolist())),
        "q_chosen": float(sel.value), "q_default": float(sel.default_value),
        "q_landscape_max": float(np.max(vals)), "q_landscape_min": float(np.min(vals)),
        "steps_to_move": mount.steps_to_move(default, chosen),
        "target_pixels_160": pixels, "restarts": int(cfg.restarts),
        "ascent_steps": int(cfg.ascent_steps), "smooth_samples": int(cfg.smooth_samples),
        "files": {"plot": str(out / "sense.png"), "views": str(out / "views.png")},
    }
    report.write_json(out / "summary.json", summary)
    return summary


def _spherical(mount, coords) -> np.ndarray:
    """``(azimuth, elevation, distance)`` of unconstrained mount coordinates, as NumPy."""
    return np.asarray(mount.spherical(jnp.asarray(coords, jnp.float32)), float)


def _plot_sense(path, env, az, el, vals, sel, images, title, around: bool = False):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mount = env.mount
    sph = functools.partial(_spherical, mount)
    fig = plt.figure(figsize=(13, 4.2), dpi=110)
    ax = fig.add_subplot(1, 3, 1)
    m = ax.pcolormesh(np.degrees(az), np.degrees(el), vals, shading="nearest", cmap="viridis")
    fig.colorbar(m, ax=ax, label="Q (hard image)")
    for c0, c1 in zip(np.asarray(sel.starts), np.asarray(sel.ends)):
        a, b = np.degrees(sph(c0)), np.degrees(sph(c1))
        ax.annotate("", xy=(b[0], b[1]), xytext=(a[0], a[1]),
                    arrowprops=dict(arrowstyle="->", color="w", lw=0.8))
    d, c = np.degrees(sph(mount.default)), np.degrees(sph(sel.coords))
    ax.plot(d[0], d[1], "s", mfc="none", mec="orange", ms=10, label="default")
    ax.plot(c[0], c[1], "*", color="red", ms=14, label="chosen")
    ax.set_xlabel("azimuth (deg)")
    ax.set_ylabel("elevation (deg)")
    ax.set_title(f"Q over the workspace at {sph(sel.coords)[2]:.2f} m\n(arrows: the ascents)",
                 fontsize=9)
    ax.legend(loc="lower right", fontsize=8)
    for i, (name, q) in enumerate((("default", float(sel.default_value)),
                                   ("chosen", float(sel.value)))):
        rgb, mask = images[name]
        ax = fig.add_subplot(1, 3, 2 + i)
        shown = rgb.copy()
        shown[mask] = 0.5 * shown[mask] + 0.5 * np.array([1.0, 0.0, 0.0])
        ax.imshow(np.clip(shown, 0, 1))
        score = "Q around it" if around else "Q"
        ax.set_title(f"{name} pose: {score} {q:.3f}, target {int(mask.sum())} px (red)",
                     fontsize=9)
        ax.axis("off")
    fig.suptitle(f"sensing-aware camera choice on {title}")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
