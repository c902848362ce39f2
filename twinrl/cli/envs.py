"""``twinrl envs``: the registered tasks and how their real twins differ, as a table and
``OUT/summary.json``."""

from __future__ import annotations

from twinrl.cli.common import add_common


def add_parser(sub) -> None:
    """The ``envs`` sub-command's parser."""
    p = sub.add_parser("envs", help="list the registered tasks and what their real twins perturb",
                       description="A table of registered tasks: observation and action sizes, "
                                   "contacts, cameras, and how each real twin differs.")
    add_common(p, "runs/envs")
    p.set_defaults(func=cmd)


def cmd(args) -> int:
    """List the tasks (``twinrl.envs.catalog``)."""
    from twinrl import envs, report
    from twinrl.envs.catalog import describe

    rows = [describe(name) for name in envs.names()]
    report.print_table("twinrl tasks", ["name", "obs", "act", "dt", "steps", "contacts",
                                        "cameras", "real twin perturbs"],
                       [[r["name"], r["obs_dim"], r["action_dim"], r["dt"], r["episode_length"],
                         "yes" if r["contacts"] else "no", ",".join(r["cameras"]),
                         r["real_twin_perturbs"]] for r in rows])
    report.write_json(args.out / "summary.json", {"tasks": rows})
    return 0
