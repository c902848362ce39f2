"""The trainers' configs: ``JSONConfig.check_fields`` (one declarative validation, one-line
messages naming ``Class.field``) and a docstring on every field of every learner config."""

import dataclasses
import inspect

import pytest

from twinrl.learn import baselines, hds, networks, pods, shac
from twinrl.learn.common import JSONConfig

CONFIGS = [shac.SHACConfig, pods.PODSConfig, hds.HDSConfig, baselines.PPOConfig,
           baselines.APGConfig, networks.NetworkConfig]


@dataclasses.dataclass(frozen=True)
class Toy(JSONConfig):
    n: int = 1
    rate: float = 0.5
    p: float = 0.5
    q: float = 0.5
    limit: float | None = None
    widths: tuple[int, ...] = (4,)
    kind: str = "a"

    def __post_init__(self):
        self.check_fields(at_least_one=("n",), positive=("rate", "limit"), non_negative=("q",),
                          within={"p": "(0, 1]"}, choices={"kind": ("a", "b")},
                          widths=("widths",), optional=("limit",))


def test_check_fields_messages():
    cases = [(dict(n=0), "Toy.n must be an integer >= 1, got 0"),
             (dict(n=1.5), "Toy.n must be an integer >= 1, got 1.5"),
             (dict(n=True), "Toy.n must be an integer >= 1, got True"),
             (dict(rate=0.0), "Toy.rate must be > 0, got 0.0"),
             (dict(rate=float("nan")), "Toy.rate must be > 0, got nan"),
             (dict(rate=None), "Toy.rate must be > 0, got None"),
             (dict(q=-1), "Toy.q must be >= 0, got -1"),
             (dict(p=0.0), "Toy.p must be in (0, 1], got 0.0"),
             (dict(p=1.5), "Toy.p must be in (0, 1], got 1.5"),
             (dict(limit=-2.0), "Toy.limit must be > 0 or None, got -2.0"),
             (dict(widths=(4, 0)), "Toy.widths must be layer widths that are integers >= 1"),
             (dict(widths=4), "Toy.widths must be layer widths"),
             (dict(kind="c"), "Toy.kind must be one of 'a', 'b', got 'c'")]
    for kwargs, message in cases:
        with pytest.raises(ValueError) as err:
            Toy(**kwargs)
        assert str(err.value).startswith(message), (kwargs, str(err.value))
        assert "\n" not in str(err.value)
    ok = Toy(n=2.0, p=1.0, limit=None, widths=[3, 5], kind="b")
    assert ok.widths == (3, 5) and Toy.from_dict(ok.to_dict()) == ok


def test_trainer_configs_use_it():
    for cls, kwargs, message in [
            (shac.SHACConfig, dict(horizon=0), "SHACConfig.horizon must be an integer >= 1"),
            (pods.PODSConfig, dict(gamma=1.0), "PODSConfig.gamma must be in (0, 1)"),
            (hds.HDSConfig, dict(noise_decay=0.0), "HDSConfig.noise_decay must be in (0, 1]"),
            (hds.HDSConfig, dict(rollout_length=0), "HDSConfig.rollout_length must be an integer"
                                                    " >= 1 or None"),
            (baselines.PPOConfig, dict(gae_lambda=2.0), "PPOConfig.gae_lambda must be in [0, 1]"),
            (baselines.APGConfig, dict(policy_hidden=(0,)), "APGConfig.policy_hidden must be"),
            (networks.NetworkConfig, dict(activation="x"), "NetworkConfig.activation must be")]:
        with pytest.raises(ValueError) as err:
            cls(**kwargs)
        assert str(err.value).startswith(message), str(err.value)
    for cls in CONFIGS:   # defaults are valid and survive the JSON round trip
        assert cls.from_dict(cls().to_dict()) == cls()


def test_every_learner_config_field_has_a_docstring():
    for cls in CONFIGS:
        src = "".join(inspect.getsource(c) for c in cls.__mro__
                      if c.__module__.startswith("twinrl") and c is not JSONConfig)
        for f in dataclasses.fields(cls):
            after = src.split(f"\n    {f.name}:", 1)
            assert len(after) == 2 and after[1].split("\n", 2)[1].strip().startswith('"""'), (
                cls.__name__, f.name)
