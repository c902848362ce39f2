"""One process of ``tests/learn/test_distributed.py``'s runs
(``python -m tests.learn._dist_worker``).

``--what shac``: ``runner.train_run`` of SHAC on ``test_shac.PointMass`` (a tiny config) into
``--out``: the runner's files, its checkpoints and the one writer, as ``twinrl train`` drives
them. ``--what fit``: the imitation actor's data-parallel minibatch fit
(``common.make_minibatch_fit`` with the global mesh, as ``imitation.train`` builds it) on a
fixed synthetic regression, its parameters saved to ``--out/fit.npz``. Without
``--num-processes`` (or with 1) the process runs alone, the one-process reference. ``--what
both``: the fit, then SHAC (one start-up for both)."""

import argparse
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


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--what", choices=("shac", "fit", "both"), required=True)
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
        if a.what in ("fit", "both"):
            fit(a.out, distributed.global_mesh() if many else None, a.fail)
        if a.what in ("shac", "both"):
            from tests.learn.test_shac import PointMass
            from twinrl.envs import system
            from twinrl.learn import runner

            class Toy(PointMass):
                config = {}  # no task config; no MJCF system (the checkpoint holds none)

            of = system.system_of
            system.system_of = lambda env: None if isinstance(env, Toy) else of(env)

            s = runner.train_run("pointmass", "shac", a.out, seed=3, epochs=a.epochs,
                                 overrides=SHAC, resume=a.resume, progress=False, env=Toy())
            if distributed.is_writer():
                (a.out / "worker.json").write_text(json.dumps(s, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
