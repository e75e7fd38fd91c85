"""Readers are never cut off by a republish: a publish keeps the version it replaces and every
version replaced less than ``manifest.keep_versions_for`` ago, a reader reads the version it
opened to the end, and a trainer picks up a new version at the next epoch only.

The reader is a real process iterating the adapter; the test republishes the build for real
(another scene content and other shard settings each time) while the reader is half-way
through a pass, and the reader reports what it read on its stdout."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from conftest import stage_params
from paradrive.cli import app
from paradrive.contracts.layout import BuildLayout
from paradrive.data import PairDataset, PairIterableDataset
from paradrive.inspection import verify_build
from paradrive.manifest import kept_versions
from paradrive.pairs import current_version, read_index
from paradrive.stages.manifest import build_manifest
from test_manifest import scenes_entry, write_clip_scene

TESTS = Path(__file__).parent
ROOT = TESTS.parent
SCENE = "synthetic-a"
DAY = 86400.0
# a trainer's loop in a process of its own: argv = build folder, passes. Each pass it says how
# far it got; half-way through it says HALF and waits for a line on stdin (the test publishes
# meanwhile). A reader opened once and never refreshed reads every pass too.
READER = """
import json, sys
from paradrive.data import PairDataset, PairIterableDataset

build, passes = sys.argv[1], int(sys.argv[2])
ds = PairIterableDataset(build, shuffle=True, seed=3, dtype="uint8", num_frames=2)
once = PairDataset(build, dtype="uint8", num_frames=2)
for epoch in range(passes):
    ds.set_epoch(epoch, refresh=True)
    seen, errors, widths, half = 0, [], set(), len(ds) // 2
    try:
        for sample in ds:
            seen += 1
            widths.add(sample["source"].shape[-1])
            if seen == half:
                print(json.dumps({"half": epoch, "version": ds.version}), flush=True)
                sys.stdin.readline()
    except Exception as exc:
        errors.append(f"{type(exc).__name__}: {exc}")
    once_errors = 0
    for i in range(len(once)):
        try:
            once[i]
        except Exception:
            once_errors += 1
    print(json.dumps({"pass": epoch, "version": ds.version, "samples": seen, "of": len(ds),
                      "errors": errors, "widths": sorted(widths), "once": once.version,
                      "once_errors": once_errors}), flush=True)
"""


@pytest.fixture(scope="module")
def contents(tmp_path_factory):
    """One scene, 8 pairs, in two contents told apart by their frame width."""
    root = tmp_path_factory.mktemp("republish")
    return {width: write_clip_scene(root / f"data{width}", SCENE, clips=("middle",),
                                    offsets=(1.0, -1.0, 2.0, -2.0), conditions=(100, 500),
                                    width=width)
            for width in (64, 80)}


def _publish(build: Path, scene: Path, **params) -> None:
    build_manifest(build, [scenes_entry(scene)], stage_params("manifest", params))


def test_a_reader_process_reads_every_pass_whole_while_the_build_is_republished(tmp_path, contents):
    build = tmp_path / "m" / "K"
    _publish(build, contents[64], shard_rows=3)
    reader = subprocess.Popen([sys.executable, "-c", READER, str(build), "5"], cwd=ROOT,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    # each republish changes the content and how it is sharded, half-way through a pass
    republishes = [(contents[80], {"shard_rows": 5}), (contents[64], {"shard_rows": 2,
                   "compression": "snappy"}), (contents[80], {"row_group_rows": 1})]
    passes = []
    try:
        for line in reader.stdout:
            doc = json.loads(line)
            if "pass" in doc:
                passes.append(doc)
                continue
            if republishes:
                scene, params = republishes.pop(0)
                _publish(build, scene, **params)
            reader.stdin.write("go\n")
            reader.stdin.flush()
        assert reader.wait(timeout=120) == 0, reader.stderr.read()
    finally:
        reader.kill()
        reader.wait()
    assert [p["errors"] for p in passes] == [[]] * 5
    assert [p["once_errors"] for p in passes] == [0] * 5
    assert all(p["samples"] == p["of"] == 8 for p in passes)   # every pass complete
    # a new version is picked up at the next epoch, never within one
    assert [p["version"] for p in passes] == ["v-000001", "v-000002", "v-000003", "v-000004",
                                              "v-000004"]
    assert [p["widths"] for p in passes] == [[64], [80], [64], [80], [80]]   # no pass mixes two
    assert {p["once"] for p in passes} == {"v-000001"}   # opened once: its version to the end
    assert BuildLayout(build).versions() == ["v-000001", "v-000002", "v-000003", "v-000004"]


def test_a_publish_keeps_the_replaced_version_and_those_replaced_within_the_keep_time(tmp_path, contents):
    build = tmp_path / "K"
    layout = BuildLayout(build)
    for k in range(3):
        _publish(build, contents[64], shard_rows=2 + k)
    assert layout.versions() == ["v-000001", "v-000002", "v-000003"]   # all replaced just now
    # v-000001 was replaced two days ago (when v-000002 was published); v-000002 is the previous
    two_days_ago = layout.version_index("v-000002").stat().st_mtime - 2 * DAY
    os.utime(layout.version_index("v-000002"), (two_days_ago, two_days_ago))
    _publish(build, contents[80], shard_rows=9)
    assert layout.versions() == ["v-000002", "v-000003", "v-000004"]
    # by count: with nothing kept for any time, the version a publish replaces still stays
    _publish(build, contents[64], shard_rows=4, keep_versions_for="0s")
    assert layout.versions() == ["v-000004", "v-000005"]
    _publish(build, contents[80], shard_rows=4, keep_versions_for="0s")
    assert layout.versions() == ["v-000005", "v-000006"]
    assert verify_build(build)["ok"]


def test_the_rule_in_one_function(tmp_path, contents):
    build = tmp_path / "K"
    layout = BuildLayout(build)
    for _ in range(4):
        _publish(build, contents[64])
    now = layout.version_index("v-000004").stat().st_mtime
    rule = lambda keep, current="v-000004", previous="v-000003": kept_versions(   # noqa: E731
        layout, keep, current=current, previous=previous, now=now)
    assert rule(DAY) == ["v-000001", "v-000002", "v-000003", "v-000004"]
    assert rule(0.0) == ["v-000003", "v-000004"]
    # an index that names v-000002 while v-000003 and v-000004 were never switched to (killed
    # publishes): no reader can hold those two
    assert rule(0.0, current="v-000002", previous="v-000001") == ["v-000001", "v-000002"]
    assert rule(DAY, current="v-000004", previous=None) == layout.versions()   # an unreadable index
    # no index before: the other folders are a killed first publish's, never read
    assert kept_versions(layout, DAY, current="v-000004", previous=None, first=True) == ["v-000004"]


def test_a_reader_opened_on_a_version_whose_time_ran_out_is_told_to_reopen(tmp_path, contents):
    build = tmp_path / "K"
    _publish(build, contents[64])
    ds = PairIterableDataset(build, shuffle=False, dtype="uint8", num_frames=2)
    state = ds.state_dict(samples_consumed=3)
    assert state["version"] == "v-000001"
    for _ in range(2):
        _publish(build, contents[80], keep_versions_for="0s")
    assert current_version(build) == "v-000003"
    with pytest.raises(ValueError, match=r"cannot resume epoch 0 mid-way: build .*: version v-000001 "
                                         r"is no longer kept .* open the build's current version "
                                         r"\(v-000003\) at the next epoch"):
        PairIterableDataset(build, dtype="uint8", num_frames=2).load_state_dict(state)


def test_a_resumed_epoch_reads_the_version_it_was_saved_with_and_the_next_epoch_the_new_one(
        tmp_path, contents):
    build = tmp_path / "K"
    _publish(build, contents[64])
    ds = PairIterableDataset(build, seed=5, dtype="uint8", num_frames=2)
    ds.set_epoch(0, refresh=True)
    whole = [s["pair_id"] for s in ds]
    state = ds.state_dict(samples_consumed=3)
    _publish(build, contents[80], shard_rows=3)   # published while the trainer was down

    resumed = PairIterableDataset(build, seed=5, dtype="uint8", num_frames=2)
    assert resumed.version == "v-000002"
    resumed.load_state_dict(state)
    assert resumed.set_epoch(0, refresh=True) is False   # a pending resume point keeps its version
    rest = list(resumed)
    assert resumed.version == "v-000001" and [s["pair_id"] for s in rest] == whole[3:]
    assert {s["source"].shape[-1] for s in rest} == {64}
    assert resumed.set_epoch(1, refresh=True) is True
    assert resumed.version == "v-000002" and {s["source"].shape[-1] for s in resumed} == {80}
    assert resumed.state_dict()["version"] == "v-000002"


def test_a_dataset_opens_a_kept_version_by_name(tmp_path, contents):
    build = tmp_path / "K"
    _publish(build, contents[64])
    _publish(build, contents[80])
    old = PairDataset(build, version="v-000001", dtype="uint8")
    assert old.version == "v-000001" and old[0]["source"].shape[-1] == 64
    assert PairDataset(build, dtype="uint8")[0]["source"].shape[-1] == 80
    assert read_index(build, "v-000001").version == "v-000001"


def test_inspect_verify_checks_the_current_version_of_a_build_with_kept_versions(tmp_path, contents):
    build = tmp_path / "K"
    for width in (64, 80, 64):
        _publish(build, contents[width])
    assert BuildLayout(build).versions() == ["v-000001", "v-000002", "v-000003"]
    res = CliRunner().invoke(app, ["inspect", str(build), "--verify", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output[res.output.index("{"):])
    # one shard and the version's 7 videos (target, 2 conditions, 4 sources), none of the others
    assert doc["verify"]["ok"] and doc["verify"]["checked_files"] == 1 + 7


def test_a_bad_keep_time_is_refused_before_any_work_in_one_line(tmp_path):
    res = CliRunner().invoke(app, ["build", "--scene", "synthetic:demo?seed=7", "--profile", "smoke",
                                   "--data", str(tmp_path / "data"), "--manifests", str(tmp_path / "m"),
                                   "--set", "manifest.keep_versions_for=soon"], env={"COLUMNS": "300"})
    assert res.exit_code == 2, res.output
    line = res.output.strip()
    assert "\n" not in line
    assert ("--set: manifest.keep_versions_for = 'soon' is not allowed (allowed: matching "
            "[0-9]+([.][0-9]+)?[smhdw]); change it to an allowed value") in line
    assert not (tmp_path / "data").exists()


def test_a_keep_time_is_a_number_and_one_unit():
    from paradrive.contracts.params import duration_seconds

    assert [duration_seconds(t) for t in ("0s", "90s", "1.5h", "1d", "2w")] == [0, 90, 5400, DAY,
                                                                              14 * DAY]
    for bad in ("1", "1 day", "-1d", "1d2h", ""):
        with pytest.raises(ValueError, match="is not a duration: write a number and one unit"):
            duration_seconds(bad)
    assert stage_params("manifest", {"keep_versions_for": "12h"}).keep_versions_seconds == DAY / 2
