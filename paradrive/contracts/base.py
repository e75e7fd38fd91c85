"""What a stage is handed (:class:`StageContext`, :class:`BuildContext`) and what it declares.

A stage module defines ``Params`` (a :class:`StageParams` whose fields are exactly the
parameters of its ``stages/<name>.yaml``, with no defaults: the values live only in the YAML)
and ``run(ctx) -> Record``. The runner validates the resolved parameters into ``Params`` and
records what ``Record.summary()`` returns in the stage's marker.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

from pydantic import BaseModel, ConfigDict, PrivateAttr, ValidationError

from paradrive.errors import ConfigError
from paradrive.contracts.layout import BuildLayout, SceneLayout
from paradrive.contracts.records import StageMarker


class StageParams(BaseModel):
    """A stage's parameters, typed; ``source`` is the resolved mapping they came from (what
    fingerprints hash, so a refactor of the types never changes a fingerprint). A parameter
    with ``choices`` in its YAML is a plain ``str`` here: the YAML is where the choices live,
    and the registry checks them."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    _source: dict[str, Any] = PrivateAttr(default_factory=dict)

    @classmethod
    def of(cls, stage: str, values: dict[str, Any]) -> Any:
        try:
            params = cls.model_validate(values)
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(x) for x in err["loc"])
            why = err["msg"].removeprefix("Value error, ")   # a validator's own sentence
            raise ConfigError(f"{stage}.{where}: {why} (got {err.get('input')!r})") from exc
        params._source = dict(values)
        return params

    @property
    def source(self) -> dict[str, Any]:
        return dict(self._source) if self._source else self.model_dump()


P = TypeVar("P", bound=StageParams)


def _no_progress(done: int, total: int, **fields: Any) -> None:
    """``progress(done, total, **figures)``: see :mod:`paradrive.pipeline.progress`."""
    return None


@dataclass
class StageContext(Generic[P]):
    """What a scene-scoped stage gets: where the scene lives and the parameters it runs with."""

    stage: str
    scene_uri: str
    scene_id: str
    layout: SceneLayout
    data_dir: Path
    params: P
    log: logging.Logger
    progress: Callable[..., None] = _no_progress
    upstream: dict[str, StageMarker] = field(default_factory=dict)  # markers of the stages it needs
    hashes: dict[str, str] = field(default_factory=dict)  # sha256 of outputs the stage computed
    # every stage's parameters in this build: what fills a gap where an earlier stage's marker,
    # written by an older version, lacks a parameter (never a way around this stage's own)
    build_params: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def scene_dir(self) -> Path:
        return self.layout.root


@dataclass
class BuildContext(Generic[P]):
    """What a build-scoped stage (manifest) gets: every scene that finished its needs."""

    stage: str
    build: str
    layout: BuildLayout          # <manifests>/<build>
    data_dir: Path
    scenes: list[dict]           # [{"scene_id", "scene_uri", "scene_dir"[, "scene_location"]}]
    params: P
    log: logging.Logger
    fingerprint: str = ""
    selection: dict | None = None   # which split files left which scenes out
    progress: Callable[[int, int], None] = _no_progress

    @property
    def build_dir(self) -> Path:
        return self.layout.root


class StageRecord(Protocol):
    """What ``run`` returns: the record it wrote, summarised for the stage's marker."""

    def summary(self) -> dict[str, Any]: ...
