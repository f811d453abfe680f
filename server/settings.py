"""The service's settings: one data directory, limits, and where frames are solved."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

MIB = 1024 * 1024


@dataclass
class Settings:
    """``data_dir``: the store (see :mod:`server.storage`). ``job_slots``: jobs run at once
    (each in its own process). ``frame_workers``: the core's process pool per job (ignored with
    ``dask_scheduler``, where frame chunks run on the cluster's workers). Limits per owner:
    ``max_upload_bytes`` (413 beyond), ``max_active_jobs`` queued or running (429 beyond).
    ``max_attempts``: a job whose process dies (or whose service is killed) is re-run at most
    this many times in all. ``atlas_cache_bytes``: the built contact atlases kept under
    DATA/cache/atlas (least recently used removed after each job)."""

    data_dir: Path
    job_slots: int = 1
    frame_workers: int = 1
    dask_scheduler: str = ""
    max_upload_bytes: int = 256 * MIB
    max_active_jobs: int = 32
    max_attempts: int = 3
    evaluate_stride: int = 4
    atlas_cache_bytes: int = 4096 * MIB
