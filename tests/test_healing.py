"""A plain re-run heals: a damaged output redoes its stage and the later ones, nothing else.

The real stages on one tiny synthetic scene (``pipeline_stages.TINY_REAL``), to a folder and to
a ``memory://`` root. Each stage's marker lists the files it wrote with their sizes; a file
deleted or truncated makes the stage out of date, and so every stage after it.
"""

from __future__ import annotations

import hashlib
import json
import uuid
from pathlib import Path

import pytest

from paradrive.inspection import verify_build
from paradrive.pipeline import StageRegistry, run_build
from paradrive.pipeline.runner import read_marker, scene_dir_for
from paradrive.storage import DataRoot

import pipeline_stages

pytestmark = pytest.mark.slow

SCENE = "synthetic:demo?seed=7"
SID = "synthetic-demo-s7"
ORDER = ["ingest", "fit", "render", "clip", "manifest"]
# One output of each stage and what is done to it (both kinds of damage over the stages).
DAMAGE = {"ingest": ("images/front/000003.jpg", "truncate"), "fit": ("gs/ckpt_000002.ply", "truncate"),
          "render": ("renders/front/target/000000.png", "delete"),
          "clip": ("clips/front/front/target.mp4", "truncate"),
          "manifest": ("pairs-00000.parquet", "delete")}


def config():
    return StageRegistry().resolve("smoke", {k: dict(v) for k, v in pipeline_stages.TINY_REAL.items()})


def build(data, manifests: Path, stages=None, **options):
    report = run_build(config(), [SCENE], data, manifests_dir=manifests, build="heal", stages=stages,
                       **options)
    return report, {r.stage: r.status for r in report.results}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    root = tmp_path_factory.mktemp("heal")
    report, states = build(root / "data", root / "manifests")
    assert set(states.values()) == {"done"}, [r.error for r in report.failures()]
    return root


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def published(build_dir: Path, rel: str) -> Path:
    """``rel`` in the version folder the build's index.json names."""
    return build_dir / json.loads((build_dir / "index.json").read_text())["version"] / rel


def expected(stage: str) -> dict[str, str]:
    i = ORDER.index(stage)
    return {s: "skipped" if k < i else "done" for k, s in enumerate(ORDER)}


@pytest.mark.parametrize("stage", ORDER)
def test_a_damaged_output_of_a_finished_scene_is_restored_by_a_plain_rerun(stage, finished,
                                                                          copy_tree):
    root = copy_tree(finished)
    rel, how = DAMAGE[stage]
    base = root / "manifests" / "heal" if stage == "manifest" else scene_dir_for(root / "data", SID)
    if stage != "manifest":
        assert rel in read_marker(base, stage).outputs  # the marker lists it
    path = published(base, rel) if stage == "manifest" else base / rel
    whole = sha(path)
    if stage == "clip":  # the clip stage hashed its videos while encoding; the marker keeps that
        assert read_marker(base, stage).outputs[rel].sha256 == whole
    if how == "delete":
        path.unlink()
    else:
        with open(path, "r+b") as f:
            f.truncate(path.stat().st_size // 2)
    report, states = build(root / "data", root / "manifests")
    assert report.exit_code == 0, [r.error for r in report.failures()]
    assert states == expected(stage)
    if stage == "manifest":  # a build republishes into a new version folder
        path = published(base, rel)
    assert sha(path) == whole  # the same bytes as before the damage
    check = verify_build(root / "manifests" / "heal")
    assert check["ok"], check["problems"]


def test_a_stage_run_alone_on_damaged_inputs_names_the_stage_a_plain_rerun_redoes(finished,
                                                                                 copy_tree):
    root = copy_tree(finished)
    scene = scene_dir_for(root / "data", SID)
    target = scene / "renders/front/target/000000.png"
    target.unlink()
    (scene / "clips/front/front/target.mp4").unlink()  # so that clip has to run
    report, states = build(root / "data", root / "manifests", stages=["clip"])
    assert states["clip"] == "failed"
    error = report.failures()[0].error
    assert "renders/front/target/000000.png is missing" in error
    assert "a plain re-run redoes render, then clip" in error
    report, states = build(root / "data", root / "manifests")
    assert states == expected("render") and target.is_file()


def test_every_stage_heals_on_a_url_root_from_one_listing(tmp_path):
    url = f"memory://heal-{uuid.uuid4().hex[:8]}/data"
    root = DataRoot.of(url, cache_dir=str(tmp_path / "cache"))
    fs, base = root.filesystem()
    manifests = tmp_path / "manifests"
    try:
        report, states = build(root, manifests)
        assert set(states.values()) == {"done"}, [r.error for r in report.failures()]
        for stage in reversed(ORDER):
            rel, how = DAMAGE[stage]
            if stage == "manifest":
                path = published(manifests / "heal", rel)
                whole = path.read_bytes()
                path.unlink()
            else:
                path = f"{base}/scenes/{SID}/{rel}"
                whole = fs.cat_file(path)
                fs.rm_file(path) if how == "delete" else fs.pipe_file(path, whole[:len(whole) // 2])
            report, states = build(root, manifests)
            assert report.exit_code == 0, [r.error for r in report.failures()]
            assert states == expected(stage), stage
            restored = (published(manifests / "heal", rel).read_bytes() if stage == "manifest"
                        else fs.cat_file(path))
            assert restored == whole, stage
            check = verify_build(manifests / "heal")
            assert check["ok"], check["problems"]
    finally:
        fs.rm(base.rsplit("/", 1)[0], recursive=True)


def flip_a_byte(path: Path) -> None:
    """Same-size damage: one byte in the middle of the file inverted."""
    with open(path, "r+b") as f:
        f.seek(path.stat().st_size // 2)
        byte = f.read(1)
        f.seek(-1, 1)
        f.write(bytes([byte[0] ^ 0xFF]))


def test_a_clip_damaged_at_the_same_size_is_redone_by_a_plain_rerun(finished, copy_tree):
    root = copy_tree(finished)
    scene = scene_dir_for(root / "data", SID)
    path = scene / "clips/front/front/target.mp4"
    whole, size = sha(path), path.stat().st_size
    flip_a_byte(path)
    assert path.stat().st_size == size
    report, states = build(root / "data", root / "manifests")
    assert report.exit_code == 0, [r.error for r in report.failures()]
    assert states == expected("clip")  # the clip hashes are read when publishing
    assert sha(path) == whole
    check = verify_build(root / "manifests" / "heal")
    assert check["ok"], check["problems"]


def test_a_forced_manifest_over_a_damaged_clip_fails_and_a_plain_rerun_heals_it(finished,
                                                                              copy_tree):
    root = copy_tree(finished)
    path = scene_dir_for(root / "data", SID) / "clips/front/front/target.mp4"
    whole = sha(path)
    flip_a_byte(path)
    report, states = build(root / "data", root / "manifests", stages=["manifest"], force=True)
    assert states["manifest"] == "failed" and "sha256" in report.failures()[0].error
    report, states = build(root / "data", root / "manifests")
    assert report.exit_code == 0, [r.error for r in report.failures()]
    assert states == expected("clip") and sha(path) == whole
    assert verify_build(root / "manifests" / "heal")["ok"]


def test_verify_outputs_reads_every_stages_hashes_and_redoes_a_same_size_damage(finished,
                                                                               copy_tree):
    root = copy_tree(finished)
    path = scene_dir_for(root / "data", SID) / "gs/ckpt_000002.ply"
    whole = sha(path)
    assert read_marker(path.parent.parent, "fit").outputs["gs/ckpt_000002.ply"].sha256 == whole
    flip_a_byte(path)
    report, states = build(root / "data", root / "manifests")
    assert states["fit"] == "skipped"  # sizes only: a plain run does not read the fit's files
    report, states = build(root / "data", root / "manifests", verify_outputs=True)
    assert report.exit_code == 0, [r.error for r in report.failures()]
    assert states == expected("fit") and sha(path) == whole
