"""``paradrive eval --build --videos --metrics``: the paper's table per offset and dataset, the
CSV of one line per video, the JSON document, the per-video cache, and the refusals that come
before any video is read. The inference set is the smoke scenes' (``test_inference_sets``)."""

from __future__ import annotations

import csv
import json
import os

import numpy as np
import pytest
from typer.testing import CliRunner

from test_inference_sets import inference_build, videos_folder  # noqa: F401  (the fixture)

from paradrive.cli import app
from paradrive.pairs import read_index, read_pairs
from paradrive.scoring import features as F
from paradrive.scoring.run import FeatureCache, VideoScore, aggregate
from paradrive.scoring.table import csv_text, paper_table

SCENE = "synthetic-demo-s7"


def _eval(build, videos, *args, code=0):
    """The command's output (stdout and stderr); with ``--json`` its document, from stdout."""
    result = CliRunner().invoke(app, ["eval", "--build", str(build), "--videos", str(videos),
                                      *args], env={"COLUMNS": "200"})
    assert result.exit_code == code, result.output
    return json.loads(result.stdout) if "--json" in args else result.output


def _rows(build, scene=SCENE):
    return [r for r in read_pairs(build).to_pylist() if r["scene_id"] == scene]


@pytest.fixture(scope="module")
def recorded_scored(inference_build, tmp_path_factory):  # noqa: F811
    """One scene's recorded videos standing in for generated ones (a model that ignores the
    requested camera), scored with every frame located (``--camera-stride 1``)."""
    folder = tmp_path_factory.mktemp("recorded")
    videos = videos_folder(inference_build["dir"], _rows(inference_build["dir"]), "source",
                           folder / "videos")
    output = _eval(inference_build["dir"], videos, "--metrics", "tce,camera",
                   "--camera-stride", "1", "--out", str(folder / "out"), code=3)
    return {"videos": videos, "out": folder / "out", "output": output,
            "doc": json.loads((folder / "out" / "scores.json").read_text())}


def test_the_recorded_video_s_metric_terr_is_its_offset_and_the_table_shows_it(recorded_scored):
    table = recorded_scored["doc"]["table"]["synthetic"]
    assert list(table) == ["±1", "±2", "±3", "±4", "mean"]
    for d in (1, 2, 3, 4):
        assert table[f"±{d}"]["videos"] == 6                    # 3 clips x 2 signs
        assert table[f"±{d}"]["terr_m"] == pytest.approx(d, abs=0.05)
        assert table[f"±{d}"]["located_videos"] == 6
    assert table["mean"]["terr_m"] == pytest.approx(2.5, abs=0.05)
    # the paper's relative form sees the same motion at every offset
    assert np.ptp([table[f"±{d}"]["terr"] for d in (1, 2, 3, 4)]) < 1e-6
    out = recorded_scored["output"]
    assert "synthetic:" in out and "±4 m" in out and "TErr m" in out and "TCE" in out
    assert "24 row(s) have no video" in out                       # the other scene: exit 3


def test_the_csv_has_one_line_per_video_traceable_to_its_file(recorded_scored):
    with open(recorded_scored["out"] / "scores.csv") as f:
        lines = list(csv.DictReader(f))
    assert len(lines) == 24
    for line in lines:
        assert os.path.isfile(line["video"]) and line["video"].startswith(str(recorded_scored["videos"]))
        assert int(line["located"]) == int(line["sampled"]) == 9
        assert float(line["terr_m"]) == pytest.approx(abs(float(line["offset_m"])), abs=0.05)
        assert float(line["tce"]) >= 0 and line["error"] == ""


def test_a_rerun_reads_the_cache_and_an_added_metric_computes_only_itself(recorded_scored,
                                                                         inference_build):  # noqa: F811
    build, videos, out = inference_build["dir"], recorded_scored["videos"], recorded_scored["out"]
    args = ("--camera-stride", "1", "--out", str(out), "--json")
    again = _eval(build, videos, "--metrics", "tce,camera", *args, code=3)
    assert again["cache"]["misses"] == 0 and again["cache"]["hits"] == 24 * 2
    assert again["table"] == recorded_scored["doc"]["table"]
    added = _eval(build, videos, "--metrics", "tce,camera,psnr", *args, code=3)
    assert added["cache"]["misses"] == 24 and added["seconds"]["psnr"]["videos"] == 24
    assert added["seconds"]["tce"]["videos"] == added["seconds"]["camera"]["videos"] == 0


def test_true_views_at_the_smoke_size_are_scored_perfect_and_unlocated_frames_get_no_number(
        inference_build, tmp_path):  # noqa: F811
    videos = videos_folder(inference_build["dir"], _rows(inference_build["dir"]), "target",
                           tmp_path / "videos")
    doc = _eval(inference_build["dir"], videos, "--camera-stride", "1", "--json", code=3)
    assert all(r["psnr"] >= 99.0 for r in doc["rows"])
    for r in doc["rows"]:
        # 160x96 frames 3-4 m aside share few features with the source: some are not located
        assert (r["terr_m"] is None) == (r["located"] == 0)
        if r["located"]:
            assert r["terr_m"] < abs(r["offset_m"]), r


def test_a_video_of_another_frame_count_is_that_row_s_error(inference_build, tmp_path):  # noqa: F811
    from paradrive.video import decode_frames, encode_video

    rows = _rows(inference_build["dir"])[:2]
    videos = videos_folder(inference_build["dir"], rows, "source", tmp_path / "videos")
    first = videos / f"{rows[0]['pair_id']}.mp4"
    short = decode_frames(first)[:4]
    os.unlink(first)
    encode_video(first, short, 10.0)
    out = _eval(inference_build["dir"], videos, "--metrics", "tce", "--out", str(tmp_path / "o"),
                code=3)
    assert "could not be scored" in out and "4 frames, the row's clip has 9" in out
    doc = json.loads((tmp_path / "o" / "scores.json").read_text())
    assert [r["pair_id"] for r in doc["failed"]] == [rows[0]["pair_id"]]
    assert doc["table"]["synthetic"]["mean"]["videos"] == 1


@pytest.mark.parametrize("args, says", [
    (("--metrics", "fid"), "--fid-weights"),
    (("--metrics", "tce,bogus"), "unknown metric 'bogus'"),
    (("--fvd-weights", "nowhere.pt"), "nowhere.pt: no such file"),
    (("--flow-weights", "raft.pth"), "--flow-weights raft.pth: no such file"),
])
def test_a_bad_metric_or_weights_is_refused_before_any_video_is_read(inference_build, tmp_path,  # noqa: F811
                                                                    args, says):
    videos = videos_folder(inference_build["dir"], _rows(inference_build["dir"])[:1], "source",
                           tmp_path / "videos")
    out = _eval(inference_build["dir"], videos, *args, code=2)
    assert says in " ".join(out.split())
    assert not (videos / "scores-cache").exists() and not (videos / "scores.json").exists()


@pytest.mark.slow
def test_feature_metrics_run_from_local_weight_files(inference_build, tmp_path):  # noqa: F811
    from scoring_nets import write_all

    weights = write_all(tmp_path / "weights")
    rows = [r for r in _rows(inference_build["dir"]) if r["clip"] == "front"
            and abs(r["offset_m"]) == 1]
    videos = videos_folder(inference_build["dir"], rows, "condition", tmp_path / "videos")
    args = ("--fid-weights", str(weights["fid"]), "--clip-weights", str(weights["clip_v"]),
            "--iq-weights", str(weights["iq"]), "--device", "cpu", "--json")
    doc = _eval(inference_build["dir"], videos, "--metrics", "fid,clip_v,iq", *args, code=3)
    group = doc["table"]["synthetic"]["±1"]
    assert group["videos"] == 2 and group["fid"] > 0
    assert -1.0 <= group["clip_v"] <= 1.0 and np.isfinite(group["iq"])   # random networks
    assert {m: doc["seconds"][m]["videos"] for m in ("fid", "clip_v", "iq")} == dict.fromkeys(
        ("fid", "clip_v", "iq"), 2)
    # the group's FID is that of the cached features: the two conditions against their source
    from paradrive.io import sha256_file

    cache = FeatureCache(videos / "scores-cache")
    by = F.weights_sha256(F.check_weights("fid", weights["fid"]))
    cached = lambda sha: cache.read(cache.key(video=sha, metric="fid", weights=by))["features"]  # noqa: E731
    gen = [cached(sha256_file(videos / f"{r['pair_id']}.mp4")) for r in rows]
    assert gen[0].shape == (9, 2048) and {r["source_sha256"] for r in rows} == {rows[0]["source_sha256"]}
    assert group["fid"] == pytest.approx(F.fid([cached(rows[0]["source_sha256"])], gen))
    again = _eval(inference_build["dir"], videos, "--metrics", "fid", *args, code=3)
    assert again["cache"]["misses"] == 0 and again["table"]["synthetic"]["±1"]["fid"] == group["fid"]
    # FVD's I3D takes 16 frames or more: the smoke clips' 9 give no FVD, named per video, and the
    # rows' other metrics are still measured
    short = _eval(inference_build["dir"], videos, "--metrics", "fvd,iq", "--fvd-weights", str(weights["fvd"]),
                  "--iq-weights", str(weights["iq"]), "--device", "cpu", "--json", code=3)
    assert not short["failed"] and len(short["skipped"]) == 2
    assert all(s["metric"] == "fvd" and "16 frames" in s["reason"] for s in short["skipped"])
    group = short["table"]["synthetic"]["±1"]
    assert group.get("fvd") is None and np.isfinite(group["iq"]) and group["videos"] == 2


def test_a_group_s_fid_pools_its_videos_frames_against_its_distinct_sources(tmp_path):
    cache = FeatureCache(tmp_path / "cache")
    rng = np.random.default_rng(0)
    src = {s: rng.normal(size=(5, 8)) for s in ("a", "b")}
    gen = {p: rng.normal(loc=0.5, size=(5, 8)) for p in ("p1", "p2", "p3")}
    scores = []
    for pair, source, offset in (("p1", "a", 1.0), ("p2", "a", -1.0), ("p3", "b", 1.0)):
        keys = (cache.key(video=pair), cache.key(video=source))
        cache.get(keys[0], lambda p=pair: {"features": gen[p]})
        cache.get(keys[1], lambda s=source: {"features": src[s]})
        scores.append(VideoScore(pair_id=pair, dataset="waymo", scene_id="s", camera="front",
                                 clip="front", offset_m=offset, video=f"{pair}.mp4",
                                 values={"tce": offset + 2}, features={"fid": keys}))
    doc = aggregate(scores, ("tce", "fid"), cache)
    group = doc["table"]["waymo"]["±1"]
    assert group["fid"] == pytest.approx(F.fid([src["a"], src["b"]], list(gen.values())))
    assert group["tce"] == pytest.approx((3 + 1 + 3) / 3)
    assert [r["offset_m"] for r in doc["by_offset"]] == [-1.0, 1.0]
    assert doc["by_offset"][0]["fid"] is None                    # one video: no distribution


def test_the_paper_layout_keeps_datasets_apart_and_prints_clip_v_as_a_percentage():
    group = {"videos": 2, "clip_v": 0.9512, "tce": 3.381, "fid": None, "located": 12.0,
             "sampled": 13.0}
    doc = {"table": {"waymo": {"±1": group, "mean": group}, "nuscenes": {"±1": group, "mean": group}},
           "rows": [{"pair_id": "waymo/x", "tce": 3.381, "error": None}]}
    blocks = paper_table(doc)
    assert [b.title for b in blocks] == ["WOD", "nuScenes"]
    assert blocks[0].headings == ["offset", "videos", "TCE", "CLIP-V", "located"]
    assert blocks[0].lines[0] == ["±1 m", "2", "3.38", "95.12", "12.0/13"]
    assert csv_text(doc).splitlines() == ["pair_id,tce,error", "waymo/x,3.381,"]


def test_the_document_names_its_build_and_the_settings_it_was_scored_with(recorded_scored, inference_build):  # noqa: F811
    doc = recorded_scored["doc"]
    assert doc["build"] == str(inference_build["dir"]) and read_index(inference_build["dir"]).kind == "inference"
    assert doc["settings"]["camera"]["stride"] == 1 and doc["metrics"] == ["tce", "camera"]


def test_a_damaged_cache_entry_is_computed_again(tmp_path):
    cache = FeatureCache(tmp_path / "cache")
    key = cache.key(video="abc", metric="tce", settings={"crop_px": 30})
    assert key != cache.key(video="abc", metric="tce", settings={"crop_px": 20})
    cache.get(key, lambda: {"pairs": np.arange(3.0)})
    cache.path(key).write_bytes(b"not an npz")
    again = cache.get(key, lambda: {"pairs": np.arange(4.0)})
    assert again["pairs"].tolist() == [0.0, 1.0, 2.0, 3.0] and cache.misses == 2
    assert cache.get(key, lambda: {"pairs": np.zeros(1)})["pairs"].tolist() == [0.0, 1.0, 2.0, 3.0]
    assert cache.hits == 1 and not list(cache.folder.rglob("*.tmp*"))


def test_a_training_build_is_refused_as_no_inference_set(inference_build, tmp_path):  # noqa: F811
    videos = tmp_path / "videos"
    videos.mkdir()
    out = _eval(inference_build["training"], videos, code=2)
    assert "a training build; scoring needs an inference set" in " ".join(out.split())
    assert "--kind inference" in out and not (videos / "scores-cache").exists()
