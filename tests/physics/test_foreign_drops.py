"""Gradients through impact and resting contact of every primitive MJX collides with a plane and
of a convex mesh, each dropped tilted (float64, T = 30, against central differences)."""

import pytest

from tests.physics._foreign import check_foreign_scene


@pytest.mark.parametrize("name", ["box_drop", "ellipsoid_drop", "capsule_drop", "cylinder_drop",
                                  "mesh_drop"])
def test_dropped_object_passes_gradcheck_with_every_group_judged(x64, name):
    check_foreign_scene(name)
