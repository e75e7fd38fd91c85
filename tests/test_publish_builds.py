"""Publishing through real builds: ``paradrive build`` killed while it republishes, a build
asked to publish clips another build's parameters made, scene locks held while the manifest
reads the clips, and build names that would lead out of ``--manifests``."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import SMOKE_SCENES, changed_entries, snapshot
from paradrive.data import PairDataset
from paradrive.errors import ConfigError
from paradrive.inspection import verify_build
from paradrive.pairs import read_index, read_pairs
from paradrive.pipeline import StageRegistry, run_build
from paradrive.pipeline.locks import LockOptions, scene_lock
from paradrive.storage import DataRoot
from paradrive.uri import parse_uri

pytestmark = pytest.mark.slow
SCENE = SMOKE_SCENES[0]
CRF30 = {"clip": {"crf": 30}}


def _build(root: Path, build: str = "K", overrides: dict | None = None, **kwargs):
    config = StageRegistry().resolve("smoke", overrides)
    return run_build(config, [SCENE], root / "data", manifests_dir=root / "m", build=build, **kwargs)


def _cli(root: Path, *args: str, env: dict | None = None) -> list[str]:
    return [sys.executable, "-m", "paradrive.cli", "build", "--scene", SCENE, "--profile", "smoke",
            "--data", str(root / "data"), "--manifests", str(root / "m"), *args]


def _env(**extra: str) -> dict:
    return {**os.environ, "COLUMNS": "1000", **extra}


@pytest.fixture(scope="module")
def built(smoke_scene, tmp_path_factory):
    """``smoke_scene`` rendered, clipped and published as build K (smoke profile)."""
    root = tmp_path_factory.mktemp("published")
    shutil.copytree(smoke_scene["data_dir"], root / "data", symlinks=True)
    assert _build(root).exit_code == 0
    return root


def _outside(root: Path, *inside: str) -> dict:
    """Everything under ``root`` but the data root and the given builds."""
    keep = ("data",) + tuple(f"m/{b}" for b in inside)
    return {k: v for k, v in snapshot(root).items()
            if not any(k == p or k.startswith(p + "/") for p in keep)}


def test_a_build_killed_while_it_republishes_leaves_the_old_build_readable(built, copy_tree):
    root = copy_tree(built)
    build = root / "m" / "K"
    old = read_index(build)
    outside = _outside(root, "K")
    proc = subprocess.Popen(_cli(root, "--build", "K", "--set", "clip.crf=30"),
                            env=_env(PARADRIVE_STOP_AT="publish:first-media"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status = os.waitpid(proc.pid, os.WUNTRACED)   # stopped after its first new media file
    assert os.WIFSTOPPED(status), proc.stderr.read().decode()[-2000:]
    proc.kill()
    assert proc.wait() == -signal.SIGKILL

    assert read_index(build) == old
    result = verify_build(build)
    assert result["ok"] and result["checked_files"] == 37, result["problems"]
    ds = PairDataset(build, verify_checksums=True)
    assert len(ds) == 72 and ds[0]["source"].shape[0] == ds.row(0)["num_frames"]

    rerun = subprocess.run(_cli(root, "--build", "K", "--set", "clip.crf=30"), env=_env(),
                           capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stdout[-2000:]
    assert verify_build(build)["ok"]
    assert _outside(root, "K") == outside
    assert _build(root, "R", CRF30).exit_code == 0   # uninterrupted, same data root
    assert read_pairs(build).equals(read_pairs(root / "m" / "R"))
    assert read_index(build).config_fingerprint == read_index(root / "m" / "R").config_fingerprint
    assert read_index(build).config_fingerprint != old.config_fingerprint


def test_a_build_does_not_publish_clips_another_builds_parameters_made(built, copy_tree):
    root = copy_tree(built)
    a = root / "m" / "K"
    old = read_index(a)
    rows = read_pairs(a)
    assert _build(root, "B", CRF30).exit_code == 0          # rewrites the scene's clips at crf 30
    only = subprocess.run(_cli(root, "--build", "K", "--stages", "manifest", "--force"),
                          env=_env(), capture_output=True, text=True)
    assert only.returncode == 1
    sid = parse_uri(SCENE).scene_id
    (line,) = [x for x in only.stdout.splitlines() if "build:K" in x]
    assert (f"scene {sid}: its clip outputs were made with other parameters" in line
            and "run this build without --stages" in line)
    assert read_index(a) == old and verify_build(a)["ok"]   # K still holds its own build

    assert _build(root).exit_code == 0                       # a plain re-run redoes the clips
    assert verify_build(a)["ok"] and verify_build(root / "m" / "B")["ok"]
    assert read_index(a).config_fingerprint == old.config_fingerprint
    assert read_pairs(a).equals(rows)


def test_the_manifest_waits_for_a_scene_another_build_holds(built, copy_tree):
    root = copy_tree(built)
    sid = parse_uri(SCENE).scene_id
    with scene_lock(DataRoot.of(root / "data"), sid, LockOptions("holder")):
        proc = subprocess.Popen(_cli(root, "--build", "K", "--stages", "manifest", "--force"),
                                env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True)
        assert proc.stdout is not None
        for line in proc.stdout:   # until the build says it waits for the lock
            if f"scene {sid} is locked by" in line:
                break
        else:
            pytest.fail(f"the manifest did not wait for the scene lock (exit {proc.wait()})")
        assert read_index(root / "m" / "K").version == "v-000001"
    out, _ = proc.communicate()
    assert proc.returncode == 0, out[-2000:]
    assert read_index(root / "m" / "K").version == "v-000002"


def test_build_dotdot_is_refused_before_anything_is_written(tmp_path):
    root = tmp_path / "D"
    (root / "media" / "other").mkdir(parents=True)
    (root / "media" / "other" / "keep.txt").write_text("keep")
    (root / "pairs-00099.parquet").write_bytes(b"not ours")
    (root / "m").mkdir()
    before = snapshot(tmp_path)
    run = subprocess.run(_cli(root, "--build", ".."), env=_env(), capture_output=True, text=True)
    assert run.returncode == 2
    (line,) = run.stdout.strip().splitlines() + run.stderr.strip().splitlines()
    assert "build name '..' is not a plain folder name" in line and "pick a name" in line
    assert changed_entries(before, snapshot(tmp_path)) == []


@pytest.mark.parametrize("name", ["..", ".", "a/b", ".hidden", "/tmp/x", "a\\b", ""])
def test_a_build_name_that_is_not_a_plain_name_is_refused(tmp_path, name):
    with pytest.raises(ConfigError, match="not a plain folder name"):
        _build(tmp_path, name, stages=["manifest"])
    assert not (tmp_path / "m").exists() or not any((tmp_path / "m").iterdir())
