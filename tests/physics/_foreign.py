"""Shared check of the foreign scenes (``tests/physics/foreign/*.xml``): MJCF files written for
these tests, not the bundled scenes, in the shapes users write (free primitives and a convex mesh
dropped on a plane, a box thrown along it, pushed by an actuated body, pressed by a 2-link arm)."""

from pathlib import Path

import jax

from twinrl.physics import Sim
from twinrl.physics.gradcheck import gradcheck

FOREIGN = Path(__file__).parent / "foreign"
HORIZON = 30  # 0.15 s at dt 0.005: each drop is free for ~10 steps, then impact and settling


def check_foreign_scene(name: str, contacts: str = "mjx") -> None:
    with jax.enable_x64(True):
        sim = Sim.load(FOREIGN / f"{name}.xml", contacts=contacts)
        r = gradcheck(sim, horizon=HORIZON, scenario="wave" if sim.nu else "zero")
    assert r.dtype == "float64"
    assert r.nan_count == 0
    assert r.failures == [], r.failures[:5]
    assert r.max_rel_error <= 1e-4
    # every group judged on a resolved entry (or inert: exactly no effect on the loss)
    assert r.unjudged == [] and r.passed_strict
    groups = {g["group"]: g for g in r.groups}
    assert groups["params.friction"]["resolved"] >= 1  # friction acts in every scene
    assert groups["params.mass"]["resolved"] >= 1 and groups["qpos"]["resolved"] >= 1
    assert r.constrained_steps >= 10  # through impact and contact, not only free flight
    assert r.count("resolved") >= 0.6 * len(r.rows)
