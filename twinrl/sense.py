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

__all__ = ["load_q", "sense", "saliency", "saliency_views", "look", "target_share",
           "plot_saliency", "plot_sense", "MARKERS", "RGBD"]


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
    plot_sense(out / "sense.png", mount, (az, el, vals), {"default": default, "chosen": chosen},
               images, {"default": float(sel.default_value), "chosen": float(sel.value)},
               f"sensing-aware camera choice on {env_name}", note="(arrows: the ascents)",
               arrows=list(zip(np.asarray(sel.starts), np.asarray(sel.ends))),
               score="Q around it" if int(cfg.smooth_samples) > 0 else "Q", saliency=seen)
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


MARKERS = {"default": dict(marker="s", mfc="none", mec="orange", ms=10, ls="none"),
           "chosen": dict(marker="*", color="red", ms=14, ls="none")}
"""How ``plot_sense`` marks a pose on Q's landscape, by name (any other: a white triangle)."""


def plot_sense(path, mount, land, poses: dict, images: dict, values: dict, title: str, *,
               note: str = "", arrows=(), score: str = "Q", saliency=None) -> Path:
    """``sense.png``: Q's landscape ``land`` (``(azimuths, elevations, values (E, A))``, radians,
    at the distance of the last of ``poses``) with each pose of ``poses`` (name -> mount
    coordinates) marked (``MARKERS``) and ``arrows`` (``(start, end)`` coordinates: the ascents);
    beside it each pose's view ``images`` (name -> ``(rgb, target mask)``) titled with its
    ``score`` ``values[name]``; under them, with ``saliency`` (``saliency_views``'s dict), the
    actor's saliency on each view's own image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    az, el, vals = land
    sph = functools.partial(_spherical, mount)
    names = list(images)
    rows = 1 if saliency is None else 2
    cols = 1 + len(names)
    fig = plt.figure(figsize=(13 * cols / 3, 4.2 * rows), dpi=110)
    ax = fig.add_subplot(rows, cols, 1)
    m = ax.pcolormesh(np.degrees(az), np.degrees(el), vals, shading="nearest", cmap="viridis")
    fig.colorbar(m, ax=ax, label="Q (hard image)")
    for c0, c1 in arrows:
        a, b = np.degrees(sph(c0)), np.degrees(sph(c1))
        ax.annotate("", xy=(b[0], b[1]), xytext=(a[0], a[1]),
                    arrowprops=dict(arrowstyle="->", color="w", lw=0.8))
    for name, c in poses.items():
        d = np.degrees(sph(c))
        ax.plot(d[0], d[1], label=name, **MARKERS.get(
            name, dict(marker="^", mfc="none", mec="w", ms=10, ls="none")))
    dist = sph(list(poses.values())[-1])[2]
    ax.set_xlabel("azimuth (deg)")
    ax.set_ylabel("elevation (deg)")
    ax.set_title(f"Q over the workspace at {dist:.2f} m" + (f"\n{note}" if note else ""),
                 fontsize=9)
    ax.legend(loc="lower right", fontsize=8)
    for i, name in enumerate(names):
        rgb, mask = images[name]
        ax = fig.add_subplot(rows, cols, 2 + i)
        shown = rgb.copy()
        shown[mask] = 0.5 * shown[mask] + 0.5 * np.array([1.0, 0.0, 0.0])
        ax.imshow(np.clip(shown, 0, 1))
        ax.set_title(f"{name} pose: {score} {float(values[name]):.3f}, target "
                     f"{int(mask.sum())} px (red)", fontsize=9)
        ax.axis("off")
    if saliency is not None:  # under each view, the actor's saliency on its own image of it
        vmax = max(float(np.max(v["saliency"])) for v in saliency.values()) or 1.0
        ax = fig.add_subplot(rows, cols, cols + 1)
        ax.axis("off")
        ax.text(0.0, 0.6, "Right: the actor's saliency, |d action / d pixel|\n"
                "(every action dimension, RGB and depth), on the\nimage it sees from each "
                f"pose; warm = larger\n(square-root scale, one scale for "
                f"{'both' if len(names) == 2 else 'all'}), grey = 0.",
                fontsize=9, va="center", ha="left", transform=ax.transAxes)
        for i, name in enumerate(names):
            ax = fig.add_subplot(rows, cols, cols + 2 + i)
            _draw_saliency(ax, saliency[name], vmax)
            ax.set_title(f"{name}: the actor's |d action / d pixel| (RGB-D)\n"
                         f"{_share_text(saliency[name])}", fontsize=9)
            ax.axis("off")
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
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
    per, _ = _action_jacobian(env, actor, actor_params, joints, coords, pixels, tuple(spec))
    return per if per_channel else jnp.sum(per[..., :RGBD], axis=-1)


def _action_jacobian(env, actor: Network, actor_params, joints, coords, pixels, keys,
                     aux=None) -> tuple[jax.Array, jax.Array | None]:
    """``saliency``'s ``per_channel`` map (n, n, 5) of the actor reading the observation's
    ``keys`` of ``pixels``, and ``aux(obs, action)`` of the same forward pass (None without)."""
    joints = jnp.asarray(joints, jnp.float32)
    coords = jnp.asarray(coords, jnp.float32)

    def action(px):
        obs = env.observation_from_image(joints, coords, px[..., :3], px[..., 3], px[..., 4],
                                         keys=keys)
        a = actor.apply(actor_params, obs)
        return jnp.reshape(a, (-1,)), None if aux is None else aux(obs, a)

    jac, extra = jax.jacrev(action, has_aux=True)(jnp.asarray(pixels, jnp.float32))
    return jnp.sum(jnp.abs(jac), axis=0), extra  # jac: (actions, n, n, 5)


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


def look(env, actor: Network, actor_params, obs, poses: dict[str, object], *, q=None,
         q_params=None, grid: tuple[int, int] | None = None, distance_coord=None) -> dict:
    """The figures' numbers of a measured observation and poses already chosen, with no ascent
    (``twinrl run`` draws its report's figures from the pose its deployment chose): the
    simulator's state of ``obs`` (``twinrl.sim2real.active.sim_state``, as the deployment reads
    it off the robot) and per pose of ``poses`` (name -> unconstrained mount coordinates)
    ``saliency_views``'s ``{"rgb", "mask", "saliency"}`` plus ``"q"``, Q on that hard image
    (nan without ``q``), under ``"views"``; with ``q`` and ``grid``, Q over
    ``workspace_grid(env.mount, distance_coord, grid)`` as ``"landscape"``: ``(azimuths,
    elevations, values (E, A))``.

    One small program, compiled once: a ``lax.map`` over the poses and the grid's of one pose's
    render, the actor's observation of it, Q and the actor's Jacobian (the saliency: computed
    at the grid's poses too, since a second program for them alone would cost a second
    compilation, which is most of the time). On the needle (the pose fit inside), 2 + 77
    poses: 30 s of CPU to trace and compile it, 1.3 s to run; ``sense``'s ascent, landscape,
    160-pixel views and saliency take 155 s of CPU."""
    from twinrl.learn.camera_choice import observed_keys, q_value, workspace_grid
    from twinrl.sim2real.active import sim_state

    n = image_size(env, actor)
    names = list(poses)
    keys = tuple(actor.obs_spec) if q is None else observed_keys(actor, q)
    at = np.asarray([poses[k] for k in names], np.float32).reshape(-1, 3)
    az = el = None
    if q is not None and grid is not None:
        az, el, coords = workspace_grid(env.mount, float(distance_coord), grid)
        at = np.concatenate([at, coords.astype(np.float32)])

    def value(o, a):
        return jnp.float32(jnp.nan) if q is None else q_value(q, q_params, o, a)

    @jax.jit
    def run(obs, at):
        state = sim_state(env, obs)
        joints = state.obs[:14]

        def see(c):  # one pose: its image, Q there and the actor's saliency on it
            px = env.image_observation(state, c, size=n, keys=("pixels/mount",))["pixels/mount"]
            per, v = _action_jacobian(env, actor, actor_params, joints, c, px, keys, value)
            return px, jnp.sum(per[..., :RGBD], axis=-1), v

        return jax.lax.map(see, at)

    px, sal, values = (np.asarray(x) for x in run(jnp.asarray(obs, jnp.float32),
                                                  jnp.asarray(at)))
    out = {"views": {name: {"rgb": px[i, ..., :3], "mask": px[i, ..., 4] > 0.5,
                            "saliency": sal[i], "q": float(values[i])}
                     for i, name in enumerate(names)}}
    if az is not None:
        out["landscape"] = (az, el, values[len(names):].reshape(len(el), len(az)))
    return out


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
