"""A normal install works: the wheel carries the stage definitions and the split lists, and a
fresh environment with only that wheel (its dependencies borrowed from this one) builds a scene
from a folder that is not the checkout."""

from __future__ import annotations

import json
import os
import site
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


# the environment of every command here: nothing that points Python or paradrive at the checkout
CLEAN_ENV = {k: v for k, v in os.environ.items()
             if k not in ("PYTHONPATH", "PARADRIVE_STAGES", "PARADRIVE_SPLITS")}


def _run(args: list, **kwargs) -> subprocess.CompletedProcess:
    kwargs.setdefault("env", CLEAN_ENV)
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=900,
                          **kwargs)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    done = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                 "-w", out, REPO])
    assert done.returncode == 0, done.stdout + done.stderr
    (path,) = out.glob("paradrive-*.whl")
    return path


@pytest.fixture(scope="module")
def fresh_env(tmp_path_factory, wheel) -> Path:
    """A new virtual environment holding the wheel; the heavy dependencies (torch, av, ...) are
    this environment's, reached through a path entry, not its editable checkout."""
    env = tmp_path_factory.mktemp("venv")
    done = _run([sys.executable, "-m", "venv", "--without-pip", env])
    assert done.returncode == 0, done.stderr
    purelib = Path(_run([env / "bin" / "python", "-c",
                         "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    deps = [p for p in site.getsitepackages() + [sysconfig.get_paths()["purelib"]] if Path(p).is_dir()]
    (purelib / "borrowed-dependencies.pth").write_text("\n".join(dict.fromkeys(deps)) + "\n")
    done = _run([sys.executable, "-m", "pip", "--python", env / "bin" / "python", "install",
                 "--no-deps", "--no-index", wheel])
    assert done.returncode == 0, done.stdout + done.stderr
    return env


def test_the_wheel_carries_stage_definitions_profiles_and_splits(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for stage in ("ingest", "fit", "render", "clip", "manifest"):
        assert f"paradrive/_stages/{stage}.yaml" in names
        assert f"paradrive/stages/{stage}.py" in names
    assert {"paradrive/_stages/profiles/smoke.yaml", "paradrive/_stages/train/default.yaml",
            "paradrive/_stages/budget/rates.yaml", "paradrive/_splits/paper-eval.txt"} <= names


@pytest.mark.slow
def test_an_installed_wheel_lists_the_stages_and_builds_a_scene(fresh_env, tmp_path):
    env = CLEAN_ENV
    where = _run([fresh_env / "bin" / "python", "-c", "import paradrive; print(paradrive.__file__)"],
                 cwd=tmp_path, env=env)
    assert str(fresh_env) in where.stdout, where.stdout + where.stderr   # the wheel, not the checkout
    listed = _run([fresh_env / "bin" / "paradrive", "stages"], cwd=tmp_path, env=env)
    assert listed.returncode == 0, listed.stdout + listed.stderr
    for stage in ("ingest", "fit", "render", "clip", "manifest"):
        assert stage in listed.stdout
    short = ["fit.checkpoints=[5,10,15,20]", "render.condition_checkpoints=[5,10,15]",
             "render.source_checkpoint=20"]
    built = _run([fresh_env / "bin" / "paradrive", "build", "--scene", "synthetic:demo?seed=7",
                  "--profile", "smoke", "--data", "data", "--manifests", "manifests",
                  "--build", "b", *[x for s in short for x in ("--set", s)]], cwd=tmp_path, env=env)
    assert built.returncode == 0, built.stdout + built.stderr
    index = json.loads((tmp_path / "manifests" / "b" / "index.json").read_text())
    assert index["totals"]["rows"] == 72
    assert index["exclude_splits"][0]["name"] == "paper-eval"   # the split list came along
