"""Declarative stages: ``stages/<name>.yaml`` and profiles ``stages/profiles/<name>.yaml``.

A stage file::

    name: fit
    entry: paradrive.gs.fit:run_stage      # module:function called with a StageContext
    needs: [ingest]
    scope: scene                            # or 'build' (runs once over many scenes)
    resources: {cpu: 2, gpu: 1, memory_gb: 16}
    outputs: ["gs/ckpt_{checkpoints:06d}.ply", "gs/fit.json"]
    reads: ["scene.json", "images"]         # optional: what a URL data root must bring to the worker
    retention:                              # optional: a boolean parameter -> the outputs it keeps
      keep_frames: ["renders/*/*/*"]        # false: let them go once every stage needing this one is done
    params:
      checkpoints: {default: [100, 500, 1000, 30000], doc: "paper §3: ..."}
      cameras: {default: auto, types: [str, list], doc: "..."}   # types: when one type is not enough

A profile overrides parameters by stage::

    name: smoke
    description: seconds per stage, for tests
    stages:
      fit: {checkpoints: [25, 50, 100, 400]}

Every name is checked: a typo in a stage file, a profile or an override is an error that says
what was expected, never a silent default.
"""

from __future__ import annotations

import difflib
import importlib
import os
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from paradrive.errors import ConfigError
from paradrive.contracts.base import StageParams


class Resources(BaseModel):
    model_config = ConfigDict(extra="forbid")
    cpu: float = 1
    gpu: float = 0
    memory_gb: float = 2


class Param(BaseModel):
    model_config = ConfigDict(extra="forbid")
    default: Any = None
    doc: str = Field(min_length=1)
    choices: list[Any] | None = None
    # value types taken when the default's own type is not the only one, e.g. [str, list]
    types: list[Literal["str", "int", "float", "bool", "list", "dict"]] | None = None


class StageSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    entry: str
    needs: list[str] = []
    scope: Literal["scene", "build"] = "scene"
    description: str = ""
    resources: Resources = Resources()
    outputs: list[str] = []
    reads: list[str] | None = None   # scene files it reads (globs); None = the whole scene folder
    params: dict[str, Param] = {}
    # retention: a boolean parameter -> the outputs (globs) it keeps; when false they are deleted
    # once every stage that needs this one has used them (paradrive.pipeline.runner)
    retention: dict[str, list[str]] = {}
    file: str = ""

    @field_validator("entry")
    @classmethod
    def _entry_form(cls, value: str) -> str:
        if ":" not in value:
            raise ValueError(f"entry must read 'module:function', got {value!r}")
        return value

    @model_validator(mode="after")
    def _retention_params(self) -> StageSpec:
        for key in self.retention:
            if not isinstance(self.params.get(key, Param(doc="-")).default, bool):
                raise ValueError(f"retention names '{key}', which must be a parameter with a "
                                 f"boolean default (true keeps the files)")
        return self

    def defaults(self) -> dict[str, Any]:
        return {k: p.default for k, p in self.params.items()}

    def fingerprinted(self, params: dict[str, Any]) -> dict[str, Any]:
        """The parameters that decide what the stage writes: all but the retention switches,
        which only decide how long the files stay."""
        return {k: v for k, v in params.items() if k not in self.retention}

    def released(self, params: dict[str, Any]) -> list[str]:
        """The outputs (globs) whose retention switch is off in ``params``."""
        return [glob for key, globs in self.retention.items() if params.get(key) is False
                for glob in globs]


class Profile(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    description: str = ""
    stages: dict[str, dict[str, Any]] = {}
    file: str = ""


def default_stages_dir() -> Path:
    """``$PARADRIVE_STAGES``, else the project's ``stages/`` folder: in a checkout (and an
    editable install) next to the package, in an installed wheel inside it (``paradrive/_stages``)."""
    env = os.environ.get("PARADRIVE_STAGES")
    if env:
        return Path(env)
    package = Path(__file__).resolve().parents[1]
    checkout = package.parent / "stages"
    return checkout if (checkout / "fit.yaml").is_file() else package / "_stages"


def _read_yaml(path: Path) -> dict:
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return doc


def _pydantic_message(path: Path, exc: ValidationError) -> str:
    lines = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"])
        if err["type"] == "extra_forbidden":
            lines.append(f"unknown key '{loc}'")
        else:
            lines.append(f"'{loc}': {err['msg']}")
    return f"{path}: " + "; ".join(lines)


def _suggest(name: str, options) -> str:
    close = difflib.get_close_matches(name, list(options), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def coerce(stage: str, key: str, param: Param, value: Any, origin: str) -> Any:
    """Check an override against the default's type (ints pass where floats are expected)."""
    default = param.default
    if isinstance(value, bool) and isinstance(default, str):
        # YAML 1.1 reads an unquoted on / off / yes / no as a boolean: take the word back
        value = next((c for c in param.choices or () if c in (("on", "yes", "true") if value
                                                                 else ("off", "no", "false"))), value)
    if param.choices is not None and value not in param.choices:
        raise ConfigError(f"{origin}: {stage}.{key} = {value!r} is not one of {param.choices}")
    if param.types is not None and value is not None:
        kind = "float" if type(value) is int and "float" in param.types else type(value).__name__
        if kind not in param.types:
            raise ConfigError(f"{origin}: {stage}.{key} = {value!r} has type "
                              f"{type(value).__name__}, expected one of {', '.join(param.types)}")
        return value
    if default is None or value is None:
        return value
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif isinstance(default, (list, tuple)):
        ok = isinstance(value, (list, tuple))
    elif isinstance(default, dict):
        ok = isinstance(value, dict)
    else:
        ok = isinstance(value, type(default))
    if not ok:
        raise ConfigError(f"{origin}: {stage}.{key} = {value!r} has type "
                          f"{type(value).__name__}, expected {type(default).__name__} "
                          f"like the default {default!r}")
    return value


class StageRegistry:
    """All stage specs and profiles of one ``stages/`` folder."""

    def __init__(self, stages_dir: str | Path | None = None):
        self.dir = Path(stages_dir) if stages_dir else default_stages_dir()
        if not self.dir.is_dir():
            raise ConfigError(f"stage folder {self.dir} does not exist; set PARADRIVE_STAGES or "
                              f"run from the project checkout")

    @cached_property
    def specs(self) -> dict[str, StageSpec]:
        specs: dict[str, StageSpec] = {}
        for path in sorted(self.dir.glob("*.yaml")):
            doc = _read_yaml(path)
            try:
                spec = StageSpec(**doc, file=str(path))
            except ValidationError as exc:
                raise ConfigError(_pydantic_message(path, exc)) from exc
            if spec.name != path.stem:
                raise ConfigError(f"{path}: name '{spec.name}' must match the file name '{path.stem}'")
            specs[spec.name] = spec
        for spec in specs.values():
            for need in spec.needs:
                if need not in specs:
                    raise ConfigError(f"{spec.file}: needs unknown stage '{need}'"
                                      f"{_suggest(need, specs)}")
        self._check_acyclic(specs)
        return specs

    @staticmethod
    def _check_acyclic(specs: dict[str, StageSpec]) -> None:
        state: dict[str, int] = {}

        def visit(name: str, chain: list[str]) -> None:
            if state.get(name) == 1:
                raise ConfigError(f"stage dependency cycle: {' -> '.join(chain + [name])}")
            if state.get(name) == 2:
                return
            state[name] = 1
            for need in specs[name].needs:
                visit(need, chain + [name])
            state[name] = 2

        for name in specs:
            visit(name, [])

    def order(self, names: list[str] | None = None) -> list[str]:
        """Stage names in dependency order (all stages, or the given subset)."""
        specs = self.specs
        wanted = list(specs) if names is None else list(names)
        for name in wanted:
            if name not in specs:
                raise ConfigError(f"unknown stage '{name}'{_suggest(name, specs)}; "
                                  f"stages are: {', '.join(self.order())}")
        ordered: list[str] = []

        def visit(name: str) -> None:
            if name in ordered:
                return
            for need in specs[name].needs:
                visit(need)
            ordered.append(name)

        for name in specs:
            visit(name)
        return [n for n in ordered if n in wanted]

    def profiles(self) -> list[str]:
        folder = self.dir / "profiles"
        return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []

    def profile(self, name: str | None) -> Profile:
        if name in (None, "", "paper", "default"):
            return Profile(name="paper", description="the paper's parameters (stage defaults)")
        path = self.dir / "profiles" / f"{name}.yaml"
        if not path.is_file():
            raise ConfigError(f"unknown profile '{name}'{_suggest(name, self.profiles())}; "
                              f"profiles are: paper, {', '.join(self.profiles())}")
        try:
            return Profile(**_read_yaml(path), file=str(path))
        except ValidationError as exc:
            raise ConfigError(_pydantic_message(path, exc)) from exc

    def resolve(self, profile: str | None = None,
                overrides: dict[str, dict[str, Any]] | None = None) -> ResolvedConfig:
        """Parameters of every stage: defaults, then the profile, then explicit overrides."""
        prof = self.profile(profile)
        params = {name: spec.defaults() for name, spec in self.specs.items()}
        origins = {name: {k: "default" for k in spec.params} for name, spec in self.specs.items()}
        layers = [(prof.stages, f"profile {prof.name} ({prof.file})"),
                  (overrides or {}, "command line")]
        for layer, origin in layers:
            for stage, values in layer.items():
                if stage not in self.specs:
                    raise ConfigError(f"{origin}: unknown stage '{stage}'{_suggest(stage, self.specs)}")
                if not isinstance(values, dict):
                    raise ConfigError(f"{origin}: '{stage}' must map parameter names to values")
                spec = self.specs[stage]
                for key, value in values.items():
                    if key not in spec.params:
                        raise ConfigError(f"{origin}: stage '{stage}' has no parameter '{key}'"
                                          f"{_suggest(key, spec.params)}; see {spec.file}")
                    params[stage][key] = coerce(stage, key, spec.params[key], value, origin)
                    origins[stage][key] = origin.split(" (")[0]
        return ResolvedConfig(profile=prof.name, params=params, origins=origins,
                              stages_dir=str(self.dir))


class ResolvedConfig(BaseModel):
    """The parameters every stage runs with; picklable, so executors can ship it to workers."""

    profile: str
    params: dict[str, dict[str, Any]]
    origins: dict[str, dict[str, str]]
    stages_dir: str

    def registry(self) -> StageRegistry:
        return StageRegistry(self.stages_dir)

    def typed(self, stage: str) -> Any:
        """The stage's parameters as its module's typed ``Params``."""
        return typed_params(self.registry().specs[stage], self.params[stage])


def typed_params(spec: StageSpec, values: dict[str, Any]) -> Any:
    """``values`` as the stage module's ``Params`` (a module without one gets the mapping)."""
    module = importlib.import_module(spec.entry.partition(":")[0])
    kind = getattr(module, "Params", None)
    if isinstance(kind, type) and issubclass(kind, StageParams):
        return kind.of(spec.name, values)
    return dict(values)


def parse_overrides(items: list[str] | None) -> dict[str, dict[str, Any]]:
    """``["fit.iterations=200", "render.offsets=[1,-1]"]`` -> {"fit": {"iterations": 200}, ...}."""
    out: dict[str, dict[str, Any]] = {}
    for item in items or []:
        key, sep, raw = item.partition("=")
        stage, dot, name = key.partition(".")
        if not sep or not dot or not stage or not name:
            raise ConfigError(f"override {item!r} must read 'stage.param=value', e.g. fit.iterations=200")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override {item!r}: value is not valid YAML ({exc})") from exc
        out.setdefault(stage, {})[name] = value
    return out
