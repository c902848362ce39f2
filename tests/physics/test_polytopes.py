"""An ellipsoid and a cylinder against a box or a convex mesh (``twinrl.physics.polytopes``, pairs
MJX 3.17 lacks): contacts and trajectory against MuJoCo C's, and ``gradcheck --strict``
(float64)."""

import mujoco
import numpy as np
import pytest

from tests.physics._foreign import FOREIGN, check_foreign_scene
from tests.physics._placer import Placer, angle, nearest, positions_against_mujoco
from twinrl.physics import Sim, collision

PADS = FOREIGN / "box_pads.xml"  # a box on a plane; an ellipsoid pad and two cylinders on it
RAMP = FOREIGN / "mesh_ramp.xml"  # a convex mesh wedge; an ellipsoid pad and a cylinder on it


def test_pairs_mjx_lacks_are_accepted():
    types = {(int(a), int(b)) for a, b in collision.ADDED}
    smooth = (mujoco.mjtGeom.mjGEOM_ELLIPSOID, mujoco.mjtGeom.mjGEOM_CYLINDER)
    poly = (mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_MESH)
    assert {(int(a), int(b)) for a in smooth for b in poly} <= types


# (body, xy, euler), placed 2 mm into the box (top face at z = 0.1, x in +-0.3, y in +-0.2):
# on its top face, over an edge, over a corner
CASES = [("pad", (-0.15, 0.05), (20, 30, 0)),  # face
         ("pad", (0.0, 0.0), (0, 0, 0)),
         ("pad", (0.28, 0.0), (0, 0, 0)),
         ("can", (0.12, -0.08), (85, 4, 10)),
         ("can", (0.0, 0.0), (6, 8, 0)),  # on its end: C's point anywhere on the disc
         ("puck", (0.15, 0.1), (8, -6, 0)),
         ("can", (0.29, 0.0), (90, 0, 0)),  # across the x edge
         ("can", (0.0, 0.21), (90, 0, 90)),  # along the y edge, overhanging it
         ("pad", (0.3, 0.2), (10, 0, 0))]  # on the corner
FACE = CASES[:6]
# Left out: a flat cylinder overhanging an edge, tilted 30 degrees (0.31, 0, 30 deg about x), where
# C's penetration test gives 1.9 mm along x although the part of the cylinder inside the box spans
# 3.8 cm of x and 1.8 cm of z (sampled); this module gives the edge's point 11 mm deep.


# on the wedge (top face sloping from z = 0.15 at x = -0.3 to 0.02 at x = 0.3, y in +-0.2)
MESH = [("pad", (-0.12, 0.05), (20, 30, 0)),
        ("pad", (0.0, 0.0), (0, 0, 0)),
        ("pad", (0.29, 0.0), (0, 0, 0)),  # over the low edge
        ("can", (0.12, -0.08), (85, 4, 10)),
        ("can", (0.0, 0.0), (6, 8, 0)),
        ("can", (0.0, 0.21), (90, 0, 90))]  # overhanging the side


@pytest.fixture(scope="module")
def placers(x64):
    return {PADS: Placer(PADS, fixed=("block",), heights=(0.05, 0.5)),
            RAMP: Placer(RAMP, heights=(0.0, 0.6))}


@pytest.mark.parametrize("case", [(PADS, c) for c in CASES] + [(RAMP, c) for c in MESH],
                         ids=lambda c: f"{c[0].stem}-{c[1][0]}{c[1][1]}")
def test_contacts_agree_with_mujoco(placers, case):
    scene, case = case
    theirs, ours = placers[scene](*case)
    assert theirs, "C has no contact: the placement missed the polytope"
    for dist, pos, normal in theirs:
        our_dist, dpos, our_normal = nearest(ours, pos)
        assert abs(our_dist - dist) <= 1e-6, (dist, our_dist)
        assert dpos <= 5e-4, dpos
        # on an edge or a corner, C's normal is the geom's at the midpoint of its penetration
        # (an ellipsoid's by ray projection), ours the SDF's gradient at the box's point
        assert angle(our_normal, normal) <= (0.05 if case in FACE or scene == RAMP else 2.5)
    assert abs(ours[0].min() - min(dist for dist, _, _ in theirs)) <= 1e-6


@pytest.mark.parametrize("path", [PADS, RAMP], ids=["box", "mesh"])
def test_trajectory_follows_mujoco(x64, path):
    # the box lands on the plane and the pads on it (first contact ~ step 10), then rest; the
    # pads land on the wedge's slope
    sim = Sim.load(path, contacts="mujoco")  # a box on the plane as C makes it
    T = 60
    ours, theirs, traj = positions_against_mujoco(sim, T)
    err = np.linalg.norm(ours - theirs, axis=-1)
    assert float(np.asarray(traj.n_active)[-1]) >= (10 if path == PADS else 3)
    # measured: box 2e-7 m, pad 1.3e-5, cylinders 2.3e-4 and 3.7e-4 (C: one contact per pair, a
    # cylinder on its end rocking on it; ours: the rim's tripod); on the wedge, sliding down its
    # slope, pad 4.2e-4, cylinder 5.5e-5
    assert err.max() <= 1e-3, err.max(axis=0)


@pytest.mark.parametrize("name", ["box_pads", "mesh_ramp"])
def test_gradcheck_strict(x64, name):
    check_foreign_scene(name)
