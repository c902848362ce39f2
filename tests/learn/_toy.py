"""A trivial resumable trainer (random parameter steps) that follows the trainer contract, so the
runner's files, checkpoints and resume plumbing are tested without compiling a real trainer."""

import dataclasses

import jax
import optax

from twinrl.learn.common import MetricLog, make_evaluator
from twinrl.learn.networks import make_policy


@dataclasses.dataclass(frozen=True)
class ToyConfig:
    epochs: int = 3
    lr: float = 1e-2
    kept: int = -1  # >= 0: the metrics mark that epoch ``kept`` (as imitation marks its best)


def train(env, config, rng, *, progress_fn=None, checkpoint_fn=None, restore=None):
    pol = make_policy(env.observation_size, env.action_size, (8,))
    k0, rng = jax.random.split(rng)
    params = pol.init(k0)
    opt = optax.adam(config.lr)
    state = {"params": params, "opt": opt.init(params), "rng": rng}
    log = MetricLog()
    if restore is not None:
        state, hist = restore(state)
        log = MetricLog(hist)
    ev = make_evaluator(env, pol.apply, 2, 20)
    start = len(log.history.get("epoch", []))
    for e in range(start, config.epochs):
        rng, k = jax.random.split(state["rng"])
        g = jax.tree.map(lambda x: jax.random.normal(k, x.shape), state["params"])
        u, o = opt.update(g, state["opt"])
        p = optax.apply_updates(state["params"], u)
        state = {"params": p, "opt": o, "rng": rng}
        row = log.record(epoch=e, env_steps=(e + 1) * 40, grad_norm=1.0,
                         **{"return": ev(p, k).mean()})
        if progress_fn:
            progress_fn(e, row)
        if checkpoint_fn:
            checkpoint_fn(e, state, log.as_dict())
    metrics = log.as_dict()
    if config.kept >= 0:
        metrics["kept"] = [float(e == config.kept) for e in range(config.epochs)]
    return pol, state["params"], metrics
