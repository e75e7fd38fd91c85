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
      checkpoints: {default: [100, 500, 1000, 30000], doc: "paper §3: ...", nonempty: true,
                    items: {min: 1}}
      cameras: {default: auto, types: [str, list], doc: "..."}   # types: when one type is not enough
      downscale: {default: 1, doc: "...", min: 1}

What a value may be is declared beside its default: ``min`` / ``max`` (inclusive), ``above`` /
``below`` (exclusive), ``choices``, ``pattern`` (a regular expression the whole string
matches), ``nonempty`` (a list, string or mapping), ``items`` (the same rules for each element of
a list or each value of a mapping) and ``nullable`` (null is taken although the default is not).
``fingerprint: false`` leaves a parameter out of the stage's fingerprint (one that decides how
long files stay, like ``manifest.keep_versions_for``, not what the stage writes).
A float is never NaN or infinite. The defaults are checked when the stage file is read, every
profile and ``--set`` value when it is applied, so a build refuses a value that cannot work
before any stage runs, naming the parameter, the value, what is allowed and where it came from.

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
import math
import os
import re
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


class Bounds(BaseModel):
    """What a value (or each element of a list, with ``items``) may be."""

    model_config = ConfigDict(extra="forbid")
    min: float | None = None
    max: float | None = None
    above: float | None = None   # exclusive bounds: a rate or a size that must be positive
    below: float | None = None
    choices: list[Any] | None = None
    pattern: str | None = None   # a regular expression the whole string matches
    nonempty: bool = False
    items: Bounds | None = None  # rules of each element of a list (each value of a mapping)
    among: str | None = None     # 'stage.param': the value (each element) must be one of its values

    @field_validator("pattern")
    @classmethod
    def _compiles(cls, value: str | None) -> str | None:
        if value is not None:
            re.compile(value)
        return value

    def allowed(self) -> str:
        """The rules in words: 'at least 1, at most 51'."""
        words = [f"one of {self.choices}" if self.choices is not None else "",
                 f"matching {self.pattern}" if self.pattern else "",
                 f"at least {self.min:g}" if self.min is not None else "",
                 f"more than {self.above:g}" if self.above is not None else "",
                 f"at most {self.max:g}" if self.max is not None else "",
                 f"less than {self.below:g}" if self.below is not None else "",
                 "not empty" if self.nonempty else "",
                 f"each element {self.items.allowed()}" if self.items is not None else "",
                 f"among {self.among}" if self.among else ""]
        return ", ".join(w for w in words if w) or "any finite value"

    def problem(self, value: Any) -> str | None:
        """Why ``value`` breaks these rules, or None."""
        if isinstance(value, float) and not math.isfinite(value):
            return "is not a finite number"
        if self.choices is not None and value not in self.choices:
            return "is not allowed"
        if self.pattern is not None and isinstance(value, str) and not re.fullmatch(self.pattern, value):
            return "is not allowed"
        if isinstance(value, (int, float)) and not isinstance(value, bool) and (
                (self.min is not None and value < self.min) or (self.max is not None and value > self.max)
                or (self.above is not None and value <= self.above)
                or (self.below is not None and value >= self.below)):
            return "is out of range"
        if self.nonempty and isinstance(value, (str, list, tuple, dict)) and not value:
            return "is empty"
        elements = list(value.values()) if isinstance(value, dict) else list(value) \
            if isinstance(value, (list, tuple)) else []
        rule = self.items or Bounds()   # without rules of their own, elements are still finite
        for element in elements:
            if element is not None and (why := rule.problem(element)):
                return f"has an element {element!r} that {why}"
        return None


class Param(Bounds):
    default: Any = None
    doc: str = Field(min_length=1)
    # value types taken when the default's own type is not the only one, e.g. [str, list]
    types: list[Literal["str", "int", "float", "bool", "list", "dict"]] | None = None
    nullable: bool = False   # null is taken although the default is not null
    # false: the value decides how long files stay or how a stage goes about its work, never
    # what it writes, so it is left out of the stage's fingerprint
    fingerprint: bool = True


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
    # a parameter (default null) that switches the stage on: a build naming no --stages runs it
    # only when the parameter is set, and a build naming it needs the parameter set
    enabled_by: str | None = None
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
        if self.enabled_by is not None and (self.enabled_by not in self.params
                                            or self.params[self.enabled_by].default is not None):
            raise ValueError(f"enabled_by names '{self.enabled_by}', which must be a parameter "
                             f"with a null default (setting it switches the stage on)")
        return self

    def enabled(self, params: dict[str, Any]) -> bool:
        """Whether a build that names no stages runs this one (always, unless ``enabled_by``
        names a parameter that is still null)."""
        return self.enabled_by is None or params.get(self.enabled_by) is not None

    def defaults(self) -> dict[str, Any]:
        return {k: p.default for k, p in self.params.items()}

    def fingerprinted(self, params: dict[str, Any]) -> dict[str, Any]:
        """The parameters that decide what the stage writes: all but the retention switches
        and the parameters declared ``fingerprint: false``, which only decide how long the
        files stay."""
        return {k: v for k, v in params.items() if k not in self.retention
                and (k not in self.params or self.params[k].fingerprint)}

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
        doc = yaml.safe_load(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a text file (byte {exc.object[exc.start]:#04x} at offset "
                          f"{exc.start} is not UTF-8); give a YAML file") from exc
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read ({exc.strerror or exc})") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}{yaml_problem(exc)}; fix the YAML there") from exc
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return doc


def yaml_problem(exc: yaml.YAMLError) -> str:
    """A YAML error in one line: ``:3:7: mapping values are not allowed here`` (line and column
    from 1, as editors count)."""
    mark = getattr(exc, "problem_mark", None)
    where = f":{mark.line + 1}:{mark.column + 1}" if mark is not None else ""
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    return f"{where}: not valid YAML: {problem}"


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
    """Check a value against the parameter's type (the default's, or ``types``; ints pass where
    floats are expected) and its declared rules; ``origin`` says where it came from."""
    if isinstance(value, bool) and isinstance(param.default, str):
        # YAML 1.1 reads an unquoted on / off / yes / no as a boolean: take the word back
        value = next((c for c in param.choices or () if c in (("on", "yes", "true") if value
                                                                 else ("off", "no", "false"))), value)
    if value is None:
        if param.default is not None and not param.nullable:
            raise ConfigError(f"{origin}: {stage}.{key} = null is not allowed (allowed: "
                              f"{param.allowed()}); change it to a value like the default "
                              f"{param.default!r}")
        return value
    value = _typed(stage, key, param, value, origin)
    why = param.problem(value)
    if why:
        raise ConfigError(f"{origin}: {stage}.{key} = {value!r} {why} (allowed: {param.allowed()}); "
                          f"change it to an allowed value")
    return value


def _typed(stage: str, key: str, param: Param, value: Any, origin: str) -> Any:
    """``value`` if its type fits the parameter (an int taken as a float where a float is due)."""
    default = param.default
    if param.types is not None:
        kind = "float" if type(value) is int and "float" in param.types else type(value).__name__
        if kind not in param.types:
            raise ConfigError(f"{origin}: {stage}.{key} = {value!r} has type "
                              f"{type(value).__name__}, expected one of {', '.join(param.types)}")
        return value
    if default is None:
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
            self._check_rules(spec, specs)
        self._check_acyclic(specs)
        return specs

    @staticmethod
    def _check_rules(spec: StageSpec, specs: dict[str, StageSpec]) -> None:
        """Each default keeps its own rules; ``among`` names a parameter that exists."""
        for key, param in spec.params.items():
            stage, _, name = (param.among or ".").partition(".")
            if param.among and name not in (specs[stage].params if stage in specs else {}):
                raise ConfigError(f"{spec.file}: {spec.name}.{key} is declared among unknown "
                                  f"parameter '{param.among}'; name one as stage.param")
            if param.default is not None and (why := param.problem(param.default)):
                raise ConfigError(f"{spec.file}: {spec.name}.{key} default {param.default!r} {why} "
                                  f"(allowed: {param.allowed()}); fix the default or the rule")

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
        # (what a message says, what `paradrive stages` shows in its "from" column)
        layers = [(prof.stages, f"profile {prof.name} ({prof.file})", f"profile {prof.name}"),
                  (overrides or {}, "--set", "command line")]
        for layer, origin, shown in layers:
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
                    origins[stage][key] = shown
        return ResolvedConfig(profile=prof.name, params=params, origins=origins,
                              stages_dir=str(self.dir))


_REGISTRIES: dict[tuple, StageRegistry] = {}


def cached_registry(stages_dir: str | Path | None = None) -> StageRegistry:
    """The stage definitions of ``stages_dir`` (default: :func:`default_stages_dir`), read once
    while the folder's stage files keep their sizes and modification times (a stat of each,
    never a read, tells)."""
    folder = Path(stages_dir) if stages_dir else default_stages_dir()
    key = (str(folder), tuple((p.name, st.st_size, st.st_mtime_ns)
                              for p in sorted(folder.glob("*.yaml")) for st in [p.stat()]))
    if key not in _REGISTRIES:
        if len(_REGISTRIES) >= 8:  # tests resolve many stage folders in one process
            _REGISTRIES.clear()
        _REGISTRIES[key] = StageRegistry(folder)
    return _REGISTRIES[key]
_LAST_REGISTRY: list[tuple[ResolvedConfig, StageRegistry]] = []


class ResolvedConfig(BaseModel):
    """The parameters every stage runs with; picklable, so executors can ship it to workers."""

    profile: str
    params: dict[str, dict[str, Any]]
    origins: dict[str, dict[str, str]]
    stages_dir: str

    def registry(self) -> StageRegistry:
        """The stage definitions of ``stages_dir``, read once. Reading and validating the stage
        files takes tens of ms and deciding one (scene, stage) needs them several times: at 1,600
        scenes that alone made a no-op re-run take many minutes. The config last asked about is
        answered at once; another (a Ray worker's copy of it) by the folder and each stage file's
        size and modification time, so an edited stage file is read again."""
        if _LAST_REGISTRY and _LAST_REGISTRY[0][0] is self:
            return _LAST_REGISTRY[0][1]
        registry = cached_registry(self.stages_dir)
        _LAST_REGISTRY[:] = [(self, registry)]
        return registry

    def selected(self, stages: list[str] | None = None) -> list[str]:
        """The stages a build runs, in order: ``stages``, or every stage switched on
        (:meth:`StageSpec.enabled`) when none are named."""
        registry = self.registry()
        names = registry.order(stages)
        return names if stages is not None else [s for s in names if registry.specs[s].enabled(self.params[s])]

    def check(self, stages: list[str] | None = None) -> None:
        """Every parameter of ``stages`` (default: all) through its stage's typed ``Params``, so
        a value the declared rules let through but the stage cannot take fails before any stage
        runs, naming where the value came from. A stage named in ``stages`` whose ``enabled_by``
        parameter is null is refused."""
        registry = self.registry()
        selected = registry.order(stages)
        for stage in selected:
            spec = registry.specs[stage]
            if stages is not None and not spec.enabled(self.params[stage]):
                param = spec.params[spec.enabled_by or ""]
                raise ConfigError(f"stage {stage} needs {stage}.{spec.enabled_by} ({param.doc}); "
                                  f"pass --set {stage}.{spec.enabled_by}=... or leave {stage} out "
                                  f"of --stages")
            self._check_among(registry.specs[stage], selected)
            try:
                typed_params(registry.specs[stage], self.params[stage])
            except ImportError:
                continue   # a stage not implemented here: it fails as it runs, naming its entry
            except ConfigError as exc:
                key = next((k for k in self.params[stage]
                            if str(exc).startswith((f"{stage}.{k}:", f"{stage}.{k}."))), None)
                origin = self.origins[stage].get(key or "", "")
                source = {"default": registry.specs[stage].file, "command line": "--set"}.get(origin, origin)
                raise ConfigError(f"{exc} (from {source})" if source else str(exc)) from exc

    def _check_among(self, spec: StageSpec, selected: list[str]) -> None:
        """Values declared ``among`` another selected stage's parameter are among its values."""
        for key, param in spec.params.items():
            stage, _, name = (param.among or "").partition(".")
            if stage not in selected:
                continue
            value, pool = self.params[spec.name][key], self.params[stage][name]
            missing = [v for v in (value if isinstance(value, list) else [value]) if v not in pool]
            if missing:
                origins = {self.origins[spec.name][key], self.origins[stage][name]}
                raise ConfigError(f"{spec.name}.{key} = {value!r} is not among {param.among} = "
                                  f"{pool!r} (values from: {', '.join(sorted(origins))}); "
                                  f"add {missing[0]!r} to {param.among} or change {spec.name}.{key}")

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


class _ValueLoader(yaml.SafeLoader):
    """PyYAML's safe loader, reading ``1e-3`` and ``3E8`` as floats: YAML 1.1 takes a float only
    with a dot, so they would stay strings (YAML 1.2 reads them as numbers)."""


_ValueLoader.add_implicit_resolver("tag:yaml.org,2002:float",
                                   re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+$"),
                                   list("-+0123456789."))


def yaml_value(raw: str) -> Any:
    """A ``--set`` value read as YAML (safe: a tag such as ``!!python/object`` raises), with
    exponent numbers written without a dot read as floats. Raises yaml.YAMLError where ``raw``
    is not plain YAML."""
    return yaml.load(raw, Loader=_ValueLoader)  # a SafeLoader: no tag constructs an object


def parse_overrides(items: list[str] | None) -> dict[str, dict[str, Any]]:
    """``["fit.iterations=200", "render.offsets=[1,-1]"]`` -> {"fit": {"iterations": 200}, ...}."""
    out: dict[str, dict[str, Any]] = {}
    for item in items or []:
        key, sep, raw = item.partition("=")
        stage, dot, name = key.partition(".")
        if not sep or not dot or not stage or not name:
            raise ConfigError(f"override {item!r} must read 'stage.param=value', e.g. fit.iterations=200")
        try:
            value = yaml_value(raw)
        except yaml.YAMLError as exc:
            problem = getattr(exc, "problem", None) or "unreadable"
            raise ConfigError(f"--set {item!r}: the value is not valid YAML ({problem}); write it "
                              f"as YAML, e.g. render.offsets_m=[1,-1] or ingest.image_ext=png") from exc
        out.setdefault(stage, {})[name] = value
    return out
