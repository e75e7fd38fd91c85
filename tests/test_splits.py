"""Splits: the paper's evaluation scenes never reach a training build; --split builds exactly a split."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from paradrive import splits
from paradrive.cli import app
from paradrive.errors import ConfigError
from paradrive.pipeline.scenes import nuscenes_scene_uris, scenes_in_folder

PAPER_SEGMENT = "segment-10444454289801298640_4360_000_4380_000_with_camera_labels.tfrecord"


def nuscenes_root(tmp_path: Path, names: list[str]) -> Path:
    """A dataroot whose scene table lists ``names`` in order (all that split matching reads)."""
    root = tmp_path / "nuscenes"
    (root / "v1.0-trainval").mkdir(parents=True)
    (root / "v1.0-trainval" / "scene.json").write_text(json.dumps([{"name": n} for n in names]))
    return root


def cli(*args):
    return CliRunner().invoke(app, list(map(str, args)), env={"COLUMNS": "250"})


def test_paper_eval_lists_the_papers_20_waymo_segments_and_20_nuscenes_indices():
    split = splits.load_split("paper-eval")
    waymo = [ln for ln in split.lines if ln.dataset == "waymo"]
    nusc = [ln for ln in split.lines if ln.dataset == "nuscenes"]
    assert len(waymo) == 20 and len(nusc) == 20
    assert waymo[0].key == "10444454289801298640_4360_000_4380_000"
    assert [ln.key for ln in nusc[:3]] == ["index:22", "index:25", "index:31"]
    assert nusc[-1].key == "index:640"


def test_a_waymo_segment_matches_wherever_its_file_lives(tmp_path):
    deep = tmp_path / "a" / "b"
    deep.mkdir(parents=True)
    (deep / PAPER_SEGMENT).write_bytes(b"")
    (tmp_path / "segment-1_with_camera_labels.tfrecord").write_bytes(b"")
    selection = splits.exclude(scenes_in_folder(tmp_path), ["paper-eval"])
    assert [Path(u).name for u in selection.uris] == ["segment-1_with_camera_labels.tfrecord"]
    assert [e["scene_id"] for e in selection.excluded] == \
        ["waymo-10444454289801298640_4360_000_4380_000"]
    assert selection.record()["exclude_splits"][0]["sha256"] == \
        splits.load_split("paper-eval").sha256


def test_a_nuscenes_index_resolves_against_the_dataroots_own_scene_table(tmp_path):
    names = [f"scene-{1000 + i}" for i in range(30)]  # position 22 is scene-1022, not scene-0022
    uris = nuscenes_scene_uris(nuscenes_root(tmp_path, names))
    selection = splits.exclude(uris, ["paper-eval"])  # 022 and 025 are in range
    assert [e["scene_id"] for e in selection.excluded] == ["nuscenes-scene-1022",
                                                           "nuscenes-scene-1025"]
    assert len(selection.uris) == 28


def test_scene_names_are_accepted_and_split_selects_exactly_its_scenes(tmp_path):
    uris = nuscenes_scene_uris(nuscenes_root(tmp_path, ["scene-0001", "scene-0002", "scene-0003"]))
    split = tmp_path / "mine.txt"
    split.write_text("# two scenes\nnuscenes:scene-0003\nnuscenes:000  # by index\n")
    assert splits.select(uris, str(split)) == [uris[0], uris[2]]


def test_a_split_line_that_matches_no_log_is_named(tmp_path):
    uris = nuscenes_scene_uris(nuscenes_root(tmp_path, ["scene-0001"]))
    split = tmp_path / "mine.txt"
    split.write_text("nuscenes:scene-0001\nnuscenes:scene-0009\n")
    with pytest.raises(ConfigError, match=r"mine.txt:2 \('nuscenes:scene-0009'\)"):
        splits.select(uris, str(split))


def test_a_log_that_two_lines_name_is_refused(tmp_path):
    uris = nuscenes_scene_uris(nuscenes_root(tmp_path, ["scene-0001", "scene-0002"]))
    split = tmp_path / "mine.txt"
    split.write_text("nuscenes:001\nnuscenes:scene-0002\n")  # index 1 is scene-0002
    with pytest.raises(ConfigError, match="named by two lines of split mine"):
        splits.exclude(uris, [str(split)])


def test_bad_split_input_is_a_usage_error_on_the_command_line(tmp_path):
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "segment-1_with_camera_labels.tfrecord").write_bytes(b"")
    common = ["build", "--scenes", tmp_path / "logs", "--data", tmp_path / "d",
              "--manifests", tmp_path / "m"]
    unknown = cli(*common, "--exclude-split", "no-such-split")
    assert unknown.exit_code == 2 and "unknown split 'no-such-split'" in unknown.output
    missing = cli(*common, "--split", "paper-eval")
    assert missing.exit_code == 2 and "40 line(s) match no log" in missing.output
    mixed = cli(*common, "--exclude-split", "none", "--exclude-split", "paper-eval")
    assert mixed.exit_code == 2 and "cannot be combined" in mixed.output
    assert not (tmp_path / "d").exists()  # refused before any scene was touched


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """Two synthetic streets as Waymo segments: seed 7 under a paper evaluation segment's name
    (deep in a sub-folder), seed 11 as an ordinary training segment."""
    from paradrive.ingest.export import export_waymo
    from paradrive.synthetic import SyntheticStreet

    folder = tmp_path_factory.mktemp("logs")
    (folder / "eval").mkdir()
    for seed, path in ((7, folder / "eval" / PAPER_SEGMENT),
                       (11, folder / "segment-train11_with_camera_labels.tfrecord")):
        street = SyntheticStreet("demo", seed=seed, frames=10, width=80, height=48,
                                 cameras=("front",))
        export_waymo(street, path, lidar=False)
    return folder


FAST = ["--profile", "smoke", "--set", "ingest.cameras=[front]", "--set", "fit.checkpoints=[5,10,15,20]",
        "--set", "render.condition_checkpoints=[5,10,15]", "--set", "render.source_checkpoint=20",
        "--set", "render.width=80", "--set", "render.height=48"]


def test_a_training_build_of_a_folder_holds_only_the_training_scene(logs, tmp_path):
    result = cli("build", "--scenes", logs, "--data", tmp_path / "d", "--manifests", tmp_path / "m",
                 "--build", "train", *FAST)
    assert result.exit_code == 0, result.output
    assert "excluded waymo-10444454289801298640_4360_000_4380_000 (split paper-eval" in result.output
    from paradrive.pairs import read_index, read_pairs

    rows = read_pairs(tmp_path / "m" / "train", ["scene_id"]).to_pylist()
    assert {r["scene_id"] for r in rows} == {"waymo-train11"}
    index = read_index(tmp_path / "m" / "train")
    assert [(s.name, s.sha256) for s in index.exclude_splits] == \
        [("paper-eval", splits.load_split("paper-eval").sha256)]
    assert [e.scene_id for e in index.excluded_scenes] == \
        ["waymo-10444454289801298640_4360_000_4380_000"]
    assert not (tmp_path / "d" / "scenes" / "waymo-10444454289801298640_4360_000_4380_000").exists()
    shown = cli("inspect", tmp_path / "m" / "train")
    assert "excluded scene waymo-10444454289801298640_4360_000_4380_000" in shown.output


def test_split_builds_exactly_its_scenes_from_a_folder_of_logs(logs, tmp_path):
    split = tmp_path / "one.txt"
    split.write_text("waymo:segment-train11_with_camera_labels.tfrecord\n")
    result = cli("build", "--scenes", logs, "--split", split, "--stages", "ingest",
                 "--data", tmp_path / "d", "--manifests", tmp_path / "m", *FAST)
    assert result.exit_code == 0, result.output
    # rich wraps long paths at any space (or inside the path), so compare without whitespace
    assert "one.txt:1scene(s)" in "".join(result.output.split())
    assert sorted(p.name for p in (tmp_path / "d" / "scenes").iterdir()) == ["waymo-train11"]
