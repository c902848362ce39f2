"""Errors of the dataset, and the checks of what a writer is given and what ``meta.json`` holds.

Every check raises ``ValueError`` naming the offending field and what is allowed, before anything
is written; ``read_meta`` raises ``DatasetError`` naming ``meta.json``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from twinrl.real.dataset._format import FORMAT, IMAGE_DTYPES, META_FILE, META_KEYS, VERSION


class DatasetError(Exception):
    """A dataset directory is missing, corrupt, truncated or busy; the message names the file.

    ``problems`` lists every problem found (each naming its file), when there were several.
    """

    def __init__(self, message: str, problems: Sequence[str] = ()):
        super().__init__(message)
        self.problems = list(problems) or [message]


class DatasetMismatch(ValueError):
    """Continuing a dataset with other settings than it was recorded with; ``key`` names the
    setting (``"image_shapes"``, ``"obs_shape"``, ...), the message both values and the file."""

    def __init__(self, message: str, key: str):
        super().__init__(message)
        self.key = key



def check_shape(name: str, value: Any) -> tuple[int, ...]:
    """``value`` (an int or a sequence of ints) as a shape tuple; ValueError naming ``name``."""
    dims = (value,) if isinstance(value, (int, np.integer)) else value
    try:
        out = tuple(int(d) for d in dims)
        ok = all(not isinstance(d, bool) and int(d) == d and int(d) >= 0 for d in dims)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{name}={value!r}; expected a tuple of non-negative integers")
    return out


def check_real_dtype(name: str, value: Any) -> np.dtype:
    """``value`` as a little-endian float, integer or bool dtype; ValueError naming ``name``."""
    try:
        dtype = np.dtype(value)
    except TypeError as e:
        raise ValueError(f"{name}={value!r} is not a numpy dtype") from e
    if dtype.kind not in "fiub":
        raise ValueError(f"{name}={dtype}; expected a float, integer or bool dtype")
    return dtype.newbyteorder("<")


def check_image_shapes(image_shapes: Mapping[str, Sequence[int]]) -> dict[str, list[int]]:
    """``image_shapes`` checked (known kind, optional ``/camera``; (H, W, 3) RGB, (H, W) others),
    as JSON lists."""
    out = {}
    for key, shape in image_shapes.items():
        kind = key.split("/", 1)[0] if isinstance(key, str) else None
        if kind not in IMAGE_DTYPES or (isinstance(key, str) and key.endswith("/")):
            raise ValueError(
                f"image_shapes key {key!r}; expected one of {', '.join(IMAGE_DTYPES)}, optionally "
                "followed by /camera (e.g. 'rgb/wrist')"
            )
        dims = check_shape(f"image_shapes[{key!r}]", shape)
        rank_ok = len(dims) == 3 and dims[2] == 3 if kind == "rgb" else len(dims) == 2
        if not rank_ok:
            want = "(H, W, 3)" if kind == "rgb" else "(H, W)"
            raise ValueError(f"image_shapes[{key!r}]={dims}; {kind} images have shape {want}")
        out[key] = list(dims)
    return out


def check_array(
    name: str,
    value: Any,
    shape: tuple[int, ...],
    dtype: np.dtype,
    casting: str,
    finite: bool = False,
) -> np.ndarray:
    """``value`` as a C-contiguous array of ``dtype`` and ``shape`` (cast per ``casting``; with
    ``finite``, NaN and inf refused); ValueError naming ``name``."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} is not an array: {e}") from e
    if a.shape != shape:
        raise ValueError(f"{name} has shape {a.shape}; expected {shape}")
    if not np.can_cast(a.dtype, dtype, casting=casting):
        raise ValueError(
            f"{name} has dtype {a.dtype}; expected {dtype} (or a dtype that converts {casting})"
        )
    a = np.asarray(a, dtype=dtype, order="C")  # not ascontiguousarray: it makes 0-d arrays 1-d
    if finite and a.dtype.kind == "f" and not np.isfinite(a).all():
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(
            f"{name} is not finite at index {bad} (value {a[bad]}); NaN and inf are not recorded"
        )
    return a


def check_finite_scalar(name: str, value: Any) -> float:
    """``value`` as a finite float; ValueError naming ``name``."""
    a = np.asarray(value)
    if a.shape != () or a.dtype.kind not in "fiub":
        raise ValueError(f"{name}={value!r}; expected a real scalar")
    out = float(a)
    if not math.isfinite(out):
        raise ValueError(f"{name}={out}; expected a finite number")
    return out


def check_flag(name: str, value: Any) -> bool:
    """``value`` (bool, or an integer 0/1) as a bool; ValueError naming ``name``."""
    a = np.asarray(value)
    if a.shape == () and a.dtype.kind in "biu" and a.item() in (0, 1):
        return bool(a.item())
    raise ValueError(f"{name}={value!r}; expected a bool")


def json_safe(value: Any, where: str) -> Any:
    """``value`` with numpy scalars/arrays turned into JSON types; ValueError naming ``where``."""
    if value is None or isinstance(value, (str, bool, int, float)):
        return value
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist(), where)
    if isinstance(value, np.generic):
        return json_safe(value.item(), where)
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                # json.dumps would turn the key into a string, so it would not read back as written.
                raise ValueError(
                    f"{where} has key {k!r} of type {type(k).__name__}; keys must be str"
                )
            out[k] = json_safe(v, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [json_safe(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise ValueError(
        f"{where} has type {type(value).__name__}, which is not JSON-serialisable; use str, int, "
        "float, bool, None and lists/dicts of them (numpy scalars and arrays are converted)"
    )


def read_meta(root: Path) -> dict[str, Any]:
    """The checked contents of ``root``'s ``meta.json``; DatasetError naming the file otherwise."""
    meta_path = root / META_FILE
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DatasetError(f"no dataset at {root}: {meta_path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(f"{meta_path} is unreadable: {e}") from e
    found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
    if found != FORMAT:
        raise DatasetError(f"{meta_path} is not a {FORMAT} meta file (format={found!r})")
    if meta.get("version") != VERSION:
        raise DatasetError(
            f"{meta_path} has format version {meta.get('version')!r}; "
            f"this reader knows version {VERSION}"
        )
    missing = [k for k in (*META_KEYS, "metadata") if k not in meta]
    if missing:
        raise DatasetError(f"{meta_path} lacks {', '.join(missing)}")
    try:
        check_shape("obs_shape", meta["obs_shape"])
        check_shape("action_shape", meta["action_shape"])
        check_real_dtype("obs_dtype", meta["obs_dtype"])
        check_real_dtype("action_dtype", meta["action_dtype"])
        check_image_shapes(meta["image_shapes"])
    except (ValueError, AttributeError) as e:
        raise DatasetError(f"{meta_path}: {e}") from e
    return meta
