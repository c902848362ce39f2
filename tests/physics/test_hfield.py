"""Height-field contacts (``twinrl.physics.hfield``): a sphere, a capsule, a box, an ellipsoid and
a cylinder on a non-flat height field, against MuJoCo C's contacts and trajectory, and through
``gradcheck --strict`` (float64)."""

import mujoco
import numpy as np
import pytest

from tests.physics._foreign import FOREIGN, check_foreign_scene
from tests.physics._placer import Placer, angle, nearest, positions_against_mujoco
from twinrl.physics import Sim, collision
from twinrl.physics.sim import put_model

DROPS = FOREIGN / "hfield_drops.xml"  # an ellipsoid, a cylinder on its side, one on its end
PRIMITIVES = FOREIGN / "hfield_primitives.xml"  # a sphere, a capsule, a box


def test_pairs_mjx_lacks_are_accepted():
    # MJX 3.17 has no function for a height field and a cylinder or an ellipsoid: put_model
    # refused the model with "no collision function for hfield 'terrain' x ellipsoid 'egg'"
    hfield = int(mujoco.mjtGeom.mjGEOM_HFIELD)
    assert {int(b) for a, b in collision.ADDED if a == hfield} == {
        int(mujoco.mjtGeom.mjGEOM_ELLIPSOID), int(mujoco.mjtGeom.mjGEOM_CYLINDER)}
    put_model(mujoco.MjModel.from_xml_path(str(DROPS)), "hfield_drops")


def test_stock_mjx_is_left_as_it_was():
    # twinrl lends MJX's table the pairs it lacks only while it calls put_model / make_data:
    # after a Sim of such a model is built and stepped, stock MJX still refuses the model
    from mujoco import mjx
    from mujoco.mjx._src import collision_driver

    before = dict(collision_driver._COLLISION_FUNC)
    sim = Sim.load(DROPS)
    sim.step(sim.init(), np.zeros(sim.nu))
    assert collision_driver._COLLISION_FUNC == before
    assert not set(collision.ADDED) & set(before)
    with pytest.raises(NotImplementedError, match="collisions not implemented"):
        mjx.put_model(mujoco.MjModel.from_xml_path(str(DROPS)))


# (scene, body, xy, euler): each geom's deepest point inside one triangle of the field, where C
# makes one contact, through the prism's top face
FACE = [(PRIMITIVES, "ball", (-0.3, -0.25), (0, 0, 0)),
        (PRIMITIVES, "rod", (0.1, -0.3), (85, 4, 10)),
        (PRIMITIVES, "crate", (-0.55, 0.1), (10, 15, 20)),
        (DROPS, "egg", (-0.3, -0.25), (20, 30, 0)),
        (DROPS, "egg", (0.2, 0.1), (0, 0, 40)),
        (DROPS, "can", (-0.3, 0.3), (0, 0, 0)),  # on its end: EPA's point anywhere on the disc
        (DROPS, "can", (-0.35, 0.2), (30, 50, 0)),
        (DROPS, "puck", (0.45, 0.3), (15, -10, 0)),
        (DROPS, "puck", (-0.6, -0.15), (20, 10, 0))]
# on a grid vertex poking into the geom (the field's peak at (0.8, -0.02), and two vertices a
# cylinder's side rests on): C repeats the vertex's contact in each of the prisms around it,
# each with EPA's normal, then mjc_fixNormal's (the geom's surface normal: ours)
VERTEX = [(DROPS, "egg", (0.8, -0.02), (0, 0, 0)),
          (PRIMITIVES, "ball", (0.8, -0.02), (0, 0, 0)),
          (DROPS, "can", (0.5, -0.3), (6, -8, 0)),
          (DROPS, "can", (0.3, 0.2), (80, 10, 30))]
# Left out, where C's per-prism test is not the field's surface: a geom's corner or rim near a
# prism's vertical side escapes sideways by less than its depth under the face (a box corner
# 13.6 mm under the surface got no contact; a disc got two with horizontal normals).


@pytest.fixture(scope="module")
def placers(x64):
    return {DROPS: Placer(DROPS), PRIMITIVES: Placer(PRIMITIVES)}


@pytest.mark.parametrize("case", FACE + VERTEX, ids=lambda c: f"{c[1]}{c[2]}")
def test_contacts_agree_with_mujoco(placers, case):
    scene, body, xy, euler = case
    theirs, ours = placers[scene](body, xy, euler)
    assert theirs, "C has no contact: the placement missed the field"
    if case in FACE:
        assert len(theirs) == 1
    for dist, pos, normal in theirs:
        our_dist, dpos, our_normal = nearest(ours, pos)
        # C's EPA stops at a tolerance of 1e-6 on a smooth geom's rounded surface
        assert abs(our_dist - dist) <= 2e-6, (dist, our_dist)
        assert dpos <= 5e-4, dpos
        # a vertex's normal: C's ray projection onto the ellipsoid vs the gradient of its SDF here
        assert angle(our_normal, normal) <= (0.05 if case in FACE else 1.0)
    # and none of ours is deeper than C's deepest (ours may add points along a ridge's edges,
    # shallower, where C repeats the vertex)
    assert abs(ours[0].min() - min(dist for dist, _, _ in theirs)) <= 2e-6


@pytest.mark.parametrize("path", [DROPS, PRIMITIVES], ids=["drops", "primitives"])
def test_trajectory_follows_mujoco(x64, path):
    # dropped tilted onto the slopes, landing (~step 20) and sliding or rolling down them: C makes
    # one contact per prism and twinrl at most 4 per geom, so the two part slowly once sliding
    sim = Sim.load(path)
    T = 60
    ours, theirs, traj = positions_against_mujoco(sim, T)
    err = np.linalg.norm(ours - theirs, axis=-1)  # (T, bodies)
    assert float(np.asarray(traj.n_active)[-1]) >= 3  # every body on the field
    assert err[:10].max() <= 1e-6  # free fall
    # measured over the 0.3 s: ellipsoid 3e-16 and sphere 8e-5 m (one face contact each, as C's),
    # the cylinders, capsule and box 7 to 12 mm (C's contacts: one per prism; ours: 4 deepest)
    assert err.max() <= 1.5e-2, err.max(axis=0)


@pytest.mark.parametrize("name", ["hfield_drops", "hfield_primitives"])
def test_gradcheck_strict(x64, name):
    check_foreign_scene(name)
