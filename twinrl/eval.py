"""Evaluation only: what the loop and the benchmarks measure against the real twin's hidden truth.

The learning side of twinrl sees only what a real robot would give it (recorded transitions and
images). Judging it needs the truth the real twin hides: its true parameters (to score
identification) and a policy trained on them (the *oracle*, to score returns). Those reads live
here, the only module outside ``twinrl/real`` allowed to call ``RealTwin.oracle`` (a test greps the
package for it); nothing here is ever fed back into learning.
"""

from __future__ import annotations

import jax
import numpy as np

__all__ = ["param_errors", "real_return", "policy_real_return", "oracle_return"]


def param_errors(twin, result) -> dict[str, float]:
    """Relative error of every fitted parameter against the twin's hidden truth (parameters the
    data fix only up to a common scale are compared after that scale: ``aligned_rel_err``;
    parameters left at nominal as not identifiable are left out)."""
    from twinrl.real2sim.sysid import compare_to_truth

    truth = twin.oracle()
    rows = compare_to_truth(result, truth.params, truth.perturbation.latency_steps)
    return {row["parameter"]: float(row.get("aligned_rel_err", row["rel_err"]))
            for row in rows if not str(row.get("status", "")).startswith(("known", "not ident"))}


def real_return(env_name, seed, policy_dir, episodes, perturbation=None):
    """Mean return of a policy checkpoint on a fresh copy of the real twin (same hidden
    perturbation), not recorded and not counted."""
    from twinrl.learn.checkpoint import load_policy

    net, params, _ = load_policy(policy_dir)
    f = jax.jit(net.apply)
    return policy_real_return(env_name, seed, lambda o: f(params, o), episodes, perturbation)


def policy_real_return(env_name, seed, act, episodes, perturbation=None):
    """Mean return of ``act: obs -> action`` over ``episodes`` episodes of a fresh copy of the real
    twin, started from the same states as ``real_return``'s (so two policies compare on equal
    terms), not recorded and not counted."""
    from twinrl import envs

    twin = envs.make_real(env_name, seed=seed, perturbation=perturbation)
    rets = []
    try:
        for e in range(episodes):
            obs, _ = twin.reset(seed=10_000 + e)
            done, ret = False, 0.0
            while not done:
                obs, rw, term, trunc, _ = twin.step(np.asarray(act(obs), np.float32))
                ret, done = ret + rw, term or trunc
            rets.append(ret)
    finally:
        twin.close()
    return float(np.mean(rets))


def oracle_return(env_name, seed, out, config, progress, perturbation=None) -> float:
    """The oracle: trained in a simulator with the twin's true parameters (evaluation only)."""
    from twinrl import envs
    from twinrl.learn.runner import continue_run

    twin = envs.make_real(env_name, seed=seed, perturbation=perturbation)
    truth = twin.oracle().params
    twin.close()
    env = envs.make(env_name, params=truth)
    if not (out / "policy" / "checkpoint.json").exists():
        continue_run(env_name, config.algo, out, seed=seed, epochs=config.epochs,
                     progress=progress, env=env, checkpoint_every=config.checkpoint_every)
    return real_return(env_name, seed, out / "policy", config.eval_episodes, perturbation)
