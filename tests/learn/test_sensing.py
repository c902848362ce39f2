"""The sensing-aware Q and the camera choice (``twinrl.learn.sensing``) on a short peg insertion:
the data's targets are the actor's returns-to-go, Q fits them, the ascent through the renderer
finds the poses a visibility score prefers, ``twinrl sense`` writes its pose, plot and views,
and ``look`` (the loop's figures) gives Q and the saliency at poses already chosen.

Compiles dominate: one 6-step episode batch, one fit, one ascent per Q, at 16-32 pixels.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import spearmanr

from twinrl import envs
from twinrl.cli import main
from twinrl import sense as sense_cmd
from twinrl.learn import sensing
from twinrl.learn.camera_choice import checked_steps, view_outcomes
from twinrl.learn.checkpoint import save_policy
from twinrl.learn.networks import Network, NetworkConfig, make_network

from tests.learn._peg import PIX, T


CFG = sensing.SensingConfig(states=5, cameras=3, every=2, hidden=(32,), fit_steps=300,
                            batch_size=16, restarts=2, ascent_steps=3)
"""The ``trained`` Q's config: 5 + 1 held-out start states, 3 poses, 3 examples an episode."""


@pytest.fixture(scope="module")
def trained(peg):
    env, actor, actor_params = peg
    rows = []
    q, q_params, m = sensing.train(env, CFG, 0, actor=(actor, actor_params),
                                   progress_fn=lambda r, row: rows.append(row))
    return CFG, q, q_params, m, rows


@pytest.fixture(scope="module")
def peg_data(peg):
    """The data ``trained`` fits and evaluates on, drawn as ``sensing.train`` draws it for seed 0
    (start states from the first of its four keys, poses from the second): the last start state
    is held out. The same compiled episodes, which the persistent cache then serves ``train``."""
    env, actor, actor_params = peg
    k_states, k_cams, _, _ = jax.random.split(jax.random.PRNGKey(0), 4)
    keys = jax.random.split(k_states, CFG.states + 1)
    coords = sensing.uniform_coords(env.mount, k_cams, (CFG.states + 1, CFG.cameras))
    return keys, coords, sensing.sensing_data(env, actor, actor_params, CFG, keys, coords)


def _part(data: sensing.SensingData, rows: slice) -> sensing.SensingData:
    return sensing.SensingData(*(jax.tree_util.tree_map(lambda x: x[rows], f) for f in data))


def test_targets_are_the_actors_return_to_go_with_the_camera_held(peg, peg_data):
    env, actor, actor_params = peg
    keys, coords, data = peg_data
    assert data.targets.shape == (6, 3, T // 2) and data.actions.shape == (6, 3, T // 2, 3)
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
    # the simulator's deployment of the same actor from the same starts and poses
    # (bench/sensing.py --where sim) has those episodes' returns and successes
    ret, ok = jax.jit(lambda k, c: view_outcomes(env, actor, actor_params, k, c))(
        keys, coords[:, 1])
    np.testing.assert_allclose(ret, data.returns[:, 1], rtol=1e-4)
    np.testing.assert_array_equal(ok, data.success[:, 1])


def test_q_fits_the_targets_and_reports_held_out_ranking(trained, peg_data):
    cfg, q, q_params, m, rows = trained
    _, _, data = peg_data
    assert len(rows) == 1 and m["pairs"] == [5 * 3 * (T // 2)]
    assert q.obs_spec["action"] == (3,) and q.out_size == 1
    for k in ("loss", "val_loss", "rank_corr", "rank_corr_pooled", "target_q_choice",
              "target_mean_pose", "target_best_pose", "return", "choice_raises_q",
              "choice_q_gain"):
        assert np.isfinite(m[k][0]), (k, m)
    # Q fits its training targets: it explains >= 90 % of their variance (an unfitted Q, or one
    # fitted to shuffled targets, explains none), and the fit's reported loss says so too
    fit_part, held_part = _part(data, slice(0, 5)), _part(data, slice(5, 6))
    targets = np.asarray(fit_part.targets)
    pred = sensing.q_predictions(q, q_params, fit_part)
    explained = 1.0 - np.mean((pred - targets) ** 2) / np.var(targets)
    assert explained >= 0.9, (explained, pred, targets)
    assert m["loss"][0] <= 0.1 * np.var(targets), (m["loss"], np.var(targets))
    # the held-out figures are Q's on the held-out start state's episodes (whether Q ranks
    # the poses of states it has not seen is the known-answer test below: one held-out state
    # of an untrained actor says nothing about that)
    held_pred, held = sensing.q_predictions(q, q_params, held_part), np.asarray(held_part.targets)
    assert m["val_loss"][0] == pytest.approx(np.mean((held_pred - held) ** 2), rel=1e-5)
    assert m["rank_corr"][0] == pytest.approx(
        spearmanr(held_pred[0, :, 0], held[0, :, 0]).statistic, abs=1e-6)
    assert m["target_q_choice"][0] == pytest.approx(held[0, held_pred[0, :, 0].argmax(), 0])


def _known_q_data(key, states: int, poses: int) -> tuple[sensing.SensingData, np.ndarray]:
    """A stand-in for the actor's episodes whose target is a known function of the start state
    ``x`` (2,) and the pose ``u`` in [-1, 1], which the observation shows (as an image shows the
    scene from the pose): ``0.5 + 0.25 x_0 - 0.4 (u - x_1 / 2)^2``, best where ``u = x_1 / 2``.
    Returns the data (one example an episode) and each state's best pose of those drawn."""
    kx, ku = jax.random.split(key)
    x = jax.random.uniform(kx, (states, 1, 1, 2), minval=-1.0, maxval=1.0)
    u = jax.random.uniform(ku, (states, poses, 1, 1), minval=-1.0, maxval=1.0)
    obs = {"state": jnp.concatenate([jnp.broadcast_to(x, (states, poses, 1, 2)), u], -1)}
    actions = jnp.concatenate([jnp.tanh(x[..., :1] + u), 0.5 * u], -1)
    targets = 0.5 + 0.25 * x[..., 0] - 0.4 * (u[..., 0] - 0.5 * x[..., 1]) ** 2
    best = np.argmin(np.abs(np.asarray(u - 0.5 * x[..., 1:])[:, :, 0, 0]), axis=1)
    data = sensing.SensingData(obs, actions, targets, jnp.zeros((states, poses, 3)),
                               10.0 * targets[..., 0], jnp.zeros((states, poses)))
    return data, best


def test_fitted_q_ranks_the_poses_of_held_out_states_by_a_known_q():
    # ``fit_q`` (``train``'s fit) on 64 start states x 4 poses of a stand-in whose best pose is
    # known, scored by ``evaluate_ranking`` on 16 states it did not see
    actor = make_network({"state": (3,)}, 2, NetworkConfig(hidden=(8,)))
    cfg = sensing.SensingConfig(hidden=(32,), fit_steps=1000, batch_size=32, learning_rate=3e-3,
                                rgb_jitter=0.0)
    q = sensing.make_q(actor, 2, cfg)
    fit_data, _ = _known_q_data(jax.random.PRNGKey(0), 64, 4)
    held, best = _known_q_data(jax.random.PRNGKey(1), 16, 4)
    q_params, _ = sensing.fit_q(q, q.init(jax.random.PRNGKey(2)), fit_data, cfg,
                                jax.random.PRNGKey(3))
    f = sensing.evaluate_ranking(q, q_params, held)
    # held out, Q explains >= 85 % of the targets' variance (an unfitted Q: none) ...
    explained = 1.0 - f["val_loss"] / float(np.var(np.asarray(held.targets)))
    # ... ranks each state's poses as the known Q does (a random Q: 0 on average) ...
    assert explained >= 0.85 and f["rank_corr"] >= 0.8, (explained, f)
    # ... and picks the best pose: on >= 3 in 4 states (a random choice: 1 in 4), and on
    # average within a tenth of the way from the best pose's target to the poses' mean
    chose = sensing.q_predictions(q, q_params, held)[:, :, 0].argmax(axis=1)
    assert np.mean(chose == best) >= 0.75, (chose, best)
    gap = f["target_best_pose"] - f["target_mean_pose"]
    assert f["target_best_pose"] - f["target_q_choice"] <= 0.1 * gap, f


def test_an_ensemble_q_fits_every_member_on_its_own_and_ranks_by_their_mean():
    # the stand-in above with a 3-member Q: each member, fitted on its own error, explains the
    # held-out targets; the members start and end apart; Q is their mean
    actor = make_network({"state": (3,)}, 2, NetworkConfig(hidden=(8,)))
    cfg = sensing.SensingConfig(hidden=(32,), fit_steps=1000, batch_size=32, learning_rate=3e-3,
                                rgb_jitter=0.0, ensemble=3)
    q = sensing.make_q(actor, 2, cfg)
    fit_data, _ = _known_q_data(jax.random.PRNGKey(0), 64, 4)
    held, _ = _known_q_data(jax.random.PRNGKey(1), 16, 4)
    q_params, _ = sensing.fit_q(q, q.init(jax.random.PRNGKey(2)), fit_data, cfg,
                                jax.random.PRNGKey(3))
    obs = {**held.obs, "action": held.actions}
    each = np.asarray(q.members(q_params, obs))[..., 0]  # (S, C, K, members)
    target = np.asarray(held.targets)
    explained = 1.0 - np.mean((each - target[..., None]) ** 2, axis=(0, 1, 2)) / np.var(target)
    assert each.shape[-1] == 3 and np.all(explained >= 0.85), explained
    assert np.mean(np.std(each, axis=-1)) > 1e-4
    np.testing.assert_allclose(np.asarray(q.apply(q_params, obs))[..., 0], each.mean(-1),
                               rtol=1e-5, atol=1e-6)
    assert sensing.evaluate_ranking(q, q_params, held)["rank_corr"] >= 0.8


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
    cfg = sensing.SensingConfig(restarts=4, ascent_steps=15, ascent_lr=0.3, tau=1.0,
                                smooth_samples=0)
    sel = jax.jit(lambda s, k: sensing.select_camera(env, q, {}, actor, {}, s, k, cfg))(
        state, jax.random.PRNGKey(3))
    assert np.all(np.isfinite(np.asarray(sel.trace)))
    gained = np.asarray(sel.trace[:, -1] - sel.trace[:, 0])
    assert np.mean(gained > 0) >= 0.75, sel.trace
    hard = jax.jit(jax.vmap(lambda c: q.apply({}, sensing.observer(env, size)(state, c))[0]))
    random = np.asarray(hard(sensing.uniform_coords(env.mount, jax.random.PRNGKey(9), (48,))))
    assert float(sel.value) >= np.quantile(random, 0.9), (float(sel.value), np.sort(random))
    # the choice is the best hard-image score among the checked iterates of every ascent
    checked, values = np.asarray(sel.checked), np.asarray(sel.checked_values)
    np.testing.assert_array_equal(checked_steps(15, 3), [0, 3, 6, 9, 12, 15])
    np.testing.assert_array_equal(checked_steps(20, 3), [0, 3, 6, 9, 12, 15, 18, 20])
    assert checked.shape == (6, 4, 3) and values.shape == (6, 4)
    np.testing.assert_array_equal(checked[0], np.asarray(sel.starts))
    np.testing.assert_array_equal(checked[-1], np.asarray(sel.ends))
    assert float(values[0, 0]) == float(sel.default_value)
    assert float(sel.value) == values.max()
    np.testing.assert_array_equal(np.asarray(sel.coords), checked.reshape(-1, 3)[values.argmax()])
    assert int(sel.chosen) == values.argmax()


def test_the_choice_prefers_a_broad_rise_of_q_to_a_spike_the_hand_eye_error_would_miss():
    # A stand-in Q over the pose alone (the observation's "camera": the pose as fractions of the
    # mount's ranges): a spike of 1.0 two thousandths wide at the default pose, a broad hill of
    # 0.8 elsewhere. Scored at the pose alone the choice is the spike; scored over a
    # neighbourhood (``smooth_samples``) it is on the hill.
    env = envs.make("peg_insertion", episode_length=T)
    spec = {"camera": (3,)}
    actor = Network(lambda k: {}, lambda p, o: jnp.zeros(o["camera"].shape[:-1] + (3,)),
                    0, 3, NetworkConfig(), spec)
    u_default = jax.nn.sigmoid(jnp.asarray(env.mount.default, jnp.float32))
    u_hill = jnp.where(u_default > 0.5, 0.2, 0.8)

    def q_fn(p, o):
        u = o["camera"]
        spike = jnp.exp(-jnp.sum((u - u_default) ** 2, -1) / (2 * 0.002 ** 2))
        hill = 0.8 * jnp.exp(-jnp.sum((u - u_hill) ** 2, -1) / (2 * 0.3 ** 2))
        return jnp.maximum(spike, hill)[..., None]

    q = Network(lambda k: {}, q_fn, 0, 1, NetworkConfig(), {**spec, "action": (3,)})
    state = env.reset(jax.random.PRNGKey(2))
    for samples in (0, 8):
        cfg = sensing.SensingConfig(restarts=4, ascent_steps=6, smooth_samples=samples)
        sel = jax.jit(lambda s, k: sensing.select_camera(env, q, {}, actor, {}, s, k, cfg))(
            state, jax.random.PRNGKey(3))
        u = np.asarray(jax.nn.sigmoid(sel.coords))
        away = float(np.abs(u - np.asarray(u_default)).max())
        if samples == 0:
            assert away < 1e-6 and float(sel.value) == pytest.approx(1.0)
        else:  # off the spike, toward the hill, and scored by the neighbourhood's mean Q
            assert away > 0.05, u
            assert float(sel.value) > float(sel.default_value) + 0.1
            assert float(sel.value) < float(np.asarray(sel.checked_values).max())
        np.testing.assert_array_equal(np.asarray(sel.checked).reshape(-1, 3)[int(sel.chosen)],
                                      np.asarray(sel.coords))


def test_sense_writes_the_choice_its_plot_and_views_and_refuses_other_checkpoints(
        peg, trained, tmp_path):
    env, actor, actor_params = peg
    cfg, q, q_params, _, _ = trained
    save_policy(tmp_path / "actor", actor, actor_params, algo="imitation", env="peg_insertion")
    cfg = cfg.__class__(**{**cfg.to_dict(), "actor": str(tmp_path / "actor")})
    save_policy(tmp_path / "q" / "policy", q, q_params, algo="sensing", env="peg_insertion",
                config=cfg)
    sense_cmd.sense("peg_insertion", tmp_path / "q", tmp_path / "out", seed=1, grid=(4, 3))
    import imageio.v3 as iio

    assert iio.imread(tmp_path / "out" / "sense.png").shape[1] > 1000
    assert iio.imread(tmp_path / "out" / "views.png").shape == (PIX, 2 * PIX + 4, 3)
    doc = json.loads((tmp_path / "out" / "summary.json").read_text())
    # the actor's saliency on both views, drawn beside them and on its own
    assert iio.imread(tmp_path / "out" / "saliency.png").shape[1] > 1000
    assert set(doc["saliency_target_share"]) == {"default", "chosen"}
    # the summary's poses are its coordinates' (the default's: the mount's), the move between
    # them takes the mount's speed limit, and the views are the two poses' images
    mount, chosen = env.mount, np.asarray(doc["chosen_coords"], np.float32)
    for key, coords in (("chosen_pose", chosen), ("default_pose", mount.default)):
        np.testing.assert_allclose(list(doc[key].values()),
                                   mount.spherical(jnp.asarray(coords, jnp.float32)), rtol=1e-5)
    moved = np.abs(np.subtract(list(doc["chosen_pose"].values()),
                               list(doc["default_pose"].values()))).max()
    steps = doc["steps_to_move"]
    assert (steps - 1) * mount.max_speed < moved <= steps * mount.max_speed + 1e-6, (moved, doc)
    views = iio.imread(tmp_path / "out" / "views.png").astype(float)
    observe = jax.jit(sensing.observer(env, PIX, keys=("pixels/mount",)))
    state = env.reset(jax.random.PRNGKey(1))
    for half, coords in ((views[:, :PIX], mount.default), (views[:, PIX + 4:], chosen)):
        rgb = np.asarray(observe(state, jnp.asarray(coords, jnp.float32))["pixels/mount"])
        np.testing.assert_allclose(half / 255, rgb[..., :3], atol=1 / 255 + 1e-6)
    # a checkpoint that is not a sensing Q, a task without a mount: one line, exit 2
    assert main(["sense", "--env", "peg_insertion", "--checkpoint", str(tmp_path / "actor"),
                 "--out", str(tmp_path / "x")]) == 2
    assert main(["train", "--algo", "sensing", "--env", "pendulum_swingup",
                 "--out", str(tmp_path / "y")]) == 2
    with pytest.raises(sensing.SensingError, match="trained on 'peg_insertion'"):
        sense_cmd.sense("needle_threading", tmp_path / "q", tmp_path / "z")
    with pytest.raises(ValueError, match="target must be"):
        sensing.SensingConfig(target="value")
    with pytest.raises(ValueError, match="check_every must be an integer >= 1, got 0"):
        sensing.SensingConfig(check_every=0)


def test_look_gives_q_and_the_saliency_at_given_poses_of_a_measured_state(peg, trained):
    # the loop's figures: no ascent, the pose already chosen; Q and the saliency at each pose
    # (and over the grid) are those of the hard image of the state read off the observation
    from twinrl.learn.camera_choice import observed_keys, q_value, workspace_grid
    from twinrl.sim2real.active import sim_state

    env, actor, actor_params = peg
    _, q, q_params, _, _ = trained
    obs = np.asarray(env.reset(jax.random.PRNGKey(3)).obs, np.float32)
    chosen = np.asarray(sensing.uniform_coords(env.mount, jax.random.PRNGKey(4)), np.float64)
    poses = {"default": np.asarray(env.mount.default, np.float64), "chosen": chosen}
    seen = sense_cmd.look(env, actor, actor_params, obs, poses, q=q, q_params=q_params,
                          grid=(4, 3), distance_coord=chosen[2])
    az, el, vals = seen["landscape"]
    assert az.shape == (4,) and el.shape == (3,) and vals.shape == (3, 4)
    grid = workspace_grid(env.mount, chosen[2], (4, 3))[2]
    at = np.concatenate([np.stack(list(poses.values())), grid]).astype(np.float32)
    state = sim_state(env, jnp.asarray(obs))
    keys = observed_keys(actor, q)

    @jax.jit
    def reference(c):  # Q on the hard image, and ``saliency`` on the actor's image
        o = sensing.observer(env, PIX, keys=keys + ("pixels/mount",))(state, c)
        return (q_value(q, q_params, o, actor.apply(actor_params, o)), o["pixels/mount"],
                sense_cmd.saliency(env, actor, actor_params, state.obs[:14], c,
                                   o["pixels/mount"]))

    refs = [reference(jnp.asarray(c)) for c in at]
    np.testing.assert_allclose(vals.reshape(-1), [float(r[0]) for r in refs[2:]], rtol=1e-4,
                               atol=1e-5)
    for (name, view), (value, px, sal) in zip(seen["views"].items(), refs):
        assert view["q"] == pytest.approx(float(value), rel=1e-4, abs=1e-5)
        np.testing.assert_allclose(view["rgb"], np.asarray(px)[..., :3], atol=1e-5)
        np.testing.assert_array_equal(view["mask"], np.asarray(px)[..., 4] > 0.5)
        np.testing.assert_allclose(view["saliency"], sal, rtol=1e-4, atol=1e-6)
        assert np.asarray(sal).max() > 0
    # no Q: the views and their saliency alone
    bare = sense_cmd.look(env, actor, actor_params, obs, {"default": poses["default"]})
    assert set(bare) == {"views"} and np.isnan(bare["views"]["default"]["q"])
    np.testing.assert_allclose(bare["views"]["default"]["saliency"], refs[0][2], rtol=1e-4,
                               atol=1e-6)


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
