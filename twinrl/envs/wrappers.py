"""Brax-style wrappers of a task that belong to the identified system, not to the trainer.

``LatencyWrapper`` delays every action by ``latency`` control steps, as the real twin does
(``twinrl.real.twin.RealTwin``: the action sent at step t is applied at t + latency, zeros before
the episode began). Real2Sim identifies that latency (``twinrl.real2sim.sysid``); carried by a
``twinrl.envs.system.System`` it reaches every learner through ``envs.make(name, system=...)``.

The queue of the last ``latency`` sent actions rides in ``State.info``, so the wrapped env stays a
pure function of pytrees: ``reset``/``step`` jit and vmap, and ``jax.grad`` of a return w.r.t. the
actions goes through the queue (an action's gradient is that of the step it is applied in). Brax's
trainers take it unmodified (``brax.envs.wrappers.training.wrap`` puts its episode and auto-reset
wrappers outside this one).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs import base as brax_base

__all__ = ["LatencyWrapper", "QUEUE_KEY"]

State = brax_base.State

QUEUE_KEY = "latency/queue"
"""``State.info`` key of the (latency, action_size) queue of sent, not yet applied actions."""
_SEEN_KEY = "latency/steps_seen"


class LatencyWrapper(brax_base.Wrapper):
    """``env`` with every action applied ``latency`` control steps after it is sent.

    The reward is that of the state reached, with the *sent* action in its control term, as the
    real twin computes it. Under Brax's ``EpisodeWrapper`` + ``AutoResetWrapper`` the queue is
    emptied when an episode auto-resets (seen as the episode's step count going back), so no
    action crosses from one episode into the next.

    The delay is part of the simulated system, so the wrapper is its own ``unwrapped``: Brax's
    ``DomainRandomizationVmapWrapper`` steps ``env.unwrapped`` with a randomised ``sys``, and the
    delay must stay in that step (``sys`` is read from and written to the wrapped task).
    """

    def __init__(self, env: brax_base.Env, latency: int):
        if isinstance(latency, bool) or int(latency) != latency or int(latency) < 1:
            raise ValueError(f"latency must be an integer >= 1 control step (0: do not wrap), "
                             f"got {latency!r}")
        super().__init__(env)
        self.latency = int(latency)

    def __repr__(self) -> str:
        return f"LatencyWrapper({self.env!r}, latency={self.latency})"

    @property
    def unwrapped(self):
        return self

    @property
    def sys(self):
        return self.env.sys

    @sys.setter
    def sys(self, value):
        self.env.sys = value

    def with_system(self, system):
        """The wrapped task built from ``system`` (``Env.with_system``), delayed by the system's
        latency (not wrapped at latency 0), as ``envs.make(name, system=system)`` builds it; this
        wrapper and its task are untouched."""
        env = self.env.with_system(system)
        return LatencyWrapper(env, system.latency) if system.latency else env

    def reset(self, rng: jax.Array) -> State:
        state = self.env.reset(rng)
        info = dict(state.info)
        info[QUEUE_KEY] = jnp.zeros((self.latency, self.env.action_size), jnp.result_type(float))
        info[_SEEN_KEY] = jnp.zeros(())
        return state.replace(info=info)

    def _queue(self, state: State) -> tuple[jax.Array, jax.Array]:
        """The queue this step starts from and the step count seen."""
        queue, seen = state.info[QUEUE_KEY], state.info[_SEEN_KEY]
        if "steps" in state.info:
            # Brax's AutoResetWrapper sets the episode's step count back to 0 when it starts a new
            # episode (and keeps our info); equal counts are repeats of one step (action_repeat).
            steps = jnp.asarray(state.info["steps"], jnp.float32)
            queue = jnp.where(steps < seen, jnp.zeros_like(queue), queue)
            seen = steps
        return queue, seen

    def executed(self, state: State) -> jax.Array:
        """The action ``step(state, ...)`` applies: the head of the queue (zeros right after an
        auto-reset emptied it). A learned model of the dynamics must see this one, not the one
        sent (``twinrl.sim2real.hybrid.make_dynamics``)."""
        return self._queue(state)[0][0]

    def step(self, state: State, action: jax.Array) -> State:
        queue, seen = self._queue(state)
        action = jnp.clip(jnp.asarray(action, queue.dtype).reshape(self.env.action_size),
                          -1.0, 1.0)
        applied, queue = queue[0], jnp.concatenate([queue[1:], action[None]], axis=0)
        nstate = self.env.step(state, applied)
        data = nstate.pipeline_state
        reward, terms = self.env.reward(data.qpos, data.qvel, action)
        metrics = dict(nstate.metrics)
        metrics.update({f"reward/{k}": v for k, v in terms.items()})
        info = dict(nstate.info)
        info[QUEUE_KEY], info[_SEEN_KEY] = queue, seen
        return nstate.replace(reward=reward, metrics=metrics, info=info)

    def unroll(self, state: State, actions: jax.Array) -> tuple[State, jax.Array]:
        """Open-loop rollout of the sent ``actions`` (T, action_size) through the delay; returns
        the final state and the (T,) rewards (``Env.unroll``'s contract)."""
        def body(s, a):
            s = self.step(s, a)
            return s, s.reward
        return jax.lax.scan(body, state, actions)
