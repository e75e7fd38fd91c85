"""Reading pairs needs only the light install: ``pip install paradrive`` brings what the adapter
(:mod:`paradrive.data`) uses, and the builder's packages come with the ``build`` extra.

A real process imports the adapter and reads a published build with every package that the light
``dependencies`` do not bring refused at import, as if it were not installed (the builder's
packages, and whatever else this environment holds); the package modules it loads, statically
and at run time, hold no builder module."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from test_architecture import PACKAGE, _imports, _module_name

REPO = Path(__file__).resolve().parents[1]
# what the build extra brings, by the names they are imported as
BUILDER_IMPORTS = ("ray", "open3d", "pyvista", "OpenImageIO", "OpenEXR", "numba", "typer", "rich",
                   "plyfile", "psutil", "yaml", "PIL", "google_crc32c", "matplotlib", "gsplat")
BUILDER_MODULES = ("paradrive.pipeline", "paradrive.gs", "paradrive.stages", "paradrive.ingest",
                   "paradrive.synthetic", "paradrive.cli", "paradrive.commands", "paradrive.train",
                   "paradrive.evaluation", "paradrive.inspection")

PROBE = r"""
import importlib.abc, json, sys

REFUSED = set(open(sys.argv[2]).read().split())


class NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in REFUSED:
            raise ModuleNotFoundError(f"No module named {name!r} (a builder package)", name=name)
        return None


sys.meta_path.insert(0, NotInstalled())
from paradrive.data import PairDataset

ds = PairDataset(sys.argv[1])
sample = ds[0]
print(json.dumps({"rows": len(ds), "keys": sorted(sample), "modules": sorted(sys.modules)}))
"""


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def _name(text: str) -> str:
    return re.sub(r"[-_.]+", "-", text).lower()


def _closure(requirements: list[str]) -> set[str]:
    """The distributions ``requirements`` install, with what they require in turn (no extras)."""
    found: set[str] = set()
    todo = [Requirement(r) for r in requirements]
    while todo:
        req = todo.pop()
        name = _name(req.name)
        if name in found or (req.marker is not None and not req.marker.evaluate({"extra": ""})):
            continue
        found.add(name)
        try:
            todo += [Requirement(r) for r in metadata.requires(req.name) or []]
        except metadata.PackageNotFoundError:
            continue
    return found


def _not_in_the_light_install() -> set[str]:
    """Top-level import names of this environment that no light dependency brings."""
    light = _closure(_pyproject()["dependencies"]) | {"paradrive"}
    owners = metadata.packages_distributions()
    return {m for m, dists in owners.items() if not {_name(d) for d in dists} & light} | set(BUILDER_IMPORTS)


def test_the_builder_packages_are_outside_the_light_install():
    assert set(BUILDER_IMPORTS) <= _not_in_the_light_install()
    assert {"torch", "numpy", "pyarrow", "av", "fsspec", "pydantic"}.isdisjoint(_not_in_the_light_install())


@pytest.fixture(scope="module")
def probe(smoke_build, tmp_path_factory):
    refused = tmp_path_factory.mktemp("light") / "refused.txt"
    refused.write_text("\n".join(sorted(_not_in_the_light_install())))
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-c", PROBE, str(smoke_build["build_dir"]), str(refused)],
                          capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


def test_the_adapter_reads_a_build_without_any_builder_package(probe, smoke_build):
    assert probe["rows"] == 72 * len(smoke_build["scene_uris"])
    assert {"source", "condition", "target"} <= set(probe["keys"])


def test_the_adapter_loads_no_builder_module(probe):
    loaded = [m for m in probe["modules"] if m.startswith(BUILDER_MODULES)]
    assert loaded == []


def test_the_adapter_imports_no_builder_module_anywhere():
    """Every import of the adapter and what it imports, in functions too: none is a builder module."""
    paths = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    seen, todo = set(), ["paradrive.data"]
    while todo:
        module = todo.pop()
        if module not in seen:
            seen.add(module)
            todo += _imports(paths[module], set(paths))
    assert sorted(m for m in seen if m.startswith(BUILDER_MODULES)) == []


def test_the_light_dependencies_name_no_builder_package_and_torch_as_a_range():
    project = _pyproject()
    names = {_name(Requirement(r).name) for r in project["dependencies"]}
    builder = {_name(Requirement(r).name) for r in project["optional-dependencies"]["build"]}
    assert names == {"torch", "numpy", "pydantic", "av", "pyarrow", "fsspec"}
    assert not names & builder
    (torch,) = [Requirement(r) for r in project["dependencies"] if Requirement(r).name == "torch"]
    assert "==" not in str(torch.specifier) and torch.specifier.contains("2.13.0")


def test_the_tests_use_the_gsplat_users_get():
    extras = _pyproject()["optional-dependencies"]
    assert "paradrive[gpu]" in extras["test"]
    assert not any(Requirement(r).name == "gsplat" for r in extras["test"])
    assert [Requirement(r).name for r in extras["gpu"]] == ["gsplat"]
