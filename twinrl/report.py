"""Human and machine outputs of every command: ``summary.json``, tables, and (later) plots/videos.

Every command that produces results writes ``DIR/summary.json`` (machine-readable figures) and
prints the same figures as a table. JSON is written atomically (tmp file + rename) so a killed
command never leaves a half-written summary.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import sys
import warnings
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from rich.console import Console
from rich.table import Table

__all__ = ["to_jsonable", "run_meta", "write_json", "print_table", "console", "MetricsWriter", "plot_curves",
           "write_video", "text_stamp", "label_frames", "compose_frame", "pct", "cell",
           "md_table", "plot_param_errors", "loop_report", "MISSING", "wilson_interval"]

# Not a terminal (CI logs, pipes): rich would wrap tables at 80 columns; logs can be wide.
console = Console(stderr=False, highlight=False,
                  width=None if sys.stdout.isatty() else 160)


def to_jsonable(x: Any) -> Any:
    """Convert numpy/JAX scalars and arrays, dataclasses (and nested containers) to JSON types."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: to_jsonable(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if hasattr(x, "__array__") and not isinstance(x, (str, bytes)):
        a = np.asarray(x)
        return to_jsonable(a.item()) if a.ndim == 0 else to_jsonable(a.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else (1e308 if x > 0 else -1e308)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


def run_meta(args=None) -> dict[str, Any]:
    """What a benchmark's JSON records of the run: versions, device, machine, Python, CPU count
    and (``argparse.Namespace``) its arguments as strings."""
    import platform

    import jax
    import mujoco

    import twinrl

    meta = {"jax": jax.__version__, "mujoco": mujoco.__version__, "twinrl": twinrl.__version__,
            "device": str(jax.devices()[0]), "machine": platform.machine(),
            "python": sys.version.split()[0], "cpu_count": os.cpu_count()}
    if args is not None:
        meta["args"] = {k: str(v) for k, v in vars(args).items()}
    return meta


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically and durably: the temporary file is fsync'd
    before the rename (else a power loss can leave the new name on empty or partial contents) and
    the directory after it (else the rename itself can be lost)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w") as f:
        f.write(json.dumps(to_jsonable(data), indent=2) + "\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    return path


def print_table(title: str, columns: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    """Print a table; floats in compact scientific or fixed notation."""
    table = Table(title=title, title_justify="left")
    for c in columns:
        table.add_column(c, justify="left" if c in columns[:1] else "right")
    for row in rows:
        table.add_row(*[_fmt(v) for v in row])
    console.print(table)


MISSING = "—"
"""How a table shows a missing value (None: a figure that was not measured). NaN stays "nan": it
is a result (a diverged run), not an absence."""


def _fmt(v: Any) -> str:
    if v is None:
        return MISSING
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if v == 0:
            return "0"
        return f"{v:.2e}" if (abs(v) < 1e-2 or abs(v) >= 1e5) else f"{v:.4g}"
    return str(v)


class MetricsWriter:
    """Per-epoch metrics to ``metrics.csv`` and TensorBoard event files in ``directory``.

    The CSV gains a row per ``write`` and is flushed each time, so a killed run keeps every epoch
    it finished; a resumed run opens it again and rewrites it from the restored history
    (``rewrite``), so the file never holds epochs the restored state did not reach.
    """

    def __init__(self, directory: str | os.PathLike, tensorboard: bool = True):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.path = self.directory / "metrics.csv"
        self._columns: list[str] | None = None
        self._tb = None
        if tensorboard:
            from tensorboardX import SummaryWriter

            self._tb = SummaryWriter(str(self.directory / "tb"), flush_secs=10)

    def rewrite(self, history: dict[str, list[float]]) -> None:
        """Replace the CSV by ``history`` (column -> per-epoch values)."""
        self._columns = list(history)
        n = max((len(v) for v in history.values()), default=0)
        tmp = self.path.with_suffix(".csv.tmp")
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(self._columns)
            for i in range(n):
                w.writerow([_csv(history[c][i]) if i < len(history[c]) else "" for c in self._columns])
        os.replace(tmp, self.path)

    def write(self, step: int, row: dict[str, Any]) -> None:
        row = {k: float(np.asarray(v)) for k, v in row.items()}
        if self._columns is None:
            self._columns = list(row)
            with open(self.path, "w", newline="") as f:
                csv.writer(f).writerow(self._columns)
        with open(self.path, "a", newline="") as f:
            csv.writer(f).writerow([_csv(row.get(c, "")) for c in self._columns])
        if self._tb is not None:
            for k, v in row.items():
                if math.isfinite(v):
                    self._tb.add_scalar(k, v, global_step=int(step))

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
            self._tb = None


def _csv(v: Any) -> str:
    return repr(float(v)) if isinstance(v, (float, int, np.floating, np.integer)) else str(v)


def plot_curves(path: str | os.PathLike, curves: dict[str, tuple[Sequence[float], Sequence[float]]],
                xlabel: str, ylabel: str, title: str = "",
                bands: dict[str, tuple[Sequence[float], Sequence[float]]] | None = None,
                hline: tuple[float, str] | None = None) -> Path:
    """Line plot of ``{label: (x, y)}`` to a PNG (Agg backend); optional ``bands`` (lo, hi) per
    label and a dashed horizontal reference line ``(value, label)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=120)
    for label, (x, y) in curves.items():
        # few points (a loop's rounds): mark them, or a single point would not show at all
        line, = ax.plot(np.asarray(x, float), np.asarray(y, float), label=label,
                        marker="o" if len(x) <= 20 else None)
        if bands and label in bands:
            lo, hi = bands[label]
            ax.fill_between(np.asarray(x, float), lo, hi, color=line.get_color(), alpha=0.2)
    if hline is not None:
        ax.axhline(hline[0], ls="--", color="k", lw=1, label=hline[1])
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)



def _save(fig, path) -> Path:
    """Lay out, write (creating the folder) and close a figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path

def write_video(path: str | os.PathLike, frames: Sequence[np.ndarray], fps: float) -> Path:
    """Write RGB frames as MP4 (H.264 via imageio-ffmpeg); GIF beside it if ffmpeg is missing.
    Returns the path actually written."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = [np.asarray(f, np.uint8) for f in frames]
    if not frames:
        raise ValueError(f"{path}: no frames to write")
    try:
        with warnings.catch_warnings():
            # imageio starts ffmpeg with subprocess (fork + exec at once): JAX's at-fork hook
            # warns of a deadlock that an exec'd child cannot reach
            warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called",
                                    category=RuntimeWarning)
            imageio.mimsave(path, frames, fps=fps, macro_block_size=1)
        return path
    except Exception:  # noqa: BLE001 - no ffmpeg backend
        gif = path.with_suffix(".gif")
        imageio.mimsave(gif, frames, duration=1000.0 / fps)
        return gif


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a success rate ``successes / n`` (95 % by default)."""
    if n < 1:
        return (float("nan"), float("nan"))
    p = successes / n
    d = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / d
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (float(max(0.0, centre - half)), float(min(1.0, centre + half)))


# ------------------------------------------------------------------------------ the loop's report
def pct(x: float | None) -> str:
    """A fraction as a percentage with one decimal (``MISSING`` for None or not finite)."""
    return MISSING if x is None or not math.isfinite(float(x)) else f"{100 * float(x):.1f} %"


def cell(v: Any) -> str:
    """A Markdown table's cell: the table's number format, ``MISSING`` for None and NaN."""
    s = _fmt(v)
    return MISSING if s in ("nan", "None") else s


def md_table(columns: Sequence[str], rows: Iterable[Sequence[Any]]) -> list[str]:
    """A Markdown table's lines (cells: ``cell``)."""
    out = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    out += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return out


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_loop_returns(path: str | os.PathLike, summary: dict,
                      model_free: Sequence[dict] = ()) -> Path:
    """``returns.png`` of a loop run, informative with a single round: left, each round's learning
    curve in its identified simulator (return vs simulated steps); right, the real twin: every
    recorded episode of each deployed policy and their mean, the sim policy without adaptation
    (evaluation), against the real steps used so far, with the oracle's return as a dashed line
    and, when given, the model-free learners' curves on the real twin (``bench/sim2real.py``'s
    runs: ``{"algo", "seed", "curve": [{"real_steps", "return"}]}``)."""
    plt = _pyplot()
    rounds = [r for r in summary["rounds"] if r.get("round", 0) >= 1]
    oracle = summary["rounds"][0].get("oracle_return") if summary["rounds"] else None
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2), dpi=110)
    for r in rounds:
        c = r.get("learning_curve") or {}
        if c.get("env_steps"):
            ax1.plot(np.asarray(c["env_steps"], float) / 1e6, c["return"], marker=".",
                     label=f"round {r['round']} ({summary['config'].get('algo', '')})")
    if oracle is not None:
        for ax in (ax1, ax2):
            ax.axhline(oracle, ls="--", color="k", lw=1, label="oracle (real twin)")
    ax1.set_xlabel("simulated steps (millions)")
    ax1.set_ylabel("episode return")
    ax1.set_title("learning in the identified simulator", fontsize=10)
    for i, r in enumerate(rounds):
        x = r.get("real_steps")
        if x is None or r.get("real_return") is None:
            continue
        eps = r.get("real_returns") or []
        ax2.scatter([x] * len(eps), eps, s=14, color="C0", alpha=0.5,
                    label="deployed: each real episode" if i == 0 else None)
        ax2.scatter([x], [r["real_return"]], s=70, marker="D", color="C0", zorder=3,
                    label="deployed: mean" if i == 0 else None)
        if r.get("sim_policy_real_return") is not None:
            ax2.scatter([x], [r["sim_policy_real_return"]], s=60, marker="x", color="C3",
                        zorder=3, label="sim policy, no adaptation (eval)" if i == 0 else None)
        ax2.annotate(f"round {r['round']}", (x, r["real_return"]), textcoords="offset points",
                     xytext=(6, -12), fontsize=8)
    for j, m in enumerate(model_free):
        curve = m.get("curve") or []
        if curve:
            ax2.plot([p["real_steps"] for p in curve], [p["return"] for p in curve],
                     color=f"C{4 + j}", lw=1.2, label=f"{m.get('algo', '?')} (model-free, "
                     f"seed {m.get('seed', '?')})")
    ax2.set_xlabel("real-twin steps used")
    ax2.set_ylabel("episode return on the real twin")
    ax2.set_title("deployed on the real twin", fontsize=10)
    steps = [r["real_steps"] for r in rounds if r.get("real_steps")]
    if steps and not model_free:
        ax2.set_xlim(0, max(steps) * 1.25)
        # the deployed returns and the oracle, a few per cent apart, with room around them
        vals = [v for r in rounds for v in ([r.get("real_return"), r.get("sim_policy_real_return"),
                                             oracle] + list(r.get("real_returns") or []))
                if v is not None and math.isfinite(float(v))]
        if vals:
            pad = 0.03 * max(abs(max(vals)), abs(min(vals)), 1e-9)
            ax2.set_ylim(min(vals) - pad, max(vals) + pad)
    for ax, where in ((ax1, "lower right"), (ax2, "best")):  # best: off the few points
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc=where)
    fig.suptitle(f"{summary['env']} (seed {summary['seed']})", fontsize=11)
    return _save(fig, path)


def plot_param_errors(path: str | os.PathLike, identified: Sequence[dict],
                      errors: dict[str, float], title: str = "") -> Path:
    """``params.png``: a horizontal bar per identified parameter, its relative error against the
    hidden truth (evaluation only), with the fit's own uncertainty as an error bar (``sd`` over
    the larger of the identified and nominal values, so a value at its bound 0 does not divide by
    0). Parameters the data fix only in combination are hatched and carry no bar: their error is
    after the common scale, and their sd (written beside them) is along the flat direction, the
    scale the data do not fix."""
    plt = _pyplot()
    by_name = {row["parameter"]: row for row in identified}
    names = list(errors)
    err = np.array([100 * abs(float(errors[n])) for n in names])

    def rel_sd(n):
        row = by_name.get(n)
        if row is None or row.get("sd") is None:
            return np.nan
        scale = max(abs(float(row.get("identified") or 0)), abs(float(row.get("initial") or 0)))
        return 100 * float(row["sd"]) / scale if scale > 0 else np.nan

    sd = np.array([rel_sd(n) for n in names])
    combo = np.array([str(by_name.get(n, {}).get("status", "")).startswith("only in combination")
                      for n in names])
    bar_sd = np.where(np.isfinite(sd) & ~combo, sd, 0.0)
    fig, ax = plt.subplots(figsize=(7.5, 0.45 * len(names) + 1.6), dpi=110)
    y = np.arange(len(names))
    bars = ax.barh(y, err, color=["C1" if c else "C0" for c in combo], alpha=0.85,
                   label="|identified - truth| / truth")
    for b, c in zip(bars, combo):
        if c:
            b.set_hatch("//")
    ax.errorbar(err, y, xerr=bar_sd, fmt="none", ecolor="k", elinewidth=1, capsize=3,
                label="+- the fit's sd (relative)")
    for yi, n in enumerate(names):
        if not np.isfinite(sd[yi]):
            note = f"{err[yi]:.2g} %"
        elif combo[yi]:
            note = f"{err[yi]:.2g} %  (alone: sd {sd[yi]:.0f} %, flat direction)"
        else:
            note = f"{err[yi]:.2g} %  (sd {sd[yi]:.2g} %)"
        ax.text(err[yi] + bar_sd[yi], yi, "  " + note, va="center", fontsize=7)
    ax.set_yticks(y, names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("relative error (%)")
    ax.set_xlim(0, max(float(np.max(err + bar_sd)) * 1.8 if len(err) else 1.0, 1.0))
    ax.set_title(title or "identified parameters vs the hidden truth (evaluation only)",
                 fontsize=10)
    from matplotlib.patches import Patch

    handles, labels = ax.get_legend_handles_labels()
    if combo.any():
        handles.append(Patch(facecolor="C1", hatch="//", alpha=0.85))
        labels.append("identified only in combination (error after the common scale)")
    ax.legend(handles, labels, fontsize=7, loc="lower right")
    ax.grid(alpha=0.3, axis="x")
    return _save(fig, path)


def text_stamp(text: str, width: int, height: int = 22) -> np.ndarray:
    """``(height, width, 3)`` uint8: ``text`` in white on black, left-aligned, rendered with
    matplotlib (a video frame's label or caption)."""
    plt = _pyplot()
    fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    fig.patch.set_facecolor("black")
    fig.text(0.01 if width > 300 else 0.02, 0.5, text, color="white",
             fontsize=max(7, height * 0.45), va="center", ha="left", family="DejaVu Sans")
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    out = np.zeros((height, width, 3), np.uint8)
    out[:min(height, img.shape[0]), :min(width, img.shape[1])] = img[:height, :width]
    return out


def label_frames(frames: Sequence[np.ndarray], labels: Sequence[str],
                 band: int = 22) -> list[np.ndarray]:
    """Burn one label per horizontal panel into each frame (a dark band at the top of each
    panel, white text rendered once with matplotlib). ``frames`` are side-by-side panels of equal
    width, ``len(labels)`` of them."""
    if not frames:
        return []
    h, w = frames[0].shape[:2]
    pw = w // len(labels)
    stamps = [text_stamp(text, pw, band) for text in labels]
    out = []
    for f in frames:
        f = np.array(f, np.uint8, copy=True)
        for i, s in enumerate(stamps):
            f[:s.shape[0], i * pw:i * pw + s.shape[1]] = s
        out.append(f)
    return out


def compose_frame(panels: Sequence[np.ndarray], labels: Sequence[str], caption: str = "",
                  height: int | None = None, band: int = 22) -> np.ndarray:
    """One video frame: the RGB ``panels`` side by side, each scaled by a whole factor (nearest
    neighbour, so a small camera image keeps its pixels) to ``height`` (default: the tallest
    panel's; a panel that does not divide it is padded below), each under a dark band with its
    label, and ``caption`` in a band under them all (none when empty). uint8 ``(band + height
    [+ band], sum of the scaled widths, 3)``."""
    if not panels or len(panels) != len(labels):
        raise ValueError(f"compose_frame: {len(panels)} panels for {len(labels)} labels")
    panels = [np.asarray(p) for p in panels]
    panels = [(np.clip(p, 0, 1) * 255).astype(np.uint8) if p.dtype.kind == "f" else
              p.astype(np.uint8) for p in panels]
    H = int(height or max(p.shape[0] for p in panels))
    cols = []
    for p, label in zip(panels, labels):
        k = max(1, H // p.shape[0])
        p = np.repeat(np.repeat(p[..., :3], k, 0), k, 1)[:H]
        p = np.pad(p, ((0, H - p.shape[0]), (0, 0), (0, 0)))
        cols.append(np.concatenate([text_stamp(label, p.shape[1], band), p], 0))
    frame = np.concatenate(cols, 1)
    if caption:
        frame = np.concatenate([frame, text_stamp(caption, frame.shape[1], band)], 0)
    return frame


def _compare_section(rounds: Sequence[dict]) -> list[str]:
    """The report's lines on learning wall clock against a second learner (``twinrl run
    --compare ppo``): per round, both learners' seconds and sim returns, and when the deployed one
    first reached the other's final return."""
    rows = []
    for r in rounds:
        c = r.get("compare")
        if not c:
            continue
        reach, theirs = c.get("deployed_s_to_compare_final"), c.get("learn_s")
        frac = reach / theirs if reach is not None and theirs else None
        rows.append([r["round"], f"`{c.get('deployed_algo')}`", c.get("deployed_learn_s"),
                     r.get("sim_return"), f"`{c.get('algo')}`", theirs, c.get("sim_return"),
                     reach, pct(frac) if frac is not None else "never"])
    if not rows:
        return []
    return (["## Learning wall clock against a second learner", "",
             "Both learners trained on the same round's identified simulator (seconds of "
             "learning, compilation included); only the first is deployed."] + [""] +
            md_table(["round", "deployed learner", "seconds", "sim return", "compared with",
                      "seconds", "sim return", "s to its final return", "of its time"], rows)
            + [""])


def loop_report(out: str | os.PathLike, summary: dict,
                model_free: Sequence[dict] = ()) -> dict[str, Path]:
    """``report.md`` of a ``twinrl run`` (plus ``returns.png`` and, when the summary has
    evaluation errors, ``params.png``) from its summary dict alone: what was run, the verdict
    (fraction of the oracle, real steps), what was identified with its uncertainty, the figures
    inline. Returns the files written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = summary.get("config", {})
    rounds = summary["rounds"]
    final = summary.get("final", {})
    done = [r for r in rounds if r.get("round", 0) >= 1]
    files: dict[str, Path] = {}
    if done:
        files["returns"] = plot_loop_returns(out / "returns.png", summary, model_free)
    last = done[-1] if done else {}
    if last.get("param_rel_error") and last.get("identified"):
        files["params"] = plot_param_errors(out / "params.png", last["identified"],
                                            last["param_rel_error"])
    env, seed = summary["env"], summary["seed"]
    md = [f"# twinrl run: {env} (seed {seed})", ""]

    # the verdict
    frac, oracle = final.get("fraction_of_oracle"), rounds[0].get("oracle_return")
    if final.get("real_return") is not None:
        v = (f"**Verdict:** after {len(done)} round{'s' * (len(done) != 1)} and "
             f"{final.get('real_steps')} real-twin steps, the deployed policy returns "
             f"{cell(final['real_return'])} on the real twin")
        v += (f", **{pct(frac)} of the oracle** ({cell(oracle)}: a policy trained the same way "
              f"on the twin's true parameters, evaluation only)." if frac is not None else
              " (no oracle was trained: `--no-oracle`).")
        md += [v, ""]
    else:
        md += ["**Verdict:** no round finished; nothing was deployed.", ""]

    # what was run
    K = cfg.get("episodes_per_round")
    steps0 = rounds[0].get("real_steps")
    md += ["## What was run", "",
           f"- **Round 0**: {K} episodes of exciting open-loop actions on the real twin "
           f"({steps0} steps).",
           f"- **Each of {len(done)} round(s)**: system identification on every real transition "
           f"so far; {'the hybrid residual dynamics refit; ' if cfg.get('hybrid') else ''}"
           f"learning with `{cfg.get('algo')}` in the identified simulator"
           + ("; a residual policy trained through the hybrid model, kept only if it does not "
              "lower the return there" if cfg.get("residual") else "") +
           f"; {K} deployed episodes recorded on the real twin.",
           f"- **Evaluation only** (never fed back): the oracle, the parameter errors against "
           f"the hidden truth, and {cfg.get('eval_episodes')} unrecorded episodes per policy.",
           ""]
    rows = [[r["round"], r.get("real_steps"), r.get("sim_return"), r.get("real_return"),
             r.get("sim_policy_real_return"), r.get("adapted_real_return"),
             {True: "accepted", False: "rejected"}.get(r.get("residual_accepted")),
             sum((r.get("seconds") or {}).values()) or None] for r in rounds]
    md += md_table(["round", "real steps (total)", "sim return", "real return (deployed)",
                     "sim policy, no adaptation (eval)", "adapted (eval)", "residual",
                     "seconds"], rows)
    md += [""]
    md += _compare_section(rounds)
    if "returns" in files:
        md += ["![returns: learning curve in the identified simulator; real returns of each "
               "deployed policy vs the oracle](returns.png)", ""]

    # what was identified
    if last.get("identified"):
        errs = last.get("param_rel_error") or {}
        md += [f"## What was identified (round {last['round']})", "",
               "Values the fit found, with its own standard deviation (from the curvature of "
               "the loss); the error against the hidden truth is evaluation only.", ""]
        prow = [[row["parameter"], row.get("initial"),
                 f"{cell(row.get('identified'))} ± {cell(row.get('sd'))}", row.get("status"),
                 pct(errs.get(row["parameter"]))] for row in last["identified"]]
        if last.get("latency") is not None:
            prow.append(["latency (steps)", None, last["latency"], "searched",
                         pct(errs.get("latency"))])
        md += md_table(["parameter", "nominal", "identified ± sd", "status",
                         "error vs truth (eval)"], prow)
        md += [""]
        if any(str(row.get("status", "")).startswith("only in combination")
               for row in last["identified"]):
            md += ["*Only in combination*: the data fix these parameters' ratios, not their "
                   "common scale (a flat direction of the loss), so each one's sd alone is "
                   "large; their errors are measured after that common scale.", ""]
        if "params" in files:
            md += ["![params: relative error of each identified parameter with the fit's "
                   "uncertainty](params.png)", ""]
    if summary.get("video"):
        md += ["## Video", "",
               f"[{Path(summary['video']).name}]({Path(summary['video']).name}): the final "
               "deployed policy on the real twin (left, labelled *real twin*, its true camera) "
               "beside the identified simulator from the same start state (right, labelled "
               "*identified simulator*). Neither episode is recorded.", ""]
    if model_free:
        md += [f"Model-free curves in `returns.png`: {len(model_free)} run(s) of "
               f"`bench/sim2real.py` on this task and seed.", ""]
    md += [f"Machine-readable figures: `summary.json`. Wall clock of this process: "
           f"{cell(summary.get('wall_s_this_process'))} s.", ""]
    (out / "report.md").write_text("\n".join(md))
    files["report"] = out / "report.md"
    return files
