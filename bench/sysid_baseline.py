"""Benchmark: twinrl's sysid against MuJoCo's own ``mujoco.sysid`` (and CMA-ES) on the same data.

Datasets (recorded once, identified by every method):

* ``pendulum_swingup`` and ``cartpole_swingup`` real twins, seed 0, ``--episodes`` episodes of
  excitation actions recorded as ``bench/sysid.py`` records them (``sysid.collect``); the first
  body's mass is *known* (read from the twin's truth, standing in for a scale) for every method;
* the user-MJCF arm of ``bench/user_mjcf_sysid.py`` (the Panda on MuJoCo C with hidden mass and
  damping scales, ``robot_logs``; latency 0, no mass known: its position servos anchor the scale).

Methods, each on the parameters twinrl's fit identifies there (names as ``sysid.param_names``):

(a) **twinrl** -- ``sysid.fit`` exactly as the two benches call it (multiple shooting on MJX,
    Gauss-Newton/Levenberg-Marquardt with JAX Jacobians, start states estimated on the real
    twins, latency chosen from 0..1);
(b) **mujoco.sysid** -- its ``optimize`` (MuJoCo's ``minimize.least_squares``, finite-difference
    Jacobians) on its ``build_residual_fn`` over MuJoCo C rollouts (``mujoco.rollout``) of the
    nominal model with the real twin's engine settings. The episodes are cut into the same
    ``--window``-sample windows, each a ``ModelSequences`` entry starting at the recorded (noisy)
    state, the recorded controls held for each control period. Every parameter is the same
    physical quantity twinrl fits (``mass/B``: the body's mass with its rotational inertia scaled
    alike; ``damping``, ``armature``, ``frictionloss`` per dof; ``friction`` per geom; ``gain``:
    ``gainprm[0]``), written into a copy of the compiled model by a ``build_model`` callback,
    started where twinrl starts it (the nominal value; 0.1 for a non-negative one the MJCF leaves
    at 0), box-bounded to [nominal / 5, 5 nominal] (non-negative fields: [0, 5 start + 10]); the
    residual is the qpos / qvel error at each recorded sample divided by the recorded signal's
    sd (an unlimited hinge's modulo 2 pi). Latency: the same grid as twinrl (0..1 control steps,
    the applied controls shifted), the lowest cost kept. Its cost at the hidden truth is
    recorded beside its optimum's (``cost_at_truth``, evaluation only): below the truth's, the
    data's minimum itself lies away from the truth.
(c) **CMA-ES** -- ``twinrl.real2sim.baselines.cmaes_fit`` on the objective of ``bench/sysid.py``'s
    part 2 (recorded starts, the latency twinrl found) over its ``COMPARE`` parameters on the
    real twins and over every mass and damping twinrl fits on the Panda (``--no-cma`` skips it).

Reports per dataset and method each parameter's relative error against the hidden truth
(evaluation only; the absolute error where the truth is 0), the worst and median error over the
parameters every method there fits, and the wall clock (twinrl's includes JAX compilation;
mujoco.sysid compiles nothing). Prints tables and writes ``OUT/sysid_baseline.json``
(``--out OUT``, default
``bench/results``).

What ``mujoco.sysid`` can fit that twinrl cannot: any quantity an ``MjSpec`` edit reaches, through
a ``Parameter``'s modifier callback (geometry, positions, solref/solimp, tendon properties, ...);
full body inertial parameters, mass, centre of mass and the rotational inertia, in physically
consistent parameterisations (``body_inertia_param``: pseudo-inertia / log-Cholesky,
``InertiaType``), where twinrl scales each body's inertia with its mass; position-servo P and D
gains together (``apply_pgain`` / ``apply_dgain`` / ``apply_pdgain`` keep ``biasprm`` consistent);
and the *sensor side*: per-sensor delays, gains and biases (``signal_modifier.apply_delay`` /
``apply_gain`` / ``apply_bias``, resampling of logs at other rates, ``SignalTransform``), with
residuals on any MuJoCo sensor rather than the task's observation. It also gives confidence
intervals (``calculate_intervals``) and an HTML report.

What twinrl fits that ``mujoco.sysid`` does not (out of the box): the start state of every
window jointly with the parameters (``mujoco.sysid`` starts each rollout at the state it is
given, so observation noise on a window's start enters its fit as model error); the action
latency searched inside the fit (its delays act on the sensor signals); flat directions named
from the Fisher information (``flat_directions``, ``status``: e.g. the common scale of masses,
gains and friction without a known mass), with a per-parameter sd; a robust (Huber) loss with its
own optimizer (scipy's losses are reachable through ``optimizer="scipy"``); fits from images
(``real2sim.visual``) and hand-eye calibration; and exact Jacobians through MJX instead of
finite differences (one linearisation is one batched JAX pass instead of n + 1 rollouts of every
window). The identified ``PhysParams`` go straight into the simulator the policy is trained in.

On the Panda twinrl's fit is ``bench/user_mjcf_sysid.py``'s without its bound test
(``PANDA_BOUND_LR``, which says what that test costs there): Levenberg-Marquardt stops after 6
iterations (the worst error of the identified parameters 9 % after 3, 0.32 % after 4, 0.187 %
from 5 on, where the loss stops falling), one refit with the flat base mass at nominal and two
Laplace steps follow; about 60 s of CPU in all, compilation included.
``--merge`` adds or replaces datasets in an existing result (``meta.rows``: each row's run).

Run: ``python bench/sysid_baseline.py [--datasets pendulum_swingup cartpole_swingup panda]
[--episodes 5] [--no-cma] [--panda-bound-lr 2.71] [--merge] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import copy
import io
import os
import sys
import time
from pathlib import Path

import numpy as np

import twinrl  # noqa: F401  (compilation cache)
from twinrl import envs, real, report
from twinrl.physics import SCENES, scene_path
from twinrl.real2sim import baselines, sysid
from twinrl.real2sim.sysid.config import parse_param
from twinrl.real2sim.sysid.problem import param_value

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)
from sysid import COMPARE  # noqa: E402  (bench/sysid.py: CMA-ES's parameters per task)
import user_mjcf_sysid  # noqa: E402  (bench/user_mjcf_sysid.py: the Panda's logs)

RESULTS = Path(__file__).resolve().parent / "results"
MAPPED = ("mass", "damping", "armature", "frictionloss", "friction", "gain")
"""twinrl's parameter fields that ``mujoco.sysid`` gets here (gravity is not mapped)."""


# ---------------------------------------------------------------------- the mapping
def model_field(model, field: str, index: int) -> tuple[np.ndarray, tuple]:
    """The ``MjModel`` array and index holding twinrl's parameter ``field``/``index`` (the
    ``PhysParams`` layout: ``mass[i]`` is body ``i + 1``)."""
    if field == "mass":
        return model.body_mass, (index + 1,)
    if field in ("damping", "armature", "frictionloss"):
        return getattr(model, f"dof_{field}"), (index,)
    if field == "friction":
        return model.geom_friction, (index, 0)
    if field == "gain":
        return model.actuator_gainprm, (index, 0)
    raise ValueError(f"field {field!r} is not mapped to mujoco.sysid; mapped: {', '.join(MAPPED)}")


def write_params(model, nominal, spec: list[tuple[str, int]], values) -> None:
    """Write physical ``values`` for twinrl parameters ``spec`` ((field, index) pairs) into
    ``model`` in place; a mass also scales its body's rotational inertia from ``nominal``'s (as
    ``PhysParams.apply`` does)."""
    for (field, i), v in zip(spec, values):
        arr, idx = model_field(model, field, i)
        arr[idx] = float(v)
        if field == "mass":
            model.body_inertia[i + 1] = nominal.body_inertia[i + 1] * (float(v)
                                                                       / nominal.body_mass[i + 1])


PANDA_BOUND_LR = 0.0
"""twinrl's ``bound_lr`` on the Panda. Its bound test refits the whole problem once per fitted
damping held at 0 (seven Levenberg-Marquardt fits started at damping 0, a Laplace step each) to
decide whether the data allow 0. The Panda's dampings are 24-61 N s/m and identified to 1e-5
relative; the tests' likelihood ratios come out at 3e9-6e13 against the threshold 2.71, so none
is held at 0 and the identified values are the same to four digits with or without the test. On
2 cores at a load of 6 the whole fit took 1,328 s (989 s of CPU), 1,259 s of it the bound test
(refits of 65-331 s each, 219,000 of its 225,570 window rollouts); without it, 84 s (60 s of
CPU). 0 skips the test; ``--panda-bound-lr 2.71`` runs user_mjcf_sysid.py's fit exactly."""


NONNEG_INIT = 0.1
"""Start of a non-negative parameter the MJCF leaves at 0 (``SysidConfig.nonneg_init``'s value)."""


def mujoco_parameters(nominal, spec: list[tuple[str, int]], names):
    """A ``mujoco.sysid.ParameterDict`` of twinrl parameters ``names``/``spec`` starting at their
    nominal values (``NONNEG_INIT`` for a non-negative one the MJCF leaves at 0, as twinrl
    starts it), bounded to [nominal / 5, 5 nominal] ([0, 5 start + 10] for non-negative fields:
    the cartpole's rail friction is 0 in the MJCF and about 1 N on the twin)."""
    from mujoco import sysid as mjs

    pd = mjs.ParameterDict()
    for name, (field, i) in zip(names, spec):
        arr, idx = model_field(nominal, field, i)
        v = float(arr[idx])
        if field in ("damping", "armature", "frictionloss"):
            v = v if v > 0 else NONNEG_INIT
            lo, hi = 0.0, 5 * v + 10.0
        else:
            lo, hi = v / 5, v * 5
        pd.add(mjs.Parameter(name, nominal=v, min_value=lo, max_value=hi))
    return pd


# ---------------------------------------------------------------------- datasets
def spec_with_joint_sensors(mjcf: str):
    """The MJCF as an ``MjSpec`` with a jointpos and a jointvel sensor per joint, what
    ``mujoco.sysid`` compares its rollouts with (hinge and slide joints)."""
    import mujoco

    src = str(mjcf)
    spec = (mujoco.MjSpec.from_string(src) if src.lstrip().startswith("<") else
            mujoco.MjSpec.from_file(str(scene_path(src) if src in SCENES else src)))
    for s in list(spec.sensors):
        spec.delete(s)
    joints = [j.name for j in spec.joints]
    for kind in (mujoco.mjtSensor.mjSENS_JOINTPOS, mujoco.mjtSensor.mjSENS_JOINTVEL):
        for j in joints:
            spec.add_sensor(type=kind, objtype=mujoco.mjtObj.mjOBJ_JOINT, objname=j)
    return spec


def twin_dataset(task: str, seed: int, episodes: int) -> dict:
    """Record a real twin as ``bench/sysid.py`` does; everything each method needs."""
    twin = real.make_real(task, seed=seed)
    data = sysid.collect(twin, episodes=episodes, seed=seed)
    truth = twin.oracle()  # evaluation only
    env = envs.make(task)
    body0 = sysid.param_names(env, ("mass",))[0]
    known_value = param_value(truth.params.as_dict(), *parse_param(env, body0))
    states = np.concatenate([data["obs"][:, :1], data["next_obs"]], axis=1)
    qpos, qvel = (np.asarray(x, np.float64) for x in env.state_from_obs(states))
    import jax

    ctrl = np.asarray(jax.vmap(jax.vmap(env.action_to_ctrl))(data["action"]), np.float64)
    idle = np.asarray(env.action_to_ctrl(np.zeros(data["action"].shape[-1])), np.float64)
    nominal = real.make_real(task, seed=seed, perturbation=real.Perturbation.none()
                             ).oracle().model
    return dict(name=task, env=env, data=data, truth=truth.params,
                true_latency=truth.perturbation.latency_steps, known=((body0, known_value),),
                qpos=qpos, qvel=qvel, ctrl=ctrl, idle_ctrl=idle, nominal=nominal,
                mjcf=env.mjcf(), frame_skip=int(env.config.frame_skip), max_latency=1,
                twinrl_cfg={}, cma=COMPARE.get(task))


def panda_dataset(seed: int, episodes: int, steps: int, frame_skip: int,
                  bound_lr: float = 0.0) -> dict:
    """The Panda logs of ``bench/user_mjcf_sysid.py`` (its defaults: no noise). twinrl's fit is
    that bench's but for ``bound_lr`` (``SysidConfig.bound_lr``; default 0 here, see
    ``PANDA_BOUND_LR``)."""
    import mujoco

    path = str(user_mjcf_sysid.PANDA)
    env = envs.from_mjcf(path, frame_skip=frame_skip)
    qpos, qvel, ctrl, truth = user_mjcf_sysid.robot_logs(path, seed, episodes, steps, frame_skip)
    names = [n for n in sysid.param_names(env) if n.split("/")[0] in ("mass", "damping")]
    return dict(name="panda (user MJCF)", env=env, data=env.transitions(qpos, qvel, ctrl),
                truth=truth, true_latency=0, known=(), qpos=qpos, qvel=qvel, ctrl=ctrl,
                idle_ctrl=ctrl[0, 0], nominal=mujoco.MjModel.from_xml_path(path), mjcf=path,
                frame_skip=frame_skip, max_latency=0,
                twinrl_cfg=dict(params=tuple(names), max_latency=0, bound_lr=bound_lr),
                cma=tuple(names))


# ---------------------------------------------------------------------- (b) mujoco.sysid
def mujoco_problem(ds: dict, names: list[str], window: int, latency: int):
    """``mujoco.sysid``'s ``(ParameterDict, residual_fn)`` for ``names`` on ``ds`` with the
    controls applied ``latency`` control steps late (module docstring, method (b))."""
    import mujoco
    from mujoco import sysid as mjs

    env, fs = ds["env"], ds["frame_skip"]
    mspec = spec_with_joint_sensors(ds["mjcf"])
    base = mspec.compile()
    nom = ds["nominal"]  # the twin's engine settings and nominal parameters
    for attr in ("integrator", "iterations", "ls_iterations", "timestep"):
        setattr(base.opt, attr, getattr(nom.opt, attr))
    for arr in ("body_mass", "body_inertia", "dof_damping", "dof_armature", "dof_frictionloss",
                "geom_friction", "actuator_gainprm", "actuator_biasprm"):
        if not np.allclose(getattr(base, arr), getattr(nom, arr)):
            raise ValueError(f"{ds['mjcf']}: the spec's {arr} differs from the nominal model's")
    for name, v in ds["known"]:  # a known mass is written in, not fitted
        write_params(base, nom, [parse_param(env, name)], [v])
    spec = [parse_param(env, n) for n in names]
    dt = float(base.opt.timestep)
    qpos, qvel, ctrl = ds["qpos"], ds["qvel"], ds["ctrl"]
    E, T = ctrl.shape[:2]
    sq = np.maximum(qpos.reshape(-1, qpos.shape[-1]).std(0), 1e-6)
    sv = np.maximum(qvel.reshape(-1, qvel.shape[-1]).std(0), 1e-6)
    nq = base.nq
    # an unlimited hinge's angle is read off its observation modulo 2 pi (the cartpole's
    # atan2): its error is taken modulo 2 pi too, as the task's cos/sin observation compares it
    wrap = np.zeros(nq, bool)
    for j in range(base.njnt):
        if (base.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and not base.jnt_limited[j]):
            wrap[base.jnt_qposadr[j]] = True

    def build_model(params, _spec):
        m = copy.copy(base)
        write_params(m, base, spec, [params[n].value[0] for n in names])
        return m

    def modify_residual(params, pred, measured, model, return_pred_all, state=None):
        k = np.rint(measured.times / dt).astype(int) - 1  # state row i: after physics step i+1
        q, v = state[k, 1:1 + nq], state[k, 1 + nq:1 + nq + model.nv]
        mq, mv = measured.data[:, :nq], measured.data[:, nq:nq + model.nv]
        dq = np.where(wrap, np.angle(np.exp(1j * (q - mq))), q - mq)
        res = np.concatenate([(dq / sq).ravel(), ((v - mv) / sv).ravel()])
        return res, pred, measured

    applied = np.concatenate([np.broadcast_to(ds["idle_ctrl"], (E, latency, ctrl.shape[-1])),
                              ctrl[:, :T - latency]], axis=1)
    inits, controls, sensors, seq = [], [], [], []
    for e in range(E):
        for s in range(0, T - window + 1, window):
            inits.append(mjs.create_initial_state(base, qpos[e, s], qvel[e, s]))
            c = np.repeat(applied[e, s:s + window], fs, axis=0)
            c = np.concatenate([c, c[-1:]])  # rollout drops the last control
            controls.append(mjs.TimeSeries(np.arange(len(c)) * dt, c))
            meas = np.concatenate([qpos[e, s + 1:s + window + 1],
                                   qvel[e, s + 1:s + window + 1]], axis=1)
            sensors.append(mjs.TimeSeries.from_names(np.arange(1, window + 1) * fs * dt, meas,
                                                     base))
            seq.append(f"ep{e}_t{s}")
    ms = mjs.ModelSequences(ds["name"], mspec, seq, inits, controls, sensors)
    residual_fn = mjs.build_residual_fn(models_sequences=[ms], build_model=build_model,
                                        modify_residual=modify_residual, resample_true=False)
    return mujoco_parameters(base, spec, names), residual_fn


def cost(residual_fn, params, x) -> float:
    """Half the squared residual norm at ``x``."""
    r = np.concatenate(residual_fn(np.asarray(x, np.float64), params.copy())[0])
    return float(0.5 * r @ r)


def mujoco_sysid_fit(ds: dict, names: list[str], window: int, max_iters: int) -> dict:
    """Identify ``names`` with ``mujoco.sysid`` on ``ds``: its ``optimize`` once per latency in
    0..``max_latency``, the lowest cost kept."""
    from mujoco import sysid as mjs

    best = None
    t0 = time.perf_counter()
    for lat in range(ds["max_latency"] + 1):
        params, residual_fn = mujoco_problem(ds, names, window, lat)
        x0 = params.as_vector()
        opt, result = mjs.optimize(params, residual_fn, optimizer="mujoco", verbose=False,
                                   max_iters=max_iters, x_scale=np.maximum(np.abs(x0), 1e-2),
                                   output=io.StringIO())  # its per-iteration log
        c = cost(residual_fn, params, result.x)
        if best is None or c < best["cost"]:
            best = dict(latency=lat, cost=c, values={n: float(opt[n].value[0]) for n in names},
                        windows=len(residual_fn(result.x, params.copy())[0]), problem=(
                            params, residual_fn))
    best["seconds"] = time.perf_counter() - t0
    # evaluation only: its cost at the hidden truth (above its optimum's: the optimizer stopped
    # short; below: the data's minimum lies away from the truth, e.g. noisy window starts)
    params, residual_fn = best.pop("problem")
    t = ds["truth"].as_dict()
    best["cost_at_truth"] = cost(residual_fn, params, [param_value(t, *parse_param(ds["env"], n))
                                                       for n in names])
    return best


# ---------------------------------------------------------------------- evaluation
def rel_errors(ds: dict, values: dict) -> dict:
    """|identified - truth| / |truth| per parameter (absolute error where the truth is 0)."""
    t = ds["truth"].as_dict()
    out = {}
    for n, v in values.items():
        tv = param_value(t, *parse_param(ds["env"], n))
        out[n] = abs(v - tv) / abs(tv) if tv != 0 else abs(v)
    return out


def run(ds: dict, window: int, max_iters: int, cma_evals: int | None, seed: int) -> dict:
    env, data = ds["env"], ds["data"]
    out = {"dataset": ds["name"], "true_latency": ds["true_latency"],
           "known": [list(k) for k in ds["known"]], "methods": {},
           "twinrl_config": {"window": window, **{k: list(v) if isinstance(v, tuple) else v
                                                  for k, v in ds["twinrl_cfg"].items()}}}
    # (a) twinrl, as bench/sysid.py / bench/user_mjcf_sysid.py call it
    t = time.perf_counter()
    res = sysid.fit(env, data, sysid.SysidConfig(known=ds["known"], window=window,
                                                 **ds["twinrl_cfg"]))
    sec = time.perf_counter() - t
    known = {n for n, _ in ds["known"]}
    fitted = [n for n in res.names if n not in known]
    vals = dict(zip(res.names, (float(v) for v in res.values)))
    out["methods"]["twinrl"] = dict(values={n: vals[n] for n in fitted}, seconds=sec,
                                    latency=int(res.latency), loss=float(res.loss),
                                    status=dict(zip(res.names, res.status)),
                                    iterations=len(res.history), rollouts=int(res.sim_rollouts))
    # (b) mujoco.sysid on the mapped ones
    names = [n for n in fitted if n.split("/")[0] in MAPPED]
    out["methods"]["mujoco.sysid"] = mujoco_sysid_fit(ds, names, window, max_iters)
    # (c) CMA-ES, bench/sysid.py part 2's objective
    if cma_evals is not None and ds["cma"]:
        cfg = sysid.SysidConfig(params=ds["cma"], known=ds["known"],
                                estimate_start=False, latency=res.latency, window=window)
        c = baselines.cmaes_fit(env, data, cfg, baselines.CmaesConfig(max_evals=cma_evals),
                                seed=seed)
        out["methods"]["CMA-ES"] = dict(
            values=dict(zip(ds["cma"], (float(v) for v in c.values))),
            seconds=float(c.seconds), loss=float(c.loss), rollouts=int(c.sim_rollouts))
    for m in out["methods"].values():
        m["rel_err"] = rel_errors(ds, m["values"])
    shared = set.intersection(*(set(m["values"]) for m in out["methods"].values()))
    out["shared"] = sorted(shared)
    for m in out["methods"].values():
        e = [m["rel_err"][n] for n in out["shared"]]
        m["worst"], m["median"] = (float(max(e)), float(np.median(e))) if e else (None, None)
    return out


def print_dataset(r: dict) -> None:
    methods = list(r["methods"])
    params = sorted(set().union(*(m["values"] for m in r["methods"].values())))
    rows = [[p] + [f"{100 * r['methods'][m]['rel_err'][p]:.2f} %" if p in r["methods"][m]["values"]
                   else "-" for m in methods] for p in params]
    rows.append(["worst (shared)"] + [f"{100 * r['methods'][m]['worst']:.2f} %" for m in methods])
    rows.append(["median (shared)"] + [f"{100 * r['methods'][m]['median']:.2f} %"
                                       for m in methods])
    rows.append(["wall clock"] + [f"{r['methods'][m]['seconds']:.1f} s" for m in methods])
    report.print_table(f"{r['dataset']}: relative parameter error against the hidden truth",
                       ["parameter"] + methods, rows)


def row_provenance(meta: dict) -> dict:
    """How a row was produced: the command, commit, date and load average of its run."""
    return {"command": meta.get("command"), "commit": meta.get("commit"),
            "dirty": meta.get("dirty"), "date": meta.get("date"),
            "load_average": meta.get("machine", {}).get("load_average")}


def committed_rows(path: Path) -> dict:
    """The rows already at ``path`` (``{"results": [], "rows": {}}`` without a file) and each
    one's provenance: ``meta.rows`` where the file has it, else the file's own ``meta``."""
    import json

    if not path.exists():
        return {"results": [], "rows": {}}
    old = json.loads(path.read_text())
    meta = old.get("meta", {})
    rows = meta.get("rows") or {r["dataset"]: row_provenance(meta) for r in old["results"]}
    return {"results": old["results"], "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", nargs="+",
                    default=["pendulum_swingup", "cartpole_swingup", "panda"],
                    choices=["pendulum_swingup", "cartpole_swingup", "panda"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=5, help="real-twin episodes (Panda: 3)")
    ap.add_argument("--window", type=int, default=20, help="samples per shooting window")
    ap.add_argument("--panda-window", type=int, default=10,
                    help="the Panda's window (bench/user_mjcf_sysid.py's default)")
    ap.add_argument("--max-iters", type=int, default=100, help="mujoco.sysid iterations")
    ap.add_argument("--cma-evals", type=int, default=2000)
    ap.add_argument("--no-cma", action="store_true", help="skip CMA-ES")
    ap.add_argument("--panda-bound-lr", type=float, default=PANDA_BOUND_LR,
                    help="twinrl's SysidConfig.bound_lr on the Panda (user_mjcf_sysid.py's fit: "
                         "2.71; default %(default)s, see PANDA_BOUND_LR)")
    ap.add_argument("--merge", action="store_true",
                    help="keep OUT/sysid_baseline.json's rows of other datasets (a dataset run "
                         "again replaces its row); meta.rows says how each row was produced")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    path = args.out / "sysid_baseline.json"
    base = committed_rows(path) if args.merge else {"results": [], "rows": {}}
    results = []
    for name in args.datasets:
        t = time.perf_counter()
        if name == "panda":
            ds = panda_dataset(args.seed, 3, 100, 4, args.panda_bound_lr)
            window = args.panda_window
        else:
            ds = twin_dataset(name, args.seed, args.episodes)
            window = args.window
        r = run(ds, window, args.max_iters, None if args.no_cma else args.cma_evals, args.seed)
        r["seconds"] = time.perf_counter() - t
        results.append(r)
        write_rows(path, base, results, args)
        print_dataset(r)
    report.print_table(
        "twinrl vs mujoco.sysid vs CMA-ES: worst / median relative error over the shared "
        "parameters, wall clock",
        ["dataset", "method", "worst", "median", "seconds"],
        [[r["dataset"], m, f"{100 * v['worst']:.2f} %", f"{100 * v['median']:.2f} %",
          f"{v['seconds']:.1f}"] for r in results for m, v in r["methods"].items()])
    print(f"wrote {path}")
    return 0


def write_rows(path: Path, base: dict, results: list[dict], args) -> None:
    """Write ``results`` merged into ``base`` (``committed_rows``; empty without ``--merge``): a
    dataset run again replaces its row in place, a new one is appended, the others are kept;
    ``meta.rows`` gives each row's provenance (this run's for ``results``)."""
    from benchio import metadata

    new = {r["dataset"]: r for r in results}
    merged = [new.pop(r["dataset"], r) for r in base["results"]] + list(new.values())
    rows = {r["dataset"]: base["rows"].get(r["dataset"]) for r in merged}
    now = row_provenance(metadata(args))
    rows.update({r["dataset"]: now for r in results})
    write_result(path, {"meta": {"rows": rows}, "results": merged}, args)


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    raise SystemExit(main())
