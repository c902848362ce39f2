"""The C++ kernel (``twinrl.render.native``) draws what the JAX renderer draws, and its reverse
pass gives the JAX renderer's gradient; forward mode still goes through JAX."""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import twinrl  # noqa: F401
from twinrl.render import Camera, Geoms, Renderer, native

# Every primitive the kernel draws, a finite and an infinite plane, a translucent box, a material
# with specular and emission, and the three kinds of light (a spot casting shadows, a directional
# and a point light with attenuation): written for this test, not a bundled scene.
SCENE = """
<mujoco>
  <visual><headlight ambient="0.1 0.1 0.1" diffuse="0.3 0.3 0.3"/></visual>
  <asset><material name="shiny" specular="0.9" shininess="0.8" emission="0.1"
                   rgba="0.2 0.6 0.9 1"/></asset>
  <worldbody>
    <light type="spot" pos="0.3 -0.2 2" dir="0 0 -1" cutoff="40" exponent="5"
           castshadow="true"/>
    <light type="directional" pos="0 0 3" dir="0.3 0.2 -1" castshadow="false"
           diffuse="0.3 0.3 0.3"/>
    <light type="point" pos="-0.5 0.5 1" attenuation="1 0.1 0.05" castshadow="false"
           diffuse="0.4 0.3 0.2" specular="0.2 0.2 0.2"/>
    <camera name="c" pos="0 -1.3 0.9" xyaxes="1 0 0 0 0.57 0.82"/>
    <geom type="plane" size="0 0 0.1" rgba="0.8 0.8 0.8 1"/>
    <geom type="plane" size="0.15 0.1 0.01" pos="0.4 -0.35 0.002" rgba="0.3 0.3 0.9 1"/>
    <geom type="sphere" size="0.08" pos="-0.3 0 0.1" rgba="0.9 0.2 0.2 1"/>
    <geom type="sphere" size="0.03" pos="-0.45 -0.2 0.03" rgba="0.9 0.5 0.2 1"/>
    <geom type="sphere" size="0.03" pos="-0.38 -0.25 0.03" rgba="0.9 0.5 0.4 1"/>
    <geom type="sphere" size="0.03" pos="-0.31 -0.3 0.03" rgba="0.9 0.5 0.6 1"/>
    <geom type="capsule" size="0.04 0.1" pos="-0.1 0.1 0.12" euler="30 40 0" material="shiny"/>
    <geom type="ellipsoid" size="0.1 0.05 0.07" pos="0.1 -0.1 0.1" euler="0 0 30"
          rgba="0.2 0.9 0.2 1"/>
    <geom type="cylinder" size="0.05 0.08" pos="0.3 0.1 0.1" euler="70 0 20"
          rgba="0.9 0.9 0.2 1"/>
    <geom type="box" size="0.06 0.04 0.05" pos="0.05 0.2 0.06" euler="0 0 45"
          rgba="0.5 0.2 0.8 0.6"/>
  </worldbody>
</mujoco>
"""

RENDERERS = {
    "whole": {},
    # the spheres culled to 2 a pixel, and 3 surfaces composited a pixel (of 9 tested)
    "culled": dict(per_pixel=2, cull_above=0, layers=3),
    "no shadows": dict(shadows=False),
}

# Image sizes (width, height) no tile divides: the kernel draws packets of pixels (a 4-column tile,
# one pixel a SIMD lane; 4 rows in float32 and 2 in float64 with AVX-512, half as many with AVX2),
# and the lanes past the image's right and bottom edges must write nothing and add nothing to a
# gradient. Every agreement test below draws at such a size.
PARTIAL64, PARTIAL32 = (41, 31), (23, 21)


@pytest.fixture(scope="module")
def scene():
    m = mujoco.MjModel.from_xml_string(SCENE)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return m, d


def _both(R, cam, g, tau):
    ours = R.render(cam, g, tau=tau)
    with native.disabled():
        theirs = R.render(cam, g, tau=tau)
    return ours, theirs


def _close(a, b, atol):
    np.testing.assert_array_equal(a.segmentation, b.segmentation)
    np.testing.assert_array_equal(a.body, b.body)
    for name in ("rgb", "depth", "weights", "background"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=atol,
                                   err_msg=name)


def test_the_kernel_is_built_here():
    # CI installs a compiler (.ci/run): without one every image is drawn in JAX, and this says why
    assert native.available(), native.status()
    assert native.status().startswith("on")


@pytest.mark.parametrize("kind", list(RENDERERS))
def test_the_kernel_draws_what_jax_draws_in_float64(scene, kind):
    m, d = scene
    R = Renderer.create(m, **RENDERERS[kind])
    assert R.kernel_attrs is not None
    for tau in (0.0, 0.6):
        with jax.enable_x64(True):
            g = Geoms.from_mujoco(m, d, dtype=jnp.float64)
            cam = Camera.from_mujoco(m, d, "c", *PARTIAL64, dtype=jnp.float64)
            ours, theirs = _both(R, cam, g, tau)
        assert ours.rgb.dtype == jnp.float64
        _close(ours, theirs, 1e-8)  # soft: coverage under 1e-12 is left out
        seen = np.unique(np.asarray(ours.segmentation))
        assert len(seen) >= 9, seen  # sky, both planes, the geoms (culled ones too)
        if tau:
            w = np.asarray(ours.weights)
            assert ((w > 1e-3) & (w < 0.999)).any()  # soft edges, not a hard image


def test_the_kernel_draws_what_jax_draws_in_float32_and_forward_mode_goes_through_jax(scene):
    m, d = scene
    R = Renderer.create(m)
    g = Geoms.from_mujoco(m, d, dtype=jnp.float32)
    cam = Camera.from_mujoco(m, d, "c", *PARTIAL32, dtype=jnp.float32)
    _close(*_both(R, cam, g, 0.0), 2e-4)
    ours, theirs = _both(R, cam, g, 0.6)
    # float32 rounding, raised to the shiny capsule's specular exponent (~100) in its highlight
    _close(ours, theirs, 2e-4)

    def image(xpos):
        return R.render(cam, g.replace(xpos=xpos), tau=0.6).rgb

    t = jnp.zeros_like(g.xpos).at[9].set(jnp.array([0.01, 0.0, 0.0]))  # move the box
    primal, tangent = jax.jvp(image, (g.xpos,), (t,))
    np.testing.assert_allclose(primal, ours.rgb, atol=1e-6)  # the kernel's values
    with native.disabled():
        _, their_tangent = jax.jvp(image, (g.xpos,), (t,))
    np.testing.assert_allclose(tangent, their_tangent, atol=1e-6)  # JAX's forward mode
    assert np.abs(tangent).max() > 1e-3


def _image_vjps(R, cam, g, tau, ct):
    """The gradient of <ct, image> w.r.t. camera and geoms: the kernel's reverse pass, JAX's."""
    def loss(c, gg):
        im = R.render(c, gg, tau=tau)
        return sum(jnp.sum(getattr(im, k) * v) for k, v in ct.items())

    ours = jax.jit(jax.grad(loss, (0, 1)))(cam, g)
    with native.disabled():
        theirs = jax.jit(jax.grad(loss, (0, 1)))(cam, g)
    return ours, theirs


@pytest.mark.parametrize("kind", list(RENDERERS))
def test_the_reverse_kernel_gives_jaxs_gradient_in_float64(scene, kind):
    """``jax.grad`` of any function of the image (colour, depth, per-geom weights, background)
    w.r.t. the camera (pose, field of view) and every geom's pose, size and colour: the C++
    reverse pass agrees with the JAX renderer's to 1e-6 of the largest entry (it leaves out
    surfaces that add under 1e-10 to a pixel), hard and soft, every primitive, light and shadow
    of the scene, culled or not."""
    m, d = scene
    R = Renderer.create(m, **RENDERERS[kind])
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        g = Geoms.from_mujoco(m, d, dtype=jnp.float64)
        cam = Camera.from_mujoco(m, d, "c", *PARTIAL64, dtype=jnp.float64)
        for tau in (0.0, 0.6):
            im = R.render(cam, g, tau=tau)
            ct = {k: jnp.asarray(rng.normal(size=getattr(im, k).shape))
                  for k in ("rgb", "depth", "weights", "background")}
            ours, theirs = _image_vjps(R, cam, g, tau, ct)
            for a, b in zip(jax.tree_util.tree_leaves(ours), jax.tree_util.tree_leaves(theirs)):
                if b.size:
                    scale = np.abs(np.asarray(b)).max()
                    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * scale + 1e-12)
            assert np.abs(np.asarray(ours[1].xpos)).max() > 0  # geoms got a gradient
            assert np.abs(np.asarray(ours[0].quat)).max() > 0


def test_reverse_mode_batches_and_second_derivatives(scene):
    """vmap of grad (a batch of cameras, one scene), float32 agreement with JAX, and second
    derivatives (a Hessian-vector product goes through JAX)."""
    m, d = scene
    R = Renderer.create(m)
    g = Geoms.from_mujoco(m, d, dtype=jnp.float32)
    cam = Camera.from_mujoco(m, d, "c", 19, 13, dtype=jnp.float32)  # partial packets
    cams = jax.tree_util.tree_map(lambda x: jnp.stack([x, x + 0.01]), cam)
    target = R.render(cam, g, tau=0.6).rgb

    def loss(c, gg):
        return jnp.mean((R.render(c, gg, tau=0.6).rgb - target) ** 2)

    f = jax.jit(jax.vmap(jax.grad(loss, (0, 1)), in_axes=(0, None)))
    ours = f(cams, g)
    with native.disabled():
        theirs = jax.jit(jax.vmap(jax.grad(loss, (0, 1)), in_axes=(0, None)))(cams, g)
    for a, b in zip(jax.tree_util.tree_leaves(ours), jax.tree_util.tree_leaves(theirs)):
        if b.size:
            np.testing.assert_allclose(a, b, rtol=0, atol=2e-3 * np.abs(np.asarray(b)).max())
    assert np.abs(np.asarray(ours[0].pos[1])).max() > 0  # the moved camera's own gradient

    def hvp(x, v):  # w.r.t. the colours
        return jax.jvp(jax.grad(lambda y: loss(cam, g.replace(rgba=y))), (x,), (v,))[1]

    v = jnp.zeros_like(g.rgba).at[2, 0].set(1.0)
    ours = jax.jit(hvp)(g.rgba * 0.9, v)
    with native.disabled():
        theirs = jax.jit(hvp)(g.rgba * 0.9, v)
    np.testing.assert_allclose(ours, theirs, rtol=1e-3, atol=1e-7)
    assert np.abs(np.asarray(ours)).max() > 0


def test_batches_of_cameras_and_scenes_are_drawn_frame_by_frame_alike(scene):
    m, d = scene
    R = Renderer.create(m)
    g = Geoms.from_mujoco(m, d)
    cams = [Camera.from_mujoco(m, d, "c", 20, 16).translated(jnp.array([0.05 * k, 0, 0]))
            for k in range(3)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *cams)
    shifts = jnp.array([0.0, 0.03])
    scenes = jax.vmap(lambda s: g.replace(xpos=g.xpos.at[2, 0].add(s)))(shifts)
    grid = jax.jit(jax.vmap(jax.vmap(lambda c, gg: R.render(c, gg, tau=0.6),
                                     in_axes=(0, None)), in_axes=(None, 0)))(batch, scenes)
    assert grid.rgb.shape == (2, 3, 16, 20, 3)
    for i, s in enumerate(shifts):
        for k, c in enumerate(cams):
            one = R.render(c, g.replace(xpos=g.xpos.at[2, 0].add(s)), tau=0.6)
            np.testing.assert_array_equal(grid.segmentation[i, k], one.segmentation)
            np.testing.assert_allclose(grid.rgb[i, k], one.rgb, atol=1e-6)
    assert not np.allclose(grid.rgb[0, 0], grid.rgb[1, 0])  # the sphere moved


def test_without_a_compiler_or_when_switched_off_jax_draws(monkeypatch, scene):
    monkeypatch.setenv("CXX", "/nonexistent/c++")
    path, why = native.probe()
    assert path is None and why.startswith("not built"), why
    monkeypatch.setenv("TWINRL_NATIVE_RENDER", "0")
    assert native.probe() == (None, "off (TWINRL_NATIVE_RENDER)")
    # meshes stay in JAX
    mesh = mujoco.MjModel.from_xml_string(
        '<mujoco><asset><mesh name="t" vertex="0 0 0 1 0 0 0 1 0 0 0 1"/></asset><worldbody>'
        '<geom type="mesh" mesh="t"/></worldbody></mujoco>')
    assert Renderer.create(mesh).kernel_attrs is None
    with native.disabled():
        assert not native.available()
    assert native.available()
