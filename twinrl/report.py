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
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from rich.console import Console
from rich.table import Table

__all__ = ["to_jsonable", "write_json", "print_table", "console", "MetricsWriter", "plot_curves",
           "write_video"]

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
        imageio.mimsave(path, frames, fps=fps, macro_block_size=1)
        return path
    except Exception:  # noqa: BLE001 - no ffmpeg backend
        gif = path.with_suffix(".gif")
        imageio.mimsave(gif, frames, duration=1000.0 / fps)
        return gif
