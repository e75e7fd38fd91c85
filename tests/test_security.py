"""Shared storage is not trusted code: no pickle from the data root, no paths out of a build or
a scene folder, no secrets in what a build writes, no scene that escapes the data root."""

from __future__ import annotations

import json
import logging
import pathlib
import shutil

import pytest
import torch

from paradrive.io import PathEscapeError, UnsafeFileError


class Payload:
    """Unpickling this runs ``Path(marker).touch()``: what a crafted file on shared storage does."""

    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (self.marker,))


def crafted_file(path: pathlib.Path, marker: pathlib.Path, **fields) -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({**fields, "payload": Payload(marker)}, path)
    return path


def test_the_crafted_file_runs_its_code_when_unpickled(tmp_path):
    """The payload the tests below refuse is live: plain pickle loading writes the marker."""
    marker = tmp_path / "ran"
    torch.load(crafted_file(tmp_path / "x.pt", marker), weights_only=False)
    assert marker.exists()


# --------------------------------------------------------------------------- pickle: fit state

@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> pathlib.Path:
    """Synthetic street, 8 frames of 80x48, ingested only."""
    from paradrive.pipeline import StageRegistry, run_build

    root = tmp_path_factory.mktemp("tiny_scene")
    config = StageRegistry().resolve("smoke", {"ingest": {
        "synthetic_frames": 8, "synthetic_width": 80, "synthetic_height": 48}})
    report = run_build(config, ["synthetic:demo?seed=7"], root / "data", stages=["ingest"],
                       manifests_dir=root / "manifests", build="tiny")
    assert not report.failures(), [r.error for r in report.failures()]
    (scene_dir,) = (root / "data" / "scenes").iterdir()
    return scene_dir


def _fit_params() -> dict:
    from paradrive.pipeline.specs import StageRegistry

    return StageRegistry().resolve("smoke", {"fit": {
        "checkpoints": [2, 4], "threads": 1, "init_points": 500, "sky_points": 100,
        "eval_views": 2, "state_interval": 2, "keep_state": True}}).params["fit"]


def test_a_pickled_fit_state_is_refused_and_the_fit_starts_over(tiny_scene, tmp_path, caplog):
    from paradrive.gs.fit import STATE_VERSION, fit_scene

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    marker = tmp_path / "ran"
    state = crafted_file(scene / "gs" / "state.pt", marker, version=STATE_VERSION, step=3)
    with caplog.at_level(logging.WARNING, logger="paradrive.gs.fit"):
        doc = fit_scene(scene, _fit_params())
    assert not marker.exists()
    assert any(str(state) in r.getMessage() and "starting over" in r.getMessage()
               and "pickle" in r.getMessage() for r in caplog.records)
    assert doc["complete"] and [c["iteration"] for c in doc["checkpoints"]] == [2, 4]
    # the state the fit wrote in its place holds tensors and plain data only
    saved = torch.load(state, weights_only=True)
    assert saved["version"] == STATE_VERSION and saved["step"] == 4
    assert isinstance(saved["rng"]["numpy"]["keys"], torch.Tensor)


# --------------------------------------------------------------------------- pickle: trainer

def _tiny_train_config() -> dict:
    from paradrive.train import load_config

    return load_config("smoke", {"data": {"num_frames": 4, "height": 32, "width": 48},
                                 "model": {"dim": 32, "depth": 2, "heads": 2},
                                 "train": {"batch_size": 2}})


def test_a_pickled_trainer_checkpoint_is_refused_on_resume_init_and_sampling(tmp_path):
    from paradrive.train import Trainer, load_for_sampling
    from paradrive.train.trainer import CHECKPOINT_FORMAT

    marker = tmp_path / "ran"
    last = crafted_file(tmp_path / "stage1" / "last.pt", marker, format=CHECKPOINT_FORMAT, stage=1)
    pairs = [{}, {}]  # never read: the checkpoint is refused first
    with pytest.raises(UnsafeFileError, match="last.pt: holds Python objects.*refused"):
        Trainer(_tiny_train_config(), 1, tmp_path / "stage1", pairs)
    with pytest.raises(UnsafeFileError, match="last.pt"):
        Trainer(_tiny_train_config(), 2, tmp_path / "stage2", pairs, init=last)
    with pytest.raises(UnsafeFileError, match="last.pt"):
        load_for_sampling(last, device="cpu")
    assert not marker.exists()


def test_a_trainer_checkpoint_loads_without_pickle(tmp_path):
    from paradrive.train import Trainer

    class Pairs(torch.utils.data.Dataset):
        def __len__(self) -> int:
            return 2

    trainer = Trainer(_tiny_train_config(), 1, tmp_path / "run", Pairs())
    trainer.save()
    ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    assert ckpt["config"] == trainer.config and ckpt["generator"].dtype == torch.uint8
    assert Trainer(_tiny_train_config(), 1, tmp_path / "run", Pairs()).step == 0
