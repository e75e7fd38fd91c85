"""The fit's camera set follows the dataset (DriveStudio's defaults), declared in stages/ingest.yaml."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.errors import ConfigError, SceneError
from paradrive.stages.ingest import ingest
from paradrive.ingest.export import export_scene
from paradrive.pipeline import StageRegistry, parse_overrides
from paradrive.scene import load_scene

FRONT3 = ["front", "front_left", "front_right"]
SIX = ["front", "front_left", "front_right", "back_left", "back_right", "back"]
TINY = ["ingest.synthetic_frames=3", "ingest.synthetic_width=48", "ingest.synthetic_height=32"]
SCENE = "synthetic:demo?seed=5"


def ingest_params(*overrides: str) -> dict:
    return StageRegistry().resolve(None, parse_overrides(TINY + list(overrides))).typed("ingest")


def test_default_fit_sets_are_drivestudios_per_dataset():
    params = StageRegistry().resolve(None).typed("ingest")
    assert params.cameras == "auto"
    assert params.camera_sets == {"waymo": FRONT3, "nuscenes": SIX, "synthetic": FRONT3}


@pytest.mark.parametrize("fmt, expected", [("waymo", FRONT3), ("nuscenes", SIX),
                                           ("drivestudio", FRONT3)])
def test_each_exported_format_ingests_its_datasets_fit_set(tmp_path, fmt, expected):
    params = ingest_params()
    uri = export_scene(SCENE, fmt, tmp_path / "log", params)
    summary = ingest(uri, tmp_path / "scene", params)
    scene = load_scene(tmp_path / "scene")
    assert summary["cameras"] == sorted(expected)
    assert sorted(scene.cameras) == sorted(expected)
    assert all(sorted(f.cameras) == sorted(expected) for f in scene.frames)


def test_synthetic_scene_ingests_the_front_three_by_default(tmp_path):
    summary = ingest(SCENE, tmp_path / "scene", ingest_params())
    assert summary["cameras"] == sorted(FRONT3)
    assert sorted(load_scene(tmp_path / "scene").cameras) == sorted(FRONT3)


def test_cameras_override_keeps_only_the_listed_cameras(tmp_path):
    summary = ingest(SCENE, tmp_path / "a", ingest_params("ingest.cameras=[front]"))
    assert summary["cameras"] == ["front"]
    sets = "ingest.camera_sets={synthetic: [front, back], waymo: [front], nuscenes: [front]}"
    summary = ingest(SCENE, tmp_path / "b", ingest_params(sets))
    assert summary["cameras"] == ["back", "front"]


def test_null_cameras_ingest_every_camera_of_the_log(tmp_path):
    params = ingest_params()
    uri = export_scene(SCENE, "waymo", tmp_path / "log", params)
    summary = ingest(uri, tmp_path / "scene", ingest_params("ingest.cameras=null"))
    assert summary["cameras"] == sorted(FRONT3)


@pytest.mark.parametrize("fmt, dataset, fit_set", [("waymo", "waymo", FRONT3), ("nuscenes", "nuscenes", SIX),
                                                    ("drivestudio", "waymo", FRONT3)])
def test_a_one_camera_log_fits_its_camera_under_auto_and_says_so(tmp_path, caplog, fmt, dataset, fit_set):
    """A log holding only part of the dataset's fit set (a one-camera DriveStudio folder):
    ``auto`` takes the cameras of the set it has and names the ones it left out."""
    uri = export_scene(SCENE, fmt, tmp_path / "log", ingest_params("ingest.cameras=[front]"))
    with caplog.at_level("WARNING", logger="paradrive.ingest"):
        summary = ingest(uri, tmp_path / "scene", ingest_params())
    assert summary["cameras"] == ["front"] and sorted(load_scene(tmp_path / "scene").cameras) == ["front"]
    (message,) = [r.getMessage() for r in caplog.records if "ingest.cameras is auto" in r.getMessage()]
    assert f"the {dataset} fit set ({', '.join(fit_set)})" in message
    assert f"the log has no {', '.join(c for c in fit_set if c != 'front')}, so the fit sees front" in message


def test_a_log_with_none_of_the_fit_set_names_scene_file_and_fix(tmp_path):
    front_only = ingest_params("ingest.cameras=[front]")
    uri = export_scene(SCENE, "nuscenes", tmp_path / "log", front_only)
    with pytest.raises(SceneError) as err:
        ingest(uri, tmp_path / "nuscenes-demo", ingest_params("ingest.camera_sets={nuscenes: [back, back_left]}"))
    text = str(err.value)
    assert text.startswith("scene nuscenes-demo: ")
    assert "calibration missing for camera(s) back, back_left" in text
    assert "ingest.cameras is auto, the nuscenes fit set" in text
    assert str(tmp_path / "log" / "v1.0-mini") in text
    assert text.endswith("--set ingest.cameras=[front]")
    assert not (tmp_path / "nuscenes-demo").exists()


def test_a_dataset_without_a_fit_set_is_an_error_naming_the_fix(tmp_path):
    params = ingest_params("ingest.camera_sets={waymo: [front]}")
    with pytest.raises(SceneError, match="camera_sets has no synthetic entry.*add camera_sets.synthetic"):
        ingest(SCENE, tmp_path / "scene", params)


def test_cameras_takes_auto_a_list_or_null_only(tmp_path):
    with pytest.raises(ConfigError, match="ingest.cameras = 3 has type int, expected one of str, list"):
        ingest_params("ingest.cameras=3")
    with pytest.raises(SceneError, match="'front' is neither auto, null nor a list"):
        ingest(SCENE, tmp_path / "scene", ingest_params("ingest.cameras=front"))


def test_export_command_writes_the_cameras_ingest_will_keep(tmp_path):
    args = ["export", "waymo", str(tmp_path / "log"), "--scene", SCENE]
    sets = [a for s in TINY for a in ("--set", s)]
    result = CliRunner().invoke(app, args + sets + ["--set", "ingest.cameras=[front]"])
    assert result.exit_code == 0, result.output
    uri = result.output.strip().splitlines()[-1]
    # a camera asked for by name must be there; auto takes the one the log has
    with pytest.raises(SceneError, match=r"calibration missing for camera\(s\) front_left "):
        ingest(uri, tmp_path / "scene", ingest_params("ingest.cameras=[front, front_left]"))
    assert ingest(uri, tmp_path / "scene", ingest_params())["cameras"] == ["front"]
