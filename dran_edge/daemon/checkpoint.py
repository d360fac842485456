"""Crash-safe state files: atomic checkpoints of nested state (numpy arrays + JSON values).

A checkpoint is one ``.npz`` file (numpy's zip of ``.npy`` arrays, loaded with
``allow_pickle=False``) holding every array of the state under ``a0, a1, ...`` and the rest of
the state as JSON under ``__meta__``, where each array is replaced by ``{"__array__": "a0"}``
and a dict with non-string keys (ints, tuples) by ``{"__items__": [[key, value], ...]}``
(tuple keys come back as tuples, other tuples as lists).
A CRC32 of the JSON plus every array's bytes guards against a torn or bit-rotted file.

Writing is atomic (POSIX): write a temp file in the same directory, ``fsync`` it,
``os.replace`` it over the target, ``fsync`` the directory. A reader sees the old or the new
checkpoint, never a mix; a kill -9 or power loss at any point leaves a loadable file.
:class:`CheckpointStore` keeps the previous generation too and falls back to it.
"""

from __future__ import annotations

import io
import json
import logging
import os
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge.errors import DecodeError

log = logging.getLogger(__name__)

FORMAT = "dran-edge-checkpoint/1"


def _flatten(obj: Any, arrays: dict[str, np.ndarray]) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype == object:
            raise TypeError("checkpoint: object arrays cannot be stored")
        key = f"a{len(arrays)}"
        arrays[key] = obj
        return {"__array__": key}
    if isinstance(obj, dict):
        if all(isinstance(k, str) for k in obj) and not set(obj) & {"__array__", "__items__"}:
            return {k: _flatten(v, arrays) for k, v in obj.items()}
        # int / tuple keys (JSON has only str keys): stored as [key, value] pairs; tuples come
        # back as lists
        return {"__items__": [[_flatten(k, arrays), _flatten(v, arrays)] for k, v in obj.items()]}
    if isinstance(obj, (list, tuple)):
        return [_flatten(v, arrays) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    raise TypeError(f"checkpoint: cannot store a {type(obj).__name__}")


def _unflatten(obj: Any, arrays: dict[str, np.ndarray]) -> Any:
    if isinstance(obj, dict):
        if set(obj) == {"__array__"}:
            return arrays[obj["__array__"]]
        if set(obj) == {"__items__"}:
            return {
                _hashable(_unflatten(k, arrays)): _unflatten(v, arrays) for k, v in obj["__items__"]
            }
        return {k: _unflatten(v, arrays) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_unflatten(v, arrays) for v in obj]
    return obj


def _hashable(key: Any) -> Any:
    return tuple(_hashable(k) for k in key) if isinstance(key, list) else key


def _crc(meta: bytes, arrays: dict[str, np.ndarray]) -> int:
    crc = zlib.crc32(meta)
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        crc = zlib.crc32(f"{key}{a.dtype.str}{a.shape}".encode(), crc)
        crc = zlib.crc32(a.tobytes(), crc)
    return crc


def dumps(state: dict) -> bytes:
    """The checkpoint bytes of ``state`` (tuples come back as lists)."""
    arrays: dict[str, np.ndarray] = {}
    tree = _flatten(state, arrays)
    meta = json.dumps({"format": FORMAT, "state": tree}, allow_nan=True).encode("utf-8")
    buf = io.BytesIO()
    # numpy's stub types **kwds as savez's own keywords (allow_pickle: bool); they are arrays
    np.savez(
        buf,
        __meta__=np.frombuffer(meta, dtype=np.uint8),
        __crc__=np.array([_crc(meta, arrays)], dtype=np.uint32),
        **arrays,  # type: ignore[arg-type]
    )
    return buf.getvalue()


def loads(data: bytes, *, source: str = "checkpoint") -> dict:
    """Inverse of :func:`dumps`; DecodeError on anything torn, corrupt or foreign."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            files = {k: z[k] for k in z.files}
    except Exception as exc:  # zipfile/numpy raise many types on a torn file
        raise DecodeError(f"{source}: not a readable checkpoint ({exc})") from None
    try:
        meta = files.pop("__meta__").tobytes()
        crc = int(files.pop("__crc__")[0])
    except KeyError:
        raise DecodeError(f"{source}: expected __meta__ and __crc__ entries") from None
    if _crc(meta, files) != crc:
        raise DecodeError(f"{source}: checksum mismatch (torn or corrupted file)")
    doc = json.loads(meta)
    if doc.get("format") != FORMAT:
        raise DecodeError(f"{source}: expected format {FORMAT!r}, got {doc.get('format')!r}")
    return _unflatten(doc["state"], files)


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: Path, data: bytes, mode: int = 0o640) -> None:
    """Replace ``path`` by ``data`` atomically and durably (temp, fsync, rename, fsync dir)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp.{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, mode)
    try:
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            view = view[n:]
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    fsync_dir(path.parent)


class CheckpointStore:
    """Two generations of checkpoints in ``directory``: ``checkpoint.npz`` and its predecessor."""

    def __init__(self, directory: str | Path, name: str = "checkpoint"):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.current = self.directory / f"{name}.npz"
        self.previous = self.directory / f"{name}.prev.npz"
        self.saves = 0
        self.last_bytes = 0

    def save(self, state: dict) -> int:
        data = dumps(state)
        if self.current.exists():
            os.replace(self.current, self.previous)
        atomic_write(self.current, data)
        self.saves += 1
        self.last_bytes = len(data)
        return len(data)

    def load(self) -> dict | None:
        """The newest loadable checkpoint, None if there is none; logs a corrupt generation."""
        for path in (self.current, self.previous):
            try:
                data = path.read_bytes()
            except FileNotFoundError:
                continue
            try:
                return loads(data, source=str(path))
            except DecodeError as exc:
                log.error("ignoring checkpoint: %s", exc)
        return None


def next_boot_epoch(directory: str | Path, clock_floor_s: float | None = None) -> int:
    """Increment and durably store the boot epoch (neighbours accept our sequence restart).

    With ``clock_floor_s`` (the wall clock, seconds) the epoch is at least that: neighbours keep
    our replay window across their own restarts (docs/wire-format.md), so a robot whose state
    directory was wiped must still come back with a larger epoch than they hold; the clock gives
    one, the counter keeps it increasing when the clock is wrong or steps back."""
    path = Path(directory) / "boot_epoch"
    try:
        epoch = int(path.read_text().strip()) + 1
    except (FileNotFoundError, ValueError):
        epoch = 1
    if clock_floor_s is not None:
        epoch = max(epoch, int(clock_floor_s))
    epoch &= 0xFFFFFFFF
    atomic_write(path, f"{epoch}\n".encode())
    return epoch
