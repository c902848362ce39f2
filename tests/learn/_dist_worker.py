"""One process of ``tests/learn/test_distributed.py``'s runs
(``python -m tests.learn._dist_worker``).

``--what shac``: ``runner.train_run`` of SHAC on ``test_shac.PointMass`` (a tiny config) into
``--out``: the runner's files, its checkpoints and the one writer, as ``twinrl train`` drives
them. ``--what fit``: the imitation actor's data-parallel minibatch fit
(``common.make_minibatch_fit`` with the global mesh, as ``imitation.train`` builds it) on a
fixed synthetic regression, its parameters saved to ``--out/fit.npz``. ``--what hds``:
``hds.train`` on ``Slider`` (a point mass with the simulator interface PODS and HDS's windows
use), with exploration, the annealed step size, the critic and half the rollouts through a
heavier slider's ``step`` (the model fraction), its parameters and step sizes saved to
``--out/hds.npz``. ``--what q``: the sensing Q's fit (``sensing.fit_q``: images augmented, an
ensemble of two, one compiled step a minibatch) on a synthetic set of 8 x 8 images, its
parameters and losses saved to ``--out/q.npz``. ``--what ppo``: one Brax PPO iteration
(``PPO``). ``--what apg``: Brax APG through the runner (refused on several processes).

Without ``--num-processes`` (or with 1) the process runs alone, the one-process reference.
Several ``--what`` run one after the other (fit, ppo, apg, q, hds, shac) in one start-up."""

import argparse
import functools
import json
import sys
from pathlib import Path

SHAC = {"num_envs": 8, "horizon": 8, "critic_iterations": 2, "critic_minibatches": 2,
        "actor_hidden": [16], "critic_hidden": [16], "eval_episodes": 2}
"""``tests/learn/test_shac.TINY``'s fields: compiles in seconds."""


def fit(out: Path, mesh, fail: bool = False) -> None:
    import jax
    import numpy as np

    from twinrl.learn import distributed
    from twinrl.learn.common import make_minibatch_fit, make_optimizer
    from twinrl.learn.networks import NetworkConfig, make_network

    k_net, k_x, k_fit = jax.random.split(jax.random.PRNGKey(0), 3)
    net = make_network(4, 2, NetworkConfig(hidden=(16,), activation="elu", output="tanh"))
    x = jax.random.normal(k_x, (256, 4))
    y = np.tanh(np.asarray(x[:, :2] - 0.5 * x[:, 2:]))
    tx = make_optimizer(1e-2, 1.0)
    params = net.init(k_net)
    if mesh is not None:  # each process's rows, assembled into the global batch they are
        mine = distributed.process_rows(256, mesh)
        whole = distributed.global_batch(np.asarray(x)[mine], mesh)
        assert whole.shape == (256, 4) and len(whole.addressable_shards) == 1
        np.testing.assert_array_equal(distributed.to_host(whole), np.asarray(x))
    if fail and jax.process_index() == 1:  # a bug in one process, its peer inside the fit
        raise ValueError("injected failure in process 1")
    run = make_minibatch_fit(net.apply, tx, 60, 32, mesh=mesh)
    params, _, losses = run(params, tx.init(params), x, y, 256, k_fit)
    if distributed.is_writer():
        leaves = jax.tree_util.tree_leaves(distributed.to_host(params))
        np.savez(out / "fit.npz", *leaves, losses=np.asarray(losses))


HDS = {"epochs": 3, "batch_size": 4, "rollout_length": 16, "horizon": 8, "line_search_steps": 3,
       "regression_steps": 16, "hidden": (16,), "eval_episodes": 2, "eval_length": 16,
       "model_fraction": 0.5, "critic": True, "critic_steps": 4, "critic_hidden": (16,)}
"""A tiny HDS: every part of its epoch (noise, annealing, model rollouts, critic) in seconds."""


def slider_env(mass: float = 1.0):
    """A ``Slider`` of ``mass`` (``slider_class``)."""
    return slider_class()(mass)


@functools.cache
def slider_class():
    """A 1-D point mass pushed towards the origin with the interface PODS and HDS's windows read
    of a twinrl env: ``sim.nq``, ``sim.rollout(data, actions, params, step_fn)``, ``sim_step``,
    ``params``, ``reward(qpos, qvel, action)``, ``observe(qpos, qvel)``, and a
    ``pipeline_state`` with ``qpos`` and ``qvel``. Compiles in seconds (no MJX)."""
    from typing import NamedTuple

    import jax
    import jax.numpy as jnp
    from brax.envs import base

    class Data(NamedTuple):
        qpos: jax.Array
        qvel: jax.Array

    class Sim:
        nq = 1

        def rollout(self, data, actions, params, step_fn):
            def body(d, a):
                d = step_fn(d, a, params)
                return d, d
            return jax.lax.scan(body, data, actions)

    class Slider(base.Env):
        episode_length = 16
        sim = Sim()
        def __init__(self, mass):
            self.params = jnp.float32(mass)

        def sim_step(self, d, a, params):
            qvel = d.qvel + 0.1 * jnp.clip(a, -1.0, 1.0) / params
            return Data(d.qpos + 0.1 * qvel, qvel)

        def reward(self, qpos, qvel, action):
            return jnp.exp(-qpos[0] ** 2 / 0.1) - 0.01 * jnp.sum(action ** 2), {}

        def observe(self, qpos, qvel):
            return jnp.concatenate([qpos, qvel])

        def reset(self, rng):
            q = jax.random.uniform(rng, (2,), minval=-1.0, maxval=1.0) * jnp.array([1.0, 0.2])
            zero = jnp.zeros(())
            return base.State(pipeline_state=Data(q[:1], q[1:]), obs=q, reward=zero,
                              done=zero, metrics={}, info={})

        def step(self, state, action):
            d = self.sim_step(state.pipeline_state, action, self.params)
            r = self.reward(d.qpos, d.qvel, action)[0]
            return state.replace(pipeline_state=d, obs=self.observe(d.qpos, d.qvel), reward=r)

        @property
        def observation_size(self):
            return 2

        @property
        def action_size(self):
            return 1

        @property
        def backend(self):
            return "jax"

    return Slider


def hds(out: Path) -> None:
    import jax
    import numpy as np

    from twinrl.learn import distributed
    from twinrl.learn.hds import HDSConfig, train

    heavy = slider_env(1.5)
    _, params, metrics = train(slider_env(), HDSConfig(**HDS), jax.random.PRNGKey(1),
                               dynamics=heavy.step)
    if distributed.is_writer():
        leaves = jax.tree_util.tree_leaves(distributed.to_host(params))
        np.savez(out / "hds.npz", *leaves,
                 **{k: np.asarray(metrics[k], np.float64) for k in (
                     "step_size", "step_size_proposal", "sa_accept", "energy", "return",
                     "value_loss", "accepted_frac")})


def q_fit(out: Path) -> None:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from twinrl.learn import distributed, sensing
    from twinrl.learn.networks import NetworkConfig, make_network

    S, C, PIX = 16, 4, 8
    kx, ku, k_init, k_fit = jax.random.split(jax.random.PRNGKey(2), 4)
    x = jax.random.uniform(kx, (S, 1, 1, 2), minval=-1.0, maxval=1.0)
    u = jax.random.uniform(ku, (S, C, 1, 1), minval=-1.0, maxval=1.0)
    ramp = jnp.linspace(0.0, 1.0, PIX)[:, None, None]  # the pose moves a gradient in the image
    image = jnp.clip(0.5 + 0.5 * u[..., None, None] * ramp + 0.1 * x[..., :1, None, None], 0, 1)
    obs = {"state": jnp.concatenate([jnp.broadcast_to(x, (S, C, 1, 2)), u], -1),
           "pixels/mount": jnp.broadcast_to(image, (S, C, 1, PIX, PIX, 5))}
    targets = 0.5 + 0.25 * x[..., 0] - 0.4 * (u[..., 0] - 0.5 * x[..., 1]) ** 2
    data = sensing.SensingData(obs, jnp.concatenate([jnp.tanh(x[..., :1] + u), 0.5 * u], -1),
                               targets, jnp.zeros((S, C, 3)), targets[..., 0],
                               jnp.zeros((S, C)))
    actor = make_network({"state": (3,), "pixels/mount": (PIX, PIX, 5)}, 2,
                         NetworkConfig(hidden=(8,)))
    cfg = sensing.SensingConfig(hidden=(16,), ensemble=2, fit_steps=12, batch_size=16,
                                learning_rate=3e-3, rgb_jitter=0.1, random_shift=1)
    q = sensing.make_q(actor, 2, cfg)
    params, losses = sensing.fit_q(q, q.init(k_init), data, cfg, k_fit)
    if distributed.is_writer():
        leaves = jax.tree_util.tree_leaves(distributed.to_host(params))
        np.savez(out / "q.npz", *leaves, losses=np.asarray(losses))


PPO = {"num_timesteps": 128, "num_envs": 8, "batch_size": 8, "num_minibatches": 2,
       "unroll_length": 8, "num_updates_per_batch": 1, "policy_hidden": (16,),
       "value_hidden": (16,), "num_evals": 2, "num_eval_envs": 4, "episode_length": 20}
"""One Brax PPO iteration (8 x 8 x 2 steps) on ``test_shac.PointMass``: ``ppo_train`` (each
process's parameters saved to ``--out/ppo<process>.npz``), then the same through the runner into
``--out/ppo``."""


def ppo(out: Path) -> None:
    import jax
    import numpy as np

    from tests.learn.test_shac import PointMass
    from twinrl.learn import distributed
    from twinrl.learn.baselines import PPOConfig, ppo_train

    _, params, metrics = ppo_train(PointMass(), PPOConfig(**PPO), 0)
    leaves = jax.tree_util.tree_leaves(distributed.to_host(params))
    np.savez(out / f"ppo{jax.process_index()}.npz", *leaves,  # Brax reports on process 0
             env_steps=np.asarray(metrics.get("env_steps", [])))
    toy_run(out / "ppo", "ppo", PPO)  # twinrl train --algo ppo: one writer


def toy_run(out: Path, algo: str, overrides: dict, epochs: int | None = None,
            resume: bool = False) -> None:
    """``runner.train_run`` of ``algo`` on ``test_shac.PointMass`` into ``out``, as ``twinrl
    train`` drives it; the writer also saves the summary to ``out/worker.json``."""
    from tests.learn.test_shac import PointMass
    from twinrl.envs import system
    from twinrl.learn import distributed, runner

    class Toy(PointMass):
        config = {}  # no task config; no MJCF system (the checkpoint holds none)

    of = system.system_of
    system.system_of = lambda env: None if isinstance(env, Toy) else of(env)
    try:
        s = runner.train_run("pointmass", algo, out, seed=3, epochs=epochs, overrides=overrides,
                             resume=resume, progress=False, env=Toy())
    finally:
        system.system_of = of
    if distributed.is_writer():
        (out / "worker.json").write_text(json.dumps(s, default=str))


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--what", nargs="+", required=True,
                   choices=("shac", "fit", "hds", "q", "ppo", "apg"))
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--coordinator")
    p.add_argument("--num-processes", type=int, default=1)
    p.add_argument("--process-id", type=int, default=0)
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--resume", action="store_true")
    p.add_argument("--timeout", type=int, default=20)
    p.add_argument("--fail", action="store_true", help="process 1 raises before the fit")
    a = p.parse_args(argv)
    from twinrl.learn import distributed

    many = a.num_processes > 1
    if many:  # before anything starts a JAX backend
        distributed.initialize(a.coordinator, a.num_processes, a.process_id,
                               timeout_s=a.timeout, heartbeat_s=a.timeout)
    a.out.mkdir(parents=True, exist_ok=True)
    with distributed.guard("worker"):
        if "fit" in a.what:
            fit(a.out, distributed.global_mesh() if many else None, a.fail)
        if "ppo" in a.what:
            ppo(a.out)
        if "apg" in a.what:  # refused on several processes
            toy_run(a.out, "apg", {"policy_updates": 2, "num_envs": 8, "num_evals": 2})
        if "q" in a.what:
            q_fit(a.out)
        if "hds" in a.what:
            hds(a.out)
        if "shac" in a.what:
            toy_run(a.out, "shac", SHAC, a.epochs, a.resume)
    return 0


if __name__ == "__main__":
    sys.exit(main())
