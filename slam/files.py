"""Atomic file writes and content digests, shared by the checkpoint and the saved map (a module
of the lowest layer: it imports nothing of the package)."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

__all__ = ["file_digest", "write_via_tmp"]


def write_via_tmp(path: Path, write: Callable[[IO[bytes]], Any]) -> None:
    """``write(file)`` into a temporary name beside ``path``, fsync, rename; on any failure
    (a full disk: ENOSPC) the temporary file is removed and nothing replaces ``path``."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def file_digest(path: Path) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()
