"""Human and machine outputs of every command: ``summary.json``, tables, and (later) plots/videos.

Every command that produces results writes ``DIR/summary.json`` (machine-readable figures) and
prints the same figures as a table. JSON is written atomically (tmp file + rename) so a killed
command never leaves a half-written summary.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from rich.console import Console
from rich.table import Table

__all__ = ["to_jsonable", "write_json", "print_table", "console"]

# Not a terminal (CI logs, pipes): rich would wrap tables at 80 columns; logs can be wide.
console = Console(stderr=False, highlight=False,
                  width=None if sys.stdout.isatty() else 160)


def to_jsonable(x: Any) -> Any:
    """Convert numpy/JAX scalars and arrays (and nested containers) to JSON types."""
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
    """Write ``data`` as indented JSON, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(to_jsonable(data), indent=2) + "\n")
    os.replace(tmp, path)
    return path


def print_table(title: str, columns: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    """Print a table; floats in compact scientific or fixed notation."""
    table = Table(title=title, title_justify="left")
    for c in columns:
        table.add_column(c, justify="left" if c in columns[:1] else "right")
    for row in rows:
        table.add_row(*[_fmt(v) for v in row])
    console.print(table)


def _fmt(v: Any) -> str:
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if v == 0:
            return "0"
        return f"{v:.2e}" if (abs(v) < 1e-2 or abs(v) >= 1e5) else f"{v:.4g}"
    return str(v)
