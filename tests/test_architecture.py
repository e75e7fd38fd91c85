"""The shape of the package, stated as layers: every module belongs to exactly one, and imports
only modules of its own layer or of a lower one. Every import counts: module level, inside a
function and under ``if TYPE_CHECKING:`` (a type import ties two modules as much as any other).
The import graph has no cycle, no stage imports a later stage, and the stage contracts match
their YAML exactly."""

from __future__ import annotations

import ast
import importlib
import os
import re
import textwrap
from pathlib import Path

import pytest

from paradrive.contracts.base import StageParams
from paradrive.contracts.specs import StageRegistry

PACKAGE = Path(__file__).resolve().parents[1] / "paradrive"
STAGE_ORDER = ("ingest", "fit", "render", "clip", "manifest", "encode")

# Lowest first. A folder (a subpackage, written "paradrive.gs.*") belongs to one layer as a whole,
# its own package module included; a module at the top of the package is listed by itself. A new
# top-level module or folder is added to the layer it belongs to; an unlisted one fails the test.
LAYERS: dict[str, tuple[str, ...]] = {
    # tools that know nothing of a scene folder or a build: math, files, codecs, the CPU kernels
    "libraries": (
        "paradrive", "paradrive.errors", "paradrive.uri", "paradrive.io", "paradrive.redact",
        "paradrive.geometry", "paradrive.devices", "paradrive.video", "paradrive.exr",
        "paradrive.streams", "paradrive.metrics", "paradrive.splits",
        "paradrive.kernels.*",
    ),
    # the shared vocabulary: where files live, the records, what a stage gets and takes, and the
    # stage definitions read from stages/*.yaml
    "contracts": ("paradrive.contracts.*",),
    # what reads and writes the files the contracts name: the canonical scene, the log readers,
    # the 3DGS model of a scene and its fit, the synthetic street, the Wan2.1 model pieces, the
    # pair manifest, its latent cache and its adapter
    "formats": (
        "paradrive.actors", "paradrive.scene", "paradrive.storage", "paradrive.pairs",
        "paradrive.latents", "paradrive.trajectories", "paradrive.manifest", "paradrive.data",
        "paradrive.gs.*", "paradrive.ingest.*", "paradrive.synthetic.*", "paradrive.wan.*",
    ),
    # the stage modules, and the true novel views the manifest stage renders for an inference set
    "stages": ("paradrive.stages.*", "paradrive.inference"),
    # running stages over scenes: the runner, the build, executors, locks, the ledger, the plan
    "pipeline": ("paradrive.pipeline.*",),
    # what users run on builds and scenes: evaluation, inspection, the viewer, the trainers,
    # the scoring of generated videos
    "applications": (
        "paradrive.evaluation", "paradrive.inspection", "paradrive.view", "paradrive.train.*",
        "paradrive.scoring.*",
    ),
    # the command line: one module per command, and the app that gathers them
    "commands": ("paradrive.cli", "paradrive.commands.*"),
}


def _folder(module: str, packages: set[str]) -> str | None:
    """The folder entry (``paradrive.gs.*``) that holds ``module``, or None for a top-level
    module (and for ``paradrive`` itself)."""
    parts = module.split(".")
    if len(parts) < 2 or (len(parts) == 2 and module not in packages):
        return None
    return ".".join(parts[:2]) + ".*"


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


PATHS = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
PACKAGES = {name for name, path in PATHS.items() if path.name == "__init__.py"}


def _entry(module: str) -> str:
    """The LAYERS entry that places ``module``: its folder's, or its own at the top."""
    return _folder(module, PACKAGES) or module


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return {name: _imports(path, set(PATHS)) for name, path in PATHS.items()}


def _rank() -> dict[str, int]:
    """Every module's layer (its index in LAYERS, lowest 0), by its folder or by itself."""
    by_entry = {entry: rank for rank, entries in enumerate(LAYERS.values()) for entry in entries}
    return {m: by_entry[_entry(m)] for m in PATHS if _entry(m) in by_entry}


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
    entries = {_entry(m) for m in graph}
    assert sorted(entries - set(listed)) == [], "add the module or its folder to its layer in LAYERS"
    assert sorted(set(listed) - entries) == [], "a listed module or folder no longer exists"


def test_each_folder_is_one_layer_and_listed_only_as_a_folder():
    """A subpackage is placed as a whole: none of its modules is listed by itself."""
    listed = {m for modules in LAYERS.values() for m in modules}
    folders = {_folder(m, PACKAGES) for m in PATHS} - {None}
    assert sorted(m for m in listed if not m.endswith(".*") and _folder(m, PACKAGES)) == []
    assert folders <= listed


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


def test_the_inference_sets_import_no_stage(graph):
    """inference sits beside the stages: what it reads of a scene (the ingest parameters it was
    made with) comes from the contracts, not from the ingest stage."""
    assert sorted(m for m in graph["paradrive.inference"] if m.startswith("paradrive.stages")) == []


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


# The command line lives in one place: only the commands and the app that gathers them print
# through typer and rich; every other module returns data that a command renders.
CONSOLE_PACKAGES = ("typer", "rich", "click")
COMMAND_MODULES = ("paradrive.cli", "paradrive.commands")


def _console_imports(path: Path) -> set[str]:
    """The console packages (typer, rich, click) ``path`` imports anywhere."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.add(node.module.partition(".")[0])
        elif isinstance(node, ast.Import):
            found.update(a.name.partition(".")[0] for a in node.names)
    return found & set(CONSOLE_PACKAGES)


def test_only_the_commands_import_typer_or_rich():
    outside = sorted(f"{name}: {', '.join(sorted(found))}" for name, path in PATHS.items()
                     if not name.startswith(COMMAND_MODULES) and (found := _console_imports(path)))
    assert outside == [], "move the printing into the command's module (paradrive/commands/)"


def test_a_library_importing_rich_is_found(tmp_path):
    source = tmp_path / "lib.py"
    source.write_text("def table():\n    from rich.table import Table\n    return Table()\n")
    assert _console_imports(source) == {"rich"}


# No function is longer than this (its ``def`` line to its last, decorators left out): one that
# is does more than one thing.
MAX_FUNCTION_LINES = 80


def _long_functions(path: Path, module: str, limit: int = MAX_FUNCTION_LINES) -> dict[str, int]:
    """``module.qualified_name`` -> lines of each function or method of ``path`` over ``limit``."""
    found: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = (child.end_lineno or child.lineno) - child.lineno + 1
                if lines > limit:
                    found[f"{module}.{prefix}{child.name}"] = lines
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(path.read_text()), "")
    return found


def test_no_function_is_over_80_lines():
    long = sorted(f"{name} ({lines} lines)" for module, path in PATHS.items()
                  for name, lines in _long_functions(path, module).items())
    assert long == [], "split it where it does more than one thing"


def test_the_function_length_counts_from_def_to_the_last_line(tmp_path):
    """80 lines from ``def`` (the decorator not counted) pass; 81 do not."""
    body = "".join(f"x{i} = {i}\n" for i in range(79))
    source = tmp_path / "lib.py"
    source.write_text("@staticmethod\ndef short():\n" + textwrap.indent(body, " " * 4)
                      + "\n\nclass C:\n    def long(self):\n" + textwrap.indent(body, " " * 8)
                      + "        return 1\n")
    assert _long_functions(source, "lib") == {"lib.C.long": 81}


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


# The picture of docs/architecture.md is drawn from the imports: folders (and, per layer, the
# top-level modules) as boxes, an arrow where one imports the other. A stale picture fails here;
# PARADRIVE_UPDATE_ARCHITECTURE=1 pytest tests/test_architecture.py draws it anew.
ARCHITECTURE_DOC = PACKAGE.parent / "docs" / "architecture.md"
PICTURE_BEGIN = "<!-- drawn by tests/test_architecture.py from the imports; do not edit -->"
PICTURE_END = "<!-- end of the drawing -->"


def _box(module: str) -> str:
    """A module's box in the picture: its folder, or its layer's top-level modules."""
    folder = _folder(module, PACKAGES)
    if folder:
        return folder[len("paradrive."):-2] + "/"
    return f"top-level {list(LAYERS)[_rank()[module]]}"


def _picture(graph: dict[str, set[str]]) -> str:
    """The folder graph as a Mermaid flowchart (lowest layer at the bottom) and a table of
    what each box holds and imports."""
    rank = _rank()
    layer_of = {_box(m): rank[m] for m in graph}
    arrows = sorted({(_box(m), _box(d)) for m, deps in graph.items() for d in deps
                     if _box(m) != _box(d)})
    ids = {box: re.sub(r"\W+", "_", box).strip("_") for box in layer_of}
    lines = ["```mermaid", "flowchart BT"]
    for rank_, layer in reversed(list(enumerate(LAYERS))):
        lines.append(f'  subgraph layer_{layer}["{layer}"]')
        lines += [f'    {ids[b]}["{b}"]' for b in sorted(b for b in layer_of if layer_of[b] == rank_)]
        lines.append("  end")
    lines += [f"  {ids[a]} --> {ids[b]}" for a, b in arrows]
    lines += ["```", "", "| box | layer | modules | lines | imports |", "|---|---|---|---|---|"]
    for box in sorted(layer_of, key=lambda b: (-layer_of[b], b)):
        members = sorted(m for m in graph if _box(m) == box)
        size = sum(len(PATHS[m].read_text().splitlines()) for m in members)
        names = ", ".join(m.rpartition(".")[2] for m in members)
        imports = ", ".join(b for a, b in arrows if a == box) or "—"
        lines.append(f"| `{box}` | {list(LAYERS)[layer_of[box]]} | {names} | {size} | {imports} |")
    return "\n".join(lines)


def test_no_arrow_of_the_drawn_folder_graph_runs_up(graph):
    rank = _rank()
    layer_of = {_box(m): rank[m] for m in graph}
    up = sorted(f"{_box(m)} -> {_box(d)}" for m, deps in graph.items() for d in deps
                if layer_of[_box(d)] > layer_of[_box(m)])
    assert up == []


def test_the_architecture_page_shows_the_current_folder_graph(graph):
    text = ARCHITECTURE_DOC.read_text()
    head, _, rest = text.partition(PICTURE_BEGIN + "\n")
    _, _, tail = rest.partition(PICTURE_END)
    drawn = _picture(graph) + "\n"
    if os.environ.get("PARADRIVE_UPDATE_ARCHITECTURE") == "1":
        ARCHITECTURE_DOC.write_text(head + PICTURE_BEGIN + "\n" + drawn + PICTURE_END + tail)
        return
    assert PICTURE_BEGIN in text and PICTURE_END in text, "the page lost its drawing's markers"
    assert rest.partition(PICTURE_END)[0] == drawn, (
        "the code's layout changed: PARADRIVE_UPDATE_ARCHITECTURE=1 pytest tests/test_architecture.py")
