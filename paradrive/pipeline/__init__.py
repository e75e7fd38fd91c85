"""Running stages over scenes: the runner, the build and the executors (and, re-exported from
the contracts, the stage registry a build runs with)."""

from paradrive.pipeline.build import BuildReport, run_build
from paradrive.pipeline.runner import StageResult, run_scene_stage
from paradrive.contracts.base import BuildContext, StageContext
from paradrive.contracts.specs import ResolvedConfig, StageRegistry, parse_overrides

__all__ = ["BuildContext", "BuildReport", "ResolvedConfig", "StageContext", "StageRegistry",
           "StageResult", "parse_overrides", "run_build", "run_scene_stage"]
