"""Atomic, checksummed estimator checkpoints (DESIGN §6).

File layout (one file, binary)::

    SOCD-CHECKPOINT\\n
    <header JSON, one line>\\n
    <payload: numpy .npz of the estimator state, no pickles>

The header holds the metadata (schema version, wall time saved, frame time of the last
sample, n_cells, profile hash) and ``sha256`` over ``canonical(meta) + payload``, so a
flipped bit in either is detected.  Writing goes to a temporary file in the same directory,
which is flushed and fsynced, renamed over the target, and then the directory is fsynced:
a crash at any point leaves either the old or the new checkpoint, never a torn one.

:func:`load_checkpoint` never raises for a bad file: it returns a :class:`LoadResult` whose
``reason`` says why the state cannot be used ("missing", "corrupt", "mismatch"), and the
daemon then starts from OCV with a large covariance and says so in its status flags.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import tempfile
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from service.cell.profile import CellProfile
from service.config import CHECKPOINT_MAGIC as MAGIC

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
#: header line longer than this is not ours
_MAX_HEADER = 1 << 20

Reason = Literal["ok", "missing", "corrupt", "mismatch"]


def profile_hash(profile: CellProfile) -> str:
    """sha256 of the profile's canonical JSON: changes whenever any field does."""
    text = json.dumps(profile.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _canonical(meta: dict) -> bytes:
    return json.dumps(meta, sort_keys=True, separators=(",", ":")).encode()


def _flatten(state: dict, prefix: str = "") -> dict[str, np.ndarray]:
    """``{"a": {"b": x}}`` -> ``{"a/b": x}``; every leaf becomes an ndarray."""
    flat: dict[str, np.ndarray] = {}
    for key, value in state.items():
        if "/" in str(key):
            raise ValueError(f"state key {key!r} contains '/'")
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten(value, name + "/"))
        else:
            arr = np.asarray(value)
            if arr.dtype == object:
                raise ValueError(f"state entry {name!r} is not a numeric array")
            flat[name] = arr
    return flat


def _unflatten(flat: dict[str, np.ndarray]) -> dict:
    out: dict = {}
    for name, value in flat.items():
        node = out
        parts = name.split("/")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def encode_checkpoint(state: dict, meta: dict) -> bytes:
    """The bytes of a checkpoint file for ``state`` (dict of arrays) and ``meta``."""
    buf = io.BytesIO()
    np.savez(buf, **_flatten(state))
    payload = buf.getvalue()
    meta = dict(meta, schema_version=SCHEMA_VERSION)
    digest = hashlib.sha256(_canonical(meta) + payload).hexdigest()
    header = json.dumps({"meta": meta, "sha256": digest, "payload_bytes": len(payload)}).encode()
    return MAGIC + header + b"\n" + payload


def save_checkpoint(
    path: str | Path,
    state: dict,
    *,
    n_cells: int,
    profile_sha256: str,
    t_s: float | None = None,
    extra: dict | None = None,
) -> Path:
    """Write a checkpoint atomically (temp file, fsync, rename, fsync dir); return its path."""
    path = Path(path)
    meta = {
        "saved_wall_s": time.time(),
        "t_s": t_s,
        "n_cells": int(n_cells),
        "profile_sha256": profile_sha256,
        **(extra or {}),
    }
    data = encode_checkpoint(state, meta)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        try:
            os.unlink(tmp_name)
        except OSError:
            pass
        raise
    _fsync_dir(path.parent)
    return path


def checkpoint_write_problem(path: str | Path) -> str | None:
    """Why :func:`save_checkpoint` could not write ``path``, or None.

    The save creates the missing folders on the way and a temporary file beside the target, so
    the nearest folder that exists must take a new file.  Tried with a temporary file there,
    removed at once: permission bits do not tell (root writes anywhere by them, yet not into a
    read-only or virtual file system such as ``/proc``)."""
    path = Path(path)
    folder = path.parent
    while not folder.exists() and folder.parent != folder:
        folder = folder.parent
    if not folder.is_dir():
        return f"{folder} is not a folder, so the checkpoint {path} cannot be written"
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".probe", dir=folder)
    except OSError as exc:
        return (f"cannot create files or folders in {folder} ({exc.strerror or exc}): the service could not "
                f"save its state to {path}")
    os.close(fd)
    os.unlink(name)
    return None


def _fsync_dir(directory: Path) -> None:
    # Makes the rename itself durable; not every platform lets a directory be opened.
    try:
        dfd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)


@dataclass
class LoadResult:
    """What :func:`load_checkpoint` found.  ``state`` is set only when ``reason == "ok"``."""

    reason: Reason
    detail: str = ""
    state: dict | None = None
    meta: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.reason == "ok"


def load_checkpoint(path: str | Path, *, n_cells: int, profile_sha256: str) -> LoadResult:
    """Read, verify and match a checkpoint against the running configuration."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return LoadResult("missing", f"{path}: no checkpoint")
    except OSError as exc:
        return LoadResult("corrupt", f"{path}: unreadable: {exc.strerror or exc}")
    result = decode_checkpoint(data, str(path))
    if not result.ok:
        return result
    meta = result.meta
    if meta.get("n_cells") != n_cells:
        return LoadResult("mismatch", f"{path}: saved for {meta.get('n_cells')} cells, pack has {n_cells}", meta=meta)
    if meta.get("profile_sha256") != profile_sha256:
        return LoadResult("mismatch", f"{path}: saved with a different cell profile", meta=meta)
    return result


def decode_checkpoint(data: bytes, name: str = "checkpoint") -> LoadResult:
    """Verify magic, header, checksum and payload; no matching against the configuration."""
    if not data.startswith(MAGIC):
        return LoadResult("corrupt", f"{name}: not a socd checkpoint (bad magic)")
    end = data.find(b"\n", len(MAGIC), len(MAGIC) + _MAX_HEADER)
    if end < 0:
        return LoadResult("corrupt", f"{name}: truncated header")
    try:
        header = json.loads(data[len(MAGIC):end])
        meta, digest, size = header["meta"], header["sha256"], int(header["payload_bytes"])
        if not isinstance(meta, dict):
            raise TypeError("meta is not an object")
    except (ValueError, KeyError, TypeError, OverflowError) as exc:
        return LoadResult("corrupt", f"{name}: bad header: {exc}")
    payload = data[end + 1:]
    if len(payload) != size:
        return LoadResult("corrupt", f"{name}: payload is {len(payload)} bytes, header says {size}", meta=meta)
    if hashlib.sha256(_canonical(meta) + payload).hexdigest() != digest:
        return LoadResult("corrupt", f"{name}: checksum mismatch", meta=meta)
    if meta.get("schema_version") != SCHEMA_VERSION:
        return LoadResult("mismatch", f"{name}: schema version {meta.get('schema_version')}, expected {SCHEMA_VERSION}", meta=meta)
    try:
        with np.load(io.BytesIO(payload), allow_pickle=False) as npz:
            flat = {k: np.array(npz[k]) for k in npz.files}
    except (ValueError, OSError, zipfile.BadZipFile) as exc:  # checksum matched, so a writer bug
        return LoadResult("corrupt", f"{name}: unreadable payload: {exc}", meta=meta)
    return LoadResult("ok", f"{name}: restored", state=_unflatten(flat), meta=meta)
