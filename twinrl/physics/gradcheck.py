"""Check reverse-mode gradients of a rollout loss against central finite differences.

The loss is a fixed random linear-plus-quadratic function of every state of an open-loop rollout,
``L = mean_t (c_q . qpos_t + c_v . qvel_t + 0.05 |qvel_t|^2)``, so every input reaches it. Its
gradient with respect to the action sequence, the initial state (qpos, qvel) and every
``PhysParams`` field is computed once by ``jax.grad`` and once per scalar by central differences.

Run it in float64 (``jax.config.update("jax_enable_x64", True)`` before building the ``Sim``):
float32 central differences are dominated by rounding.

Stability of a finite-difference estimate. Through contacts the loss is piecewise smooth; a
perturbation that switches a contact or a limit on or off gives a difference quotient that is no
derivative at all. Each scalar is differenced with two step sizes, ``h`` and ``4h``, and its
rounding noise is bounded by ``r = 4 eps max(|L|, 1) / h``. With ``s = |fd(h) - fd(4h)|`` and
``k = |forward(h) - backward(h)|`` (one-sided quotients at ``h``):

- *resolved*: ``s + r <= 0.1 rtol |fd|`` and ``k <= max(1e-3 |fd|, 20 r)`` -- the estimate is
  good to a tenth of the tolerance: judged by relative error ``|g - fd| / max(|g|, |fd|) <= rtol``;
- *kink*: otherwise, when ``s > max(1e-6 |fd|, 10 r)`` or ``k > max(1e-3 |fd|, 20 r)`` -- the
  estimates disagree beyond rounding, so a contact or limit switched inside the window. The
  one-sided test catches symmetric kinks, e.g. a box resting flat whose tilt either way lifts
  different corners, where central differences at every step size agree on the mean of the two
  slopes. Reported, not judged;
- *noise-limited*: the rest (gradients so small that rounding dominates the quotient): judged in
  absolute terms, ``|g - fd| <= 10 (s + r)``.

``max_rel_error`` is the largest relative error over resolved entries. Non-finite gradients fail.

Measured noise. ``r`` assumes the loss is computed to a few ulps; a rollout can amplify its own
rounding far beyond that. A box resting flat on a plane is the plain case: its tilt about x and y
is zero in exact arithmetic, and rounding alone decides which corners carry the weight, so the
derivative along those dofs is noise in both the gradient and the quotients (moving the start
height by 1e-14 of itself, a few ulps, turns the gradient w.r.t. the x-rotation's armature from
-5.7e-8 into +7.0e-8 and its central difference from -3.9e-7 into +2.2e-7, where the loss's
largest derivative is 3.4). So the noise is measured as well: the gradient is computed again at
two points whose every input is moved by ``JITTER`` (1e-13) of ``max(1, |x|)`` either way, and
the central difference at ``h`` again at the first; their changes (``grad_noise``,
``fd_noise`` per row) join the bounds above: resolved now needs ``s + r + fd_noise <= 0.1 rtol
|fd|`` (the kink tests keep ``r``), and a noise-limited entry is judged by ``|g - fd| <= 10 (s +
r + fd_noise + grad_noise)``, provided its ``grad_noise`` stays within ``rtol`` of the largest
effect the differences see (``rtol max_j |fd_j| max(1, |x_j|) / max(1, |x_i|)``): a gradient
noisier than that fails. Resolved entries are judged as before: a gradient that an ulp-sized
move changes by more than ``rtol`` of a resolved derivative fails there. (Before this, the flat
box failed on one or two such entries on every seed, with errors of 3e-8 to 6e-7; the unrolled
solve's 1.4e6 against 3.4 on the same box still fails, as a resolved entry.) The loss's own
change at the first jittered point, beyond the gradient's first-order prediction, is reported as
``loss_jitter``: the forward's roughness, which bounds what any difference at ``h`` resolves
(an entry's quotient carries about ``loss_jitter / h`` of noise, so nothing below ``loss_jitter /
(0.1 rtol h)`` resolves). A pendulum's is 1e-15; a box resting flat on a plane, 1e-9 (rounding
decides which corners carry it, and the rollout amplifies that; stock ``mjx.step`` alike), so
there mass, friction and gravity, whose derivatives are 1e-5 to 1e-3, go unjudged at ``h`` =
1e-6 (at 1e-4 gravity's horizontal entries resolve, mass and friction still do not), and
``twinrl gradcheck`` says why rather than only naming the groups.

Coverage. A check that resolves no entry of a group has judged nothing through it (a friction
coefficient through a rollout that never slides, say). Each group reports how many entries were
resolved; a group with none is *unjudged* (``GradcheckResult.unjudged``), unless it is *inert*:
every entry's gradient and both difference quotients exactly zero (the input does not reach the
loss, e.g. friction loss on a dof without a friction-loss row), or -- *numerically inert* -- every
entry noise-limited with an effect below the loss's rounding even over a 100 % change,
``|g| max(1, |x|) <= 100 eps max(|L|, 1)`` (an input whose effect something cancels exactly in
exact arithmetic: gravity on an arm whose bodies are all gravity-compensated, ~1e-18 left by
rounding). ``passed`` ignores unjudged groups; ``passed_strict`` (``twinrl gradcheck --strict``)
fails on them.

Cost. Each checked entry costs four rollouts (two step sizes, both signs); ``entries`` bounds the
entries checked per group (a seeded random subset, reported; the gradient is still computed in
full), so a large model's check can judge every group at a fraction of the cost. The stages
overlap where they can: the gradient compiles (in a thread; XLA does not hold Python's lock) while
the differences' batched rollout is traced, and that compiles while the gradient runs.

Range. A step can leave the range where the model is defined: the Control Suite's fish has fin
bodies of 1e-7 inertia and no armature, so an armature step of 1e-6 below zero makes the mass
matrix indefinite and the loss NaN. An entry whose differences are non-finite is differenced again
with its step shrunk 100,000-fold, at most twice (within 4h of where the model breaks the loss is
curved on the scale of h, and a 1,000-fold smaller step still left the fin's one-sided differences
apart by 1e-3, a "kink"; 100,000-fold resolves it to 1.4e-9). One still non-finite is *outside*:
reported, not judged (its gradient must still be finite).

Ties. MuJoCo gives a contact the larger of its two geoms' friction coefficients. Where they are
equal -- every geom of a model that sets one default friction, e.g. Gymnasium's half_cheetah --
each coefficient alone is at a kink of that max: lowering it changes nothing, raising it raises the
contact's (half_cheetah: backward difference exactly 0, forward twice the central one, at every
step size), so no single entry can be resolved; the gradient there is the mean of the two slopes
(``jnp.maximum`` splits a tie). Scaling a whole group is smooth through such ties (the max of
scaled values is the scaled max), so each ``params`` group of several entries gets one more
entry, index ``scale``: the derivative along ``x_group -> (1 + t) x_group``, ``g . x_group``
against its central difference in ``t``, classified like the others. It judges how the group's
entries add up wherever they act, including through ties.

Orientations. A free or ball joint's quaternion has 4 numbers and 3 degrees of freedom; a
perturbation of one component leaves the unit sphere and measures nothing physical. The initial
state is therefore perturbed in the tangent space, ``qpos = qpos0 (+) dq`` with ``dq`` of size nv
(position for slides, hinges and free translations; a body-frame rotation vector for each
quaternion, ``q0 * exp(dq / 2)``), and reported as the group ``qpos`` with ``nv`` entries.

Solver tolerance. Finite differences see the forward solve's stopping rule: a solve that stops at
MuJoCo's default tolerance (1e-8) moves the loss by ~1e-9 when a perturbation changes its
iteration count, which swamps a difference quotient at h = 1e-6. ``gradcheck`` therefore solves
to ``tolerance`` (default 1e-12 in float64) so that the differenced function is the solution the
implicit derivative describes.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.flatten_util import ravel_pytree

from mujoco.mjx._src import collision_driver as _driver
from mujoco.mjx._src.types import JointType

from twinrl.physics._threads import Background
from twinrl.physics.integrator import tangent_qpos
from twinrl.physics.mjwarn import mujoco_warnings
from twinrl.physics.params import PhysParams
from twinrl.physics.scenes import SCENES, Scenario, scenario as make_scenario
from twinrl.physics.sim import CONTACT_BOUNDS, Sim

__all__ = ["GradcheckResult", "gradcheck", "combine_summaries", "tangent_qpos"]

JITTER = 1e-13
"""How far, relative to ``max(1, |x|)``, the inputs move to measure the noise (docstring)."""


@dataclasses.dataclass
class GradcheckResult:
    scene: str
    horizon: int
    dtype: str
    rtol: float
    rows: list[dict[str, Any]]
    groups: list[dict[str, Any]]
    constrained_steps: int
    free_steps: int
    seconds_compile_and_grad: float = 0.0
    scenario: str = ""
    tolerance: float | None = None
    loss_jitter: float = 0.0
    """How far the loss moved beyond its gradient's prediction when every input moved by
    ``JITTER`` of itself ("Measured noise"): the forward's own roughness."""
    step: float = 0.0
    """The finite-difference step ``h`` (relative to ``max(1, |x|)``)."""
    timings: dict[str, float] = dataclasses.field(default_factory=dict)
    """Seconds per stage: ``trace`` (and lower), ``compile`` and ``gradient`` (its first run),
    ``noise`` (two more gradients), ``differences`` (every batch; the first, which compiles,
    also as ``differences_first_batch``), and the number of ``rollouts`` differenced."""

    @property
    def resolution_floor(self) -> float:
        """The smallest derivative differences at ``step`` can resolve through the forward's
        roughness: an entry's quotient carries about ``loss_jitter / step`` of noise, and
        resolving takes that under a tenth of ``rtol`` of the derivative (module docstring)."""
        return self.loss_jitter / self.step / (0.1 * self.rtol) if self.step > 0 else 0.0

    @property
    def unjudged_by_roughness(self) -> list[str]:
        """The unjudged groups whose largest gradient lies below ``resolution_floor``: those
        the forward's own roughness explains."""
        return [g["group"] for g in self.groups if g["group"] in self.unjudged
                and g["max_abs_grad"] <= self.resolution_floor]

    @property
    def nan_count(self) -> int:
        return sum(int(not np.isfinite(r["grad"])) for r in self.rows)

    @property
    def max_rel_error(self) -> float:
        errs = [r["rel_err"] for r in self.rows if r["status"] == "resolved"]
        return float(max(errs)) if errs else 0.0

    def count(self, status: str) -> int:
        return sum(int(r["status"] == status) for r in self.rows)

    @property
    def failures(self) -> list[dict[str, Any]]:
        return [r for r in self.rows if not r["ok"]]

    @property
    def passed(self) -> bool:
        return self.nan_count == 0 and not self.failures

    @property
    def unjudged(self) -> list[str]:
        """Groups with no resolved entry that are not inert (module docstring)."""
        return [g["group"] for g in self.groups if g["resolved"] == 0 and not g["inert"]]

    @property
    def passed_strict(self) -> bool:
        """``passed``, and every group judged on at least one resolved entry (or inert)."""
        return self.passed and not self.unjudged

    def summary(self) -> dict[str, Any]:
        return {
            "scene": self.scene, "horizon": self.horizon, "dtype": self.dtype, "rtol": self.rtol,
            "scenario": self.scenario, "tolerance": self.tolerance,
            "max_rel_error": self.max_rel_error, "nan_count": self.nan_count,
            "unjudged": self.unjudged, "passed_strict": self.passed_strict,
            "resolved": self.count("resolved"), "noise_limited": self.count("noise"),
            "kinks": self.count("kink"), "outside": self.count("outside"),
            "failures": len(self.failures), "entries": len(self.rows),
            "constrained_steps": self.constrained_steps, "free_steps": self.free_steps,
            "loss_jitter": self.loss_jitter, "step": self.step, "passed": self.passed,
            "timings": self.timings,
            "groups": self.groups, "rows": self.rows,
        }


def combine_summaries(summaries: list[dict[str, Any]]) -> dict[str, Any]:
    """One summary of several scenes' checks (each ``GradcheckResult.summary()`` with its
    ``passed`` verdict): each scene's summary without its rows under ``scenes``, the largest
    relative error, the non-finite count, whether all passed, and every row tagged with its
    ``scene``."""
    return {"scenes": [{k: v for k, v in s.items() if k != "rows"} for s in summaries],
            "max_rel_error": max(s["max_rel_error"] for s in summaries),
            "nan_count": sum(s["nan_count"] for s in summaries),
            "passed": all(s["passed"] for s in summaries),
            "rows": [dict(row, scene=s["scene"]) for s in summaries for row in s["rows"]]}

def _labels(inputs: dict[str, Any], dof_names: list[str]) -> list[tuple[str, str]]:
    """(group, index) per scalar, in the order ``ravel_pytree`` lays them out (leaf order)."""
    labels = []
    leaves_with_path = jax.tree_util.tree_flatten_with_path(inputs)[0]
    for path, leaf in leaves_with_path:
        name = ".".join(str(getattr(k, "key", getattr(k, "name", k))) for k in path)
        for idx in np.ndindex(*leaf.shape):
            index = ",".join(map(str, idx))
            if name == "qpos":  # tangent coordinates: name the dof
                index = f"{index}:{dof_names[idx[0]]}"
            labels.append((name, index))
    return labels


def _dof_names(mj_model) -> list[str]:
    """A label per dof: joint name (or index) and, for free/ball joints, x/y/z or rx/ry/rz."""
    names = []
    for j in range(mj_model.njnt):
        jn = mj_model.joint(j).name or f"joint{j}"
        t = mj_model.jnt_type[j]
        if t == JointType.FREE:
            names += [f"{jn}.{a}" for a in ("x", "y", "z", "rx", "ry", "rz")]
        elif t == JointType.BALL:
            names += [f"{jn}.{a}" for a in ("rx", "ry", "rz")]
        else:
            names.append(jn)
    return names


MANY_CANDIDATES = 1000
"""Contact candidates per step above which the check suggests MJX's contact bounds."""
PROGRESS_EVERY = 20.0
"""Seconds between progress lines while the differences run."""
BATCH = 64
"""Most rollouts per batch of the finite differences: one compile for every batch, and memory
that does not grow with the model's number of inputs."""
BATCH_BYTES = 2e9
"""Memory a batch may take, at ``EFC_COPIES`` constraint Jacobians per rollout (``batch_size``)."""
EFC_COPIES = 16
"""Constraint-Jacobian-sized arrays one batched rollout holds: the Control Suite's dog (7,951
contact candidates, a 31,804 x 85 Jacobian of 21.6 MB) ran out of 20 GB in a batch of 64."""


def batch_size(sim: Sim, data=None) -> int:
    """Rollouts per batch for ``sim``: ``BATCH``, fewer where its constraint Jacobian is large
    (the dog's 4). ``data``: ``sim.init()``, when the caller has it already."""
    d = sim.init() if data is None else data
    efc_bytes = max(1, int(np.prod(d._impl.efc_J.shape))) * jnp.asarray(0.0).dtype.itemsize
    return int(np.clip(BATCH_BYTES // (EFC_COPIES * efc_bytes), 1, BATCH))


def _contact_candidates(data) -> int:
    """Contacts MJX evaluates every step (every candidate pair, touching or not), from a
    ``sim.init()``."""
    try:
        return int(data._impl.contact.dist.shape[0])
    except AttributeError:  # a layout without that field: not worth failing the check over
        return -1


class _Batched:
    """The batched loss over ``rows`` inputs, in batches of ``batch`` (the last padded, so one
    compile serves all), with a progress line at most every ``PROGRESS_EVERY`` seconds."""

    def __init__(self, fn, rows: int, say, batch: int = BATCH):
        self.fn, self.rows, self.say = fn, rows, say
        self.chunk = min(rows, batch)
        self.done, self.first, self.last = 0, 0.0, time.perf_counter()

    def __call__(self, xs) -> np.ndarray:
        out = []
        for start in range(0, xs.shape[0], self.chunk):
            part = xs[start:start + self.chunk]
            pad = self.chunk - part.shape[0]
            if pad:
                part = jnp.concatenate([part, jnp.broadcast_to(part[:1], (pad, part.shape[1]))])
            t0 = time.perf_counter()
            out.append(np.asarray(self.fn(part), np.float64)[:self.chunk - pad])
            self.done += self.chunk - pad
            now = time.perf_counter()
            self.first = self.first or now - t0
            if now - self.last >= PROGRESS_EVERY:
                self.say(f"differences: {self.done} of {max(self.done, 3 * self.rows)} rollouts")
                self.last = now
        return np.concatenate(out)


def classify(g, fd1, fd4, fwd, bwd, rounding, rtol, fd_noise=0.0, g_noise=0.0,
             g_noise_cap=np.inf):
    """Status ("kink" | "resolved" | "noise" | "outside") and verdict of each entry (module
    docstring).

    Args are arrays over entries: reverse-mode gradient ``g``; central differences at ``h`` and
    ``4h``; forward and backward one-sided differences at ``h``; rounding bound; tolerance; the
    measured noise of the central difference and of the gradient, and the most gradient noise
    a noise-limited entry may have ("Measured noise").
    Returns ``(status, ok, rel_err, abs_err)``.
    """
    g, fd1, fd4, fwd, bwd, rounding, fd_noise, g_noise = (
        np.asarray(a, np.float64) for a in (g, fd1, fd4, fwd, bwd, rounding, fd_noise, g_noise))
    noise = rounding + fd_noise  # the quotient's own noise: the bound, plus what was measured
    spread, sided = np.abs(fd1 - fd4), np.abs(fwd - bwd)
    err = np.abs(g - fd1)
    rel = err / np.maximum(np.maximum(np.abs(g), np.abs(fd1)), 1e-300)
    one_sided_kink = sided > np.maximum(1e-3 * np.abs(fd1), 20 * rounding)
    # Resolved first: two step sizes that agree to a tenth of the tolerance are a derivative
    # estimate good enough to judge, even where their spread (h^2 truncation) exceeds 1e-6.
    resolved = ~one_sided_kink & (spread + noise <= 0.1 * rtol * np.abs(fd1))
    kink = ~resolved & ((spread > np.maximum(1e-6 * np.abs(fd1), 10 * rounding))
                        | one_sided_kink)
    outside = ~(np.isfinite(fd1) & np.isfinite(fd4))  # module docstring, "Range"
    status = np.where(outside, "outside", np.where(kink, "kink", np.where(
        resolved, "resolved", "noise")))
    noise_ok = (err <= 10 * (spread + noise + g_noise)) & (g_noise <= g_noise_cap)
    ok = np.where(kink | outside, True, np.where(resolved, rel <= rtol, noise_ok))
    return status, ok & np.isfinite(g), rel, err


def gradcheck(sim: Sim, *, horizon: int | None = None, scenario: Scenario | str | None = None,
              h: float = 1e-6, rtol: float = 1e-4, seed: int = 0,
              tolerance: float | None = 1e-12, settle: int = 0,
              entries: int | None = None,
              progress: Callable[[str], None] | None = None) -> GradcheckResult:
    """Compare ``jax.grad`` of a rollout loss with central finite differences.

    Args:
      sim: the simulator (build it with x64 enabled for a meaningful check).
      horizon: rollout length T (default: the scenario's; 100, 50 for peg_in_hole).
      scenario: initial state and actions, or the name of one (``twinrl.physics.scenes.SCENARIOS``:
        ``"wave"``, ``"zero"``, or a bundled scene's own). Default: the bundled scene's own
        scenario when ``sim`` was loaded by a bundled scene's name, else ``"wave"``. A named
        generic scenario starts from the MJCF's first keyframe (qpos, qvel) when it has one,
        else from ``qpos0`` at rest.
      h: finite-difference step, relative to ``max(1, |x|)``.
      rtol: tolerance on the relative error of stable entries.
      seed: seed of the loss weights and of generic scenarios.
      tolerance: constraint-solver tolerance for the check (``None``: the MJCF's); see the
        module docstring.
      settle: physics steps of MuJoCo C, without actuation, from the scenario's initial state
        before the check starts: a walker dropped from its ``qpos0`` then starts on the ground,
        so the check goes through its contacts (and its friction) within a short horizon.
      entries: check at most this many entries per group (a random subset drawn with ``seed``;
        every group's ``scale`` entry is kept); ``None``: all of them.
      progress: called with a line at each stage (tracing, compiling, the gradient, the
        differences' batches, at most every ``PROGRESS_EVERY`` seconds while they run), so a
        large model's check is not silent for minutes.
    """
    say = progress or (lambda msg: None)
    if not rtol > 0:
        raise ValueError(f"rtol must be > 0, got {rtol}")
    if not h > 0:
        raise ValueError(f"h must be > 0, got {h}")
    if entries is not None and not entries >= 1:
        raise ValueError(f"entries must be >= 1, got {entries}")
    if tolerance is not None:
        if not tolerance >= 0:
            raise ValueError(f"tolerance must be >= 0, got {tolerance}")
        mj = copy.deepcopy(sim.mj_model)
        mj.opt.tolerance = tolerance
        sim = sim.recompiled(mj)
    if scenario is None or isinstance(scenario, str):
        name = scenario or (sim.name if sim.bundled else "wave")
        sc = make_scenario(name, sim.nq, sim.nv, sim.nu, np.array(sim.mj_model.qpos0), horizon,
                           seed)
        if name not in SCENES and sim.mj_model.nkey:  # a user's MJCF: start at its keyframe 0
            sc = dataclasses.replace(sc, qpos=np.array(sim.mj_model.key_qpos[0], np.float64),
                                     qvel=np.array(sim.mj_model.key_qvel[0], np.float64))
    else:
        name, sc = "custom", scenario
    if settle:
        if settle < 0:
            raise ValueError(f"settle must be >= 0, got {settle}")
        mj_data = mujoco.MjData(sim.mj_model)
        mj_data.qpos[:], mj_data.qvel[:] = sc.qpos, sc.qvel
        with mujoco_warnings(f"{name}: settling"):
            mujoco.mj_step(sim.mj_model, mj_data, nstep=int(settle))
        sc = dataclasses.replace(sc, qpos=mj_data.qpos.copy(), qvel=mj_data.qvel.copy())
    dtype = jnp.asarray(0.0).dtype
    rng = np.random.default_rng(seed + 1)
    c_q = jnp.asarray(rng.normal(size=sim.nq), dtype)
    c_v = jnp.asarray(rng.normal(size=sim.nv), dtype)
    jnt_types = tuple(int(t) for t in sim.mj_model.jnt_type)
    qpos0 = jnp.asarray(sc.qpos, dtype)

    inputs = {
        "actions": jnp.asarray(sc.actions, dtype),
        "qpos": jnp.zeros(sim.nv, dtype),  # tangent coordinates around the scenario's qpos
        "qvel": jnp.asarray(sc.qvel, dtype),
        "params": sim.default_params(),
    }
    x0, unflatten = ravel_pytree(inputs)

    def loss(x):
        z = unflatten(x)
        qpos = tangent_qpos(jnt_types, qpos0, z["qpos"])
        _, tr = sim.rollout(sim.init(qpos, z["qvel"]), z["actions"], z["params"])
        per_step = tr.qpos @ c_q + tr.qvel @ c_v + 0.05 * jnp.sum(tr.qvel ** 2, axis=-1)
        return jnp.mean(per_step), tr.n_active

    t0 = time.perf_counter()
    T = int(sc.actions.shape[0])
    data0 = sim.init()  # its layout: the contacts and the constraint Jacobian per step
    candidates = _contact_candidates(data0)
    bounded = any(_driver._numeric(sim.mj_model, b) >= 0 for b in CONTACT_BOUNDS)
    say(f"tracing the gradient of a {T}-step rollout ({sim.nv} dofs, {x0.size} inputs, "
        f"{candidates} contacts per step{' after its bounds' if bounded else ''})")
    if candidates > MANY_CANDIDATES and not bounded:
        say(f"{candidates} contacts: MJX has no broad phase and evaluates every candidate "
            f"every step; bounding them (max_geom_pairs, max_contact_points: "
            f"--max-geom-pairs, --max-contact-points) cuts the time and memory")
    lowered = jax.jit(jax.value_and_grad(loss, has_aux=True)).lower(x0)
    t1 = time.perf_counter()
    say(f"traced in {t1 - t0:.1f} s; compiling it while the differences' rollouts are traced")
    # The gradient runs three times, the batched forward thousands: XLA's optimisation passes
    # pay for themselves only on the latter (humanoid, 20 steps: the gradient's compile 49 s ->
    # 16 s at level 0, each run 0.04 -> 0.11 s). XLA compiles without Python's lock, so the
    # gradient compiles in a thread while this one traces the differences' batched rollout,
    # which then compiles in another while the gradient runs ("Cost").
    grad_job = Background(lowered.compile,
                           compiler_options={"xla_backend_optimization_level": 0})

    labels = _labels(inputs, _dof_names(sim.mj_model))
    # One extra entry per parameter group: the derivative along scaling the whole group
    # (module docstring, "Ties"); a group of one entry already has it as its entry.
    x0np = np.asarray(x0, np.float64)
    members: dict[str, list[int]] = {}  # group -> indices of its entries, in label order
    for i, (grp, _) in enumerate(labels):
        members.setdefault(grp, []).append(i)
    dirs = []
    for grp, idx in members.items():
        if grp.startswith("params.") and len(idx) > 1 and np.any(x0np[idx]):
            d = np.zeros(x0np.size)
            d[idx] = x0np[idx]
            dirs.append((grp, d))
    totals = {grp: len(idx) + any(d == grp for d, _ in dirs) for grp, idx in members.items()}
    if entries is not None:  # a seeded subset per group (module docstring, "Cost")
        pick = np.random.default_rng(seed + 2)
        members = {grp: sorted(pick.choice(idx, size=min(entries, len(idx)), replace=False)
                               .tolist()) for grp, idx in members.items()}
    chosen = np.array(sum(members.values(), []), int)  # entries to difference, by group
    order = {int(i): j for j, i in enumerate(chosen)}
    members = {grp: [order[i] for i in idx] for grp, idx in members.items()}
    labels = [labels[i] for i in chosen]
    n = chosen.size
    D = jnp.asarray(np.array([d for _, d in dirs]).reshape(len(dirs), x0np.size), dtype)
    k = len(dirs)
    rows = 1 + 2 * (n + k)
    chunk = min(rows, batch_size(sim, data0))
    tf = time.perf_counter()
    forward = jax.jit(jax.vmap(lambda x: loss(x)[0])).lower(
        jax.ShapeDtypeStruct((chunk, x0np.size), dtype))
    trace_differences = time.perf_counter() - tf
    forward_job = Background(forward.compile)
    value_and_grad = grad_job.result()
    t2 = time.perf_counter()
    (_, n_active), g = value_and_grad(x0)
    g = np.asarray(jax.block_until_ready(g), np.float64)
    seconds = time.perf_counter() - t0
    say(f"compiled in {grad_job.seconds:.1f} s, ran in {seconds - (t2 - t0):.1f} s; the "
        f"gradient again at 2 inputs moved in their last bits (its noise)")
    # "Measured noise": the same gradient at inputs moved in their last bits
    x0_abs = np.abs(x0np)
    jitters = [jnp.asarray(x0np + JITTER * np.maximum(1.0, x0_abs)
                           * rng.choice([-1.0, 1.0], size=x0_abs.size), dtype)
               for _ in range(2)]
    g_jit = [np.asarray(value_and_grad(xj)[1], np.float64) for xj in jitters]
    t3 = time.perf_counter()
    batched = _Batched(lambda xs: forward_job.result()(xs), rows, say, chunk)
    say(f"differencing {n + k} entries: {3 * batched.rows} rollouts in batches of "
        f"{batched.chunk}")
    # each entry's step (then each group direction's); shrunk below where a difference left
    # the model's valid range
    steps64 = np.concatenate([h * np.maximum(1.0, np.abs(x0np[chosen])), np.full(k, h)])

    # each entry's direction: its row of the identity, then each group's scaling
    along_rows = jnp.concatenate([jax.nn.one_hot(chosen, x0np.size, dtype=dtype), D])

    def evaluate(scale, x=x0, idx=None):
        # the loss at x (row 0) and at x +- each entry's step (entries idx; default all); one
        # batch shape for every call (the last batch padded): a single compile
        idx = np.arange(n + k) if idx is None else idx
        st = jnp.asarray(scale * steps64[idx], dtype)[:, None]
        V = along_rows[jnp.asarray(idx)]
        out = batched(jnp.concatenate([x[None], x + st * V, x - st * V]))
        return out[0], out[1:idx.size + 1], out[idx.size + 1:]

    # "Range": a step that leaves the model's valid range (armature below zero on a body of
    # 1e-7 inertia, where the step is ten times the value) makes the loss non-finite there;
    # such entries (only they) are differenced again with their step shrunk 100,000-fold, at
    # most twice.
    l0, plus1, minus1 = evaluate(1.0)
    _, plus4, minus4 = evaluate(4.0)
    for _ in range(2):
        outside = np.flatnonzero(~np.isfinite(np.stack([plus1, minus1, plus4, minus4]))
                                 .all(axis=0))
        if not outside.size:
            break
        steps64[outside] /= 1e5
        _, plus1[outside], minus1[outside] = evaluate(1.0, idx=outside)
        _, plus4[outside], minus4[outside] = evaluate(4.0, idx=outside)
    l_jit, plus_jit, minus_jit = evaluate(1.0, jitters[0])
    t4 = time.perf_counter()
    timings = {"trace": t1 - t0, "compile": grad_job.seconds,
               "gradient": seconds - (t2 - t0), "noise": t3 - t0 - seconds,
               "trace_differences": trace_differences,
               "compile_differences": forward_job.seconds, "differences": t4 - t3,
               "differences_first_batch": batched.first, "rollouts": batched.done}
    # beyond the first-order change the move itself makes (the gradient is full-length here)
    loss_jitter = float(abs(l_jit - l0 - g @ (np.asarray(jitters[0], np.float64) - x0np)))

    def differences(scale, plus, minus):
        h_i = scale * steps64
        return (plus - minus) / (2 * h_i), (plus - l0) / h_i, (l0 - minus) / h_i

    fd1, fwd1, bwd1 = differences(1.0, plus1, minus1)
    fd4, _, _ = differences(4.0, plus4, minus4)
    fd_noise = np.abs(differences(1.0, plus_jit, minus_jit)[0] - fd1)
    l0 = abs(l0)
    eps = float(jnp.finfo(dtype).eps)
    rounding = 4 * eps * max(l0, 1.0) / steps64

    along = lambda v: np.concatenate([v[chosen], np.asarray(D, np.float64) @ v])
    g_noise = np.max([np.abs(along(gj) - along(g)) for gj in g_jit], axis=0)
    g = along(g)
    labels = labels + [(grp, "scale") for grp, _ in dirs]
    for j, (grp, _) in enumerate(dirs):
        members[grp].append(n + j)
    # an entry's own scale (max(1, |x|); 1 along a group's scaling, whose step is h)
    scale_of = np.concatenate([np.maximum(1.0, np.abs(x0np[chosen])), np.ones(k)])
    # the gradient's noise may not exceed rtol of the largest effect the differences see
    # (over finite differences only: a step that leaves the model's valid range -- armature
    # below zero on a body of 1e-7 inertia -- gives NaN there, which must not fail every other
    # entry's noise test)
    effect = np.abs(fd1) * scale_of
    cap = rtol * np.max(effect[np.isfinite(effect)], initial=0.0) / scale_of
    status, ok, rel, err = classify(g, fd1, fd4, fwd1, bwd1, rounding, rtol, fd_noise, g_noise,
                                    cap)
    rows = [{"group": grp, "index": index, "grad": float(g[i]), "fd": float(fd1[i]),
             "abs_err": float(err[i]), "rel_err": float(rel[i]), "status": str(status[i]),
             "ok": bool(ok[i]), "fd_noise": float(fd_noise[i]), "grad_noise": float(g_noise[i])}
            for i, (grp, index) in enumerate(labels)]

    group_rows = []
    for grp, idx in members.items():
        rs = [rows[i] for i in idx]
        res = [r for r in rs if r["status"] == "resolved"]
        inert = bool(np.all(g[idx] == 0) and np.all(fd1[idx] == 0) and np.all(fd4[idx] == 0))
        # numerically inert: below the loss's rounding even over a 100 % change (docstring)
        inert = inert or bool(np.all(status[idx] == "noise") and np.all(
            np.abs(g[idx]) * scale_of[idx] <= 100 * eps * max(l0, 1.0)))
        group_rows.append({
            "group": grp, "entries": len(rs), "entries_total": totals[grp],
            "resolved": len(res), "inert": inert,
            "noise_limited": sum(r["status"] == "noise" for r in rs),
            "kinks": sum(r["status"] == "kink" for r in rs),
            "outside": sum(r["status"] == "outside" for r in rs),
            "max_abs_grad": float(max(abs(r["grad"]) for r in rs)),
            "max_rel_err": float(max((r["rel_err"] for r in res), default=0.0)),
            "max_abs_err": float(max((r["abs_err"] for r in rs
                                      if r["status"] not in ("kink", "outside")),
                                     default=0.0)),
            "failures": sum(not r["ok"] for r in rs),
            "nonfinite": sum(int(not np.isfinite(r["grad"])) for r in rs),
        })

    na = np.asarray(n_active)
    return GradcheckResult(
        scene=sim.name, horizon=int(sc.actions.shape[0]), dtype=str(dtype), rtol=rtol, rows=rows,
        groups=group_rows, constrained_steps=int((na > 0).sum()), free_steps=int((na == 0).sum()),
        seconds_compile_and_grad=seconds, timings=timings, scenario=name, tolerance=tolerance,
        loss_jitter=loss_jitter, step=h)
