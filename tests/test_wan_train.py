"""``paradrive train --model wan``: both stages with tiny random Wan weights on latent samples and
on a smoke build's videos, the loss falling, exact resume, the configs, and the same steps on
the stand-in device."""

from __future__ import annotations

import json

import pytest
import torch
from simulated_device import DEVICE, simulated_device

from paradrive.errors import ConfigError
from paradrive.train.trainer import collate
from paradrive.wan.recam import stage_parameter_names
from paradrive.train.wan import WanTrainer, latent_frame_indices, load_wan_config, relative_camera

C, T, H, W = 16, 2, 6, 10


class LatentPairs:
    """Samples shaped like the adapter's ``latents=True`` ones: the target a smooth function of
    the source and the camera, so there is something to learn."""

    def __init__(self, n: int = 2):
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        g = torch.Generator().manual_seed(i)
        source = torch.randn(C, T, H, W, generator=g)
        rel_pose = torch.eye(4).repeat(T, 1, 1)
        rel_pose[:, 0, 3] = 1.0 + i                         # a lateral offset of 1 + i metres
        return {"source_latents": source, "target_latents": source.roll(1 + i, dims=-1),
                "condition_latents": source.roll(1 + i, dims=-1) + 0.1 * torch.randn(C, T, H, W, generator=g),
                "rel_pose": rel_pose, "camera": rel_pose[:, :3, :4].reshape(T, 12) + 0.5,
                "text_embedding": torch.zeros(8, 32), "pair_id": f"pair{i}"}


def config(**train) -> dict:
    return load_wan_config("smoke", {"train": {"save_every": 3, **train}})


def weights(path) -> dict:
    return torch.load(path, weights_only=True)["model"]


def test_wan_configs_resolve_by_name_and_are_checked():
    smoke = load_wan_config("smoke")
    assert smoke["model"]["transformer"] == "tiny" and smoke["data"]["num_frames"] == 9
    default = load_wan_config(None)
    assert (default["data"]["num_frames"], default["data"]["height"], default["data"]["width"]) == (121, 480, 832)
    assert default["train"]["steps"] == 6000 and default["train"]["lr"] == 1e-4
    assert default["model"]["camera"] == "auto"   # relative, or recammaster_per_frame with model.recammaster
    assert (default["model"]["max_frames"], default["model"]["frame_embedding"]) == (31, "shared")   # the paper's E_f
    assert default["model"]["cross_attn_zero_out"] is False
    with pytest.raises(ConfigError, match="model.camera = 'absolute' is not allowed"):
        load_wan_config("smoke", {"model": {"camera": "absolute"}})
    with pytest.raises(ConfigError, match="unknown setting 'dim'"):
        load_wan_config("smoke", {"model": {"dim": 8}})


def test_the_camera_is_the_relative_pose_at_each_latent_frames_first_video_frame():
    assert latent_frame_indices(121) == list(range(0, 121, 4)) and len(latent_frame_indices(121)) == 31
    assert latent_frame_indices(8) == [0, 4]
    rel = torch.eye(4).repeat(1, 9, 1, 1)
    rel[0, :, 0, 3] = torch.arange(9.0)                     # x offset = frame index
    camera = relative_camera(rel)
    assert camera.shape == (1, 3, 12) and camera.dtype == torch.float32
    assert camera[0, :, 3].tolist() == [0.0, 4.0, 8.0]
    assert camera[0, 0].tolist() == [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]


def test_the_camera_form_is_the_configs_choice(tmp_path):
    batch = collate([LatentPairs()[1]])
    auto = WanTrainer(config(), 1, tmp_path / "rel", LatentPairs())
    assert auto.config["model"]["camera"] == "relative"   # no ReCamMaster weights: ΔT
    relative = auto.latents(batch)["camera"]
    assert torch.equal(relative, batch["rel_pose"][:, :, :3, :4].reshape(1, T, 12))
    assert relative[0, :, 3].tolist() == [2.0, 2.0]   # the lateral offset, the same at every frame
    inverse = load_wan_config("smoke", {"model": {"camera": "recammaster_per_frame"}})
    per_frame = WanTrainer(inverse, 1, tmp_path / "pf", LatentPairs()).latents(batch)["camera"]
    assert per_frame[0, :, 3].tolist() == [-2.0, -2.0]   # the inverse: the other sign, no rotation
    assert per_frame[0, :, :3].tolist() == [[1.0, 0.0, 0.0]] * 2
    other = load_wan_config("smoke", {"model": {"camera": "recammaster"}})
    assert torch.equal(WanTrainer(other, 1, tmp_path / "rm", LatentPairs()).latents(batch)["camera"], batch["camera"])


def test_stage1_loss_falls_on_one_pair(tmp_path):
    trainer = WanTrainer(config(batch_size=1, lr=3e-3), 1, tmp_path / "s1", LatentPairs(1))
    losses = trainer.train(40)
    first, last = sum(losses[:10]) / 10, sum(losses[-10:]) / 10
    assert last < 0.95 * first, (first, last)   # only the self-attention learns: a tiny model moves slowly


def test_stage2_trains_only_its_modules_and_keeps_stage1_weights(tmp_path):
    WanTrainer(config(), 1, tmp_path / "s1", LatentPairs()).train(3)
    stage1 = weights(tmp_path / "s1" / "last.pt")
    trainer = WanTrainer(config(), 2, tmp_path / "s2", LatentPairs(), init=tmp_path / "s1" / "last.pt")
    trained = stage_parameter_names(trainer.model, 2)
    assert {n for n, p in trainer.model.named_parameters() if p.requires_grad} == trained
    fresh = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    trainer.train(3)
    stage2 = weights(tmp_path / "s2" / "last.pt")
    assert all(torch.equal(stage1[k], stage2[k]) for k in stage1 if k not in trained)
    changed = {k for k in stage2 if not torch.equal(stage2[k], fresh[k])}
    assert changed == trained


def test_stage2_without_stage1_weights_is_refused(tmp_path):
    with pytest.raises(ValueError, match="stage 2 starts from stage-1 weights"):
        WanTrainer(config(), 2, tmp_path / "s2", LatentPairs())


def test_a_stopped_run_resumes_to_the_same_weights_as_an_uninterrupted_one(tmp_path):
    WanTrainer(config(), 1, tmp_path / "whole", LatentPairs(3)).train(7)
    WanTrainer(config(), 1, tmp_path / "parts", LatentPairs(3)).train(3)   # stops after its save at 3
    resumed = WanTrainer(config(), 1, tmp_path / "parts", LatentPairs(3))
    assert resumed.step == 3
    resumed.train(7)
    a, b = weights(tmp_path / "whole" / "last.pt"), weights(tmp_path / "parts" / "last.pt")
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].numpy().tobytes() == b[key].numpy().tobytes(), key
    steps = [json.loads(line)["step"] for line in (tmp_path / "parts" / "metrics.jsonl").read_text().splitlines()]
    assert steps == list(range(1, 8))


def test_resume_refuses_a_checkpoint_of_another_model(tmp_path):
    WanTrainer(config(), 1, tmp_path / "s1", LatentPairs()).train(3)
    other = load_wan_config("smoke", {"model": {"camera": "recammaster"}})
    with pytest.raises(ValueError, match="was trained with model="):
        WanTrainer(other, 1, tmp_path / "s1", LatentPairs())


def test_wan_trainer_steps_on_a_device_compute_what_they_compute_on_the_cpu(tmp_path):
    cpu = WanTrainer(config(), 2 - 1, tmp_path / "cpu", LatentPairs()).train(2)
    with simulated_device():
        trainer = WanTrainer({**config(), "device": str(DEVICE)}, 1, tmp_path / "dev", LatentPairs())
        losses = trainer.train(2)
        assert all(p.device == DEVICE for p in trainer.model.parameters())
    # the stand-in device sums some gradients in another order (differences of ~1e-9)
    torch.testing.assert_close(losses, cpu, rtol=1e-5, atol=1e-6)


def test_train_command_runs_both_wan_stages_on_a_smoke_build_and_samples(smoke_build, tmp_path):
    import av
    import typer
    from typer.testing import CliRunner

    from paradrive.commands.train import register

    app = typer.Typer()  # the command as paradrive.cli registers it, without the other commands
    register(app)
    app.command("noop", hidden=True)(lambda: None)  # keeps 'train' a sub-command, as in paradrive

    build, out = str(smoke_build["build_dir"]), tmp_path / "run"
    common = ["train", "--build", build, "--model", "wan", "--config", "smoke", "--out", str(out)]
    runner = CliRunner()
    r1 = runner.invoke(app, common + ["--stage", "1"])
    assert r1.exit_code == 0, r1.output
    r2 = runner.invoke(app, common + ["--stage", "2", "--sample", str(tmp_path / "s.mp4"), "--pair", "1"])
    assert r2.exit_code == 0, r2.output

    cfg = load_wan_config("smoke")
    for stage in (1, 2):
        lines = (out / f"stage{stage}" / "metrics.jsonl").read_text().splitlines()
        assert [json.loads(line)["step"] for line in lines] == list(range(1, cfg["train"]["steps"] + 1))
    stage1, stage2 = weights(out / "stage1" / "last.pt"), weights(out / "stage2" / "last.pt")
    assert all(torch.equal(stage1[k], stage2[k]) for k in stage1 if ".ffn." not in k)   # stage 1 frozen
    assert any(".render_attn." in k for k in stage2)
    with av.open(str(tmp_path / "s.mp4")) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == cfg["data"]["num_frames"]
    assert frames[0].shape == (cfg["data"]["height"], cfg["data"]["width"], 3)

    # a wan config is not the reference model's
    reference = runner.invoke(app, ["train", "--build", build, "--config", "wan-smoke", "--out", str(tmp_path / "r")])
    assert reference.exit_code == 2 and "add --model wan" in reference.output


def test_training_reads_a_builds_cached_latents_without_the_vae(wan_builds, wan_folder, copy_tree, tmp_path):
    from paradrive.wan.encode import EncodeSettings, encode_build
    from paradrive.train.wan import open_wan_dataset

    build = copy_tree(wan_builds["train"], "train")   # one scene of the smoke clips: half the smoke build's videos
    encode_build(build, EncodeSettings(vae=str(wan_folder), text_encoder=None, device="cpu",
                                       dtype="bfloat16", compute_dtype="float32", batch=2, shard_pairs=20,
                                       num_frames=None, size=(48, 80), resize="crop"))   # small: fast
    cfg = load_wan_config("smoke", {"model": {"vae": None, "text_encoder": None}})   # no folders: latents only
    dataset = open_wan_dataset(build, cfg)
    assert "target_latents" in dataset[0] and "target" not in dataset[0]
    trainer = WanTrainer(cfg, 1, tmp_path / "run", dataset)
    z = trainer.latents(collate([dataset[0]]))
    assert z["camera"].shape == (1, 3, 12)   # ΔT per latent frame: the lateral offset, no rotation
    assert torch.equal(z["camera"][0], dataset[0]["rel_pose"][:, :3, :4].reshape(3, 12))
    losses = trainer.train(2)
    assert len(losses) == 2 and all(torch.isfinite(torch.tensor(losses)))
    assert trainer._vae is None   # never loaded: the cache holds the latents and the text embedding


def test_settings_the_model_cannot_read_are_refused_before_any_step(tmp_path):
    few = load_wan_config("smoke", {"model": {"max_frames": 2}})   # 9-frame clips: 3 latent frames
    with pytest.raises(ConfigError, match="need 3 .*set model.max_frames=3"):
        WanTrainer(few, 1, tmp_path / "a", LatentPairs())
    odd = load_wan_config("smoke", {"data": {"height": 40}})       # a 5-row latent grid, patches of 2
    with pytest.raises(ConfigError, match="multiples of 16x16"):
        WanTrainer(odd, 1, tmp_path / "b", LatentPairs())
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_stage2_trains_the_ffn_only_when_asked(tmp_path):
    WanTrainer(config(), 1, tmp_path / "s1", LatentPairs()).train(1)
    init = tmp_path / "s1" / "last.pt"
    paper = WanTrainer(config(), 2, tmp_path / "s2", LatentPairs(), init=init)
    beyond = WanTrainer(load_wan_config("smoke", {"model": {"stage2_ffn": True}}), 2, tmp_path / "s2f",
                        LatentPairs(), init=init)
    trained = {n for n, p in paper.model.named_parameters() if p.requires_grad}
    more = {n for n, p in beyond.model.named_parameters() if p.requires_grad}
    assert not any(".ffn." in n for n in trained) and more - trained == {
        n for n, _ in beyond.model.named_parameters() if ".ffn." in n}
    beyond.train(1)
    assert any(".ffn." in k for k in weights(tmp_path / "s2f" / "last.pt"))   # and its checkpoint holds them
