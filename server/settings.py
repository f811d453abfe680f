"""The service's settings: one data directory, limits, and where frames are solved.

:class:`Settings` is their only form: ``handretarget serve`` builds it from its options, the app
and the job runner read it, and each job process gets it whole (``--settings``, its JSON)."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, field_validator

MIB = 1024 * 1024


class Settings(BaseModel):
    """``data_dir``: the store (see :mod:`server.storage`). ``job_slots``: jobs run at once
    (each in its own process). ``frame_workers``: the core's process pool per job (ignored with
    ``dask_scheduler``, where frame chunks run on the cluster's workers). Limits per owner:
    ``max_upload_bytes`` (413 beyond), ``max_active_jobs`` queued or running (429 beyond).
    ``max_attempts``: a job whose process dies (or whose service is killed) is re-run at most
    this many times in all. ``evaluate_stride``: every how many frames a job's evaluation
    measures. ``atlas_cache_bytes``: the built contact atlases kept under DATA/cache/atlas
    (least recently used removed after each job).

    Limits of work (issue 16): ``job_time_limit_s`` wall time of one job's process from its
    start, and ``job_memory_mb`` the memory (PSS) of the job process and its local pool, both
    checked every 0.2 s by the job process's watchdog (:mod:`server.job_process`; exceeding
    either fails the job with a message naming the limit and stops its pool; frames solved on a
    Dask cluster use the cluster workers' memory, which only the cluster's own limits bound).
    ``validation_memory_mb``: an upload is validated in a child process killed past this much
    memory (413), and a clip whose arrays would not fit in it is refused before it is
    decompressed (:mod:`server.isolation`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    data_dir: Path
    job_slots: int = Field(default=1, ge=1)
    frame_workers: int = Field(default=1, ge=1)
    dask_scheduler: str = ""
    max_upload_bytes: int = Field(default=256 * MIB, ge=1)
    max_active_jobs: int = Field(default=32, ge=1)
    max_attempts: int = Field(default=3, ge=1)
    evaluate_stride: int = Field(default=4, ge=1)
    atlas_cache_bytes: int = Field(default=4096 * MIB, ge=0)
    job_time_limit_s: float = Field(default=3600.0, gt=0)
    job_memory_mb: int = Field(default=4096, ge=1)
    validation_memory_mb: int = Field(default=1024, ge=1)
    #: open ``GET /v1/jobs/{id}/events`` streams per owner (429 beyond)
    max_streams_per_owner: int = Field(default=8, ge=1)
    #: bytes one owner may store: assets as uploaded plus their jobs' artifacts (413 beyond)
    storage_quota_bytes: int = Field(default=10240 * MIB, ge=1)
    #: seconds an upload may go without a byte arriving (408 beyond; its scratch file removed)
    read_timeout_s: float = Field(default=60.0, gt=0)
    #: requests of one owner in progress at once, and of those uploads / imports / proposals (429 beyond)
    max_requests_per_owner: int = Field(default=16, ge=1)
    max_heavy_requests_per_owner: int = Field(default=2, ge=1)
    #: a request body that is not an upload (JSON) may have this many bytes (413 beyond)
    max_json_bytes: int = Field(default=1 * MIB, ge=1024)

    @field_validator("dask_scheduler")
    @classmethod
    def _dask_address(cls, value: str) -> str:
        """The core's own check (tcp://HOST:PORT), so a bad address stops the service at start."""
        from retarget_core.solve.config import check_dask_address

        check_dask_address(value, "dask_scheduler")
        return value
