"""Q's design, measured cheaply: one run's data made once, then many Q fits ranked on it.

``bench/q_rank.py --retrain`` measures one Q setting in 12-20 minutes, nearly all of it the
actor's episodes that make Q's data (the fit itself takes seconds). Here, for one ``--run
TASK=DIR`` (a ``twinrl run`` output directory: its last round's actor and identified twin), the
data are made once and kept in ``OUT/q_fit_data.pkl`` (reused while the run, the states, poses
and keys are the same):

- training data: the largest of ``--states`` start states x ``--cameras`` poses (keys from
  ``--key + 1``); each smaller ``--states`` value takes the first states of it;
- held-out data: ``--test-states`` x ``--cameras`` (keys from ``--key``, drawn as
  ``bench/q_rank.py`` draws them, so the run's own Q scores as there).

Then every ``--variants`` loss is fitted with ``--seeds`` seeds on each training size, with the
run's Q settings (network, steps, learning rate, RGB jitter) and minibatches of whole states
(``batch_size // cameras`` states, all their poses). A variant is ``mse`` (Q's loss), ``centred:W``
(the MSE plus W times the MSE of Q's and the target's deviations from their state's mean:
what a camera choice ranks on) or ``centred-only`` (the latter alone). Reported per (size,
variant): Spearman's rank correlation across the poses of a state (``sensing.evaluate_ranking``),
its mean over seeds with their range, the pooled correlation, and the success at Q's preferred
pose; beside them the run's own Q and, for a pose actor, two scores that are not Q: the target
pixel count alone (what Q has to beat) and minus the pose estimate's true error, from the hidden
state (evaluation only: how far perception alone ranks the poses).

Prints a table and writes ``OUT/q_fit.json``.

    python bench/q_fit.py --run needle_threading=runs/needle --states 32 64 --seeds 4 \\
        --variants mse centred:4 centred-only --out bench/results
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, _jaxconfig)
import jax
import jax.numpy as jnp
import numpy as np
import optax

from twinrl.report import print_table, run_meta, write_json


def _keys(key: int, states: int):
    """The start states' and the poses' keys, drawn as ``bench/q_rank.py`` draws them."""
    k_states, k_cams, _ = jax.random.split(jax.random.PRNGKey(key), 3)
    return jax.random.split(k_states, states), k_cams


def _data(env, actor, ap, cfg, key: int, states: int, cameras: int):
    from twinrl.learn import sensing
    from twinrl.learn.camera_choice import uniform_coords

    keys, k_cams = _keys(key, states)
    coords = uniform_coords(env.mount, k_cams, (states, cameras))
    return jax.device_get(sensing.sensing_data(env, actor, ap, cfg, keys, coords))


def _parse_variant(v: str) -> tuple[float, float]:
    """(weight of the MSE, weight of the centred MSE)."""
    if v == "mse":
        return 1.0, 0.0
    if v == "centred-only":
        return 0.0, 1.0
    name, _, w = v.partition(":")
    try:
        if name == "centred" and float(w) >= 0:
            return 1.0, float(w)
    except ValueError:
        pass
    raise SystemExit(f"--variants: {v!r} is not mse, centred:W (W >= 0) or centred-only")


def fit(q, cfg, data, states: int, weights: tuple[float, float], seed: int):
    """Q's parameters after ``cfg.fit_steps`` steps on the first ``states`` states of ``data``,
    minibatches of whole (state, step) groups of all poses."""
    from twinrl.learn.common import make_optimizer, rgb_jitter

    def grouped(x):  # (S, C, K, ...) -> (S * K, C, ...)
        x = jnp.swapaxes(jnp.asarray(x[:states]), 1, 2)
        return x.reshape((-1,) + x.shape[2:])

    obs = {k: grouped(v) for k, v in data.obs.items() if k in q.obs_spec}
    acts, targets = grouped(data.actions), grouped(data.targets)
    n, cams = targets.shape
    groups = max(1, int(cfg.batch_size) // cams)
    tx = make_optimizer(cfg.learning_rate, cfg.max_grad_norm)
    augment = rgb_jitter(cfg.rgb_jitter) if cfg.rgb_jitter else None
    w_mse, w_centred = weights

    def loss(p, o, a, t):
        flat = {k: v.reshape((-1,) + v.shape[2:]) for k, v in o.items()}
        v = q.apply(p, {**flat, "action": a.reshape(-1, a.shape[-1])})[..., 0].reshape(t.shape)
        d = (v - v.mean(1, keepdims=True)) - (t - t.mean(1, keepdims=True))
        return w_mse * jnp.mean((v - t) ** 2) + w_centred * jnp.mean(d ** 2)

    @jax.jit
    def run(p, key):
        def body(carry, k):
            p, s = carry
            k_idx, k_aug = jax.random.split(k)
            idx = jax.random.randint(k_idx, (groups,), 0, n)
            o = {k: v[idx] for k, v in obs.items()}
            if augment is not None:
                flat = augment({k: v.reshape((-1,) + v.shape[2:]) for k, v in o.items()}, k_aug)
                o = {k: flat[k].reshape(o[k].shape) for k in o}
            value, g = jax.value_and_grad(loss)(p, o, acts[idx], targets[idx])
            u, s = tx.update(g, s, p)
            return (optax.apply_updates(p, u), s), value

        (p, _), losses = jax.lax.scan(body, (p, tx.init(p)), jax.random.split(key,
                                                                                int(cfg.fit_steps)))
        return p, losses

    k_init, k_fit = jax.random.split(jax.random.PRNGKey(seed))
    return run(q.init(k_init), k_fit)


def _figures(pred: np.ndarray, data) -> dict:
    """``sensing.evaluate_ranking``'s figures of the scores ``pred`` (S, C, K) on ``data``."""
    from twinrl.learn import sensing

    keep = ("rank_corr", "rank_corr_pooled", "success_q_choice", "success_mean_pose")
    f = sensing.evaluate_ranking(None, None, data, np.asarray(pred, np.float64))
    return {k: f[k] for k in keep}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="TASK=DIR, a twinrl run directory")
    p.add_argument("--states", type=int, nargs="+", default=[32, 64])
    p.add_argument("--test-states", type=int, default=40)
    p.add_argument("--cameras", type=int, default=8)
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--variants", nargs="+", default=["mse", "centred:4", "centred-only"])
    p.add_argument("--key", type=int, default=777_000)
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    weights = {v: _parse_variant(v) for v in args.variants}
    if min(args.states) < 1 or args.test_states < 2 or args.cameras < 2 or args.seeds < 1:
        raise SystemExit("--states and --seeds must be >= 1, --test-states and --cameras >= 2")
    from q_rank import load_run, parse_run  # noqa: E402  (bench/, beside this script)

    from twinrl.learn import sensing

    task, run = parse_run(args.run)
    _, env, actor, ap, q_run, qp_run, cfg = load_run(task, run)

    t0 = time.perf_counter()
    ident = dict(run=str(run.resolve()), train=max(args.states), test=args.test_states,
                 cameras=args.cameras, key=args.key)
    cache = args.out / "q_fit_data.pkl"
    stored = pickle.loads(cache.read_bytes()) if cache.exists() else None
    if stored is not None and stored["ident"] == ident:
        train, test = stored["train"], stored["test"]
        print(f"[bench] data from {cache}", flush=True)
    else:
        print(f"[bench] the actor's episodes: {args.test_states} held-out and {max(args.states)} "
              f"training states x {args.cameras} poses ...", flush=True)
        test = _data(env, actor, ap, cfg, args.key, args.test_states, args.cameras)
        train = _data(env, actor, ap, cfg, args.key + 1, max(args.states), args.cameras)
        args.out.mkdir(parents=True, exist_ok=True)
        cache.write_bytes(pickle.dumps({"ident": ident, "train": train, "test": test}))
    data_s = time.perf_counter() - t0

    rows = [{"states": cfg.states, "variant": "the run's Q",
             "seeds": 1, **_figures(sensing.q_predictions(q_run, qp_run, test), test)}]
    if "support" in test.obs:
        pixels = np.asarray(test.obs["support"])[..., 0]
        rows.append({"states": 0, "variant": "target pixels alone", "seeds": 1,
                     **_figures(pixels, test)})
    if "estimate" in test.obs:  # evaluation only: the hidden true state's estimate
        truth = jax.vmap(env.estimate_from_obs)(jax.vmap(env.reset)(
            _keys(args.key, args.test_states)[0]).obs)
        err = np.linalg.norm(np.asarray(test.obs["estimate"]) - np.asarray(truth)[:, None, None],
                             axis=-1)
        rows.append({"states": 0, "variant": "minus the estimate's true error (oracle)",
                     "seeds": 1, **_figures(-err, test)})
    q = sensing.make_q(actor, env.action_size, cfg)
    for S in args.states:
        for v, w in weights.items():
            t = time.perf_counter()
            per_seed = [_figures(sensing.q_predictions(q, fit(q, cfg, train, S, w, s)[0], test),
                                 test) for s in range(args.seeds)]
            ranks = [f["rank_corr"] for f in per_seed]
            row = {"states": S, "variant": v, "seeds": args.seeds,
                   **{k: float(np.mean([f[k] for f in per_seed])) for k in per_seed[0]},
                   "rank_corr_range": [min(ranks), max(ranks)], "per_seed": per_seed,
                   "fit_s": (time.perf_counter() - t) / args.seeds}
            rows.append(row)
            print(f"[bench] {S} states, {v}: rank {row['rank_corr']:.2f} "
                  f"({min(ranks):.2f} .. {max(ranks):.2f})", flush=True)
    out = {"meta": run_meta(args), "task": task, "run": str(run), "config": cfg.to_dict(),
           "data_s": data_s, "rows": rows}
    write_json(args.out / "q_fit.json", out)
    print_table(f"Q fits on {task}: rank correlation across {args.cameras} poses of "
                f"{args.test_states} held-out states (identified twin)",
                ["train states", "variant", "seeds", "rank per state (seed range)", "pooled",
                 "success: Q's pose / mean pose"],
                [[r["states"] or "-", r["variant"], r["seeds"],
                  f"{r['rank_corr']:.2f}" + (" ({:.2f} .. {:.2f})".format(*r["rank_corr_range"])
                                             if "rank_corr_range" in r else ""),
                  f"{r['rank_corr_pooled']:.2f}",
                  f"{r['success_q_choice']:.2f} / {r['success_mean_pose']:.2f}"] for r in rows])
    print(f"wrote {args.out / 'q_fit.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
