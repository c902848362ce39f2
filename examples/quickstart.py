"""Real2Sim -> Learn@Sim -> Sim2Real in one page of the Python API (about a minute on 2 cores).

    python examples/quickstart.py [OUT]     # OUT (default runs/quickstart) gets the policy

The pendulum's real twin (MuJoCo C with hidden perturbations: masses, damping, friction,
actuator gain, latency, sensor noise) is recorded, the differentiable simulator is identified
from those transitions, a policy is learned in it with PODS (analytic gradients through MJX),
and deployed on the real twin. ``twinrl run`` does all of this with rounds, residual adaptation,
a report and plots; this is the same thing by hand.
"""

import sys
from pathlib import Path

import jax
import numpy as np

import twinrl  # noqa: F401  (the compilation cache, a quiet console)
from twinrl import envs, real
from twinrl.learn import PODSConfig, pods
from twinrl.learn.checkpoint import load_policy, save_policy
from twinrl.real2sim import sysid

TASK = "pendulum_swingup"
OUT = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/quickstart")

# Real2Sim: two exciting episodes on the real twin (a gymnasium.Env), then the fit
twin = real.make_real(TASK, seed=0)
data = sysid.collect(twin, episodes=2)
fit = sysid.fit(envs.make(TASK), data)
# Trajectories fix a pendulum's mass, damping, friction and gain only up to one common scale
# (statuses "only in combination"): the dynamics are identified all the same; give a weighed
# mass with SysidConfig(known=(("mass/pole", kg),)) to pin each value.
sysid.print_result(fit)

# Learn@Sim: PODS in the identified simulator (its parameters and latency)
env = envs.make(TASK, system=fit.system)
policy, params, metrics = pods.train(env, PODSConfig(epochs=10), jax.random.key(0))
print(f"return in the identified simulator: {metrics['return'][-1]:.1f}")
# a checkpoint with the identified system beside it: `twinrl eval --checkpoint OUT/policy --real`
save_policy(OUT / "policy", policy, params, system=fit.system, algo="pods", env=TASK)
policy, params, meta = load_policy(OUT / "policy")

# Sim2Real: the policy on the real twin
act = jax.jit(policy.apply)
returns = []
for episode in range(3):
    obs, _ = twin.reset(seed=100 + episode)
    total, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, _ = twin.step(np.asarray(act(params, obs)))
        total += reward
        done = terminated or truncated
    returns.append(total)
twin.close()
print(f"return on the real twin: {np.mean(returns):.1f} (3 episodes)")
