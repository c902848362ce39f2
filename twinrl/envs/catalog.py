"""What ``twinrl envs`` lists about a registered task: its sizes, whether its bodies touch, its
cameras and reward terms, and in words how its real twin may differ from it."""

from __future__ import annotations

import itertools

import mujoco

from twinrl.envs.base import PerturbationSpec


def has_contacts(mj_model) -> bool:
    """Whether any two geoms of different bodies can collide (contype/conaffinity), in a model
    whose contacts are not disabled (``<flag contact="disable"/>``, as in several Control Suite
    models)."""
    if mj_model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT):
        return False
    for i, j in itertools.combinations(range(mj_model.ngeom), 2):
        bi, bj = mj_model.geom_bodyid[i], mj_model.geom_bodyid[j]
        if bi == bj or (bi == 0 and bj == 0):
            continue
        if (mj_model.geom_contype[i] & mj_model.geom_conaffinity[j]) or (
                mj_model.geom_contype[j] & mj_model.geom_conaffinity[i]):
            return True
    return False


def describe_perturbation(spec: PerturbationSpec) -> str:
    """A real twin's perturbation distribution in one line: the scale ranges it draws from (those
    left at 1 are not listed), the joints it adds damping or friction to, its latency, noise and
    camera and grasp offsets."""
    scales = (("mass", spec.mass_scale), ("damping", spec.damping_scale),
              ("friction", spec.friction_scale), ("gain", spec.gain_scale))
    parts = [f"{what} x{lo:g}-{hi:g}" if lo != hi else f"{what} x{lo:g}"
             for what, (lo, hi) in scales if (lo, hi) != (1, 1)]  # untouched: not listed
    parts += [f"+damping {j} {lo:g}-{hi:g}" for j, lo, hi in spec.extra_damping]
    parts += [f"+frictionloss {j} {lo:g}-{hi:g} (unmodeled)" for j, lo, hi in spec.extra_frictionloss]
    parts += [f"latency {set(spec.latency_steps)} steps",
              f"obs noise <= {spec.obs_noise_std[1]:g}",
              f"camera offset sd {spec.camera_pos_std * 100:g} cm / {spec.camera_rot_std:g} rad"]
    if spec.tool_pos_std or spec.tool_rot_std:
        parts.append(f"grasp offset sd {spec.tool_pos_std * 1000:g} mm / {spec.tool_rot_std:g} rad")
    return ", ".join(parts)


def describe(name: str) -> dict:
    """Task ``name``'s entry in the catalogue: ``name``, ``obs_dim``, ``action_dim``, ``dt``,
    ``episode_length``, ``contacts``, ``cameras``, ``reward_terms``, ``real_twin_perturbs``."""
    from twinrl.envs.registry import make

    env = make(name)
    return {"name": name, "obs_dim": env.observation_size, "action_dim": env.action_size,
            "dt": env.dt, "episode_length": env.episode_length,
            "contacts": has_contacts(env.sim.mj_model), "cameras": list(env.cameras),
            "reward_terms": list(env.reward_term_names),
            "real_twin_perturbs": describe_perturbation(env.perturbation_spec)}
