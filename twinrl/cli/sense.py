"""``twinrl sense``: choose the mount camera's pose by gradient ascent of a sensing-aware Q
(``twinrl.sense``)."""

from __future__ import annotations

from pathlib import Path

from twinrl.cli.common import UsageError, add_common, at_least_one, check_task


def add_parser(sub) -> None:
    """The ``sense`` sub-command's parser."""
    p = sub.add_parser(
        "sense", help="choose the camera pose by gradient ascent of the sensing-aware Q",
        description="For the start state reset(--seed) of a manipulation task, choose the mount "
                    "camera's pose by gradient ascent of Q(image(pose), actor(image(pose))) "
                    "through the differentiable renderer (a `twinrl train --algo sensing` run). "
                    "Writes sense.png (Q over the workspace, the ascents, the views from the "
                    "default and the chosen pose, and under each the actor's saliency: "
                    "|d action / d pixel| over the RGB-D image), views.png (the actor's images), "
                    "saliency.png (each view beside its saliency) and summary.json (the chosen "
                    "pose, Q, steps the mount needs to get there).")
    p.add_argument("--env", required=True, help="task name (see `twinrl envs`)")
    p.add_argument("--checkpoint", required=True, type=Path,
                   help="a `twinrl train --algo sensing` run (or its policy/), or a `twinrl run` "
                        "of a manipulation task (its last round's q/) or one of its rounds")
    p.add_argument("--restarts", type=int, default=None,
                   help="ascents from the default and random poses (default: Q's config)")
    p.add_argument("--steps", type=int, default=None, help="Adam steps per ascent")
    add_common(p, "runs/sense")
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    """Choose the camera pose for the start state reset(``--seed``)."""
    from twinrl import report
    from twinrl.loop.checkpoints import sensing_q
    from twinrl.sense import sense

    check_task(args.env)
    at_least_one(args, "restarts", "steps")
    if not args.checkpoint.exists():
        raise UsageError(f"checkpoint {args.checkpoint} does not exist")
    checkpoint = sensing_q(args.checkpoint)
    with report.console.status("choosing the camera pose ...") as status:
        s = sense(args.env, checkpoint, args.out, seed=args.seed, restarts=args.restarts,
                  steps=args.steps, progress=status.update)
    p = s["chosen_pose"]
    report.print_table(f"sense {args.env} (start state seed {args.seed})",
                       ["pose", "azimuth", "elevation", "distance", "Q", "target px",
                        "saliency on target"],
                       [["default", s["default_pose"]["azimuth_rad"],
                         s["default_pose"]["elevation_rad"], s["default_pose"]["distance_m"],
                         s["q_default"], s["target_pixels_160"]["default"],
                         s["saliency_target_share"]["default"]],
                        ["chosen", p["azimuth_rad"], p["elevation_rad"], p["distance_m"],
                         s["q_chosen"], s["target_pixels_160"]["chosen"],
                         s["saliency_target_share"]["chosen"]]])
    print(f"wrote {s['files']['plot']} and {s['files']['saliency']} (mount moves "
          f"{s['steps_to_move']} steps)")
    return 0

