"""The on-disk format of a dataset: names, magics, and the record codec both sides share.

A chunk is ``FILE_MAGIC`` followed by self-delimiting records (``PREFIX`` + CRC, JSON header, raw
array body); see ``twinrl.real.dataset`` for the layout and why it is this one. The writer
encodes records with ``encode_record``; the reader and a resuming writer walk a chunk with
``scan_chunk``, which drops a torn tail and resynchronises after damage.
"""

from __future__ import annotations

import json
import re
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = "twinrl.real.dataset"  # the format's name in meta.json
VERSION = 1
META_FILE = "meta.json"
LOCK_FILE = ".lock"
FILE_MAGIC = b"TWRLDS\x00\x01"
RECORD_MAGIC = b"TRec"
PREFIX = struct.Struct("<4sIQII")  # magic, header length, body length, header crc, body crc
PREFIX_CRC = struct.Struct("<I")
PREFIX_SIZE = PREFIX.size + PREFIX_CRC.size
# A header this long is damage that happens to pass the prefix CRC check, not a real header.
MAX_HEADER = 1 << 24
CHUNK_RE = re.compile(r"^chunk-(\d{5,})-(\d{5,})\.twr(\.open)?$")

IMAGE_DTYPES: dict[str, np.dtype] = {
    "rgb": np.dtype(np.uint8),
    "depth": np.dtype("<f4"),
    "segmentation": np.dtype("<i4"),
}
"""Image kinds and their stored dtypes; an image key is a kind, optionally ``kind/camera``."""

META_KEYS = ("env", "obs_shape", "obs_dtype", "action_shape", "action_dtype", "image_shapes")
"""The recorded settings a continuing writer must match (``meta.json`` keys)."""


def encode_record(header: dict[str, Any], arrays: list[tuple[str, np.ndarray]]) -> bytes:
    """One record's bytes: checksummed prefix, JSON header (with the arrays' names, dtypes and
    shapes) and the arrays' raw bytes."""
    if arrays:
        header = {**header, "arrays": [[name, a.dtype.str, list(a.shape)] for name, a in arrays]}
    hbytes = json.dumps(header, separators=(",", ":")).encode("utf-8")
    body = b"".join(a.tobytes() for _, a in arrays)
    prefix = PREFIX.pack(
        RECORD_MAGIC, len(hbytes), len(body), zlib.crc32(hbytes), zlib.crc32(body)
    )
    return prefix + PREFIX_CRC.pack(zlib.crc32(prefix)) + hbytes + body


def list_chunks(root: Path) -> list[tuple[int, int, bool, Path]]:
    """(session, index, is_open, path) of every chunk file, in recording order."""
    out = []
    for p in root.iterdir():
        m = CHUNK_RE.match(p.name)
        if m:
            out.append((int(m[1]), int(m[2]), m[3] is not None, p))
    return sorted(out)


def read_prefix(data: bytes, pos: int) -> tuple[int, int, int, int] | None:
    """(header length, body length, header crc, body crc) of the record prefix at ``pos``, or
    None when there is no intact prefix there (wrong magic, implausible length, bad CRC)."""
    if len(data) - pos < PREFIX_SIZE:
        return None
    magic, hlen, blen, hcrc, bcrc = PREFIX.unpack_from(data, pos)
    if magic != RECORD_MAGIC or hlen > MAX_HEADER:
        return None
    (pcrc,) = PREFIX_CRC.unpack_from(data, pos + PREFIX.size)
    if pcrc != zlib.crc32(data[pos : pos + PREFIX.size]):
        return None
    return hlen, blen, hcrc, bcrc


def resync(data: bytes, start: int) -> int:
    """Offset of the next valid record prefix at or after ``start`` (``len(data)`` if none)."""
    while True:
        i = data.find(RECORD_MAGIC, start)
        if i < 0:
            return len(data)
        if read_prefix(data, i) is not None:
            return i
        start = i + 1


def scan_chunk(
    file: Path, data: bytes, closed: bool, problems: list[str]
) -> list[tuple[int, dict[str, Any], memoryview]]:
    """(offset, header, body) of every intact non-footer record; damage is appended to ``problems``.

    ``closed``: the file has the ``.twr`` name, so it must end with a footer; an ``.open`` chunk may
    end in a torn record (a killed writer), which is dropped without a problem.
    """
    view = memoryview(data)
    records: list[tuple[int, dict[str, Any], memoryview]] = []
    footer: dict[str, Any] | None = None
    if data[: len(FILE_MAGIC)] == FILE_MAGIC:
        pos = len(FILE_MAGIC)
    elif not closed and FILE_MAGIC.startswith(data):
        return records  # killed while creating the chunk
    else:
        problems.append(f"{file}: bad file magic (not a twinrl chunk, or its start is damaged)")
        pos = resync(data, 0)

    def torn(pos: int, why: str) -> None:
        if closed:
            problems.append(f"{file}: truncated: {why}")

    def zero_filled_tail(pos: int) -> bool:
        # Power loss after unsynced appends leaves the file at its new length with the unwritten
        # blocks read back as zeros: an unreadable record at ``pos`` with no record after it, in a
        # file that ends in zero bytes. In an ``.open`` chunk that is a torn tail, not damage.
        return not closed and data[-1:] == b"\0" and resync(data, pos + 1) == len(data)

    while pos < len(data):
        if footer is not None:
            problems.append(
                f"{file}: {len(data) - pos} unexpected bytes after the footer at offset {pos}"
            )
            break
        remaining = len(data) - pos
        if remaining < PREFIX_SIZE and RECORD_MAGIC.startswith(
            data[pos : pos + min(remaining, len(RECORD_MAGIC))]
        ):
            torn(pos, f"the file ends {remaining} bytes into the record header at offset {pos}")
            break
        prefix = read_prefix(data, pos)
        if prefix is None and zero_filled_tail(pos):
            break
        if prefix is None:
            nxt = resync(data, pos + 1)
            problems.append(
                f"{file}: damaged record header at offset {pos}; skipped {nxt - pos} bytes"
            )
            pos = nxt
            continue
        hlen, blen, hcrc, bcrc = prefix
        start = pos + PREFIX_SIZE
        end = start + hlen + blen
        if end > len(data):
            torn(
                pos,
                f"the record at offset {pos} needs {end - pos} bytes, "
                f"the file ends after {remaining}",
            )
            break
        hbytes = data[start : start + hlen]
        body = view[start + hlen : end]
        if zlib.crc32(hbytes) != hcrc or zlib.crc32(body) != bcrc:
            if zero_filled_tail(pos):
                break
            part = "header" if zlib.crc32(hbytes) != hcrc else "body"
            problems.append(
                f"{file}: record at offset {pos} fails its {part} checksum (damaged); skipped"
            )
            pos = end
            continue
        try:
            header = json.loads(hbytes)
            if not isinstance(header, dict):
                raise ValueError("header is not a JSON object")
        except (UnicodeDecodeError, ValueError) as e:
            problems.append(
                f"{file}: record at offset {pos} has an unreadable header ({e}); skipped"
            )
            pos = end
            continue
        if header.get("kind") == "footer":
            footer = header
        else:
            records.append((pos, header, body))
        pos = end

    if footer is None:
        if closed:
            problems.append(f"{file}: no footer: the closed chunk was truncated")
    elif footer.get("records") != len(records):
        problems.append(
            f"{file}: footer counts {footer.get('records')!r} records, {len(records)} are intact"
        )
    return records
