"""Point clouds: unprojection round trip, Chamfer and Sinkhorn EMD values and gradients. ~10 s."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl.render import look_at
from twinrl.render.pointcloud import chamfer, depth_to_points, sinkhorn_emd


@pytest.fixture(scope="module")
def cloud():
    return jax.random.normal(jax.random.PRNGKey(0), (48, 3)) * 0.05


def test_depth_to_points_round_trip():
    cam = look_at([0.0, -1.0, 0.5], [0, 0, 0], width=8, height=6)
    depth = jnp.full((6, 8), 1.3)
    pts, w = depth_to_points(cam, depth, depth > 1.0)
    px, z = cam.project(pts)
    np.testing.assert_allclose(z, 1.3, rtol=1e-5)
    cols, rows = np.meshgrid(np.arange(8) + 0.5, np.arange(6) + 0.5)
    np.testing.assert_allclose(np.asarray(px).reshape(6, 8, 2)[..., 0], cols, atol=1e-4)
    np.testing.assert_allclose(np.asarray(px).reshape(6, 8, 2)[..., 1], rows, atol=1e-4)
    assert float(w.sum()) == 48
    with pytest.raises(ValueError, match="depth has shape"):
        depth_to_points(cam, jnp.ones((5, 8)))


def test_chamfer(cloud):
    assert float(chamfer(cloud, cloud)) == 0.0
    assert float(chamfer(cloud, cloud + 0.01)) > 0
    g = jax.grad(lambda d: chamfer(cloud, cloud + d))(jnp.full(3, 0.01))
    assert np.all(np.isfinite(g)) and np.all(np.asarray(g) > 0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        chamfer(cloud[:, :2], cloud)


def test_sinkhorn_emd(cloud):
    assert abs(float(sinkhorn_emd(cloud, cloud))) < 1e-7
    shift = jnp.array([0.01, -0.02, 0.0])
    np.testing.assert_allclose(sinkhorn_emd(cloud, cloud + shift), 5e-4, rtol=0.1)
    w = jnp.ones(48).at[:8].set(0.0)
    g = jax.jit(jax.grad(lambda d: sinkhorn_emd(cloud, cloud + d, w, w)))(shift)
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g, 2 * shift, atol=2e-3)  # d/dd |d|^2
