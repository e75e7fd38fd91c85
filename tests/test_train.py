"""Reference trainer: autoencoder, conditioning layout, rectified flow, two-stage training, resume,
sampling, configs and the ``paradrive train`` command."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml

from conftest import stage_params
from paradrive.errors import ConfigError
from paradrive.stages.manifest import build_manifest

from paradrive.train import (PatchAutoencoder, Trainer, VideoDiT, ModelConfig, euler_sample,
                             flow_matching_loss, interpolate, is_stage2_parameter, load_config,
                             load_for_sampling, sample_video, write_video)
from paradrive.data import to_unit_range
from paradrive.train.trainer import CONFIG_DIR, collate, open_dataset, parse_set, trainable_mask
from test_manifest import scenes_entry, write_clip_scene

FRAMES, HEIGHT, WIDTH = 5, 32, 48


def tiny_config(**train) -> dict:
    """The smoke config shrunk further: 5 frames of 32 x 48 -> 3 latent frames of 4 x 6 tokens."""
    cfg = load_config("smoke", {"data": {"num_frames": FRAMES, "height": HEIGHT, "width": WIDTH},
                                "model": {"dim": 32, "depth": 2, "heads": 2},
                                "train": {"batch_size": 2, "lr": 3e-3, "save_every": 0, **train}})
    return cfg


class PairTensors(torch.utils.data.Dataset):
    """Pairs shaped like ``paradrive.data.PairDataset`` samples: a smooth moving pattern as target,
    its sideways-shifted copy as source, a dimmed copy as condition, ΔT a lateral translation."""

    def __init__(self, n: int = 2, frames: int = FRAMES, height: int = HEIGHT, width: int = WIDTH):
        self.items = []
        ys, xs = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
        for i in range(n):
            offset = float(i % 2) * 2 - 1
            target = torch.stack([torch.stack([torch.sin(6 * xs + 0.3 * k + i), torch.cos(4 * ys - 0.2 * k),
                                               torch.sin(3 * (xs + ys) + i)]) for k in range(frames)]) * 0.8
            rel = torch.eye(4).repeat(frames, 1, 1)
            rel[:, 0, 3] = -offset  # a left shift of the source is a move along -x of the target camera
            self.items.append({"source": target.roll(3 * int(offset), dims=-1), "condition": 0.7 * target,
                               "target": target, "rel_pose": rel, "identity_pose": torch.eye(4).repeat(frames, 1, 1),
                               "intrinsics": torch.tensor([40.0, 40.0, width / 2, height / 2]),
                               "offset_m": offset, "condition_iteration": 100, "pair_id": f"pair/{i}", "prompt": ""})

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        return self.items[i]


def tiny_model(rendering: bool = False, seed: int = 0) -> VideoDiT:
    torch.manual_seed(seed)
    return VideoDiT(ModelConfig(latent_channels=12, dim=32, depth=2, heads=2, max_frames=8, rendering=rendering))


# -- autoencoder ---------------------------------------------------------------------------------
def test_patch_autoencoder_is_lossless_with_every_coefficient_kept():
    video = torch.rand(2, 4, 3, 16, 24) * 2 - 1
    codec = PatchAutoencoder((2, 8, 8))
    latents = codec.encode(video)
    assert latents.shape == (2, 2, 3 * 128, 2, 3)
    assert torch.allclose(codec.decode(latents), video, atol=1e-5)


def test_truncated_patch_autoencoder_keeps_the_patch_mean_as_first_channel():
    video = torch.rand(1, 2, 3, 8, 8) * 2 - 1
    codec = PatchAutoencoder((2, 8, 8), coefficients=1)
    latents = codec.encode(video)
    assert latents.shape == (1, 1, 3, 1, 1)
    assert torch.allclose(latents[0, 0, :, 0, 0], video[0].mean(dim=(0, 2, 3)), atol=1e-5)
    assert torch.allclose(codec.decode(latents), video.mean(dim=(1, 3, 4), keepdim=True).expand_as(video), atol=1e-5)


def test_causal_patch_autoencoder_gives_wan_latent_frame_counts():
    codec = PatchAutoencoder((4, 8, 8), coefficients=16, causal=True)
    assert codec.latent_shape(121, 480, 832) == (31, 48, 60, 104)
    groups = codec.frame_groups(121)
    assert len(groups) == 31 and groups[:3] == [0, 4, 8] and groups[-1] == 120
    video = torch.rand(1, 9, 3, 8, 8) * 2 - 1
    lossless = PatchAutoencoder((4, 8, 8), causal=True)
    assert torch.allclose(lossless.decode(lossless.encode(video)), video, atol=1e-5)


def test_another_video_encoder_plugs_in_by_import_path():
    from paradrive.train import VideoEncoder, make_autoencoder

    encoder = make_autoencoder({"kind": "paradrive.train.autoencoder:PatchAutoencoder",
                                "options": {"patch": [1, 4, 4], "coefficients": 2}})
    assert isinstance(encoder, VideoEncoder)
    assert encoder.latent_shape(3, 8, 8) == (3, 6, 2, 2)
    with pytest.raises(ValueError, match="package.module:Factory"):
        make_autoencoder({"kind": "vae3d"})


def test_patch_autoencoder_rejects_clips_that_do_not_divide():
    with pytest.raises(ValueError, match="num_frames"):
        PatchAutoencoder((2, 8, 8)).encode(torch.zeros(1, 5, 3, 16, 16))


# -- conditioning layout -------------------------------------------------------------------------
def test_target_half_carries_relative_pose_and_source_half_identity_pose_with_frame_embedding():
    model = tiny_model()
    b, f, c, h, w = 1, 3, 12, 2, 3
    x_t, x_s = torch.randn(b, f, c, h, w), torch.randn(b, f, c, h, w)
    rel = torch.eye(4).repeat(b, f, 1, 1)
    rel[..., 1, 3] = torch.tensor([1.0, 2.0, 3.0])  # a different ΔT per frame
    seen = {}

    def capture(module, args):
        seen["x"] = args[0].clone()

    model.blocks[0].register_forward_pre_hook(capture)
    model(x_t, torch.tensor([0.5]), x_s, rel)
    seq = seen["x"].view(b, 2 * f, h * w, -1)  # the DiT's input: (B, 2f·l, d) -> (B, 2f, l, d)

    with torch.no_grad():
        c_r = model.camera_encoder(rel)
        c_i = model.camera_encoder(torch.eye(4).repeat(b, f, 1, 1))
        e_f = model.frame_embed[:f]
        target_extra = seq[:, :f] - model.patchify(x_t)
        source_extra = seq[:, f:] - model.patchify(x_s)
    # every token of a frame gets the same vector: c_r + E_f for the target, c_I + E_f for the source
    assert torch.allclose(target_extra, (c_r + e_f)[:, :, None].expand_as(target_extra), atol=1e-5)
    assert torch.allclose(source_extra, (c_i + e_f)[:, :, None].expand_as(source_extra), atol=1e-5)
    assert not torch.allclose(c_r, c_i)


def test_changing_relative_pose_changes_only_the_target_half():
    model = tiny_model()
    x = torch.randn(1, 2, 12, 2, 3)
    rel_a = torch.eye(4).repeat(1, 2, 1, 1)
    rel_b = rel_a.clone()
    rel_b[..., 1, 3] = 2.0
    with torch.no_grad():
        a, b = model.embed_inputs(x, x, rel_a), model.embed_inputs(x, x, rel_b)
    assert not torch.allclose(a[:, :2], b[:, :2])
    assert torch.equal(a[:, 2:], b[:, 2:])


def test_condition_tokens_carry_relative_pose_and_frame_embedding():
    model = tiny_model(rendering=True)
    cond = torch.randn(1, 2, 12, 2, 3)
    rel = torch.eye(4).repeat(1, 2, 1, 1)
    rel[..., 0, 3] = 1.5
    with torch.no_grad():
        extra = model.embed_condition(cond, rel) - model.patchify(cond)
        expected = (model.camera_encoder(rel) + model.frame_embed[:2])[:, :, None]
    assert torch.allclose(extra, expected.expand_as(extra), atol=1e-5)


def test_fresh_stage2_model_computes_what_its_stage1_weights_do():
    stage1, stage2 = tiny_model(seed=1), tiny_model(rendering=True, seed=2)
    for p in stage1.parameters():  # make the stage-1 function non-trivial (zero-initialised heads)
        p.data.add_(0.05 * torch.randn_like(p))
    missing = stage2.load_state_dict(stage1.state_dict(), strict=False).missing_keys
    assert missing and all(is_stage2_parameter(k) for k in missing)
    x, cond = torch.randn(2, 1, 2, 12, 2, 3), torch.randn(1, 2, 12, 2, 3)
    rel, t = torch.eye(4).repeat(1, 2, 1, 1), torch.tensor([0.3])
    with torch.no_grad():
        assert torch.allclose(stage1(x[0], t, x[1], rel), stage2(x[0], t, x[1], rel, condition=cond), atol=1e-6)


# -- rectified flow ------------------------------------------------------------------------------
def test_flow_path_runs_from_noise_at_t0_to_data_at_t1():
    x0, x1 = torch.randn(2, 3), torch.randn(2, 3)
    assert torch.equal(interpolate(x0, x1, torch.zeros(2)), x0)
    assert torch.equal(interpolate(x0, x1, torch.ones(2)), x1)


def test_flow_loss_is_zero_for_the_true_velocity_x1_minus_x0():
    x1 = torch.randn(4, 2, 3, 2, 2)

    def oracle(x_t, t):  # the straight path's velocity, recovered from x_t and the known endpoint
        return (x1 - x_t) / (1 - t).view(-1, 1, 1, 1, 1)

    loss = flow_matching_loss(oracle, x1, torch.Generator().manual_seed(0))
    assert loss.item() < 1e-8
    assert flow_matching_loss(lambda x_t, t: torch.zeros_like(x_t), x1, torch.Generator().manual_seed(0)) > 0.5


def test_euler_sampler_follows_a_straight_flow_to_the_data_in_n_steps():
    x1, noise = torch.randn(1, 2, 3, 2, 2), torch.randn(1, 2, 3, 2, 2)
    calls = []

    def velocity(x, t):
        calls.append(float(t[0]))
        return (x1 - x) / (1 - t).view(-1, 1, 1, 1, 1)

    out = euler_sample(velocity, noise, steps=5)
    assert torch.allclose(out, x1, atol=1e-5)
    assert calls == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8])


def diffsynth_grid(shift: float, steps: int = 1000) -> tuple[np.ndarray, np.ndarray]:
    """DiffSynth-Studio's training schedule for Wan, written out from its published formula
    (FlowMatchScheduler(shift, sigma_min=0, extra_one_step=True).set_timesteps(1000, training=True)):
    sigmas = linspace(1, 0, steps + 1)[:-1], shifted to shift*s / (1 + (shift - 1)*s),
    timesteps = 1000 * sigmas, weight = bell - min(bell) scaled to sum to `steps`, with
    bell = exp(-2 ((timestep - steps/2) / steps)^2)."""
    sigmas = np.linspace(1.0, 0.0, steps + 1)[:-1]
    sigmas = shift * sigmas / (1 + (shift - 1) * sigmas)
    timesteps = sigmas * 1000
    bell = np.exp(-2 * ((timesteps - steps / 2) / steps) ** 2)
    weights = (bell - bell.min()) * (steps / (bell - bell.min()).sum())
    return timesteps, weights


@pytest.mark.parametrize("shift", [1.0, 5.0])
def test_recammaster_weighting_is_diffsynths_grid_and_bell_weight(shift):
    from paradrive.train.flow import draw, recammaster_grid

    timesteps, weights = diffsynth_grid(shift)
    t, w = recammaster_grid(shift)
    np.testing.assert_allclose(1000 * (1 - t.numpy()), timesteps, rtol=0, atol=1e-9)   # our t is 1 - sigma
    np.testing.assert_allclose(w.numpy(), weights, rtol=1e-12, atol=1e-12)
    assert w.mean().item() == pytest.approx(1.0) and float(w.min()) == 0.0
    # drawn times are grid points, each with its own weight, spread over the whole grid
    _, times, drawn = draw((4000, 1), torch.Generator().manual_seed(0), shift=shift, weighting="recammaster")
    sigma = 1 - times.double().numpy()
    k = np.abs(1000 * sigma[:, None] - timesteps[None, :]).argmin(axis=1)   # as DiffSynth's training_weight finds it
    np.testing.assert_allclose(1000 * sigma, timesteps[k], atol=1e-3)
    np.testing.assert_allclose(drawn.numpy(), weights[k], rtol=1e-6)
    assert len(np.unique(k)) > 900
    if shift == 5.0:   # the shift moves times toward the noise end: most sigmas above one half
        assert (sigma > 0.5).mean() > 0.75


def test_per_sample_draws_do_not_depend_on_the_batch_they_are_in():
    from paradrive.train.flow import draw

    gens = lambda: [torch.Generator().manual_seed(s) for s in (11, 12, 13)]   # noqa: E731
    whole = draw((3, 2, 4), gens(), weighting="recammaster", shift=5.0)
    parts = [draw((1, 2, 4), [g], weighting="recammaster", shift=5.0) for g in gens()]
    for got, pieces in zip(whole, zip(*parts)):
        assert torch.equal(got, torch.cat(pieces))


def test_weighted_loss_is_the_mean_of_each_samples_weighted_error():
    x1 = torch.randn(3, 2, 4)
    gens = [torch.Generator().manual_seed(s) for s in (1, 2, 3)]
    loss = flow_matching_loss(lambda x_t, t: torch.zeros_like(x_t), x1, gens, weighting="recammaster", shift=5.0)
    from paradrive.train.flow import draw

    x0, _, w = draw(x1.shape, [torch.Generator().manual_seed(s) for s in (1, 2, 3)], weighting="recammaster",
                    shift=5.0)
    expected = ((x1 - x0) ** 2).mean(dim=(1, 2)) * w
    torch.testing.assert_close(loss, expected.mean())


# -- training --------------------------------------------------------------------------------------
def test_stage1_loss_falls_when_overfitting_a_fixed_batch(tmp_path):
    data = PairTensors(2)
    trainer = Trainer(tiny_config(), 1, tmp_path / "stage1", data)
    batch = collate([data[0], data[1]])
    before = trainer.evaluate(batch)
    losses = trainer.train(40)
    k = 8
    first, last = sum(losses[:k]) / k, sum(losses[-k:]) / k
    assert last < 0.6 * first, losses
    assert trainer.evaluate(batch) < 0.6 * before  # same noise and times before and after


def test_stage2_loss_falls_and_only_new_modules_train(tmp_path):
    cfg, data = tiny_config(), PairTensors(2)
    Trainer(cfg, 1, tmp_path / "stage1", data).train(20)
    trainer = Trainer(cfg, 2, tmp_path / "stage2", data, init=tmp_path / "stage1" / "last.pt")
    before = {k: v.clone() for k, v in trainer.model.state_dict().items()}
    frozen = [n for n, p in trainer.model.named_parameters() if not p.requires_grad]
    trained = [n for n, p in trainer.model.named_parameters() if p.requires_grad]
    assert frozen and trained and all(is_stage2_parameter(n) for n in trained)
    assert {n.split(".")[2] for n in trained} == {"render_norm", "render_attn", "cross_norm", "cross_attn"}
    stage1 = torch.load(tmp_path / "stage1" / "last.pt", weights_only=False)["model"]
    assert all(torch.equal(before[n], stage1[n]) for n in frozen)  # started from the stage-1 weights

    batch = collate([data[0], data[1]])
    start = trainer.evaluate(batch)
    trainer.train(30)
    after = trainer.model.state_dict()
    assert all(torch.equal(before[n], after[n]) for n in frozen), "a stage-1 parameter moved in stage 2"
    assert all(not torch.equal(before[n], after[n]) for n in trained), \
        [n for n in trained if torch.equal(before[n], after[n])]
    assert trainer.evaluate(batch) < 0.95 * start  # the condition rendering lowers the loss further


def test_uint8_batches_are_normalised_by_the_trainer_like_float_ones(tmp_path):
    data = PairTensors(2)
    trainer = Trainer(tiny_config(), 1, tmp_path / "run", data)
    batch = collate([data[0], data[1]])
    videos = ("source", "condition", "target")
    as_bytes = {**batch, **{k: ((batch[k] + 1) * 127.5).round().to(torch.uint8) for k in videos}}
    as_float = {**batch, **{k: to_unit_range(as_bytes[k]) for k in videos}}
    z_bytes, z_float = trainer.latents(as_bytes), trainer.latents(as_float)
    assert z_bytes.keys() == z_float.keys()
    assert all(torch.equal(z_bytes[k], z_float[k]) for k in z_float)
    assert trainer.evaluate(as_bytes) == trainer.evaluate(as_float)
    # a uint8 batch read as if it were already in [-1, 1] would encode to other latents
    assert not torch.equal(trainer.encoder.encode(as_bytes["target"].float()), z_float["target"])


def test_uint8_batches_are_normalised_on_the_trainers_device(tmp_path):
    from simulated_device import DEVICE, simulated_device, to_cpu

    data = PairTensors(2)
    batch = collate([data[0], data[1]])
    as_bytes = {**batch, "target": ((batch["target"] + 1) * 127.5).round().to(torch.uint8)}
    on_cpu = Trainer(tiny_config(), 1, tmp_path / "cpu", data).latents(as_bytes)["target"]
    with simulated_device():
        trainer = Trainer({**tiny_config(), "device": str(DEVICE)}, 1, tmp_path / "dev", data)
        on_device = trainer.latents(as_bytes)["target"]  # bytes moved, normalised on the device
        assert on_device.device == DEVICE
        assert torch.equal(to_cpu(on_device), on_cpu)


def test_the_trainer_reads_a_build_as_uint8_and_trains_on_it(tmp_path):
    scene = write_clip_scene(tmp_path / "data", "synthetic-t", clips=("front",), offsets=(1.0, -1.0),
                             conditions=(100,), num_frames=FRAMES, width=WIDTH, height=HEIGHT)
    build_manifest(tmp_path / "b", [scenes_entry(scene)], stage_params("manifest", {}))
    cfg = tiny_config()
    cfg["data"]["num_workers"] = 0
    dataset = open_dataset(tmp_path / "b", cfg)
    sample = dataset[0]
    assert sample["target"].dtype == torch.uint8 and sample["target"].shape == (FRAMES, 3, HEIGHT, WIDTH)
    losses = Trainer(cfg, 1, tmp_path / "run", dataset).train(2)
    assert len(losses) == 2 and all(loss == loss and loss < 10 for loss in losses)


def test_stage2_without_stage1_weights_is_refused(tmp_path):
    with pytest.raises(ValueError, match="--init"):
        Trainer(tiny_config(), 2, tmp_path / "stage2", PairTensors(2))


def test_stage1_can_train_only_the_papers_modules():
    model = tiny_model()
    mask = trainable_mask(model, 1, ["self_attn", "camera_encoder", "frame_embed"])
    trained = {n for n, on in mask.items() if on}
    assert "frame_embed" in trained and "camera_encoder.net.0.weight" in trained
    assert "blocks.0.self_attn.q.weight" in trained
    assert "blocks.0.ffn.0.weight" not in trained and "patch_embed.weight" not in trained


def test_resumed_run_continues_exactly_like_an_uninterrupted_one(tmp_path):
    cfg = tiny_config(save_every=3)
    data = PairTensors(3)  # 3 pairs, batch 2: epochs of one batch, so resume crosses epochs too
    straight = Trainer(cfg, 1, tmp_path / "straight", data)
    full = straight.train(7)

    first = Trainer(cfg, 1, tmp_path / "resumed", data).train(3)
    resumed = Trainer(cfg, 1, tmp_path / "resumed", data)  # picks up last.pt
    assert resumed.step == 3
    rest = resumed.train(7)
    assert first + rest == full
    for (name, a), b in zip(straight.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.equal(a, b), name
    steps = [json.loads(l)["step"] for l in (tmp_path / "resumed" / "metrics.jsonl").read_text().splitlines()]
    assert steps == list(range(1, 8))


def test_resume_refuses_a_checkpoint_of_another_model(tmp_path):
    Trainer(tiny_config(), 1, tmp_path / "run", PairTensors(2)).train(1)
    other = load_config("smoke", {"data": {"num_frames": FRAMES, "height": HEIGHT, "width": WIDTH},
                                  "train": {"batch_size": 2}})
    with pytest.raises(ValueError, match="model"):
        Trainer(other, 1, tmp_path / "run", PairTensors(2))


def test_sample_writes_a_video_with_the_clips_frame_count(tmp_path):
    import av
    Trainer(tiny_config(), 1, tmp_path / "stage1", PairTensors(2)).train(2)
    model, encoder, _, stage = load_for_sampling(tmp_path / "stage1" / "last.pt", device="cpu")
    assert stage == 1 and not model.training
    video = sample_video(model, encoder, PairTensors(1)[0], steps=3)
    assert video.shape == (FRAMES, 3, HEIGHT, WIDTH) and video.abs().max() <= 1
    path = write_video(tmp_path / "sample.mp4", video, fps=10)
    with av.open(str(path)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == FRAMES and frames[0].shape == (HEIGHT, WIDTH, 3)


# -- configs ---------------------------------------------------------------------------------------
def test_every_training_setting_is_declared_with_a_default_and_a_doc():
    doc = yaml.safe_load((CONFIG_DIR / "default.yaml").read_text())

    def leaves(node, where):
        for key, value in node.items():
            if isinstance(value, dict) and "default" in value:
                yield f"{where}.{key}", value
            else:
                yield from leaves(value, f"{where}.{key}")

    found = list(leaves(doc["params"], "default"))
    assert len(found) > 20
    for where, leaf in found:
        assert isinstance(leaf.get("doc"), str) and leaf["doc"].strip(), f"{where} has no doc"


def test_the_smoke_profile_and_overrides_are_checked_like_stage_parameters():
    cfg = load_config("smoke")   # a profile: values only, each a known setting
    assert cfg["model"]["dim"] == 64 and cfg["train"]["lr"] == 1e-3
    with pytest.raises(ConfigError, match="model.dim.*has type str, expected int"):
        load_config("smoke", parse_set(["model.dim=wide"]))
    with pytest.raises(ConfigError, match="is a section"):
        load_config("smoke", parse_set(["model=3"]))


def test_default_config_holds_the_papers_schedule():
    cfg = load_config()
    assert (cfg["data"]["num_frames"], cfg["data"]["height"], cfg["data"]["width"]) == (121, 480, 832)
    assert cfg["train"]["steps"] == 6000 and cfg["train"]["lr"] == 1e-4 and cfg["train"]["batch_size"] == 1
    assert cfg["flow"]["schedule"] == "uniform"


def test_unknown_override_is_named():
    with pytest.raises(ConfigError, match="modle"):
        load_config("smoke", parse_set(["modle.dim=8"]))
    assert load_config("smoke", parse_set(["model.dim=96"]))["model"]["dim"] == 96


# -- end to end ------------------------------------------------------------------------------------
@pytest.mark.slow
def test_train_command_runs_both_stages_on_a_smoke_build_and_samples(smoke_build, tmp_path):
    import av
    import typer
    from typer.testing import CliRunner

    from paradrive.commands.train import register

    app = typer.Typer()  # the command as paradrive.cli registers it, without the other commands
    register(app)
    app.command("noop", hidden=True)(lambda: None)  # keeps 'train' a sub-command, as in paradrive

    build, out = str(smoke_build["build_dir"]), tmp_path / "run"
    common = ["train", "--build", build, "--config", "smoke", "--out", str(out), "--steps", "6"]
    runner = CliRunner()
    r1 = runner.invoke(app, common + ["--stage", "1"])
    assert r1.exit_code == 0, r1.output
    r2 = runner.invoke(app, common + ["--stage", "2", "--sample", str(tmp_path / "s.mp4"), "--pair", "1"])
    assert r2.exit_code == 0, r2.output

    for stage in (1, 2):
        lines = (out / f"stage{stage}" / "metrics.jsonl").read_text().splitlines()
        assert [json.loads(l)["step"] for l in lines] == list(range(1, 7))
    stage1 = torch.load(out / "stage1" / "last.pt", weights_only=False)["model"]
    stage2 = torch.load(out / "stage2" / "last.pt", weights_only=False)["model"]
    assert all(torch.equal(stage1[k], stage2[k]) for k in stage1)  # stage 1 frozen in stage 2
    assert any(is_stage2_parameter(k) for k in stage2)
    with av.open(str(tmp_path / "s.mp4")) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    cfg = load_config("smoke")
    assert len(frames) == cfg["data"]["num_frames"]
    assert frames[0].shape == (cfg["data"]["height"], cfg["data"]["width"], 3)

    again = runner.invoke(app, common + ["--stage", "2"])  # a finished run resumes and stops at once
    assert again.exit_code == 0 and "already at step 6" in again.output
