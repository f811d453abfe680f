"""Atomic file writes: a result is written next to its destination under a temporary name and
moved into place, so a reader never sees a half-written file and a failed write leaves the
previous file untouched."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np


@contextmanager
def atomic_path(path, suffix: str = ""):
    """Yield a temporary path beside ``path``; on success it replaces ``path`` (mode 0644, or
    the replaced file's mode), on any error it is removed."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=suffix or path.suffix + ".tmp", dir=folder)
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp creates the file 0600; give it the mode a plain open() would have
        os.chmod(tmp, path.stat().st_mode & 0o7777 if path.exists() else 0o644)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def save_npz_atomic(path, arrays: dict) -> None:
    """np.savez_compressed of ``arrays`` to ``path``, atomically."""
    with atomic_path(path, suffix=".npz.tmp") as tmp:
        with open(tmp, "wb") as handle:
            np.savez_compressed(handle, **arrays)
