"""The training loop's own settings: the EMA of the trained parameters (kept, resumed exactly, what
generation samples with), the learning-rate schedule after warm-up, the retention of kept
checkpoints, and weight folders refused before step 0."""

from __future__ import annotations

import json
import math

import pytest
import torch
from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.train.trainer import Trainer, read_checkpoint, scheduled_lr
from paradrive.train.wan import WanTrainer, load_wan_config
from paradrive.wan.recam import ReCamDrivingWan, checkpoint_size, make_tiny_transformer
from test_train import PairTensors, tiny_config
from test_wan_train import LatentPairs

DECAY = 0.9


def reference(out, **train):
    return Trainer(tiny_config(**train), 1, out, PairTensors(3))


def wan(out, **train):
    return WanTrainer(load_wan_config("smoke", {"train": train}), 1, out, LatentPairs(3))


TRAINERS = {"reference": reference, "wan": wan}


class Killed(Exception):
    """Raised from a step's callback: the run dies there, past its last save, saving nothing more."""


def _run_until_killed(trainer, at: int) -> None:
    def die(step, _loss):
        if step == at:
            raise Killed
    with pytest.raises(Killed):
        trainer.train(on_step=die)


def _trained(trainer) -> dict[str, torch.Tensor]:
    return {n: p.detach().double().clone() for n, p in trainer.model.named_parameters() if p.requires_grad}


# -- EMA -------------------------------------------------------------------------------------------
def test_the_ema_after_n_steps_is_the_hand_computed_average(tmp_path):
    trainer = reference(tmp_path / "run", ema_decay=DECAY, save_every=5)
    average = _trained(trainer)                       # the EMA starts at the weights the run starts from
    assert average.keys() == trainer.ema.keys()

    def step(_step, _loss):
        for name, weight in _trained(trainer).items():
            average[name] = DECAY * average[name] + (1 - DECAY) * weight
    trainer.train(5, on_step=step)
    for name, value in trainer.ema.items():
        assert torch.allclose(value.double(), average[name], rtol=1e-6, atol=1e-7), name
    weights = _trained(trainer)
    assert any(not torch.allclose(trainer.ema[n].double(), weights[n]) for n in weights)   # not the weights
    saved = torch.load(tmp_path / "run" / "last.pt", weights_only=True)["ema"]
    assert saved.keys() == trainer.ema.keys()
    assert all(torch.equal(saved[n], trainer.ema[n]) for n in saved)


def test_without_ema_decay_there_is_no_ema_in_the_checkpoint(tmp_path):
    trainer = reference(tmp_path / "run", save_every=2)
    trainer.train(2)
    assert trainer.ema is None
    assert "ema" not in torch.load(tmp_path / "run" / "last.pt", weights_only=True)


@pytest.mark.parametrize("kind", TRAINERS)
def test_a_stopped_and_resumed_runs_ema_is_the_uninterrupted_runs_bit_for_bit(kind, tmp_path):
    make = TRAINERS[kind]
    make(tmp_path / "whole", ema_decay=DECAY, save_every=3).train(7)
    _run_until_killed(make(tmp_path / "parts", ema_decay=DECAY, save_every=3), 5)   # dies past its save at 3
    resumed = make(tmp_path / "parts", ema_decay=DECAY, save_every=3)
    assert resumed.step == 3 and not resumed.notes
    resumed.train(7)
    a = torch.load(tmp_path / "whole" / "last.pt", weights_only=True)
    b = torch.load(tmp_path / "parts" / "last.pt", weights_only=True)
    for part in ("ema", "model"):
        assert a[part].keys() == b[part].keys()
        for name in a[part]:
            assert a[part][name].numpy().tobytes() == b[part][name].numpy().tobytes(), (part, name)


def test_generation_samples_with_the_ema_when_the_checkpoint_holds_one(tmp_path):
    from paradrive.train.generate import load_generator

    wan(tmp_path / "run", ema_decay=DECAY, save_every=3).train(3)
    ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    own = dict(load_generator(tmp_path / "run", {}).model.named_parameters())
    differ = [n for n in ckpt["ema"] if not torch.equal(ckpt["ema"][n], ckpt["model"][n])]
    assert differ
    for name in ckpt["ema"]:
        assert torch.equal(own[name].detach(), ckpt["ema"][name]), name
    for name in set(ckpt["model"]) - set(ckpt["ema"]):
        assert torch.equal(own[name].detach(), ckpt["model"][name]), name


def test_the_trainers_sample_swaps_the_ema_in_and_the_weights_back(tmp_path):
    trainer = reference(tmp_path / "run", ema_decay=DECAY)
    trainer.train(3)
    before = _trained(trainer)
    with trainer.averaged():
        assert all(torch.equal(_trained(trainer)[n], trainer.ema[n].double()) for n in before)
    after = _trained(trainer)
    assert all(torch.equal(before[n], after[n]) for n in before)


def test_the_13b_checkpoints_with_ema_by_computation():
    """docs/train-recamdriving.md's sizes with train.ema_decay on: 4 more bytes a trained parameter."""
    from diffusers import WanTransformer3DModel

    from paradrive.wan.recam import wan21_t2v_1_3b_config

    sizes = []
    for stage, ffn in ((1, False), (2, False), (2, True)):
        with torch.device("meta"):
            model = ReCamDrivingWan(WanTransformer3DModel(**wan21_t2v_1_3b_config()), rendering=stage == 2,
                                    max_frames=31)
        size = checkpoint_size(model, stage, ffn)
        sizes.append(round((size["bytes"] + 4 * size["trained"]) / 1e9, 2))
    assert sizes == [5.68, 10.49, 23.71]


def test_a_checkpoint_with_ema_is_larger_by_the_trained_parameters_fp32_bytes(tmp_path):
    wan(tmp_path / "plain", save_every=1).train(1)
    wan(tmp_path / "ema", ema_decay=DECAY, save_every=1).train(1)
    size = checkpoint_size(ReCamDrivingWan(make_tiny_transformer(0), rendering=False, max_frames=2), 1)
    grown = (tmp_path / "ema" / "last.pt").stat().st_size - (tmp_path / "plain" / "last.pt").stat().st_size
    assert 4 * size["trained"] <= grown < 4 * size["trained"] + 64_000, (grown, size)


# -- the learning rate -----------------------------------------------------------------------------
def _train(schedule: str, **more) -> dict:
    return {"lr": 1e-3, "min_lr": 1e-5, "warmup_steps": 2, "steps": 12, "lr_schedule": schedule, **more}


@pytest.mark.parametrize("step", [0, 1, 2, 5, 11, 12, 20])
def test_the_learning_rate_follows_its_formula(step):
    lr, low, warmup, total = 1e-3, 1e-5, 2, 12
    p = min(1.0, max(0, step - warmup) / (total - warmup))
    expected = {
        "constant": lr,
        "linear": low + (lr - low) * (1 - p),
        "cosine": low + (lr - low) * (1 + math.cos(math.pi * p)) / 2,
    }
    for schedule, value in expected.items():
        want = lr * (step + 1) / warmup if step < warmup else value
        assert scheduled_lr(_train(schedule), step) == pytest.approx(want, rel=1e-12), schedule
    assert scheduled_lr(_train("cosine"), total) == pytest.approx(low)      # min_lr at the run's end
    assert scheduled_lr(_train("linear"), warmup) == pytest.approx(lr)      # full rate right after warm-up


def test_a_resumed_run_goes_on_with_the_schedule(tmp_path):
    settings = {"lr_schedule": "cosine", "min_lr": 1e-5, "warmup_steps": 2, "steps": 8, "save_every": 3}
    reference(tmp_path / "whole", **settings).train(8)
    _run_until_killed(reference(tmp_path / "parts", **settings), 5)    # saved at 3, logged 4 and 5
    resumed = reference(tmp_path / "parts", **settings)
    assert resumed.step == 3
    resumed.train(8)

    def rates(run):
        return [json.loads(line)["lr"] for line in (tmp_path / run / "metrics.jsonl").read_text().splitlines()]
    cfg = tiny_config(**settings)["train"]
    assert rates("parts") == rates("whole") == [scheduled_lr(cfg, s) for s in range(8)]
    whole = rates("whole")
    assert whole[0] < whole[1] == whole[2] > whole[3] > whole[-1]   # warm-up, full rate, decay


# -- retention -------------------------------------------------------------------------------------
def test_kept_checkpoints_are_the_last_few_and_every_nth_and_each_loads(tmp_path):
    trainer = reference(tmp_path / "run", checkpoint_every=1, keep_last=2, keep_every=3, ema_decay=DECAY)
    trainer.train(8)
    kept = sorted(p.name for p in (tmp_path / "run").glob("ckpt_*.pt"))
    assert kept == ["ckpt_000003.pt", "ckpt_000006.pt", "ckpt_000007.pt", "ckpt_000008.pt"]
    for name in kept:
        ckpt = read_checkpoint(tmp_path / "run" / name, "kept")
        assert ckpt["step"] == int(name[5:11]) and "ema" in ckpt
    resumed = reference(tmp_path / "other", checkpoint_every=1, keep_last=2, keep_every=3, ema_decay=DECAY)
    resumed._init_from(tmp_path / "run" / "ckpt_000006.pt")               # a kept one starts another run


def test_keep_last_zero_keeps_every_checkpoint(tmp_path):
    reference(tmp_path / "run", checkpoint_every=2, keep_last=0).train(6)
    assert sorted(p.name for p in (tmp_path / "run").glob("ckpt_*.pt")) == [
        "ckpt_000002.pt", "ckpt_000004.pt", "ckpt_000006.pt"]


# -- weight folders --------------------------------------------------------------------------------
def _refused(tmp_path, flag, folder):
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["train", "--build", str(tmp_path / "no-build"), "--model", "wan",
                                      "--config", "smoke", "--out", str(out), flag, str(folder)])
    assert result.exit_code == 2, result.output
    (line,) = [line for line in result.output.splitlines() if line.strip()]
    assert line.startswith("error:") and flag in line and str(folder) in line
    assert "last.pt" not in line and not out.exists()
    return line


@pytest.mark.parametrize("flag", ["--transformer", "--vae", "--text-encoder"])
def test_a_weight_folder_that_does_not_exist_is_refused_before_step_0(flag, tmp_path):
    line = _refused(tmp_path, flag, tmp_path / "nowhere")
    assert "no such folder" in line and "diffusers folder" in line


@pytest.mark.parametrize("flag, says", [("--transformer", "config.json and safetensors"),
                                        ("--vae", "config.json"), ("--text-encoder", "text_encoder/")])
def test_a_weight_folder_without_its_files_is_refused_before_step_0(flag, says, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert says in _refused(tmp_path, flag, empty)
