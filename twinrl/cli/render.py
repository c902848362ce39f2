"""``twinrl render``: a task's episode (sim or real twin) as PNGs and a video
(``twinrl.real.twin.render_episode``), or your MJCF drawn by OpenGL and by the differentiable
renderer side by side (``twinrl.render.check.check_mjcf``)."""

from __future__ import annotations

from pathlib import Path

from twinrl.cli.common import UsageError, add_common, at_least_one, check_size, check_task, is_mjcf


def add_parser(sub) -> None:
    """The ``render`` sub-command's parser."""
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
    p.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"),
                   help="image size (default 320 240)")
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
    add_common(p, "runs/render")
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    """Render ``--env``: a task's episode, or an MJCF with both renderers."""
    from twinrl import report
    from twinrl.real.twin import render_episode

    check_size(args.size)
    if is_mjcf(args.env):
        return _render_mjcf(args)
    for flag in ("gradcheck", "layers", "cull_above"):
        if getattr(args, flag) not in (None, False):
            raise UsageError(f"--{flag.replace('_', '-')} is for your MJCF (--env FILE.xml); "
                             "the tasks' scenes are checked by the test suite")
    check_task(args.env)
    at_least_one(args, "steps")
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
    from twinrl import report
    from twinrl.render import check

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
    with report.console.status(f"loading {path.name}...") as status:
        try:
            summary, model = check.check_mjcf(path, args.out, *args.size, camera=args.camera,
                                              steps=args.steps or 0,
                                              with_gradcheck=args.gradcheck,
                                              progress=status.update, **settings)
        except check.SceneError as e:
            raise UsageError(f"--env {args.env}: {e}") from None
    grads, f, camera = summary["gradcheck"], summary["figures"], summary["camera"]
    if grads is not None:
        report.print_table(
            f"render --gradcheck {path.name}: the soft image's gradient against float64 central "
            f"differences (|g - fd| / |fd| per group, tolerance {check.GRAD_RTOL:g})",
            ["group", "entries", "|grad|", "rel err", "ok"],
            [[r["group"], r["entries"], f"{r['grad_norm']:.3g}",
              "inert" if r["inert"] else f"{r['rel_err']:.2e}", "yes" if r["ok"] else "NO"]
             for r in grads])
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
    report.console.print(f"wrote {summary['files']['compare']}")
    report.write_json(args.out / "summary.json", summary)
    if grads is not None and not all(r["ok"] for r in grads):
        bad = [r["group"] for r in grads if not r["ok"]]
        c = check.crowding(model, **settings)
        hint = "" if c is None else (f"; {c['why']}: --cull-above {c['cull_above']} --layers "
                                     f"{c['layers']} composites every surface (slower)")
        report.console.print(f"gradcheck FAIL: {', '.join(bad)} off by more than "
                             f"{100 * check.GRAD_RTOL:g} %{hint}")
        return 1
    return 0
