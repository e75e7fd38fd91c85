"""Checkpoints of both trainers: a damaged last.pt (empty, cut off, garbage, a part missing) is
named in one line, never read as a file that needs pickle, and a run falls back to the checkpoint
before it; a Wan checkpoint holds what trains, not the frozen base, and is checked against it."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from paradrive.io import UnsafeFileError
from paradrive.train.trainer import PREVIOUS, DamagedCheckpoint, Trainer
from paradrive.wan.recam import ReCamDrivingWan, checkpoint_size, make_tiny_transformer, stage_parameter_names
from paradrive.train.wan import WanTrainer, load_wan_config
from test_train import PairTensors, tiny_config
from test_wan_train import LatentPairs


def reference(out, **train):
    return Trainer(tiny_config(**train), 1, out, PairTensors(2))


def wan(out, **train):
    return WanTrainer(load_wan_config("smoke", {"train": train}), 1, out, LatentPairs(2))


TRAINERS = {"reference": reference, "wan": wan}


def _without(key):
    def damage(path):
        ckpt = torch.load(path, weights_only=True)
        del ckpt[key]
        torch.save(ckpt, path)
    return damage


DAMAGE = {
    "empty": lambda path: path.write_bytes(b""),
    "cut off": lambda path: path.write_bytes(path.read_bytes()[: path.stat().st_size // 2]),
    "garbage": lambda path: path.write_bytes(bytes(range(256)) * 64),
    "without its config": _without("config"),
    "without its optimiser": _without("optimizer"),
}
SAYS = {"empty": "is empty", "cut off": "not a whole checkpoint", "garbage": "not a whole checkpoint",
        "without its config": "lacks config", "without its optimiser": "lacks optimizer"}


@pytest.mark.parametrize("kind", TRAINERS)
@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_last_checkpoint_is_named_in_one_line_with_the_fix(kind, damage, tmp_path):
    make = TRAINERS[kind]
    make(tmp_path / "run", save_every=2).train(2)            # one save: last.pt, nothing before it
    last = tmp_path / "run" / "last.pt"
    assert not (tmp_path / "run" / PREVIOUS).exists()
    DAMAGE[damage](last)
    with pytest.raises(DamagedCheckpoint) as caught:
        make(tmp_path / "run", save_every=2)
    message = str(caught.value)
    assert str(last) in message and SAYS[damage] in message and "\n" not in message
    assert "delete" in message and "another --out" in message
    assert not isinstance(caught.value, UnsafeFileError) and "pickle" not in message


@pytest.mark.parametrize("kind", TRAINERS)
def test_a_damaged_last_checkpoint_falls_back_to_the_one_before_and_says_so(kind, tmp_path):
    make = TRAINERS[kind]
    whole = make(tmp_path / "whole", save_every=2)
    whole.train(4)
    run = make(tmp_path / "run", save_every=2)
    run.train(4)                                              # saves at 2 (previous.pt) and 4 (last.pt)
    assert torch.load(tmp_path / "run" / PREVIOUS, weights_only=True)["step"] == 2
    DAMAGE["cut off"](tmp_path / "run" / "last.pt")
    resumed = make(tmp_path / "run", save_every=2)
    assert resumed.step == 2
    (note,) = resumed.notes
    assert "last.pt" in note and "not a whole checkpoint" in note
    assert f"resuming from {tmp_path / 'run' / PREVIOUS}" in note
    resumed.train(4)                                          # and computes what the whole run did
    for (name, a), b in zip(whole.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.equal(a, b), name


def test_a_checkpoint_that_really_needs_pickle_is_still_refused_as_such(tmp_path):
    run = tmp_path / "run"
    reference(run, save_every=2).train(2)
    torch.save({"evil": object()}, run / "last.pt")           # a whole archive holding a Python object
    with pytest.raises(UnsafeFileError, match="Python objects"):
        reference(run, save_every=2)


def test_train_command_reports_a_damaged_checkpoint_in_one_line(wan_builds, tmp_path):
    from typer.testing import CliRunner

    from paradrive.cli import app

    out = tmp_path / "run"
    args = ["train", "--build", str(wan_builds["train"]), "--model", "wan", "--config", "smoke", "--out", str(out),
            "--steps", "2", "--set", "train.save_every=1"]
    assert CliRunner().invoke(app, args).exit_code == 0
    DAMAGE["cut off"](out / "stage1" / "last.pt")
    fell_back = CliRunner().invoke(app, args)
    assert fell_back.exit_code == 0, fell_back.output
    assert "note:" in fell_back.output and "resuming from" in fell_back.output and "(step 1)" in fell_back.output
    for name in ("last.pt", PREVIOUS):
        DAMAGE["garbage"](out / "stage1" / name)
    # the real command, as a user's shell runs it: one line on stderr, exit 2
    refused = subprocess.run([sys.executable, "-m", "paradrive.cli", *args], capture_output=True, text=True,
                             timeout=600)
    assert refused.returncode == 2
    lines = [line for line in refused.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "not a whole checkpoint" in lines[0], refused.stderr
    assert "Traceback" not in refused.stderr and "Aborted" not in refused.stderr


def test_a_wan_checkpoint_holds_the_trained_parameters_not_the_frozen_base(tmp_path):
    trainer = wan(tmp_path / "s1")
    trainer.train(2)
    ckpt = torch.load(tmp_path / "s1" / "last.pt", weights_only=True)
    assert set(ckpt["model"]) == stage_parameter_names(trainer.wan, 1)
    assert not any(".ffn." in k or ".attn2." in k or k.startswith("transformer.patch_embedding") for k in ckpt["model"])
    assert ckpt["base"] == {"folder": "tiny", "config_sha256": trainer.base["config_sha256"]}
    size = checkpoint_size(trainer.wan, 1)
    assert size["saved"] == sum(v.numel() for v in ckpt["model"].values()) < size["base"]
    # the file is the counted bytes plus the archive's own: names, counters, the config
    on_disk = (tmp_path / "s1" / "last.pt").stat().st_size
    assert size["bytes"] <= on_disk < size["bytes"] + 64_000, (on_disk, size)

    stage2 = WanTrainer(load_wan_config("smoke"), 2, tmp_path / "s2", LatentPairs(2), init=tmp_path / "s1" / "last.pt")
    stage2.train(2)
    saved = torch.load(tmp_path / "s2" / "last.pt", weights_only=True)["model"]
    assert set(saved) == stage_parameter_names(stage2.wan, 1) | stage_parameter_names(stage2.wan, 2)
    for name, value in ckpt["model"].items():                 # stage 1's, frozen, travel with stage 2
        assert torch.equal(saved[name], value), name


def test_a_checkpoint_loaded_onto_another_base_names_the_base_it_was_trained_on(tmp_path):
    wan(tmp_path / "s1").train(2)
    trainer = wan(tmp_path / "fresh")
    trainer.base = {"folder": "/models/other-wan", "config_sha256": "0" * 64}   # a base of another config
    with pytest.raises(ValueError, match=r"trained on the transformer in tiny .*pass --transformer tiny"):
        trainer._init_from(tmp_path / "s1" / "last.pt")


def test_the_13b_models_checkpoints_by_computation():
    """The figures docs/train-recamdriving.md quotes, from the real configuration's shapes."""
    from diffusers import WanTransformer3DModel

    from paradrive.wan.recam import wan21_t2v_1_3b_config

    sizes = {}
    for stage, ffn in ((1, False), (2, False), (2, True)):
        with torch.device("meta"):
            model = ReCamDrivingWan(WanTransformer3DModel(**wan21_t2v_1_3b_config()), rendering=stage == 2,
                                    max_frames=31)   # the paper's E_f: one row per latent frame of a 121-frame clip
        sizes[stage, ffn] = checkpoint_size(model, stage, ffn)
    assert sizes[1, False]["base"] == 1_418_996_800
    assert (sizes[1, False]["saved"], sizes[1, False]["trained"]) == (354_863_616, 354_863_616)
    assert (sizes[2, False]["saved"], sizes[2, False]["trained"]) == (921_831_936, 566_968_320)
    assert (sizes[2, True]["saved"], sizes[2, True]["trained"]) == (1_747_900_416, 1_393_036_800)
    assert [round(sizes[k]["bytes"] / 1e9, 2) for k in ((1, False), (2, False), (2, True))] == [4.26, 8.22, 18.14]


def test_tiny_model_counts_match_its_parameters():
    model = ReCamDrivingWan(make_tiny_transformer(0), rendering=True, max_frames=2)
    size = checkpoint_size(model, 2)
    assert size["base"] == sum(p.numel() for p in model.transformer.parameters())
    trained = stage_parameter_names(model, 2)
    assert size["trained"] == sum(p.numel() for n, p in model.named_parameters() if n in trained)


def test_a_damaged_init_checkpoint_is_named_in_one_line(tmp_path):
    wan(tmp_path / "s1").train(1)
    DAMAGE["cut off"](tmp_path / "s1" / "last.pt")
    with pytest.raises(DamagedCheckpoint, match=r"^--init .*last.pt is not a whole checkpoint"):
        WanTrainer(load_wan_config("smoke"), 2, tmp_path / "s2", LatentPairs(2), init=tmp_path / "s1" / "last.pt")


def test_a_step_that_fails_stops_the_run_in_one_line(wan_builds, tmp_path):
    from typer.testing import CliRunner

    from paradrive.cli import app

    result = CliRunner().invoke(app, ["train", "--build", str(wan_builds["train"]), "--model", "wan", "--config",
                                      "smoke", "--out", str(tmp_path / "run"), "--steps", "3", "--set",
                                      "train.lr=1.0e+30"])
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output
    (line,) = [line for line in result.output.splitlines() if line.strip()]
    assert line.startswith("error: stage 1 stopped at step") and "loss is not finite" in line
