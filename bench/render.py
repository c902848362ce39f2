"""Benchmark of the differentiable renderer (twinrl.render) and of visual Real2Sim.

1. Speed: frames/s at 64x64 and 128x128 (``--sizes``), batch 1 and 16 (``--batches``; vmap over
   cameras): the hard image (what the arm tasks observe), the soft image (tau = 0.5) forward only
   and forward + gradient (of an image loss w.r.t. the camera and the geoms: poses, sizes,
   colours), on each scene of ``--scenes`` (``SPEED_SCENES``: push and the manipulation suite's
   arm scenes, peg insertion, spatula flipping and needle threading, each seen from its ``mount``
   camera in the state of its task's ``reset``; the table gives each scene's geom count).
   Then a batch of 16 image observations of each arm task in ``--scenes`` (``observations``:
   ``ArmTask.image_observation``'s pixels, what the image actor and Q learn from).
   Then the floor (``floor``, ``--no-floor`` skips it): the simplest soft image written in JAX
   (spheres, coverage, composite, Lambert), timed alike: what XLA on this machine gives at best.
2. Geom-count sweep (``--sweep``, default 10 20 40): synthetic arm-like scenes (``sweep_mjcf``: a
   floor and capsule, box, cylinder and sphere links, ``--sweep-layouts``: ``dense``, a chain
   always in the same volume, so that more links overlap more; ``tiled``, one link a cell of a
   grid over the same floor, so that only the count grows), 64x64, batch 16; the cost of 40
   geoms against 10, and how far per-pixel culling and layers move the
   image from the renderer's without either (hard segmentation agreement; soft RGB: largest and
   mean difference, pixels off by more than 0.01).
3. Agreement with OpenGL (``mujoco.Renderer``) on every bundled scene: mean |depth difference|,
   segmentation agreement, RGB PSNR.
4. Visual Real2Sim (``--visual``): over seeds, hidden camera offsets of 3-4 cm and 5-6 degrees
   (``Perturbation`` constructed directly) and a hidden object pose/size/colour change on
   ``push``; (a) camera fitted with the scene known, (b) the box fitted with the camera known.
   Frames are ``--size`` square (default 256: a real RGB-D camera's resolution order, where a
   pixel is 3.75 mm at the box), ``--frames`` of them (default 5); the Adam stage sees every
   4th pixel (``--coarse`` 64), the refinement every pixel.

Images nobody differentiates (the hard image, the soft forward) are drawn by the C++ kernel
(``twinrl.render.native``; ``meta.native`` in the JSON says whether it was on); ``--jax`` also
times this renderer with the kernel off, interleaved (the column "vs JAX" is the kernel's
speed-up). ``--baseline REF`` also times the renderer of git revision REF (``twinrl/render`` as
it was there, loaded beside this one), interleaved with this one call by call, so that both see
the same machine load; speed rows then carry both and their ratio. Timings are the best of
``--repeats`` calls after a warm-up call. Prints tables, writes ``DIR/render.json``.

    python bench/render.py --out bench/results                 # speed, sweep, agreement
    python bench/render.py --out /tmp/r --baseline main        # ... against main's renderer
    python bench/render.py --out /tmp/r --no-speed --visual    # visual Real2Sim, 5 seeds
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, jaxconfig)
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twinrl import report  # noqa: E402
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)
from twinrl.physics import load_mjcf  # noqa: E402
from twinrl.physics.scenes import SCENES  # noqa: E402
from twinrl.render import Camera, Geoms, Renderer, native, quat_to_mat  # noqa: E402
from twinrl.render import camera as camera_module  # noqa: E402
from twinrl.render import renderer as renderer_module  # noqa: E402

CAMS = {"cartpole": ("front", [0.3, 0.5]), "pendulum": ("front", [0.7]),
        "push": ("top", None), "peg_in_hole": ("front", [0.01, -0.02])}
ARM_TASKS = ("peg_insertion", "spatula_flipping", "needle_threading")
SPEED_SCENES = ["push", *ARM_TASKS]
"""Scenes of the speed table: bundled scene names (``load_mjcf``) or arm tasks (``envs.make``),
each with its camera in ``SPEED_CAMERAS``."""
SPEED_CAMERAS = {"push": "top", **{t: "mount" for t in ARM_TASKS}}
TAU = 0.5


SWEEP_LAYOUTS = ("dense", "tiled")


def sweep_mjcf(n: int, seed: int = 0, layout: str = "dense") -> str:
    """MJCF of a floor, a light and ``n`` primitive links (capsule, box, cylinder, sphere in
    turn), seen by camera ``top``. ``layout="dense"``: links 2-3 cm thick and 6-10 cm long laid
    along a random walk that stays in the same 0.5 m x 0.5 m x 0.3 m volume whatever ``n`` (so
    more links overlap more: at 41 geoms a pixel composites about twice the surfaces it does at
    11). ``layout="tiled"``: the same kind of links, 5-7 cm long, one lying in each cell of a
    grid over the same 0.5 m x 0.5 m of floor (more links cover more of the image and hardly
    overlap: a pixel meets about as many surfaces at 41 geoms as at 11, and only the count of
    geoms in the scene grows)."""
    if layout not in SWEEP_LAYOUTS:
        raise ValueError(f"layout must be one of {SWEEP_LAYOUTS}, got {layout!r}")
    rng = np.random.default_rng(seed)
    kinds = ["capsule", "box", "cylinder", "sphere"]
    links = []

    def link(i, c, axis, rad, half):
        kind = kinds[i % 4]
        size = {"capsule": f"{rad} {half}", "cylinder": f"{rad} {half}",
                "box": f"{rad} {rad * 1.3} {half}", "sphere": f"{1.6 * rad}"}[kind]
        rgba = " ".join(f"{v:.3f}" for v in rng.uniform(0.2, 0.9, 3)) + " 1"
        links.append(f'<geom name="g{i}" type="{kind}" size="{size}" pos="{c[0]:.4f} '
                     f'{c[1]:.4f} {c[2]:.4f}" zaxis="{axis[0]:.4f} {axis[1]:.4f} {axis[2]:.4f}" '
                     f'rgba="{rgba}"/>')

    if layout == "dense":
        p = np.array([0.0, 0.0, 0.15])
        for i in range(n):
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            half = rng.uniform(0.03, 0.05)
            q = np.clip(p + 2 * half * d, [-0.25, -0.25, 0.03], [0.25, 0.25, 0.3])
            c, axis = 0.5 * (p + q), q - p
            link(i, c, axis / max(np.linalg.norm(axis), 1e-9), rng.uniform(0.01, 0.015), half)
            p = q
    else:
        cols = int(np.ceil(np.sqrt(n)))
        rows = int(np.ceil(n / cols))
        cell = np.array([0.5 / cols, 0.5 / rows])
        for i in range(n):
            r, k = divmod(i, cols)
            centre = np.array([-0.25 + (k + 0.5) * cell[0], -0.25 + (r + 0.5) * cell[1]])
            half = rng.uniform(0.025, 0.035)
            rad = rng.uniform(0.01, 0.015)
            yaw = rng.uniform(0, np.pi)
            axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            centre = centre + rng.uniform(-0.1, 0.1, 2) * cell
            link(i, [centre[0], centre[1], 1.7 * rad], axis, rad, half)
    return f"""<mujoco model="{'sweep' if layout == 'dense' else 'tiled'}{n}">
  <visual><global offwidth="640" offheight="480"/></visual>
  <worldbody>
    <light name="top" pos="0 0 3" dir="0 0 -1"/>
    <camera name="top" pos="0 -0.9 0.9" xyaxes="1 0 0 0 0.7071 0.7071"/>
    <geom name="floor" type="plane" size="2 2 0.1" rgba="0.8 0.8 0.8 1"/>
    {chr(10).join('    ' + g for g in links)}
  </worldbody>
</mujoco>"""


def load_baseline(ref: str):
    """``(renderer module, camera module)`` of ``twinrl/render`` at git revision ``ref``, loaded
    as a package of its own beside the working tree's (every file of ``twinrl/render`` at that
    revision, its imports of ``twinrl.render`` pointed at the copy)."""
    repo = Path(__file__).resolve().parents[1]
    pkg = "twinrl_render_baseline"
    root = Path(tempfile.mkdtemp(prefix="render_baseline_"))
    files = subprocess.run(["git", "-C", str(repo), "ls-tree", "-r", "--name-only", ref,
                            "twinrl/render/"], capture_output=True, text=True,
                           check=True).stdout.split()
    for name in files:
        data = subprocess.run(["git", "-C", str(repo), "show", f"{ref}:{name}"],
                              capture_output=True, check=True).stdout
        if name.endswith(".py"):
            data = data.decode().replace("twinrl.render", pkg).encode()
        dest = root / pkg / Path(name).relative_to("twinrl/render")
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_bytes(data)
    sys.path.insert(0, str(root))
    return importlib.import_module(f"{pkg}.renderer"), importlib.import_module(f"{pkg}.camera")


def _cases(mods, m, d, cam_name, S, B, **create):
    """Compiled hard image, soft forward and soft forward+gradient of a batch of ``B`` cameras,
    ``S`` x ``S``, for each renderer implementation in ``mods`` ({label: (renderer module,
    camera module)}; label "jax": this renderer with the C++ kernel off)."""
    out = {}
    for label, (rmod, cmod) in mods.items():
        with _implementation(label):
            out[label] = _compiled(rmod, cmod, m, d, cam_name, S, B, **create)
    return out


def _implementation(label):
    """The context a label's functions are traced in: "jax" with the C++ kernel off."""
    return native.disabled() if label == "jax" else contextlib.nullcontext()


def _compiled(rmod, cmod, m, d, cam_name, S, B, **create):
    """One implementation's three cases ({mode: (compiled function, arguments)})."""
    R = rmod.Renderer.create(m, **create)
    g = rmod.Geoms.from_mujoco(m, d)
    cam = cmod.Camera.from_mujoco(m, d, cam_name, S, S)
    target = R.render(cam, g, tau=TAU).rgb
    # every camera off the target's (batch 1 too): the reverse kernel skips pixels whose
    # cotangent is 0, and a frame equal to its target would cost nothing
    cams = jax.tree_util.tree_map(
        lambda x: jnp.stack([x] * B) + 0.001 * (jnp.arange(B) + 1).reshape((B,) + (1,) * x.ndim),
        cam)

    def loss(c, g):
        return jnp.mean((R.render(c, g, tau=TAU).rgb - target) ** 2)

    hard = jax.jit(jax.vmap(lambda c: R.render(c, g).rgb))
    fwd = jax.jit(jax.vmap(lambda c: R.render(c, g, tau=TAU).rgb))
    grad = jax.jit(jax.vmap(jax.grad(loss, argnums=(0, 1)), in_axes=(0, None)))
    # compiled here, so that the implementation chosen at trace time is this label's
    return {"hard": (hard.lower(cams).compile(), (cams,)),
            "forward": (fwd.lower(cams).compile(), (cams,)),
            "forward+grad": (grad.lower(cams, g).compile(), (cams, g))}


def _time_interleaved(cases, repeats):
    """Best seconds per call of each (label, mode), the labels' calls interleaved."""
    for fns in cases.values():
        for f, a in fns.values():
            jax.block_until_ready(f(*a))  # compile + warm-up
    best = {(k, mode): np.inf for k, fns in cases.items() for mode in fns}
    for _ in range(repeats):
        for k, fns in cases.items():
            for mode, (f, a) in fns.items():
                t = time.perf_counter()
                jax.block_until_ready(f(*a))
                best[k, mode] = min(best[k, mode], time.perf_counter() - t)
    return best


def _rows(best, scene, S, B, labels, **extra):
    rows = []
    for mode in ("hard", "forward", "forward+grad"):
        row = {"scene": scene, "size": S, "batch": B, "mode": mode, **extra}
        for k in labels:
            row[f"frames_per_s_{k}" if k != "new" else "frames_per_s"] = B / best[k, mode]
        if "baseline" in labels:
            row["speedup"] = best["baseline", mode] / best["new", mode]
        if "jax" in labels:
            row["speedup_vs_jax"] = best["jax", mode] / best["new", mode]
        rows.append(row)
    return rows


def _load(scene):
    """(model, camera name, data at the scene's state): an arm task's at its ``reset``."""
    qpos = None
    if scene.startswith(("sweep", "tiled")):
        layout = "dense" if scene.startswith("sweep") else "tiled"
        m = mujoco.MjModel.from_xml_string(sweep_mjcf(int(scene[5:]), layout=layout))
        cam = "top"
    elif scene in ARM_TASKS:
        from twinrl import envs

        env = envs.make(scene)
        m, cam = env.sim.mj_model, SPEED_CAMERAS[scene]
        qpos = np.asarray(env.reset(jax.random.PRNGKey(0)).pipeline_state.qpos)
    else:
        m, cam = load_mjcf(scene), SPEED_CAMERAS.get(scene, CAMS.get(scene, ("top",))[0])
    d = mujoco.MjData(m)
    if qpos is not None:
        d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    return m, cam, d


def _progress(rows):
    """One line of frames/s per mode, as each case finishes (a run cut short still shows them)."""
    print("[bench]   " + ", ".join(f"{r['mode']} {r['frames_per_s']:.4g}" for r in rows)
          + " frames/s", flush=True)


def speed(mods, scenes, sizes=(64, 128), batches=(1, 16), repeats=5):
    rows = []
    for scene in scenes:
        m, cam_name, d = _load(scene)
        for S in sizes:
            for B in batches:
                print(f"[bench] {scene} {S}x{S} batch {B} ...", flush=True)
                best = _time_interleaved(_cases(mods, m, d, cam_name, S, B), repeats)
                rows += _rows(best, scene, S, B, list(mods), geoms=int(m.ngeom))
                _progress(rows[-3:])
    return rows


def candidates(m, d, cam_name, S, band_px):
    """Mean count of link geoms (not planes) a pixel must consider, over the pixels with at least
    one: those whose bounding sphere (``geom_rbound``) the pixel's ray passes within ``band_px``
    pixels of, at the sphere's depth (the soft silhouette's band; 0: the hard image's rays that
    may hit). A bound on what the per-pixel work of the scene is, from geometry alone."""
    cid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, cam_name)
    pos, rot = d.cam_xpos[cid], d.cam_xmat[cid].reshape(3, 3)
    f = 2 * np.tan(np.radians(m.cam_fovy[cid]) / 2) / S  # a pixel's width at unit depth
    u = (np.arange(S) + 0.5 - S / 2) * f
    x, y = np.meshgrid(u, -u)
    r = np.stack([x, y, -np.ones_like(x)], -1) @ rot.T
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    links = [g for g in range(m.ngeom) if m.geom_type[g] != mujoco.mjtGeom.mjGEOM_PLANE]
    c = d.geom_xpos[links] - pos                                   # (G, 3)
    along = r @ c.T                                                # (S, S, G)
    dist = np.sqrt(np.maximum(np.sum(c * c, -1) - along ** 2, 0))
    gap_px = (dist - m.geom_rbound[links]) / (np.maximum(along, 1e-6) * f)
    n = np.sum(gap_px <= band_px, -1)
    return float(np.mean(n[n > 0])) if np.any(n > 0) else 0.0


def sweep(mods, counts, S=64, B=16, repeats=5, layouts=("dense",)):
    """Frames/s against the number of geoms (per ``layouts``, ``sweep_mjcf``), and the culled
    image against the unculled one; ``covered``: the share of pixels whose hard image shows a
    link rather than the floor; ``candidates_hard`` / ``candidates_soft``: ``candidates``, the
    links a pixel near them must consider in the hard and the soft image."""
    rows = []
    for layout, n in [(lay, n) for lay in layouts for n in counts]:
        scene = f"{'sweep' if layout == 'dense' else 'tiled'}{n}"
        m, cam_name, d = _load(scene)
        print(f"[bench] {scene} ({m.ngeom} geoms) {S}x{S} batch {B} ...", flush=True)
        best = _time_interleaved(_cases(mods, m, d, cam_name, S, B), repeats)
        _progress(_rows(best, scene, S, B, list(mods)))
        g = Geoms.from_mujoco(m, d)
        cam = Camera.from_mujoco(m, d, cam_name, S, S)
        culled = Renderer.create(m)
        full = Renderer.create(m, per_pixel=m.ngeom, layers=m.ngeom)  # no culling, no layers
        h1, h2 = culled.render(cam, g), full.render(cam, g)
        s1, s2 = culled.render(cam, g, tau=TAU), full.render(cam, g, tau=TAU)
        diff = np.abs(np.asarray(s1.rgb) - np.asarray(s2.rgb))
        seg = np.asarray(h2.segmentation)
        rows += _rows(best, scene, S, B, list(mods), geoms=int(m.ngeom), layout=layout,
                      covered=float(np.mean(seg > 0)),
                      candidates_hard=candidates(m, d, cam_name, S, 0.0),
                      candidates_soft=candidates(m, d, cam_name, S, 15 * TAU + 2),
                      culled_seg_agreement=float(np.mean(np.asarray(h1.segmentation)
                                                         == np.asarray(h2.segmentation))),
                      culled_soft_rgb_max_diff=float(np.max(diff)),
                      culled_soft_rgb_mean_diff=float(np.mean(diff)),
                      culled_soft_pixels_off=int(np.sum(np.max(diff, -1) > 0.01)))
    return rows


def observations(scenes, with_jax, S=64, B=16, repeats=5):
    """A batch of ``B`` arm tasks' image observations (``ArmTask.image_observation``'s pixels,
    ``S`` x ``S`` hard: what the image actor and Q learn from) a second, from ``B`` reset states
    at the mount's default pose; with ``with_jax`` also with the C++ kernel off, interleaved."""
    from twinrl import envs

    rows = []
    for scene in [s for s in scenes if s in ARM_TASKS]:
        env = envs.make(scene)
        states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), B))
        coords = jnp.broadcast_to(jnp.asarray(env.mount.default, jnp.float32), (B, 3))

        def obs(s, c, env=env):
            return env.image_observation(s, c, size=S, keys=("pixels/mount",))["pixels/mount"]

        print(f"[bench] {scene} image observations {S}x{S} batch {B} ...", flush=True)
        cases = {}
        for label in ["new"] + (["jax"] if with_jax else []):
            with _implementation(label):
                f = jax.jit(jax.vmap(obs)).lower(states, coords).compile()
            cases[label] = {"observation": (f, (states, coords))}
        best = _time_interleaved(cases, repeats)
        row = {"scene": scene, "size": S, "batch": B, "per_s": B / best["new", "observation"]}
        if with_jax:
            row["per_s_jax"] = B / best["jax", "observation"]
            row["speedup_vs_jax"] = best["jax", "observation"] / best["new", "observation"]
        rows.append(row)
    return rows


def selections(scenes, with_jax, S=64, repeats=3):
    """Seconds per camera choice (``sensing.select_camera``: ``SensingConfig``'s restarts and
    Adam steps of the pose through the soft image, then the hard image's score of the checked
    iterates) on each arm task at its reset state, ``S`` x ``S`` views. The networks are
    stand-ins (the actor acts 0; Q is the target's share of the view), so the time is the
    renderer's and its gradient's; with ``with_jax`` also with the C++ kernel off."""
    from twinrl import envs
    from twinrl.learn import sensing
    from twinrl.learn.networks import Network, NetworkConfig

    rows = []
    cfg = sensing.SensingConfig()
    for scene in [s for s in scenes if s in ARM_TASKS]:
        env = envs.make(scene)
        spec = {"state": (env.observation_size,), "pixels/mount": (S, S, 5)}
        na = env.action_size
        actor = Network(lambda k: {}, lambda p, o, na=na: jnp.zeros(o["state"].shape[:-1] + (na,)),
                        0, na, NetworkConfig(), spec)
        q = Network(lambda k: {}, lambda p, o: jnp.mean(o["pixels/mount"][..., 4],
                                                        axis=(-2, -1))[..., None],
                    0, 1, NetworkConfig(), {**spec, "action": (na,)})
        state = env.reset(jax.random.PRNGKey(0))
        key = jax.random.PRNGKey(1)

        def choose(st, k, env=env, q=q, actor=actor):
            return sensing.select_camera(env, q, {}, actor, {}, st, k, cfg).coords

        print(f"[bench] {scene} camera choice {S}x{S} ...", flush=True)
        cases = {}
        for label in ["new"] + (["jax"] if with_jax else []):
            with _implementation(label):  # (a new function each: jit caches traces by it)
                f = jax.jit(lambda s, k: choose(s, k)).lower(state, key).compile()
            cases[label] = {"choice": (f, (state, key))}
        best = _time_interleaved(cases, repeats)
        row = {"scene": scene, "size": S, "restarts": cfg.restarts, "steps": cfg.ascent_steps,
               "seconds": best["new", "choice"]}
        if with_jax:
            row["seconds_jax"] = best["jax", "choice"]
            row["speedup_vs_jax"] = best["jax", "choice"] / best["new", "choice"]
        rows.append(row)
    return rows


def floor(S=64, B=16, n=4, repeats=5):
    """The simplest soft image XLA can be asked for, timed like the renderer: ``n`` spheres in
    front of the camera, each pixel's coverage a sigmoid of its ray's distance to the sphere (in
    pixels), composited front to back with the smooth depth order, Lambert + ambient shading by
    one light, no shadows, no boxes, cylinders, planes or culling; arrays (sphere, pixel) with the
    pixels minor (what XLA's CPU code vectorises best). Forward and forward + gradient w.r.t. the
    camera position and every sphere's centre, radius and colour, batch ``B`` (``jax.vmap``).
    What a renderer written in JAX can reach on this machine at best: the renderer does all of
    this and more per (pixel, geom) pair."""
    rng = np.random.default_rng(0)
    cen = jnp.asarray(np.c_[rng.uniform(-0.2, 0.2, (n, 2)), rng.uniform(0.0, 0.1, n)],
                      jnp.float32)
    rad = jnp.asarray(rng.uniform(0.05, 0.1, n), jnp.float32)
    col = jnp.asarray(rng.uniform(0.2, 1.0, (n, 3)), jnp.float32)
    px = 0.8 / S  # pixel size at unit depth (a ~44 degree field of view)
    u = (jnp.arange(S, dtype=jnp.float32) + 0.5 - S / 2) * px
    rx, ry = (a.ravel() for a in jnp.meshgrid(u, -u))
    rz = -jnp.ones_like(rx)
    light = np.array([0.3, 0.4, 0.866], np.float32)

    def image(pos, cen, rad, col):
        rr = rx * rx + ry * ry + rz * rz
        s, cover, lam = [], [], []
        for g in range(n):  # one (P,) array per sphere and quantity: no slicing, no stacking
            oc = [pos[i] - cen[g, i] for i in range(3)]
            sg = -(oc[0] * rx + oc[1] * ry + oc[2] * rz) / rr  # closest approach
            p = [oc[0] + sg * rx, oc[1] + sg * ry, oc[2] + sg * rz]
            dist = jnp.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2] + 1e-20)
            s.append(sg)
            cover.append(jax.nn.sigmoid(-(dist - rad[g]) / (TAU * px * sg)))
            lam.append(0.3 + 0.7 * jnp.maximum(sum(light[i] * p[i] for i in range(3)) / dist,
                                               0.0))
        rgb = 0.0
        for g in range(n):  # w_g = a_g prod_{k != g} (1 - a_k [k in front of g])
            w = cover[g] * lam[g]
            for k in range(n):
                if k != g:
                    w = w * (1.0 - cover[k] * jax.nn.sigmoid((s[g] - s[k]) / 0.01))
            rgb = rgb + w[:, None] * col[g]
        return rgb  # (P, 3)

    target = image(jnp.array([0.0, 0.0, 1.5]), cen, rad, col)
    cams = (jnp.array([0.0, 0.0, 1.5], jnp.float32)
            + 0.001 * jnp.arange(B, dtype=jnp.float32)[:, None])

    def loss(pos, cen, rad, col):
        return jnp.mean((image(pos, cen, rad, col) - target) ** 2)

    fwd = jax.jit(jax.vmap(image, in_axes=(0, None, None, None)))
    grad = jax.jit(jax.vmap(jax.grad(loss, argnums=(0, 1, 2, 3)), in_axes=(0, None, None, None)))
    best = _time_interleaved({"new": {"forward": (fwd, (cams, cen, rad, col)),
                                      "forward+grad": (grad, (cams, cen, rad, col))}}, repeats)
    return [{"scene": f"floor: {n} spheres", "geoms": n, "size": S, "batch": B, "mode": mode,
             "frames_per_s": B / best["new", mode]} for mode in ("forward", "forward+grad")]


def agreement(S=64):
    from twinrl.render.opengl import CameraRenderer

    rows = []
    for scene in SCENES:
        cam_name, qpos = CAMS[scene]
        m = load_mjcf(scene)
        d = mujoco.MjData(m)
        if qpos is not None:
            d.qpos[:] = qpos
        mujoco.mj_forward(m, d)
        gl_r = CameraRenderer(m, S, S)
        gl = gl_r.images(d, cam_name)
        gl_r.close()
        im = Renderer.create(m).render(Camera.from_mujoco(m, d, cam_name, S, S),
                                       Geoms.from_mujoco(m, d))
        seg = np.asarray(im.segmentation)
        dd = np.abs(np.asarray(im.depth) - gl["depth"])
        mse = np.mean((np.clip(np.asarray(im.rgb), 0, 1) * 255 - gl["rgb"]) ** 2)
        rows.append({"scene": scene, "depth_mean_abs_m": float(dd.mean()),
                     "depth_mean_abs_on_geoms_m": float(dd[seg >= 0].mean()),
                     # a pixel OpenGL's tessellated silhouette gives to the background (far plane,
                     # ~200 m away) dominates the plain mean; this is the mean where both agree
                     "depth_mean_abs_where_seg_agrees_m": float(
                         dd[seg == gl["segmentation"]].mean()),
                     "segmentation_agreement": float(np.mean(seg == gl["segmentation"])),
                     "rgb_psnr_db": float(10 * np.log10(255.0 ** 2 / mse))})
    return rows


# ---------------------------------------------------------------------- visual real2sim
def _rot_err_deg(q1, q2):
    A, B = np.asarray(quat_to_mat(jnp.asarray(q1))), np.asarray(quat_to_mat(jnp.asarray(q2)))
    return float(np.rad2deg(np.arccos(np.clip((np.trace(A.T @ B) - 1) / 2, -1, 1))))


def _real_frames(m_real, S, qposes):
    from twinrl.render.opengl import render_states

    frames = render_states(m_real, "top", qposes, S, S)
    d = mujoco.MjData(m_real)
    d.qpos[:] = qposes[-1]
    mujoco.mj_forward(m_real, d)
    cam = Camera.from_mujoco(m_real, d, "top", S, S)
    return frames, cam


def visual(seeds, S, cfg):
    from twinrl.real.perturbation import Perturbation
    from twinrl.real2sim import visual as V

    m = load_mjcf("push")
    d0 = mujoco.MjData(m)
    mujoco.mj_forward(m, d0)
    cam0 = Camera.from_mujoco(m, d0, "top", S, S)
    box = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "box")
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(1000 + seed)
        extra = np.random.default_rng(2000 + seed)
        unit = lambda v: v / np.linalg.norm(v)  # noqa: E731
        pos_off = unit(rng.normal(size=3)) * rng.uniform(0.03, 0.04)
        rot_off = unit(rng.normal(size=3)) * np.deg2rad(rng.uniform(5.0, 6.0))
        pert = Perturbation(camera_pos_offset=tuple(pos_off), camera_rot_offset=tuple(rot_off))
        qposes = []
        for k in range(cfg["frames"]):
            # frames past the third come from their own stream: the hidden values (drawn next)
            # stay the same whatever the number of frames
            r = rng if k < 3 else extra
            q = m.qpos0.copy()
            q[0:2] = r.uniform(-0.12, 0.12, 2)
            q[2:4] = np.array([0.15, 0.0]) + r.uniform(-0.05, 0.05, 2)
            qposes.append(q)
        # (a) camera, scene known
        m_real = load_mjcf("push")
        pert.apply(m_real)
        frames, true_cam = _real_frames(m_real, S, qposes)
        t = time.perf_counter()
        cam, info = V.fit_camera(m, V.check_frames(frames, m.nq), cam0, cfg["camera"], seed)
        t_cam = time.perf_counter() - t
        # (b) object, camera known: the real box is moved, resized and recoloured (hidden)
        m_obj = load_mjcf("push")
        pert.apply(m_obj)
        scale = np.exp(rng.uniform(-0.12, 0.12, 3))
        m_obj.geom_size[box] *= scale
        rgb_true = np.clip(m.geom_rgba[box, :3] + rng.uniform(-0.12, 0.12, 3), 0.05, 0.95)
        m_obj.geom_rgba[box, :3] = rgb_true
        dpos = np.r_[rng.uniform(-0.015, 0.015, 2), 0.0]
        dz = m_obj.geom_size[box, 2] - m.geom_size[box, 2]  # the box still rests on the floor
        qposes_b = [q.copy() for q in qposes]
        for q in qposes_b:
            q[2:5] += dpos + np.array([0, 0, dz])
        frames_b, _ = _real_frames(m_obj, S, qposes_b)
        frames_b = [{**f, "qpos": q} for f, q in zip(frames_b, qposes)]  # the nominal guess
        t = time.perf_counter()
        res = V.fit_object(m, V.check_frames(frames_b, m.nq), true_cam, "box", cfg["object"],
                           seed)
        t_obj = time.perf_counter() - t
        true_off = dpos + np.array([0, 0, dz])
        rows.append({
            "seed": seed,
            "hidden_cam_offset_mm": float(np.linalg.norm(pos_off) * 1e3),
            "hidden_cam_rot_deg": float(np.rad2deg(np.linalg.norm(rot_off))),
            "cam_pos_err_mm_before": float(np.linalg.norm(cam0.pos - true_cam.pos) * 1e3),
            "cam_pos_err_mm": float(np.linalg.norm(np.asarray(cam.pos - true_cam.pos)) * 1e3),
            "cam_rot_err_deg_before": _rot_err_deg(cam0.quat, true_cam.quat),
            "cam_rot_err_deg": _rot_err_deg(cam.quat, true_cam.quat),
            "obj_pos_err_mm_before": float(np.linalg.norm(true_off) * 1e3),
            "obj_pos_err_mm": float(np.linalg.norm(res["pos_offset"] - true_off) * 1e3),
            "size_err_pct_before": float(np.max(np.abs(m.geom_size[box] / m_obj.geom_size[box]
                                                       - 1)) * 100),
            "size_err_pct": float(np.max(np.abs(res["size"] / m_obj.geom_size[box] - 1)) * 100),
            "colour_err_255_before": float(np.max(np.abs(m.geom_rgba[box, :3] - rgb_true)) * 255),
            "colour_err_255": float(np.max(np.abs(res["rgb"] - rgb_true)) * 255),
            "seconds_camera": t_cam, "seconds_object": t_obj,
        })
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench/results"),
                    help="directory of render.json")
    ap.add_argument("--scenes", nargs="*", default=SPEED_SCENES,
                    help="scenes of the speed table (bundled names or arm tasks)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128],
                    help="image sizes of the speed table")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16],
                    help="batch sizes (cameras per call) of the speed table; the floor and the "
                         "sweep are at batch 16")
    ap.add_argument("--sweep", type=int, nargs="*", default=[10, 20, 40],
                    help="link counts of the geom-count sweep (none: skip it)")
    ap.add_argument("--sweep-layouts", nargs="+", choices=SWEEP_LAYOUTS,
                    default=list(SWEEP_LAYOUTS),
                    help="dense: the links in one volume, overlapping more as they grow; tiled: "
                         "one a cell of a grid over the floor, hardly overlapping")
    ap.add_argument("--baseline", default=None, metavar="REF",
                    help="also time twinrl/render of this git revision, interleaved")
    ap.add_argument("--jax", action="store_true",
                    help="also time this renderer with its C++ kernel off (images and their "
                         "gradients drawn in JAX, as before the kernel), interleaved")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--no-floor", dest="floor", action="store_false",
                    help="skip the floor (the simplest soft image in JAX, timed alike)")
    ap.add_argument("--visual", action="store_true", help="also run the visual Real2Sim fits")
    ap.add_argument("--no-speed", action="store_true", help="skip the speed table and sweep")
    ap.add_argument("--no-agreement", action="store_true")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--size", type=int, default=256, help="image size of the visual fits' frames")
    ap.add_argument("--frames", type=int, default=5, help="frames per visual fit")
    ap.add_argument("--coarse", type=int, default=64,
                    help="image size the Adam stage sees (VisualConfig.coarse_size)")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--refine-iters", type=int, default=30,
                    help="Levenberg-Marquardt iterations after Adam (0: Adam only)")
    args = ap.parse_args(argv)
    if args.out.suffix == ".json":
        ap.error(f"--out is a directory now (render.json is written into it), got {args.out}")
    out = {"meta": {"cpu_count": os.cpu_count(), "jax": jax.__version__,
                    "mujoco": mujoco.__version__, "devices": str(jax.devices()),
                    "machine": platform.machine(), "load_average": list(os.getloadavg()),
                    "baseline": args.baseline}}
    out["meta"]["native"] = native.status()
    mods = {"new": (renderer_module, camera_module)}
    if args.jax:
        mods["jax"] = (renderer_module, camera_module)
    if args.baseline:
        mods["baseline"] = load_baseline(args.baseline)
    cols = (["frames/s"] + (["JAX f/s", "vs JAX"] if args.jax else [])
            + (["baseline f/s", "speedup"] if args.baseline else []))

    def cells(r):
        return ([r["frames_per_s"]]
                + ([r["frames_per_s_jax"], r["speedup_vs_jax"]] if args.jax else [])
                + ([r["frames_per_s_baseline"], r["speedup"]] if args.baseline else []))

    if not args.no_speed:
        t0 = time.perf_counter()
        out["speed"] = speed(mods, args.scenes, sizes=args.sizes, batches=args.batches,
                             repeats=args.repeats)
        report.print_table(f"renderer speed (hard image; soft image, tau {TAU})",
                           ["scene", "geoms", "size", "batch", "mode", *cols],
                           [[r["scene"], r["geoms"], r["size"], r["batch"], r["mode"], *cells(r)]
                            for r in out["speed"]])
        out["observations"] = observations(args.scenes, args.jax, repeats=args.repeats)
        if out["observations"]:
            report.print_table("image observations of the arm tasks (64x64 hard, batch 16)",
                               ["scene", "per s"] + (["JAX per s", "vs JAX"] if args.jax else []),
                               [[r["scene"], r["per_s"]]
                                + ([r["per_s_jax"], r["speedup_vs_jax"]] if args.jax else [])
                                for r in out["observations"]])
        out["selections"] = selections(args.scenes, args.jax)
        if out["selections"]:
            report.print_table("camera choice on the arm tasks (sensing.select_camera, 64x64)",
                               ["scene", "restarts x steps", "seconds"]
                               + (["JAX seconds", "vs JAX"] if args.jax else []),
                               [[r["scene"], f"{r['restarts']} x {r['steps']}", r["seconds"]]
                                + ([r["seconds_jax"], r["speedup_vs_jax"]] if args.jax else [])
                                for r in out["selections"]])
        if args.floor:
            out["floor"] = floor(repeats=args.repeats)
            report.print_table("the floor: the simplest soft image in JAX (64x64, batch 16)",
                               ["scene", "mode", "frames/s"],
                               [[r["scene"], r["mode"], r["frames_per_s"]] for r in out["floor"]])
        if args.sweep:
            out["sweep"] = sweep(mods, args.sweep, repeats=args.repeats,
                                 layouts=args.sweep_layouts)
            report.print_table("geom-count sweep (64x64, batch 16)",
                               ["layout", "links", "geoms", "covered", "cand. hard / soft",
                                "mode", *cols,
                                "culled seg agree", "soft RGB max diff", "mean diff", "px > 0.01"],
                               [[r["layout"], r["scene"][5:], r["geoms"], r["covered"],
                                 f"{r['candidates_hard']:.1f} / {r['candidates_soft']:.1f}",
                                 r["mode"],
                                 *cells(r), r["culled_seg_agreement"],
                                 r["culled_soft_rgb_max_diff"], r["culled_soft_rgb_mean_diff"],
                                 r["culled_soft_pixels_off"]] for r in out["sweep"]])
            for layout in args.sweep_layouts:
                for mode in ("hard", "forward", "forward+grad"):
                    fps = {r["geoms"]: r["frames_per_s"] for r in out["sweep"]
                           if r["mode"] == mode and r["layout"] == layout}
                    if len(fps) > 1:
                        lo, hi = min(fps), max(fps)
                        ratio = fps[lo] / fps[hi]
                        # "sweep_cost_ratio" stays the dense layout's (as before the tiled one)
                        key = ("sweep_cost_ratio" if layout == "dense"
                               else f"sweep_cost_ratio_{layout}")
                        out.setdefault(key, {})[mode] = ratio
                        print(f"{layout} {mode}: {hi} geoms cost {ratio:.2f}x of {lo}")
        out["meta"]["speed_seconds"] = time.perf_counter() - t0
        out["meta"]["load_average_after_speed"] = list(os.getloadavg())
    if not args.no_agreement:
        out["agreement"] = agreement()
        report.print_table("hard image vs OpenGL (mujoco.Renderer), 64x64",
                           ["scene", "depth mean|d| (m)", "where seg agrees (m)", "seg agree",
                            "RGB PSNR"],
                           [[r["scene"], r["depth_mean_abs_m"],
                             r["depth_mean_abs_where_seg_agrees_m"], r["segmentation_agreement"],
                             r["rgb_psnr_db"]] for r in out["agreement"]])
    if args.visual:
        from twinrl.real2sim.visual import VisualConfig

        vc = VisualConfig(steps=args.steps, restarts=1, refine_iters=args.refine_iters,
                          coarse_size=args.coarse)
        cfg = {"frames": args.frames, "camera": vc, "object": vc}
        t0 = time.perf_counter()
        rows = visual(args.seeds, args.size, cfg)
        out["visual"] = {"size": args.size, "frames": args.frames, "coarse": args.coarse,
                         "steps": args.steps, "refine_iters": args.refine_iters, "rows": rows,
                         "wall_seconds": time.perf_counter() - t0}
        keys = ["cam_pos_err_mm", "cam_rot_err_deg", "obj_pos_err_mm", "size_err_pct",
                "colour_err_255"]
        report.print_table(f"visual real2sim on push, {args.frames} frames, "
                           f"{args.size}x{args.size} (before -> after)",
                           ["seed", "hidden cam", *keys, "seconds"],
                           [[r["seed"], f"{r['hidden_cam_offset_mm']:.0f} mm "
                             f"{r['hidden_cam_rot_deg']:.1f} deg",
                             *[f"{r[k + '_before']:.3g} -> {r[k]:.3g}" for k in keys],
                             r["seconds_camera"] + r["seconds_object"]]
                            for r in rows])
        print(f"visual real2sim wall time: {out['visual']['wall_seconds']:.0f} s")
    path = write_result(args.out / "render.json", out, args)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
