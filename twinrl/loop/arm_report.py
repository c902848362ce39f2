"""The SAM-RL loop's report (``twinrl run`` on a manipulation task): ``report.md`` beside its
``summary.json``, and the figures of its last round's actor and Q in ``sense/``.

``write_report`` reads the summary alone (what the loop recorded: ``progress.json``'s rows with
the evaluation merged in) and links the files the loop wrote: the verdict (real success with the
deployed camera against the default camera, each with its 95 % Wilson interval), what was run,
each stage's figures per round (hand-eye and grasp errors, sysid's errors against the hidden
truth, the plans solved, the actor's success in the identified twin, Q's rank correlation, the
residual's verdict, the stages' wall clock), success per camera mode, and the figures.
``write_figures`` draws the last round's figures for the start of its last deployed episode, from
the pose the deployment chose there (not chosen again): Q's landscape with the chosen and default
views and the actor's saliency on both or, where no Q was trained, the actor's saliency on the
deployed view.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from twinrl import report

__all__ = ["write_figures", "write_report", "success_rows", "FIGURES", "GRID", "CAMERAS"]

FIGURES = "sense"
"""The run directory's folder of the last round's figures (``write_figures``)."""


# ------------------------------------------------------------------------------ figures
GRID = (11, 7)
"""Azimuths x elevations of the report's landscape of Q (``twinrl sense`` draws 15 x 9): the
figure's program runs the actor's Jacobian at every pose of it too, ~20 ms a pose on the needle
(its compilation, ~20 s, does not grow with the grid)."""


def write_figures(run, env, record: dict) -> dict[str, str]:
    """The last round's figures in ``OUT/sense/`` (``env``: the round's identified twin;
    ``record``: the round's row of the summary), for the start of its last deployed episode:
    the state read off the robot there (the dataset's last complete episode's first
    observation) and the pose the deployment chose for it (``record["chosen_coords"]``), not
    chosen again (``twinrl.sense.look``: one small compilation, no ascent). With a
    sensing-aware Q (``q/``): ``sense.png`` (Q over a ``GRID`` of the workspace at the chosen
    pose's distance with the default and chosen poses marked -- where the default camera was
    deployed, the grid's best instead of a chosen one --, the views from them with Q there, and
    under each the actor's saliency), ``views.png``, ``saliency.png`` and ``summary.json``;
    without one, the actor's saliency on the deployed view (``saliency.png``, ``summary.json``).
    Returns the files written, by kind ({} where no deployed episode was recorded)."""
    import imageio.v3 as iio

    from twinrl.learn.sensing import load_actor
    from twinrl.loop.engine import read_dataset
    from twinrl.sense import load_q, look, plot_saliency, plot_sense, target_share

    rdir = run.dir.round(run.config.rounds)
    out = run.dir.out / FIGURES
    data = read_dataset(run.dir.dataset)
    complete = np.flatnonzero(data.episode_complete)
    chosen = [c for c in record.get("chosen_coords") or [] if c is not None]
    if not len(complete) or not chosen:
        run.say("  no deployed episode recorded: no figures for the report")
        return {}
    obs = data.obs[data.episode_starts[complete[-1]]]
    mount = env.mount
    default = np.asarray(mount.default, np.float64)
    deployed = np.asarray(chosen[-1], np.float64)
    camera = record.get("deployed_camera")
    poses = {"default": default}
    if camera == "selected":
        poses["chosen"] = deployed
    elif camera != "default":
        poses[str(camera or "deployed")] = deployed
    actor, actor_params, _ = load_actor(rdir.actor)
    q = q_params = None
    if (rdir.q / "policy").exists():
        run.say("  Q's landscape and the actor's saliency for the report ...")
        q, q_params, _ = load_q(rdir.q)
    else:
        run.say("  the actor's saliency for the report ...")
    seen = look(env, actor, actor_params, obs, poses, q=q, q_params=q_params,
                grid=GRID if q is not None else None, distance_coord=deployed[2])
    views = seen["views"]
    where = (f"the start of round {run.config.rounds}'s last deployed episode on "
             f"{run.env_name}")
    files = {"saliency": str(plot_saliency(out / "saliency.png", views,
                                           f"the actor's saliency at {where}"))}
    sph = lambda c: dict(zip(("azimuth_rad", "elevation_rad", "distance_m"),  # noqa: E731
                             np.asarray(mount.spherical(np.asarray(c, np.float32)),
                                        float).tolist()))
    doc = {"kind": "sense", "env": run.env_name, "seed": run.seed, "state": where,
           "deployed_camera": camera, "image_size": int(views["default"]["rgb"].shape[0]),
           "coords": {k: np.asarray(v).tolist() for k, v in poses.items()},
           "poses": {k: sph(v) for k, v in poses.items()},
           "target_pixels": {k: int(v["mask"].sum()) for k, v in views.items()},
           "saliency_target_share": {k: target_share(v) for k, v in views.items()}}
    if q is not None:
        az, el, vals = seen["landscape"]
        marks = dict(poses)
        if "chosen" not in poses:  # the default camera was deployed: where Q's grid peaks
            i, j = np.unravel_index(np.argmax(vals), vals.shape)
            marks["Q's best on the grid"] = np.asarray(
                mount.coords_of([az[j], el[i], sph(deployed)["distance_m"]]), np.float64)
        files["plot"] = str(plot_sense(
            out / "sense.png", mount, (az, el, vals), marks,
            {k: (v["rgb"], v["mask"]) for k, v in views.items()},
            {k: v["q"] for k, v in views.items()}, f"Q's camera choice at {where}",
            note=f"({GRID[0]} x {GRID[1]} poses)", saliency=views))
        gap = np.ones((views["default"]["rgb"].shape[0], 4, 3))
        row = [x for k in views for x in (views[k]["rgb"], gap)][:-1]
        iio.imwrite(out / "views.png", (np.concatenate(row, axis=1) * 255).clip(0, 255)
                    .astype(np.uint8))
        files["views"] = str(out / "views.png")
        doc.update({"q": {k: v["q"] for k, v in views.items()},
                    "q_landscape_max": float(np.max(vals)),
                    "q_landscape_min": float(np.min(vals)), "grid": list(GRID),
                    "steps_to_move": mount.steps_to_move(default, deployed)})
    doc["files"] = files
    report.write_json(out / "summary.json", doc)
    return files


# ------------------------------------------------------------------------------ the report
def _rate(successes) -> tuple[int, int, float, float, float] | None:
    """``(k, n, k / n, lo, hi)`` of a list of 0/1 outcomes (None when there is none)."""
    if not successes:
        return None
    k, n = int(round(float(np.sum(successes)))), len(successes)
    lo, hi = report.wilson_interval(k, n)
    return k, n, k / n, lo, hi


def _rate_text(successes) -> str:
    r = _rate(successes)
    if r is None:
        return report.MISSING
    k, n, p, lo, hi = r
    return f"{k}/{n} ({100 * p:.0f} %, 95 % interval {100 * lo:.0f}-{100 * hi:.0f} %)"


def success_rows(rec: dict) -> list[list[Any]]:
    """Real success per camera mode of one round's record: the deployed camera (recorded
    episodes), the default camera (evaluation), and with and without the residual (evaluation,
    where one was kept), each ``[mode, episodes, successes, rate, "lo-hi %"]``."""
    cam = _camera(rec.get("deployed_camera"))
    modes = ((f"{cam} camera (deployed, recorded)", rec.get("real_successes")),
             ("default camera (evaluation)", rec.get("default_camera_successes")),
             (f"{cam} camera with the residual (evaluation)",
              rec.get("residual_eval_successes")),
             (f"{cam} camera without the residual (evaluation)",
              rec.get("no_residual_eval_successes")))
    rows = []
    for name, s in modes:
        r = _rate(s)
        if r is not None:
            k, n, p, lo, hi = r
            rows.append([name, n, k, report.pct(p), f"{100 * lo:.0f}-{100 * hi:.0f} %"])
    return rows


def _err_pair(rec: dict, got: str, before: str, unit: str, word: str) -> str | None:
    if rec.get(got) is None:
        return None
    text = f"{rec[got]:.2f} {unit}"
    return text + (f" ({word} {rec[before]:.2f} {unit})" if rec.get(before) is not None else "")


CAMERAS = {"selected": "Q's chosen", "default": "default", "random": "random"}
"""How the report names a deployed camera mode."""


def _camera(mode) -> str:
    return CAMERAS.get(mode, str(mode or "deployed"))


def _stage_rows(rec: dict, cfg: dict) -> list[list[Any]]:
    """``[stage, what it gave (evaluation against the hidden truth marked), seconds]`` of the
    stages that ran."""
    sec = rec.get("seconds") or {}
    he = [x for x in (_err_pair(rec, "hand_eye_pos_err_mm", "uncalibrated_pos_err_mm", "mm",
                                "uncalibrated"),
                      _err_pair(rec, "hand_eye_rot_err_deg", "uncalibrated_rot_err_deg", "deg",
                                "uncalibrated"))
          if x]
    grasp = _err_pair(rec, "grasp_tcp_err_mm", "nominal_tcp_err_mm", "mm", "nominal grasp")
    errs = rec.get("param_rel_error") or {}
    sysid = None
    if errs:
        v = np.abs(np.asarray([float(x) for x in errs.values()]))
        worst = max(errs, key=lambda k: abs(float(errs[k])))
        sysid = (f"{len(errs)} parameters off the truth by median {100 * np.median(v):.1f} %, "
                 f"at most {100 * v.max():.1f} % ({worst}) (eval)")
    if not cfg.get("sysid", True):
        sysid = "off (`sysid=false`): the nominal servos and latency"
    elif rec.get("latency") is not None:
        sysid = f"latency {rec['latency']} step(s)" + (f"; {sysid}" if sysid else "")
    n_sim = (cfg.get("imitation") or {}).get("eval_episodes")
    hyb = ""
    if rec.get("hybrid_rmse") is not None:
        hyb = (f"; hybrid model's held-out one-step RMSE {rec['hybrid_rmse']:.2e} against the "
               f"twin's {rec.get('hybrid_sim_rmse') or float('nan'):.2e}")
    residual = {True: "kept", False: "rejected by its gate", None: "none trained"}[
        rec.get("residual_accepted")] + hyb
    q = None
    if rec.get("q_rank_corr") is not None:
        q = (f"held-out rank correlation {rec['q_rank_corr']:.2f} per state"
             + (f", {rec['q_rank_corr_pooled']:.2f} pooled"
                if rec.get("q_rank_corr_pooled") is not None else ""))
    sim = (f"{report.pct(rec['sim_success'])} in the identified twin"
           + (f" ({n_sim} episodes)" if n_sim else "")) if rec.get("sim_success") is not None \
        else None
    deploy = (f"{_rate_text(rec.get('real_successes'))} with the "
              f"{_camera(rec.get('deployed_camera'))} camera; {rec.get('camera_steps')} steps "
              f"moving the mount") if rec.get("real_successes") else None
    rows = [["hand-eye calibration", "; ".join(he) + " (eval)" if he else None,
             sec.get("calibrate")],
            ["grasp in the hand", f"tool point {grasp} (eval)" if grasp else None, None],
            ["sysid", sysid, sec.get("sysid")],
            ["plan", None if rec.get("plan_success") is None else
             f"{report.pct(rec['plan_success'])} of the starts solved", sec.get("plan")],
            ["imitation (image actor)", sim, sec.get("imitation")],
            ["sensing (Q)", q, sec.get("sensing")],
            ["camera check (identified twin)", _check_text(rec, cfg), sec.get("camera_check")],
            ["residual", residual, sec.get("residual")],
            ["deploy (real)", deploy, sec.get("deploy")],
            ["evaluation (real, unrecorded)",
             f"default camera {_rate_text(rec.get('default_camera_successes'))}"
             if rec.get("default_camera_successes") else None, sec.get("evaluation")]]
    return [r for r in rows if r[1] is not None or r[2] is not None]  # stages that ran


def _verdict(rec: dict, cfg: dict, episodes: int | None) -> str:
    if not rec.get("real_successes"):
        return "**Verdict:** no round finished its deployment; nothing was deployed."
    cam = rec.get("deployed_camera") or cfg.get("camera")
    v = (f"**Verdict:** with {episodes} real episodes in all, the deployed actor "
         f"({_camera(cam)} camera) solved **{_rate_text(rec['real_successes'])}** of its real "
         f"episodes")
    if rec.get("default_camera_successes"):
        v += (f"; the same actor with the fixed default camera (evaluation) "
              f"{_rate_text(rec['default_camera_successes'])}")
    v += "."
    if cfg.get("camera") == "selected" and cam == "default":
        rank = rec.get("q_rank_corr")
        if rec.get("sim_selected_success") is not None:
            v += (f" In the identified twin Q's choice did no better than the default camera "
                  f"({_check_text(rec, cfg)}): the default camera was deployed instead.")
        else:
            v += (f" Q's held-out rank correlation ({'—' if rank is None else f'{rank:.2f}'}) "
                  f"was below camera_min_rank {cfg.get('camera_min_rank')}: the default camera "
                  f"was deployed instead of Q's choice.")
    return v


def _check_text(rec: dict, cfg: dict) -> str | None:
    """The camera check's figures (``camera_check.json``'s, as the round's record keeps them)."""
    sel, dft = rec.get("sim_selected_success"), rec.get("sim_default_success")
    if sel is None or dft is None:
        return None
    return (f"Q's choice {report.pct(sel)} against the default camera's {report.pct(dft)} on "
            f"{cfg.get('camera_check')} fresh starts")


def _settings(summary: dict) -> list[list[Any]]:
    cfg = summary.get("config") or {}
    im = cfg.get("imitation") or {}
    keys = ("rounds", "episodes_per_round", "calibrate", "grasp", "sysid", "demonstrations",
            "camera", "camera_min_rank", "camera_check", "residual", "eval_episodes", "image_size")
    rows = [[k, json.dumps(cfg.get(k))] for k in keys if k in cfg]
    rows.append(["imitation", json.dumps(im)])
    rows.append(["sensing", json.dumps(cfg.get("sensing") or {})])
    return rows


def _link(out: Path, path, text: str) -> str | None:
    """A Markdown link to ``path`` relative to ``out`` (None when it does not exist)."""
    if path is None:
        return None
    p = Path(path)
    p = p if p.is_absolute() else out / p
    if not p.exists():
        return None
    try:
        rel = p.relative_to(out)
    except ValueError:
        rel = p
    return f"[{text}]({rel.as_posix()})"


def write_report(out, summary: dict, figures: dict[str, str] | None = None) -> Path:
    """``out/report.md`` of a SAM-RL loop run from its ``summary`` (the dict ``summary.json``
    holds) and the ``figures`` ``write_figures`` drew (by default those the summary names);
    ``params.png`` (sysid's errors against the truth) beside it where the summary has them.
    Returns the report's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = summary.get("config") or {}
    rounds = summary.get("rounds") or []
    done = [r for r in rounds if r.get("round", 0) >= 1]
    last = done[-1] if done else {}
    figures = dict(summary.get("figures") or {}) if figures is None else figures
    env, seed = summary["env"], summary["seed"]
    md = [f"# twinrl run: {env} (seed {seed})", "",
          _verdict(last, cfg, summary.get("real_episodes")), ""]

    steps0 = rounds[0].get("real_steps") if rounds else None
    K = cfg.get("episodes_per_round")
    md += ["## What was run", "",
           f"- **Task** `{env}`; **real twin**: the hidden perturbation drawn from seed {seed} "
           f"(masses, damping, friction, servo gains, latency, observation noise, the camera's "
           f"hand-eye offset, the tool's grasp).",
           f"- **Real episodes used**: {summary.get('real_episodes')} "
           f"({steps0} steps of exciting motions in round 0, then {K} deployed episodes per "
           f"round; {last.get('real_steps')} real steps in all), plus evaluation episodes that "
           f"no stage reads.",
           f"- **Rounds**: {len(done)}; every stage of a round learns in the twin identified "
           f"from the real data so far (`docs/tutorials/sam-rl-loop.md`).", "",
           "Settings (`loop.json` has them all):", ""]
    md += report.md_table(["setting", "value"], _settings(summary)) + [""]

    for rec in done:
        md += [f"## Round {rec['round']}: each stage", "",
               "*(eval)*: measured against the hidden truth, evaluation only (no stage reads "
               "it).", ""]
        md += report.md_table(["stage", "what it gave", "seconds"], _stage_rows(rec, cfg))
        md += [""]
    if last:
        md += ["## Real success per camera mode", "",
               f"Round {last['round']}; the interval is the Wilson score interval of the "
               f"episodes' successes (95 %).", ""]
        md += report.md_table(["camera", "episodes", "successes", "rate", "95 % interval"],
                              success_rows(last)) + [""]
    errs = last.get("param_rel_error") or {}
    if errs:
        report.plot_param_errors(out / "params.png", [], errs,
                                 title="sysid: identified parameters vs the hidden truth "
                                       "(evaluation only)")
    md += ["## Figures", ""]
    shown = [("success.png", "real success per round: the deployed camera, the default camera "
              "and the actor in the identified twin")]
    if figures.get("plot"):
        mark = ("star: the pose the deployment chose there" if
                last.get("deployed_camera") == "selected" else
                "the default camera was deployed; triangle: Q's best on the grid")
        shown.append((figures["plot"], f"Q over the mount's workspace at the start of the last "
                      f"deployed episode (square: the default pose; {mark}), the views from the "
                      f"default and the deployed pose, and under each the actor's saliency on "
                      f"its own image"))
    if figures.get("saliency"):
        shown.append((figures["saliency"], "the actor's saliency: |d action / d pixel| over "
                      "the RGB-D image it sees (`twinrl.sense.saliency`)"))
    if errs:
        shown.append(("params.png", "sysid's relative errors against the hidden truth"))
    for path, text in shown:
        link = _link(out, path, text)
        if link:
            md += [f"!{link}", "", f"*{text}.*", ""]
    links = [_link(out, summary.get("video"), "final.mp4"),
             _link(out, "summary.json", "summary.json"), _link(out, "loop.json", "loop.json"),
             _link(out, "eval/evaluation.json", "eval/evaluation.json")]
    md += ["## Files", "",
           "- " + " · ".join(x for x in links if x),
           "- final.mp4: one more real episode of the deployed actor (not recorded), the real "
           "scene (left) beside the mount's view from the deployed pose (right: the image the "
           "actor acts on), captioned with the camera's pose and the step." if
           summary.get("video") else "- no video (`video=false`).", ""]
    wall = summary.get("wall_s_this_process")
    total = sum(sum((r.get("seconds") or {}).values()) for r in rounds)
    clock = f"Stages' wall clock over all rounds: {total:.0f} s"
    if wall is not None and math.isfinite(float(wall)):
        clock += f"; this process: {wall:.0f} s"
        if summary.get("video_s") is not None:
            clock += f" (the video {summary['video_s']:.0f} s)"
    if summary.get("figures_s") is not None:
        clock += f", then the figures: {summary['figures_s']:.0f} s"
    md += [clock + ".", ""]
    path = out / "report.md"
    path.write_text("\n".join(md))
    return path
