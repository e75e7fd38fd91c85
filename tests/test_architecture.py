"""The shape of the package: no import cycles, no stage importing a later stage, libraries that
do not reach into the pipeline, and stage contracts that match their YAML exactly."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

from paradrive.pipeline.specs import StageRegistry
from paradrive.contracts.base import StageParams

PACKAGE = Path(__file__).resolve().parents[1] / "paradrive"
STAGE_ORDER = ("ingest", "fit", "render", "clip", "manifest")
LIBRARIES = ("paradrive.gs", "paradrive.synthetic", "paradrive.ingest", "paradrive.video",
             "paradrive.geometry", "paradrive.metrics", "paradrive.streams", "paradrive.exr",
             "paradrive.io")


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The package modules ``path`` imports at run time (``if TYPE_CHECKING:`` blocks aside)."""
    tree = ast.parse(path.read_text())
    typing_only = {id(n) for node in ast.walk(tree)
                   if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
                   for n in ast.walk(node)}
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            for alias in node.names:
                full = f"{base}.{alias.name}"
                found.add(full if full in modules else base)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m in modules and m != name}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    paths = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {name: _imports(path, set(paths)) for name, path in paths.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str]:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return []

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return []


def test_the_import_graph_has_no_cycle(graph):
    assert _cycle(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_no_stage_imports_a_later_stage(graph):
    for i, stage in enumerate(STAGE_ORDER):
        later = {f"paradrive.stages.{s}" for s in STAGE_ORDER[i + 1:]}
        assert not graph[f"paradrive.stages.{stage}"] & later, stage


def test_libraries_know_no_stage_module_and_no_pipeline(graph):
    stages = {f"paradrive.stages.{s}" for s in STAGE_ORDER}
    for name, deps in graph.items():
        if name.startswith(LIBRARIES):
            bad = {d for d in deps if d in stages or d.startswith("paradrive.pipeline")}
            assert not bad, f"{name} imports {sorted(bad)}"


@pytest.mark.parametrize("stage", STAGE_ORDER)
def test_each_stage_params_match_its_yaml_exactly(stage):
    spec = StageRegistry().specs[stage]
    module = importlib.import_module(spec.entry.partition(":")[0])
    assert spec.entry == f"paradrive.stages.{stage}:run"
    assert issubclass(module.Params, StageParams)
    assert set(module.Params.model_fields) == set(spec.params)
    # no default restated in code: every value comes from the YAML
    assert all(f.is_required() for f in module.Params.model_fields.values())
    module.Params.of(stage, spec.defaults())   # the YAML's values type-check
