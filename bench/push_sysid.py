"""Push identification, taken apart: box mass and friction from the push real twin, by case.

Records ``--episodes`` episodes of push's closed-loop excitation from a real twin observed in full
states (``observation="state"``), then fits box mass, box friction, pusher friction, the
motor gains and the pusher damping (pusher mass known -- weighed --, floor friction held at 0.05 so
the box's coefficient is the contact's; the box's tilt and rocking left out of the residuals).
The twin is twin ``--twin-seed``'s hidden perturbation, or only some of its parts
(``--only mass_scale friction_scale ...``: the others nominal), so each cause can be looked at
alone. ``--start truth`` starts the fit at the hidden truth (evaluation only), to tell an
objective whose minimum is elsewhere from a fit that stops short. ``--contacts``,
``--iterations`` and ``--loss`` choose the simulator and the objective. ``--staged`` fits the
pusher first, on the windows where it keeps clear of the box, then the box from planar positions
(``staged``); ``--slide-first`` fits the pusher, then the box's friction alone on the windows
where it slides free, then its mass (``slide_first``). The box friction's truth is the box-floor
contact's coefficient, the larger of the twin's box and floor values (the fit holds its floor's
at 0.05).

Prints a table (truth, identified, sd, relative error per parameter) and writes
``OUT/push_sysid.json``. About 2-3 minutes per case on 2 cores.

    python bench/push_sysid.py --out B                                   # stock simulator
    python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --out B
    python bench/push_sysid.py --contacts mujoco --iterations 12 --only friction_scale --out B
    python bench/push_sysid.py --contacts mujoco --iterations 12 --start truth --out B
    python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --staged --out B
    python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --slide-first --out B
    python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --staged --window 1 \
        --recorded-starts --twin-seed 2 --only mass_scale friction_scale gain_scale \
        damping_scale latency_steps --out B    # one-step windows from the recorded states
    python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --staged --window 1 \
        --recorded-starts --twin-seed 2 --noise 0.0003 --out B   # the same, a 0.3 mm sensor
    python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --staged --window 1 \
        --recorded-starts --indirect 6 --out B     # de-biased by indirect inference (15 min)
    python bench/push_sysid.py --contacts mujoco --iterations 12 --loss l2 --staged --window 1 \
        --recorded-starts --spread 6 --out B       # how far that answer spreads (4 min)

Why the box's fits stop percents off: docs/known-limits.md (the box rocks on its corners, and
its height, tilt and the pusher-box gap matter below the sensors' noise).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

import twinrl  # noqa: F401  (compilation cache)
from twinrl import envs, real, report
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)
from twinrl.physics.collision import CONTACTS
from twinrl.real.perturbation import Perturbation
from twinrl.real2sim import sysid
from twinrl.real2sim.sysid.config import LOSSES, parse_param
from twinrl.real2sim.sysid.indirect import noise_sd_from_quaternions
from twinrl.real2sim.sysid.problem import param_value

PARAMS = ("mass/box", "friction/box", "friction/pusher", "gain/fx", "gain/fy", "damping/px",
          "damping/py")
PARTS = ("mass_scale", "friction_scale", "gain_scale", "damping_scale", "latency_steps",
         "obs_noise_std")
FLOOR_FRICTION = 0.05  # below the box's: the box-floor contact's coefficient is the box's
# [qpos (9): pusher x y, box x y z, quaternion; qvel (8): pusher, box linear, angular]
WEIGHTS = tuple(0.0 if i in (4, 5, 6, 7, 13, 14, 15, 16) else 1.0 for i in range(17))
PUSHER = ("gain/fx", "gain/fy", "damping/px", "damping/py")
PUSHER_WEIGHTS = tuple(1.0 if i in (0, 1, 9, 10) else 0.0 for i in range(17))
POSITION_WEIGHTS = tuple(1.0 if i in (0, 1, 2, 3, 8) else 0.0 for i in range(17))
# ``--planar-velocities``: the same with the pusher's and the box's planar velocities
PLANAR_WEIGHTS = tuple(1.0 if i in (0, 1, 2, 3, 8, 9, 10, 11, 12) else 0.0 for i in range(17))
CLEAR_WINDOW = 5  # steps per stage-1 window: short, so that some keep clear of the box


def box_contact_truth(env, params):
    """The twin's ``params`` with the box's friction replaced by the box-floor contact's
    coefficient, the larger of the two geoms' (MuJoCo's rule): with the floor held at
    ``FLOOR_FRICTION`` the fit's box value stands for the contact's, so that is its truth (the
    floor's value on twins whose floor is the rougher)."""
    floor, box = (env.sim.mj_model.geom(g).id for g in ("floor", "box"))
    friction = np.array(params.friction)
    friction[box] = max(friction[box], friction[floor])
    return params.replace(friction=friction)


def floor_held(env, friction):
    """``friction`` with the floor's coefficient at ``FLOOR_FRICTION``."""
    friction = np.array(friction)
    friction[env.sim.mj_model.geom("floor").id] = FLOOR_FRICTION
    return friction


def staged(env, data, known, common, weights=POSITION_WEIGHTS):
    """Two stages: (1) the pusher's gains and damping, and the latency, on the short windows
    where the pusher stays clear of the box (``Push.pusher_clear``), from its own states only;
    (2) box mass, box friction and pusher friction on all windows, the pusher's values known,
    from planar positions only (the box's velocities chatter with its rocking; positions
    integrate it away). Returns both results and the number of stage-1 windows."""
    first, pusher, n_clear = pusher_first(env, data, known, common)
    c2 = sysid.SysidConfig(params=("mass/box", "friction/box", "friction/pusher"),
                           known=known + pusher, observation_weights=weights,
                           **common, latency=first.latency)
    return first, sysid.fit(env, data, c2), n_clear


SLIDE_WINDOW = 3  # steps per stage-2 window of ``slide_first``: a free slide lasts ~5
SLIDE_SPEED = 0.05  # m/s: such a window starts with the box moving at least this fast
BOX_POSITION_WEIGHTS = tuple(1.0 if i in (2, 3) else 0.0 for i in range(17))


def clear_throughout(env, w) -> np.ndarray:
    """Which windows ``w`` keep the pusher clear of the box at every step (``Push.pusher_clear``
    of the start and every target state)."""
    return env.pusher_clear(np.concatenate([w.obs0[:, None], w.targets], axis=1)).all(axis=1)


def pusher_first(env, data, known, common):
    """``staged``'s stage 1: the pusher's gains and damping, and the latency, on the
    ``CLEAR_WINDOW``-step windows where it keeps clear of the box. Returns the fit, the pusher's
    values as ``known`` entries and the number of windows."""
    c1 = sysid.SysidConfig(params=PUSHER, known=known, observation_weights=PUSHER_WEIGHTS,
                           **{**common, "window": CLEAR_WINDOW})
    w = sysid.windows_from_dataset(env, data, c1.window, max_latency=c1.max_latency)
    clear = clear_throughout(env, w)
    first = sysid.fit(env, w.select(clear), c1)
    return first, tuple((n, float(v)) for n, v in zip(first.names, first.values)
                        if n in PUSHER), int(clear.sum())


def slide_first(env, data, known, common):
    """Three stages, the box's friction apart from its mass: (1) the pusher (``pusher_first``);
    (2) the box's friction alone on the ``SLIDE_WINDOW``-step windows where the pusher keeps
    clear and the box starts faster than ``SLIDE_SPEED`` -- it slides on its own, decelerating
    at friction times g whatever its mass --, from the box's planar position; (3) box mass and
    pusher friction on all windows from planar positions, the rest known. Free slides are short
    on push (the pusher's damping caps the box near 0.3 m/s; it stops in ~5 steps, the first 2
    with the pusher still near): 11-37 such windows (overlapping, stride 1) in 5 episodes.
    Returns the three fits and the stage-1 and stage-2 window counts."""
    first, pusher, n_clear = pusher_first(env, data, known, common)
    c2 = sysid.SysidConfig(params=("friction/box",), known=known + pusher,
                           observation_weights=BOX_POSITION_WEIGHTS,
                           **{**common, "window": SLIDE_WINDOW}, latency=first.latency)
    w = sysid.windows_from_dataset(env, data, c2.window, stride=1, max_latency=c2.max_latency)
    slide = clear_throughout(env, w) & (np.linalg.norm(w.obs0[:, 11:13], axis=-1) > SLIDE_SPEED)
    second = sysid.fit(env, w.select(slide), c2)
    box = (("friction/box", float(second.values[0])),)
    c3 = sysid.SysidConfig(params=("mass/box", "friction/pusher"), known=known + pusher + box,
                           observation_weights=POSITION_WEIGHTS, **common,
                           latency=first.latency)
    return first, second, sysid.fit(env, data, c3), n_clear, int(slide.sum())


BOX = ("mass/box", "friction/box", "friction/pusher")


def _indirect_parts(env, data, known, common, weights, *, episodes, config):
    """What indirect inference on push needs: the real data's staged fits, the sensor noise
    read off the box's quaternions (``noise_sd_from_quaternions``), ``estimate(data)`` (the
    staged fit's box mass, box friction and pusher friction) and ``simulate(theta, seed)``
    (push data in MuJoCo C from the real fit's pusher and latency, the candidate ``theta`` and
    that noise, the excitation drawn with ``seed``)."""
    model = env.sim.mj_model
    qpos = np.concatenate([data["obs"], data["next_obs"][:, -1:]], axis=1)[..., :model.nq]
    noise = noise_sd_from_quaternions(model, qpos)
    first, res, n_clear = staged(env, data, known, common, weights)
    ids = (("mass", model.body("box").id - 1), ("friction", model.geom("box").id),
           ("friction", model.geom("pusher").id))

    def estimate(d):
        return box_values(staged(env, d, known, common, weights)[1])

    def simulate(theta, seed):
        p = {k: np.array(v, np.float64) for k, v in res.params.as_dict().items()}
        for (field, i), v in zip(ids, theta):
            p[field][i] = v
        p["friction"] = floor_held(env, p["friction"])
        pert = Perturbation.from_params(model, res.params.replace(**p),
                                        latency_steps=first.latency, obs_noise_std=noise)
        twin = real.make_real("push", perturbation=pert, config=config)
        try:
            return sysid.collect(twin, episodes=episodes, seed=seed)
        finally:
            twin.close()

    return first, res, n_clear, noise, estimate, simulate


def box_values(fit) -> np.ndarray:
    """A fit's box mass, box friction and pusher friction (``BOX``)."""
    value = dict(zip(fit.names, fit.values))
    return np.array([value[n] for n in BOX])


def debiased(env, data, known, common, weights, *, reps, iterations, episodes, config):
    """``staged`` de-biased by indirect inference (``sysid.indirect``): the same staged fit run
    on push data simulated in MuJoCo C from the real fit's pusher and latency, candidate box mass,
    box friction and pusher friction, and the sensor noise read off the box's quaternions
    (``noise_sd_from_quaternions``); the same excitation seeds at every candidate. Returns the
    real data's staged fits, the ``IndirectResult`` and the noise sd used."""
    first, res, n_clear, noise, estimate, simulate = _indirect_parts(
        env, data, known, common, weights, episodes=episodes, config=config)

    def progress(h):
        print(f"  indirect {h['iteration']}: theta "
              f"{', '.join(f'{n} {v:.4g}' for n, v in zip(BOX, h['theta']))}", flush=True)

    ind = sysid.indirect(estimate, simulate, data, raw=box_values(res),
                         reps=reps, iterations=iterations, progress=progress)
    return first, res, n_clear, ind, noise


SPREAD_STEP = 0.1  # ``spread``: the relative step of mass and friction for the binding slope


def spread(env, data, known, common, weights, truth, *, reps, episodes, config) -> dict:
    """How far indirect inference's answer can be trusted from one dataset like ``data``: the
    staged estimator run on ``reps`` datasets simulated at the box's ``truth`` (mass, friction,
    pusher friction; evaluation only) and at mass and at friction ``SPREAD_STEP`` above it
    (the same seeds), the real fit's pusher, latency and noise. The binding function's slope in
    log coordinates (rows: mass, friction moved; columns: what the estimator reads) carries the
    estimator's covariance over datasets to the sd of the answer (mass, friction), as the
    delta method does. Returns the real data's staged fits, their stage-1 window count and
    the figures."""
    first, res, n_clear, noise, estimate, simulate = _indirect_parts(
        env, data, known, common, weights, episodes=episodes, config=config)
    truth = np.asarray(truth, np.float64)
    moves = {"truth": np.ones(3), "mass": np.array([1 + SPREAD_STEP, 1, 1]),
             "friction": np.array([1, 1 + SPREAD_STEP, 1])}
    logs = {}
    for name, f in moves.items():
        logs[name] = np.array([np.log(estimate(simulate(truth * f, 100 + r)))
                               for r in range(reps)])
        print(f"  spread: {name} done ({reps} datasets)", flush=True)
    slope = np.stack([(logs[k] - logs["truth"]).mean(0) for k in ("mass", "friction")]
                     ) / np.log1p(SPREAD_STEP)
    inv = np.linalg.inv(slope[:, :2].T)
    answer_sd = np.sqrt(np.diag(inv @ np.cov(logs["truth"][:, :2].T) @ inv.T))
    return first, res, n_clear, dict(
        noise_sd=noise, reps=reps, step=SPREAD_STEP,
        bias=(np.exp(logs["truth"].mean(0)) / truth - 1).tolist(),
        estimate_log_sd=logs["truth"].std(0, ddof=1).tolist(), slope=slope.tolist(),
        answer_sd=answer_sd.tolist(), logs={k: v.tolist() for k, v in logs.items()})


def run(args) -> dict:
    config = {"observation": "state"}
    hidden = real.make_real("push", seed=args.twin_seed, config=config).oracle().perturbation
    pert = hidden if args.only is None else dataclasses.replace(
        Perturbation.none(), **{k: getattr(hidden, k) for k in args.only})
    if args.noise is not None:  # the twin's sensor, made finer or coarser
        pert = dataclasses.replace(pert, obs_noise_std=args.noise)
    twin = real.make_real("push", seed=args.twin_seed, perturbation=pert, config=config)
    truth = twin.oracle()  # evaluation only
    data = sysid.collect(twin, episodes=args.episodes, seed=args.seed)
    sim_config = dict(contacts=args.contacts, solver_iterations=args.iterations, **config)
    env = envs.make("push", **sim_config)
    true_of = lambda n: float(param_value(truth.params.as_dict(), *parse_param(env, n)))  # noqa
    contact_truth = box_contact_truth(env, truth.params)
    if args.start == "truth":
        env = envs.make("push", params=contact_truth.replace(
            friction=floor_held(env, contact_truth.friction)), **sim_config)
    known = (("mass/pusher", true_of("mass/pusher")), ("friction/floor", FLOOR_FRICTION))
    common = dict(loss=args.loss, start_prior_sd=args.start_prior_sd)
    if args.window is not None:
        common["window"] = args.window
    if args.recorded_starts:
        common["estimate_start"] = False
    t = time.perf_counter()
    n_slide = None
    indirect = None
    if args.spread:
        box_truth = [float(param_value(contact_truth.as_dict(), *parse_param(env, n)))
                     for n in BOX]
        first, res, n_clear, out = spread(
            env, data, known, common, PLANAR_WEIGHTS if args.planar_velocities
            else POSITION_WEIGHTS, box_truth, reps=args.spread, episodes=args.episodes,
            config=config)
        rows = [dict(parameter=n, truth=v, identified=float(v * (1 + b)),
                     sd=float(np.exp(s) - 1) * v, rel_err=abs(b),
                     status=f"estimator at the truth (log sd {s:.3f})")
                for n, v, b, s in zip(BOX, box_truth, out["bias"], out["estimate_log_sd"])]
        indirect = dict(spread=out)
    elif args.indirect:
        first, res, n_clear, ind, noise = debiased(
            env, data, known, common, PLANAR_WEIGHTS if args.planar_velocities
            else POSITION_WEIGHTS, reps=args.indirect, iterations=args.indirect_iterations,
            episodes=args.episodes, config=config)
        rows = [r for r in sysid.compare_to_truth(first, contact_truth, pert.latency_steps)
                if r["parameter"] in PUSHER]
        raw = {r["parameter"]: r for r in sysid.compare_to_truth(res, contact_truth,
                                                                pert.latency_steps)}
        for n, v, sd in zip(BOX, ind.values, ind.sd):
            true_v = raw[n]["truth"]  # not ``t``: that is the clock the run's seconds read
            rows.append(dict(parameter=n, truth=true_v, identified=float(v), sd=float(sd),
                             rel_err=abs(float(v) - true_v) / abs(true_v),
                             status=f"raw {raw[n]['identified']:.4g} ({raw[n]['rel_err']:.1%})"))
        indirect = dict(noise_sd=noise, reps=args.indirect, values=ind.values.tolist(),
                        raw=ind.raw.tolist(), sd=ind.sd.tolist(),
                        jacobian=ind.jacobian.tolist(), history=list(ind.history))
    elif args.staged or args.slide_first:
        if args.slide_first:
            first, second, res, n_clear, n_slide = slide_first(env, data, known, common)
            box = [r for r in sysid.compare_to_truth(second, contact_truth, pert.latency_steps)
                   if r["parameter"] == "friction/box"]
        else:
            (first, res, n_clear), box = staged(env, data, known, common, PLANAR_WEIGHTS
                                                 if args.planar_velocities
                                                 else POSITION_WEIGHTS), []
        rows = ([r for r in sysid.compare_to_truth(first, contact_truth, pert.latency_steps)
                 if r["parameter"] in PUSHER] + box)
        rows += [r for r in sysid.compare_to_truth(res, contact_truth, pert.latency_steps)
                 if r["parameter"] not in [x["parameter"] for x in rows] + ["friction/floor"]]
    else:
        cfg = sysid.SysidConfig(params=PARAMS, known=known, observation_weights=WEIGHTS,
                                **common)
        res = sysid.fit(env, data, cfg)
        rows = [r for r in sysid.compare_to_truth(res, contact_truth, pert.latency_steps)
                if r["parameter"] != "friction/floor"]
        n_clear = None
    return dict(twin_seed=args.twin_seed, only=args.only, episodes=args.episodes,
                contacts=args.contacts, iterations=args.iterations, loss=args.loss,
                start=args.start, start_prior_sd=args.start_prior_sd, window=args.window,
                recorded_starts=args.recorded_starts, planar_velocities=args.planar_velocities,
                staged=args.staged, slide_first=args.slide_first,
                clear_windows=n_clear, slide_windows=n_slide,
                latency=res.latency, true_latency=pert.latency_steps,
                noise=args.noise, obs_noise_std=pert.obs_noise_std, loss_value=res.loss,
                indirect=indirect,
                seconds=time.perf_counter() - t, rows=rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--twin-seed", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0, help="excitation seed")
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--only", nargs="+", choices=PARTS, default=None,
                    help="perturb only these parts of the twin's hidden perturbation")
    ap.add_argument("--noise", type=float, default=None,
                    help="the twin's observation noise sd (default: its hidden one; with "
                         "--only, 0 unless obs_noise_std is named)")
    ap.add_argument("--contacts", choices=CONTACTS, default="mjx")
    ap.add_argument("--iterations", type=int, default=None,
                    help="solver iterations of the fitting simulator (default: push.xml's 6)")
    ap.add_argument("--loss", choices=LOSSES, default="huber")
    ap.add_argument("--start", choices=("nominal", "truth"), default="nominal")
    ap.add_argument("--start-prior-sd", type=float,
                    default=sysid.SysidConfig.start_prior_sd,
                    help="SysidConfig.start_prior_sd: the estimated window starts' prior sd")
    stages = ap.add_mutually_exclusive_group()
    stages.add_argument("--staged", action="store_true",
                    help="pusher first on windows clear of the box, then the box from positions")
    stages.add_argument("--slide-first", action="store_true",
                    help="pusher first, then box friction on free slides, then box mass")
    ap.add_argument("--window", type=int, default=None,
                    help="SysidConfig.window of the box's fits (default: its 20 steps)")
    ap.add_argument("--planar-velocities", action="store_true",
                    help="with --staged: the box's fit also on the planar velocities")
    ap.add_argument("--recorded-starts", action="store_true",
                    help="every stage's windows start from the recorded states "
                         "(SysidConfig.estimate_start off)")
    ap.add_argument("--indirect", type=int, default=0, metavar="R",
                    help="with --staged: de-bias the staged fit by indirect inference, R "
                         "simulated datasets per step (sysid.indirect)")
    ap.add_argument("--indirect-iterations", type=int, default=6)
    ap.add_argument("--spread", type=int, default=0, metavar="R",
                    help="with --staged: instead of a fit, how far indirect inference's answer "
                         "spreads from one dataset: the estimator on R datasets simulated at "
                         "the box's truth and 10 %% above it in mass and in friction")
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)
    if args.episodes < 1 or (args.iterations is not None and args.iterations < 1):
        ap.error("--episodes and --iterations must be >= 1")
    if args.window is not None and args.window < 1:
        ap.error(f"--window must be >= 1, got {args.window}")
    if args.noise is not None and not args.noise >= 0:
        ap.error(f"--noise must be >= 0, got {args.noise}")
    if args.indirect and (not args.staged or args.indirect < 2
                          or args.indirect_iterations < 1):
        ap.error("--indirect R goes with --staged, R >= 2, --indirect-iterations >= 1")
    if args.spread and (not args.staged or args.spread < 3 or args.indirect):
        ap.error("--spread R goes with --staged, R >= 3, and not with --indirect")
    if args.planar_velocities and not args.staged:
        ap.error("--planar-velocities goes with --staged")
    if not args.start_prior_sd > 0:
        ap.error(f"--start-prior-sd must be > 0, got {args.start_prior_sd}")
    r = run(args)
    stages = (f", staged + indirect inference ({args.indirect} x {args.indirect_iterations}; "
              f"noise {r['indirect']['noise_sd']:.3g} m read off the quaternions)"
              if args.indirect else f", slide first ({r['clear_windows']} clear, "
              f"{r['slide_windows']} slide windows)"
              if args.slide_first else f", staged ({r['clear_windows']} clear windows)"
              if args.staged else "")
    report.print_table(
        f"push twin {args.twin_seed} ({'only ' + ', '.join(args.only) if args.only else 'all'}; "
        f"noise {r['obs_noise_std']:.2g} m), {args.contacts} contacts, {args.loss}, from {args.start}"
        f"{stages}: "
        f"loss {r['loss_value']:.3g}",
        ["parameter", "truth", "identified", "sd", "rel err", "status"],
        [[x["parameter"], x["truth"], x["identified"], x["sd"], x["rel_err"], x["status"]]
         for x in r["rows"]])
    if args.spread:
        sp = r["indirect"]["spread"]
        report.print_table(
            f"indirect inference's spread from one dataset ({args.spread} simulated; noise "
            f"{sp['noise_sd']:.3g} m): the estimator at the truth, its slope, the answer's sd",
            ["moved", "reads mass", "reads box friction", "reads pusher friction"],
            [["slope: mass", *sp["slope"][0]], ["slope: friction", *sp["slope"][1]],
             ["estimator bias (relative)", *sp["bias"]],
             ["estimator log sd", *sp["estimate_log_sd"]]])
        print(f"the answer's sd: mass {sp['answer_sd'][0]:.1%}, friction "
              f"{sp['answer_sd'][1]:.1%}")
    print(f"wrote {write_result(args.out / 'push_sysid.json', r, args)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
