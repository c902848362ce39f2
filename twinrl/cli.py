"""The ``twinrl`` command.

Each sub-command has ``--help``, ``--seed`` and ``--out DIR``; those that produce results write
``DIR/summary.json`` beside their human outputs and print a table. Bad input (a missing or
malformed MJCF, an unknown scene) gets one clear line on stderr and exit status 2; a check that
runs and fails exits 1.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

__all__ = ["main"]


class UsageError(Exception):
    """Bad input named in one line, no traceback."""


def _one_line_warnings(prefix: str) -> None:
    """Print MuJoCo's warnings (``twinrl.physics.MuJoCoWarning``) on the command line as one line
    each, ``PREFIX: warning: ...``, not Python's two (file:line, then the source line that called
    MuJoCo); every other warning keeps Python's format."""
    import warnings

    from twinrl.physics.mjwarn import MuJoCoWarning

    default = warnings.formatwarning

    def formatwarning(message, category, filename, lineno, line=None):
        if issubclass(category, MuJoCoWarning):
            return f"{prefix}: warning: {message}\n"
        return default(message, category, filename, lineno, line)

    warnings.formatwarning = formatwarning


MJCF_RUN_HINT = ("the loop is for the registered tasks: identify your MJCF with `twinrl sysid "
                 "--env PATH --from LOG.npz`, learn in it with `twinrl train --env PATH "
                 "--reward FILE.py:FUNCTION`")


def _check_task(name: str, mjcf_hint: str | None = None) -> None:
    """A registered task's name, else one line listing them (with ``mjcf_hint`` when ``name``
    is an MJCF file, which this command does not take)."""
    from twinrl import envs

    if name not in envs.names():
        if mjcf_hint and str(name).lower().endswith(".xml"):
            raise UsageError(f"--env {name}: {mjcf_hint}")
        raise UsageError(f"unknown task {name!r}; registered tasks are {', '.join(envs.names())}")


def _at_least_one(args, *flags: str) -> None:
    """One line naming the first of ``flags`` (argparse dests) given and below 1."""
    for flag in flags:
        v = getattr(args, flag)
        if v is not None and v < 1:
            raise UsageError(f"--{flag} must be >= 1, got {v}")


def _check_size(size) -> None:
    """``--size W H``: both at least 1 (the renderer's own bound, its offscreen buffer, is
    checked where the model is loaded)."""
    if min(size) < 1:
        raise UsageError(f"--size {size[0]} {size[1]}: width and height must be >= 1")


def _common(p: argparse.ArgumentParser, out_default: str) -> None:
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", type=Path, default=Path(out_default),
                   help=f"output directory (default {out_default})")


# ---------------------------------------------------------------------------------- gradcheck
def _gradcheck_parser(sub) -> None:
    p = sub.add_parser(
        "gradcheck", help="check reverse-mode gradients of a rollout against finite differences",
        description="Reverse-mode gradients of a rollout loss w.r.t. actions, initial state and "
                    "every PhysParams field, against central finite differences. Exits 1 if a "
                    "relative error exceeds the tolerance or a gradient is non-finite.")
    p.add_argument("targets", nargs="*", default=["all"], metavar="SCENE|TASK|MJCF-PATH",
                   help="bundled scene name, a manipulation task's name (peg_insertion, "
                        "spatula_flipping, needle_threading: its scene through the scripted "
                        "expert's tool-object contacts), path to your MJCF, or 'all' (default: "
                        "the bundled scenes)")
    p.add_argument("--horizon", "-T", type=int, default=None,
                   help="rollout steps (default: 100; 50 for peg_in_hole)")
    p.add_argument("--x64", action="store_true",
                   help="float64 (needed for a meaningful check; float32 differences are noise)")
    p.add_argument("--rtol", type=float, default=None,
                   help="relative tolerance (default 1e-4 with --x64, 2e-2 without)")
    p.add_argument("--iterations", type=int, default=None,
                   help="constraint-solver iterations (default: the MJCF's option)")
    p.add_argument("--scenario", default=None, metavar="NAME",
                   help="initial state and actions: 'wave' (smooth random actions from the "
                        "model's qpos0 at rest; the default for your MJCF), 'zero' (no actuation: "
                        "a dropped object), or a bundled scene's name for its own scenario "
                        "(cartpole, pendulum, push, peg_in_hole; the default for that scene)")
    p.add_argument("--tolerance", type=float, default=None,
                   help="constraint-solver tolerance during the check (default 1e-12 with --x64 "
                        "so differences see the solution, not the stopping rule; else the MJCF's)")
    p.add_argument("--gradient", default="implicit", choices=("implicit", "unrolled"),
                   help="derivative of the constraint solve: of its converged solution (implicit "
                        "function theorem, default) or of its fixed iterations")
    p.add_argument("--contacts", default="mjx", choices=("mjx", "mujoco"),
                   help="collision rules: stock MJX's (default) or MuJoCo C's box on a plane "
                        "(every lower corner touches; MJX keeps those within 1 mm of the deepest)")
    p.add_argument("--settle", type=int, default=0, metavar="N",
                   help="run N physics steps (MuJoCo C, no actuation) before the check, so it "
                        "starts where the model has come to rest, e.g. a walker on the ground")
    p.add_argument("--strict", action="store_true",
                   help="also exit 1 when an input group has no resolved entry (nothing judged "
                        "through it) and is not inert")
    p.add_argument("--step", type=float, default=None, metavar="H",
                   help="finite-difference step, relative to max(1, |x|) (default 1e-6 with "
                        "--x64, else 1e-3); a larger one resolves smaller gradients (rounding "
                        "noise ~ eps |L| / H) at the risk of more kinks in the window")
    p.add_argument("--entries", type=int, default=None, metavar="K",
                   help="difference at most K entries per input group (a seeded random subset; "
                        "each costs 4 rollouts): a large model's check at a fraction of the cost")
    _common(p, "runs/gradcheck")
    p.set_defaults(func=_cmd_gradcheck)


def _task_scenes() -> tuple[str, ...]:
    """Tasks whose scene ``gradcheck`` takes by the task's name (the manipulation suite: its
    MJCF is composed, not a bundled file), with the task's scripted expert as the scenario."""
    from twinrl.envs import TASKS
    from twinrl.envs.arm.base import ArmTask

    return tuple(n for n, e in TASKS.items() if issubclass(e.env_class, ArmTask))


def unjudged_line(r) -> str:
    """The line naming a gradcheck's unjudged groups, and why where the forward's own roughness
    explains it (``GradcheckResult.unjudged_by_roughness``)."""
    from twinrl.physics.gradcheck import JITTER

    why = (f"; moving every input by {JITTER:g} of itself moved the loss by "
           f"{r.loss_jitter:.1e} beyond its gradient, so differences at --step {r.step:g} "
           f"resolve no derivative below ~{r.resolution_floor:.1e} (a body resting flat, a "
           f"contact that switches on rounding: a scenario that moves it, or a larger --step)"
           if r.unjudged_by_roughness else "")
    return f"not judged (no resolved entry): {', '.join(r.unjudged)}{why}"


def _cmd_gradcheck(args) -> int:
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    from twinrl import report
    from twinrl.physics import SCENES, Sim
    from twinrl.physics.gradcheck import gradcheck

    targets = list(SCENES) if args.targets == ["all"] else args.targets
    _at_least_one(args, "horizon", "iterations", "entries")
    rtol = args.rtol if args.rtol is not None else (1e-4 if args.x64 else 2e-2)
    if not rtol > 0:
        raise UsageError(f"--rtol must be > 0, got {args.rtol}")
    tolerance = args.tolerance if args.tolerance is not None else (1e-12 if args.x64 else None)
    if tolerance is not None and not tolerance >= 0:
        raise UsageError(f"--tolerance must be >= 0, got {args.tolerance}")
    h = args.step if args.step is not None else (1e-6 if args.x64 else 1e-3)
    if not h > 0:
        raise UsageError(f"--step must be > 0, got {args.step}")
    # fail fast on bad input
    sims, scenarios = [], {}
    for t in targets:
        if t in _task_scenes():  # a manipulation task: its scene, through the expert's contacts
            from twinrl import envs

            env = envs.make(t)
            sims.append(Sim.load(env.mjcf(), frame_skip=int(env.config.frame_skip), name=t,
                                 iterations=args.iterations, gradient=args.gradient,
                                 contacts=args.contacts))
            if args.scenario is None:
                scenarios[t] = env.gradcheck_scenario(args.horizon or 30, seed=args.seed)
        else:
            sims.append(Sim.load(t, iterations=args.iterations, gradient=args.gradient,
                                 contacts=args.contacts))
    if not args.x64:
        report.console.print("[yellow]float32: finite differences are coarse; use --x64 for the "
                             "real check[/yellow]")
    results = []
    for sim in sims:
        t0 = time.perf_counter()
        with report.console.status(f"{sim.name}: compiling and differencing the rollout..."):
            try:
                r = gradcheck(sim, horizon=args.horizon, h=h, rtol=rtol, seed=args.seed,
                              scenario=scenarios.get(sim.name, args.scenario),
                              tolerance=tolerance, settle=args.settle,
                              entries=args.entries)
            except ValueError as e:
                raise UsageError(f"{sim.name}: {e}") from None
        secs = time.perf_counter() - t0
        report.print_table(
            f"gradcheck {sim.name}  T={r.horizon}  {r.dtype}  scenario {r.scenario}  "
            f"(constrained steps {r.constrained_steps}, free {r.free_steps})",
            ["input", "n", "resolved", "noise-lim", "kinks", "max |grad|", "max rel err",
             "max abs err", "fail", "judged"],
            [[g["group"], g["entries"] if g["entries"] == g["entries_total"]
              else f'{g["entries"]} of {g["entries_total"]}', g["resolved"],
              g["noise_limited"], g["kinks"],
              g["max_abs_grad"], g["max_rel_err"], g["max_abs_err"], g["failures"],
              "yes" if g["resolved"] else ("inert" if g["inert"] else "NO")]
             for g in r.groups])
        ok = r.passed_strict if args.strict else r.passed
        verdict = "[green]PASS[/green]" if ok else "[red]FAIL[/red]"
        report.console.print(f"{verdict} {sim.name}: max rel error {r.max_rel_error:.2e} "
                             f"(tol {rtol:g}) over {r.count('resolved')} resolved entries, "
                             f"non-finite {r.nan_count}, failures {len(r.failures)}, "
                             f"{secs:.0f} s")
        if r.unjudged:
            report.console.print(f"[yellow]{unjudged_line(r)}[/yellow]"
                                 + ("" if args.strict else " (--strict fails on this)"))
        report.console.print("")
        summ = r.summary() | {"seconds": secs, "passed": ok}
        results.append(summ)
        if len(sims) > 1:
            report.write_json(args.out / sim.name / "summary.json", summ)

    if len(results) == 1:
        summary = results[0]
    else:
        summary = {"scenes": [{k: v for k, v in s.items() if k != "rows"} for s in results],
                   "max_rel_error": max(s["max_rel_error"] for s in results),
                   "nan_count": sum(s["nan_count"] for s in results),
                   "passed": all(s["passed"] for s in results),
                   "rows": [dict(row, scene=s["scene"]) for s in results for row in s["rows"]]}
        report.print_table("gradcheck summary", ["scene", "max rel err", "non-finite", "pass"],
                           [[s["scene"], s["max_rel_error"], s["nan_count"],
                             "yes" if s["passed"] else "NO"] for s in results])
    path = report.write_json(args.out / "summary.json", summary)
    report.console.print(f"wrote {path}")
    return 0 if all(s["passed"] for s in results) else 1


# ---------------------------------------------------------------------------------- envs
def _envs_parser(sub) -> None:
    p = sub.add_parser("envs", help="list the registered tasks and what their real twins perturb",
                       description="A table of registered tasks: observation and action sizes, "
                                   "contacts, cameras, and how each real twin differs.")
    _common(p, "runs/envs")
    p.set_defaults(func=_cmd_envs)


def _has_contacts(mj_model) -> bool:
    """Whether any two geoms of different bodies can collide (contype/conaffinity)."""
    import itertools

    for i, j in itertools.combinations(range(mj_model.ngeom), 2):
        bi, bj = mj_model.geom_bodyid[i], mj_model.geom_bodyid[j]
        if bi == bj or (bi == 0 and bj == 0):
            continue
        if (mj_model.geom_contype[i] & mj_model.geom_conaffinity[j]) or (
                mj_model.geom_contype[j] & mj_model.geom_conaffinity[i]):
            return True
    return False


def _perturbs(spec) -> str:
    scales = (("mass", spec.mass_scale), ("damping", spec.damping_scale),
              ("friction", spec.friction_scale), ("gain", spec.gain_scale))
    parts = [f"{what} x{lo:g}-{hi:g}" if lo != hi else f"{what} x{lo:g}"
             for what, (lo, hi) in scales if (lo, hi) != (1, 1)]  # untouched: not listed
    parts += [f"+damping {j} {lo:g}-{hi:g}" for j, lo, hi in spec.extra_damping]
    parts += [f"+frictionloss {j} {lo:g}-{hi:g} (unmodeled)" for j, lo, hi in spec.extra_frictionloss]
    parts += [f"latency {set(spec.latency_steps)} steps",
              f"obs noise <= {spec.obs_noise_std[1]:g}",
              f"camera offset sd {spec.camera_pos_std * 100:g} cm / {spec.camera_rot_std:g} rad"]
    if spec.tool_pos_std or spec.tool_rot_std:
        parts.append(f"grasp offset sd {spec.tool_pos_std * 1000:g} mm / {spec.tool_rot_std:g} rad")
    return ", ".join(parts)


def _cmd_envs(args) -> int:
    from twinrl import envs, report

    rows = []
    for name in envs.names():
        env = envs.make(name)
        rows.append({"name": name, "obs_dim": env.observation_size, "action_dim": env.action_size,
                     "dt": env.dt, "episode_length": env.episode_length,
                     "contacts": _has_contacts(env.sim.mj_model), "cameras": list(env.cameras),
                     "reward_terms": list(env.reward_term_names),
                     "real_twin_perturbs": _perturbs(env.perturbation_spec)})
    report.print_table("twinrl tasks", ["name", "obs", "act", "dt", "steps", "contacts",
                                        "cameras", "real twin perturbs"],
                       [[r["name"], r["obs_dim"], r["action_dim"], r["dt"], r["episode_length"],
                         "yes" if r["contacts"] else "no", ",".join(r["cameras"]),
                         r["real_twin_perturbs"]] for r in rows])
    report.write_json(args.out / "summary.json", {"tasks": rows})
    return 0


# ---------------------------------------------------------------------------------- collect
def _collect_parser(sub) -> None:
    p = sub.add_parser(
        "collect", help="record episodes of a real twin into a durable dataset",
        description="Run a policy on a task's real twin and record every transition as it "
                    "happens (a killed run keeps everything but the transition in flight; run "
                    "again on the same --out to append more episodes).")
    p.add_argument("--env", required=True, help="task name (see `twinrl envs`)")
    p.add_argument("--episodes", type=int, required=True, help="episodes to record")
    p.add_argument("--policy", default="excite", choices=("excite", "random", "zero"),
                   help="'excite' (default: random levels, each held 3-15 steps, as sysid's "
                        "excitation: the system travels, so its trajectories and images show it "
                        "in many states; with --observation state the task's closed-loop "
                        "excitation where it has one, as push's strokes), 'random' (uniform in "
                        "the action box every step: it jitters in place) or 'zero'")
    p.add_argument("--images", action="store_true",
                   help="also record RGB, depth and segmentation of the default camera")
    p.add_argument("--size", type=int, nargs=2, default=(64, 64), metavar=("W", "H"),
                   help="image size with --images (default 64 64)")
    p.add_argument("--observation", default="task", choices=("task", "state"),
                   help="what each transition records: 'task' (default: the task's observation, "
                        "what a policy sees) or 'state' (the full qpos and qvel, as a motion-"
                        "capture rig gives them): what `twinrl sysid` needs where the task's "
                        "observation does not determine the state (push)")
    _common(p, "runs/collect")
    p.set_defaults(func=_cmd_collect)


def _cmd_collect(args) -> int:
    import numpy as np
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from twinrl import envs, report
    from twinrl.real import dataset as ds
    from twinrl.real.dataset import DatasetWriter
    from twinrl.real.twin import record_episode
    from twinrl.real2sim.sysid import excitation_actions

    _check_task(args.env)
    _at_least_one(args, "episodes")
    w, h = args.size
    # The real twin runs in its own process, as a robot would (twinrl.real.remote); its hidden
    # perturbation's seed includes a secret salt kept in OUT/eval/, beside the dataset, for
    # evaluation only (`twinrl sysid --visual --twin-seed` reads it).
    from twinrl.real.remote import TwinClient, secret_file

    fresh_out = not args.out.exists()
    full = args.observation == "state"
    twin = TwinClient(args.env, seed=args.seed, secret=secret_file(args.out, args.env, args.seed),
                      width=w, height=h, **({"config": {"observation": "state"}} if full else {}))
    obs, _ = twin.reset(seed=args.seed)
    act_shape = twin.action_space.shape
    image_shapes = None
    if args.images:
        # Rendered once before the dataset is touched, so a size the renderer refuses fails here
        # instead of after meta.json has been written claiming that size.
        from twinrl.real.twin import IMAGE_KINDS

        try:
            twin.render_images(twin.camera, IMAGE_KINDS)
        except ValueError as e:
            twin.close()
            if fresh_out:  # nothing recorded: leave no directory behind (the twin's secret)
                import shutil

                shutil.rmtree(args.out, ignore_errors=True)
            raise UsageError(f"--size {w} {h}: {e}") from None
        image_shapes = {"rgb": (h, w, 3), "depth": (h, w), "segmentation": (h, w)}
    dataset_dir = args.out / "dataset"
    try:
        writer = DatasetWriter(dataset_dir, env=args.env, obs_shape=obs.shape,
                               action_shape=act_shape, image_shapes=image_shapes,
                               obs_dtype=np.float32, action_dtype=np.float32,
                               metadata={"observation": "state"} if full else None)
    except (ValueError, OSError, ds.DatasetError) as e:  # another env, a live writer, ...
        raise UsageError(f"--out {args.out}: {e}") from None
    # full states are for sysid: the task's own closed-loop excitation where it has one (push:
    # held random levels rarely touch the box), as sysid.collect's policy="auto"
    task_excitation = getattr(envs.make(args.env, observation="state"), "excitation_policy",
                              None) if full else None
    returns, steps = [], 0
    first_episode = writer.episode_id
    columns = [TextColumn("[bold]collect"), BarColumn(), MofNCompleteColumn(),
               TextColumn("episodes  return {task.fields[ret]}"), TimeElapsedColumn()]
    try:
        with writer, Progress(*columns, console=report.console) as bar:
            task = bar.add_task("collect", total=args.episodes, ret="-")
            for ep in range(args.episodes):
                # Each episode's randomness is a function of (--seed, its id in the dataset):
                # re-running on the same --out appends new episodes, not copies of the first ones.
                seq = np.random.SeedSequence([args.seed, first_episode + ep])
                obs, _ = twin.reset(seed=int(seq.generate_state(1)[0]))
                rng = np.random.default_rng(seq.spawn(1)[0])
                if args.policy == "excite" and task_excitation is not None:
                    policy = task_excitation(rng)
                elif args.policy == "excite":
                    levels = excitation_actions(rng, twin.episode_length,
                                                int(np.prod(act_shape)))
                    policy = lambda o, t: levels[min(t, len(levels) - 1)].reshape(act_shape)  # noqa: E731
                elif args.policy == "random":
                    policy = lambda o, t: rng.uniform(-1, 1, act_shape)  # noqa: E731
                else:
                    policy = lambda o, t: np.zeros(act_shape)  # noqa: E731
                ret, n = record_episode(twin, writer, policy, obs, images=args.images)
                returns.append(ret)
                steps += n
                bar.update(task, advance=1, ret=f"{ret:.2f}")
    except OSError as e:  # disk full, quota, I/O error: what was recorded before stays readable
        raise UsageError(f"writing {dataset_dir} failed after {len(returns)} complete "
                         f"episode(s) of this run: {e.strerror or e}; the dataset keeps every "
                         f"transition recorded before") from None
    twin.close()
    summary = {"env": args.env, "policy": args.policy, "seed": args.seed,
               "episodes": args.episodes, "first_episode_id": first_episode, "steps": steps,
               "returns": returns, "mean_return": float(np.mean(returns)),
               "dataset": str(args.out / "dataset")}
    report.print_table(f"collected {args.env}", ["episodes", "steps", "mean return", "min", "max"],
                       [[args.episodes, steps, float(np.mean(returns)), float(np.min(returns)),
                         float(np.max(returns))]])
    report.write_json(args.out / "summary.json", summary)
    return 0


# ---------------------------------------------------------------------------------- render
def _render_parser(sub) -> None:
    p = sub.add_parser("render", help="render a task (sim or real twin) to PNGs and a video, "
                                      "or your MJCF with both renderers",
                       description="A task: RGB, depth and segmentation PNGs of the last frame "
                                   "and a video of an open-loop episode of smooth random actions. "
                                   "Your MJCF (--env FILE.xml): one frame drawn by MuJoCo's "
                                   "OpenGL and by twinrl's differentiable renderer side by side "
                                   "(compare.png) and how far they agree (summary.json).")
    p.add_argument("--env", required=True,
                   help="task name (see `twinrl envs`) or the path of your MJCF")
    p.add_argument("--real", action="store_true",
                   help="the real twin (hidden perturbation, camera at its true offset pose)")
    p.add_argument("--steps", type=int, default=None,
                   help="episode steps (default 100); for an MJCF, physics steps without "
                        "actuation from its first keyframe (else qpos0) before the frame "
                        "(default 0)")
    p.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    p.add_argument("--camera", default=None,
                   help="camera name (default: the task's or the MJCF's first; an MJCF without "
                        "one is seen from where MuJoCo's viewer opens)")
    p.add_argument("--gradcheck", action="store_true",
                   help="MJCF only: also check the soft image's gradient w.r.t. the camera and "
                        "every geom's position, size and colour against float64 central "
                        "differences, at 64x48 (exit 1 if a group is off by more than 5 %%)")
    p.add_argument("--layers", type=int, default=None,
                   help="MJCF only: surfaces the soft image composites per pixel "
                        "(Renderer.create's layers, default 8)")
    p.add_argument("--cull-above", type=int, default=None,
                   help="MJCF only: geoms of one type beyond which each pixel tests its nearest "
                        "few (Renderer.create's cull_above, default 8)")
    _common(p, "runs/render")
    p.set_defaults(func=_cmd_render)


def _cmd_render(args) -> int:
    from twinrl import envs, report
    from twinrl.real.twin import render_episode

    _check_size(args.size)
    if args.env.lower().endswith(".xml") or Path(args.env).is_file():
        return _render_mjcf(args)
    for flag in ("gradcheck", "layers", "cull_above"):
        if getattr(args, flag) not in (None, False):
            raise UsageError(f"--{flag.replace('_', '-')} is for your MJCF (--env FILE.xml); "
                             "the tasks' scenes are checked by the test suite")
    _check_task(args.env)
    _at_least_one(args, "steps")
    args.steps = 100 if args.steps is None else args.steps
    with report.console.status(f"rendering {args.env} ({'real twin' if args.real else 'sim'})..."):
        try:
            paths = render_episode(args.env, real=args.real, seed=args.seed, out_dir=args.out,
                                   steps=args.steps, width=args.size[0], height=args.size[1],
                                   camera=args.camera)
        except ValueError as e:  # a size beyond the model's offscreen buffer, a camera name
            if not str(e).startswith(("image size", "camera")):
                raise
            raise UsageError(str(e)) from None
    report.print_table(f"render {args.env}", ["kind", "file"], [[k, str(v)] for k, v in paths.items()])
    report.write_json(args.out / "summary.json", {"env": args.env, "real": args.real,
                                                  "seed": args.seed, "steps": args.steps,
                                                  "files": {k: str(v) for k, v in paths.items()}})
    return 0


def _render_mjcf(args) -> int:
    """``twinrl render --env FILE.xml``: OpenGL and the differentiable renderer side by side."""
    import mujoco

    from twinrl import report
    from twinrl.physics import mujoco_warnings
    from twinrl.render import check
    from twinrl.render.renderer import UnsupportedGeomError

    if args.real:
        raise UsageError("--real is a registered task's real twin; an MJCF has none")
    if args.steps is not None and args.steps < 0:
        raise UsageError(f"--steps must be >= 0, got {args.steps}")
    path = Path(args.env)
    if not path.is_file():
        raise UsageError(f"MJCF file not found: {args.env}")
    settings = {k: v for k, v in (("layers", args.layers), ("cull_above", args.cull_above))
                if v is not None}
    for k, v in settings.items():
        if v < (1 if k == "layers" else 0):
            raise UsageError(f"--{k.replace('_', '-')} must be >= {1 if k == 'layers' else 0}, "
                             f"got {v}")
    try:
        with mujoco_warnings(str(path), stacklevel=2):
            spec = mujoco.MjSpec.from_file(str(path))
            model = spec.compile()
            camera = args.camera or (model.camera(0).name or 0 if model.ncam else None)
            if camera is None:
                model, camera = check.with_view_camera(spec), check.VIEW
    except ValueError as e:  # MuJoCo's parse and compile errors
        raise UsageError(f"--env {args.env}: {' '.join(str(e).split())}") from None
    data = mujoco.MjData(model)
    if model.nkey:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    with mujoco_warnings(f"{path}: {args.steps or 0} steps", stacklevel=2):
        mujoco.mj_step(model, data, nstep=int(args.steps or 0))
        mujoco.mj_forward(model, data)
    args.out.mkdir(parents=True, exist_ok=True)
    with report.console.status(f"rendering {path.name} with OpenGL and twinrl.render..."):
        try:
            result = check.compare(model, data, camera, *args.size, **settings)
        except (UnsupportedGeomError, ValueError) as e:  # hfield/SDF geoms; size; camera name
            raise UsageError(f"--env {args.env}: {e}") from None
        far = float(model.vis.map.zfar * model.stat.extent)
        files = {"compare": check.figure(result, far, args.out / "compare.png",
                                         f"{path.name}, camera {camera!r}")}
    import imageio.v2 as imageio

    for side in ("opengl", "twinrl"):
        files[f"{side}_rgb"] = args.out / f"{side}_rgb.png"
        imageio.imwrite(files[f"{side}_rgb"], result[side]["rgb"])
    grads = None
    if args.gradcheck:
        with report.console.status("the soft image's gradient against central differences "
                                   "(float64, 64x48)..."):
            grads = check.gradcheck(model, data, camera, **settings)
        report.print_table(
            f"render --gradcheck {path.name}: the soft image's gradient against float64 central "
            f"differences (|g - fd| / |fd| per group, tolerance {check.GRAD_RTOL:g})",
            ["group", "entries", "|grad|", "rel err", "ok"],
            [[r["group"], r["entries"], f"{r['grad_norm']:.3g}",
              "inert" if r["inert"] else f"{r['rel_err']:.2e}", "yes" if r["ok"] else "NO"]
             for r in grads])
    f = result["figures"]
    report.print_table(f"render {path.name}: OpenGL against twinrl.render, camera {camera!r}",
                       ["same geom id", "depth |diff| mean / p99 (mm)", "RGB PSNR (dB)",
                        "geoms drawn"],
                       [[f"{100 * f['segmentation_agreement']:.3f} %",
                         "-" if f["depth_mean_abs_m"] is None else
                         f"{1e3 * f['depth_mean_abs_m']:.3f} / {1e3 * f['depth_p99_abs_m']:.2f}",
                         f"{f['rgb_psnr_db']:.1f}", f["geoms_drawn"]]])
    if f["textures"]:
        report.console.print(f"{path.name} has {f['textures']} texture(s); twinrl.render draws "
                             "materials' colours without textures, skyboxes or reflections, so "
                             "the RGB differs there (depth and segmentation do not)")
    report.console.print(f"wrote {files['compare']}")
    report.write_json(args.out / "summary.json", {
        "mjcf": str(path), "camera": camera if isinstance(camera, str) else int(camera),
        "size": list(args.size), "steps": int(args.steps or 0), "renderer": settings,
        "figures": f,
        "gradcheck": grads, "files": {k: str(v) for k, v in files.items()}})
    if grads is not None and not all(r["ok"] for r in grads):
        bad = [r["group"] for r in grads if not r["ok"]]
        c = check.crowding(model, **settings)
        hint = "" if c is None else (f"; {c['why']}: --cull-above {c['cull_above']} --layers "
                                     f"{c['layers']} composites every surface (slower)")
        report.console.print(f"gradcheck FAIL: {', '.join(bad)} off by more than "
                             f"{100 * check.GRAD_RTOL:g} %{hint}")
        return 1
    return 0


# ---------------------------------------------------------------------------------- train
def _train_parser(sub) -> None:
    from twinrl.learn.runner import ALGORITHMS

    p = sub.add_parser(
        "train", help="learn a policy in the simulator (PODS, HDS, SHAC; Brax PPO/APG baselines)",
        description="Train a policy in the differentiable simulator. Writes metrics.csv, "
                    "TensorBoard events (tb/), curve.png, the policy checkpoint (policy/: orbax "
                    "params + checkpoint.json) and summary.json; the training state is saved "
                    "every epoch so --resume continues a killed run to the same result.")
    p.add_argument("--env", required=True,
                   help="task name (see `twinrl envs`), or your MJCF file with --reward")
    p.add_argument("--algo", required=True, choices=list(ALGORITHMS),
                   help="pods, pods2 (second order), hds, shac, imitation (an actor from "
                        "trajopt demonstrations), sensing (the camera-scoring Q of an image "
                        "actor), or the baselines ppo, apg")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--epochs", type=int, default=None,
                        help="epochs (pods/pods2/hds/shac; default: the tuned value)")
    length.add_argument("--steps", type=int, default=None,
                        help="environment steps (ppo/apg; default: the tuned value)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="override a config field (JSON value; dotted for nested fields), "
                        "repeatable, e.g. --set lr=3e-4 --set trajopt.order=2")
    p.add_argument("--resume", action="store_true",
                   help="continue the killed run in --out from its last saved epoch")
    mjcf = p.add_argument_group("your MJCF (--env FILE.xml; envs.from_mjcf)")
    mjcf.add_argument("--reward", metavar="FILE.py:FUNCTION",
                      help="the reward: a function (qpos, qvel, action) -> scalar or dict of "
                           "terms, in jax.numpy (or module:FUNCTION)")
    mjcf.add_argument("--reset-noise", type=float, default=0.0,
                      help="uniform +- noise on every qpos and qvel entry at reset (default 0)")
    mjcf.add_argument("--episode-length", type=int, default=None,
                      help="control steps per episode (default 1000)")
    mjcf.add_argument("--frame-skip", type=int, default=None,
                      help="physics steps per control step (default 1)")
    _common(p, "runs/train")
    p.set_defaults(func=_cmd_train)


def _mjcf_task(args):
    """``twinrl train --env FILE.xml --reward ...``'s task and its spec (``envs.mjcf``), or
    (None, None) for a registered task name (where the MJCF options are refused)."""
    from twinrl import envs
    from twinrl.envs.mjcf import load_reward, task_spec

    own = ("reward", "episode_length", "frame_skip")
    if not str(args.env).lower().endswith(".xml"):
        given = [f"--{k.replace('_', '-')}" for k in own if getattr(args, k) is not None]
        if args.reset_noise:
            given.append("--reset-noise")
        if given:
            raise UsageError(f"{', '.join(given)}: for your MJCF (--env FILE.xml); task "
                             f"{args.env!r} has its own")
        return None, None
    if not Path(args.env).is_file():
        raise UsageError(f"--env {args.env}: no such MJCF file")
    if args.reward is None:
        raise UsageError(f"--env {args.env}: an MJCF has no reward; give --reward "
                         f"FILE.py:FUNCTION (a function (qpos, qvel, action) -> reward)")
    _at_least_one(args, "episode_length", "frame_skip")
    if not (args.reset_noise >= 0 and math.isfinite(args.reset_noise)):
        raise UsageError(f"--reset-noise must be a finite value >= 0, got {args.reset_noise}")
    config = {k: getattr(args, k) for k in ("episode_length", "frame_skip")
              if getattr(args, k) is not None}
    try:
        env = envs.from_mjcf(args.env, reward=load_reward(args.reward),
                             reset_noise=args.reset_noise, **config)
    except (ValueError, TypeError) as e:
        raise UsageError(str(e).splitlines()[0]) from None
    return env, task_spec(env, args.reward)


def _cmd_train(args) -> int:
    from twinrl import report
    from twinrl.learn.runner import parse_overrides, train_run

    env, spec = _mjcf_task(args)
    if env is None:
        _check_task(args.env)
    _at_least_one(args, "epochs", "steps")
    s = train_run(env.name if env is not None else args.env, args.algo, args.out,
                  seed=args.seed, epochs=args.epochs, steps=args.steps,
                  overrides=parse_overrides(args.set), resume=args.resume, env=env,
                  env_spec=spec)
    f = s["final"]
    report.print_table(f"trained {args.algo} on {args.env}",
                       ["epochs", "env steps", "final return", "best return", "wall s"],
                       [[s["epochs"], f.get("env_steps"), f.get("return"), s["best_return"],
                         f.get("wall_s")]])
    return 0


# ---------------------------------------------------------------------------------- eval
def _eval_parser(sub) -> None:
    p = sub.add_parser("eval", help="evaluate a policy checkpoint in sim or in the real twin",
                       description="Deterministic episodes of a trained policy; writes "
                                   "summary.json (returns) and a video of the first episode.")
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="a policy checkpoint (or the --out of `twinrl train`)")
    p.add_argument("--real", action="store_true",
                   help="run on the task's real twin (MuJoCo C, hidden perturbation for --seed)")
    p.add_argument("--episodes", type=int, default=5, help="episodes (default 5)")
    p.add_argument("--no-video", action="store_true", help="skip the video")
    p.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    _common(p, "runs/eval")
    p.set_defaults(func=_cmd_eval)


def _cmd_eval(args) -> int:
    from twinrl.learn.runner import eval_run

    if not args.checkpoint.exists():
        raise UsageError(f"checkpoint {args.checkpoint} does not exist")
    _at_least_one(args, "episodes")
    _check_size(args.size)
    eval_run(args.checkpoint, args.out, real=args.real, episodes=args.episodes, seed=args.seed,
             video=not args.no_video, size=tuple(args.size))
    return 0


# ---------------------------------------------------------------------------------- sysid
def _sysid_parser(sub) -> None:
    p = sub.add_parser(
        "sysid", help="Real2Sim: identify the simulator from a recorded dataset",
        description="From transitions recorded by `twinrl collect`, fit PhysParams and the action "
                    "latency by multiple shooting through the simulator (report table with "
                    "uncertainty and identifiability); with --visual, fit the camera and the "
                    "task's object to the recorded RGB-D + segmentation frames instead. With "
                    "--env ROBOT.xml, fit your own MJCF to your qpos/qvel/ctrl log (.npz) and "
                    "write OUT/identified.xml.")
    p.add_argument("--env", required=True,
                   help="task name (see `twinrl envs`), or the path of your robot's MJCF "
                        "(`twinrl.envs.from_mjcf`: its full state observed; --from then takes "
                        "an .npz log)")
    p.add_argument("--from", dest="source", required=True, type=Path,
                   help="dataset directory (`twinrl collect --out DIR` writes DIR/dataset); with "
                        "an MJCF, an .npz with qpos (E, T+1, nq), qvel (E, T+1, nv) and the "
                        "controls sent between them ctrl (E, T, nu), in the actuators' units, "
                        "sampled every --frame-skip physics steps")
    p.add_argument("--param", action="append", default=[], metavar="NAME",
                   help="a parameter to fit, repeatable (default: every mass, damping, friction "
                        "loss and gain), e.g. --param mass/upper; an unknown name lists them")
    p.add_argument("--max-latency", type=int, default=None,
                   help="largest action latency tried, in samples (default: SysidConfig's, 1)")
    p.add_argument("--frame-skip", type=int, default=None,
                   help="with an MJCF: physics steps of its timestep per logged sample "
                        "(default 1)")
    p.add_argument("--visual", action="store_true",
                   help="visual Real2Sim from the dataset's images (needs `collect --images`)")
    p.add_argument("--known", action="append", default=[], metavar="PARAM=VALUE",
                   help="a parameter known from elsewhere, e.g. --known mass/cart=1.05 (fixes the "
                        "common scale that trajectories cannot)")
    p.add_argument("--window", type=int, default=None,
                   help="shooting window, steps (default: SysidConfig's, 20)")
    p.add_argument("--frames", type=int, default=12,
                   help="frames used with --visual, evenly spread over the dataset (default 12: the "
                        "camera's yaw and sideways position are fixed only by where the moving "
                        "objects appear, so they need views of them in many places)")
    p.add_argument("--twin-seed", type=int, default=None,
                   help="evaluation only, with --visual: the seed of the real twin the dataset "
                        "was recorded on (`collect --seed`); adds the errors against its hidden "
                        "camera and object to summary.json")
    _common(p, "runs/sysid")
    p.set_defaults(func=_cmd_sysid)


def _cmd_sysid(args) -> int:
    from twinrl import envs, report
    from twinrl.real import dataset as ds

    if args.env.lower().endswith(".xml") or Path(args.env).is_file():
        return _sysid_mjcf(args)
    _check_task(args.env)
    if args.frame_skip is not None:
        raise UsageError("--frame-skip is for an MJCF's log; a task's dataset is sampled at the "
                         "task's own control period")
    source = args.source
    if not (source / "meta.json").exists() and (source / "dataset" / "meta.json").exists():
        source = source / "dataset"
    if not (source / "meta.json").exists():
        raise UsageError(f"--from {args.source}: no dataset there (no meta.json)")
    try:
        data = ds.read(source, strict=False)
    except ds.DatasetError as e:  # no dataset there, or its meta.json is unreadable
        raise UsageError(f"--from {source}: {e}") from None
    if data.problems:  # damage costs the records it hit; the fit uses every intact one
        more = f" (and {len(data.problems) - 1} more)" if len(data.problems) > 1 else ""
        print(f"twinrl sysid: warning: dataset damaged, using its {len(data)} intact "
              f"transitions: {data.problems[0]}{more}", file=sys.stderr)
    if data.meta.get("env") not in (None, args.env):
        raise UsageError(f"--from {source} was recorded on {data.meta.get('env')!r}, "
                         f"not {args.env!r}")
    if args.twin_seed is not None and not args.visual:
        raise UsageError("--twin-seed evaluates a visual fit: use it with --visual")
    if args.visual:
        from twinrl.real2sim.visual import visual_sysid

        if not data.images:
            raise UsageError(f"--from {source} holds no images: record with "
                             f"`twinrl collect --images`")
        summary = visual_sysid(args.env, data, args.out, seed=args.seed, n_frames=args.frames)
        if args.twin_seed is not None:
            from twinrl.eval import visual_errors
            from twinrl.real.remote import secret_file

            # `twinrl collect` keeps the twin's secret beside the dataset (evaluation only)
            secret = secret_file(source.parent, args.env, args.twin_seed)
            summary["evaluation"] = {"twin_seed": args.twin_seed, **visual_errors(
                args.env, args.twin_seed, summary, secret if secret.exists() else None)}
            report.print_table(f"evaluation only: errors against real twin seed {args.twin_seed}",
                               ["error", "value"],
                               [[k, v] for k, v in summary["evaluation"].items()
                                if k != "twin_seed"])
            report.write_json(args.out / "summary.json", summary)
        return 0
    recorded = (data.meta.get("metadata") or {}).get("observation", "task")
    env = envs.make(args.env, **({"observation": "state"} if recorded == "state" else {}))
    if not env.observes_state:
        raise UsageError(f"--from {source}: {args.env}'s observation does not determine its "
                         f"state, so sysid cannot start a simulated window from it; record full "
                         f"states: twinrl collect --env {args.env} --observation state ...")
    _fit_and_report(args, env, data, len(data), source)
    return 0


def _sysid_config(args):
    from twinrl.real2sim import sysid

    known = []
    for item in args.known:
        name, _, value = item.partition("=")
        try:
            known.append((name.strip(), float(value)))
        except ValueError:
            raise UsageError(f"--known {item!r} must look like PARAM=NUMBER") from None
    _at_least_one(args, "window")
    if args.max_latency is not None and args.max_latency < 0:
        raise UsageError(f"--max-latency must be >= 0, got {args.max_latency}")
    over = {k: v for k, v in (("window", args.window), ("max_latency", args.max_latency))
            if v is not None}
    if args.param:
        over["params"] = tuple(args.param)
    return sysid.SysidConfig(known=tuple(known), **over)


def _sysid_mjcf(args) -> int:
    """``twinrl sysid --env ROBOT.xml --from LOG.npz``: Real2Sim on a user's MJCF and logs."""
    import numpy as np

    from twinrl import envs

    if args.visual or args.twin_seed is not None:
        raise UsageError("--visual and --twin-seed fit a registered task's camera and object; "
                         "an MJCF's sysid takes its qpos/qvel/ctrl log")
    _at_least_one(args, "frame_skip")
    try:  # an MJCF MJX cannot simulate, an actuator without a ctrlrange
        env = envs.from_mjcf(args.env, frame_skip=args.frame_skip or 1)
    except ValueError as e:
        raise UsageError(str(e)) from None
    if not args.source.is_file():
        raise UsageError(f"--from {args.source}: no such file (an MJCF's sysid takes an .npz "
                         f"with qpos, qvel and ctrl)")
    try:
        with np.load(args.source) as z:
            missing = [k for k in ("qpos", "qvel", "ctrl") if k not in z.files]
            if missing:
                raise UsageError(f"--from {args.source}: no {', '.join(missing)} array (it has "
                                 f"{', '.join(z.files) or 'none'})")
            qpos, qvel, ctrl = z["qpos"], z["qvel"], z["ctrl"]
    except (OSError, ValueError) as e:  # not an .npz, a pickled object array, ...
        raise UsageError(f"--from {args.source}: not a readable .npz ({e})") from None
    try:
        data = env.transitions(qpos, qvel, ctrl)
    except ValueError as e:
        raise UsageError(f"--from {args.source}: {e}") from None
    summary, res = _fit_and_report(args, env, data, int(np.prod(data["action"].shape[:2])),
                                   args.source)
    from twinrl import report
    from twinrl.envs.mjcf import save_mjcf

    summary["mjcf"] = str(save_mjcf(env, res.params, args.out / "identified.xml"))
    report.write_json(args.out / "summary.json", summary)
    report.console.print(f"identified MJCF: {summary['mjcf']}")
    return 0


def _fit_and_report(args, env, data, transitions: int, source):
    """sysid's fit, its table and ``OUT/summary.json``: ``(summary, result)``."""
    from twinrl import report
    from twinrl.real2sim import sysid

    try:
        config = _sysid_config(args)
        with report.console.status(f"sysid on {transitions} transitions ..."):
            res = sysid.fit(env, data, config)
    except ValueError as e:
        raise UsageError(str(e)) from None
    sysid.print_result(res, title=f"sysid {env.name}")
    summary = {
        "env": args.env, "dataset": str(source), "transitions": transitions,
        "latency": res.latency, "loss": res.loss, "sim_rollouts": res.sim_rollouts,
        "seconds": res.seconds, "table": res.table,
        "params": {k: v.tolist() for k, v in res.params.as_dict().items()}}
    report.write_json(args.out / "summary.json", summary)
    return summary, res


# ---------------------------------------------------------------------------------- run
def _run_parser(sub) -> None:
    p = sub.add_parser(
        "run", help="the whole loop: Real2Sim -> Learn@Sim -> Sim2Real on a task's real twin",
        description="Round 0 records exciting episodes on the real twin; each round then "
                    "identifies the simulator (sysid), refits the hybrid dynamics, learns in sim "
                    "(--algo), and deploys with residual adaptation, recording the real episodes. "
                    "Writes summary.json, report.md, returns.png, params.png and final.mp4; "
                    "--resume continues a killed run without losing recorded data. On a "
                    "manipulation task (peg_insertion, needle_threading, spatula_flipping) it "
                    "runs the SAM-RL loop instead: round 0 records episodes with images; each "
                    "round calibrates the camera mount from them, plans demonstrations in the "
                    "identified twin, clones an image actor, learns the sensing-aware Q and "
                    "deploys with the camera Q chooses (summary.json, success.png, final.mp4).")
    p.add_argument("--env", default="cartpole_swingup",
                   help="task name (default cartpole_swingup)")
    p.add_argument("--rounds", type=int, default=None, help="rounds after round 0 (default 1)")
    p.add_argument("--episodes-per-round", type=int, default=None,
                   help="real episodes recorded per round (default 2)")
    p.add_argument("--algo", default=None,
                   help="learner in sim (default ppo; shac and hds learn through the "
                        "simulator's gradients, hds mixes in the hybrid model)")
    p.add_argument("--epochs", type=int, default=None,
                   help="training epochs per round (default: tuned per task)")
    p.add_argument("--no-oracle", action="store_true",
                   help="skip the oracle policy (evaluation only; saves a training run)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="manipulation tasks: a setting of the SAM-RL loop (twinrl.loop_arm."
                        "ArmLoopConfig), repeatable, e.g. --set demonstrations=16 --set "
                        "imitation.fit_steps=1000 --set camera=default")
    p.add_argument("--resume", action="store_true", help="continue a killed run in --out")
    _common(p, "runs/loop")
    p.set_defaults(func=_cmd_run)


def _cmd_run(args) -> int:
    from twinrl.loop import LoopConfig, LoopError, run
    from twinrl.loop.arm import is_arm_task

    _check_task(args.env, MJCF_RUN_HINT)
    if is_arm_task(args.env):
        return _run_arm(args)
    if args.set:
        raise UsageError("--set configures the manipulation loop (peg_insertion, "
                         "needle_threading, spatula_flipping); use --rounds, --algo, ... here")
    overrides = {k: v for k, v in (("rounds", args.rounds),
                                   ("episodes_per_round", args.episodes_per_round),
                                   ("algo", args.algo), ("epochs", args.epochs)) if v is not None}
    if args.no_oracle:
        overrides["oracle"] = False
    try:
        config = LoopConfig(**overrides)
        run(args.env, args.out, config, seed=args.seed, resume=args.resume)
    except LoopError as e:
        raise UsageError(str(e)) from None
    return 0


def _run_arm(args) -> int:
    """``twinrl run`` on a manipulation task: the SAM-RL loop (``twinrl.loop_arm``)."""
    from twinrl.learn.runner import RunError, parse_overrides
    from twinrl.loop import LoopError
    from twinrl.loop import arm as loop_arm

    for flag, value in (("--algo", args.algo), ("--epochs", args.epochs)):
        if value is not None:
            raise UsageError(f"{flag} is the state-based loop's; the manipulation loop learns an "
                             f"image actor by imitation (see --set imitation.FIELD=VALUE)")
    try:
        overrides = parse_overrides(args.set)
        for k, v in (("rounds", args.rounds), ("episodes_per_round", args.episodes_per_round)):
            if v is not None:
                overrides[k] = v
        if args.no_oracle:
            overrides["eval_episodes"] = 0
        config = loop_arm.make_config(overrides)
        loop_arm.run(args.env, args.out, config, seed=args.seed, resume=args.resume)
    except (LoopError, RunError) as e:
        raise UsageError(str(e)) from None
    return 0


# ---------------------------------------------------------------------------------- sense
def _sense_parser(sub) -> None:
    p = sub.add_parser(
        "sense", help="choose the camera pose by gradient ascent of the sensing-aware Q",
        description="For the start state reset(--seed) of a manipulation task, choose the mount "
                    "camera's pose by gradient ascent of Q(image(pose), actor(image(pose))) "
                    "through the differentiable renderer (a `twinrl train --algo sensing` run). "
                    "Writes sense.png (Q over the workspace, the ascents, the views from the "
                    "default and the chosen pose), views.png (the actor's 64x64 images) and "
                    "summary.json (the chosen pose, Q, steps the mount needs to get there).")
    p.add_argument("--env", required=True, help="task name (see `twinrl envs`)")
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="a `twinrl train --algo sensing` run (or its policy/)")
    p.add_argument("--restarts", type=int, default=None,
                   help="ascents from the default and random poses (default: Q's config)")
    p.add_argument("--steps", type=int, default=None, help="Adam steps per ascent")
    _common(p, "runs/sense")
    p.set_defaults(func=_cmd_sense)


def _cmd_sense(args) -> int:
    from twinrl import report
    from twinrl.sense import sense

    _check_task(args.env)
    _at_least_one(args, "restarts", "steps")
    if not args.checkpoint.exists():
        raise UsageError(f"checkpoint {args.checkpoint} does not exist")
    with report.console.status("choosing the camera pose ...") as status:
        s = sense(args.env, args.checkpoint, args.out, seed=args.seed, restarts=args.restarts,
                  steps=args.steps, progress=status.update)
    p = s["chosen_pose"]
    report.print_table(f"sense {args.env} (start state seed {args.seed})",
                       ["pose", "azimuth", "elevation", "distance", "Q", "target px"],
                       [["default", s["default_pose"]["azimuth_rad"],
                         s["default_pose"]["elevation_rad"], s["default_pose"]["distance_m"],
                         s["q_default"], s["target_pixels_160"]["default"]],
                        ["chosen", p["azimuth_rad"], p["elevation_rad"], p["distance_m"],
                         s["q_chosen"], s["target_pixels_160"]["chosen"]]])
    print(f"wrote {s['files']['plot']} (mount moves {s['steps_to_move']} steps)")
    return 0


# ---------------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twinrl",
        description="Robot learning through differentiable digital twins "
                    "(Real2Sim -> Learn@Sim -> Sim2Real).")
    parser.add_argument("--verbose", "-v", action="store_true",
                        help="show the XLA/absl runtime log (warnings and errors, e.g. about "
                             "executables loaded from the compilation cache), hidden by default")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _envs_parser(sub)
    _collect_parser(sub)
    _render_parser(sub)
    _gradcheck_parser(sub)
    _run_parser(sub)
    _sysid_parser(sub)
    _train_parser(sub)
    _eval_parser(sub)
    _sense_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from twinrl import _jaxconfig
    from twinrl.learn.checkpoint import CheckpointError
    from twinrl.learn.imitation import DemonstrationError
    from twinrl.learn.runner import RunError
    from twinrl.learn.sensing import SensingError
    from twinrl.physics import MJCFError, PhysParamsError
    from twinrl.real.dataset import DatasetError

    if args.verbose:
        _jaxconfig.set_verbose()
    _one_line_warnings(f"twinrl {args.command}")
    try:
        return args.func(args)
    except (UsageError, MJCFError, PhysParamsError, DatasetError, FileNotFoundError, RunError,
            CheckpointError, DemonstrationError, SensingError) as e:
        print(f"twinrl {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"twinrl {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
