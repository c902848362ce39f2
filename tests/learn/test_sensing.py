"""The sensing-aware Q and the camera choice (``twinrl.learn.sensing``) on a short peg insertion:
the data's targets are the actor's returns-to-go, Q fits them, the ascent through the renderer
finds the poses a visibility score prefers, and ``twinrl sense`` writes its pose, plot and views.

Compiles dominate: one 6-step episode batch, one fit, one ascent per Q, at 16-32 pixels.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.cli import main
from twinrl import sense as sense_cmd
from twinrl.learn import sensing
from twinrl.learn.checkpoint import save_policy
from twinrl.learn.networks import Network, NetworkConfig, make_network

T, PIX = 6, 16


@pytest.fixture(scope="module")
def peg():
    env = envs.make("peg_insertion", episode_length=T)
    spec = {"state": (14,), "pixels/mount": (PIX, PIX, 5)}
    actor = make_network(spec, env.action_size, NetworkConfig(hidden=(16,), output="tanh"))
    return env, actor, actor.init(jax.random.PRNGKey(0))


@pytest.fixture(scope="module")
def trained(peg):
    env, actor, actor_params = peg
    cfg = sensing.SensingConfig(states=5, cameras=3, every=2, hidden=(32,), fit_steps=300,
                                batch_size=16, restarts=2, ascent_steps=3)
    rows = []
    q, q_params, m = sensing.train(env, cfg, 0, actor=(actor, actor_params),
                                   progress_fn=lambda r, row: rows.append(row))
    return cfg, q, q_params, m, rows


def test_targets_are_the_actors_return_to_go_with_the_camera_held(peg):
    env, actor, actor_params = peg
    cfg = sensing.SensingConfig(every=2)
    keys = jax.random.split(jax.random.PRNGKey(4), 2)
    coords = sensing.uniform_coords(env.mount, jax.random.PRNGKey(5), (2, 2))
    data = sensing.sensing_data(env, actor, actor_params, cfg, keys, coords)
    assert data.targets.shape == (2, 2, T // 2) and data.actions.shape == (2, 2, T // 2, 3)
    # an independent replay of one episode, step by step: its return-to-go per step left
    observe = jax.jit(sensing.observer(env, PIX))
    step, act = jax.jit(env.step), jax.jit(actor.apply)
    s, rewards = env.reset(keys[1]), []
    for t in range(T):
        a = act(actor_params, observe(s, coords[1, 0]))
        if t % 2 == 0:
            np.testing.assert_allclose(a, data.actions[1, 0, t // 2], atol=1e-5)
        s = step(s, a)
        rewards.append(float(s.reward))
    to_go = np.cumsum(rewards[::-1])[::-1] / np.arange(T, 0, -1)
    np.testing.assert_allclose(data.targets[1, 0], to_go[::2], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(data.returns[1, 0], sum(rewards), rtol=1e-4)
    # the camera changes what the (untrained, image-driven) actor does, so the returns differ
    assert float(jnp.abs(data.returns[:, 0] - data.returns[:, 1]).max()) > 0


def test_q_fits_the_targets_and_reports_held_out_ranking(trained):
    cfg, q, q_params, m, rows = trained
    assert len(rows) == 1 and m["pairs"] == [5 * 3 * (T // 2)]
    for k in ("loss", "val_loss", "rank_corr", "rank_corr_pooled", "target_q_choice",
              "target_mean_pose", "target_best_pose", "return", "choice_raises_q",
              "choice_q_gain"):
        assert np.isfinite(m[k][0]), (k, m)
    assert -1.0 <= m["rank_corr"][0] <= 1.0
    assert 0.0 <= m["choice_raises_q"][0] <= 1.0 and m["choice_q_gain"][0] >= 0.0
    assert m["target_mean_pose"][0] <= m["target_best_pose"][0] + 1e-9
    assert q.obs_spec["action"] == (3,) and q.out_size == 1


def test_ranking_figures_follow_the_order_q_gives_the_poses():
    # a stand-in Q that scores the action's first entry: with targets in the same order across a
    # state's poses the rank correlation is 1 and Q's choice is the best pose; reversed, -1 and
    # the worst
    q = Network(lambda k: {}, lambda p, o: o["action"][..., :1], 0, 1, NetworkConfig(),
                {"state": (1,), "action": (2,)})
    S, C = 3, 4
    acts = jnp.broadcast_to(jnp.arange(C, dtype=jnp.float32)[None, :, None, None], (S, C, 1, 2))
    obs = {"state": jnp.zeros((S, C, 1, 1))}
    order = jnp.broadcast_to(jnp.arange(C, dtype=jnp.float32) / C, (S, C))[..., None]
    for sign, corr in ((1.0, 1.0), (-1.0, -1.0)):
        targets = 0.5 + sign * (order - 0.4)
        data = sensing.SensingData(obs, acts, targets, jnp.zeros((S, C, 3)), 10 * targets[..., 0],
                                   jnp.zeros((S, C)))
        f = sensing.evaluate_ranking(q, {}, data)
        assert f["rank_corr"] == pytest.approx(corr)
        # pooled over the states: the same order within each, equal targets across them
        assert f["rank_corr_pooled"] == pytest.approx(corr)
        best, worst = float(targets.max()), float(targets.min())
        assert f["target_q_choice"] == pytest.approx(best if sign > 0 else worst)
        assert f["return"] == pytest.approx(10 * f["target_q_choice"])


def test_ascent_through_the_renderer_finds_where_the_target_shows():
    # A stand-in Q that scores the target's share of the soft image: the ascent must move the
    # camera to poses that show it, as a random search over many poses would.
    env = envs.make("peg_insertion", episode_length=T)
    size = 32
    spec = {"state": (14,), "pixels/mount": (size, size, 5)}
    actor = Network(lambda k: {}, lambda p, o: jnp.zeros(o["state"].shape[:-1] + (3,)),
                    0, 3, NetworkConfig(), spec)
    q = Network(lambda k: {}, lambda p, o: 100.0 * jnp.mean(
        o["pixels/mount"][..., 4], axis=(-2, -1))[..., None], 0, 1, NetworkConfig(),
        {**spec, "action": (3,)})
    state = env.reset(jax.random.PRNGKey(2))
    cfg = sensing.SensingConfig(restarts=4, ascent_steps=15, ascent_lr=0.3, tau=1.0)
    sel = jax.jit(lambda s, k: sensing.select_camera(env, q, {}, actor, {}, s, k, cfg))(
        state, jax.random.PRNGKey(3))
    assert np.all(np.isfinite(np.asarray(sel.trace)))
    gained = np.asarray(sel.trace[:, -1] - sel.trace[:, 0])
    assert np.mean(gained > 0) >= 0.75, sel.trace
    hard = jax.jit(jax.vmap(lambda c: q.apply({}, sensing.observer(env, size)(state, c))[0]))
    random = np.asarray(hard(sensing.uniform_coords(env.mount, jax.random.PRNGKey(9), (48,))))
    assert float(sel.value) >= np.quantile(random, 0.9), (float(sel.value), np.sort(random))
    assert float(sel.value) >= float(sel.default_value)


def test_sense_writes_the_choice_its_plot_and_views_and_refuses_other_checkpoints(
        peg, trained, tmp_path):
    env, actor, actor_params = peg
    cfg, q, q_params, _, _ = trained
    save_policy(tmp_path / "actor", actor, actor_params, algo="imitation", env="peg_insertion")
    cfg = cfg.__class__(**{**cfg.to_dict(), "actor": str(tmp_path / "actor")})
    save_policy(tmp_path / "q" / "policy", q, q_params, algo="sensing", env="peg_insertion",
                config=cfg)
    s = sense_cmd.sense("peg_insertion", tmp_path / "q", tmp_path / "out", seed=1, grid=(4, 3))
    import imageio.v3 as iio

    assert iio.imread(tmp_path / "out" / "sense.png").shape[1] > 1000
    assert iio.imread(tmp_path / "out" / "views.png").shape == (PIX, 2 * PIX + 4, 3)
    doc = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert doc["q_chosen"] >= doc["q_default"] and doc["steps_to_move"] >= 0
    lo, hi = env.mount.azimuth
    assert lo <= doc["chosen_pose"]["azimuth_rad"] <= hi
    # a checkpoint that is not a sensing Q, a task without a mount: one line, exit 2
    assert main(["sense", "--env", "peg_insertion", "--checkpoint", str(tmp_path / "actor"),
                 "--out", str(tmp_path / "x")]) == 2
    assert main(["train", "--algo", "sensing", "--env", "pendulum_swingup",
                 "--out", str(tmp_path / "y")]) == 2
    with pytest.raises(sensing.SensingError, match="trained on 'peg_insertion'"):
        sense_cmd.sense("needle_threading", tmp_path / "q", tmp_path / "z")
    with pytest.raises(ValueError, match="target must be"):
        sensing.SensingConfig(target="value")


# ---------------------------------------------------------------------- deployment on a real twin
@pytest.fixture(scope="module")
def twin():
    from twinrl.real.perturbation import Perturbation
    from twinrl.real.twin import RealTwin

    t = RealTwin("peg_insertion", perturbation=Perturbation.none(), width=PIX, height=PIX,
                 config={"episode_length": T})
    yield t
    t.close()


def test_real_image_observation_is_the_simulators_view_of_the_read_state(peg, twin):
    """What the image actor sees on the (unperturbed) real twin -- OpenGL RGB, depth and the
    segmentation's target mask -- is what the simulator renders of the state read off the twin's
    observation (``state_from_obs``), at an arbitrary mount pose."""
    from twinrl.sim2real import active

    env, _, _ = peg
    obs, _ = twin.reset(seed=2)
    coords = np.array([0.8, -0.5, 0.3])
    twin.move_camera(coords)
    real = active.real_image_observation(twin, env, obs, PIX)
    sim = jax.jit(lambda o, c: env.image_observation(active.sim_state(env, o), c, size=PIX))(
        jnp.asarray(obs), jnp.asarray(coords, jnp.float32))
    np.testing.assert_allclose(real["state"], np.asarray(sim["state"]), atol=1e-6)
    r, s = real["pixels/mount"], np.asarray(sim["pixels/mount"])
    assert np.mean(np.abs(r[..., 3] - s[..., 3])) < 1e-3  # depth, m
    assert np.mean(r[..., 4] == s[..., 4]) >= 0.97 and r[..., 4].sum() >= 3  # the target's mask
    assert np.mean(np.abs(r[..., :3] - s[..., :3])) < 0.1  # RGB: shading differs (measured 0.06)
    # the target cloud (mean, spread, log count) from the commanded pose: the same numbers
    np.testing.assert_allclose(real["target"][:6], np.asarray(sim["target"])[:6], atol=2e-3)
    assert abs(real["target"][6] - float(sim["target"][6])) < 0.15
    with pytest.raises(ValueError, match="renders 16x16; the actor needs 32x32"):
        active.real_image_observation(twin, env, obs, 32)


def test_deployment_moves_the_camera_to_qs_choice_and_counts_the_moves(peg, trained, twin):
    from twinrl.learn.camera_choice import q_value
    from twinrl.sim2real import active

    env, actor, actor_params = peg
    cfg, q, q_params, _, _ = trained
    dep = active.Deployer(env, actor, actor_params, q=q, q_params=q_params, sensing=cfg)
    twin.move_camera(env.mount.default)
    res = dep.run(twin, active.DeployConfig(camera="selected", episodes=2, reselect_every=4),
                  seed=5)
    assert res["steps"] == [T, T] and res["choices"] == [2, 2]
    assert len(res["success"]) == 2 and set(res["success"]) <= {0.0, 1.0}
    first = np.asarray(res["coords"][0])
    # the first choice is Q's best by its hard image, never below the default pose's Q
    obs, _ = twin.reset(seed=5)
    state = active.sim_state(env, jnp.asarray(obs))
    hard = lambda c: env.image_observation(state, jnp.asarray(c, jnp.float32), size=PIX)  # noqa
    value = lambda c: float(q_value(q, q_params, hard(c), actor.apply(actor_params, hard(c))))
    assert value(first) >= value(env.mount.default) - 1e-5
    assert res["camera_steps"][0] >= env.mount.steps_to_move(env.mount.default, first)
    # the fixed camera never moves; a random one moves as far as the mount says
    twin.move_camera(env.mount.default)
    fixed = dep.run(twin, active.DeployConfig(camera="default", episodes=2))
    assert fixed["camera_steps"] == [0, 0] and fixed["choices"] == [1, 1]
    rand = dep.run(twin, active.DeployConfig(camera="random", episodes=2), seed=1)
    a, b = (np.asarray(c) for c in rand["coords"])
    assert rand["camera_steps"][1] == env.mount.steps_to_move(a, b) and not np.allclose(a, b)
    with pytest.raises(ValueError, match="needs the sensing-aware Q"):
        active.Deployer(env, actor, actor_params).run(twin, active.DeployConfig(episodes=1))
    with pytest.raises(ValueError, match="deploys a state policy"):
        dep.run(twin, active.DeployConfig(camera="oracle", episodes=1))
    with pytest.raises(ValueError, match="camera must be one of"):
        active.DeployConfig(camera="best")


def test_oracle_deployment_of_a_state_expert_succeeds_on_the_real_twin():
    """``camera="oracle"``: a state policy on the twin's observation; the scripted peg expert
    (in JAX) inserts the peg on the unperturbed twin, and the deployment says so."""
    from twinrl.real.perturbation import Perturbation
    from twinrl.real.twin import RealTwin
    from twinrl.sim2real import active

    env = envs.make("peg_insertion")
    step = env.controller.max_step

    def expert(_, obs):
        d = obs[20:23]
        lateral = jnp.hypot(d[0], d[1]) < 0.004
        a = jnp.concatenate([-d[:2] / step, jnp.where(lateral, -1.0, (0.08 - d[2]) / step)[None]])
        return jnp.clip(a, -1.0, 1.0)

    policy = Network(init=lambda k: {}, apply=expert, in_size=env.observation_size, out_size=3,
                     config=NetworkConfig(), obs_spec=env.observation_size)
    real = RealTwin("peg_insertion", perturbation=Perturbation.none())
    res = active.deploy(env, real, policy, {}, active.DeployConfig(camera="oracle", episodes=2))
    real.close()
    assert res["success"] == [1.0, 1.0] and res["camera_steps"] == [0, 0]
    assert res["steps"] == [env.episode_length] * 2 and res["choices"] == [0, 0]


def test_q_of_a_pose_actor_also_sees_the_pose_and_what_the_fit_stands_on():
    # the pose actor's estimate is the same from every pose it is right from: Q needs the
    # commanded pose and the fit's support to tell them apart; the camera choice computes both
    from twinrl.learn.camera_choice import observed_keys

    actor = make_network({"estimate": (24,)}, 3, NetworkConfig(hidden=(8,)))
    q = sensing.make_q(actor, 3, sensing.SensingConfig(hidden=(8,)))
    assert set(q.obs_spec) == {"estimate", "camera", "support", "action"}
    assert observed_keys(actor, q) == ("camera", "estimate", "support")
    pixels = make_network({"state": (14,), "pixels/mount": (PIX, PIX, 5)}, 3,
                          NetworkConfig(hidden=(8,)))
    assert sensing.q_inputs(pixels) == dict(pixels.obs_spec)  # an image Q reads the image
