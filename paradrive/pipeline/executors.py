"""Executors decide where (scene, stage) tasks run; stages never know.

``LocalExecutor`` runs every task in this process, scene after scene. Each scene's stages run
in dependency order and stop at the scene's first failure (the rest are recorded ``blocked``);
other scenes go on. ``RayExecutor`` (``paradrive.pipeline.ray_executor``) runs each (scene, stage)
as a Ray task with the stage's declared resources.

The contract every executor keeps: ``on_start(scene_uri, stage)`` when a stage is handed to a
worker and ``on_result(StageResult)`` when it comes back, both called on the driver (so the
ledger and the progress bar live in one process), and one result per (scene, stage) asked. A
stage handed out again after its worker died gets another ``on_start`` (the ledger counts
attempts from them). ``data_dir`` is a :class:`~paradrive.storage.DataRoot`: a folder every
worker sees, or a URL each worker copies scenes from and back. ``locks`` (the build's name and
how long to wait for a scene another build holds) goes to every
:func:`~paradrive.pipeline.runner.run_scene_stage`. ``on_progress(Snapshot)`` is called on the
driver as a running stage advances (:mod:`paradrive.pipeline.progress`). ``verify_outputs``
makes every stage's up-to-date check read its outputs' sha256, not only their sizes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol
from collections.abc import Callable

from paradrive.pipeline.locks import LockOptions
from paradrive.pipeline.progress import ProgressSink
from paradrive.pipeline.runner import StageResult, run_scene_stage
from paradrive.contracts.specs import ResolvedConfig
from paradrive.storage import DataRoot

ResultCallback = Callable[[StageResult], None]
StartCallback = Callable[[str, str], None]


@dataclass(frozen=True)
class SceneTask:
    scene_uri: str
    stages: tuple[str, ...]


class Executor(Protocol):
    name: str

    def run(self, config: ResolvedConfig, tasks: list[SceneTask], data_dir: DataRoot, *,
            force: bool = False, on_start: StartCallback | None = None,
            on_result: ResultCallback | None = None,
            locks: LockOptions | None = None,
            on_progress: ProgressSink | None = None,
            verify_outputs: bool = False) -> list[StageResult]:
        ...

    def run_build_stage(self, config: ResolvedConfig, stage: str,
                        call: Callable[[], StageResult]) -> StageResult:
        """Run ``call``, one build-scoped stage, where this executor runs work of its kind."""
        ...


def blocked_result(result: StageResult, stage: str) -> StageResult:
    """The result recorded for a stage that cannot run because an earlier one failed."""
    return StageResult(result.scene_id, stage, "blocked",
                       error=f"not run: {result.stage} failed")


class LocalExecutor:
    name = "local"

    def run_build_stage(self, config: ResolvedConfig, stage: str,
                        call: Callable[[], StageResult]) -> StageResult:
        return call()

    def run(self, config: ResolvedConfig, tasks: list[SceneTask], data_dir: DataRoot, *,
            force: bool = False, on_start: StartCallback | None = None,
            on_result: ResultCallback | None = None,
            locks: LockOptions | None = None,
            on_progress: ProgressSink | None = None,
            verify_outputs: bool = False) -> list[StageResult]:
        results: list[StageResult] = []
        for task in tasks:
            failed: StageResult | None = None
            for stage in task.stages:
                if failed is not None:
                    result = blocked_result(failed, stage)
                else:
                    if on_start:
                        on_start(task.scene_uri, stage)
                    result = run_scene_stage(config, stage, task.scene_uri, data_dir, force=force,
                                             locks=locks, on_progress=on_progress,
                                             verify_outputs=verify_outputs)
                    if result.status == "failed":
                        failed = result
                results.append(result)
                if on_result:
                    on_result(result)
        return results

