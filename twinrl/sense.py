"""``twinrl sense``: the camera pose the sensing-aware Q chooses for a start state, Q's landscape
over the mount's workspace, the views from the default and the chosen pose, and the image actor's
saliency on each view (``saliency``: which pixels move its action, SAM-RL's figure).

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

from twinrl.learn.camera_choice import image_size, landscape, select_camera
from twinrl.learn.networks import Network
from twinrl.learn.sensing import SensingConfig, SensingError, load_actor

__all__ = ["load_q", "sense", "saliency", "saliency_views", "target_share", "plot_saliency",
           "RGBD"]


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
          steps: int | None = None, grid: tuple[int, int] = (15, 9), progress=None,
          env=None) -> dict:
    """``twinrl sense``: the camera pose Q chooses for the start state ``reset(seed)`` of
    ``env_name``; writes ``out/sense.png`` (Q over the workspace at the chosen distance, with the
    default, the ascents and the choice marked; the views from the default and the chosen pose
    side by side, RGB and the target mask, and under each the actor's ``saliency`` there),
    ``out/views.png`` (the two images the actor would see), ``out/saliency.png``
    (``plot_saliency`` of both views) and ``out/summary.json``. ``env``: the task to simulate
    (default: ``env_name`` with the ``System`` saved beside Q, as Q was trained). Returns the
    summary."""
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
    if env is None:
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
    say("the actor's saliency on both views ...")
    seen = saliency_views(env, actor, actor_params, state,
                          {"default": default, "chosen": chosen})
    out.mkdir(parents=True, exist_ok=True)
    _plot_sense(out / "sense.png", env, az, el, vals, sel, images, env_name,
                around=int(cfg.smooth_samples) > 0, saliency=seen)
    plot_saliency(out / "saliency.png", seen, f"the actor's saliency on {env_name} "
                  f"(start state seed {int(seed)})")
    small = [seen[k]["rgb"] for k in ("default", "chosen")]
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
        "target_pixels_160": pixels,
        "saliency_target_share": {k: target_share(v) for k, v in seen.items()},
        "restarts": int(cfg.restarts),
        "ascent_steps": int(cfg.ascent_steps), "smooth_samples": int(cfg.smooth_samples),
        "files": {"plot": str(out / "sense.png"), "views": str(out / "views.png"),
                  "saliency": str(out / "saliency.png")},
    }
    report.write_json(out / "summary.json", summary)
    return summary


def _spherical(mount, coords) -> np.ndarray:
    """``(azimuth, elevation, distance)`` of unconstrained mount coordinates, as NumPy."""
    return np.asarray(mount.spherical(jnp.asarray(coords, jnp.float32)), float)


def _plot_sense(path, env, az, el, vals, sel, images, title, around: bool = False,
                saliency=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mount = env.mount
    sph = functools.partial(_spherical, mount)
    rows = 1 if saliency is None else 2
    fig = plt.figure(figsize=(13, 4.2 * rows), dpi=110)
    ax = fig.add_subplot(rows, 3, 1)
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
        ax = fig.add_subplot(rows, 3, 2 + i)
        shown = rgb.copy()
        shown[mask] = 0.5 * shown[mask] + 0.5 * np.array([1.0, 0.0, 0.0])
        ax.imshow(np.clip(shown, 0, 1))
        score = "Q around it" if around else "Q"
        ax.set_title(f"{name} pose: {score} {q:.3f}, target {int(mask.sum())} px (red)",
                     fontsize=9)
        ax.axis("off")
    if saliency is not None:  # under each view, the actor's saliency on its own image of it
        vmax = max(float(np.max(v["saliency"])) for v in saliency.values()) or 1.0
        ax = fig.add_subplot(rows, 3, 4)
        ax.axis("off")
        ax.text(0.0, 0.6, "Right: the actor's saliency, |d action / d pixel|\n"
                "(every action dimension, RGB and depth), on the\nimage it sees from each "
                "pose; warm = larger\n(square-root scale, one scale for both), grey = 0.",
                fontsize=9, va="center", ha="left", transform=ax.transAxes)
        for i, name in enumerate(("default", "chosen")):
            ax = fig.add_subplot(rows, 3, 5 + i)
            _draw_saliency(ax, saliency[name], vmax)
            ax.set_title(f"{name}: the actor's |d action / d pixel| (RGB-D)\n"
                         f"{_share_text(saliency[name])}", fontsize=9)
            ax.axis("off")
    fig.suptitle(f"sensing-aware camera choice on {title}")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------ saliency
RGBD = 4
"""The mount image's camera channels (RGB and depth; the fifth, the target's mask, comes from the
segmentation): what ``saliency`` sums over."""


def saliency(env, actor: Network, actor_params, joints, coords, pixels, *,
             per_channel: bool = False) -> jax.Array:
    """The image actor's saliency (SAM-RL's figure): ``|d action / d pixel|`` at one image
    observation, the Jacobian of every action dimension w.r.t. the mount image ``pixels``
    ``(n, n, 5)`` (RGB, depth, the target's mask; ``ArmTask.observation_from_image``'s layout),
    its absolute values summed over the action's dimensions and the RGB-D channels (``RGBD``)
    -> ``(n, n)``; with ``per_channel``, every channel's (the mask's too) -> ``(n, n, 5)``.

    The actor reads the image through ``env.observation_from_image`` (its ``obs_spec`` keys
    only), with the measured ``joints`` (14,) and the commanded mount ``coords``: a CNN reads the
    pixels themselves, a ``"target"`` actor the target cloud's statistics, a ``"pose"`` actor
    the target's pose fitted to the depth (the converged fit's derivative: nonzero on the target
    pixels the fit uses, ~1e-10 of the largest elsewhere). A pixel the action does not depend on
    scores 0: the figure says which pixels move the action."""
    spec = actor.obs_spec
    if not isinstance(spec, dict):
        raise ValueError(f"saliency needs an image actor (a dict obs_spec); this one reads "
                         f"{spec!r}")
    keys = tuple(spec)
    joints = jnp.asarray(joints, jnp.float32)
    coords = jnp.asarray(coords, jnp.float32)

    def action(px):
        obs = env.observation_from_image(joints, coords, px[..., :3], px[..., 3], px[..., 4],
                                         keys=keys)
        return jnp.reshape(actor.apply(actor_params, obs), (-1,))

    jac = jax.jacrev(action)(jnp.asarray(pixels, jnp.float32))  # (actions, n, n, 5)
    per = jnp.sum(jnp.abs(jac), axis=0)
    return per if per_channel else jnp.sum(per[..., :RGBD], axis=-1)


def saliency_views(env, actor: Network, actor_params, state,
                   poses: dict[str, object]) -> dict[str, dict[str, np.ndarray]]:
    """The actor's image of ``state`` from the mount at each of ``poses`` (name -> unconstrained
    mount coordinates; the simulator's render at the actor's image size, ``image_observation``)
    and its ``saliency`` there: per name ``{"rgb" (n, n, 3), "mask" (n, n) the target's,
    "saliency" (n, n)}``, as NumPy (one compilation for every pose)."""
    n = image_size(env, actor)

    @jax.jit
    def run(state, coords):
        px = env.image_observation(state, coords, size=n, keys=("pixels/mount",))["pixels/mount"]
        return px, saliency(env, actor, actor_params, state.obs[:14], coords, px)

    views = {}
    for name, coords in poses.items():
        px, sal = run(state, jnp.asarray(coords, jnp.float32))
        px = np.asarray(px)
        views[name] = {"rgb": px[..., :3], "mask": px[..., 4] > 0.5, "saliency": np.asarray(sal)}
    return views


def target_share(view: dict[str, np.ndarray]) -> float:
    """The share of a ``saliency_views`` view on the target's pixels (nan where it is all 0)."""
    total = float(np.sum(view["saliency"]))
    return float(np.sum(view["saliency"][view["mask"]])) / total if total > 0 else float("nan")


def plot_saliency(path, views: dict[str, dict[str, np.ndarray]], title: str = "") -> Path:
    """``saliency.png``: per view (``saliency_views``) the actor's image and, beside
    it, its saliency over the image in grey (one colour scale for every view, so they compare),
    titled with the share of the saliency on the target's pixels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vmax = max((float(np.max(v["saliency"])) for v in views.values()), default=0.0) or 1.0
    fig, axes = plt.subplots(1, 2 * len(views), figsize=(3.2 * 2 * len(views), 3.6), dpi=110,
                             squeeze=False)
    for i, (name, v) in enumerate(views.items()):
        ax_img, ax_sal = axes[0, 2 * i], axes[0, 2 * i + 1]
        ax_img.imshow(np.clip(v["rgb"], 0, 1), interpolation="nearest")
        ax_img.set_title(f"{name} view (what the actor sees)", fontsize=8)
        _draw_saliency(ax_sal, v, vmax)
        ax_sal.set_title(f"{name}: |d action / d pixel|\n{_share_text(v)}", fontsize=8)
        for ax in (ax_img, ax_sal):
            ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.92) if title else None)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def _share_text(view) -> str:
    share = target_share(view)
    return "no pixel moves the action" if not np.isfinite(share) else \
        f"{100 * share:.0f} % of it on the target ({int(view['mask'].sum())} px)"


def _draw_saliency(ax, view, vmax: float):
    """The saliency in warm colours (square-root scale, so the small values show) over the
    actor's image in dark grey; pixels at 0 (below 1e-6 of ``vmax``: rounding, the pose fit's)
    are left grey."""
    from matplotlib.colors import PowerNorm

    grey = 0.45 * np.mean(np.clip(view["rgb"], 0, 1), axis=-1)
    ax.imshow(grey, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    sal = np.ma.masked_where(view["saliency"] <= 1e-6 * vmax, view["saliency"])
    return ax.imshow(sal, cmap="autumn", norm=PowerNorm(0.5, vmin=0, vmax=vmax),
                     interpolation="nearest")
