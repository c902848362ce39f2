"""Render the committed benchmark results (``bench/results/*.json``) into the documentation.

Writes ``docs/benchmarks.md`` (one section per bench: what it measures and how, its table, the
command that reproduces it, and the machine, commit and date of the result) and the README's
results table between ``<!-- results:start -->`` and ``<!-- results:end -->``. Every figure on
those pages comes from the JSON; a bench without a committed result says so, with its command.

    python bench/pages.py           # rewrite the pages from the JSON
    python bench/pages.py --check   # exit 1 (and say which) if a page differs from what the JSON gives
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
BENCHMARKS_PAGE = ROOT / "docs" / "benchmarks.md"
README = ROOT / "README.md"
START, END = "<!-- results:start -->", "<!-- results:end -->"


def fmt(x: Any, digits: int = 3) -> str:
    """A table cell: integers with thousands separators, floats to ``digits`` significant
    digits, None as a dash."""
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}"
    if isinstance(x, float):
        if x != x:
            return "nan"
        if abs(x) >= 10 ** digits:
            return f"{x:,.0f}"
        return f"{x:.{digits}g}"
    return str(x).replace("|", "\\|")


def pct(x: float | None, digits: int = 2, signed: bool = True) -> str:
    """A relative error as a percentage (``signed``: with its sign)."""
    if x is None:
        return "–"
    return f"{100 * x:+.{digits}f} %" if signed else f"{100 * x:.{digits}f} %"


def table(header: list[str], rows: list[list[Any]]) -> str:
    """A Markdown table; cells already strings are kept, others go through ``fmt``."""
    cell = lambda v: v if isinstance(v, str) else fmt(v)  # noqa: E731
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


# ---- one renderer per bench: the result's JSON -> (a Markdown table, headline rows) ----------

def loop_table(doc: dict) -> str:
    rows = [[r["env"], r["seed"], r["real_steps"], r["real_return"], r["oracle_return"],
             pct(r["fraction_of_oracle"], 1, signed=False), pct(r["largest_param_error"], 2,
                                                               signed=False),
             r["residual_accepted"], r["wall_s"]] for r in doc["runs"]]
    return table(["task", "twin seed", "real steps", "real return", "oracle return",
                  "of the oracle", "largest parameter error", "residual kept", "wall (s)"], rows)


def loop_headline(doc: dict) -> list[list[str]]:
    return [[f"the loop (`make run`): {r['env']}, twin {r['seed']}",
             f"real return / oracle's, from {r['real_steps']:,} real steps, {r['wall_s'] / 60:.1f} min",
             pct(r["fraction_of_oracle"], 1, signed=False)] for r in doc["runs"]]


def physics_table(doc: dict) -> str:
    rows = [[r["scene"], r["gradient"], r["contacts"], f"{fmt(r['compile_forward_s'])} / "
             f"{fmt(r['compile_grad_s'])}", r["forward_steps_per_s_single"],
             r["forward_steps_per_s_vmap256"], r["grad_steps_per_s_single"],
             r["grad_steps_per_s_vmap16"], r["stock_forward_steps_per_s_vmap256"],
             r["mujoco_c_steps_per_s"]] for r in doc["scenes"]]
    return table(["scene", "gradient", "contacts", "compile fwd / grad (s)", "fwd, 1 env",
                  "fwd, vmap 256", "grad, 1 env", "grad, vmap 16", "stock MJX fwd, vmap 256",
                  "MuJoCo C, 1 thread"], rows)


def physics_headline(doc: dict) -> list[list[str]]:
    return [[f"physics: {r['scene']}", "env-steps/s, forward vmap 256 / gradient vmap 16",
             f"{fmt(r['forward_steps_per_s_vmap256'])} / {fmt(r['grad_steps_per_s_vmap16'])}"]
            for r in doc["scenes"] if r["gradient"] == "implicit" and r["contacts"] == "mjx"]


def sysid_table(doc: dict) -> str:
    rows = []
    for r in doc["results"]:
        for row in r["anchored"]["rows"]:
            rows.append([r["task"], r["seed"], row["parameter"], row["truth"], row["identified"],
                         row["sd"], pct(row["rel_err"], signed=False), row["covered"], row["status"]])
    return table(["task", "twin seed", "parameter", "truth", "identified", "sd", "|error|",
                  "within 3 sd", "sysid says"], rows)


def sysid_headline(doc: dict) -> list[list[str]]:
    out = []
    for r in doc["results"]:
        errs = [abs(x["rel_err"]) for x in r["anchored"]["rows"]
                if x["status"] == "identified" and x["rel_err"] is not None]
        if errs:
            out.append([f"sysid: {r['task']}, twin {r['seed']}",
                        f"largest error of {len(errs)} identified parameters "
                        f"({r['episodes']} episodes)", f"{100 * max(errs):.2f} %"])
    return out


def sysid_baseline_table(doc: dict) -> str:
    rows = []
    for r in doc["results"]:
        for m, v in r["methods"].items():
            rows.append([r["dataset"], m, ", ".join(f"{n} {pct(e, 2, signed=False)}"
                                                    for n, e in v["rel_err"].items()),
                         pct(v["worst"], 2, signed=False), pct(v["median"], 2, signed=False),
                         v["seconds"]])
    out = table(["dataset", "method", "error per parameter", "worst (shared)",
                 "median (shared)", "wall (s)"], rows)
    return out + sysid_baseline_flat(doc) + sysid_baseline_rows(doc)


def sysid_baseline_flat(doc: dict) -> str:
    """Per dataset where twinrl reports shared parameters not identifiable (no effect on the
    data, e.g. a body welded to the world): each method's worst error without them, since the
    worst over all shared parameters is then set by where each method leaves a parameter the
    data do not see."""
    lines = []
    for r in doc["results"]:
        status = r["methods"].get("twinrl", {}).get("status", {})
        flat = [n for n in r.get("shared", []) if status.get(n, "").startswith("not identifiable")]
        rest = [n for n in r.get("shared", []) if n not in flat]
        if not flat or not rest:
            continue
        worst = ", ".join(f"{m} {pct(max(v['rel_err'][n] for n in rest), 2, signed=False)}"
                          for m, v in r["methods"].items())
        lines.append(f"- {r['dataset']}: without {', '.join(flat)} (twinrl: "
                     f"{status[flat[0]]}), the worst error is {worst}")
    return ("\n\nWhere twinrl reports a parameter not identifiable the data do not pin it "
            "and the worst error above is set by where each method leaves it:\n\n"
            + "\n".join(lines)) if lines else ""


def sysid_baseline_rows(doc: dict) -> str:
    """How the rows were produced where they come from several runs (``meta.rows``, written by
    ``--merge``): each run's command, commit, date and load average, with its datasets."""
    groups: dict[tuple, list[str]] = {}
    for name, p in (doc.get("meta", {}).get("rows") or {}).items():
        load = p.get("load_average") or []
        key = (committed_command(p.get("command") or "?"), (p.get("commit") or "?")[:10],
               p.get("date") or "?", f"{load[0]:.1f}" if load else "?")
        groups.setdefault(key, []).append(name)
    if len(groups) < 2:
        return ""
    lines = [f"- {', '.join(names)}: `{cmd}` at commit `{commit}`, {date}, load average "
             f"{load} at the end" for (cmd, commit, date, load), names in groups.items()]
    return "\n\nThe rows come from separate runs:\n\n" + "\n".join(lines)


def sysid_baseline_headline(doc: dict) -> list[list[str]]:
    out = []
    for r in doc["results"]:
        t, b = r["methods"]["twinrl"], r["methods"]["mujoco.sysid"]
        out.append([f"sysid vs mujoco.sysid: {r['dataset']}",
                    "worst error (shared parameters), twinrl / mujoco.sysid; wall clock",
                    f"{pct(t['worst'], 2, signed=False)} / {pct(b['worst'], 2, signed=False)}; "
                    f"{t['seconds']:.0f} s / {b['seconds']:.0f} s"])
    return out


def user_mjcf_table(doc: dict) -> str:
    rows = [[r["parameter"], r["truth"], pct(r["nominal_rel_err"], 1), pct(r["rel_err"], 3),
             r["status"]] for r in doc["rows"]]
    return (f"{doc['samples']} logged samples, observation noise sd {doc['noise'][0]:g} rad / "
            f"{doc['noise'][1]:g} rad/s; the fit took {doc['fit_s']:.0f} s.\n\n"
            + table(["parameter", "truth", "nominal error", "identified error", "sysid says"],
                    rows))


def user_mjcf_headline(doc: dict) -> list[list[str]]:
    n = sum(r["status"] == "identified" for r in doc["rows"])
    err = doc.get("identified_max_rel_err")
    return [["sysid of your MJCF (the Panda, MuJoCo C logs)",
             f"largest error of {n} identified masses and damping",
             "–" if err is None else f"{100 * err:.2f} %"]]


def arm_sysid_table(doc: dict) -> str:
    """Per task and twin: each parameter's error against the truth beside the nominal's, then
    the tool point's gap to the real twin after 5/10/25 replayed steps."""
    out = []
    for r in doc["runs"]:
        rows = [[name, v["truth"], pct(v["nominal_rel_err"], 1, signed=False),
                 pct(v["rel_err"], 2, signed=False)] for name, v in r["params"].items()]
        rows.append(["latency (steps)", r["true_latency"], "", r["latency"]])
        gap = r["tool_gap_m"]
        steps = r["steps"]
        out += [f"**{r['task']}, twin {r['seed']}** (fit {r['fit_seconds']:.0f} s)", "",
                table(["parameter", "truth", "nominal error", "identified error"], rows), "",
                "Tool point's gap to the real twin (mm), the same actions replayed open loop:", "",
                table(["twin"] + [f"after {n} steps" for n in steps],
                      [[k] + [f"{1e3 * x:.2f}" for x in gap[k]]
                       for k in ("nominal", "identified", "truth")]), ""]
    return "\n".join(out).rstrip()


def arm_sysid_headline(doc: dict) -> list[list[str]]:
    out = []
    for r in doc["runs"]:
        gap = r["tool_gap_m"]
        out.append([f"arm sysid: {r['task']}, twin {r['seed']}",
                    f"tool gap to the real twin after {r['steps'][-1]} replayed steps, "
                    "identified (nominal)",
                    f"{1e3 * gap['identified'][-1]:.1f} mm ({1e3 * gap['nominal'][-1]:.1f} mm)"])
    return out


def hand_eye_table(doc: dict) -> str:
    """Per case: the fitted hand-eye offset's error against the hidden one (and the uncalibrated
    camera's), the tool point's error after the grasp's fit (and the nominal grasp's) where it
    was run, and each fit's seconds."""
    rows = []
    for r in doc["rows"]:
        grasp = "grasp_tcp_err_mm" in r
        rows.append([r["task"], r["seed"], r["poses"], r["variant"].removeprefix("tool-"),
                     r.get("steps", "–"),
                     f"{r['hand_eye_pos_err_mm']:.2f} mm / {r['hand_eye_rot_err_deg']:.3f} deg",
                     f"{r['uncalibrated_pos_err_mm']:.1f} mm / "
                     f"{r['uncalibrated_rot_err_deg']:.2f} deg",
                     f"{r.get('hand_eye_seconds', r['seconds']):.0f}",
                     f"{r['grasp_tcp_err_mm']:.2f} mm ({r['nominal_tcp_err_mm']:.2f})"
                     if grasp else "–",
                     f"{r['grasp_seconds']:.0f}" if grasp else "–"])
    return table(["task", "twin", "poses", "tool", "Adam steps", "hand-eye error",
                  "uncalibrated", "seconds", "tool point error (nominal grasp)",
                  "grasp seconds"], rows)


def generic_table(doc: dict) -> str:
    """Any result: the first list of flat records it holds, as a table of its scalar fields."""
    for key, value in doc.items():
        if key != "meta" and isinstance(value, list) and value and isinstance(value[0], dict):
            cols = [k for k, v in value[0].items() if isinstance(v, (int, float, str, bool))
                    or v is None]
            return table(cols, [[r.get(c) for c in cols] for r in value])
    return "(no table in this result)"


def dmc_figures(doc: dict, task: str) -> list[dict]:
    """The published figures ``dmc.json`` holds for ``task`` (a list; one dict in older files)."""
    figs = doc.get("published", {}).get(task) or []
    return [figs] if isinstance(figs, dict) else figs


def dmc_near(fig: dict, steps: float) -> tuple[int, float, float, int] | None:
    """A published curve's ``(control steps, mean, sd, seeds)`` nearest ``steps``."""
    curve = fig.get("curve") or {}
    if not curve or not steps:
        return None
    k = min(curve, key=lambda c: abs(int(c) - steps))
    return (int(k), *curve[k])


def dmc_table(doc: dict) -> str:
    """Our runs beside the published figures at about the same control steps, then every
    published figure with its budget and source, and those published without a number."""
    runs = [r for r in doc["runs"] if "error" not in r]
    rows = []
    for r in runs:
        steps = r.get("env_steps") or 0
        near, at, ratio = [], None, []
        for f in dmc_figures(doc, r["task"]):
            n = dmc_near(f, steps)
            if n is not None:
                near.append(f"{f['algo']} {n[1]:.0f} ± {n[2]:.0f}")
                at = n[0]
            elif f.get("return") is None and f.get("steps") and steps:
                ratio.append(f"{f['steps'] / steps:.0f}x")
        rows.append([r["task"], r["algo"], r["seed"], r.get("return"), r.get("best_return"),
                     steps or None, r.get("wall_s"), " / ".join(near) or "–",
                     fmt(at) if at else "–", " / ".join(ratio) or "–"])
    ours = table(["task", "algo", "seed", "final return (max 1000)", "best evaluation",
                  "env steps", "wall (s)", "published at about the same control steps "
                  "(mean ± sd over seeds, states)", "their control steps",
                  "Playground PPO's steps / this run's"], rows)
    prows, without = [], {}
    for task in doc.get("published", {}):
        for f in dmc_figures(doc, task):
            if f.get("return") is None:
                without.setdefault((f["algo"], f.get("steps"), f.get("reason", ""),
                                    f.get("source")), []).append(task)
                continue
            prows.append([task, f["algo"], f.get("obs", "–"),
                          f"{f['return']:.0f} ± {f.get('sd', float('nan')):.0f}",
                          f.get("seeds"), f.get("steps"), f.get("agent_steps"),
                          f"[csv]({f['source']})" if f.get("source") else "–"])
    lines = [f"{algo} ({fmt(steps)} steps) on {', '.join(tasks)}: no number; {reason} "
             f"([source]({src}))." for (algo, steps, reason, src), tasks in without.items()]
    budget = max((r.get("env_steps") or 0 for r in runs), default=0)
    top = max((f.get("steps") or 0 for t in doc.get("published", {})
               for f in dmc_figures(doc, t)), default=0)
    scale = (f" The largest published budget, {fmt(top)} steps, is {top / budget:.0f} times "
             f"this table's largest run ({fmt(budget)}); where the ratio is 10 or more the "
             f"budgets differ by an order of magnitude or more, and a row says where a CPU "
             f"budget gets, not whether it matches." if budget and top else "")
    written = doc.get("meta", {}).get("published_written")
    note = (f" The published block was written by `{written['command']}` at commit "
            f"`{written['commit'][:10]}`, {written['date']}." if written else "")
    return (ours + "\n\nPublished figures (returns over 1000 control steps, from states; a "
            "TD-MPC2 agent step is two control steps, its action repeat). Equal steps are not "
            "equal computation: those methods are off-policy and reuse each step in many "
            "updates (DreamerV3 and TD-MPC2 also learn a world model, TD-MPC2 plans with it)."
            + scale + note + "\n\n"
            + table(["task", "algorithm", "observations", "return (mean ± sd)", "seeds",
                     "control steps", "agent steps", "source"], prows)
            + ("\n\n" + "\n".join(lines) if lines else ""))


def dmc_headline(doc: dict) -> list[list[str]]:
    return [[f"Control Suite: {r['task']}, {r['algo']}",
             f"return of 1000 after {fmt(r['env_steps'])} env steps, {r['wall_s'] / 60:.1f} min",
             fmt(r["return"])] for r in doc["runs"]
            if "error" not in r and r["task"] == "dmc/cartpole-swingup"]


def learn_table(doc: dict) -> str:
    rows = []
    for task, res in doc.get("tasks", {}).items():
        for algo, r in res["algos"].items():
            per_seed = r.get("fraction_of_ppo_wall_per_seed") or []
            rows.append([task, algo, f"{fmt(r['final_mean'])} ± {fmt(r['final_std'])}",
                         r.get("wall_s_mean"), r.get("compile_s"), r.get("time_to_ppo_final_s"),
                         f"{r.get('ppo_final_reached', 0)}/{r['seeds']}",
                         " / ".join("never" if x is None else fmt(x) for x in per_seed) or "—",
                         r.get("cold_fraction_of_ppo_cold_wall")])
    return table(["task", "algo", "final return (mean ± sd)", "learning wall (s)",
                  "compile (s)", "s to PPO's final return", "seeds that reach it",
                  "fraction of PPO's learning wall, per seed", "cold cache: fraction of PPO's"],
                 rows)


def learn_headline(doc: dict) -> list[list[str]]:
    out = []
    for task, res in doc.get("tasks", {}).items():
        algos = {a: r for a, r in res["algos"].items() if a != "ppo"}
        if not algos or "ppo" not in res["algos"]:
            continue
        best = min(algos, key=lambda a: (-(algos[a].get("ppo_final_reached") or 0),
                                         algos[a].get("fraction_of_ppo_wall") or float("inf")))
        r = algos[best]
        out.append([f"Learn@Sim: {task}, {best} against Brax PPO",
                    f"fraction of PPO's learning wall clock to reach its final return "
                    f"({r.get('ppo_final_reached')}/{r['seeds']} seeds reach it)",
                    fmt(r.get("fraction_of_ppo_wall"))])
    return out


def sensing_table(doc: dict) -> str:
    """Per task and twin: each camera mode's real success with its 95 % Wilson interval, the
    camera the loop deploys (its Q rank against the gate, then where the run checked it, Q's
    choice against the default in the identified twin, pick selected or default), and the
    selected camera against the default one on the same starts (per twin, then pooled)."""
    cell = lambda x: (f"{100 * x['success']:.0f} % "  # noqa: E731
                      f"({100 * x['ci95'][0]:.0f}-{100 * x['ci95'][1]:.0f})")
    diff = lambda x: f"{100 * x['difference']:+.0f} (p {x['sign_test_p']:.2g})"  # noqa: E731
    per = doc.get("per_twin", [])
    gates = {(r["task"], r["seed"]): r for r in doc.get("rows", []) if r["mode"] == "loop"}
    rows = []
    for task, seed in dict.fromkeys((x["task"], x["seed"]) for x in per):
        by = {x["mode"]: x for x in per if x["task"] == task and x["seed"] == seed}
        g = gates.get((task, seed))
        checked = g is not None and g.get("deploy_camera") and \
            g["q_rank_corr"] >= (doc.get("camera_min_rank") or -1)
        loop = (f"{cell(by['loop'])}: {g['deployed_from']} (Q {g['q_rank_corr']:.2f}"
                f"{', twin check' if checked else ''})" if g is not None and "loop" in by else "–")
        rows.append([task, str(seed), *(cell(by[m]) if m in by else "–"
                                        for m in ("selected", "default", "random")), loop,
                     str(by["selected"]["episodes"]) if "selected" in by else "–",
                     diff(by["selected - default"]) if "selected - default" in by else "–"])
    for x in doc.get("paired", []):
        sel = [t for t in doc.get("table", []) if t["task"] == x["task"]]
        by = {t["mode"]: f"{100 * t['success']:.0f} %" for t in sel}
        rows.append([x["task"], "pooled", *(by.get(m, "–") for m in ("selected", "default",
                                                                      "random", "loop")),
                     str(x["episodes"]), diff(x)])
    gate = doc.get("camera_min_rank")
    head = "the loop's camera" + (f" (selected where Q rank >= {gate:g} and, where checked, "
                                  f"Q's choice beat the default in the identified twin)"
                                  if gate is not None else "")
    return table(["task", "twin", "selected camera", "default camera", "random camera", head,
                  "episodes per mode", "selected - default, points (sign test)"], rows)


def sensing_headline(doc: dict) -> list[list[str]]:
    """Per task: the real success of the camera the loop deploys (``"loop"``; Q's choice where it
    passes the loop's gate), else of Q's choice, with Q's choice against the default camera."""
    out = []
    for x in doc.get("paired", []):
        by = {t["mode"]: t for t in doc.get("table", []) if t["task"] == x["task"]}
        mode = "loop" if "loop" in by else "selected"
        twins = list(dict.fromkeys(str(r["seed"]) for r in doc.get("per_twin", [])
                                   if r["task"] == x["task"]))
        if mode in by:
            what = ("the loop's camera (Q's choice where it passes the loop's checks)" if mode == "loop"
                    else "the chosen camera")
            out.append([f"SAM-RL loop: {x['task']}, twin{'s' if len(twins) > 1 else ''} "
                        f"{', '.join(twins)}",
                        f"real success with {what}, {x['episodes']} starts (Q's choice "
                        f"{100 * x['difference']:+.0f} points over the default camera)",
                        f"{100 * by[mode]['success']:.0f} %"])
    return out


def q_rank_table(doc: dict) -> str:
    """Per loop run: Q's rank correlation per state across poses on fresh states (bootstrap 95 %
    interval), pooled, the loop's own held-out figure, the retest (the outcome one small camera
    move away ranking the outcome) and the success at Q's preferred pose against the mean pose."""
    cell = lambda r, k: "–" if r.get(k) is None else fmt(r[k])  # noqa: E731
    rows = [[r["task"], str(r["twin_seed"]), f"{r['states']} x {r['cameras']}",
             f"{r['rank_corr']:.2f} ({r['rank_corr_ci95'][0]:.2f}-{r['rank_corr_ci95'][1]:.2f})",
             f"{r['rank_corr_pooled']:.2f}", cell(r, "loop_rank_corr"),
             cell(r, "retest_rank_corr"),
             f"{100 * r['success_q_choice']:.0f} % / {100 * r['success_mean_pose']:.0f} %"]
            for r in doc["rows"]]
    return table(["task", "twin", "states x poses", "rank per state (95 %)", "pooled",
                  "the loop's (held-out fifth)", "outcome one move away ranks it",
                  "success: Q's pose / mean pose"], rows)


def actor_views_table(doc: dict) -> str:
    """Per loop run: the image actor's success fed the true state, from random views (split by
    whether the view's fitted pose is right) and from the default view."""
    cell = lambda x: "–" if x is None else f"{100 * x:.0f} %"  # noqa: E731
    rows = []
    for r in doc["rows"]:
        rnd = r["random"]
        rows.append([r["task"], str(r["twin_seed"]), str(r["episodes"]),
                     cell(r.get("truth", {}).get("success")), cell(rnd["success"]),
                     cell(r["default"]["success"]), cell(rnd.get("p_good")),
                     f"{cell(rnd.get('s_good'))} / {cell(rnd.get('s_bad'))}",
                     cell(rnd.get("need_bad"))])
    return table(["task", "twin", "starts", "true state", "random views", "default view",
                  "random views whose fit is right", "success from those / the others",
                  "the others would need (for 90 %)"], rows)


def real_failures_table(doc: dict) -> str:
    """Per loop run: the starts its actor failed in the real twin against those it solved --
    the actor in the twin from the same starts (its view; the true pose), the real actions
    replayed in the twin, the expert's plans in the twin and replayed in real."""
    cell = lambda x: "–" if x is None else f"{100 * x:.0f} %"  # noqa: E731
    mm = lambda g, k: (f"{g[k + '_xy_mm']:.1f} / {g[k + '_z_mm']:.1f}"  # noqa: E731
                       if k + "_xy_mm" in g else "–")
    rows = []
    for r in doc["rows"]:
        for g in r["groups"]:
            rows.append([r["task"], str(r["twin_seed"]), r["camera"],
                         f"{g['group']} {g['starts']} of {r['episodes']}", cell(g["sim_actor"]),
                         cell(g["sim_truth"]), cell(g["replay"]), cell(g.get("replay_grasp")),
                         f"{cell(g['plan_sim'])} / {cell(g['plan_real'])} "
                         f"({g['plan_real_n']})", mm(g, "real_end"), mm(g, "replay_end")])
    return table(["task", "twin", "camera", "real starts", "actor in the twin",
                  "actor in the twin, true pose", "real actions in the twin",
                  "... at the true grasp",
                  "plans: in the twin / replayed in real (starts)", "real end: xy / z (mm)",
                  "real actions' end in the twin"], rows)


def gradcheck_large_table(doc: dict) -> str:
    rows = [[r["model"], r.get("flags") or "", r.get("status"), r.get("wall_s"),
             *(r.get("timings", {}).get(k) for k in ("trace", "compile", "gradient",
                                                      "differences", "rollouts")),
             r.get("peak_rss_gb")] for r in doc["rows"]]
    return table(["model", "flags", "result", "wall (s)", "trace (s)", "compile (s)",
                  "gradient (s)", "differences (s)", "rollouts", "peak memory (GB)"], rows)


@dataclass(frozen=True)
class Bench:
    """A bench's section: its script, title, method paragraph, the command that reproduces the
    reference result, and how its JSON becomes a table and headline rows (README)."""
    name: str
    title: str
    method: str
    command: str
    render: Callable[[dict], str] = generic_table
    headline: Callable[[dict], list[list[str]]] = field(default=lambda doc: [])


BENCHES = [
    Bench("loop", "The whole loop",
          "`twinrl run` as `make run` runs it, in a fresh process: exciting episodes recorded on "
          "the real twin, sysid, the hybrid model, Brax PPO in the identified simulator, the "
          "residual gate and deployment; the final policy's return on the real twin against an "
          "oracle trained on the hidden truth (evaluation only), the real steps it took, and "
          "the command's wall-clock time, compilation included.",
          "python bench/loop.py --out bench/results", loop_table, loop_headline),
    Bench("physics", "Physics throughput",
          "T = 100-step open-loop rollouts of each bundled scene, float32: compile seconds of the "
          "forward rollout and of its gradient, forward env-steps/s for one environment and "
          "vmap 256, forward+backward env-steps/s of the rollout loss's gradient w.r.t. the "
          "actions (one environment, vmap 16; a gradient's steps count once), the same "
          "forward through stock `mjx.step`, and MuJoCo C's `mj_step` on one thread. Best of "
          "`--repeats` timings after a warm-up. On a GPU, wide batches step several times "
          "faster than on a CPU while one environment runs far slower (small kernels are "
          "launch-bound), so the trainers that differentiate a few rollouts at a time are "
          "faster on the CPU.",
          "python bench/physics.py --out bench/results", physics_table, physics_headline),
    Bench("render", "Differentiable rendering",
          "Frames/s of `twinrl.render` at 64x64 and 128x128, batch 1 and 16: the hard image, the "
          "soft image forward, and forward + gradient w.r.t. the camera and every geom's pose, "
          "size and colour, on push and the arm scenes from their mount cameras; then the "
          "image observations of the arm tasks, a geom-count sweep, and the agreement of depth "
          "and segmentation with MuJoCo's OpenGL. `--visual` adds visual Real2Sim on push "
          "(hidden camera offsets 3-4 cm / 5-6 deg; the box moved, resized and recoloured).",
          "python bench/render.py --out bench/results"),
    Bench("sysid", "System identification on the real twins",
          "Per task and twin seed: exciting episodes recorded on the default real twin, then "
          "`sysid.fit` with the default parameter set, start states estimated, the latency "
          "chosen, and the first body's mass known (weighed; without it the common scale of "
          "masses, gains, damping and friction is a flat direction, which sysid reports). Each "
          "parameter against the twin's hidden truth (evaluation only), with the fit's sd and "
          "whether the error lies within 3 sd. Without `--no-cma` the bench also runs CMA-ES "
          "on the same objective and counts the rollouts each needs.",
          "python bench/sysid.py --out bench/results", sysid_table, sysid_headline),
    Bench("user_mjcf_sysid", "Real2Sim on your own MJCF",
          "The \"robot\" is MuJoCo C running twinrl's Panda MJCF with every body's mass scaled "
          "by a factor in [0.85, 1.2] and every joint's damping by one in [0.6, 1.6]; episodes "
          "hold random controls and log qpos, qvel and ctrl as a robot's logger would. "
          "`sysid.fit(env, env.transitions(...))` fits every mass and damping from the "
          "nominal MJCF; the base, welded to the world, is reported not identifiable.",
          "python bench/user_mjcf_sysid.py --out bench/results", user_mjcf_table,
          user_mjcf_headline),
    Bench("sysid_baseline", "twinrl's sysid against MuJoCo's own mujoco.sysid",
          "The same recorded data identified three ways: the pendulum and cartpole real twins "
          "(seed 0, first mass known) and the Panda logs of the user-MJCF bench. twinrl's "
          "`sysid.fit` as those benches call it (on the Panda without the bound test, whose "
          "refits cannot hold a 24-61 N s/m damping at 0 and took most of the fit's time); "
          "`mujoco.sysid.optimize` (MuJoCo's "
          "least-squares, finite-difference Jacobians) on MuJoCo C rollouts of the nominal model "
          "over the same windows, each started at the recorded state, with the same physical "
          "parameters, the same known mass and the same latency grid; CMA-ES on `bench/sysid.py`'s "
          "objective with the recorded starts. Relative error of each parameter against the hidden truth "
          "(evaluation only), worst and median over the parameters every method fits, and wall "
          "clock (twinrl's includes JAX compilation). The script's docstring lists what each "
          "tool can fit that the other cannot.",
          "python bench/sysid_baseline.py --out bench/results", sysid_baseline_table,
          sysid_baseline_headline),
    Bench("push_sysid", "Push: box mass and friction",
          "Push's box mass and friction from its real twin observed in full states, case by "
          "case: the whole hidden perturbation or parts of it, the contact rule, the loss, the "
          "start, staged fits, and indirect inference (`--indirect R`). See "
          "[known limits](known-limits.md) for where it stands.",
          "python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --staged "
          "--recorded-starts --indirect 6 --out bench/results"),
    Bench("learn", "Learn@Sim trainers",
          "`pods`, `pods2`, `hds`, `shac` and Brax `ppo`/`apg` on `pendulum_swingup` and "
          "`cartpole_swingup` in simulation, over seeds: final return; compile seconds apart "
          "from learning (seed 0 once on an empty compilation cache, then every seed with its "
          "programs in the cache: compile = the difference); the learning seconds each "
          "differentiable learner takes to first reach PPO's final return, per seed, as a "
          "fraction of PPO's learning wall clock (the target: at most 0.2), and the same on "
          "cold caches (compile included).",
          "python bench/learn.py --algos ppo shac --envs cartpole_swingup pendulum_swingup "
          "--out bench/results", learn_table, learn_headline),
    Bench("learn_push", "Learn@Sim through contacts: push",
          "The same comparison on `push` (a sphere pushes a box to a goal through contacts), one "
          "seed at a smaller budget (PPO 1 M steps, SHAC 100 epochs): return against learning "
          "wall clock, compile apart. Written as `learn.json` in its `--out` and kept here as "
          "`learn_push.json`.",
          "python bench/learn.py --algos ppo shac --envs push --seeds 1 --set "
          "ppo.num_timesteps=1000000 --set shac.epochs=100 --out DIR", learn_table,
          learn_headline),
    Bench("dmc", "The DeepMind Control Suite at a fixed budget",
          "Brax PPO and SHAC on the `dmc/` tasks (the Control Suite's own XML and rewards) at a "
          "CPU budget: final return of the deterministic policy over 1000-step episodes, env "
          "steps and wall clock (compile included), beside published figures at about the same "
          "number of control steps: the learning-curve data TD-MPC2 (Hansen et al., ICLR 2024) "
          "released for SAC, DreamerV3 and TD-MPC2 from states, 3 seeds, read from its CSVs "
          "(one of its agent steps is two control steps). MuJoCo Playground's Brax PPO runs "
          "(60 M steps, 2048 environments, on a GPU) are given as learning curves only, so "
          "their settings and source are recorded, not a number read off a plot.",
          "python bench/dmc.py --tasks dmc/cartpole-swingup dmc/pendulum-swingup --algos ppo "
          "shac --budget 2000000 --epochs 400 --out bench/results", dmc_table, dmc_headline),
    Bench("gradcheck_large", "Gradient checks of large models",
          "`twinrl gradcheck FILE --x64 --horizon 20` on the Control Suite's models of 20 or "
          "more joints (the installed `dm_control` package's XML), each in a fresh process "
          "with the compilation cache off: wall clock, the check's own stage times (trace and "
          "lower, compile, the gradient's first run, the finite differences with their "
          "batched forward's compile), the rollouts differenced and the peak resident memory.",
          "python bench/gradcheck_large.py --out bench/results", gradcheck_large_table),
    Bench("scale", "Past one process",
          "SHAC and Brax PPO on `cartpole_swingup` under `jax.distributed`: env-steps/s and wall "
          "clock at 1 and 2 CPU processes (one core each, `taskset`), and the return reached; "
          "`--widths` adds environment counts for an accelerator. See the "
          "[Scaling out](tutorials/scaling-out.md) tutorial.",
          "python bench/scale.py --out bench/results"),
    Bench("sim2real", "Model-free on the real twin",
          "Real-twin steps that sbx-rl's SAC and TD3, trained directly on a loop run's real "
          "twin, need to reach 90 % of the oracle, against the loop's few real steps. Needs "
          "the `bench` extra in a separate environment.",
          "python bench/sim2real.py --out bench/results"),
    Bench("residual", "Residual adaptation",
          "The loop on a real twin with an effect sysid cannot model (a constant actuator "
          "offset): the real return of the policy learned in the identified simulator, before "
          "and after the residual policy trained through the hybrid model.",
          "python bench/residual.py --out bench/results"),
    Bench("manipulation", "The manipulation suite",
          "Per arm task: compile seconds, forward and gradient env-steps/s (single and vmap "
          "16), the target's visibility over the camera mount's workspace, trajectory "
          "optimisation's success from the privileged state over random starts, and the "
          "optimised plans replayed open loop on the real twins.",
          "python bench/manipulation.py --out bench/results"),
    Bench("imitation", "Imitation of trajectory optimisation",
          "Success of the state actor and of the image actor in the simulator after behaviour "
          "cloning and DAgger rounds, on fresh starts, from the plans of the manipulation bench.",
          "python bench/imitation.py --plans bench/results --out bench/results"),
    Bench("arm_sysid", "The arm loop's sysid",
          "The SAM-RL loop's identification (latency, servo stiffness and damping) judged by "
          "what it is for: each parameter's error against the hidden truth, and the tool "
          "point's gap to the real twin when the identified twin replays the same actions. "
          "The gap is the mean over starts of the scripted expert's actions replayed from the "
          "same start; the truth row is the simulator with the hidden parameters (what is "
          "left is what no parameter of the fit models).",
          "python bench/arm_sysid.py --out bench/results", arm_sysid_table,
          arm_sysid_headline),
    Bench("hand_eye", "Hand-eye calibration",
          "The arm loop's camera-mount calibration by visual Real2Sim against the hidden "
          "offset, with the tool in the fit and left out, from one mount pose or several; "
          "`--grasp` adds the tool's grasp in the hand; `--steps` the fits' Adam steps before "
          "their Levenberg-Marquardt refinement (the loop's `calibration_steps`).",
          "python bench/hand_eye.py --out bench/results", hand_eye_table),
    Bench("q_rank", "Ranking camera poses",
          "How well a loop's sensing-aware Q ranks camera poses on fresh states of its "
          "identified twin (Spearman's correlation per state across poses, with a bootstrap "
          "interval), and how often the ascent through the renderer raises Q above the "
          "default pose. Needs a `twinrl run` output directory (`RUNk`: a `twinrl run --env "
          "TASK --seed S --out RUNk`, S the twin).",
          "python bench/q_rank.py --run needle_threading=runs/needle --out bench/results",
          q_rank_table),
    Bench("actor_views", "What limits the image actor",
          "A loop run's image actor in its identified twin on fresh starts: fed the true state "
          "where it reads a fitted pose (what cloning alone reaches), from a random mount pose "
          "per episode (the loop's own evaluation) and from the default pose. A random view is "
          "*right* where 90 % of its steps' fitted poses are within 5 mm of the truth (along the "
          "actor's own episode); the last column is the success the other views would need for "
          "90 % overall. `RUNk`: a `twinrl run --env TASK --seed S --out RUNk`, S the twin.",
          "python bench/actor_views.py --run needle_threading=runs/needle --episodes 100 "
          "--out bench/results", actor_views_table),
    Bench("real_failures", "Where the real failures come from",
          "A loop run's image actor deployed on its hidden real twin with the loop's camera "
          "(50 starts, the sensing bench's), its starts split into those it failed and those "
          "it solved; per group: the same actor in the identified twin from the same starts "
          "(the camera where the real episode put it; and fed the true pose where it reads a "
          "fitted one), the real episode's actions replayed open loop in the identified twin "
          "(and in it with the tool at the real twin's hidden grasp instead of the fitted one), "
          "and trajectory optimisation in the identified twin (the loop's plan stage) from "
          "each failed start and as many solved ones, its plans replayed open loop in the "
          "real twin. The ends are medians of the true peg tip's distance from the hole's axis "
          "and its height above the hole's top (success: within 16 mm of the axis and below "
          "-17.5 mm, the tip's lowest point 30 mm down).",
          "python bench/real_failures.py --run peg_insertion=runs/peg --episodes 50 --plan "
          "--out bench/results", real_failures_table),
    Bench("sensing", "Active sensing on the real twins",
          "A SAM-RL loop's image actor deployed on the loop's own hidden real twin (`RUNk`: a "
          "`twinrl run --env TASK --seed S --out RUNk`, S the twin, the loop's defaults) with "
          "the camera Q "
          "selects, the default camera and a random one, 50 starts per mode: each mode's "
          "success with its 95 % (Wilson) interval, and the selected camera against the "
          "default one on the same starts (exact sign test), per twin and pooled. The loop's "
          "camera is the one `twinrl run` deploys now: Q's choice where Q's held-out rank "
          "reaches the loop's `camera_min_rank` and, on 20 fresh starts in the identified twin, "
          "Q's choice succeeds more often than the default camera (the run's `camera_check` "
          "stage; runs from before it gain it with `twinrl run --resume`), else the default "
          "camera (the same episodes). "
          "`--state-actor` and `--model-free-steps` add the state-based oracle and model-free "
          "SAC/TD3 (SAM-RL's Table I comparison).",
          "python bench/sensing.py --tasks needle_threading --run needle_threading=runs/needle "
          "--episodes 50 --modes selected default random --out DIR; one DIR per loop run, then "
          "python bench/sensing.py --merge DIR0/sensing.json DIR1/sensing.json ... --out "
          "bench/results", sensing_table, sensing_headline),
]


def committed_command(command: str) -> str:
    """The command as it reproduces the committed file: its ``--out DIR`` written ``--out
    bench/results`` (a result measured into a scratch directory and then committed)."""
    import re

    return re.sub(r"--out(=|\s+)\S+", "--out bench/results", command)


def reproduce(meta: dict, command: str) -> list[str]:
    """The command lines that reproduce a committed result. A result merged from several
    (``meta.merged``, e.g. ``bench/sensing.py --merge``) gets each merged command first; their
    scratch paths become ``DIR0``, ``DIR1``, ... (``--out``). A loop run named ``TASK=/abs/path``
    (``--run``) becomes ``TASK=RUN0``, ``TASK=RUN1``, ... (a ``twinrl run`` output directory).
    The merge itself is shown as the merge of those directories' files, whatever earlier merged
    file it read."""
    import re

    merged = [c for c in meta.get("merged") or [] if c]
    main = meta.get("command", command)
    names: dict[str, str] = {}
    for c in merged:
        for m in re.finditer(r"--out(?:=|\s+)(\S+)", c):
            names.setdefault(m.group(1), f"DIR{sum(v.startswith('DIR') for v in names.values())}")
    for c in [*merged, main]:
        for m in re.finditer(r"(?:^|[\s=])\w+=(/\S+)", c):
            names.setdefault(m.group(1), f"RUN{sum(v.startswith('RUN') for v in names.values())}")
    if names:
        pattern = re.compile("|".join(re.escape(k) for k in sorted(names, key=len, reverse=True)))
        rename = lambda c: pattern.sub(lambda m: names[m.group(0)], c)  # noqa: E731
    else:
        rename = lambda c: c  # noqa: E731
    main = rename(main)
    dirs = [names[m.group(1)] for c in merged for m in re.finditer(r"--out(?:=|\s+)(\S+)", c)]
    files = re.search(r"--merge((?:\s+(?!-)\S+)+)", main)
    if dirs and files:
        # a merge that took an earlier merged result (a twin re-measured and merged into the
        # committed file): from scratch it is the merge of every command's directory's file
        name = Path(files.group(1).split()[-1]).name
        main = main.replace(files.group(0), "--merge " + " ".join(
            f"{d}/{name}" for d in dict.fromkeys(dirs)))
    return [rename(c) for c in merged] + [committed_command(main)]


def provenance(meta: dict) -> str:
    """One line: machine, commit, date and versions of a result."""
    m = meta.get("machine", {})
    v = meta.get("versions", {})
    commit = meta.get("commit", "unknown")[:10] + (" (with local changes)" if meta.get("dirty")
                                                    else "")
    load = m.get("load_average")
    load_s = f", load average {load[0]:.1f} at the end" if load else ""
    return (f"{m.get('cores', '?')} cores ({m.get('cpu_model', '?')}; {m.get('device', '?')}"
            f"{load_s}), commit `{commit}`, {meta.get('date', '?')}, jax {v.get('jax', '?')}, "
            f"mujoco {v.get('mujoco', '?')}")


def load_results(results: Path = RESULTS) -> dict[str, dict]:
    """Every ``NAME.json`` of ``results`` by name."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(results.glob("*.json"))}


def benchmarks_page(docs: dict[str, dict]) -> str:
    """The benchmarks page's Markdown."""
    out = ["# Benchmarks", "",
           "<!-- generated by bench/pages.py from bench/results/*.json: edit those, not this -->",
           "",
           "Every figure on this page comes from a result file committed in `bench/results/` "
           "and was written by the bench itself, with the command, commit, machine and date "
           "given under its table. `python bench/pages.py` regenerates this page and the "
           "README's table; the tests fail when they differ from the JSON. Timings depend on "
           "the machine and on what else runs on it (the load average is recorded).", ""]
    for b in BENCHES:
        out += [f"## {b.title} {{#{b.name.replace('_', '-')}}}", "", b.method, ""]
        doc = docs.get(b.name)
        if doc is None:
            out += ["No committed result yet. Reproduce with:", "", "```sh", b.command, "```",
                    ""]
            continue
        meta = doc.get("meta", {})
        out += [b.render(doc), "", "Reproduce with:", "", "```sh",
                *reproduce(meta, b.command), "```", "",
                f"Measured on {provenance(meta)}.", ""]
    return "\n".join(out).rstrip() + "\n"


def readme_table(docs: dict[str, dict]) -> str:
    """The README's headline results, between its markers."""
    rows = []
    for b in BENCHES:
        if b.name in docs:
            anchor = b.name.replace("_", "-")
            rows += [[*r, f"[{b.name}](docs/benchmarks.md#{anchor})"]
                     for r in b.headline(docs[b.name])]
    if not rows:
        return "No committed benchmark results yet."
    return table(["benchmark", "figure", "value", "details"], rows)


def with_readme_table(readme: str, docs: dict[str, dict]) -> str:
    """``readme`` with the text between the results markers replaced."""
    if START not in readme or END not in readme:
        raise SystemExit(f"README.md has no {START} ... {END} markers")
    head, rest = readme.split(START, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{START}\n{readme_table(docs)}\n{END}{tail}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 if a page is out of date with the JSON")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    docs = load_results(args.results)
    wanted = {BENCHMARKS_PAGE: benchmarks_page(docs),
              README: with_readme_table(README.read_text(), docs)}
    stale = [p for p, text in wanted.items() if not p.exists() or p.read_text() != text]
    if args.check:
        for p in stale:
            print(f"{p.relative_to(ROOT)} is out of date with bench/results/*.json: run "
                  f"python bench/pages.py", file=sys.stderr)
        return 1 if stale else 0
    for p in stale:
        p.write_text(wanted[p])
        print(f"wrote {p.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
