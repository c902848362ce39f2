"""The cartpole family's loop, Real2Sim -> Learn@Sim -> Sim2Real, in rounds, resumable:
``twinrl run`` on every task whose observation determines its state (cartpole, pendulum, ...).

What a user comes for: hand twinrl a system it cannot see inside (a task's real twin), let it watch
a few episodes, get back a policy that works on that system. Round 0 records ``K`` episodes with a
safe exciting open-loop policy (``twinrl.real2sim.sysid.excitation_actions``). Every round
``r >= 1``:

1. **sysid** on every real transition recorded so far -> ``PhysParams`` and action latency
   (``twinrl.real2sim.sysid``);
2. **hybrid refit**: the residual dynamics on top of the identified simulator
   (``twinrl.sim2real.hybrid``);
3. **learn in sim**, in the identified simulator: Brax PPO by default (see ``LoopConfig.algo`` for
   the measurements behind that choice), or any trainer of ``twinrl.learn.runner.ALGORITHMS``;
   with ``algo="hds"``, HDS with a fraction of rollouts through the hybrid model;
4. **residual**: the residual policy (zero at first, so the first deployment is exactly the
   simulator's policy) is trained through the hybrid model from recorded real states
   (``twinrl.sim2real.residual``) and kept only if it lowers the full-episode return neither
   through that model nor through the identified simulator (``residual.accept``; else pi_sim is
   deployed);
5. **deploy**: ``K`` real episodes of pi_sim + residual are run and recorded.

The round is data: ``ROUND`` is the list of its ``Stage`` values (sysid, hybrid, learn,
residual, deploy; round 0 is ``COLLECT``), each a small function that declares the values it
needs and gives by name (``data``, ``system``, ``env``, ``hybrid``, ``policy_dir``, ``residual``),
returns them, and saves them in its round's directory so a resumed run loads them back; the
engine (``twinrl.loop.engine``) walks them. ``FAMILY`` is what this family supplies to it.

Bookkeeping per round: real steps used so far, identified-parameter errors, sim return, real return
and the oracle's return. The **oracle** (evaluation only, never fed back) is a policy trained the
same way in a simulator given the twin's *true* parameters, evaluated on the real twin; the
parameter errors likewise read the twin's hidden truth. Both happen in evaluation functions
(``twinrl.eval``, the only module
outside ``twinrl/real`` allowed to read the twin's oracle) that the learning stages never call.

The real twin is served in another process (``twinrl.real.remote.TwinClient``): the loop holds a
``gymnasium.Env`` client with no model or perturbation in it, whose hidden perturbation is seeded
by the public seed and a secret salt. Everything evaluation writes (the salt, ``twin.json``; the
oracle's training, ``oracle/``; the per-round evaluation records, ``evaluation.json``) goes to
``OUT/eval/``, a directory the stages never read; ``summary.json`` and the report merge it in at
the end.

Resume: every stage writes its outputs, then marks itself done in ``progress.json`` (atomically).
Real episodes go to ``dataset/`` as they happen (``twinrl.real.dataset``), so a run killed at any
moment loses nothing recorded; ``resume=True`` skips the finished stages, counts the episodes the
dataset already holds for the interrupted collection stage, and resumes training from its last
saved epoch (``twinrl.learn.runner``). Episode ``e`` of round ``r`` is seeded from ``(seed, r,
e)`` alone, so a resumed run records the episodes an uninterrupted one would have.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from twinrl import eval as evaluation
from twinrl import report
from twinrl.loop.engine import (Family, RunContext, Stage, episodes_in, real_steps,
                                seconds_so_far)
from twinrl.loop.engine import run as run_family
from twinrl.loop.errors import LoopError
from twinrl.loop.rundir import RoundDir, RunDir
from twinrl.loop.shared import EpisodeLog, collect_round0

__all__ = ["LoopConfig", "run", "COLLECT", "ROUND", "FAMILY", "deployed_policy",
           "identified_system"]


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Settings of ``twinrl run``."""

    rounds: int = 1
    """Rounds of sysid -> hybrid -> learn -> deploy after the round-0 collection (1 by default:
    the default cartpole loop takes ~7 min 50 s on 2 cores with a cold compilation cache, of the
    10 minutes ``make run`` has; ``summary.json`` gives each stage's seconds)."""
    episodes_per_round: int = 2
    """Real episodes recorded per round (round 0: exciting open-loop actions)."""
    algo: str = "ppo"
    """Learner in sim (``twinrl.learn.runner.ALGORITHMS``). Brax PPO by default, for measured
    reasons (2 cores, ``cartpole_swingup``, seed 0): with SHAC the loop's sim policy stalled at 88
    (balanced, but the cart drifting 5-16 m out, where the ``centered`` reward term is flat and
    gives no gradient back), 68 % of the oracle; SHAC alone reaches PPO's final return on 2 of 3
    seeds (``bench/results/learn.json``; no setting screened reached it on 3, docs' known
    limits). With PPO (3.5 M
    simulated steps, ~3.5 min beside the oracle's) the default loop reaches 99.5-101.7 % of the
    oracle on cartpole real twins 0-2 (entropy cost 0.03, ``learn.tuned.TUNED``). SHAC with
    horizon 64 learns the identified simulator of twin 0 well (sim return 195.0, real 192.5, where
    PPO's loop made 191.5), but the same trainer on the twin's true parameters (the oracle)
    rose slowly and ended at a sim return of 130 after 300 epochs (real 94), and on
    ``bench/learn.py``'s seed 2 it levels off at 187.5: not robust enough to be the default. The
    differentiable simulator still does the sysid and the residual adaptation; ``hds`` is the
    learner that mixes the hybrid model into learning (``model_fraction``); ``compare`` trains
    a second learner beside this one for the report."""
    epochs: int | None = None
    """Training epochs per round (None: the algorithm's tuned value for the task)."""
    model_fraction: float = 0.25
    """HDS's beta: fraction of rollouts through the hybrid model (0 disables the hybrid in
    learning; used with ``algo="hds"`` only)."""
    hybrid: bool = True
    """Fit the hybrid residual dynamics each round (needed for the residual policy)."""
    residual: bool = True
    """Adapt with a residual policy trained through the hybrid model before each deployment."""
    sysid_window: int | None = None
    """Multiple-shooting window length (steps) of sysid (None: ``SysidConfig``'s default)."""
    checkpoint_every: int = 10
    """Save the learner's train state every this many epochs (a killed round resumes from the
    last save; saving every epoch costs SHAC on cartpole about a second an epoch)."""
    compare: str | None = None
    """A second learner (e.g. ``"ppo"``) trained on each round's identified simulator for the
    report only (``round<r>/compare/``), never deployed: its learning wall clock and sim return
    beside the deployed learner's, and the seconds the deployed learner took to first reach the
    second's final return. Costs the second learner's training time."""
    oracle: bool = True
    """Train and evaluate the oracle policy (evaluation only)."""
    oracle_in_background: bool = True
    """Train the oracle in a lower-priority child process from the start, while the loop's stages
    run: it needs nothing the loop records, and it takes the CPU the stages leave idle."""
    eval_episodes: int = 3
    """Evaluation-only real episodes of the oracle and of the sim policy without adaptation (not
    recorded, not counted as real steps)."""
    video: bool = True
    """Write final.mp4: the final real episode beside the simulator's."""

    def __post_init__(self):
        for name in ("rounds", "episodes_per_round", "eval_episodes", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise LoopError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.model_fraction < 1.0:
            raise LoopError(f"model_fraction must be in [0, 1), got {self.model_fraction}")
        if self.model_fraction > 0 and not self.hybrid:
            raise LoopError("model_fraction > 0 needs the hybrid model (hybrid=True)")
        if self.residual and not self.hybrid:
            raise LoopError("the residual policy is trained through the hybrid model: "
                            "residual=True needs hybrid=True")


# ------------------------------------------------------------------------------ the stages
def record(run: RunContext, episodes, policy, reset_rng) -> list[float]:
    """Record ``episodes`` (indices) on the real twin: episode ``e`` reset with a seed drawn from
    ``reset_rng(e)``, driven by ``policy(e)``; returns their returns."""
    from twinrl.real.record import record_episodes

    recorded = record_episodes(run.twin, episodes, policy,
                               lambda e: int(reset_rng(e).integers(0, 2**31 - 1)),
                               writer=run.writer)
    return [x.ret for x in recorded]


def collect_excitation(run: RunContext, r: int, rdir: RoundDir) -> None:
    """Round 0: ``K`` episodes of safe exciting open-loop actions, recorded (those the dataset
    already holds, from an interrupted run, are not recorded again). Episode ``e``'s actions
    come from the seed ``[seed, e]``, its reset from ``[seed, e, 1]``."""
    from twinrl.real2sim import sysid

    T = run.nominal_env.episode_length

    def policy(e):
        acts = sysid.excitation_actions(np.random.default_rng([run.seed, e]), T,
                                        run.nominal_env.action_size)
        return lambda o, t: acts[min(t, T - 1)]

    def episodes(todo):
        record(run, todo, policy, lambda e: np.random.default_rng([run.seed, e, 1]))
        return {"real_return": None}

    collect_round0(run, "exciting episodes on the real twin", episodes)


def fit_system(run: RunContext, r: int, rdir: RoundDir, data) -> dict[str, Any]:
    """sysid on every real transition so far -> the identified ``System`` (parameters and action
    latency) in ``system.json``, and the fit's record (the System, its table and cost) in
    ``sysid.json``."""
    from twinrl.real2sim import sysid

    run.say(f"  sysid on {len(data)} real transitions ...")
    t0 = time.perf_counter()
    window = {"window": run.config.sysid_window} if run.config.sysid_window else {}
    res = sysid.fit(run.nominal_env, data, sysid.SysidConfig(**window))
    report.write_json(rdir.sysid, {
        "latency": res.latency, "system": res.system.to_json(), "table": res.table,
        "loss": res.loss, "sim_rollouts": res.sim_rollouts, "seconds": res.seconds})
    res.system.save(rdir.system)
    run.ev.mark(f"round{r}/sysid", param_rel_error=evaluation.param_errors(
        run.env_name, run.seed, res, run.perturbation, run.secret))
    run.prog.mark(f"round{r}/sysid", latency=res.latency, sysid_rollouts=res.sim_rollouts,
                  seconds=seconds_so_far(run.prog, r, sysid=time.perf_counter() - t0))
    return load_system(run, rdir)


def identified_system(rdir: RoundDir | Path, env_name: str):
    """The ``System`` (parameters + action latency) a round's sysid identified
    (``RoundDir.identified_system``: older runs' ``sysid.json`` too, so they resume)."""
    rdir = rdir if isinstance(rdir, RoundDir) else RoundDir(rdir)
    return rdir.identified_system(env_name)


def load_system(run: RunContext, rdir: RoundDir, **_) -> dict[str, Any]:
    # the identified twin, latency included, is what every later stage simulates
    from twinrl import envs

    system = identified_system(rdir, run.env_name)
    return {"system": system, "env": envs.make(run.env_name, system=system)}


def fit_hybrid(run: RunContext, r: int, rdir: RoundDir, env, system, data) -> dict[str, Any]:
    """The residual dynamics on top of the identified simulator -> ``hybrid/``."""
    from twinrl.sim2real import hybrid

    run.say("  fitting the hybrid residual dynamics ...")
    t0 = time.perf_counter()
    fit = hybrid.fit(env, data, latency=system.latency, rng=jax.random.key(run.seed + r))
    hybrid.save(rdir.hybrid, fit)
    run.prog.mark(f"round{r}/hybrid", hybrid_sim_rmse=fit.metrics["sim_val_rmse"],
                  hybrid_rmse=fit.metrics["hybrid_val_rmse"],
                  seconds=seconds_so_far(run.prog, r, hybrid=time.perf_counter() - t0))
    return load_hybrid(run, rdir)


def load_hybrid(run: RunContext, rdir: RoundDir, **_) -> dict[str, Any]:
    from twinrl.sim2real import hybrid

    return {"hybrid": hybrid.load(rdir.hybrid)}


def learn(run: RunContext, r: int, rdir: RoundDir, env, hybrid) -> dict[str, Any]:
    """The policy learned in the identified simulator -> ``train/`` (resumes from its last
    saved epoch); with ``algo="hds"`` a fraction of rollouts goes through the hybrid model."""
    from twinrl.learn.runner import continue_run

    config = run.config
    run.say(f"  learning with {config.algo} in the identified simulator ...")
    kwargs, overrides = {}, {}
    if config.algo == "hds" and config.model_fraction > 0 and hybrid is not None:
        from twinrl.sim2real.hybrid import make_dynamics

        kwargs["dynamics"] = make_dynamics(env, hybrid)
        overrides["model_fraction"] = config.model_fraction
    t0 = time.perf_counter()
    s = continue_run(run.env_name, config.algo, rdir.train, seed=run.seed + r,
                     epochs=config.epochs, overrides=overrides, progress=run.progress,
                     env=env, train_kwargs=kwargs, checkpoint_every=config.checkpoint_every)
    run.prog.mark(f"round{r}/learn", sim_return=s["final"].get("return"),
                  train_epochs=s["epochs"],
                  seconds=seconds_so_far(run.prog, r, learn=time.perf_counter() - t0))
    return {"policy_dir": rdir.train}


def _columns(path: Path, *keys: str) -> dict[str, list[float]]:
    """Columns ``keys`` of a trainer's ``metrics.csv`` (empty lists when it is absent)."""
    import csv

    rows = list(csv.DictReader(open(path))) if path.exists() else []
    return {k: [float(r[k]) for r in rows if r.get(k) not in (None, "")] for k in keys}


def compare_learn(run: RunContext, r: int, rdir: RoundDir, env) -> dict[str, Any]:
    """``LoopConfig.compare``'s learner on the same identified simulator -> ``compare/``, for
    the report only: both learners' wall clock and sim return, and when the deployed learner
    first reached the compared one's final return (None: never)."""
    from twinrl.learn.runner import continue_run

    algo, t0 = run.config.compare, time.perf_counter()
    run.say(f"  learning with {algo} too, for the report's comparison only ...")
    out = rdir.path / "compare"
    continue_run(run.env_name, algo, out, seed=run.seed + r, progress=run.progress, env=env,
                 checkpoint_every=run.config.checkpoint_every)
    mine = _columns(rdir.train_metrics, "wall_s", "return")
    theirs = _columns(out / "metrics.csv", "wall_s", "return")
    target = theirs["return"][-1] if theirs["return"] else None
    reach = next((w for w, v in zip(mine["wall_s"], mine["return"])
                  if target is not None and v >= target), None)
    run.prog.mark(f"round{r}/compare", compare={
        "algo": algo, "sim_return": target,
        "learn_s": theirs["wall_s"][-1] if theirs["wall_s"] else None,
        "deployed_algo": run.config.algo,
        "deployed_learn_s": mine["wall_s"][-1] if mine["wall_s"] else None,
        "deployed_s_to_compare_final": reach},
        seconds=seconds_so_far(run.prog, r, compare=time.perf_counter() - t0))
    return {}


def train_residual(run: RunContext, r: int, rdir: RoundDir, env, hybrid, data,
                   policy_dir) -> dict[str, Any]:
    """The residual policy trained through the hybrid model from recorded real states ->
    ``residual/``; kept only if it lowers the full-episode return neither through that model nor
    through the identified simulator (``residual.accept``), else saved as all zeros (exactly
    pi_sim). Gives ``residual``: the gate's verdict (``residual_gate``)."""
    from twinrl.learn.checkpoint import load_policy, save_policy
    from twinrl.sim2real import hybrid as hybrid_dynamics
    from twinrl.sim2real import residual

    if rdir.residual_metrics() is None:
        t0 = time.perf_counter()
        base, base_params, _ = load_policy(policy_dir)
        pol = residual.make_residual(base, base_params)
        run.say("  training the residual policy through the hybrid model ...")
        dynamics = hybrid_dynamics.make_dynamics(env, hybrid)
        res_params, metrics, verdict = residual.train_gated(env, dynamics, pol, data.obs,
                                                            seed=run.seed + r)
        said = "accepted" if verdict.accepted else "rejected (deploying pi_sim)"
        run.say(f"  residual {said}: full-episode return through the hybrid model "
                f"{verdict.before:.1f} -> {verdict.after:.1f}, the identified simulator "
                f"{verdict.reference_before:.1f} -> {verdict.reference_after:.1f}")
        save_policy(rdir.residual, pol.delta, res_params, kind="residual", metrics=metrics)
        run.prog.mark(f"round{r}/residual",
                      seconds=seconds_so_far(run.prog, r, residual=time.perf_counter() - t0))
    else:  # trained by a run made before this stage had its own mark
        run.prog.mark(f"round{r}/residual")
    return {"residual": residual_gate(rdir)}


def residual_gate(rdir: RoundDir) -> dict[str, Any]:
    """The residual's acceptance (``residual.accept``) as recorded in its checkpoint."""
    m = rdir.residual_metrics() or {}
    return {"residual_accepted": bool(m["accepted"]) if "accepted" in m else None,
            "residual_model_return": [m.get("model_return_before"), m.get("model_return_after")]}


def deployed_policy(config, env, hybrid, policy_dir, rdir: RoundDir):
    """The deployed ``obs -> action``: pi_sim (``policy_dir``), plus the residual the round's
    ``residual`` stage saved when the loop adapts (``config.residual`` with a hybrid model)."""
    from twinrl.learn.checkpoint import load_policy
    from twinrl.sim2real import residual

    base, base_params, _ = load_policy(policy_dir)
    if not config.residual or hybrid is None:
        f = jax.jit(base.apply)
        return lambda o: np.asarray(f(base_params, o))
    if rdir.residual_metrics() is None:
        raise LoopError(f"{rdir.path}: residual policy missing")
    pol = residual.make_residual(base, base_params)
    _, res_params, _ = load_policy(rdir.residual)
    f = jax.jit(pol.act)
    return lambda o: np.asarray(f(res_params, o))


def deploy(run: RunContext, r: int, rdir: RoundDir, env, hybrid, policy_dir,
           residual) -> None:
    """``K`` real episodes of the deployed policy (pi_sim + residual), recorded as they happen
    (an interrupted deployment resumes at its first unrecorded episode; episode ``e`` resets
    from the seed ``[seed, r, e]``); then, for evaluation only, pi_sim alone and the deployed
    policy on the same unrecorded episodes."""
    config, prog, K = run.config, run.prog, run.K
    gate = residual or {"residual_accepted": None, "residual_model_return": [None, None]}
    t0 = time.perf_counter()
    act = deployed_policy(config, env, hybrid, policy_dir, rdir)
    have = episodes_in(run.dir.dataset) - K * r  # K complete episodes per earlier round
    run.say(f"  deploying on the real twin ({K - have} episodes) ...")
    log = EpisodeLog(run, r, "deploy_returns_partial")
    for e in range(max(0, have), K):
        log.add(*record(run, [e], lambda e: lambda o, t: act(o),
                        lambda e: np.random.default_rng([run.seed, r, e])))
    rets = log.rows
    t_eval = time.perf_counter()
    # without an accepted residual the deployed policy is pi_sim (scored once)
    no_adapt = evaluation.real_return(run.env_name, run.seed, policy_dir, config.eval_episodes,
                                      run.perturbation, run.secret)
    adapted = (evaluation.policy_real_return(run.env_name, run.seed, act, config.eval_episodes,
                                             run.perturbation, run.secret)
               if gate["residual_accepted"] else no_adapt)
    run.ev.mark(f"round{r}/deploy", sim_policy_real_return=no_adapt, adapted_real_return=adapted)
    prog.mark(f"round{r}/deploy", real_return=float(np.mean(rets)) if rets else None,
              real_returns=rets, real_steps=real_steps(run),
              seconds=seconds_so_far(prog, r, deploy=t_eval - t0,
                                     evaluation=time.perf_counter() - t_eval), **gate)


COLLECT = Stage("collect", needs=(), gives=(), make=collect_excitation)
"""Round 0's stage."""

ROUND = (
    Stage("sysid", needs=("data",), gives=("system", "env"), make=fit_system, load=load_system),
    Stage("hybrid", needs=("env", "system", "data"), gives=("hybrid",), make=fit_hybrid,
          load=load_hybrid, enabled=lambda c: c.hybrid),
    Stage("learn", needs=("env", "hybrid"), gives=("policy_dir",), make=learn,
          load=lambda run, rdir, **_: {"policy_dir": rdir.train}, shared=True),
    Stage("compare", needs=("env",), gives=(), make=compare_learn,
          enabled=lambda c: c.compare is not None, shared=True),
    Stage("residual", needs=("env", "hybrid", "data", "policy_dir"), gives=("residual",),
          make=train_residual, load=lambda run, rdir, **_: {"residual": residual_gate(rdir)},
          enabled=lambda c: c.residual and c.hybrid),
    Stage("deploy", needs=("env", "hybrid", "policy_dir", "residual"), gives=(), make=deploy),
)
"""The stages of every round ``r >= 1``, in order; each takes the round's ``data`` (every intact
real transition so far) and what earlier stages gave."""


# ------------------------------------------------------------------------------ the family
def check_task(env_name: str, config: LoopConfig) -> None:
    """The cartpole family runs any task whose observation determines its state, with a
    learner of ``twinrl.learn.runner.ALGORITHMS``."""
    from twinrl import envs
    from twinrl.learn.runner import algorithm

    algorithm(config.algo)
    if config.compare is not None:
        algorithm(config.compare)
    if not envs.make(env_name).observes_state:  # refused before any work
        raise LoopError(f"{env_name}'s observation does not determine its state, and the loop "
                        f"identifies the simulator from recorded observations; identify it "
                        f"from full states instead: twinrl collect --env {env_name} "
                        f"--observation state, then twinrl sysid")


def open_twin(rd: RunDir, env_name: str, config: LoopConfig, seed: int, perturbation, say):
    """The real twin's server (it creates the secret the oracle's process then reads), the
    oracle in the background, and the dataset writer."""
    from twinrl import envs
    from twinrl.loop.oracle import OracleProcess
    from twinrl.real.dataset import DatasetWriter
    from twinrl.real.remote import TwinClient

    # Evaluation only, never read by the stages: the twin's secret, the oracle, the records.
    twin = TwinClient(env_name, seed=seed, secret=rd.secret, perturbation=perturbation)
    oracle_job = None
    if config.oracle and config.oracle_in_background:
        say("training the oracle (evaluation only) in the background")
        oracle_job = OracleProcess(env_name, seed, rd.oracle_policy, config, perturbation,
                                   secret=rd.secret)
    obs0, _ = twin.reset(seed=seed)
    writer = DatasetWriter(rd.dataset, env=env_name, obs_shape=obs0.shape,
                           action_shape=twin.action_space.shape, obs_dtype=np.float32,
                           action_dtype=np.float32)
    return envs.make(env_name), twin, writer, oracle_job


def summarise(run: RunContext, summary: dict) -> None:
    """The oracle's return (evaluation only) in every round, and the final fraction of it."""
    config = run.config
    oracle_return = None
    t_wait = time.perf_counter()
    if run.background is not None:
        if run.background.running():
            run.say("waiting for the oracle's training ...")
        oracle_return = run.background.result()
    elif config.oracle:
        oracle_return = evaluation.oracle_return(run.env_name, run.seed, run.dir.oracle_policy,
                                                 config, run.progress, run.perturbation,
                                                 run.secret)
    for rec in summary["rounds"]:
        rec["oracle_return"] = oracle_return
    summary["final"]["oracle_return"] = oracle_return
    if oracle_return:
        summary["final"]["fraction_of_oracle"] = ((summary["final"].get("real_return") or 0.0)
                                                  / oracle_return)
    summary["oracle_wait_s"] = time.perf_counter() - t_wait


RECORD_KEYS = {"real_steps": None, "real_return": None, "real_returns": None, "sim_return": None,
               "oracle_return": None, "param_rel_error": {}, "sim_policy_real_return": None,
               "adapted_real_return": None, "residual_accepted": None, "latency": None,
               "compare": None, "seconds": {}}
"""A round's row of the summary (from ``progress.json``; evaluation's merged in after)."""


def final_video(run: RunContext, values: dict, size: tuple[int, int] = (320, 240)) -> Path:
    """``final.mp4``: an episode of the final deployed policy on the real twin (left, its true
    camera) beside the identified simulator's episode from the same recorded start (right).
    Neither episode is recorded in the dataset."""
    import mujoco

    from twinrl.real.remote import TwinClient
    from twinrl.render.opengl import CameraRenderer

    rdir = run.dir.round(run.config.rounds)
    env = values["env"]
    act = deployed_policy(run.config, env, values["hybrid"], values["policy_dir"], rdir)
    # Both sides without shadows: in software OpenGL (no GPU) shadow mapping is ~90 % of a frame
    # (cartpole 320x240: 80 ms -> 6 ms), and the video is for looking at, not for fitting.
    twin = TwinClient(run.env_name, seed=run.seed, secret=run.secret,
                      perturbation=run.perturbation, width=size[0], height=size[1],
                      shadows=False)
    renderer = CameraRenderer(env.sim.mj_model, *size, shadows=False)
    frames = []
    try:
        obs, _ = twin.reset(seed=20_000 + run.seed)
        qpos, qvel = env.state_from_obs(jnp.asarray(obs))
        state = env.reset(jax.random.key(0))
        state = state.replace(pipeline_state=env.sim.init(qpos, qvel), obs=env.observe(qpos, qvel))
        # committed to the device like step's outputs, so step compiles once, not twice
        state = jax.device_put(state, jax.devices()[0])
        step = jax.jit(env.step)
        d = mujoco.MjData(env.sim.mj_model)
        done = False
        while not done:
            obs, _, term, trunc, _ = twin.step(act(obs))
            state = step(state, jnp.asarray(act(np.asarray(state.obs))))
            d.qpos[:] = np.asarray(state.pipeline_state.qpos)
            mujoco.mj_forward(env.sim.mj_model, d)
            real_img = twin.render_images(twin.camera, ("rgb",))["rgb"]
            sim_img = renderer.images(d, env.cameras[0], ("rgb",))["rgb"]
            frames.append(np.concatenate([real_img, sim_img], axis=1))
            done = term or trunc
    finally:
        renderer.close()
        twin.close()
    frames = report.label_frames(frames, ["real twin", "identified simulator"])
    return report.write_video(run.dir.video, frames, fps=1.0 / env.dt)


def write_outputs(run: RunContext, summary: dict) -> None:
    """The table, ``summary.json`` and the report (``report.md``, ``returns.png``)."""
    rounds = summary["rounds"]
    for rec in rounds:  # what the report draws: each round's learning curve and fit
        _add_round_details(run.dir.round(rec["round"]), rec)
    rows = [[r["round"], r["real_steps"], r["sim_return"], r["real_return"],
             r["sim_policy_real_return"], r.get("adapted_real_return"), r["oracle_return"],
             max(r["param_rel_error"].values()) if r["param_rel_error"] else None]
            for r in rounds]
    cols = ["round", "real steps", "sim return", "real return", "no-adapt real", "adapted real",
            "oracle", "max param err"]
    report.print_table(f"twinrl run {run.env_name} (seed {run.seed})", cols, rows)
    report.write_json(run.dir.summary, summary)
    report.loop_report(run.out, summary, _model_free_runs(run.env_name, run.seed))


def _add_round_details(rdir: RoundDir, rec: dict[str, Any]) -> None:
    """Round ``rec["round"]``'s learning curve in its identified simulator (``env_steps``,
    ``return`` of its ``train/metrics.csv``) and its sysid table (value, sd, status per
    parameter), for the report."""
    if rdir.train_metrics.exists():
        rec["learning_curve"] = _columns(rdir.train_metrics, "env_steps", "return")
    if rdir.sysid.exists():
        rec["identified"] = json.loads(rdir.sysid.read_text()).get("table", [])


def _model_free_runs(env_name: str, seed: int) -> list[dict]:
    """``bench/sim2real.py``'s model-free runs on this task and twin seed, when its results file
    exists (in the working directory's or the source tree's ``bench/results/``)."""
    for base in (Path.cwd(), Path(__file__).resolve().parents[2]):
        f = base / "bench" / "results" / "sim2real.json"
        if f.exists():
            try:
                runs = json.loads(f.read_text()).get("runs", [])
            except (OSError, json.JSONDecodeError):
                return []
            return [r for r in runs if r.get("task") == env_name and r.get("seed") == seed]
    return []


FAMILY = Family("cartpole", LoopConfig, COLLECT, ROUND, check_task, open_twin, RECORD_KEYS,
                summarise, final_video, write_outputs)
"""The cartpole family (every task whose observation determines its state: cartpole,
pendulum, ...): what it supplies to ``twinrl.loop.engine``."""


def run(env_name: str, out: str | Path, config: LoopConfig = LoopConfig(), *, seed: int = 0,
        resume: bool = False, progress: bool = True, perturbation=None) -> dict[str, Any]:
    """Run the loop on ``env_name``'s real twin (hidden perturbation drawn from ``seed``) into
    ``out``; returns the summary (also ``out/summary.json``).

    ``perturbation`` (a ``twinrl.real.perturbation.Perturbation``) replaces the drawn one: a
    benchmark's custom real twin, e.g. one with an effect the simulator cannot model. Like the drawn
    one it is applied by the twin and never shown to the learning stages."""
    return run_family(FAMILY, env_name, out, config, seed=seed, resume=resume,
                      progress=progress, perturbation=perturbation)
