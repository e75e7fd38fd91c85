"""Fingerprints and resume: a re-run skips what is up to date and redoes exactly what a change invalidates."""

from __future__ import annotations

import json
from collections import Counter

import pytest

import paradrive
from paradrive.pipeline import StageRegistry, run_build
from paradrive.pipeline.runner import read_marker, scene_dir_for

import pipeline_stages

SCENES = ["synthetic:alpha?seed=1", "synthetic:beta?seed=2"]
IDS = ["synthetic-alpha-s1", "synthetic-beta-s2"]
STAGES = ["ingest", "fit", "render", "clip"]


@pytest.fixture
def stage_dir(tmp_path):
    return pipeline_stages.write_stages(tmp_path / "stages")


@pytest.fixture
def build(stage_dir, tmp_path):
    """Run the stand-in pipeline over SCENES with overrides; returns {(scene_id, stage): status}."""

    def _run(overrides=None, **kwargs):
        config = StageRegistry(stage_dir).resolve(None, overrides or {})
        report = run_build(config, SCENES, tmp_path / "data", manifests_dir=tmp_path / "manifests",
                           build="fp", **kwargs)
        assert not report.failures(), [r.error for r in report.failures()]
        return {(r.scene_id, r.stage): r.status for r in report.results}

    _run.data = tmp_path / "data"
    _run.build_dir = tmp_path / "manifests" / "fp"
    return _run


def statuses(result: dict, stage: str) -> set[str]:
    return {status for (sid, st), status in result.items() if st == stage}


def test_first_build_runs_every_stage_once(build):
    result = build()
    assert set(result.values()) == {"done"}
    assert Counter(pipeline_stages.finished(build.data)) == Counter(
        [(st, sid) for sid in IDS for st in STAGES] + [("manifest", "build")])


def test_rerun_with_same_parameters_skips_everything(build):
    build()
    before = pipeline_stages.calls(build.data)
    digest = pipeline_stages.tree_digest(build.data)
    result = build()
    assert set(result.values()) == {"skipped"}
    assert pipeline_stages.calls(build.data) == before  # no stage function was even called
    assert pipeline_stages.tree_digest(build.data) == digest


def test_changing_render_offsets_rerenders_and_reclips_but_does_not_refit(build):
    build()
    n = len(pipeline_stages.finished(build.data))
    result = build({"render": {"offsets_m": [2.0, -2.0]}})
    assert statuses(result, "ingest") == statuses(result, "fit") == {"skipped"}
    assert statuses(result, "render") == statuses(result, "clip") == {"done"}
    assert result[("build:fp", "manifest")] == "done"
    redone = pipeline_stages.finished(build.data)[n:]
    assert Counter(st for st, _ in redone) == {"render": 2, "clip": 2, "manifest": 1}
    rows = [json.loads(line) for line in (build.build_dir / "pairs.jsonl").read_text().splitlines()]
    assert sorted({r["offset_m"] for r in rows}) == [-2.0, 2.0]


def test_a_build_stage_parameter_outside_the_fingerprint_changes_nothing(build, stage_dir):
    """The build stages are fingerprinted as the scene stages are (``spec.fingerprinted``): a
    parameter declared ``fingerprint: false`` (how long versions stay) republishes nothing."""
    manifest = stage_dir / "manifest.yaml"
    manifest.write_text(manifest.read_text() + '  keep_for: {default: 1d, doc: "how long old '
                        'versions stay", fingerprint: false}\n')
    build()
    published = json.loads((build.build_dir / "index.json").read_text())["config_fingerprint"]
    result = build({"manifest": {"keep_for": "2d"}})
    assert result[("build:fp", "manifest")] == "skipped"
    assert json.loads((build.build_dir / "index.json").read_text())["config_fingerprint"] == published
    assert build({"manifest": {"shard_rows": 7}})[("build:fp", "manifest")] == "done"


def test_changing_an_ingest_param_redoes_everything(build):
    build()
    result = build({"ingest": {"synthetic_frames": 6}})
    assert set(result.values()) == {"done"}
    assert len(list((scene_dir_for(build.data, IDS[0]) / "images").iterdir())) == 6


def test_changing_clip_param_redoes_clip_and_manifest_only(build):
    build()
    result = build({"clip": {"crf": 23}})
    assert {st for (_, st), s in result.items() if s == "done"} == {"clip", "manifest"}


def test_a_changed_parameter_then_reverted_is_redone_again(build):
    """The marker holds the fingerprint of the last run, not a history: reverting redoes the work."""
    build()
    first = pipeline_stages.tree_digest(build.data)
    build({"render": {"offsets_m": [3.0]}})
    result = build()
    assert statuses(result, "render") == {"done"} and statuses(result, "fit") == {"skipped"}
    after = pipeline_stages.tree_digest(build.data)
    # the reverted build writes the same files again (the 3 m renders of the detour stay)
    assert {k: v for k, v in after.items() if k in first} == first


def test_a_missing_output_redoes_its_stage_and_the_later_ones_of_that_scene_only(build):
    build()
    digest = pipeline_stages.tree_digest(build.data)
    (scene_dir_for(build.data, IDS[0]) / "gs" / "fit.json").unlink()
    result = build()
    assert {k for k, s in result.items() if s == "done"} == {
        (IDS[0], "fit"), (IDS[0], "render"), (IDS[0], "clip"), ("build:fp", "manifest")}
    assert pipeline_stages.tree_digest(build.data) == digest


def test_a_truncated_output_is_redone_though_its_name_is_there(build):
    build()
    ckpt = scene_dir_for(build.data, IDS[1]) / "gs" / "ckpt_000001.txt"
    whole = ckpt.read_bytes()
    ckpt.write_bytes(whole[:3])
    result = build()
    assert result[(IDS[1], "ingest")] == "skipped" and result[(IDS[1], "fit")] == "done"
    assert ckpt.read_bytes() == whole


def test_markers_list_the_files_their_stage_wrote_with_sizes(build):
    build()
    scene = scene_dir_for(build.data, IDS[0])
    ingest = read_marker(scene, "ingest").outputs
    assert sorted(ingest) == ["images/000000.txt", "images/000001.txt", "images/000002.txt",
                              "images/000003.txt", "scene.json"]
    assert ingest["scene.json"].bytes == (scene / "scene.json").stat().st_size
    # render declares only renders.json; the files it wrote beside it are recorded too
    assert sorted(read_marker(scene, "render").outputs) == [
        "renders/+1m.txt", "renders/-1m.txt", "renders/renders.json"]


def test_an_old_marker_without_outputs_counts_while_its_declared_outputs_exist(build):
    build()
    scene = scene_dir_for(build.data, IDS[0])
    for stage in STAGES:
        path = scene / ".paradrive" / f"{stage}.json"
        marker = json.loads(path.read_text())   # as an older version wrote it
        for key in ("outputs", "run", "upstream_runs", "schema_version"):
            marker.pop(key)
        path.write_text(json.dumps(marker))
    (build.build_dir / ".paradrive" / "manifest.json").unlink()  # builds had none either
    result = build()
    assert {k for k, s in result.items() if s == "done"} == {("build:fp", "manifest")}  # once
    (scene / "clips" / "clips.json").unlink()
    result = build()
    assert {k for k, s in result.items() if s == "done"} == {(IDS[0], "clip"), ("build:fp", "manifest")}


def test_marker_records_params_inputs_and_version(build):
    build()
    marker = read_marker(scene_dir_for(build.data, IDS[0]), "render")
    fit = read_marker(scene_dir_for(build.data, IDS[0]), "fit")
    assert marker.params == {"offsets_m": [1.0, -1.0]}
    assert marker.inputs == {"fit": fit.fingerprint}
    assert marker.version == paradrive.__version__


def test_a_new_software_version_redoes_everything(build, monkeypatch):
    build()
    monkeypatch.setattr(paradrive, "__version__", paradrive.__version__ + ".post1")
    assert set(build().values()) == {"done"}


def test_force_redoes_everything(build):
    build()
    assert set(build(force=True).values()) == {"done"}


def test_a_stage_killed_before_its_marker_is_redone(build):
    """No marker (the process died before writing it) means not done, whatever files exist."""
    build()
    pairs = (build.build_dir / "pairs.jsonl").read_bytes()
    (scene_dir_for(build.data, IDS[1]) / ".paradrive" / "clip.json").unlink()
    result = build()
    assert [k for k, s in result.items() if s == "done"] == [(IDS[1], "clip"), ("build:fp", "manifest")]
    assert (build.build_dir / "pairs.jsonl").read_bytes() == pairs


@pytest.mark.slow
def test_real_pipeline_reruns_render_and_clip_but_not_fit_when_offsets_change(tmp_path):
    """The same rules with the real stages, on one tiny synthetic scene."""
    overrides = {k: dict(v) for k, v in pipeline_stages.TINY_REAL.items()}
    registry = StageRegistry()

    def run(overrides):
        report = run_build(registry.resolve("smoke", overrides), ["synthetic:demo?seed=7"],
                           tmp_path / "data", manifests_dir=tmp_path / "manifests", build="real")
        assert not report.failures(), [r.error for r in report.failures()]
        return {r.stage: r.status for r in report.results}

    assert set(run(overrides).values()) == {"done"}
    assert set(run(overrides).values()) == {"skipped"}
    overrides["render"]["offsets_m"] = [2.0, -2.0]
    assert run(overrides) == {"ingest": "skipped", "fit": "skipped", "render": "done",
                              "clip": "done", "manifest": "done"}
    from paradrive.pairs import read_pairs
    offsets = set(read_pairs(tmp_path / "manifests" / "real").column("offset_m").to_pylist())
    assert offsets == {2.0, -2.0}
