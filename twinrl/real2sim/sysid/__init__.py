"""System identification from trajectories: fit ``PhysParams`` and the action latency to a dataset.

Real2Sim, first half (the loop's ``sysid`` stage, ``twinrl.loop``; SAM-RL Sec. 4.1, the Hybrid
Differentiable Simulation study's "parameter identification"): find the simulator parameters under
which recorded real transitions are most likely, by gradient-based optimisation *through* the
simulator.

Method
------
* **Multiple shooting** (Bock & Plitt 1984). A long rollout from one recorded state diverges (a
  pole swinging through upright amplifies any parameter error exponentially, and its gradient
  explodes with it), so the data are cut into short windows of ``window`` steps; each window
  starts from the state read off its first recorded observation (``Env.state_from_obs``), is
  rolled out open loop with its recorded actions, and is compared with the recorded next
  observations. Windows are independent, so they are vmapped, in fixed-size batches (one compile
  for any dataset size).
* **Estimated start states** (``estimate_start``, on by default: full multiple shooting): every
  window's start state is fitted with the parameters, so noise on the recorded start does not
  bias them (errors in variables). A start moves in tangent coordinates
  (``twinrl.physics.integrator.tangent_qpos``: a quaternion by a rotation vector, never along
  its norm), under a weak Gaussian prior around the recorded state (``start_prior_sd``, weighed
  like the parameters' prior), and is eliminated per window by the Schur complement (as in
  bundle adjustment). The prior decides only what no residual sees: without it, a flat disc's
  spin rate (Hessian 1e-8, gradient 5e-6; Marquardt's damping is relative to that diagonal)
  took LM steps of 1e5 rad/s, the rollouts blew up, and the damping rose until the parameters
  could not move.
* **Robust loss** on residuals normalised per observation dimension (by the data's spread):
  Huber or Cauchy, so a few bad windows (a glitch, an unmodelled knock) cannot drag the fit.
* **Bounds by reparameterisation**: the optimiser works on ``PhysParams.unconstrain()``
  coordinates (log for masses and gains, softplus^-1 for damping and friction), so every step is
  a valid model. A weak Gaussian prior around the initial values (``prior_sd`` in these
  coordinates) only matters along directions the data cannot see.
* **Parameters at their bound 0**: softplus coordinates cannot reach 0 (the value's slope
  vanishes there), so a damping or friction loss whose truth is 0 would stall at a small positive
  value and bias the parameters that trade off against it. After the fit, each fitted
  non-negative parameter is refitted held at 0 and kept there when the data's deviance rises by
  less than ``bound_lr`` (a likelihood-ratio test against the boundary null, scaled for the
  correlation inside a window); it is reported ``at bound 0`` with a one-sided sd in physical
  units, and the other parameters' sd are marginal over it.
* **Levenberg-Marquardt** (Gauss-Newton with Marquardt damping, iteratively reweighted for the
  robust loss) on the residual Jacobian from forward-mode AD (one tangent per parameter through
  every window); ``optimizer="adam"`` uses optax's Adam on reverse-mode gradients instead (kept
  to measure: LM needs far fewer rollouts on these few-parameter problems).
* **Latency** is discrete: the fit is run for each latency 0..``max_latency`` (the action applied
  at step t is the one sent at t - latency; zeros before the episode began, as the real twin
  does) and the latency with the smallest loss is kept.
* **Uncertainty** by the Laplace / Gauss-Newton approximation: the Fisher information
  ``J^T W J / sigma_d^2`` of the residuals at the optimum (``sigma_d^2`` the residual variance of
  each observation dimension), inverted with the prior. Residuals inside one window are
  correlated (one noisy start state moves all of them), so by default the covariance is the
  window-clustered sandwich ``H^-1 (sum_w g_w g_w^T) H^-1`` (``uncertainty="sandwich"``), which
  stays honest under that correlation and under model mismatch; ``"gauss_newton"`` is the plain
  ``H^-1``.
* **Identifiability**: eigen-directions of the data's Fisher information whose standard deviation
  exceeds ``max_rel_sd`` are *flat*. A parameter whose posterior sd exceeds ``max_rel_sd`` is
  reported not identifiable. If a direction is all but unconstrained (sd > ``flat_sd``) and
  mostly one parameter (e.g. a geom friction without contacts), that parameter is put back to its
  nominal value and the rest are refitted;
  if it is a combination (rigid-body dynamics are unchanged when every mass, force gain, damping
  and friction is scaled by one factor -- trajectories alone cannot tell a heavy robot with a
  strong motor from a light one with a weak motor), its component stays at the prior and the
  parameters in it are flagged "only in combination". Fix the scale with a known value
  (``SysidConfig.known``, e.g. the weighed cart mass) to identify each parameter on its own.

Friction loss and MJX: MJX allocates a friction-loss constraint row only for dofs whose friction
loss is non-zero in the compiled MJCF (``dof_hasfrictionloss``, fixed at ``mjx.put_model``); on
other dofs ``PhysParams.frictionloss`` has no effect and zero gradient. The cartpole's MJCF has
no rail friction, its real twin does. So the fit builds its own simulator from the MJCF with a
tiny friction loss (``frictionloss_floor``, 1e-6 N: no measurable force) on every dof whose
friction loss is fitted: the row exists, and the fitted value flows into it.

The evaluation against the truth (``compare_to_truth``) takes the true parameters as an argument
and lives apart from the fit: learning code never sees the real twin's hidden perturbation.

Example::

    twin = twinrl.real.make_real("cartpole_swingup", seed=0)
    data = collect(twin, episodes=5, seed=0)          # excitation actions on the real twin
    result = fit(twinrl.envs.make("cartpole_swingup"), data, SysidConfig())
    print_result(result)
    env = twinrl.envs.make("cartpole_swingup", system=result.system)  # params + latency

Modules (each does one thing; the names above are importable from here):

- ``config``: ``SysidConfig``, the fittable parameters' names (``param_names``, ``parse_param``);
- ``data``: ``excitation_actions``, ``collect`` (real-twin excitation), ``Windows``,
  ``windows_from_dataset`` (multiple-shooting windows);
- ``problem``: ``Problem``, ``build_problem`` (robust residuals and their Jacobian through MJX);
- ``optimise``: Levenberg-Marquardt and Adam on a ``Problem``;
- ``uncertainty``: the Laplace posterior, flat directions and the tests at the bound 0;
- ``fit``: ``fit`` and ``SysidResult``;
- ``reporting``: ``print_result`` and (evaluation only) ``compare_to_truth``;
- ``indirect``: ``indirect`` (an estimator de-biased by simulation: the noise on recorded starts
  biases one-step fits, and indirect inference finds the parameters whose simulated data the
  estimator reads as it read the real data) and ``noise_sd_from_quaternions``.
"""

from twinrl.real2sim.sysid.config import FITTABLE, SysidConfig, param_names
from twinrl.real2sim.sysid.data import Windows, collect, excitation_actions, windows_from_dataset
from twinrl.real2sim.sysid.fit import SysidResult, fit
from twinrl.real2sim.sysid.indirect import IndirectResult, indirect, noise_sd_from_quaternions
from twinrl.real2sim.sysid.problem import Problem, build_problem
from twinrl.real2sim.sysid.reporting import compare_to_truth, print_result

__all__ = [
    "SysidConfig", "SysidResult", "Windows", "Problem", "fit", "windows_from_dataset",
    "build_problem", "param_names", "compare_to_truth", "excitation_actions", "collect",
    "print_result", "FITTABLE", "indirect", "IndirectResult", "noise_sd_from_quaternions",
]
