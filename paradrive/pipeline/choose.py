"""Pick an executor by name (``--executor local|ray``)."""

from __future__ import annotations

from paradrive.pipeline.executors import Executor, LocalExecutor


def make_executor(name: str, **options) -> Executor:
    if name == "local":
        return LocalExecutor()
    if name == "ray":
        from paradrive.pipeline.ray_executor import RayExecutor

        return RayExecutor(**options)
    raise ValueError(f"unknown executor {name!r}; use 'local' or 'ray'")
