"""Bundled MJCF scenes and the gradient-check scenario of each.

Each scenario starts where a rollout visits both constraint-free and constrained steps, so a
gradient check exercises the solve's forward and backward in both regimes:
- ``cartpole``: smooth (no constraints at all);
- ``pendulum``: swings freely over the top and round into its joint limit;
- ``push``: the box drops onto the floor, the pusher touches it, pushes, and pulls away;
- ``peg_in_hole``: the peg starts in free space above the hole, then touches walls and floor.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

__all__ = ["SCENES", "SCENARIOS", "Scenario", "scene_path", "scenario"]

_DIR = Path(__file__).parent
SCENES = ("cartpole", "pendulum", "push", "peg_in_hole")
# Gradient-check scenarios: generic ones for any MJCF, and each bundled scene's own.
SCENARIOS = ("wave", "zero") + SCENES


def scene_path(name: str) -> Path:
    """Path of a bundled scene's MJCF."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; bundled scenes are {', '.join(SCENES)}")
    return _DIR / f"{name}.xml"


@dataclasses.dataclass(frozen=True)
class Scenario:
    """Initial state and open-loop actions of a gradient check."""

    qpos: np.ndarray
    qvel: np.ndarray
    actions: np.ndarray  # (T, nu)
    horizon: int


def _wave(t: np.ndarray, nu: int, rng: np.random.Generator, scale: float) -> np.ndarray:
    """Smooth pseudo-random actions: a few sines of random phase per actuator."""
    freqs = rng.uniform(0.5, 3.0, size=(3, nu))
    phases = rng.uniform(0, 2 * np.pi, size=(3, nu))
    a = np.sin(t[:, None, None] * freqs * 2 * np.pi * 0.01 + phases).sum(1) / 3
    return scale * a


def scenario(name: str, nq: int, nv: int, nu: int, qpos0: np.ndarray, horizon: int | None = None,
             seed: int = 0) -> Scenario:
    """A gradient-check scenario by name (``SCENARIOS``), from ``qpos0`` at rest.

    ``"wave"``: smooth pseudo-random actions (a few sines per actuator, amplitude 0.5);
    ``"zero"``: no actuation (a dropped object, a passive mechanism); a bundled scene's name: that
    scene's own scenario (it needs that scene's sizes).
    """
    if name not in SCENARIOS:
        raise ValueError(f"unknown gradcheck scenario {name!r}; choose one of "
                         f"{', '.join(SCENARIOS)}")
    if name in SCENES:
        want = {"cartpole": (2, 2, 1), "pendulum": (1, 1, 1), "push": (9, 8, 2),
                "peg_in_hole": (2, 2, 2)}[name]
        if (nq, nv, nu) != want:
            raise ValueError(f"scenario {name!r} is the bundled {name} scene's (nq, nv, nu) = "
                             f"{want}; this model has {(nq, nv, nu)}: use --scenario wave or zero")
    rng = np.random.default_rng(seed)
    default_t = {"peg_in_hole": 50}.get(name, 100)
    T = horizon or default_t
    t = np.arange(T, dtype=np.float64)
    qpos, qvel = np.array(qpos0, dtype=np.float64), np.zeros(nv)
    actions = _wave(t, nu, rng, 0.5) if nu and name != "zero" else np.zeros((T, nu))
    if name == "cartpole":
        qpos[:] = [0.0, 0.3]
        qvel[:] = [0.2, -0.5]
    elif name == "pendulum":
        qpos[:] = [-2.9]          # short of upright, swinging over the top
        qvel[:] = [-3.0]          # into the -220 deg limit (-3.84 rad): free first, then limited
    elif name == "push":
        qpos[2] = 0.15            # box x (free joint at qpos[2:9])
        qpos[4] = 0.07            # dropped from 2 cm above the floor
        # push in +x for the first 60% of the horizon, then pull back; small y sway
        k = int(0.6 * T)
        actions[:, 0] = np.where(t < k, 0.6, -0.8)
        actions[:, 1] = 0.1 * np.sin(t * 0.1)
    elif name == "peg_in_hole":
        qpos[:] = [0.004, 0.0]    # offset 4 mm in x (clearance is 5 mm) so the peg grazes a wall
        actions[:, 0] = 0.05 * np.sin(t * 0.2)
        actions[:, 1] = -0.3
    return Scenario(qpos=qpos, qvel=qvel, actions=actions, horizon=T)
