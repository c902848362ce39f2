"""``twinrl render --env FILE.xml``: a user's MJCF drawn by OpenGL and by the differentiable
renderer side by side, with how far they agree (``twinrl.render.check``)."""

import json

import mujoco
import numpy as np
import pytest

from twinrl import cli
from twinrl.render import check

SCENE = """<mujoco model="desk">
  <asset><mesh name="wedge" vertex="0 0 0  0.1 0 0  0 0.1 0  0 0 0.08"/></asset>
  <worldbody>
    <light pos="0 0 2" dir="0 0 -1"/>
    <geom name="floor" type="plane" size="0.6 0.6 0.1" rgba="0.7 0.7 0.7 1"/>
    <body name="box" pos="0 0 0.05"><freejoint/>
      <geom type="box" size="0.05 0.04 0.05" rgba="0.8 0.2 0.2 1"/></body>
    <body name="rod" pos="0.2 0.1 0.03" euler="0 90 30"><freejoint/>
      <geom type="capsule" size="0.02 0.08" rgba="0.2 0.6 0.9 1"/></body>
    <body name="frame" pos="-0.2 0 0.1"><site name="s"/>
      <geom type="mesh" mesh="wedge" rgba="0.3 0.8 0.3 1"/></body>
  </worldbody>
</mujoco>"""


def test_an_mjcf_without_a_camera_is_drawn_alike_from_the_viewers_pose():
    model = check.with_view_camera(mujoco.MjSpec.from_string(SCENE))
    assert model.camera(model.ncam - 1).name == check.VIEW
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    r = check.compare(model, data, check.VIEW, 80, 60)
    f = r["figures"]
    assert f["geoms_drawn"] == 4 and f["geom_pixels_opengl"] > 0.3 * f["pixels"]
    # every geom is in view, and both renderers put it at the same pixels and depth
    seen = set(np.unique(r["opengl"]["segmentation"])) - {-1}
    assert seen == {0, 1, 2, 3} and set(np.unique(r["twinrl"]["segmentation"])) - {-1} == seen
    assert f["segmentation_agreement"] >= 0.99 and f["depth_mean_abs_m"] <= 1e-3
    assert f["rgb_psnr_db"] >= 25 and f["textures"] == 0


def test_render_command_on_an_mjcf_writes_the_comparison(tmp_path, capsys):
    xml = tmp_path / "desk.xml"
    xml.write_text(SCENE)
    code = cli.main(["render", "--env", str(xml), "--size", "64", "48", "--steps", "20",
                     "--out", str(tmp_path / "r")])
    assert code == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "r/summary.json").read_text())
    assert summary["camera"] == check.VIEW and summary["steps"] == 20
    assert summary["figures"]["segmentation_agreement"] >= 0.99
    for name in ("compare", "opengl_rgb", "twinrl_rgb"):
        assert (tmp_path / "r" / summary["files"][name]).stat().st_size > 0


def test_render_gradcheck_on_an_mjcf_judges_the_camera_and_every_geom(tmp_path, capsys):
    xml = tmp_path / "desk.xml"
    xml.write_text(SCENE)
    code = cli.main(["render", "--env", str(xml), "--size", "32", "24", "--gradcheck",
                     "--out", str(tmp_path / "r")])
    assert code == 0, capsys.readouterr().err
    rows = json.loads((tmp_path / "r/summary.json").read_text())["gradcheck"]
    groups = {r["group"]: r for r in rows}
    assert set(groups) == {"camera.pos", "camera.rot"} | {
        f"{g}.{f}" for g in ("floor", "box:box#1", "rod:capsule#2", "frame:mesh#3")
        for f in ("pos", "size", "rgb")}
    assert all(r["ok"] for r in rows) and max(r["rel_err"] for r in rows) < 1e-4
    # a mesh's size does not shape it (its vertices do): nothing moves either way
    assert groups["frame:mesh#3.size"]["inert"]
    assert sum(not r["inert"] for r in rows) == len(rows) - 1


def test_crowding_names_what_the_soft_image_leaves_out():
    rods = "".join(f'<geom type="capsule" size="0.01 0.1" pos="{0.02 * i} 0 0.1"/>'
                   for i in range(10))
    model = mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{rods}</worldbody></mujoco>")
    c = check.crowding(model)
    assert "10 capsules (more than cull_above=8" in c["why"]
    assert c["cull_above"] == 10 and c["layers"] == 10
    assert check.crowding(model, cull_above=10, layers=10) is None
    assert check.crowding(mujoco.MjModel.from_xml_string(SCENE)) is None


@pytest.mark.parametrize("xml, extra, message", [
    (None, [], "MJCF file not found"),
    (SCENE, ["--real"], "--real is a registered task's real twin; an MJCF has none"),
    (SCENE, ["--camera", "nosuch"], "camera 'nosuch' is not in the scene"),
    ("<mujoco><worldbody><geom type='box'", [], "desk.xml: "),
    (SCENE, ["--layers", "0"], "--layers must be >= 1, got 0"),
])
def test_render_of_a_bad_mjcf_request_is_one_line(tmp_path, capsys, xml, extra, message):
    path = tmp_path / "desk.xml"
    if xml is not None:
        path.write_text(xml)
    code = cli.main(["render", "--env", str(path), "--size", "32", "24", "--out",
                     str(tmp_path / "r")] + extra)
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and message in err, err


def test_the_spatula_scenes_soft_image_gradient_holds_for_every_geom():
    """The mount's view of spatula flipping: 25 geoms, cylinders among them (the arm's base, the
    pancake's 1.2 mm-thick top). Before the cylinder's kinks and its missed rays' depth had their
    derivatives, the pancake's groups were 92-185 % off and the base's 43-57 %."""
    from twinrl import envs

    model = envs.make("spatula_flipping").sim.mj_model
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    rows = check.gradcheck(model, data, "mount", 32, 24)
    assert len(rows) == 2 + 3 * 25
    assert all(r["ok"] for r in rows), [(r["group"], r["rel_err"]) for r in rows if not r["ok"]]
    assert sum(not r["inert"] for r in rows) >= 50
