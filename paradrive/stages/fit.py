"""The ``fit`` stage (``stages/fit.yaml``): a 3D Gaussian Splatting model of one scene, with
checkpoints at the configured iterations and ``gs/fit.json`` (:class:`FitRecord`).

The training itself is :func:`paradrive.gs.fit.fit_scene`; this module holds the contract.
"""

from __future__ import annotations


from pydantic import field_validator

from paradrive.contracts.base import StageContext, StageParams
from paradrive.contracts.records import FitRecord


class Params(StageParams):
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


def run(ctx: StageContext[Params]) -> FitRecord:
    from paradrive.gs.fit import fit_scene
    from paradrive.stages.ingest import recorded_params

    threshold = recorded_params(ctx.layout).moving_threshold_m
    return fit_scene(ctx.layout, ctx.params, log=ctx.log, progress=ctx.progress,
                     moving_threshold_m=threshold)
