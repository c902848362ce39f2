"""The manipulation loop's residual stage (``twinrl.loop.arm``, SAM-RL's residual policy) on short
peg insertion: a ``"pose"`` actor seen from the state (perfect perception, as the model renders
no images) is the base; the hybrid model is fitted to recorded transitions, the residual trained
through it and gated by ``residual.accept``; a rejected residual is saved as exactly zero and not
deployed, an accepted one is; where the hybrid model predicts held-out transitions no better
than the simulator, or the actor reads other image features, none is trained, and the stage says
so.

Apart from ``test_loop_arm.py`` (the kill-and-resume test) so that the two run on both workers.
"""

import functools
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.envs.system import System
from twinrl.learn.checkpoint import load_policy, save_policy
from twinrl.learn.networks import NetworkConfig, make_network
from twinrl.loop import LoopError, Progress
from twinrl.loop import arm as loop_arm
from twinrl.loop.rundir import RoundDir
from twinrl.sim2real import active, residual

T = 6
"""Episode length: the gate rolls out full episodes, so it is short."""


def _run(tmp, **config):
    said = []
    cfg = loop_arm.ArmLoopConfig(
        residual_policy={"steps": 3, "horizon": 3, "batch_size": 4}, **config)
    return SimpleNamespace(env_name="peg_insertion", seed=0, config=cfg, K=4,
                           prog=Progress(tmp / "progress.json"),
                           say=lambda *a, **k: said.append(" ".join(map(str, a))), said=said)


def _data(env, episodes=4, bias=0.0):
    """Transitions of random actions in the simulator, laid out as the loop's dataset; with
    ``bias``, the system executes each action plus ``bias`` (an offset the simulator lacks, which
    the hybrid model learns)."""
    rng = np.random.default_rng(0)
    step = _jitted_step(env)
    rows = {k: [] for k in ("obs", "action", "next_obs", "episode_id")}
    for e in range(episodes):
        s = env.reset(jax.random.PRNGKey(e))
        for _ in range(T):
            a = rng.uniform(-1, 1, env.action_size).astype(np.float32)
            s2 = step(s, jnp.clip(jnp.asarray(a) + bias, -1, 1))
            for k, v in zip(rows, (s.obs, a, s2.obs, e)):
                rows[k].append(np.asarray(v))
            s = s2
    return _Data(**{k: np.stack(v) for k, v in rows.items()})


@functools.lru_cache(maxsize=None)
def _jitted_step(env):
    return jax.jit(env.step)  # compiled once for both data sets


class _Data(SimpleNamespace):
    def __len__(self):
        return len(self.obs)

    def first_episodes(self, n):  # as the dataset's (episodes numbered from 0 here)
        keep = self.episode_id < n
        return _Data(**{k: v[keep] for k, v in vars(self).items()})


@pytest.fixture(scope="module")
def peg():
    env = envs.make("peg_insertion", episode_length=T)
    actor = make_network({"estimate": (env.observation_size,)}, env.action_size,
                         NetworkConfig(hidden=(16,), output="tanh"))
    return env, actor, actor.init(jax.random.PRNGKey(3))


def test_a_pose_actor_on_the_state_reads_the_perfect_estimate(peg):
    env, actor, params = peg
    base = active.pose_actor_on_state(env, actor)
    obs = np.stack([np.asarray(env.reset(jax.random.PRNGKey(k)).obs) for k in range(3)])
    one = [np.asarray(actor.apply(params, {"estimate": env.estimate_from_obs(o)})) for o in obs]
    np.testing.assert_allclose(np.asarray(base.apply(params, obs)), np.stack(one), atol=1e-6)
    # the residual starts at zero: the first deployment is the actor's
    pol = residual.make_residual(base, params)
    p0 = pol.delta.init(jax.random.PRNGKey(0))
    d, a = jax.vmap(lambda o: pol.correction(p0, o))(obs)
    assert np.all(np.asarray(d) == 0)
    np.testing.assert_allclose(np.asarray(a), np.stack(one), atol=1e-6)
    target = make_network({"target": (7,), "state": (14,)}, 3, NetworkConfig(hidden=(4,)))
    with pytest.raises(ValueError, match="needs a 'pose' actor"):
        active.pose_actor_on_state(env, target)


@pytest.fixture(scope="module")
def staged(peg, tmp_path_factory, request):
    """The stage run once with the gate's verdict forced to a rejection (its numbers real)."""
    env, actor, params = peg
    tmp = tmp_path_factory.mktemp("residual")
    rdir = RoundDir(tmp / "round1")
    save_policy(rdir.actor / "policy", actor, params, algo="imitation", env=env.name)
    verdicts = []
    real_accept = residual.accept

    def rejecting(*a, **k):
        verdicts.append(real_accept(*a, **k))
        return verdicts[-1]._replace(accepted=False)

    mp = pytest.MonkeyPatch()
    request.addfinalizer(mp.undo)
    mp.setattr(residual, "accept", rejecting)
    run = _run(tmp)
    given = loop_arm.stages.train_residual(run, 1, rdir, env, System.nominal("peg_insertion"),
                                           _data(env, bias=0.5))
    return run, rdir, verdicts, given


def test_the_residual_is_trained_through_the_hybrid_model_and_gated(staged):
    run, rdir, verdicts, given = staged
    rec = run.prog.record(1)
    assert (rdir.hybrid / "checkpoint.json").exists() and len(verdicts) == 1
    v = verdicts[0]
    assert rec["residual_accepted"] is False
    # the verdict is the stage's value, and a resumed run reads the same one back
    assert given == {"residual_accepted": False}
    assert loop_arm.stages.load_residual(run, rdir) == given
    # the model beat the twin on held-out transitions, so the residual was trained at all
    assert rec["hybrid_rmse"] < 0.95 * rec["hybrid_sim_rmse"], rec
    assert rec["residual_model_return"] == pytest.approx([v.before, v.after])
    assert rec["residual_sim_return"] == pytest.approx([v.reference_before, v.reference_after])
    assert np.all(np.isfinite([v.before, v.after, v.reference_before, v.reference_after]))
    assert any("rejected" in s for s in run.said)
    delta, params, meta = load_policy(rdir.residual)
    # rejected: saved as exactly zero, and the deployment has no residual
    assert all(np.all(np.asarray(x) == 0) for x in jax.tree.leaves(params))
    assert meta["metrics"]["accepted"] == 0.0 and np.isfinite(meta["metrics"]["objective"])


def test_only_an_accepted_residual_is_deployed(staged, peg):
    _, rdir, _, given = staged
    env = peg[0]
    config = loop_arm.ArmLoopConfig(camera="default")
    assert loop_arm.deployer(config, env, rdir, given["residual_accepted"]).residual is None
    dep = loop_arm.deployer(config, env, rdir, True)
    obs = np.asarray(env.reset(jax.random.PRNGKey(0)).obs)
    np.testing.assert_array_equal(dep.residual(obs, np.zeros(3, np.float32)), np.zeros(3))
    assert loop_arm.deployer(config, env, rdir, None).residual is None


def test_no_residual_where_the_model_is_no_better_than_the_twin(peg, tmp_path):
    """Transitions of the simulator itself: the hybrid model has nothing to add, so no residual
    is trained (nor deployed), and the stage says why."""
    env, actor, params = peg
    rdir = RoundDir(tmp_path / "round1")
    save_policy(rdir.actor / "policy", actor, params, algo="imitation", env=env.name)
    run = _run(tmp_path)
    given = loop_arm.stages.train_residual(run, 1, rdir, env, System.nominal("peg_insertion"),
                                           _data(env))
    rec = run.prog.record(1)
    assert rec["residual_accepted"] is None and rec["hybrid_rmse"] >= 0.95 * rec["hybrid_sim_rmse"]
    assert given == {"residual_accepted": None} == loop_arm.stages.load_residual(run, rdir)
    assert "better than the identified twin" in run.said[-1]
    assert not rdir.residual.exists()


def test_an_actor_of_other_features_gets_no_residual(peg, tmp_path):
    env = peg[0]
    target = make_network({"target": (7,), "state": (14,)}, 3, NetworkConfig(hidden=(4,)))
    rdir = RoundDir(tmp_path / "round1")
    save_policy(rdir.actor / "policy", target,
                target.init(jax.random.PRNGKey(0)), algo="imitation", env=env.name)
    run = _run(tmp_path)
    given = loop_arm.stages.train_residual(run, 1, rdir, env, System.nominal("peg_insertion"),
                                           None)
    assert run.prog.record(1)["residual_accepted"] is None and given["residual_accepted"] is None
    assert "no residual policy" in run.said[0] and not rdir.residual.exists()
    with pytest.raises(LoopError, match="residual_policy: ResidualConfig.steps"):
        loop_arm.make_config({"residual_policy.steps": 0})


def test_fits_of_real_data_run_it_under_the_controller_that_recorded_it(tmp_path):
    """Round 0 records with the nominal controller, later rounds with the calibrated one: sysid
    and the hybrid model fit round 0's episodes (``nominal_episodes``) under the nominal
    controller (the task ``with_system`` of the system without its ``controller``), the twin
    itself left calibrated."""
    from twinrl.envs.system import ControllerCalibration, System

    speed = (1.0, 0.9, 1.1, 1.2, 1.0, 1.0, 0.8)
    system = System.nominal("peg_insertion").replace(controller=ControllerCalibration(speed),
                                                      latency=1)
    env = envs.make("peg_insertion", system=system)  # the latency's wrapper around the task
    nominal = env.with_system(system.replace(controller=None))
    assert nominal.env.controller.joint_speed is None and nominal.latency == 1
    assert tuple(env.env.controller.joint_speed) == speed
    data = _Data(episode_id=np.repeat(np.arange(6), 3), obs=np.zeros((18, 2)))
    assert len(loop_arm.nominal_episodes(_run(tmp_path), data)) == 4 * 3  # K = 4
    assert len(loop_arm.nominal_episodes(_run(tmp_path, calibrate_controller=False), data)) == 18
