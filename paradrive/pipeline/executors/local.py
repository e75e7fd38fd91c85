"""The local executor: every task in this process, scene after scene."""

from __future__ import annotations

from paradrive.contracts.specs import ResolvedConfig
from paradrive.pipeline.executors.base import Completion, Executor, RunOptions, SceneTask, run_stage
from paradrive.storage import DataRoot


class LocalExecutor(Executor):
    """Each scene's stages run in dependency order and stop at the scene's first failure; other
    scenes go on."""

    name = "local"

    def run_tasks(self, config: ResolvedConfig, tasks: list[SceneTask], data_dir: DataRoot,
                  options: RunOptions, done: Completion) -> None:
        for task in tasks:
            for index, stage in enumerate(task.stages):
                if options.on_start:
                    options.on_start(task.scene_uri, stage)
                result = run_stage(config, stage, task.scene_uri, data_dir, options)
                if not done.stage_done(task, index, result):
                    break
