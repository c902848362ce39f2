"""How well a loop's sensing-aware Q ranks camera poses, on many fresh simulated states.

The Q stage reports its ranking on the states it held out: a fifth of ``SensingConfig.states``
(6 of the loop's 32), each Spearman's correlation over 8 poses, so its mean moves by about
+-0.15 from one draw of states to the next. Here, for each ``--run TASK=DIR`` (a ``twinrl run``
output directory: its last round's actor, Q and identified twin), ``--states`` start states that
no stage saw (keys from ``--key``) x ``--cameras`` poses uniform over the mount's workspace, the
actor's episodes in the identified twin (``sensing.sensing_data``, the same examples and target
as Q's training), and:

- ``rank_corr``: the mean over states of Spearman's correlation between Q and the target across
  the poses of a state (the issue's "rank correlation between Q and the measured outcome of
  (camera, action) pairs", per state: what a camera choice needs), with a bootstrap 95 % interval
  over states; ``rank_corr_pooled``, over all (state, pose) pairs;
- the target and success at Q's preferred pose among the sampled ones, against their mean;
- ``choice_raises_q``: on the first ``--choices`` states, how often the gradient ascent through
  the renderer (``select_camera``, Q's own settings) ends above Q at the default pose (its
  choice among all restarts, by its score: Q averaged around the pose where
  ``SensingConfig.smooth_samples`` > 0; ``choice_raises_q_at_pose``: by Q at the pose itself),
  and ``default_ascent_raises_q``: how often the one ascent that
  starts at the default pose passes it (its best hard-image score past the start).

``--retest EPS`` runs the actor again from every pose moved by EPS of its ranges' widths (0.01:
about half a degree, a few millimetres) and reports how well the outcome there ranks the outcome
at the pose itself, per state (``retest_rank_corr``): the ranking Q could reach if it knew the
exact outcome one small camera move away, i.e. how much of a state's ranking is a smooth
function of the pose at all.

``--retrain FIELD=VALUE ...`` (``SensingConfig`` fields, e.g. ``states=64``) first trains a new Q
for the run's actor in its identified twin with those settings over the loop's own (same seed as
the loop's Q stage), and measures that one instead: what more data or another network would give,
on the same fresh states.

Prints a table and writes ``DIR/q_rank.json`` (``--out DIR``).

    python bench/q_rank.py --run needle_threading=runs/needle --states 40 --out bench/results
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, jaxconfig)
import jax
import jax.numpy as jnp
import numpy as np

from twinrl import envs
from twinrl.report import print_table
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)


def parse_run(item: str) -> tuple[str, Path]:
    """``--run``'s ``TASK=DIR`` (a finished ``twinrl run`` directory), or a one-line exit."""
    task, sep, path = item.partition("=")
    if not sep or task not in envs.registry.TASKS:
        raise SystemExit(f"--run takes TASK=DIR; got {item!r}")
    if not (Path(path) / "summary.json").exists():
        raise SystemExit(f"--run {item}: no finished twinrl run there")
    return task, Path(path)


def evaluate_runs(args, evaluate, name: str) -> list[dict]:
    """``evaluate(task, run, args)`` of each ``--run TASK=DIR`` (all checked first), the rows
    written to ``args.out / name`` after each run, so a run that fails keeps the others'."""
    runs = [parse_run(item) for item in args.run]
    rows = []
    for task, run in runs:
        rows.append(evaluate(task, run, args))
        write_result(args.out / name, {"rows": rows}, args)
    return rows


def load_run(task: str, run: Path):
    """A run's last round: ``(summary, env, actor, actor_params, q, q_params, config)``, the
    env being the task in the round's identified twin and ``config`` Q's ``SensingConfig``."""
    from twinrl.envs.system import System
    from twinrl.learn import sensing
    from twinrl.loop.arm import run_env
    from twinrl.sense import load_q

    summary = json.loads((run / "summary.json").read_text())
    if summary.get("env") != task:
        raise SystemExit(f"--run {task}={run}: that run is on {summary.get('env')!r}")
    rdir = run / f"round{summary['final']['round']}"
    env = run_env(run, System.load(rdir / "system.json"))  # at the run's image size
    actor, ap, _ = sensing.load_actor(rdir / "actor")
    q, qp, meta = load_q(rdir / "q")
    return summary, env, actor, ap, q, qp, sensing.SensingConfig.from_dict(
        meta.get("config") or {})


def evaluate(task: str, run: Path, args) -> dict:
    from twinrl.learn import sensing
    from twinrl.learn.camera_choice import select_camera, uniform_coords

    summary, env, actor, ap, q, qp, cfg = load_run(task, run)
    t0 = time.perf_counter()
    if args.retrain:
        cfg = sensing.SensingConfig.from_dict({**cfg.to_dict(), **args.retrain})
        q, qp, _ = sensing.train(env, cfg, summary.get("seed", 0) + summary["final"]["round"],
                                 actor=(actor, ap))
    train_s = time.perf_counter() - t0
    k_states, k_cams, k_choice = jax.random.split(jax.random.PRNGKey(args.key), 3)
    keys = jax.random.split(k_states, args.states)
    coords = uniform_coords(env.mount, k_cams, (args.states, args.cameras))
    data = sensing.sensing_data(env, actor, ap, cfg, keys, coords)
    pred = sensing.q_predictions(q, qp, data)
    figures = sensing.evaluate_ranking(q, qp, data, pred)
    per_state = sensing.rank_corr_per_state(pred, np.asarray(data.targets))
    boot = np.random.default_rng(0).choice(per_state, (10_000, len(per_state))).mean(1)
    choose = jax.jit(lambda s, k: select_camera(env, q, qp, actor, ap, s, k, cfg))
    reset = jax.jit(env.reset)
    sels = [choose(reset(keys[i]), k) for i, k in enumerate(
        jax.random.split(k_choice, min(args.choices, args.states)))]
    gains = np.asarray([float(sel.value) - float(sel.default_value) for sel in sels])
    # the choice's hard-image Q at the pose itself (not averaged around it) against the default's
    raw_gains = np.asarray([float(np.asarray(sel.checked_values).reshape(-1)[int(sel.chosen)])
                            - float(np.asarray(sel.checked_values)[0, 0]) for sel in sels])
    # the ascent that starts at the default pose, alone: its best scored iterate past the start
    from_default = np.asarray([float(np.max(np.asarray(sel.checked_values)[1:, 0]))
                               - float(np.asarray(sel.checked_values)[0, 0]) for sel in sels])
    retest = retest_figures(env, actor, ap, cfg, keys, coords, data, pred, args.retest)
    scored = score_figures(env, actor, ap, q, qp, cfg, keys, coords, data)
    out = {"task": task, "run": str(run), "twin_seed": summary.get("seed"),
           "states": args.states, "cameras": args.cameras, **figures,
           "rank_corr_ci95": np.percentile(boot, [2.5, 97.5]).tolist(),
           "rank_corr_per_state": per_state.tolist(),
           "loop_rank_corr": summary["final"].get("q_rank_corr"),
           "retrain": dict(args.retrain), "train_s": train_s,
           "choice_raises_q": _share(gains > 0), "choices": len(gains),
           "choice_raises_q_at_pose": _share(raw_gains > 0),
           "default_ascent_raises_q": _share(from_default > 0),
           "choice_q_gain": float(np.mean(gains)) if len(gains) else None,
           **retest, **scored, "wall_s": time.perf_counter() - t0}
    print(f"[bench] {task} {run.name}: rank {out['rank_corr']:.2f} "
          f"({out['rank_corr_ci95'][0]:.2f} .. {out['rank_corr_ci95'][1]:.2f}), ascent raises Q "
          f"on {_pct(out['choice_raises_q'])} (from the default pose alone "
          f"{_pct(out['default_ascent_raises_q'])}) ({out['wall_s']:.0f} s)", flush=True)
    return out


def jittered(coords, eps: float, key) -> jax.Array:
    """``coords`` (unconstrained mount coordinates) moved by ``eps`` of each range's width
    (azimuth, elevation, distance) in a random direction, kept inside the range."""
    u = jax.nn.sigmoid(coords)
    d = jax.random.normal(key, coords.shape)
    u = jnp.clip(u + eps * d / jnp.linalg.norm(d, axis=-1, keepdims=True), 0.01, 0.99)
    return jnp.log(u) - jnp.log1p(-u)


def retest_figures(env, actor, ap, cfg, keys, coords, data, pred, eps: float) -> dict:
    """``--retest``: the same states with every pose moved by ``eps`` of its ranges, the
    actor's episodes again, and how well the outcome there ranks the outcome at the pose itself
    (per state, across its poses: ``retest_rank_corr``) -- what Q could reach if it knew the
    exact outcome one small camera move away; beside it Q's rank against the moved poses'
    outcomes (``q_rank_corr_moved``). Empty when ``eps`` is 0."""
    if not eps > 0:
        return {}
    from twinrl.learn import sensing

    moved = jittered(coords, eps, jax.random.PRNGKey(1))
    data2 = sensing.sensing_data(env, actor, ap, cfg, keys, moved)
    t1, t2 = np.asarray(data.targets), np.asarray(data2.targets)
    same = sensing.rank_corr_per_state(t2, t1)
    spread = np.std(t1[:, :, 0], axis=1)
    return {"retest_eps": eps, "retest_rank_corr": float(np.mean(same)),
            "retest_rank_corr_per_state": same.tolist(),
            "q_rank_corr_moved": float(np.mean(sensing.rank_corr_per_state(pred, t2))),
            "target_sd_across_poses": float(np.mean(spread)),
            "target_change_moved": float(np.mean(np.abs(t2 - t1)[:, :, 0]))}


def score_figures(env, actor, ap, q, qp, cfg, keys, coords, data) -> dict:
    """The choice's own score (``SensingConfig.smooth_samples`` > 0: Q on the hard image averaged
    over the pose and that many poses around it, as ``select_camera`` scores its candidates) at
    every sampled (start state, pose), and its rank correlation with the outcome per state
    (``score_rank_corr``) and pooled. Empty without smoothing."""
    if int(cfg.smooth_samples) == 0:
        return {}
    from twinrl.learn import sensing
    from twinrl.learn.camera_choice import (image_size, neighbourhood_offsets, observed_keys,
                                            observer, q_value, score_around)

    hard = observer(env, image_size(env, actor), keys=observed_keys(actor, q))
    offsets = neighbourhood_offsets(cfg, jax.random.PRNGKey(2))

    @jax.jit
    def around(k, cs):  # (C, 3) poses of one start state -> (C,) scores
        state = env.reset(k)

        def one(c):
            o = hard(state, c)
            return q_value(q, qp, o, actor.apply(ap, o))

        return score_around(one, cs, offsets)

    score = np.stack([np.asarray(around(k, c)) for k, c in zip(keys, coords)])  # (S, C)
    target = np.asarray(data.targets)[:, :, 0]
    per_state = sensing.rank_corr_per_state(score[:, :, None], target[:, :, None])
    # pooled: every (state, pose) pair ranked together, as one "state"
    pooled = sensing.rank_corr_per_state(score.reshape(1, -1, 1), target.reshape(1, -1, 1))[0]
    return {"score_rank_corr": float(np.mean(per_state)),
            "score_rank_corr_per_state": per_state.tolist(),
            "score_rank_corr_pooled": float(pooled)}


def _share(flags: np.ndarray) -> float | None:
    return float(np.mean(flags)) if len(flags) else None  # None: --choices 0


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f} %"


def _retrain_settings(items: list[str]) -> dict:
    """``--retrain``'s ``FIELD=VALUE`` items (``twinrl train --set``'s parsing), each a
    ``SensingConfig`` field."""
    from twinrl.learn.runner import RunError, parse_overrides
    from twinrl.learn.sensing import SensingConfig

    try:
        settings = parse_overrides(items)
    except RunError as e:
        raise SystemExit(f"--retrain: {e}") from None
    fields = [f.name for f in dataclasses.fields(SensingConfig)]
    unknown = sorted(set(settings) - set(fields))
    if unknown:
        raise SystemExit(f"--retrain: SensingConfig has no field {', '.join(unknown)}; its "
                         f"fields: {', '.join(fields)}")
    return settings


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", nargs="+", required=True, help="TASK=DIR twinrl run directories")
    p.add_argument("--states", type=int, default=40)
    p.add_argument("--cameras", type=int, default=8)
    p.add_argument("--choices", type=int, default=20,
                   help="states on which the ascent through the renderer is run")
    p.add_argument("--key", type=int, default=777_000,
                   help="PRNG key of the states and poses (the loop's Q drew its own from the "
                        "run's seed)")
    p.add_argument("--retest", type=float, default=0.0, metavar="EPS",
                   help="also run every pose moved by EPS of its ranges (e.g. 0.01) and rank "
                        "the outcomes there against those at the poses (retest reliability)")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    p.add_argument("--retrain", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="train a new Q with these SensingConfig settings and measure that one")
    args = p.parse_args(argv)
    args.retrain = _retrain_settings(args.retrain)
    if not 0 <= args.retest < 0.5:
        raise SystemExit(f"--retest must be in [0, 0.5), got {args.retest}")
    if args.states < 2 or args.cameras < 2 or args.choices < 0:
        raise SystemExit("--states and --cameras must be >= 2, --choices >= 0")
    rows = evaluate_runs(args, evaluate, "q_rank.json")
    print_table(f"Q's ranking of camera poses on {args.states} fresh states x {args.cameras} "
                f"poses (identified twin)",
                ["task", "twin", "rank per state (95 %)", "loop's (held-out 1/5)", "pooled",
                 "success: Q's pose / mean pose", "ascent raises Q (score)",
                 "... Q at the pose", "... from the default pose alone",
                 "outcome one move away ranks it", "score around the pose: rank (pooled)"],
                [[r["task"], r["twin_seed"], f"{r['rank_corr']:.2f} ({r['rank_corr_ci95'][0]:.2f}"
                  f" .. {r['rank_corr_ci95'][1]:.2f})", r["loop_rank_corr"],
                  f"{r['rank_corr_pooled']:.2f}",
                  f"{r['success_q_choice']:.2f} / {r['success_mean_pose']:.2f}",
                  f"{_pct(r['choice_raises_q'])} of {r['choices']}",
                  _pct(r['choice_raises_q_at_pose']), _pct(r['default_ascent_raises_q']),
                  f"{r['retest_rank_corr']:.2f}" if "retest_rank_corr" in r else "-",
                  f"{r['score_rank_corr']:.2f} ({r['score_rank_corr_pooled']:.2f})"
                  if "score_rank_corr" in r else "-"]
                 for r in rows])
    print(f"wrote {args.out / 'q_rank.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
