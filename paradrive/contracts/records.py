"""The files stages write and later stages read, as typed records.

``fit.json`` (:class:`FitRecord`), ``renders/renders.json`` (:class:`RendersRecord`),
``clips/clips.json`` (:class:`ClipsRecord`) and a build's ``index.json`` (:class:`IndexRecord`).
Each knows its schema version, saves itself atomically with :meth:`Record.save` and loads with
:meth:`Record.load`, which names the file and the fix when it is missing, not JSON, of another
schema version or malformed. Consumers read fields, never keys. Optional fields of the nested
parts are left out of the file when unset, as readers of the format expect.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError, model_serializer

from paradrive.errors import SceneError, validation_message
from paradrive.io import write_json

R = TypeVar("R", bound="Record")
Pose = list[float]          # a 4x4 matrix, row-major, 16 floats


class Part(BaseModel):
    """A nested part of a record; its unset (None) fields are not written."""

    model_config = ConfigDict(extra="forbid")

    @model_serializer(mode="wrap")
    def _without_none(self, handler: Any) -> dict[str, Any]:
        return {k: v for k, v in handler(self).items() if v is not None}


class Record(BaseModel):
    """A stage's JSON file: ``save`` writes it (temporary name, then rename), ``load`` checks it."""

    model_config = ConfigDict(extra="forbid")
    WHAT: ClassVar[str]                       # the file's name in messages
    SCHEMA_VERSION: ClassVar[int | None] = None
    FIX: ClassVar[str]                        # what re-creates the file

    def save(self, path: str | Path) -> None:
        write_json(path, self.model_dump())

    @classmethod
    def load(cls: type[R], path: str | Path, scene_id: str | None = None) -> R:
        path = Path(path)
        sid = scene_id or path.parent.parent.name

        def fail(what: str) -> SceneError:
            return SceneError(what, scene_id=sid, path=path, fix=cls.FIX)

        if not path.is_file():
            raise fail(f"{cls.WHAT} is missing")
        try:
            doc = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise fail(f"{cls.WHAT} is not valid JSON ({exc})") from exc
        if not isinstance(doc, dict):
            raise fail(f"{cls.WHAT} is not a JSON object")
        if cls.SCHEMA_VERSION is not None and doc.get("schema_version") != cls.SCHEMA_VERSION:
            raise fail(f"{cls.WHAT} schema_version {doc.get('schema_version')!r} is not "
                       f"{cls.SCHEMA_VERSION}")
        try:
            return cls.model_validate(doc)
        except ValidationError as exc:
            raise fail(f"{cls.WHAT} {validation_message(exc)}") from exc


# --------------------------------------------------------------------------- fit.json

class CheckpointMetrics(Part):
    iteration: int
    psnr: float
    ssim: float
    num_gaussians: int
    seconds: float
    cpu_seconds: float
    peak_rss_mb: float
    peak_gpu_mb: float | None = None


class FitInit(Part):
    method: str
    points: int
    sky_points: int
    sky_radius_m: float
    scene_scale_m: float


class ActorNode(Part):
    """One actor node of a scene-graph fit: its track's id, class and checkpoint file name."""

    id: str
    cls: str
    rigid: bool
    file: str
    init_points: int


class HeldoutCamera(Part):
    """A camera's held-out images against a checkpoint's renders at their poses: ``kind`` frames
    (its held-out frames) or camera (a camera left out of the fit, every frame)."""

    kind: str
    views: int
    psnr: float
    ssim: float
    psnr_static: float | None = None    # outside the moving actors' boxes, where there are any
    psnr_dynamic: float | None = None   # inside them


class HeldoutRecord(Part):
    """What a fit held out (``every``-th frame, ``cameras``) and the checkpoint ``iteration``'s
    mean PSNR / SSIM over the ``views`` held-out images, and per camera."""

    every: int
    cameras: list[str]
    iteration: int
    views: int
    psnr: float
    ssim: float
    per_camera: dict[str, HeldoutCamera]


class FitRecord(Record):
    WHAT: ClassVar[str] = "fit.json"
    FIX: ClassVar[str] = "re-run the fit stage for this scene"

    scene_id: str
    complete: bool
    fingerprint: str
    iterations: int
    checkpoints: list[CheckpointMetrics]
    eval_views: int
    resolution: list[int]
    n_views: int
    cameras: list[str]
    device: str
    init: FitInit
    scene_scale: float
    densify: dict[str, int]
    dynamic: bool = False
    actors: list[ActorNode] = []
    heldout: HeldoutRecord | None = None   # only a fit that held views out has it

    def save(self, path: str | Path) -> None:
        write_json(path, self.model_dump(exclude={"heldout"} if self.heldout is None else None))

    def summary(self) -> dict[str, Any]:
        last = self.at(None)
        held = {"heldout_psnr": self.heldout.psnr} if self.heldout is not None else {}
        return {"iterations": self.iterations, "complete": self.complete,
                "psnr": last.psnr if last else None, "num_gaussians": last.num_gaussians if last else None,
                **held}

    def at(self, iteration: int | None) -> CheckpointMetrics | None:
        """The metrics of ``iteration``, else of the last checkpoint (None before the first)."""
        match = [c for c in self.checkpoints if c.iteration == iteration]
        if match:
            return match[0]
        return max(self.checkpoints, key=lambda c: c.iteration) if self.checkpoints else None


# --------------------------------------------------------------------------- renders.json

class WindowRecord(Part):
    clip: str
    frame_start: int
    num_frames: int


class SkippedClip(Part):
    clip: str
    reason: str


class CameraSkippedClip(Part):
    camera: str
    clip: str
    reason: str


class RenderedStream(Part):
    kind: str
    dir: str
    c2w: list[Pose]
    iteration: int | None = None
    offset_m: float | None = None


class RenderedCamera(Part):
    intrinsics: list[float]
    stored_size: list[int]
    crop: list[int]
    windows: list[WindowRecord]
    skipped: list[SkippedClip]
    frames: list[int]
    c2w: list[Pose]
    streams: dict[str, RenderedStream]
    moving: list[float] | None = None   # per frame, the share of the target masked as moving


class SkyDomeRecord(Part):
    centre: list[float]
    radius_m: float


class RendersRecord(Record):
    WHAT: ClassVar[str] = "renders.json"
    SCHEMA_VERSION: ClassVar[int | None] = 1
    FIX: ClassVar[str] = "run the render stage for this scene first"

    schema_version: int = 1
    scene_id: str
    width: int
    height: int
    frame_naming: str = "position in scene.json frames"
    condition_checkpoints: list[int]
    source_checkpoint: int
    offsets_m: list[float]
    clip_frames: int
    depth: bool
    alpha: bool
    depth_units: str = "metres, z-depth along the camera axis; +inf = sky"
    sky_dome: SkyDomeRecord | None
    cameras: dict[str, RenderedCamera]

    def summary(self) -> dict[str, Any]:
        cams = self.cameras.values()
        return {"cameras": len(self.cameras), "frames": sum(len(c.frames) for c in cams),
                "streams": sum(len(c.streams) for c in cams),
                "skipped_clips": sum(len(c.skipped) for c in cams)}


# --------------------------------------------------------------------------- clips.json

class ClipStream(Part):
    file: str
    bytes: int
    sha256: str
    kind: str
    iteration: int | None = None
    offset_m: float | None = None
    c2w: list[Pose] | None = None
    depth_dir: str | None = None


class Quality(Part):
    psnr: float
    ssim: float


class ClipRecord(Part):
    camera: str
    clip: str
    frame_start: int
    num_frames: int
    frame_indices: list[int]
    timestamps_us: list[int]
    c2w: list[Pose]
    streams: dict[str, ClipStream]
    quality: dict[str, Quality]
    dynamic_fraction: float | None = None   # the target's share masked as moving, over the clip


class CameraIntrinsics(Part):
    intrinsics: list[float]


class FitFigures(BaseModel):
    """The fit's training-view figures at the source checkpoint (null when unknown)."""

    model_config = ConfigDict(extra="forbid")
    iteration: int | None
    train_psnr: float | None
    train_ssim: float | None


class ClipsRecord(Record):
    WHAT: ClassVar[str] = "clips.json"
    SCHEMA_VERSION: ClassVar[int | None] = 1
    FIX: ClassVar[str] = "run the clip stage for this scene first"

    schema_version: int = 1
    scene_id: str
    dataset: str
    source: str
    fps: float
    width: int
    height: int
    codec: str
    cameras: dict[str, CameraIntrinsics]
    fit: FitFigures
    clips: list[ClipRecord]
    skipped: list[CameraSkippedClip]

    def summary(self) -> dict[str, Any]:
        return {"clips": len(self.clips), "streams": sum(len(c.streams) for c in self.clips),
                "skipped": len(self.skipped), "codec": self.codec}

    def video_hashes(self) -> dict[str, str]:
        """sha256 of every video, by its path relative to the scene folder."""
        return {s.file: s.sha256 for c in self.clips for s in c.streams.values()}


# --------------------------------------------------------------------------- index.json

class ColumnRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    type: str


class ShardRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")
    file: str
    rows: int
    bytes: int
    sha256: str
    first_pair_id: str | None
    last_pair_id: str | None


class IndexTotals(BaseModel):
    model_config = ConfigDict(extra="forbid")
    rows: int
    shards: int
    shard_bytes: int
    media_files: int
    media_bytes: int
    scenes: int
    scenes_skipped: int


class MediaRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mode: str
    placed: dict[str, int]
    data_root: str | None = None   # a symlink build's links lead only into this data folder


class IndexScene(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scene_id: str
    dataset: str
    scene_uri: str
    scene_dir: str
    rows: int
    cameras: list[str]
    clips: list[str]
    skipped_clips: list[CameraSkippedClip]
    transform: str = "lateral"   # how its sources were moved (render.transform)
    heldout_psnr: float | None = None   # its fit's final checkpoint on the views it held out
    heldout_ssim: float | None = None

    @model_serializer(mode="wrap")
    def _heldout_when_known(self, handler: Any) -> dict[str, Any]:
        # a scene fitted without a holdout reads as before: no held-out keys at all
        return {k: v for k, v in handler(self).items()
                if v is not None or k not in ("heldout_psnr", "heldout_ssim")}


class SkippedScene(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scene_id: str
    scene_uri: str
    reason: str


class SplitFile(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    file: str
    sha256: str
    scenes: int


class ExcludedScene(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scene_id: str
    scene_uri: str
    split: str
    line: str


class HeldoutFilter(BaseModel):
    """``manifest.min_heldout_psnr`` at publish time and the scenes it left out."""

    model_config = ConfigDict(extra="forbid")
    min_psnr: float
    dropped: list[SkippedScene]


class DroppedClip(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scene_id: str
    camera: str
    clip: str


class DynamicFilter(BaseModel):
    """``manifest.max_dynamic_fraction`` at publish time, the rows it left out and their clips."""

    model_config = ConfigDict(extra="forbid")
    max_fraction: float
    dropped_rows: int
    dropped_clips: list[DroppedClip]


class IndexRecord(BaseModel):
    """A published build's ``index.json``: its shards, media, scenes and how it was made."""

    model_config = ConfigDict(extra="forbid")
    format: str
    schema_version: int
    build: str
    version: str | None = None   # the version folder (v-<nnnnnn>) shards and URIs are relative to
    kind: str
    created_at: str
    software: dict[str, str]
    config_fingerprint: str
    params: dict[str, Any]
    sort: list[str]
    columns: list[ColumnRecord]
    shards: list[ShardRecord]
    totals: IndexTotals
    media: MediaRecord
    scenes: list[IndexScene]
    skipped_scenes: list[SkippedScene]
    exclude_splits: list[SplitFile]
    excluded_scenes: list[ExcludedScene]
    heldout_filter: HeldoutFilter | None = None   # manifest.min_heldout_psnr, when it was set
    dynamic_filter: DynamicFilter | None = None   # manifest.max_dynamic_fraction, when it was set

    def save(self, path: str | Path) -> None:
        write_json(path, self.model_dump())

    def summary(self) -> dict[str, Any]:
        return {"rows": self.totals.rows, "shards": self.totals.shards,
                "scenes": self.totals.scenes, "skipped": [s.scene_id for s in self.skipped_scenes]}


# --------------------------------------------------------------------------- .paradrive/<stage>.json

class OutputFile(Part):
    """How a marker records one output: its size and sha256, and the modification time (ns),
    inode and change time (ns) it had when it was hashed (a file let go keeps only its size and
    sha256; a marker written before hashes or stats were recorded lacks them)."""

    bytes: int
    sha256: str | None = None
    mtime_ns: int | None = None
    inode: int | None = None
    ctime_ns: int | None = None


class DroppedOutputs(Part):
    """Outputs a retention switch let go (``files``) and the run of each stage that used them
    (``after``)."""

    files: dict[str, OutputFile]
    after: dict[str, str | None]


class StageMarker(Record):
    """A completed stage's marker, ``.paradrive/<stage>.json`` in a scene folder (a scene
    stage: what it ran with, what it read, what it wrote) or in a build folder (a build stage:
    ``build``, ``scene_runs``, ``outputs``). The one way the code reads or writes one.

    Fields a kind of marker has not are left out of the file, so a marker reads as it always
    did; one written before ``schema_version`` existed is version 1, one written before
    ``outputs`` were recorded has none (None), and keys an older version wrote that this one
    does not know are ignored."""

    model_config = ConfigDict(extra="ignore")
    WHAT: ClassVar[str] = "stage marker"
    SCHEMA_VERSION: ClassVar[int | None] = 1
    FIX: ClassVar[str] = "re-run the build (a plain re-run redoes a stage whose marker is unreadable)"

    schema_version: int = 1
    stage: str
    scene_id: str | None = None
    build: str | None = None
    scene_uri: str | None = None
    fingerprint: str
    params: dict[str, Any] | None = None
    inputs: dict[str, str] | None = None
    version: str | None = None
    seconds: float | None = None
    finished_at: str | None = None
    summary: dict[str, Any] | None = None
    run: str | None = None
    upstream_runs: dict[str, str | None] | None = None
    scene_runs: dict[str, Any] | None = None
    outputs: dict[str, OutputFile] | None = None
    dropped: DroppedOutputs | None = None

    @model_serializer(mode="wrap")
    def _what_it_has(self, handler: Any) -> dict[str, Any]:
        return {k: v for k, v in handler(self).items() if v is not None}

    @classmethod
    def read(cls, path: str | Path) -> StageMarker | None:
        """The marker at ``path``; None when there is none, or it cannot be read as one (the
        stage then counts as not done, and a re-run does it again)."""
        try:
            doc = json.loads(Path(path).read_text())
            if isinstance(doc, dict):
                doc.setdefault("schema_version", 1)   # written before markers had a version
            marker = cls.model_validate(doc)
        except (FileNotFoundError, NotADirectoryError, json.JSONDecodeError, UnicodeDecodeError,
                ValidationError):
            return None
        return marker if marker.schema_version == cls.SCHEMA_VERSION else None
