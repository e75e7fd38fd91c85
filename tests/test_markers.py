"""Stage markers (``.paradrive/<stage>.json``) are typed records (:class:`StageMarker`): written
with the keys, in the order, markers always had (a version first), and markers of older
versions still load, so an upgrade redoes nothing."""

from __future__ import annotations

import json

from paradrive.contracts.records import StageMarker
from paradrive.pipeline import StageRegistry, run_build
from paradrive.pipeline.runner import read_marker, scene_dir_for

import pipeline_stages

SCENE, SID = "synthetic:alpha?seed=1", "synthetic-alpha-s1"
SCENE_KEYS = ["schema_version", "stage", "scene_id", "scene_uri", "fingerprint", "params", "inputs",
              "version", "seconds", "finished_at", "summary", "run", "upstream_runs", "outputs"]


def _build(tmp_path, **overrides):
    config = StageRegistry(pipeline_stages.write_stages(tmp_path / "stages")).resolve(None, overrides)
    report = run_build(config, [SCENE], tmp_path / "data", manifests_dir=tmp_path / "m", build="b")
    assert not report.failures(), [r.error for r in report.failures()]
    return {(r.scene_id, r.stage): r.status for r in report.results}


def test_markers_keep_their_keys_and_order_with_a_version_first(tmp_path):
    _build(tmp_path)
    scene = scene_dir_for(tmp_path / "data", SID)
    for stage in ("ingest", "fit", "render", "clip"):
        doc = json.loads((scene / ".paradrive" / f"{stage}.json").read_text())
        assert list(doc) == SCENE_KEYS and doc["schema_version"] == 1, stage
        assert doc["outputs"] and all(set(info) == {"bytes", "sha256", "mtime_ns", "inode", "ctime_ns"}
                                      for info in doc["outputs"].values())
    build = json.loads((tmp_path / "m" / "b" / ".paradrive" / "manifest.json").read_text())
    assert list(build) == ["schema_version", "stage", "build", "fingerprint", "scene_runs", "outputs"]
    assert StageMarker.read(tmp_path / "m" / "b" / ".paradrive" / "build.json") is None   # not a stage's


def test_a_marker_an_older_version_wrote_loads_and_nothing_is_redone(tmp_path):
    _build(tmp_path)
    scene = scene_dir_for(tmp_path / "data", SID)
    for stage in ("ingest", "fit", "render", "clip"):
        path = scene / ".paradrive" / f"{stage}.json"
        doc = json.loads(path.read_text())
        del doc["schema_version"]
        doc["retired_key"] = {"an older version": "wrote this"}
        for info in doc["outputs"].values():   # written before outputs' stats were recorded
            del info["mtime_ns"], info["inode"], info["ctime_ns"]
        path.write_text(json.dumps(doc, indent=2))
    marker = read_marker(scene, "render")
    assert marker is not None and marker.schema_version == 1 and marker.outputs
    assert all(info.mtime_ns is None for info in marker.outputs.values())
    assert set(_build(tmp_path).values()) == {"skipped"}
    resaved = json.loads(marker.model_dump_json())
    assert "retired_key" not in resaved and list(resaved) == SCENE_KEYS


def test_a_marker_of_another_schema_or_unreadable_is_not_done(tmp_path):
    _build(tmp_path)
    scene = scene_dir_for(tmp_path / "data", SID)
    path = scene / ".paradrive" / "clip.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "schema_version": 2}))
    assert read_marker(scene, "clip") is None
    (scene / ".paradrive" / "render.json").write_text("{ not json")
    assert read_marker(scene, "render") is None
    result = _build(tmp_path)
    assert result[(SID, "render")] == result[(SID, "clip")] == "done"
    assert result[(SID, "fit")] == "skipped"
