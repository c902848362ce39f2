"""Imitation (behaviour cloning + DAgger relabelled by trajopt) on a short pendulum swing-up."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.learn import imitation, plans, trajopt

T = 60


@pytest.fixture(scope="module")
def pendulum_demos():
    env = envs.make("pendulum_swingup", episode_length=T)
    keys = jax.random.split(jax.random.PRNGKey(3), 8)
    cfg = trajopt.TrajoptConfig(order=1, step_size=0.5, line_search_steps=6)

    def solve(k):
        s = env.reset(k)
        a, _ = trajopt.optimize(*trajopt.env_problem(env, s), jnp.zeros((T, 1)), cfg, 30)
        return a, env.unroll(s, a)[1].sum()

    actions, returns = jax.jit(jax.vmap(solve))(keys)
    return env, imitation.Demonstrations(np.asarray(keys), np.asarray(actions)), returns


def test_dagger_actor_beats_random_and_relabels_what_it_visits(pendulum_demos, monkeypatch):
    env, demos, demo_returns = pendulum_demos
    cfg = imitation.ImitationConfig(hidden=(64, 64), fit_steps=600, batch_size=128,
                                    dagger_rounds=1, dagger_episodes=4, relabel_every=10,
                                    relabel_iterations=5, eval_episodes=8, label_weight=3.0,
                                    visit_noise=0.2)
    fits, fitted = [], []  # each fit's (rows, weights); the parameters it returns

    def recording_fit(*a, **kw):
        fit = make_fit(*a, **kw)

        def recorded(p, o, obs, y, n, k, w):
            fits.append((n, np.asarray(w)))
            out = fit(p, o, obs, y, n, k, w)
            fitted.append(out[0])
            return out
        return recorded

    make_fit = imitation.make_minibatch_fit
    monkeypatch.setattr(imitation, "make_minibatch_fit", recording_fit)
    rounds, seen = [], []
    _, params, m = imitation.train(env, cfg, 0, demos=demos,
                                   progress_fn=lambda r, row: rounds.append(r),
                                   round_fn=lambda r, p: seen.append((r, p)))
    assert rounds == [0, 1]
    # round 0: the demonstrations' pairs; DAgger labels one in 10 of 4 episodes' states
    assert m["pairs"] == [8 * T, 8 * T + 4 * T // 10] and m["labels"] == [4 * T // 10, 0]
    # the second fit sees the labels, weighted label_weight against a demonstration's 1
    (n0, w0), (n1, w1) = fits
    assert (n0, n1) == (8 * T, 8 * T + 4 * T // 10)
    np.testing.assert_array_equal(w1[:n0], 1.0)
    np.testing.assert_array_equal(w1[n0:n1], 3.0)
    assert np.all(np.isfinite(m["loss"]))
    keys = jax.random.split(jax.random.PRNGKey(11), 8)
    rand = jax.vmap(lambda k: env.unroll(env.reset(k), jax.random.uniform(
        k, (T, 1), minval=-1, maxval=1))[1].sum())(keys)
    margin = 0.5 * (float(np.mean(demo_returns)) - float(np.mean(rand)))
    assert margin > 0
    # keep="best": the round with the highest (success, return) is returned and marked kept
    best = max(range(2), key=lambda r: (m["success"][r], m["return"][r], r))
    assert m["kept"] == [float(r == best) for r in range(2)]
    assert [r for r, _ in seen] == [0, 1]  # round_fn sees each round's fitted actor
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(fitted[best])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(jax.tree_util.tree_leaves(seen[1][1]), jax.tree_util.tree_leaves(fitted[1])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert max(m["return"]) >= float(np.mean(rand)) + margin, (m, float(np.mean(rand)))


def test_restarts_clone_from_other_keys_and_the_best_on_the_eval_starts_goes_on(
        pendulum_demos, monkeypatch):
    """``restarts``: each cloning from its own keys, scored on the same eval starts; the best
    (success, then return) is the actor returned, and restart 0 is the single cloning's."""
    env, demos, _ = pendulum_demos
    cfg = imitation.ImitationConfig(hidden=(32,), fit_steps=150, batch_size=64, dagger_rounds=0,
                                    eval_episodes=8, restarts=3)
    fitted = []

    def recording_fit(*a, **kw):
        fit = make_fit(*a, **kw)

        def recorded(*args):
            out = fit(*args)
            fitted.append(out[0])
            return out
        return recorded

    make_fit = imitation.make_minibatch_fit
    monkeypatch.setattr(imitation, "make_minibatch_fit", recording_fit)
    _, params, m = imitation.train(env, cfg, 0, demos=demos)
    assert len(fitted) == 3
    # each restart's actor on the eval starts train scores them on (its key's third split)
    k_eval = jax.random.split(jax.random.PRNGKey(0), 4)[2]
    observe, _ = imitation.make_observer(env, cfg)

    def score(p):
        ep = imitation.actor_episodes(env, observe, lambda o: net.apply(p, o), cfg, k_eval,
                                      cfg.eval_episodes)
        return float(np.mean(ep.success)), float(np.mean(ep.rewards.sum(1)))
    net = imitation.make_network(*_spec(env, cfg))
    scores = [score(p) for p in fitted]
    assert len(set(r for _, r in scores)) == 3  # three different clonings, not one thrice
    best = max(range(3), key=lambda i: (*scores[i], -i))
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(fitted[best])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert m["success"][0] == pytest.approx(scores[best][0])
    assert m["return"][0] == pytest.approx(scores[best][1], rel=1e-5)
    assert m["clone_success_worst"][0] == pytest.approx(min(s for s, _ in scores))
    _, one, _ = imitation.train(env, dataclasses.replace(cfg, restarts=1), 0, demos=demos)
    for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(fitted[0])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="restarts"):
        imitation.ImitationConfig(restarts=0)


def _spec(env, cfg):
    """The actor network ``train`` builds for ``cfg`` on ``env`` (its spec, action size, config)."""
    _, spec = imitation.make_observer(env, cfg)
    return spec, env.action_size, imitation.NetworkConfig(
        hidden=tuple(cfg.hidden), activation="elu", output="tanh", image_head=cfg.image_head,
        conv_strides=tuple(cfg.conv_strides))


def test_a_plan_is_judged_where_its_episode_ends(pendulum_demos):
    # DAgger's label filter (solved_labels) keeps a label when plans.solves says its plan,
    # from the visited state, solves the task after the steps left in that episode
    env, demos, _ = pendulum_demos

    class SwungOut(type(env)):
        def success(self, qpos, qvel):  # the pole more than 0.3 rad out
            return (jnp.abs(qpos[0]) > 0.3).astype(jnp.float32)

    env = SwungOut(env.config)
    starts = jax.vmap(env.reset)(jnp.asarray(demos.keys[:2]))
    plans_ = jnp.asarray(demos.actions[:2])
    rep = lambda x: jnp.repeat(x, T, axis=0)  # noqa: E731
    left = jnp.tile(jnp.arange(1, T + 1), 2)  # each start judged after 1 .. T of its steps
    solved = jax.jit(jax.vmap(lambda s, a, n: plans.solves(env, s, a, n)))(
        jax.tree_util.tree_map(rep, starts), rep(plans_), left)

    def swung_out(s, a):
        def body(s, a):
            s = env.step(s, a)
            return s, env.success(s.pipeline_state.qpos, s.pipeline_state.qvel)
        return jax.lax.scan(body, s, a)[1]

    expected = np.asarray(jax.vmap(swung_out)(starts, plans_)).reshape(-1)
    assert 0 < expected.sum() < expected.size  # the verdict changes along the plans
    np.testing.assert_array_equal(np.asarray(solved), expected)


def test_plans_from_given_start_keys_are_the_optimiser_s_from_those_starts(pendulum_demos):
    # plans.plan(keys=...): chosen starts (a real twin's, bench/real_failures.py), planned as the
    # fixture's own trajopt does from them
    env, demos, returns = pendulum_demos

    class Never(type(env)):
        def success(self, qpos, qvel):
            return jnp.zeros((), jnp.float32)

    res = plans.plan(Never(env.config), 99, iterations=30, batch=2, restarts=0,
                     keys=demos.keys[2:4])
    assert res["starts"] == 2 and res["optimisations_run"] == 2
    np.testing.assert_array_equal(res["keys"], demos.keys[2:4])
    np.testing.assert_allclose(res["plans"], demos.actions[2:4], atol=2e-3)
    final = jax.vmap(lambda k, a: env.unroll(env.reset(k), a)[1].sum())(
        jnp.asarray(demos.keys[2:4]), jnp.asarray(res["plans"]))
    np.testing.assert_allclose(np.asarray(final), np.asarray(returns[2:4]), rtol=1e-3)


def test_demonstration_files_are_checked(tmp_path):
    with pytest.raises(FileNotFoundError, match="no demonstration file"):
        imitation.load_demonstrations(tmp_path / "none.npz")
    np.savez(tmp_path / "bad.npz", actions=np.zeros((2, 3, 1)))
    with pytest.raises(ValueError, match=r"not a demonstration file: no \['keys'\]"):
        imitation.load_demonstrations(tmp_path / "bad.npz")
    np.savez(tmp_path / "failed.npz", keys=np.zeros((2, 2), np.uint32),
             actions=np.zeros((2, 3, 1)), success=np.zeros(2))
    with pytest.raises(ValueError, match="no successful demonstration"):
        imitation.load_demonstrations(tmp_path / "failed.npz")
    np.savez(tmp_path / "ok.npz", keys=np.arange(4, dtype=np.uint32).reshape(2, 2),
             actions=np.ones((2, 3, 1)), success=np.array([0.0, 1.0]))
    d = imitation.load_demonstrations(tmp_path / "ok.npz")
    assert d.keys.tolist() == [[2, 3]] and d.actions.shape == (1, 3, 1)
    with pytest.raises(ValueError, match="observation must be one of 'state', 'pixels'"):
        imitation.ImitationConfig(observation="rgb")
    with pytest.raises(ValueError, match="label_weight must be >= 0 or None, got -1"):
        imitation.ImitationConfig(label_weight=-1)
    with pytest.raises(ValueError, match="keep must be one of 'best', 'last'"):
        imitation.ImitationConfig(keep="first")


def test_a_dagger_label_counts_as_much_as_a_demonstrated_state():
    # a demonstrated state is rendered from `views` poses, a visited one from one: its label is
    # weighted by views unless told otherwise
    w = lambda **kw: imitation.label_weight(imitation.ImitationConfig(**kw))  # noqa: E731
    assert w() == 1.0 and w(views=8) == 1.0  # state observations: one pair per state
    assert w(observation="target", views=8) == 8.0 and w(observation="pixels") == 1.0
    assert w(observation="target", views=8, label_weight=2) == 2.0


def test_only_views_with_a_right_pose_estimate_are_cloned():
    # the fit's estimate against the true state's observation: within 5 mm in every entry, or
    # the pair is left out (an edge-on view's wrong heading would teach the wrong answer)
    from brax.envs.base import State

    truth = jnp.zeros((2, 3, 4))
    est = truth.at[0, 1, 2].set(0.004).at[1, 2, 0].set(-0.02)
    states = State(pipeline_state=None, obs=truth, reward=jnp.zeros((2, 3)), done=None)
    w = imitation.accurate({"estimate": est}, states)
    assert w.tolist() == [[1, 1, 1], [1, 1, 0]]
    assert imitation.accurate({"state": est}, states).tolist() == [[1, 1, 1]] * 2


def test_the_commanded_camera_pose_is_an_input_where_the_observation_is_in_its_frame():
    # pixels and the target cloud are seen from the camera: the actor reads the pose it
    # commanded; the fitted pose is in the world's frame, where the pose would only let the
    # actor learn each view's fit error (unless asked for)
    env = envs.make("peg_insertion")
    spec = lambda **kw: imitation.make_observer(env, imitation.ImitationConfig(**kw))[1]  # noqa
    assert "camera" in spec(observation="pixels") and "camera" in spec(observation="target")
    assert set(spec(observation="pose")) == {"estimate"}
    assert set(spec(observation="pose", camera_input=True)) == {"estimate", "camera"}
    assert "camera" not in spec(observation="pixels", camera_input=False)
    with pytest.raises(ValueError, match="camera_input must be one of None, True, False"):
        imitation.ImitationConfig(camera_input="yes")


def test_a_right_estimate_is_cloned_when_the_twin_holds_an_identified_grasp():
    # The pose estimate puts the peg where the twin believes it is (the identified grasp); the
    # observation the twin steps with is the robot's nominal report. A perfect estimate must
    # count as right: judged against the nominal report, the peg's tip is 12 mm off here and
    # every row of every demonstration was dropped (peg twin 1's actor learned nothing: 0 %).
    from brax.envs.base import State

    from twinrl.envs.system import System

    system = System.nominal("peg_insertion").replace(objects={"tool": {
        "pos_offset": np.array([0.004, -0.003, 0.003]),
        "rot_offset": np.array([-0.05, 0.06, 0.0])}})
    env = envs.make("peg_insertion", system=system)
    qpos, qvel = env.initial_state(jax.random.PRNGKey(0))
    report = env.observe(qpos, qvel)
    est = env.observe(qpos, qvel, nominal=False)
    assert float(jnp.max(jnp.abs(est - report))) > 0.005  # the grasp moves the tip
    states = State(pipeline_state=None, obs=report[None, None], reward=jnp.zeros((1, 1)),
                   done=None)
    assert imitation.accurate({"estimate": est[None, None]}, states, env).tolist() == [[1.0]]
    assert imitation.accurate({"estimate": est[None, None]}, states).tolist() == [[0.0]]
    off = est.at[17].add(0.01)  # the hole fitted 1 cm off
    assert imitation.accurate({"estimate": off[None, None]}, states, env).tolist() == [[0.0]]
