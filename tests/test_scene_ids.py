"""Scene ids are unique and stable: ordinary inputs keep the ids they always had, a name beyond
ASCII keeps what a file name can hold and gains a hash of itself, two different logs that would
share an id each gain a hash of their identity (whatever their order), and one log given twice
is refused before any work, naming both places."""

from __future__ import annotations

import json
import os
import re

import pytest
from typer.testing import CliRunner

from conftest import stage_params
from paradrive.cli import app
from paradrive.errors import ConfigError
from paradrive.ingest.export import export_scene
from paradrive.pipeline.scenes import SceneInput, distinct_scenes, expand_scene_inputs
from paradrive.uri import parse_uri

HASH = "[0-9a-f]{8}"
ORDINARY = {
    "synthetic:demo?seed=7": "synthetic-demo-s7",
    "waymo:/logs/segment-1005081002024129653_5313_150_5333_150_with_camera_labels.tfrecord":
        "waymo-1005081002024129653_5313_150_5333_150",
    "nuscenes:/data/nuscenes?version=v1.0-mini#scene-0061": "nuscenes-scene-0061",
    "drivestudio:/data/waymo/processed/training/023": "drivestudio-023",
    "video:/logs/drive.mp4?fps=5": "video-drive",
}


def _ids(uris: list[str]) -> list[str]:
    return [parse_uri(u).scene_id for u in uris]


def test_ordinary_inputs_keep_their_ids_and_uris():
    uris = list(ORDINARY)
    assert _ids(uris) == list(ORDINARY.values())
    assert distinct_scenes([SceneInput(u, u) for u in uris]) == uris


def test_a_name_beyond_ascii_keeps_what_it_can_and_gains_a_hash_of_itself():
    tokyo, osaka = parse_uri("video:/x/東京.mp4").scene_id, parse_uri("video:/x/大阪.mp4").scene_id
    assert re.fullmatch(f"video-{HASH}", tokyo) and re.fullmatch(f"video-{HASH}", osaka)
    assert tokyo != osaka and tokyo == parse_uri("video:/elsewhere/東京.mp4").scene_id  # stable
    assert re.fullmatch(f"video-drive-{HASH}", parse_uri("video:/x/drive-東京.mp4").scene_id)
    assert re.fullmatch(f"waymo-{HASH}", parse_uri("waymo:/x/ß.tfrecord").scene_id)
    assert parse_uri("video:/x/ß.mp4").scene_id != parse_uri("video:/x/ü.mp4").scene_id


def test_two_files_of_one_name_get_ids_of_their_own_whatever_their_order(tmp_path):
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "drive.mp4").write_bytes(folder.encode())
    a, b = f"video:{tmp_path / 'a' / 'drive.mp4'}?fps=5", f"video:{tmp_path / 'b' / 'drive.mp4'}"
    forward = distinct_scenes([SceneInput(a, "--scene"), SceneInput(b, "--scene"),
                               SceneInput("synthetic:demo?seed=7", "--scene")])
    backward = distinct_scenes([SceneInput(b, "--scene"), SceneInput(a, "--scene")])
    assert forward[:2] == backward[::-1] and forward[2] == "synthetic:demo?seed=7"
    assert forward[0].startswith(f"{a}#drive-") and forward[1].startswith(f"{b}#drive-")
    ids = _ids(forward[:2])
    assert len(set(ids)) == 2 and all(re.fullmatch(f"video-drive-{HASH}", i) for i in ids)
    assert parse_uri(forward[0]).query == {"fps": "5"}          # the query stays as written
    assert distinct_scenes([SceneInput(u, u) for u in forward]) == forward   # settled: no change
    # one start and end of a video are one log, another cut of it another log
    cuts = distinct_scenes([SceneInput(f"{b}?start=0&end=5", "1"), SceneInput(f"{b}?start=5", "2")])
    assert len(set(_ids(cuts))) == 2


def test_the_same_log_given_twice_is_refused_naming_both_lines(tmp_path):
    (tmp_path / "logs").mkdir()
    video = tmp_path / "logs" / "drive.mp4"
    video.write_bytes(b"x")
    os.symlink(video, tmp_path / "logs" / "link.mp4")
    listing = tmp_path / "list.txt"
    listing.write_text(f"video:{video}\n# a comment\nvideo:{tmp_path / 'logs' / 'link.mp4'}#other\n")
    with pytest.raises(ConfigError) as err:
        expand_scene_inputs([str(listing)])
    assert str(err.value) == (f"{listing}:1 (video:{video}) and {listing}:3 (video:"
                              f"{tmp_path / 'logs' / 'link.mp4'}#other) are the same log ({video}); "
                              f"give it once")
    with pytest.raises(ConfigError, match="--scene \\(synthetic:demo\\?seed=7\\) and --scene "
                                          "\\(synthetic:demo\\?seed=7\\) are the same log"):
        distinct_scenes([SceneInput("synthetic:demo?seed=7", "--scene")] * 2)
    with pytest.raises(ConfigError, match="same log \\(scene nuscenes-scene-0061\\)"):
        distinct_scenes([SceneInput("nuscenes:/a?version=v1.0-mini#scene-0061", "1"),
                         SceneInput("nuscenes:/b?version=v1.0-trainval#scene-0061", "2")])
    segment = tmp_path / "logs" / "segment-1_with_camera_labels.tfrecord"
    segment.write_bytes(b"")
    with pytest.raises(ConfigError, match=f"--scenes {tmp_path / 'logs'} \\(waymo:{segment}\\) and "
                                          f"--scenes {segment} \\(waymo:{segment}\\) are the same log"):
        expand_scene_inputs([str(tmp_path / "logs"), str(segment)])


def test_a_build_of_one_log_twice_exits_2_before_any_work(tmp_path):
    res = CliRunner().invoke(app, ["build", "--scene", "synthetic:demo?seed=7", "--scene",
                                   "synthetic:demo?seed=7", "--profile", "smoke", "--data",
                                   str(tmp_path / "data"), "--manifests", str(tmp_path / "m")],
                             env={"COLUMNS": "300"})
    assert res.exit_code == 2, res.output
    assert res.output.strip().count("\n") == 0 and "are the same log (scene synthetic-demo-s7)" in res.output
    assert not (tmp_path / "data").exists() and not (tmp_path / "m").exists()


def test_two_logs_of_one_name_build_two_scenes_and_a_rerun_converges(tmp_path):
    params = stage_params("ingest", profile="smoke")
    uris = []
    for seed, folder in ((7, "a"), (8, "b")):
        exported = parse_uri(export_scene(f"synthetic:demo?seed={seed}&frames=6", "waymo",
                                          tmp_path / folder, params)).path
        drive = tmp_path / folder / "drive.tfrecord"
        os.replace(exported, drive)
        uris.append(f"waymo:{drive}")
    args = ["build", "--scene", uris[0], "--scene", uris[1], "--profile", "smoke", "--stages",
            "ingest", "--data", str(tmp_path / "data"), "--manifests", str(tmp_path / "m")]
    first = CliRunner().invoke(app, args, env={"COLUMNS": "300"})
    assert first.exit_code == 0, first.output
    scenes = sorted(p.name for p in (tmp_path / "data" / "scenes").iterdir())
    assert len(scenes) == 2 and all(re.fullmatch(f"waymo-drive-{HASH}", s) for s in scenes)
    sources = {json.loads((tmp_path / "data" / "scenes" / s / "scene.json").read_text())["source"]
               for s in scenes}
    assert {parse_uri(s).path for s in sources} == {parse_uri(u).path for u in uris}
    again = CliRunner().invoke(app, args, env={"COLUMNS": "300"})
    assert again.exit_code == 0 and again.output.count("skipped ingest") == 2, again.output
