"""``envs.make(..., params=...)`` refuses parameters that do not fit the task's model, by name."""

import pytest

from twinrl import envs
from twinrl.physics import PhysParams, PhysParamsError


def test_another_tasks_params_are_refused_naming_the_field():
    push = envs.make("push").sim.default_params()
    with pytest.raises(PhysParamsError,
                       match=r"^PhysParams.mass has shape \(2,\); task 'pendulum_swingup' "
                             r"\(scene 'pendulum'\) needs \(1,\)") as e:
        envs.make("pendulum_swingup", params=push)
    assert "\n" not in str(e.value)


def test_a_mass_of_the_wrong_shape_is_refused():
    p = envs.make("cartpole_swingup").sim.default_params()
    with pytest.raises(ValueError, match=r"PhysParams.mass has shape \(\); .* needs \(2,\)"):
        envs.make("cartpole_swingup", params=p.replace(mass=p.mass[0]))
    with pytest.raises(ValueError, match=r"PhysParams.mass has shape \(0,\)"):
        envs.make("cartpole_swingup", params=p.replace(mass=p.mass[:0]))
    with pytest.raises(TypeError, match="params must be a PhysParams, got dict"):
        envs.make("cartpole_swingup", params=p.as_dict())
    assert isinstance(envs.make("cartpole_swingup", params=p).params, PhysParams)
