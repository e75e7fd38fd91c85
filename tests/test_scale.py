"""The build-level work at many scenes, checked at a few: what ``bench/bench_scale.py`` makes is
what the runner would have made, and the properties that keep that work linear in the scenes
hold without timing anything: a no-op re-run reads no output (no sha256 is computed), verifying
in parallel finds what verifying alone finds, in the same order, and takes a bounded number of
files ahead, ``paradrive status`` reads the ledger in the same number of queries at any size, and
the manifest's pose columns are built from arrays exactly as from Python values."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from conftest import load_bench
from paradrive.inspection import _ordered, verify_build
from paradrive.pairs import read_index
from paradrive.pipeline import run_build
from paradrive.pipeline import runner
from paradrive.pipeline.ledger import Ledger
from paradrive.pipeline.runner import read_marker
from paradrive.uri import parse_uri

SCENES = 6


@pytest.fixture(scope="module")
def scaled(tmp_path_factory):
    """``SCENES`` copies of one built scene, as the scale bench makes them, published."""
    bench = load_bench("bench_scale")
    work = tmp_path_factory.mktemp("scale")
    setup = bench.make_scenes(work, SCENES)
    uris = [bench.scene_uri(i) for i in range(SCENES)]
    report = run_build(bench.config(), uris, work / "data", stages=["manifest"],
                       manifests_dir=work / "manifests", build=bench.BUILD)
    assert not report.failures(), [r.error for r in report.failures()]
    return {"bench": bench, "work": work, "uris": uris, "setup": setup}


def test_copies_are_scenes_of_their_own(scaled):
    work, uris = scaled["work"], scaled["uris"]
    build = work / "manifests" / scaled["bench"].BUILD
    index = read_index(build)
    assert index.totals.scenes == SCENES and index.totals.rows == 72 * SCENES
    for scene in index.scenes:
        marker = read_marker(Path(scene.scene_dir), "ingest")
        assert marker.scene_id == scene.scene_id and marker.scene_uri == scene.scene_uri
    template = work / "template" / "scenes" / "synthetic-demo-s7"  # the copies' records are their own
    assert read_marker(template, "ingest").scene_id == "synthetic-demo-s7"
    assert '"synthetic-demo-s7"' in (template / "clips" / "clips.json").read_text()
    fingerprints = {read_marker(Path(s.scene_dir), "clip").fingerprint for s in index.scenes}
    assert len(fingerprints) == SCENES  # each copy's chain starts from its own URI
    assert verify_build(build)["ok"]
    ledger = Ledger.open_existing(work / "manifests", scaled["bench"].BUILD)
    assert ledger.summary()["counts"]["done"] == len(uris)


def test_a_no_op_rerun_skips_everything_and_hashes_nothing(scaled, monkeypatch):
    bench, work = scaled["bench"], scaled["work"]
    hashed: list[Path] = []
    real = runner.sha256_file
    monkeypatch.setattr(runner, "sha256_file", lambda path: hashed.append(Path(path)) or real(path))
    report = run_build(bench.config(), scaled["uris"], work / "data",
                       manifests_dir=work / "manifests", build=bench.BUILD)
    assert {r.status for r in report.results} == {"skipped"}, [
        (r.scene_id, r.stage, r.status) for r in report.results if r.status != "skipped"]
    assert len(report.results) == 4 * SCENES + 1
    assert hashed == []


def test_a_touched_clip_is_read_again_and_damage_is_still_found(scaled, copy_tree, monkeypatch):
    bench = scaled["bench"]
    data = copy_tree(scaled["work"] / "data", "data")  # a copy: other inodes, so every clip is read
    scene = data / "scenes" / parse_uri(bench.scene_uri(0)).scene_id
    hashed: list[Path] = []
    real = runner.sha256_file
    monkeypatch.setattr(runner, "sha256_file", lambda path: hashed.append(Path(path)) or real(path))

    def run():
        hashed.clear()
        return run_build(bench.config(), [bench.scene_uri(0)], data, stages=["clip"],
                         manifests_dir=data.parent / "m", build="touched").results[0]

    assert run().status == "skipped" and len(hashed) == 37  # the clips and clips.json
    clip = sorted((scene / "clips").rglob("*.mp4"))[0]
    body = bytearray(clip.read_bytes())
    body[len(body) // 2] ^= 0xFF
    clip.write_bytes(bytes(body))  # the same size, another content and modification time
    assert run().status == "done"


def test_a_published_copy_damaged_at_the_same_size_is_healed_by_a_plain_re_run(scaled, copy_tree):
    """manifest.media: copy, so the build's videos are files of their own (no inode shared with
    the clips); one byte of one inverted in place: the next build publishes again."""
    bench = scaled["bench"]
    work = copy_tree(scaled["work"], "work")
    from paradrive.pipeline import StageRegistry

    overrides = {**bench.OVERRIDES, "manifest": {**bench.OVERRIDES.get("manifest", {}), "media": "copy"}}
    config = StageRegistry().resolve(bench.PROFILE, overrides)

    def publish():
        return run_build(config, scaled["uris"], work / "data", stages=["manifest"],
                         manifests_dir=work / "manifests", build=bench.BUILD).results[-1]

    assert publish().status == "done" and publish().status == "skipped"
    build = work / "manifests" / bench.BUILD
    video = sorted((build / read_index(build).version / "media").rglob("*.mp4"))[5]
    body = bytearray(video.read_bytes())
    body[len(body) // 2] ^= 0xFF
    video.write_bytes(bytes(body))
    assert not verify_build(build)["ok"]
    assert publish().status == "done"
    assert verify_build(build)["ok"] and read_index(build).media.placed.get("copy", 0) >= 1


def test_verify_in_parallel_finds_what_verify_alone_finds(scaled, copy_tree):
    build = copy_tree(scaled["work"] / "manifests" / scaled["bench"].BUILD, "build")
    version = build / read_index(build).version
    videos = sorted((version / "media").rglob("*.mp4"))
    videos[3].unlink()
    body = bytearray(videos[40].read_bytes())
    body[10] ^= 0x01
    videos[40].write_bytes(bytes(body))
    alone, parallel = verify_build(build, jobs=1), verify_build(build, jobs=2)
    assert alone == parallel
    assert not alone["ok"] and len(alone["problems"]) == 2
    assert alone["checked_files"] == 1 + 36 * SCENES  # the shard, each video once


def test_parallel_checks_take_a_bounded_number_of_items_ahead():
    taken: list[int] = []

    def items():
        for i in range(100):
            taken.append(i)
            yield i

    results = _ordered(lambda i: i * i, items(), jobs=2)
    assert next(results) == 0
    assert len(taken) <= 4 * 2
    assert list(results) == [i * i for i in range(1, 100)]


def _queries_of_status(tmp_path: Path, scenes: int) -> int:
    ledger = Ledger.for_build(tmp_path / f"m{scenes}", "b")
    uris = [f"synthetic:demo?seed={i}" for i in range(scenes)]
    ledger.register(uris, ["ingest", "fit"], ["manifest"])
    for uri in uris:
        ledger.start(uri, "ingest")
    statements: list[str] = []
    conn: sqlite3.Connection = ledger._connection()
    conn.set_trace_callback(statements.append)
    summary = ledger.summary()
    ledger.takeovers()
    ledger.scene_ids()
    assert summary["scenes"] == scenes and summary["counts"]["running"] == scenes
    return len(statements)


def test_status_reads_the_ledger_in_as_many_queries_at_any_size(tmp_path):
    assert _queries_of_status(tmp_path, 2) == _queries_of_status(tmp_path, 40) <= 5


def test_pose_columns_from_arrays_equal_those_from_python_values():
    from paradrive.manifest import _number_lists
    from paradrive.pairs import SCHEMA

    rng = np.random.default_rng(3)
    lengths = (8, 1, 121)
    columns = {"rel_pose": [rng.normal(size=(n, 16)).astype(np.float32) for n in lengths],
               "target_c2w": [rng.normal(size=(n, 16)) for n in lengths],
               "frame_indices": [list(range(n)) for n in lengths],
               "timestamps_us": [[10 ** 12 + k for k in range(n)] for n in lengths]}
    for name, values in columns.items():
        kind = SCHEMA.field(name).type
        python = [[list(map(float, f)) for f in v] if name in ("rel_pose", "target_c2w") else v
                  for v in values]
        assert _number_lists(values, kind).equals(pa.array(python, type=kind)), name


def test_a_build_stage_may_hold_a_lock_per_scene_beyond_a_low_open_file_limit():
    """Publishing holds every scene's lock, an open file each: 1,600 scenes pass the soft limit
    of 1,024 many systems start with, so the build stage raises it towards the hard one."""
    code = ("import resource\n"
            "soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)\n"
            "resource.setrlimit(resource.RLIMIT_NOFILE, (64, hard))\n"
            "from paradrive.pipeline.build import _allow_open_files\n"
            "_allow_open_files(1600)\n"
            "now = resource.getrlimit(resource.RLIMIT_NOFILE)[0]\n"
            "assert now == min(1856, hard) if hard != resource.RLIM_INFINITY else now == 1856, now\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
