"""The shape of the package, stated as layers: every module belongs to exactly one, and imports
only modules of its own layer or of a lower one. Every import counts: module level, inside a
function and under ``if TYPE_CHECKING:`` (a type import ties two modules as much as any other).
The import graph has no cycle, no stage imports a later stage, and the stage contracts match
their YAML exactly."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

from paradrive.contracts.base import StageParams
from paradrive.pipeline.specs import StageRegistry

PACKAGE = Path(__file__).resolve().parents[1] / "paradrive"
STAGE_ORDER = ("ingest", "fit", "render", "clip", "manifest", "encode")

# Lowest first. A new module is added to the layer it belongs to; an unlisted one fails the test.
LAYERS: dict[str, tuple[str, ...]] = {
    # tools that know nothing of a scene folder or a build: math, files, codecs, the rasterizer
    "libraries": (
        "paradrive", "paradrive.errors", "paradrive.uri", "paradrive.io", "paradrive.redact",
        "paradrive.geometry", "paradrive.devices", "paradrive.video", "paradrive.exr",
        "paradrive.streams", "paradrive.metrics", "paradrive.splits",
        "paradrive.gs", "paradrive.gs._native", "paradrive.gs._tiles", "paradrive.gs._fused",
        "paradrive.gs.sh",
        "paradrive.gs.rasterize", "paradrive.gs.model", "paradrive.gs.init", "paradrive.gs.losses",
        "paradrive.gs._fit_loss", "paradrive.gs.strategy", "paradrive.gs.ply",
        "paradrive.synthetic.raycast",
        "paradrive.ingest.protowire", "paradrive.ingest.tfrecord", "paradrive.ingest.undistort",
        "paradrive.ingest.waymo_proto", "paradrive.ingest.sfm", "paradrive.ingest.roadmotion",
        "paradrive.ingest.egomask",
        "paradrive.train.autoencoder", "paradrive.train.flow", "paradrive.train.model", "paradrive.train.distributed",
        "paradrive.wan", "paradrive.wan.vae", "paradrive.wan.text", "paradrive.wan.recam",
    ),
    # the shared vocabulary: where files live, the records, what a stage gets and takes, and the
    # stage definitions read from stages/*.yaml (pipeline/specs.py: the runner's side of them)
    "contracts": (
        "paradrive.contracts", "paradrive.contracts.layout", "paradrive.contracts.records",
        "paradrive.contracts.base", "paradrive.contracts.params", "paradrive.pipeline.specs",
    ),
    # what reads and writes the files the contracts name: the canonical scene, the log readers,
    # the 3DGS model of a scene, the synthetic street, the pair manifest and its adapter
    "formats": (
        "paradrive.actors", "paradrive.scene", "paradrive.storage", "paradrive.pairs",
        "paradrive.trajectories", "paradrive.manifest", "paradrive.data",
        "paradrive.gs.graph", "paradrive.gs.views", "paradrive.gs.fit",
        "paradrive.synthetic", "paradrive.synthetic.street", "paradrive.synthetic.traffic",
        "paradrive.ingest", "paradrive.ingest.common", "paradrive.ingest.nuscenes_tables",
        "paradrive.ingest.synthetic", "paradrive.ingest.waymo", "paradrive.ingest.nuscenes",
        "paradrive.ingest.drivestudio", "paradrive.ingest.export", "paradrive.ingest.video",
        "paradrive.ingest.videomasks",
        "paradrive.wan.latents", "paradrive.wan.encode",
    ),
    # the stage modules, and the true novel views the manifest stage renders for an inference set
    "stages": ("paradrive.stages", *(f"paradrive.stages.{s}" for s in STAGE_ORDER), "paradrive.inference"),
    "pipeline": (
        "paradrive.pipeline", "paradrive.pipeline.budget", "paradrive.pipeline.build",
        "paradrive.pipeline.choose", "paradrive.pipeline.executors", "paradrive.pipeline.ledger",
        "paradrive.pipeline.locks", "paradrive.pipeline.progress", "paradrive.pipeline.ray_executor",
        "paradrive.pipeline.runner", "paradrive.pipeline.scenes", "paradrive.pipeline.status",
    ),
    # the commands: build, inspect, eval, view, train
    "cli": (
        "paradrive.cli", "paradrive.evaluation", "paradrive.inspection", "paradrive.view",
        "paradrive.train", "paradrive.train.cli", "paradrive.train.trainer",
        "paradrive.wan.cli", "paradrive.wan.train", "paradrive.wan.convert", "paradrive.wan.generate",
    ),
}


def _module_name(path: Path, root: Path = PACKAGE.parent) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set[str], root: Path = PACKAGE.parent) -> set[str]:
    """The package modules ``path`` (a file under ``root``) imports anywhere: module level, in
    functions and in ``if TYPE_CHECKING:`` blocks."""
    tree = ast.parse(path.read_text())
    name = _module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
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


def _rank() -> dict[str, int]:
    return {module: rank for rank, modules in enumerate(LAYERS.values()) for module in modules}


def _layer_breaches(graph: dict[str, set[str]], rank: dict[str, int]) -> list[str]:
    """``module -> dependency`` for every import of a higher layer."""
    return sorted(f"{name} -> {dep}" for name, deps in graph.items() for dep in deps
                  if rank[dep] > rank[name])


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


def test_every_module_belongs_to_exactly_one_layer(graph):
    listed = [m for modules in LAYERS.values() for m in modules]
    assert sorted(m for m in set(listed) if listed.count(m) > 1) == []
    assert sorted(set(graph) - set(listed)) == [], "add the module to its layer in LAYERS"
    assert sorted(set(listed) - set(graph)) == [], "a listed module no longer exists"


def test_no_module_imports_a_higher_layer(graph):
    assert _layer_breaches(graph, _rank()) == []


def test_a_type_only_import_of_a_higher_layer_is_a_breach(tmp_path):
    """The rule holds for ``if TYPE_CHECKING:`` imports too: a library naming a stage's type
    is reported."""
    source = tmp_path / "paradrive" / "lib.py"
    source.parent.mkdir()
    source.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                      "    from paradrive.stages.fit import Params\n")
    deps = _imports(source, {"paradrive.lib", "paradrive.stages.fit"}, root=tmp_path)
    assert deps == {"paradrive.stages.fit"}
    rank = {"paradrive.lib": 0, "paradrive.stages.fit": 3}
    assert _layer_breaches({"paradrive.lib": deps, "paradrive.stages.fit": set()}, rank) == [
        "paradrive.lib -> paradrive.stages.fit"]


def test_the_import_graph_has_no_cycle(graph):
    assert _cycle(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_no_stage_imports_a_later_stage(graph):
    for i, stage in enumerate(STAGE_ORDER):
        later = {f"paradrive.stages.{s}" for s in STAGE_ORDER[i + 1:]}
        assert not graph[f"paradrive.stages.{stage}"] & later, stage


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


def test_the_command_line_starts_without_torch():
    """Every command registers at start-up; one that imported torch there (1.2 s idle, seconds on
    a loaded machine) would make ``paradrive status`` and ``inspect`` pay it. The modules that
    need torch are imported when their command runs."""
    import subprocess
    import sys

    code = ("import sys, paradrive.cli; heavy = sorted(m for m in ('torch', 'diffusers', 'pycolmap', "
            "'open3d', 'pyvista') if m in sys.modules); print(','.join(heavy))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == ""
