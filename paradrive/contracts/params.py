"""The typed parameters of the stages whose work a library below the stages does: the ingest
readers (:mod:`paradrive.ingest`), the fit (:mod:`paradrive.gs.fit`) and the manifest writer
(:mod:`paradrive.manifest`) take them, and the stage modules run with them. Their fields are
exactly the parameters of ``stages/<name>.yaml``, with no defaults: the values live only there.

The ingest parameters a scene was made with are read back here too (:func:`recorded_params`,
from its ingest stage marker): the later stages, the inference sets and eval all import them
from this module, none from the ingest stage.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from pydantic import field_validator

from paradrive.contracts.base import StageParams
from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import StageMarker


class IngestParams(StageParams):
    cameras: str | list[str] | None
    camera_sets: dict[str, list[str]]
    max_frames: int | None
    image_ext: str
    jpeg_quality: int
    lidar: bool
    sky_masks: bool
    synthetic_frames: int
    synthetic_width: int
    synthetic_height: int
    synthetic_curvature: float
    moving_threshold_m: float | None
    keep_lidar: bool
    video_max_fps: float
    video_folder_fps: float
    video_sfm_width: int
    video_max_scale_uncertainty: float
    video_scale_range_frames: int
    video_road_points_bias: float
    video_focal_frames: int
    video_focal_min_rise: float
    video_unmeasured_focal_max_turn_deg: float
    video_repeat_ratio: float
    video_codec_crf: int | None



def params_of(values: Mapping[str, Any] | None = None,
              defaults: Mapping[str, Any] | None = None) -> IngestParams:
    """Ingest parameters from a recorded mapping (a scene's ingest marker). What an older
    marker lacks comes from ``defaults``: the build's own ingest parameters (its profile and
    ``--set``), or where none are given the stage file's defaults (read once, not per call);
    keys the stage no longer has are left out."""
    if defaults is None:
        from paradrive.contracts.specs import cached_registry

        defaults = cached_registry().specs["ingest"].defaults()
    known = {k: v for k, v in (values or {}).items() if k in IngestParams.model_fields}
    return IngestParams.of("ingest", {**defaults, **known})


def recorded_values(layout: SceneLayout) -> dict[str, Any] | None:
    """The parameter mapping the scene at ``layout`` was ingested with (its stage marker), or
    None where it has no readable marker (a scene folder made without the runner)."""
    marker = StageMarker.read(layout.marker("ingest"))
    return marker.params if marker is not None else None


def recorded_params(layout: SceneLayout, defaults: Mapping[str, Any] | None = None) -> IngestParams:
    """The parameters the scene at ``layout`` was ingested with, typed; ``defaults`` (the
    build's ingest parameters) where its marker lacks one or it has none (:func:`params_of`)."""
    return params_of(recorded_values(layout), defaults)

class FitParams(StageParams):
    checkpoints: list[int]
    cameras: list[str] | None
    downscale: float
    seed: int
    threads: int
    device: str
    backend: str
    sh_degree: int
    sh_degree_interval: int
    ssim_lambda: float
    lr_means: float
    lr_means_final: float
    lr_scales: float
    lr_quats: float
    lr_opacities: float
    lr_sh0: float
    lr_shN: float
    grow_grad2d: float
    grow_scale3d: float
    prune_scale3d: float
    prune_opa: float
    refine_start_iter: int
    refine_stop_iter: int
    refine_every: int
    reset_every: int
    max_gaussians: int
    init: str
    init_points: int
    init_opacity: float
    init_depth_min: float
    init_depth_max: float
    init_depth_candidates: int
    init_ground_margin: float | None
    init_top_up: float
    lidar_voxel: float
    lidar_max_points: int
    sky_points: int
    sky_radius: float
    sky_depth_weight: float
    depth_weight: float
    depth_inverse: bool
    flatten_weight: float
    shape_ratio_weight: float
    shape_ratio_max: float
    shape_ratio_every: int
    eval_views: int
    holdout_every: int
    holdout_cameras: list[str]
    state_interval: int
    keep_state: bool
    dynamic: str
    nonrigid: str
    actor_init_points: int
    actor_pose_lr: float

    @field_validator("checkpoints")
    @classmethod
    def _positive_sorted(cls, value: list[int]) -> list[int]:
        its = sorted(set(value))
        if not its or its[0] <= 0:
            raise ValueError(f"checkpoints must be positive iterations, got {value!r}")
        return its

    @field_validator("downscale")
    @classmethod
    def _at_least_one(cls, value: float) -> float:
        if value < 1.0:
            raise ValueError(f"downscale must be >= 1, got {value!r}")
        return value

    @property
    def iterations(self) -> int:
        """The run length: the last checkpoint."""
        return self.checkpoints[-1]


class ManifestParams(StageParams):
    shard_rows: int
    shard_bytes: int | None
    row_group_rows: int
    compression: str
    media: str
    verify_inputs: bool
    quality: bool
    kind: str
    exclude_splits: list[str]
    min_heldout_psnr: float | None
    max_dynamic_fraction: float | None
    keep_versions_for: str

    @field_validator("keep_versions_for")
    @classmethod
    def _a_duration(cls, value: str) -> str:
        duration_seconds(value)
        return value

    @property
    def keep_versions_seconds(self) -> float:
        """``keep_versions_for`` in seconds."""
        return duration_seconds(self.keep_versions_for)


DURATION_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0, "w": 604800.0}
_DURATION = re.compile(r"(\d+(?:\.\d+)?)([smhdw])")


def duration_seconds(text: str) -> float:
    """``"90s"``, ``"30m"``, ``"12h"``, ``"1d"``, ``"2w"`` (a number and one unit) in seconds;
    anything else is a ValueError saying what is taken."""
    match = _DURATION.fullmatch(text.strip()) if isinstance(text, str) else None
    if match is None:
        raise ValueError(f"{text!r} is not a duration: write a number and one unit of "
                         f"{', '.join(DURATION_UNITS)} (seconds, minutes, hours, days, weeks), "
                         f"e.g. '1d', '12h' or '0s'")
    return float(match.group(1)) * DURATION_UNITS[match.group(2)]
