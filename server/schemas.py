"""Request and response bodies of the /v1 API (pydantic)."""

from __future__ import annotations

from enum import StrEnum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt, field_validator

SHA256 = r"^[0-9a-f]{64}$"


class JobState(StrEnum):
    """The one list of job states (the store, the runner and the API all use it)."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"

    @property
    def final(self) -> bool:
        return self in FINAL_STATES


ACTIVE_STATES = (JobState.QUEUED, JobState.RUNNING)
FINAL_STATES = (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)


class Problem(BaseModel):
    """Every 4xx/5xx body: ``detail`` says what is wrong and what to do about it."""

    detail: str


#: What an asset is (see :mod:`server.assets`).
AssetKind = Literal["rig", "annotations", "clip", "file"]


class Asset(BaseModel):
    id: str = Field(description="sha256 of the content")
    kind: AssetKind
    name: str
    size: int
    created: float
    info: dict[str, Any]


#: Paging of list endpoints: ``limit`` items per page (at most MAX_PAGE), ``next_cursor`` in a
#: page that has more after it (pass it as ``cursor`` for the next one; null on the last page).
DEFAULT_PAGE, MAX_PAGE = 100, 1000


class AssetList(BaseModel):
    assets: list[Asset]
    next_cursor: str | None = Field(default=None, description="pass as ?cursor= for the next page; null: last page")


class GrabImport(BaseModel):
    """A GRAB sequence and the user's MANO model (and meshes), uploaded as ``file`` assets."""

    model_config = ConfigDict(extra="forbid")
    sequence: str = Field(pattern=SHA256, description="the GRAB sequence .npz")
    mano: str = Field(pattern=SHA256, description="the MANO model of that hand (MANO_RIGHT.pkl / MANO_LEFT.pkl)")
    hand: Literal["right", "left"] = Field(default="right", description="which hand of the sequence to import")
    object_mesh: str = Field(pattern=SHA256, description="the object's mesh (.ply / .obj / .stl)")
    table_mesh: str | None = Field(default=None, pattern=SHA256)
    vtemp: str | None = Field(default=None, pattern=SHA256, description="the subject's hand template mesh")
    name: str = Field(default="grab_clip.npz", max_length=200)


class SubstituteRequest(BaseModel):
    """A clip asset with its object replaced by an uploaded mesh (a ``file`` asset)."""

    model_config = ConfigDict(extra="forbid")
    clip: str = Field(pattern=SHA256, description="the clip asset whose object is replaced")
    object_mesh: str = Field(pattern=SHA256, description="the new object's mesh (.ply / .obj / .stl / .off)")
    transform: list[float] | None = Field(
        default=None, min_length=16, max_length=16,
        description="4 x 4 row by row (metres) placing the new object in the old object's frame; "
                    "default: registered onto the old object (its contact region)")
    min_share: float = Field(default=0.8, ge=0.0, le=1.0,
                             description="refuse when a smaller share of the contacts reaches the new object")
    allow_intersection: bool = Field(default=False,
                                     description="make the clip even when the source hand lies inside the new object")
    name: str = Field(default="substituted_clip.npz", max_length=200)


class ProposeRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    target_rig: str = Field(pattern=SHA256)
    source_rig: str | None = Field(default=None, pattern=SHA256,
                                   description="default: the demo source hand (what demo clips are made with)")


#: a relative asset path to a USD file: segments start with a letter, digit or "_" (so no
#: leading "/", no ".." and no hidden names), no scheme, no backslash
RIG_ASSET_PATH = r"^[A-Za-z0-9_][A-Za-z0-9_.-]*(/[A-Za-z0-9_][A-Za-z0-9_.-]*)*\.(usda|usdc|usd)$"


class JobCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    clip: str = Field(pattern=SHA256)
    rig: str = Field(pattern=SHA256, description="the target rig")
    annotations: str = Field(pattern=SHA256)
    source_rig: str | None = Field(default=None, pattern=SHA256,
                                   description="the rig the clip was made with; default: the clip's demo hand")
    preset: Literal["default", "paper"] = "default"
    overrides: dict[str, Any] = Field(default_factory=dict, description='dotted config keys, e.g. {"solver.maxeval": 50}')
    evaluate: bool = Field(default=True, description="also write metrics.json and the report's plots")
    frames: tuple[StrictInt, StrictInt] | None = Field(
        default=None, description="[start, end) frames of the clip to retarget (end excluded); null: the whole clip")
    control_rate_hz: float | None = Field(
        default=None, gt=0, le=10000,
        description="robot rigs (URDF / MJCF): the control rate of the joint commands in animation.json's "
                    "robot section; null: the clip's frame rate")
    rig_asset_path: str | None = Field(
        default=None, max_length=300, pattern=RIG_ASSET_PATH,
        description="the path animation.usda sublayers for the rig, as you will place it (relative to "
                    "animation.usda, e.g. 'hand.usda' or 'assets/hand.usda'): the layer then composes over "
                    "your own USD rig file; null: over the job's rig.usda. Only for a rig uploaded as USD")

    @field_validator("frames")
    @classmethod
    def _range(cls, frames):
        if frames is not None and not 0 <= frames[0] < frames[1]:
            raise ValueError(f"[start, end) must have 0 <= start < end, got {list(frames)}")
        return frames


class Job(BaseModel):
    id: str
    state: JobState
    stage: str
    progress: float
    frames_done: int
    frames_total: int
    attempts: int
    created: float
    started: float | None
    finished: float | None
    timings: dict[str, float]
    summary: dict[str, Any]
    error: str | None
    request: JobCreate
    artifacts: list[str]


class JobList(BaseModel):
    jobs: list[Job]
    next_cursor: str | None = Field(default=None, description="pass as ?cursor= for the next page; null: last page")
