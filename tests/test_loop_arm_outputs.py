"""The SAM-RL loop's outputs: the image actor's saliency (``twinrl.sense.saliency``) is
``|d action / d pixel|`` (zero on the pixels an actor does not read), ``final.mp4``'s frames put
the real scene beside the view the actor sees, and ``report.md`` says what the summary recorded
(the verdict and each camera mode's success with its Wilson interval)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs, report
from twinrl.learn.networks import Network, NetworkConfig
from twinrl.loop.arm import film_frames
from twinrl.loop.arm_report import write_report
from twinrl.sense import saliency

N = 32


@pytest.fixture(scope="module")
def peg():
    return envs.make("peg_insertion")


def _actor(read):
    """A hand-made image actor: two actions from the pixels ``read`` picks out."""
    spec = {"pixels/mount": (N, N, 5), "state": (14,)}
    return Network(lambda k: {}, lambda p, o: read(o["pixels/mount"]) + 0.0 * o["state"][:2],
                   0, 2, NetworkConfig(), spec)


def test_saliency_is_nonzero_exactly_on_the_pixels_the_actor_reads(peg):
    pixels = jax.random.uniform(jax.random.key(0), (N, N, 5), minval=0.2, maxval=0.9)
    joints = jnp.zeros(14)
    coords = jnp.asarray(peg.mount.default, jnp.float32)

    def read(px):  # red of a 3 x 2 block (nonlinear), and the depth of one pixel
        return jnp.stack([jnp.tanh(jnp.sum(px[2:5, 10:12, 0] ** 2)), 3.0 * px[20, 30, 3]])

    sal = np.asarray(saliency(peg, _actor(read), {}, joints, coords, pixels))
    read_mask = np.zeros((N, N), bool)
    read_mask[2:5, 10:12] = read_mask[20, 30] = True
    assert sal.shape == (N, N)
    assert np.all(sal[read_mask] > 0) and np.all(sal[~read_mask] == 0)
    assert sal[20, 30] == pytest.approx(3.0)  # |d (3 depth) / d depth|
    per = np.asarray(saliency(peg, _actor(read), {}, joints, coords, pixels, per_channel=True))
    assert per.shape == (N, N, 5)
    assert np.all(per[2:5, 10:12, 0] > 0) and np.all(per[2:5, 10:12, 1:] == 0)
    assert per[20, 30, 3] == pytest.approx(3.0) and np.all(per[20, 30, [0, 1, 2, 4]] == 0)

    # an actor that reads only the target's mask: no camera pixel (RGB-D) moves it
    def mask_only(px):
        return jnp.stack([jnp.sum(px[..., 4]), jnp.sum(px[..., 4]) ** 2])

    assert not np.any(np.asarray(saliency(peg, _actor(mask_only), {}, joints, coords, pixels)))
    with pytest.raises(ValueError, match="image actor"):
        saliency(peg, Network(lambda k: {}, lambda p, o: o, 3, 3, NetworkConfig(), 3), {},
                 joints, coords, pixels)


def test_final_video_frames_show_the_real_scene_beside_the_actors_view(peg):
    n, T = 16, 50
    rng = np.random.default_rng(0)
    shots = [{"view": rng.integers(1, 255, (n, n, 3), np.uint8),
              "scene": rng.integers(1, 255, (n, n, 3), np.uint8), "t": t,
              "coords": np.asarray(peg.mount.default, np.float64)} for t in range(3)]
    k = 16  # the panels scaled to 256 pixels, as final_video scales them
    frames = film_frames(shots, peg, "peg_insertion", "chosen view", T, k * n, verdict=True,
                         hold=4)
    assert len(frames) == 3 + 4
    band = 22
    for f, shot in zip(frames, shots + [shots[-1]] * 4):
        assert f.shape == (band + k * n + band, 2 * k * n, 3) and f.dtype == np.uint8
        img = f[band:band + k * n]
        scene, view = img[:, :k * n], img[:, k * n:]  # the real scene left, the view right
        np.testing.assert_array_equal(scene, shot["scene"].repeat(k, 0).repeat(k, 1))
        np.testing.assert_array_equal(view, shot["view"].repeat(k, 0).repeat(k, 1))
        for part in (f[:band, :k * n], f[:band, k * n:], f[-band:]):  # labels and caption
            assert part.max() > 128  # white text on the dark band
    # the caption changes with the step; the held frames add the verdict
    assert not np.array_equal(frames[0][-band:], frames[1][-band:])
    assert not np.array_equal(frames[2][-band:], frames[3][-band:])
    assert all(np.array_equal(frames[3], g) for g in frames[4:])
    with pytest.raises(ValueError, match="2 panels for 1 labels"):
        report.compose_frame([shots[0]["view"]] * 2, ["one"])


def _summary(video=None):
    rec = {"round": 1, "real_steps": 500, "real_successes": [1.0, 1.0, 0.0, 1.0, 1.0],
           "real_success": 0.8, "deployed_camera": "selected", "camera_steps": 13,
           "plan_success": 0.96, "sim_success": 0.75, "q_rank_corr": 0.56,
           "q_rank_corr_pooled": 0.77, "latency": 1, "residual_accepted": False,
           "hybrid_rmse": 1e-3, "hybrid_sim_rmse": 1.1e-3,
           "seconds": {"calibrate": 10.0, "deploy": 5.0},
           "hand_eye_pos_err_mm": 0.33, "uncalibrated_pos_err_mm": 13.9,
           "grasp_tcp_err_mm": 0.81, "nominal_tcp_err_mm": 8.7,
           "param_rel_error": {"gain/joint1": 0.03, "gain/joint2": -0.052, "latency": 0.0},
           "default_camera_successes": [1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 0.0]}
    return {"env": "needle_threading", "seed": 2,
            "config": {"rounds": 1, "episodes_per_round": 5, "camera": "selected",
                       "camera_min_rank": 0.2, "imitation": {"eval_episodes": 20}},
            "rounds": [{"round": 0, "real_steps": 250, "seconds": {"collect": 3.0}}, rec],
            "final": rec, "real_episodes": 10, "wall_s_this_process": 20.0, "video": video}


def test_the_report_says_the_verdict_and_each_cameras_success_with_its_interval(tmp_path):
    (tmp_path / "final.mp4").write_bytes(b"x")
    (tmp_path / "sense").mkdir()
    (tmp_path / "sense" / "saliency.png").write_bytes(b"x")
    s = _summary(str(tmp_path / "final.mp4"))
    text = write_report(tmp_path, s, {"plot": str(tmp_path / "sense" / "sense.png"),
                                      "saliency": str(tmp_path / "sense" / "saliency.png")}
                        ).read_text()
    lines = text.splitlines()
    assert lines[0] == "# twinrl run: needle_threading (seed 2)"
    assert lines[2].startswith("**Verdict:**")
    lo, hi = report.wilson_interval(4, 5)
    assert f"4/5 (80 %, 95 % interval {100 * lo:.0f}-{100 * hi:.0f} %)" in lines[2]
    lo, hi = report.wilson_interval(6, 10)
    assert f"6/10 (60 %, 95 % interval {100 * lo:.0f}-{100 * hi:.0f} %)" in lines[2]
    rows = [x for x in lines if x.startswith("| Q's chosen camera (deployed")
            or x.startswith("| default camera (evaluation)")]
    assert len(rows) == 2 and "| 5 | 4 | 80.0 % |" in rows[0] and "| 10 | 6 | 60.0 % |" in rows[1]
    assert "0.33 mm (uncalibrated 13.90 mm)" in text and "0.81 mm (nominal grasp 8.70 mm)" in text
    assert "rank correlation 0.56 per state, 0.77 pooled" in text
    assert "rejected by its gate" in text and "latency 1 step(s)" in text
    # links only to files that exist: the saliency and the video, not the missing landscape
    assert "](sense/saliency.png)" in text and "](final.mp4)" in text
    assert "sense/sense.png" not in text
    assert (tmp_path / "params.png").exists() and "](params.png)" in text
    # Q's choice not trusted: the report says the default camera was deployed instead
    s["final"] = s["rounds"][1] = {**s["rounds"][1], "deployed_camera": "default",
                                   "q_rank_corr": 0.1}
    text = write_report(tmp_path, s).read_text()
    assert "below camera_min_rank 0.2: the default camera was deployed" in text
    json.dumps(s)  # the summary the report read stays JSON
