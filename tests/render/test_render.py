"""Renderer: hard images equal OpenGL's; soft-image gradients equal finite differences (x64);
the soft silhouette gives a lateral move a gradient; batching; errors. About 40 s cold."""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from twinrl.physics import load_mjcf
from twinrl.real.twin import CameraRenderer
from twinrl.render import Camera, Geoms, Renderer, UnsupportedGeomError, look_at

S = 24
BOX = 3  # push.xml: floor, goal, pusher, box


@pytest.fixture(scope="module")
def push():
    m = load_mjcf("push")
    d = mujoco.MjData(m)
    d.qpos[2:4] = [0.12, 0.03]
    mujoco.mj_forward(m, d)
    return m, d


@pytest.mark.parametrize("scene,cam,qpos,size", [("push", "top", None, 32),
                                                 ("pendulum", "front", [0.7], 32),
                                                 ("peg_in_hole", "front", [0.01, -0.02], 32),
                                                 # a pixel ray here misses the pole by 7 um
                                                 ("cartpole", "front", [0.3, 0.5], 64)])
def test_hard_image_matches_opengl(scene, cam, qpos, size):
    m = load_mjcf(scene)
    d = mujoco.MjData(m)
    if qpos is not None:
        d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    gl = CameraRenderer(m, size, size).images(d, cam)  # EGL, else OSMesa: no skip
    im = Renderer.create(m).render(Camera.from_mujoco(m, d, cam, size, size),
                                   Geoms.from_mujoco(m, d))
    seg = np.asarray(im.segmentation)
    assert np.mean(seg == gl["segmentation"]) >= 0.99
    assert np.mean(np.abs(np.asarray(im.depth) - gl["depth"])) <= 1e-3
    body = np.where(seg >= 0, m.geom_bodyid[np.maximum(seg, 0)], -1)
    np.testing.assert_array_equal(np.asarray(im.body), body)
    psnr = 10 * np.log10(1.0 / np.mean((np.asarray(im.rgb) - gl["rgb"] / 255.0) ** 2))
    assert psnr > 25, psnr


def test_grazing_rays_hit_or_miss_as_in_float64():
    """A ray from 3 m that passes 7 um outside (inside) a 25 mm capsule, sphere or cylinder misses
    (hits) it in float32: the textbook discriminant lost this to rounding."""
    from twinrl.render import primitives as P

    rng = np.random.default_rng(0)
    for gtype, size in ((3, [0.025, 0.3, 0.0]), (5, [0.025, 0.3, 0.0]), (2, [0.025, 0, 0])):
        for _ in range(20):
            z = rng.uniform(-0.05, 0.05) if gtype != 2 else 0.0
            phi = rng.uniform(0, 2 * np.pi)
            side = np.array([np.cos(phi), np.sin(phi), 0.0])
            for gap, hits in ((7e-6, False), (-7e-6, True)):
                p = (0.025 + gap) * side + [0, 0, z]  # the ray's closest point to the axis
                d = np.cross(side, [0.0, 0.0, 1.0]) + rng.uniform(-0.2, 0.2) * np.array([0, 0, 1])
                d /= np.linalg.norm(d)
                o = p - 3.0 * d
                hit = getattr(P, {2: "hit_sphere", 3: "hit_capsule", 5: "hit_cylinder"}[gtype])
                s = float(hit(jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32),
                              jnp.asarray(size, jnp.float32)))
                assert np.isfinite(s) == hits, (gtype, gap, o, d, s)


def test_hits_have_the_closed_forms_derivative_implicitly(x64):
    """``hit_implicit`` (the renderer's hit) equals each primitive's closed-form hit, and its
    implicit derivative equals the closed form's own (both ways: grad and jacfwd) and central
    differences, on rays that hit every face kind: sides, caps, slabs, the capsule's ends."""
    from twinrl.render import primitives as P

    rng = np.random.default_rng(1)
    sizes = {0: [0.25, 0.2, 0.1], 2: [0.3, 0, 0], 3: [0.2, 0.3, 0], 4: [0.2, 0.3, 0.4],
             5: [0.25, 0.2, 0], 6: [0.2, 0.3, 0.25]}
    for gtype, size in sizes.items():
        size = jnp.asarray(size, jnp.float64)
        # rays from 2 m towards points spread over the geom's bounding box
        aim = rng.uniform(-1, 1, (64, 3)) * np.maximum(np.asarray(size), 0.3) * [1, 1, 0.9]
        if gtype == 0:
            aim[:, 2] = 0.0
        d = rng.normal(size=(64, 3))
        d[:, 2] = -np.abs(d[:, 2]) - 0.3  # from above, so the plane is seen from its front
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o, r = jnp.asarray(aim - 2.0 * d), jnp.asarray(d)
        closed = P.PRIMITIVES[gtype][1]
        s_closed, s_impl = closed(o, r, size), P.hit_implicit(gtype, o, r, size)
        np.testing.assert_array_equal(s_impl, s_closed)
        ok = np.isfinite(np.asarray(s_closed))
        assert 16 <= ok.sum() < 64, (gtype, ok.sum())  # hits and misses both

        def total(f, o, r, size, ok=jnp.asarray(ok)):
            return jnp.sum(jnp.where(ok, f(o, r, size), 0.0) * jnp.arange(64.0))

        g_impl = jax.jit(jax.grad(lambda *a: total(lambda *b: P.hit_implicit(gtype, *b), *a),
                                  (0, 1, 2)))(o, r, size)
        g_closed = jax.jit(jax.grad(lambda *a: total(closed, *a), (0, 1, 2)))(o, r, size)
        for a, b in zip(g_impl, g_closed):
            np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-9)
        j_impl = jax.jit(jax.jacfwd(lambda sz: P.hit_implicit(gtype, o, r, sz)))(size)
        np.testing.assert_allclose(np.asarray(j_impl)[ok], np.asarray(
            jax.jit(jax.jacfwd(lambda sz: closed(o, r, sz)))(size))[ok], rtol=1e-8, atol=1e-9)
        eps = 1e-7
        shift = jax.jit(jax.vmap(lambda e: total(closed, o + e, r, size)))
        steps = eps * jnp.eye(3)[:, None, :] * jnp.ones((1, 64, 1))
        fd = (shift(steps) - shift(-steps)) / (2 * eps)
        np.testing.assert_allclose(jnp.sum(g_impl[0], 0), fd, rtol=1e-5, atol=1e-6)


def test_a_cylinders_deepest_point_has_the_derivative_of_the_minimum(x64):
    """Rays through a thin disc (a pancake, 1.2 mm thick) enter through a cap and leave through
    the side: their deepest point sits on the SDF's kink, where the soft distance's derivative
    is the two pieces' mix, not one of them (which was off on 241 of these 4,000 rays)."""
    from twinrl.render import primitives as prim

    size = jnp.array([0.015, 0.0006, 0.0])
    rng = np.random.default_rng(0)
    target = rng.uniform(-1, 1, (4000, 3)) * [0.02, 0.02, 0.002]
    o = jnp.broadcast_to(jnp.array([0.3, -0.2, 0.35]), (4000, 3))
    r = jnp.asarray(target) - o
    for x, name in ((size, "size"), (jnp.zeros(3), "shift")):
        def dist(x, name=name):
            if name == "size":
                return prim.closest_cylinder(o, r, x, 40)[1]
            return prim.closest_cylinder(o - x, r, size, 40)[1]
        jac = np.asarray(jax.jacfwd(dist)(x))[:, :2 if name == "size" else 3]
        eps = 1e-6  # the line search places s to ~3e-10: differences good to ~1e-3 at a kink
        fd = np.stack([(np.asarray(dist(x.at[k].add(eps))) - np.asarray(dist(x.at[k].add(-eps))))
                       / (2 * eps) for k in range(jac.shape[1])], 1)
        inside = np.asarray(dist(x)) < 0
        assert inside.sum() > 1000  # many rays pierce the disc
        # one piece alone put 6 % of the entries up to 0.9 off; a difference that straddles a
        # change of regime (the kink meeting the rim) may be off on a ray or two
        off = np.abs(jac - fd) > 2e-3
        assert off.mean() < 1e-3 and np.abs(jac - fd).max() < 0.1, (off.sum(), name)


def test_a_large_vmapped_batch_is_drawn_in_chunks_alike(push, monkeypatch):
    """A batch whose (pixel, surface) pairs exceed ``BATCH_ELEMENTS`` is drawn in JAX a chunk
    of cameras at a time: the same images, and derivatives (reverse and forward mode) still go
    through the whole batch. (Without derivatives the C++ kernel takes any batch whole.)"""
    from twinrl.render import batching, native

    m, d = push
    R, g = Renderer.create(m), Geoms.from_mujoco(m, d)
    n = 14  # an image size no other test uses, so the batched render is traced anew here
    assert R.surfaces() == 4 and R.batch_chunk(n, n, 6) == 6
    monkeypatch.setattr(batching, "BATCH_ELEMENTS", 2 * n * n * 4)
    assert R.batch_chunk(n, n, 6) == 2 and R.batch_chunk(n, n, 5) == 1  # divisors only
    cams = [look_at([0.3 + 0.1 * k, -1.0, 1.0], [0.15, 0, 0], width=n, height=n)
            for k in range(6)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *cams)
    with native.disabled():
        hard = jax.jit(jax.vmap(lambda c: R.render(c, g)))(batch)
        soft = jax.jit(jax.vmap(lambda c: R.render(c, g, tau=0.5)))(batch)
        assert "while" in jax.jit(jax.vmap(lambda c: R.render(c, g))).lower(batch).as_text()
    assert "while" not in jax.jit(jax.vmap(lambda c: R.render(c, g))).lower(batch).as_text()
    for k, c in enumerate(cams):
        one, one_soft = R.render(c, g), R.render(c, g, tau=0.5)  # the kernel's
        np.testing.assert_array_equal(hard.segmentation[k], one.segmentation)
        np.testing.assert_allclose(hard.rgb[k], one.rgb, atol=1e-6)
        np.testing.assert_allclose(soft.rgb[k], one_soft.rgb, atol=1e-6)

    def loss(xpos):
        im = jax.vmap(lambda c: R.render(c, g.replace(xpos=xpos), tau=0.5))(batch)
        return jnp.sum(im.rgb ** 2)

    grad, jac = jax.grad(loss)(g.xpos), jax.jacfwd(loss)(g.xpos)
    assert np.all(np.isfinite(grad)) and np.abs(grad[BOX]).max() > 0
    np.testing.assert_allclose(grad, jac, rtol=1e-3, atol=1e-4)


def test_products_are_traced_at_full_float32_precision_whatever_the_callers_default(push):
    # A GPU's TensorFloat-32 products (JAX's default there) round float32 inputs to 10 bits:
    # the renderer, its gradient and the point-cloud losses trace every product at HIGHEST even
    # under a caller's bfloat16 default (on the CPU jaxprs show the precision asked all the same)
    from twinrl.render.pointcloud import depth_to_points, sinkhorn_emd

    m, d = push
    R, g = Renderer.create(m), Geoms.from_mujoco(m, d)
    cam = Camera.from_mujoco(m, d, "top", 8, 8)

    def loss(c, g):
        im = R.render(c, g, tau=0.5)
        pts, w = depth_to_points(c, im.depth)
        return jnp.sum(im.rgb) + sinkhorn_emd(pts[:8], pts[8:16], w[:8], w[8:16])

    with jax.default_matmul_precision("bfloat16"):
        jaxprs = [str(jax.make_jaxpr(loss)(cam, g)),
                  str(jax.make_jaxpr(jax.grad(loss, argnums=(0, 1)))(cam, g))]
    for j in jaxprs:
        dots = j.count("dot_general[")
        assert dots >= 10 and j.count("precision=(Precision.HIGHEST, Precision.HIGHEST)") == dots


def test_mesh_renders_like_the_same_box():
    xml = """<mujoco><asset><mesh name="cube" vertex="-.05 -.05 -.05 .05 -.05 -.05 -.05 .05 -.05
      .05 .05 -.05 -.05 -.05 .05 .05 -.05 .05 -.05 .05 .05 .05 .05 .05"/></asset>
      <visual><global offwidth="64" offheight="64"/></visual>
      <worldbody><light pos="0 0 3" dir="0 0 -1"/><camera name="c" pos="0.2 -0.6 0.4"
      xyaxes="1 0.3 0 0 0.6 0.8"/><geom type="plane" size="1 1 .1"/>
      <geom name="m" type="mesh" mesh="cube" pos="0.05 0 0.05" euler="0 0 20" rgba="1 0 0 1"/>
      </worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    gl = CameraRenderer(m, 32, 32).images(d, "c")
    im = Renderer.create(m).render(Camera.from_mujoco(m, d, "c", 32, 32), Geoms.from_mujoco(m, d))
    assert np.mean(np.asarray(im.segmentation) == gl["segmentation"]) >= 0.99
    assert np.mean(np.abs(np.asarray(im.depth) - gl["depth"])) <= 1e-3


def test_opengl_shadow_map_is_sized_to_the_image_and_the_model_is_left_alone(push):
    # MuJoCo draws the shadow map at <quality shadowsize> (push: 4096^2) whatever the image's
    # size: most of a software-OpenGL frame. Sized to a 32x32 image it casts the same shadows.
    m, d = push
    own = int(m.vis.quality.shadowsize)
    sized, full = CameraRenderer(m, 32, 32), CameraRenderer(m, 32, 32, shadow_size=own)
    none = CameraRenderer(m, 32, 32, shadows=False)
    assert own > 1024 and sized.shadow_size == 1024 and full.shadow_size == own
    assert int(m.vis.quality.shadowsize) == own
    a, b, c = (r.images(d, "top", ("rgb",))["rgb"] for r in (sized, full, none))
    assert np.mean(np.any(b != c, -1)) > 0.05  # shadows are in view,
    assert np.mean(np.all(a == b, -1)) >= 0.99  # and the sized map casts the same ones
    for r in (sized, full, none):
        r.close()
    with pytest.raises(ValueError, match="shadow_size"):
        CameraRenderer(m, 32, 32, shadow_size=0)
    assert int(m.vis.quality.shadowsize) == own


@pytest.fixture(scope="module")
def fd_setup(push, x64):
    m, d = push
    R = Renderer.create(m, shadows=False, iters=40)
    cam = Camera.from_mujoco(m, d, "top", S, S)
    g = Geoms.from_mujoco(m, d)
    moved = g.replace(xpos=g.xpos.at[BOX].add(jnp.array([0.015, -0.01, 0.0])),
                      size=g.size.at[BOX].multiply(1.1), rgba=g.rgba.at[BOX, :3].add(0.1))
    target = R.render(cam.rotated(jnp.array([0.01, -0.01, 0.02])), moved, tau=0.7)

    def loss(p):
        c = cam.rotated(p["rot"]).translated(p["cam"])
        gg = g.replace(xpos=g.xpos.at[BOX].add(p["obj"]), size=g.size.at[BOX].set(p["size"]),
                       rgba=g.rgba.at[BOX].set(p["rgba"]))
        im = R.render(c, gg, tau=0.7)
        return (jnp.sum((im.rgb - target.rgb) ** 2) + jnp.sum((im.depth - target.depth) ** 2)
                + jnp.sum((im.weights - target.weights) ** 2))

    p0 = {"cam": jnp.zeros(3), "rot": jnp.zeros(3), "obj": jnp.zeros(3), "size": g.size[BOX],
          "rgba": g.rgba[BOX]}
    return jax.jit(loss), p0


@pytest.mark.parametrize("name", ["cam", "rot", "obj", "size", "rgba"])
def test_gradients_match_finite_differences(fd_setup, name):
    loss, p0 = fd_setup
    assert p0[name].dtype == jnp.float64
    grad = jax.jit(jax.grad(loss))(p0)[name]
    assert np.all(np.isfinite(grad))
    eps = 1e-6
    fd = []
    for j in range(p0[name].shape[0]):
        e = jnp.zeros_like(p0[name]).at[j].set(eps)
        fd.append((loss({**p0, name: p0[name] + e}) - loss({**p0, name: p0[name] - e})) / (2 * eps))
    fd = np.array(fd)
    if name == "size":  # a box's size has 3 components, all used
        assert np.all(np.abs(fd) > 0)
    err = np.linalg.norm(np.asarray(grad) - fd) / np.linalg.norm(fd)
    assert err < 0.05, (name, np.asarray(grad), fd)


def test_lateral_move_gets_a_gradient_the_right_way(push):
    m, d = push
    R = Renderer.create(m)
    cam = Camera.from_mujoco(m, d, "top", S, S)
    g = Geoms.from_mujoco(m, d)
    target = R.render(cam, g.replace(xpos=g.xpos.at[BOX, 0].add(0.02)))  # the box 2 cm to +x

    def loss(dx, tau):
        im = R.render(cam, g.replace(xpos=g.xpos.at[BOX, 0].add(dx)), tau=tau)
        mask = (target.segmentation == BOX).astype(im.rgb.dtype)
        return jnp.sum((im.weights[..., R.index(BOX)] - mask) ** 2) + jnp.sum(
            (im.rgb - target.rgb) ** 2)

    grad = jax.jit(jax.grad(loss), static_argnums=1)  # tau = 0 selects the hard image
    hard = grad(0.0, 0.0)
    soft = grad(0.0, 1.0)
    assert hard == 0.0  # the hard image (like mjx.ray's depth) is flat in a lateral move
    assert soft < 0.0  # soft: moving towards +x lowers the loss


def test_vmap_over_cameras_and_scenes(push):
    m, d = push
    R = Renderer.create(m)
    g = Geoms.from_mujoco(m, d)
    cams = [look_at([0.3, -1.0, 1.0], [0.15, 0, 0], width=S, height=S),
            look_at([1.0, 0.5, 0.8], [0.15, 0, 0], width=S, height=S)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *cams)
    out = jax.jit(jax.vmap(lambda c: R.render(c, g, tau=0.5).depth))(batch)
    for k, c in enumerate(cams):
        np.testing.assert_allclose(out[k], R.render(c, g, tau=0.5).depth, rtol=1e-5, atol=1e-5)
    gs = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), g)
    gs = gs.replace(xpos=gs.xpos.at[1, BOX, 0].add(0.05))
    segs = jax.vmap(lambda g: R.render(cams[0], g).segmentation)(gs)
    assert not np.array_equal(segs[0], segs[1])


def test_renderers_of_one_scene_are_equal_and_share_the_compiled_render(push):
    # equal by content, not identity: a second task (or real twin) made from the same MJCF
    # renders through the first one's compiled image instead of tracing and compiling again
    from twinrl.render import batching

    m, d = push
    a, b = Renderer.create(m), Renderer.create(load_mjcf("push"))
    assert a is not b and a == b and hash(a) == hash(b)
    assert a != Renderer.create(m, shadows=False) and a != Renderer.create(m, geom_ids=[1, 2])
    assert a != Renderer.create(load_mjcf("pendulum")) and a != "a renderer"
    cam, g = look_at([0.3, -1.0, 1.0], [0.15, 0, 0], width=12, height=10), Geoms.from_mujoco(m, d)
    first = a.render(cam, g, tau=0.3)
    compiled = batching.render_jit._cache_size()
    second = b.render(cam, g, tau=0.3)
    assert batching.render_jit._cache_size() == compiled
    np.testing.assert_array_equal(first.rgb, second.rgb)


def test_from_mujoco_matches_look_at_and_projection(push):
    m, d = push
    cam = Camera.from_mujoco(m, d, "top", S, S)
    np.testing.assert_allclose(cam.xmat, d.cam_xmat[0].reshape(3, 3), atol=1e-6)
    # the centre of the box projects where the renderer sees the box
    px, depth = cam.project(jnp.asarray(d.geom_xpos[BOX]))
    im = Renderer.create(m).render(cam, Geoms.from_mujoco(m, d))
    col, row = np.asarray(px).astype(int)
    assert int(im.segmentation[row, col]) == BOX
    assert 0 < float(depth) < float(im.depth[row, col]) + 0.1


def test_window_sees_exactly_those_pixels(push):
    """A crop, and every 3rd pixel of a 48x48 image, render as those pixels of the full image (same
    rays through the same pixel centres); projection inverts the rays; gradients flow to the
    pose through the principal point."""
    m, d = push
    R = Renderer.create(m)
    g = Geoms.from_mujoco(m, d)
    full = Camera.from_mujoco(m, d, "top", 48, 48)
    ref = R.render(full, g)
    o, rays = full.rays()
    for (r0, c0, h, w, k) in [(5, 9, 20, 14, 1), (1, 2, 16, 15, 3)]:
        win = full.window(r0, c0, h, w, k)
        sl = np.s_[r0:r0 + k * h:k, c0:c0 + k * w:k]
        np.testing.assert_allclose(win.rays()[1], rays[sl], atol=1e-6)
        np.testing.assert_allclose(win.pixel_size(), k * full.pixel_size(), rtol=1e-6)
        im = R.render(win, g)
        np.testing.assert_array_equal(im.segmentation, ref.segmentation[sl])
        np.testing.assert_allclose(im.depth, ref.depth[sl], rtol=1e-4)  # float32 roots
        px, _ = win.project(o + 0.8 * win.rays()[1])
        centres = np.stack(np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5), -1)
        np.testing.assert_allclose(px, centres, atol=1e-3)
    gpos = jax.grad(lambda p: dataclasses.replace(full, pos=p).window(1, 2, 16, 15, 3).project(
        jnp.asarray(d.geom_xpos[BOX]))[0][0])(full.pos)
    assert np.all(np.isfinite(gpos)) and np.any(gpos != 0)
    with pytest.raises(ValueError, match="leave the 48x48"):
        full.window(40, 0, 10, 10)
    with pytest.raises(ValueError, match=">= 1"):
        full.window(0, 0, 4, 4, step=0)


def test_window_of_a_stack_of_cameras_is_each_cameras_window(push):
    """A stack of cameras (a leading axis on every array, as a hand-eye fit holds one per
    frame) windows into a stack with one principal point per camera, each the window of its
    own camera -- it had made one (2,) principal point for the stack, which a vmap over the
    stack refused (the needle's 128x128 calibration, coarsened to 64x64)."""
    m, d = push
    a = Camera.from_mujoco(m, d, "top", 48, 48)
    moved = dataclasses.replace(a, pos=a.pos + 0.01)
    off_centre = jnp.asarray([20.0, 27.0])
    for cams in ((a, moved),  # the default principal point
                 (dataclasses.replace(a, principal=jnp.asarray([24.0, 24.0])),
                  dataclasses.replace(moved, principal=off_centre))):
        stack = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *cams)
        win = stack.window(1, 2, 16, 15, 3)
        assert win.principal.shape == (2, 2)
        rays = jax.vmap(lambda c: c.rays()[1])(win)
        for i, cam in enumerate(cams):
            np.testing.assert_allclose(rays[i], cam.window(1, 2, 16, 15, 3).rays()[1],
                                       atol=1e-6)


def test_bad_inputs(push):
    m, d = push
    R = Renderer.create(m)
    cam = Camera.from_mujoco(m, d, "top", S, S)
    g = Geoms.from_mujoco(m, d)
    with pytest.raises(ValueError, match="xpos must be"):
        R.render(cam, g.replace(xpos=g.xpos[None]))
    with pytest.raises(ValueError, match="Geoms has"):
        R.render(cam, g.replace(xpos=g.xpos[:2], xmat=g.xmat[:2]))
    with pytest.raises(TypeError, match="Camera"):
        R.render("top", g)
    with pytest.raises(ValueError, match="fovy"):
        Camera.create([0, 0, 1], [1, 0, 0, 0], fovy=0.0)
    with pytest.raises(ValueError, match="pos must be"):
        Camera.create([0, 0], [1, 0, 0, 0])
    with pytest.raises(ValueError, match="camera 'nope'"):
        Camera.from_mujoco(m, d, "nope")
    with pytest.raises(ValueError, match="vmap"):
        R.render(dataclasses.replace(cam, pos=cam.pos[None]), g)
    hf = mujoco.MjModel.from_xml_string(
        '<mujoco><asset><hfield name="h" nrow="2" ncol="2" size="1 1 .1 .1"/></asset>'
        '<worldbody><geom type="hfield" hfield="h"/></worldbody></mujoco>')
    with pytest.raises(UnsupportedGeomError, match="hfield"):
        Renderer.create(hf)


def _row_of_capsules(n):
    links = "".join(f'<geom type="capsule" size="0.03 0.06" pos="{-0.45 + 0.3 * k:.2f} 0 0.1" '
                    f'euler="0 {20 * k} 0" rgba="0.{k + 1} 0.5 0.3 1"/>' for k in range(n))
    return mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><light pos="0 0 3" dir="0 0 -1"/><camera name="c" pos="0 -1.3 0.6" '
        f'xyaxes="1 0 0 0 0.42 0.9"/><geom type="plane" size="2 2 0.1"/>{links}'
        '</worldbody></mujoco>')


def test_culling_keeps_the_image_and_its_gradient_where_geoms_do_not_crowd():
    """Four capsules 16 pixels apart, more than the soft band (12.5 pixels at tau 0.7): culled to
    one capsule per pixel, the hard
    image is the same, the soft image and its gradient w.r.t. a capsule's pose and size agree with
    the unculled renderer's (the geoms left out of a pixel contribute nothing there)."""
    m = _row_of_capsules(4)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    cam = Camera.from_mujoco(m, d, "c", 64, 64)
    g = Geoms.from_mujoco(m, d)
    culled, full = Renderer.create(m, per_pixel=1, cull_above=0), Renderer.create(m, per_pixel=4)
    assert culled.culled(3, np.arange(1, 5)) and not full.culled(3, np.arange(1, 5))
    # by default a type is culled only beyond cull_above (8) geoms: smaller ones are drawn whole
    assert not Renderer.create(m, per_pixel=1).culled(3, np.arange(8))
    assert Renderer.create(m, per_pixel=1).culled(3, np.arange(9))
    with pytest.raises(ValueError, match="cull_above must be >= 0"):
        Renderer.create(m, cull_above=-1)
    a, b = culled.render(cam, g), full.render(cam, g)
    assert len(np.unique(np.asarray(b.segmentation))) == 6  # sky, floor, the four capsules
    np.testing.assert_array_equal(a.segmentation, b.segmentation)
    np.testing.assert_allclose(a.depth, b.depth, rtol=1e-6)
    np.testing.assert_allclose(a.rgb, b.rgb, atol=1e-5)

    def loss(R, dx, ds):
        im = R.render(cam, g.replace(xpos=g.xpos.at[2].add(dx), size=g.size.at[2].add(ds)),
                      tau=0.7)
        return jnp.sum(im.rgb ** 2) + jnp.sum(im.weights ** 2) + jnp.sum(im.depth)

    args = (jnp.zeros(3), jnp.zeros(3))
    np.testing.assert_allclose(loss(culled, *args), loss(full, *args), rtol=1e-5)
    for ga, gb in zip(jax.grad(loss, (1, 2))(culled, *args), jax.grad(loss, (1, 2))(full, *args)):
        assert np.linalg.norm(gb) > 0
        np.testing.assert_allclose(ga, gb, rtol=1e-3, atol=1e-3 * np.linalg.norm(gb))


def test_layers_keep_the_hard_image_and_the_soft_one_where_surfaces_do_not_crowd():
    """Compositing only each pixel's 2 most covering surfaces (of 5: floor and four capsules
    further apart than the soft band) changes neither image nor the gradient; with 1 surface
    the hard image is still exact (the nearest hit is kept)."""
    m = _row_of_capsules(4)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    cam = Camera.from_mujoco(m, d, "c", 64, 64)
    g = Geoms.from_mujoco(m, d)
    full = Renderer.create(m, layers=5)
    for R in (Renderer.create(m, layers=1), Renderer.create(m, layers=2)):
        a, b = R.render(cam, g), full.render(cam, g)
        np.testing.assert_array_equal(a.segmentation, b.segmentation)
        np.testing.assert_allclose(a.depth, b.depth, rtol=1e-6)
        np.testing.assert_allclose(a.rgb, b.rgb, atol=1e-5)
        np.testing.assert_allclose(a.weights, b.weights, atol=1e-6)
    two = Renderer.create(m, layers=2)

    def loss(R, dx):
        im = R.render(cam, g.replace(xpos=g.xpos.at[2].add(dx)), tau=0.7)
        return jnp.sum(im.rgb ** 2) + jnp.sum(im.weights ** 2) + jnp.sum(im.depth)

    np.testing.assert_allclose(loss(two, jnp.zeros(3)), loss(full, jnp.zeros(3)), rtol=1e-5)
    ga, gb = jax.grad(loss, 1)(two, jnp.zeros(3)), jax.grad(loss, 1)(full, jnp.zeros(3))
    assert np.linalg.norm(gb) > 0
    np.testing.assert_allclose(ga, gb, rtol=1e-3, atol=1e-3 * np.linalg.norm(gb))
