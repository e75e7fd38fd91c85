"""Retention: outputs a stage's switches let go once the stages needing them have used them,
without breaking the skip logic (a re-run does nothing) and healing honestly (a later need of
them makes them again)."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import pytest

from paradrive.pipeline import StageRegistry, run_build
from paradrive.pipeline.budget import scene_footprint
from paradrive.pipeline.runner import read_marker
from paradrive.storage import DataRoot, file_stats

SCENE = "synthetic:demo?seed=7"
SCENE_ID = "synthetic-demo-s7"
STAGES = ["ingest", "fit", "render", "clip"]
LET_GO = {"render": {"keep_frames": False}, "ingest": {"keep_lidar": False}}


def build(data: Path, overrides: dict | None = None, stages=STAGES, profile="smoke"):
    config = StageRegistry().resolve(profile, overrides or {})
    return run_build(config, [SCENE], data, stages=stages, manifests_dir=data.parent / "manifests")


def statuses(report) -> dict[str, str]:
    return {r.stage: r.status for r in report.results}


def frames(scene_dir: Path) -> list[Path]:
    return list((scene_dir / "renders").rglob("*.png"))


@pytest.fixture(scope="module")
def built(smoke_scene, tmp_path_factory):
    """The smoke scene (seed 7) through clip with every file kept."""
    import shutil

    root = tmp_path_factory.mktemp("retention")
    shutil.copytree(smoke_scene["data_dir"], root / "data", symlinks=True)
    report = build(root / "data")
    assert not report.failures(), [r.error for r in report.failures()]
    return root / "data"


@pytest.fixture
def let_go(built, copy_tree):
    """A copy of the built scene, re-run once with the retention switches off."""
    data = copy_tree(built, "data")
    before = scene_footprint(data, SCENE_ID)
    report = build(data, LET_GO)
    return data, before, report


def test_switching_retention_on_lets_go_without_running_any_stage(let_go):
    data, before, report = let_go
    scene_dir = data / "scenes" / SCENE_ID
    assert statuses(report) == {s: "skipped" for s in STAGES}
    after = scene_footprint(data, SCENE_ID)
    assert before["renders"] > 10 * after["renders"] and after["lidar"] == 0 < before["lidar"]
    assert sum(after.values()) < sum(before.values())
    assert after["clips"] == before["clips"] and after["gs"] == before["gs"]
    assert not frames(scene_dir) and (scene_dir / "renders" / "renders.json").is_file()
    marker = read_marker(scene_dir, "render")
    assert marker.dropped.after == {"clip": read_marker(scene_dir, "clip").run}
    assert all(rel.startswith("renders/front/") for rel in marker.dropped.files)
    assert "renders/renders.json" in marker.outputs
    assert read_marker(scene_dir, "ingest").dropped.after == {"fit": read_marker(scene_dir, "fit").run}


def test_rerun_with_retention_on_runs_nothing_and_touches_no_file(let_go):
    data, _, _ = let_go
    scene_dir = data / "scenes" / SCENE_ID
    stats = file_stats(scene_dir)   # markers included: (size, mtime_ns) of every file
    report = build(data, LET_GO)
    assert statuses(report) == {s: "skipped" for s in STAGES}
    assert file_stats(scene_dir) == stats


def test_fresh_build_with_retention_lets_go_after_clip(built, copy_tree):
    data = copy_tree(built, "data")
    scene_dir = data / "scenes" / SCENE_ID
    (scene_dir / ".paradrive" / "render.json").unlink()   # render and clip run again
    report = build(data, LET_GO)
    assert statuses(report) == {"ingest": "skipped", "fit": "skipped", "render": "done", "clip": "done"}
    assert not frames(scene_dir)
    assert read_marker(scene_dir, "render").dropped.files


def test_changed_clip_parameter_renders_the_frames_again(let_go):
    data, _, _ = let_go
    scene_dir = data / "scenes" / SCENE_ID
    first = read_marker(scene_dir, "render")
    report = build(data, {**LET_GO, "clip": {"crf": 23}})
    assert statuses(report) == {"ingest": "skipped", "fit": "skipped", "render": "done", "clip": "done"}
    again = read_marker(scene_dir, "render")
    assert again.run != first.run and again.fingerprint == first.fingerprint
    # the same frames, rendered again, then let go once the new clips were encoded
    assert again.dropped.files == first.dropped.files
    assert again.dropped.after == {"clip": read_marker(scene_dir, "clip").run}
    assert not frames(scene_dir)
    clips = json.loads((scene_dir / "clips" / "clips.json").read_text())
    assert all((scene_dir / s["file"]).is_file() for c in clips["clips"] for s in c["streams"].values())
    assert statuses(build(data, {**LET_GO, "clip": {"crf": 23}})) == {s: "skipped" for s in STAGES}


def test_stage_asked_alone_on_let_go_outputs_fails_naming_the_stage_to_add(let_go):
    data, _, _ = let_go
    report = build(data, {**LET_GO, "clip": {"crf": 23}}, stages=["clip"])
    (failure,) = report.failures()
    assert failure.stage == "clip"
    assert "retention" in failure.error and "'render' in --stages" in failure.error


def test_keeping_again_keeps_what_is_rendered_from_then_on(let_go):
    data, _, _ = let_go
    scene_dir = data / "scenes" / SCENE_ID
    report = build(data)   # retention back on its defaults (keep everything)
    assert statuses(report) == {s: "skipped" for s in STAGES}
    report = build(data, {"clip": {"crf": 23}})
    assert statuses(report)["render"] == "done" and frames(scene_dir)
    assert read_marker(scene_dir, "render").dropped is None


# --------------------------------------------------------------------------- the stand-in stages

def stand_in_stages(folder: Path, stage: str, switch: str, glob: str) -> Path:
    """The stand-in stages (milliseconds each), ``stage`` with a retention switch set off."""
    import pipeline_stages

    pipeline_stages.write_stages(folder)
    spec = folder / f"{stage}.yaml"
    spec.write_text(spec.read_text().replace("params:\n", f"retention:\n  {switch}: [\"{glob}\"]\n"
                                             f"params:\n  {switch}: {{default: false, doc: \"x\"}}\n"))
    return folder


def test_changed_fit_parameter_ingests_again_when_ingest_let_go(tmp_path):
    import pipeline_stages

    folder = stand_in_stages(tmp_path / "stages", "ingest", "keep_images", "images/*")
    data = tmp_path / "data"

    def run(overrides=None):
        config = StageRegistry(folder).resolve(None, overrides or {})
        report = run_build(config, [SCENE], data, stages=STAGES, manifests_dir=tmp_path / "m")
        return statuses(report)

    assert run() == {s: "done" for s in STAGES}
    assert not list((data / "scenes" / SCENE_ID / "images").glob("*"))
    assert run() == {s: "skipped" for s in STAGES}
    assert run({"fit": {"checkpoints": [1, 2, 3]}}) == {s: "done" for s in STAGES}
    ran = [stage for stage, _ in pipeline_stages.finished(data)]
    assert ran == ["ingest", "fit", "render", "clip"] * 2


def test_url_root_lets_go_the_remote_files(tmp_path):
    """On a URL data root the files go from the remote folder, and a re-run still skips."""
    folder = stand_in_stages(tmp_path / "stages", "render", "keep_renders", "renders/*m.txt")
    url = f"memory://retention-{uuid.uuid4().hex[:8]}/data"
    root = DataRoot.of(url, cache_dir=str(tmp_path / "cache"))
    fs, base = root.filesystem()
    config = StageRegistry(folder).resolve(None)
    report = run_build(config, [SCENE], root, stages=STAGES, manifests_dir=tmp_path / "m")
    assert statuses(report) == {s: "done" for s in STAGES}
    remote = [p for p in fs.find(f"{base}/scenes/{SCENE_ID}") if "/renders/" in p]
    assert [Path(p).name for p in remote] == ["renders.json"]
    assert json.loads(fs.cat_file(f"{base}/scenes/{SCENE_ID}/.paradrive/render.json"))["dropped"]["files"]
    report = run_build(config, [SCENE], root, stages=STAGES, manifests_dir=tmp_path / "m")
    assert statuses(report) == {s: "skipped" for s in STAGES}
