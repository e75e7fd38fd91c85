"""What every executor shares: the options of a run, the log, and completion.

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

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from paradrive.contracts.specs import ResolvedConfig
from paradrive.pipeline.locks import LockOptions
from paradrive.pipeline.progress import ProgressSink
from paradrive.pipeline.runner import StageResult, run_scene_stage
from paradrive.storage import DataRoot

ResultCallback = Callable[[StageResult], None]
StartCallback = Callable[[str, str], None]


@dataclass(frozen=True)
class SceneTask:
    scene_uri: str
    stages: tuple[str, ...]


@dataclass(frozen=True)
class RunOptions:
    """How a run goes, whatever runs it (see the module doc)."""

    force: bool = False
    on_start: StartCallback | None = None
    on_result: ResultCallback | None = None
    locks: LockOptions | None = None
    on_progress: ProgressSink | None = None
    verify_outputs: bool = False

    def for_worker(self) -> RunOptions:
        """These options without the driver's callbacks: what a task sent to another process
        takes along (its progress reaches the driver another way)."""
        return dataclasses.replace(self, on_start=None, on_result=None, on_progress=None)


def run_stage(config: ResolvedConfig, stage: str, scene_uri: str, data_dir: DataRoot,
              options: RunOptions) -> StageResult:
    """One (scene, stage) with a run's options, wherever an executor runs it."""
    return run_scene_stage(config, stage, scene_uri, data_dir, force=options.force, locks=options.locks,
                           on_progress=options.on_progress, verify_outputs=options.verify_outputs)


def blocked_result(result: StageResult, stage: str) -> StageResult:
    """The result recorded for a stage that cannot run because an earlier one failed."""
    return StageResult(result.scene_id, stage, "blocked",
                       error=f"not run: {result.stage} failed")


@dataclass
class Completion:
    """The results of one run, in the order they came back; each one is handed to
    ``on_result`` as it is recorded."""

    on_result: ResultCallback | None = None
    results: list[StageResult] = field(default_factory=list)

    def record(self, result: StageResult) -> None:
        self.results.append(result)
        if self.on_result:
            self.on_result(result)

    def stage_done(self, task: SceneTask, index: int, result: StageResult) -> bool:
        """Record stage ``index`` of ``task``; after a failure its later stages are recorded
        ``blocked``. Returns whether the scene goes on to its next stage."""
        self.record(result)
        if result.status == "failed":
            for later in task.stages[index + 1:]:
                self.record(blocked_result(result, later))
            return False
        return index + 1 < len(task.stages)


class Executor:
    """Runs (scene, stage) tasks somewhere; subclasses say where (:meth:`run_tasks`)."""

    name = "base"

    def __init__(self) -> None:
        self.log = logging.getLogger(f"paradrive.{self.name}")

    def run(self, config: ResolvedConfig, tasks: list[SceneTask], data_dir: DataRoot,
            options: RunOptions | None = None) -> list[StageResult]:
        """Every stage of every task; a scene's stages in order, stopping at its first failure.
        Returns one result per (scene, stage) asked."""
        options = options or RunOptions()
        done = Completion(options.on_result)
        if tasks:
            self.run_tasks(config, [t for t in tasks if t.stages], DataRoot.of(data_dir), options, done)
        return done.results

    def run_tasks(self, config: ResolvedConfig, tasks: list[SceneTask], data_dir: DataRoot,
                  options: RunOptions, done: Completion) -> None:
        raise NotImplementedError

    def run_build_stage(self, config: ResolvedConfig, stage: str,
                        call: Callable[[], StageResult]) -> StageResult:
        """Run ``call``, one build-scoped stage, where this executor runs work of its kind (by
        default in this process)."""
        return call()
