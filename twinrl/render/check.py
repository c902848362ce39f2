"""The differentiable renderer against MuJoCo's OpenGL on any MJCF (``twinrl render --env FILE``).

``gradcheck`` tells a user whether the physics' gradients hold on *their* MJCF; this tells them
whether ``twinrl.render.Renderer`` draws their scene as MuJoCo does before they fit a camera or an
object to images through it. ``compare`` renders one state of a model from one camera with both --
``CameraRenderer`` (``mujoco.Renderer``, OpenGL) and ``Renderer`` (hard image, ``tau = 0``) -- and
measures how far they agree: depth where both see the same geom (OpenGL tessellates curved geoms,
so a few mm at silhouettes), the share of pixels with the same geom id, and the RGB's PSNR (our
shading is OpenGL's fixed-function model without textures or reflections). A model without a
camera gets MuJoCo's default free view as a fixed camera (``with_view_camera``), so both renderers
read the very same camera from the model. ``check_mjcf`` does all of it for an MJCF file and
writes the images.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

__all__ = ["VIEW", "with_view_camera", "compare", "figure", "gradcheck", "GRAD_RTOL",
           "crowding", "check_mjcf", "SceneError"]

VIEW = "twinrl_view"
"""Name of the camera ``with_view_camera`` adds."""


def with_view_camera(spec: mujoco.MjSpec) -> mujoco.MjModel:
    """``spec`` compiled with a fixed camera ``VIEW`` where MuJoCo's viewer opens: looking at
    ``stat.center`` from ``1.5 stat.extent`` away, at the model's ``<visual><global azimuth
    elevation fovy>`` (``mjv_defaultFreeCamera``)."""
    m = spec.compile()
    g = m.vis.global_
    az, el = np.deg2rad(g.azimuth), np.deg2rad(g.elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down
        right = np.array([np.sin(az), -np.cos(az), 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.stack([right, up, -forward], axis=1).reshape(-1))
    pos = np.asarray(m.stat.center) - 1.5 * float(m.stat.extent) * forward
    spec.worldbody.add_camera(name=VIEW, pos=pos, quat=quat, fovy=float(g.fovy))
    return spec.compile()


def compare(model: mujoco.MjModel, data: mujoco.MjData, camera: str | int, width: int,
            height: int, **renderer) -> dict:
    """Both renderers' images of ``data`` (after ``mj_forward``) from ``camera`` and how far they
    agree. Returns ``{"opengl": images, "twinrl": images, "figures": {...}}`` (images: ``rgb``
    uint8, ``depth`` metres, ``segmentation`` geom ids, -1 for none). Raises
    ``renderer.UnsupportedGeomError`` for a geom type ``Renderer`` cannot draw and ``ValueError``
    for a size beyond the model's offscreen buffer or an unknown camera. ``renderer``:
    ``Renderer.create``'s settings (``layers``, ``cull_above``, ...)."""
    from twinrl.render import Camera, Geoms, Renderer
    from twinrl.render.opengl import CameraRenderer

    gl_renderer = CameraRenderer(model, width, height)
    try:
        gl = gl_renderer.images(data, camera)
    finally:
        gl_renderer.close()
    renderer = Renderer.create(model, **renderer)
    im = renderer.render(Camera.from_mujoco(model, data, camera, width, height),
                         Geoms.from_mujoco(model, data))
    ours = {"rgb": (np.clip(np.asarray(im.rgb, np.float64), 0, 1) * 255).round().astype(np.uint8),
            "depth": np.asarray(im.depth, np.float32),
            "segmentation": np.asarray(im.segmentation, np.int32)}
    same = ours["segmentation"] == gl["segmentation"]
    seen = same & (gl["segmentation"] >= 0)
    dd = np.abs(ours["depth"].astype(np.float64) - gl["depth"])
    mse = float(np.mean((ours["rgb"].astype(np.float64) - gl["rgb"]) ** 2))
    figures = {
        "pixels": int(same.size),
        "geom_pixels_opengl": int(np.sum(gl["segmentation"] >= 0)),
        "segmentation_agreement": float(np.mean(same)),
        "depth_mean_abs_m": float(dd[seen].mean()) if seen.any() else None,
        "depth_p99_abs_m": float(np.quantile(dd[seen], 0.99)) if seen.any() else None,
        "rgb_psnr_db": float("inf") if mse == 0 else float(10 * np.log10(255.0 ** 2 / mse)),
        "geoms_drawn": int(renderer.ngeom),
        "textures": int(model.ntex),  # not drawn by ``Renderer``: the RGB differs there
    }
    return {"opengl": gl, "twinrl": ours, "figures": figures}


def figure(result: dict, far: float, path: str | Path, title: str = "") -> Path:
    """A 2 x 4 grid of ``compare``'s images: OpenGL on top, ours below (RGB, depth on one colour
    scale, segmentation in one palette), and where they differ (depth error in mm where both see
    the same geom; red where the geom ids differ)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gl, ours = result["opengl"], result["twinrl"]
    valid = [d[d < 0.999 * far] for d in (gl["depth"], ours["depth"])]
    both = np.concatenate(valid)
    lo, hi = (float(both.min()), float(both.max())) if both.size else (0.0, 1.0)
    palette = np.random.default_rng(0).uniform(0.25, 1.0, size=(256, 3))
    seg_rgb = lambda s: np.where((s >= 0)[..., None], palette[np.mod(s, 256)], 0.0)
    fig, axes = plt.subplots(2, 4, figsize=(13, 6.2))
    for row, (name, im) in enumerate((("OpenGL (mujoco.Renderer)", gl), ("twinrl.render", ours))):
        depth = np.ma.masked_where(im["depth"] >= 0.999 * far, im["depth"])
        axes[row, 0].imshow(im["rgb"])
        axes[row, 0].set_ylabel(name)
        axes[row, 1].imshow(depth, cmap="viridis", vmin=lo, vmax=max(hi, lo + 1e-6))
        axes[row, 2].imshow(seg_rgb(im["segmentation"]))
    same = ours["segmentation"] == gl["segmentation"]
    err = np.where(same & (gl["segmentation"] >= 0), np.abs(ours["depth"] - gl["depth"]) * 1e3,
                   np.nan)
    shown = axes[0, 3].imshow(err, cmap="magma", vmin=0, vmax=max(np.nanmax(err), 1e-3)
                              if np.isfinite(err).any() else 1.0)
    fig.colorbar(shown, ax=axes[0, 3], fraction=0.046, label="|depth difference| (mm)")
    diff = np.zeros(same.shape + (3,))
    diff[~same] = (1.0, 0.1, 0.1)
    axes[1, 3].imshow(diff)
    f = result["figures"]
    for ax, label in zip(axes[0], ("RGB", "depth", "segmentation", "depth error, same geom")):
        ax.set_title(label, fontsize=10)
    axes[1, 3].set_title(f"geom ids differ ({100 * (1 - f['segmentation_agreement']):.3f} %)",
                         fontsize=10)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    depth_txt = ("no geom seen" if f["depth_mean_abs_m"] is None else
                 f"depth mean {1e3 * f['depth_mean_abs_m']:.3f} mm, "
                 f"p99 {1e3 * f['depth_p99_abs_m']:.2f} mm")
    fig.suptitle(f"{title}  --  same geom id on {100 * f['segmentation_agreement']:.3f} % of "
                 f"pixels; {depth_txt}; RGB PSNR {f['rgb_psnr_db']:.1f} dB", fontsize=11)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


GRAD_RTOL = 0.05
"""``gradcheck``'s tolerance on a group's relative error (the renderer's tests' own)."""


def gradcheck(model: mujoco.MjModel, data: mujoco.MjData, camera: str | int, width: int = 64,
              height: int = 48, *, tau: float = 0.5, eps: float = 1e-6, seed: int = 0,
              **renderer) -> list:
    """The soft image's gradient against float64 central differences on ``model`` (module
    docstring). Returns one row per group: ``{"group", "entries", "grad_norm", "fd_norm",
    "rel_err", "ok"}``, groups ``camera.pos``, ``camera.rot`` and ``<geom>.pos|size|rgb`` for
    each drawn geom (a group neither side moves is ``inert``: ``rel_err`` 0)."""
    import jax
    import jax.numpy as jnp
    from jax.flatten_util import ravel_pytree

    from twinrl.render import Camera, Geoms, Renderer

    with jax.enable_x64(True):
        R = Renderer.create(model, **{"iters": 40, **renderer, "shadows": False})
        ids = np.asarray(R.geom_ids)
        cam = Camera.from_mujoco(model, data, camera, width, height, dtype=jnp.float64)
        g = Geoms.from_mujoco(model, data, dtype=jnp.float64)
        rng = np.random.default_rng(seed)
        w_rgb = jnp.asarray(rng.normal(size=(height, width, 3)))
        w_depth = jnp.asarray(rng.normal(size=(height, width)))
        p0 = {"camera": {"pos": jnp.zeros(3), "rot": jnp.zeros(3)},
              "geom": {"pos": jnp.zeros((ids.size, 3)), "size": g.size[ids],
                       "rgb": g.rgba[ids, :3]}}

        def loss(p):
            c = cam.rotated(p["camera"]["rot"]).translated(p["camera"]["pos"])
            q = p["geom"]
            im = R.render(c, g.replace(xpos=g.xpos.at[ids].add(q["pos"]),
                                       size=g.size.at[ids].set(q["size"]),
                                       rgba=g.rgba.at[ids, :3].set(q["rgb"])), tau=tau)
            return jnp.mean(w_rgb * im.rgb) + jnp.mean(w_depth * im.depth)

        x0, unravel = ravel_pytree(p0)
        grad = np.asarray(ravel_pytree(jax.jit(jax.grad(loss))(p0))[0])
        flat = jax.jit(jax.vmap(lambda x: loss(unravel(x))))
        eye = np.eye(x0.size) * eps
        fd = np.concatenate([  # in chunks: a few hundred renders, each a vmapped batch
            (np.asarray(flat(x0 + e)) - np.asarray(flat(x0 - e))) / (2 * eps)
            for e in np.array_split(eye, max(1, x0.size // 32))])
    index = np.arange(x0.size)
    slices = {k: v for k, v in zip(("camera.pos", "camera.rot"), np.split(index[:6], 2))}
    rest = index[6:].reshape(3, ids.size, 3)  # ravel_pytree: geom fields pos, rgb, size
    names = [_geom_label(model, int(i)) for i in ids]
    for k, field in enumerate(("pos", "rgb", "size")):
        for j, name in enumerate(names):
            slices[f"{name}.{field}"] = rest[k, j]
    rows = []
    # below this a group's differences are rounding (the loss is O(1), eps 1e-6): a geom out of
    # view whose coverage is exp(-huge) has a gradient of 1e-60 and differences of exactly 0
    floor = max(1e-8, 1e-6 * max(float(np.linalg.norm(fd[i])) for i in slices.values()))
    for group, idx in slices.items():
        gn, fn = float(np.linalg.norm(grad[idx])), float(np.linalg.norm(fd[idx]))
        err = float(np.linalg.norm(grad[idx] - fd[idx]))
        rel = 0.0 if err == 0 else err / max(fn, floor)
        rows.append({"group": group, "entries": int(len(idx)), "grad_norm": gn, "fd_norm": fn,
                     "rel_err": rel, "ok": bool(np.isfinite(gn) and rel <= GRAD_RTOL),
                     "inert": gn == 0 and fn == 0})
    order = ["camera.pos", "camera.rot"] + [f"{n}.{f}" for n in names
                                            for f in ("pos", "size", "rgb")]
    return sorted(rows, key=lambda r: order.index(r["group"]))


def _geom_label(model: mujoco.MjModel, i: int) -> str:
    """A geom's name, else ``body:type#id`` (an unnamed geom is named by what holds it)."""
    if model.geom(i).name:
        return model.geom(i).name
    body = model.body(int(model.geom_bodyid[i])).name or f"body{int(model.geom_bodyid[i])}"
    kind = mujoco.mjtGeom(int(model.geom_type[i])).name.removeprefix("mjGEOM_").lower()
    return f"{body}:{kind}#{i}"


def crowding(model: mujoco.MjModel, **renderer) -> dict | None:
    """Why ``Renderer.create(model, **renderer)`` draws the soft image from each pixel's leading
    surfaces only (module docstring): ``{"why": text, "cull_above": n, "layers": n}``, the
    settings that composite every surface; ``None`` if it composites every surface already."""
    from twinrl.render import Renderer

    R = Renderer.create(model, **renderer)
    groups = R.groups()
    culled = [f"{len(idx)} {mujoco.mjtGeom(int(t)).name.removeprefix('mjGEOM_').lower()}s"
              for t, idx in groups if R.culled(t, idx)]
    slots = sum(R.per_pixel if R.culled(t, idx) else len(idx) for t, idx in groups)
    if not culled and slots <= R.layers:
        return None
    why = []
    if culled:
        why.append(f"{', '.join(culled)} (more than cull_above={R.cull_above} of a type)")
    if slots > R.layers:
        why.append(f"{slots} surfaces to composite per pixel (more than layers={R.layers})")
    every = max(R.cull_above, max(len(idx) for _, idx in groups))
    return {"why": f"this scene has {' and '.join(why)}: the soft image composites each pixel's "
                   "leading surfaces, which switch as geoms move",
            "cull_above": every, "layers": max(R.layers, len(R.geom_ids))}


class SceneError(ValueError):
    """An MJCF ``check_mjcf`` cannot draw: MuJoCo cannot load it, it holds a geom type the
    renderer lacks, the size exceeds its offscreen buffer, or the camera is not in it."""


def check_mjcf(path: str | Path, out: str | Path, width: int, height: int, *,
               camera: str | None = None, steps: int = 0, with_gradcheck: bool = False,
               progress=None, **renderer) -> tuple[dict, mujoco.MjModel]:
    """The MJCF at ``path`` drawn by OpenGL and by ``Renderer`` side by side (``compare``), from
    ``camera`` (default: the model's first, else MuJoCo's free view, ``with_view_camera``) after
    ``steps`` physics steps without actuation from its first keyframe (else ``qpos0``); with
    ``with_gradcheck``, the soft image's gradient against central differences too
    (``gradcheck``). Writes ``out/compare.png``, ``out/opengl_rgb.png`` and
    ``out/twinrl_rgb.png``. ``progress(text)`` hears what is being done; ``renderer``:
    ``Renderer.create``'s settings (``layers``, ``cull_above``).

    Returns ``(summary, model)``: ``{"mjcf", "camera", "size", "steps", "renderer", "figures",
    "gradcheck", "files"}`` (``gradcheck`` None without the check), and the model drawn (with
    the added camera where it has one). Raises ``SceneError`` for an MJCF it cannot draw."""
    import imageio.v2 as imageio

    from twinrl.physics import mujoco_warnings

    path, out, say = Path(path), Path(out), progress or (lambda text: None)
    try:
        with mujoco_warnings(str(path)):
            spec = mujoco.MjSpec.from_file(str(path))
            model = spec.compile()
            camera = camera or (model.camera(0).name or 0 if model.ncam else None)
            if camera is None:
                model, camera = with_view_camera(spec), VIEW
    except ValueError as e:  # MuJoCo's parse and compile errors
        raise SceneError(" ".join(str(e).split())) from None
    data = mujoco.MjData(model)
    if model.nkey:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    with mujoco_warnings(f"{path}: {steps} steps"):
        mujoco.mj_step(model, data, nstep=int(steps))
        mujoco.mj_forward(model, data)
    out.mkdir(parents=True, exist_ok=True)
    say(f"rendering {path.name} with OpenGL and twinrl.render...")
    try:
        result = compare(model, data, camera, width, height, **renderer)
    except ValueError as e:  # hfield/SDF geoms (UnsupportedGeomError); size; camera name
        raise SceneError(str(e)) from None
    far = float(model.vis.map.zfar * model.stat.extent)
    files = {"compare": figure(result, far, out / "compare.png", f"{path.name}, camera {camera!r}")}
    for side in ("opengl", "twinrl"):
        files[f"{side}_rgb"] = out / f"{side}_rgb.png"
        imageio.imwrite(files[f"{side}_rgb"], result[side]["rgb"])
    grads = None
    if with_gradcheck:
        say("the soft image's gradient against central differences (float64, 64x48)...")
        grads = gradcheck(model, data, camera, **renderer)
    summary = {"mjcf": str(path), "camera": camera if isinstance(camera, str) else int(camera),
               "size": [width, height], "steps": int(steps), "renderer": renderer,
               "figures": result["figures"], "gradcheck": grads,
               "files": {k: str(v) for k, v in files.items()}}
    return summary, model
