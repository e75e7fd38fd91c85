"""Executors decide where (scene, stage) tasks run; stages never know.

:class:`~paradrive.pipeline.executors.base.Executor` is what they share: the options of a run,
the log, and completion (one result per (scene, stage) asked; a scene's stages after its first
failure recorded ``blocked``). ``local`` runs every task in this process, scene after scene;
``ray`` runs each (scene, stage) as a Ray task with the stage's declared resources.
"""

from __future__ import annotations

from paradrive.pipeline.executors.base import Executor, RunOptions, SceneTask
from paradrive.pipeline.executors.local import LocalExecutor

__all__ = ["Executor", "LocalExecutor", "RunOptions", "SceneTask", "make_executor"]


def make_executor(name: str, **options) -> Executor:
    """The executor ``--executor NAME`` picks, built with its own options (Ray's address, …)."""
    if name == "local":
        return LocalExecutor()
    if name == "ray":
        from paradrive.pipeline.executors.ray import RayExecutor

        return RayExecutor(**options)
    raise ValueError(f"unknown executor {name!r}; use 'local' or 'ray'")
