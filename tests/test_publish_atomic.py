"""Publishing a build in one step: a republish killed at any point leaves the old build whole,
the temporaries it left are found and removed, and a re-run lands the new build as an
uninterrupted one would. The publishing process is a real one, killed with SIGKILL where it
stopped itself (``PARADRIVE_STOP_AT``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import changed_entries, snapshot, stage_params
from paradrive.data import PairDataset
from paradrive.errors import ParaDriveError
from paradrive.inspection import verify_build
from paradrive.io import is_temporary
from paradrive.manifest import publish, scene_rows
from paradrive.pairs import read_index, read_pairs, version_dir
from paradrive.stages.manifest import build_manifest
from test_manifest import scenes_entry, write_clip_scene

TESTS = Path(__file__).parent
SCENE = "synthetic-a"
# build_manifest in a process of its own: argv = build folder, scene folder, media mode
PUBLISH = """
import sys
from pathlib import Path
from conftest import stage_params
from paradrive.stages.manifest import build_manifest
from test_manifest import scenes_entry
build_manifest(Path(sys.argv[1]), [scenes_entry(Path(sys.argv[2]))],
               stage_params("manifest", {"shard_rows": 1, "media": sys.argv[3]}))
"""


def _scene(root: Path, width: int) -> Path:
    """One scene, 2 pairs; ``width`` tells one version of its clips from the other."""
    return write_clip_scene(root / f"data{width}", SCENE, clips=("middle",), offsets=(1.0, 2.0),
                            conditions=(100,), width=width)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("publish")
    return {"old": _scene(root, 64), "new": _scene(root, 80)}


def _publish(build: Path, scene: Path, mode: str = "hardlink") -> None:
    build_manifest(build, [scenes_entry(scene)], stage_params("manifest", {"shard_rows": 1,
                                                                           "media": mode}))


def _killed_at(point: str, build: Path, scene: Path, mode: str = "hardlink") -> None:
    """Publish ``scene`` into ``build`` in a new process and SIGKILL it at ``point``."""
    env = {**os.environ, "PARADRIVE_STOP_AT": point,
           "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", PUBLISH, str(build), str(scene), mode], env=env,
                            cwd=TESTS, stderr=subprocess.PIPE)
    _, status = os.waitpid(proc.pid, os.WUNTRACED)  # returns once the process stopped itself
    assert os.WIFSTOPPED(status), f"the publish ended before {point}: {proc.stderr.read().decode()}"
    proc.kill()
    assert proc.wait() == -signal.SIGKILL


def _samples(build: Path) -> list[tuple]:
    """Every sample's pair id and frame shapes, read through the adapter with checksums on."""
    ds = PairDataset(build, verify_checksums=True)
    return [(s["pair_id"], tuple(s["source"].shape), tuple(s["target"].shape))
            for s in (ds[i] for i in range(len(ds)))]


@pytest.mark.parametrize("point", ["publish:first-media", "publish:before-switch"])
def test_a_republish_killed_midway_leaves_the_old_build_whole(tmp_path, scenes, point):
    build = tmp_path / "m" / "K"
    _publish(build, scenes["old"])
    before = _samples(build)
    index = read_index(build)
    assert {shape[-1] for _, *shapes in before for shape in shapes} == {64}
    outside = snapshot(scenes["old"].parent.parent)

    _killed_at(point, build, scenes["new"])
    assert read_index(build) == index   # the old index still names the old version
    result = verify_build(build)
    assert result["ok"], result["problems"]
    assert _samples(build) == before    # every sample is the old build's, none the new one's
    left = sorted(p.name for p in build.iterdir() if is_temporary(p.name) or p.name == "v-000002")
    if point == "publish:first-media":  # the new version, half linked, under its temporary name
        assert len(left) == 1 and left[0].startswith(".v-.tmp-")
    else:                               # the new version complete, but no index names it
        assert left == ["v-000002"]

    _publish(build, scenes["new"])     # a plain re-run
    assert verify_build(build)["ok"]
    assert {shape[-1] for _, *shapes in _samples(build) for shape in shapes} == {80}
    assert not [p for p in build.iterdir() if is_temporary(p.name)]
    versions = sorted(p.name for p in build.iterdir() if p.name.startswith("v-"))
    # the version it replaced stays for its readers; one no index ever named (the killed
    # publish's, complete but never switched to) goes
    assert versions == [index.version, read_index(build).version]
    reference = tmp_path / "m" / "R"
    _publish(reference, scenes["new"])  # the same build, never interrupted
    assert read_pairs(build).equals(read_pairs(reference))
    assert changed_entries(outside, snapshot(scenes["old"].parent.parent)) == []


def test_a_killed_copy_mode_republish_keeps_serving_the_old_copies(tmp_path, scenes):
    build = tmp_path / "K"
    _publish(build, scenes["old"], "copy")
    before = _samples(build)
    _killed_at("publish:first-media", build, scenes["new"], "copy")
    assert verify_build(build)["ok"] and _samples(build) == before
    _publish(build, scenes["new"], "copy")
    assert verify_build(build)["ok"] and read_index(build).media.placed == {"copy": 4}


def test_republishing_the_same_copies_links_them_from_the_previous_version(tmp_path, scenes):
    build = tmp_path / "K"
    _publish(build, scenes["old"], "copy")
    first = version_dir(build, read_index(build)) / "media" / SCENE / "clips/front/middle/target.mp4"
    inode = first.stat().st_ino
    _publish(build, scenes["old"], "copy")
    index = read_index(build)
    second = version_dir(build, index) / "media" / SCENE / "clips/front/middle/target.mp4"
    assert index.media.placed == {"kept": 4} and second.stat().st_ino == inode
    assert first.exists() and verify_build(build)["ok"]   # the replaced version stays whole


def test_temporaries_a_killed_publish_leaves_are_the_ones_the_next_publish_removes(tmp_path, scenes):
    build = tmp_path / "K"
    _publish(build, scenes["old"])
    _killed_at("publish:first-media", build, scenes["new"])
    (left,) = [p for p in build.iterdir() if p.name.startswith(".v-")]
    assert is_temporary(left.name) and left.is_dir()
    _publish(build, scenes["old"])
    assert not left.exists() and not [p for p in build.rglob("*") if is_temporary(p.name)]


# --------------------------------------------------------------------------- whose folder

def test_a_folder_the_builder_did_not_make_is_never_published_into(tmp_path, scenes):
    parent = tmp_path / "D"
    (parent / "media" / "other").mkdir(parents=True)
    (parent / "media" / "other" / "keep.txt").write_text("keep")
    (parent / "pairs-00099.parquet").write_bytes(b"someone else's")
    outside = snapshot(parent)
    with pytest.raises(ParaDriveError, match=r"holds files the builder did not write \(media, "
                                             r"pairs-00099.parquet\).*choose another --build"):
        _publish(parent, scenes["old"])
    assert changed_entries(outside, snapshot(parent)) == []


def test_a_build_folder_carries_the_builders_marker_and_runner_files_are_kept(tmp_path, scenes):
    build = tmp_path / "K"
    build.mkdir()
    (build / "ledger.sqlite").write_bytes(b"ledger")   # the runner makes it before publishing
    _publish(build, scenes["old"])
    assert (build / ".paradrive" / "build.json").is_file()
    assert (build / "ledger.sqlite").read_bytes() == b"ledger"
    # a stray file in a folder with the marker is left alone, never deleted
    (build / "notes.txt").write_text("mine")
    _publish(build, scenes["new"])
    assert (build / "notes.txt").read_text() == "mine"


def test_publish_without_a_staging_folder_makes_its_own(tmp_path, scenes):
    rows, media, summary = scene_rows(scenes["old"])
    index = publish(tmp_path / "K", rows, media, scenes=[summary], skipped=[],
                    params=stage_params("manifest", {}), build="K")
    assert index.version == "v-000001" and verify_build(tmp_path / "K")["ok"]
    assert not [p for p in (tmp_path / "K").iterdir() if is_temporary(p.name)]
