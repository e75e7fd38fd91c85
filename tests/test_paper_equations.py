"""The paper's equations, term by term, on the tiny Wan model (paradrive.wan.recam), and the camera
conventions against ReCamMaster's own formula.

Stage 1 reads x_i = Cat(x_t + c_r + E_f, x_s + c_I + E_f) and stage 2 adds the condition stream
x̄_gs = x_gs + c_r + E_f: one frame embedding E_f of f rows shared by the three, and the same
camera term c_r on the condition as on the target. Stage 2's cross attention starts from Wan2.1's
(the block's text cross attention), its rendering attention from Wan2.1's self-attention.

The camera input's sign: for a +2 m pair (the source 2 m to the target's left) ReCamMaster's
loader gives the target camera relative to the source's first frame, x = +2 m; ``relative`` (ΔT)
is the other sign, ``recammaster_per_frame`` ReCamMaster's sign without the ego's motion."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from paradrive import geometry
from paradrive.train.trainer import collate
from paradrive.train.wan import WanTrainer, load_wan_config
from paradrive.wan.recam import ReCamDrivingWan, make_tiny_transformer
from test_wan_train import LatentPairs

B, C, T, H, W = 2, 16, 2, 6, 10
TOKENS = (H // 2) * (W // 2)   # tokens per latent frame: the tiny transformer's 2x2 patch


def tiny(stage: int = 2, seed: int = 0, **options) -> ReCamDrivingWan:
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return ReCamDrivingWan(make_tiny_transformer(seed), rendering=stage == 2, max_frames=T, **options)


def inputs(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)

    def draw(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=g, device="cpu")

    return {"x_t": draw(B, C, T, H, W), "t": torch.rand(B, generator=g, device="cpu"),
            "source_latents": draw(B, C, T, H, W), "camera": draw(B, T, 12), "text_embedding": draw(B, 5, 32),
            "condition_latents": draw(B, C, T, H, W)}


def capture(model: ReCamDrivingWan, x: dict, modules: dict) -> dict[str, torch.Tensor]:
    """The first positional input each of ``modules`` (name -> module) receives in one forward."""
    seen: dict[str, torch.Tensor] = {}
    hooks = [module.register_forward_pre_hook(lambda _m, args, name=name: seen.setdefault(name, args[0].detach()))
             for name, module in modules.items()]
    try:
        with torch.no_grad():
            model(x["x_t"], x["t"], x["source_latents"], x["camera"], x["text_embedding"], x["condition_latents"])
    finally:
        for hook in hooks:
            hook.remove()
    return seen


def patch_tokens(model: ReCamDrivingWan, latents: torch.Tensor) -> torch.Tensor:
    """Wan's patch embedding alone: (B, C, T, h, w) -> (B, T * l, dim)."""
    with torch.no_grad():
        return model.transformer.patch_embedding(latents).flatten(2).transpose(1, 2)


def frame(tokens: torch.Tensor, k: int) -> torch.Tensor:
    """The l tokens of latent frame k of a token sequence (B, N, dim)."""
    return tokens[:, k * TOKENS:(k + 1) * TOKENS]


# -- E_f -------------------------------------------------------------------------------------------
def test_target_source_and_condition_frame_k_get_the_same_row_of_one_frame_embedding():
    model, x = tiny(), inputs()
    assert model.frame_embed.shape == (T, model.dim)   # f rows: the latent frames of one clip
    with torch.no_grad():
        model.frame_embed.normal_()
    block, add = model.transformer.blocks[0], model.recam[0]
    seen = capture(model, x, {"joined": block.norm1, "condition": add.render_norm})
    joined = seen["joined"] - patch_tokens(model, torch.cat([x["x_t"], x["source_latents"]], dim=2))
    condition = seen["condition"] - patch_tokens(model, x["condition_latents"])
    for k in range(T):
        row = model.frame_embed[k].detach().expand(B, TOKENS, -1)
        torch.testing.assert_close(frame(joined, k), row)            # target frame k: row k
        torch.testing.assert_close(frame(joined, T + k), row)        # source frame k: row k
        torch.testing.assert_close(frame(condition, k), row)         # condition frame k: row k
    assert not torch.allclose(frame(joined, 0), frame(joined, 1))    # and frames are told apart


def test_the_per_half_frame_embedding_beyond_the_paper_gives_the_source_rows_after_the_target():
    model, x = tiny(frame_embedding="per_half"), inputs()
    assert model.frame_embed.shape == (2 * T, model.dim)
    with torch.no_grad():
        model.frame_embed.normal_()
    seen = capture(model, x, {"joined": model.transformer.blocks[0].norm1, "condition": model.recam[0].render_norm})
    joined = seen["joined"] - patch_tokens(model, torch.cat([x["x_t"], x["source_latents"]], dim=2))
    condition = seen["condition"] - patch_tokens(model, x["condition_latents"])
    for k in range(T):
        torch.testing.assert_close(frame(joined, T + k), model.frame_embed[T + k].detach().expand(B, TOKENS, -1))
        torch.testing.assert_close(frame(condition, k), model.frame_embed[k].detach().expand(B, TOKENS, -1))
    with pytest.raises(ValueError, match="frame_embedding='both'"):
        tiny(frame_embedding="both")


# -- c_r -------------------------------------------------------------------------------------------
def test_the_condition_tokens_carry_the_same_camera_term_as_the_target_and_the_source_the_identitys():
    model, x = tiny(), inputs()
    with torch.no_grad():
        for add in model.recam:
            add.cam_encoder.weight.normal_()
            add.cam_encoder.bias.normal_()
    block, add = model.transformer.blocks[0], model.recam[0]
    modules = {"attn": block.attn1, "render_in": add.render_norm, "render": add.render_attn}
    moved = torch.randn(B, T, 12, generator=torch.Generator().manual_seed(9), device="cpu")
    other = {**x, "camera": x["camera"] + moved}
    a, b = capture(model, x, modules), capture(model, other, modules)
    weight, bias = add.cam_encoder.weight.detach(), add.cam_encoder.bias.detach()
    for k in range(T):
        c_r = (x["camera"][:, k] @ weight.T + bias)[:, None].expand(B, TOKENS, -1)
        change = ((other["camera"] - x["camera"])[:, k] @ weight.T)[:, None].expand(B, TOKENS, -1)
        # the condition's attention input: its normalised tokens plus c_r of frame k
        torch.testing.assert_close(frame(a["render"], k), add.render_norm(frame(a["render_in"], k)) + c_r)
        # a change of the target camera moves the target's and the condition's term alike ...
        torch.testing.assert_close(frame(b["attn"], k) - frame(a["attn"], k), change, rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(frame(b["render"], k) - frame(a["render"], k), change, rtol=1e-4, atol=1e-5)
        # ... and leaves the source's c_I = E_cam(I) as it was
        torch.testing.assert_close(frame(b["attn"], T + k), frame(a["attn"], T + k))


# -- stage 2's initialisation ----------------------------------------------------------------------
def _same(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_the_cross_attention_starts_as_the_wan_blocks_cross_attention_and_the_rendering_as_its_self_attention():
    model = tiny()
    for block, add in zip(model.transformer.blocks, model.recam):
        assert _same(add.cross_attn, block.attn2) and _same(add.cross_norm, block.norm2)
        assert _same(add.render_attn, block.attn1)
        assert add.cross_attn.to_q.weight.data_ptr() != block.attn2.to_q.weight.data_ptr()   # copies, not shared
        q = torch.randn(B, 7, model.dim, generator=torch.Generator().manual_seed(1), device="cpu")
        context = torch.randn(B, 11, model.dim, generator=torch.Generator().manual_seed(2), device="cpu")
        with torch.no_grad():
            torch.testing.assert_close(add.cross_attn(q, context, None, None), block.attn2(q, context, None, None))
    zeroed = tiny(cross_attn_zero_out=True)   # beyond the paper: the output projection zeroed, the rest Wan's
    for block, add in zip(zeroed.transformer.blocks, zeroed.recam):
        out = add.cross_attn.to_out[0]
        assert not out.weight.any() and not out.bias.any()
        wan, ours = block.attn2.state_dict(), add.cross_attn.state_dict()
        assert all(torch.equal(ours[k], wan[k]) for k in wan if not k.startswith("to_out."))


def test_a_stage2_run_starts_its_new_attentions_from_the_base_not_from_stage1s_training(tmp_path):
    cfg = load_wan_config("smoke", {"train": {"lr": 0.05}})
    WanTrainer(cfg, 1, tmp_path / "s1", LatentPairs()).train(2)
    stage2 = WanTrainer(cfg, 2, tmp_path / "s2", LatentPairs(), init=tmp_path / "s1" / "last.pt")
    base = make_tiny_transformer(int(cfg["seed"]))   # Wan2.1's weights of the smoke run
    for i, add in enumerate(stage2.wan.recam):
        trained = stage2.wan.transformer.blocks[i]
        assert not _same(trained.attn1, base.blocks[i].attn1)        # stage 1 trained the self-attention
        assert _same(add.render_attn, base.blocks[i].attn1)           # the rendering attention is Wan2.1's
        assert _same(add.cross_attn, base.blocks[i].attn2) and _same(add.cross_norm, base.blocks[i].norm2)


# -- the camera conventions ------------------------------------------------------------------------
FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])   # OpenCV axes of a forward camera


def drive(lateral: float, frames: int = 9) -> np.ndarray:
    """c2w (F, 4, 4) of a forward camera 1.5 m up, driving 0.5 m a frame along world x, ``lateral``
    metres to the left (world y)."""
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, :3, :3] = FORWARD
    poses[:, :3, 3] = [[0.5 * k, lateral, 1.5] for k in range(frames)]
    return poses


def recammaster_reference(source_c2w: np.ndarray, target_c2w: np.ndarray, every: int = 4) -> np.ndarray:
    """ReCamMaster's camera input from its definition: per kept frame k, the target camera in the
    coordinates of the condition (source) camera at the first frame, inv(c2w_source[0]) c2w_target[k]."""
    return np.stack([np.linalg.inv(source_c2w[0]) @ target_c2w[k] for k in range(0, len(target_c2w), every)])


def test_a_2m_pairs_translation_sign_under_each_convention_against_recammasters_formula():
    from paradrive.data import recammaster_camera

    target, source = drive(0.0), drive(2.0)   # a +2 m pair: the source 2 m to the left
    reference = recammaster_reference(source, target)
    assert reference[:, 0, 3].tolist() == [2.0, 2.0, 2.0]            # ReCamMaster: +2 m
    assert reference[:, 2, 3].tolist() == [0.0, 2.0, 4.0]            # and the ego's own motion

    rel = geometry.relative_pose(target, source)
    relative = rel[::4, :3, :4].reshape(-1, 12)
    np.testing.assert_allclose(relative[:, 3], -reference[:, 0, 3])   # relative: the other sign
    per_frame = geometry.recammaster_per_frame_camera(rel, every=4)
    np.testing.assert_allclose(per_frame[:, 3], reference[:, 0, 3])   # recammaster_per_frame: its sign ...
    np.testing.assert_allclose(per_frame[:, 11], 0.0)                 # ... without the ego's motion
    np.testing.assert_allclose(per_frame[0], reference[0, :3, :4].reshape(12), atol=1e-6)
    np.testing.assert_allclose(geometry.target_in_source(target, source)[::4, :3, :4].reshape(-1, 12), per_frame,
                               atol=1e-6)
    np.testing.assert_allclose(recammaster_camera(target, source), reference[:, :3, :4].reshape(-1, 12), atol=1e-6)


class PairOf2m(LatentPairs):
    """The +2 m pair as a latent sample (two latent frames: video frames 0 and 4): ``rel_pose``
    per latent frame and ``camera`` in ReCamMaster's own form, as a latent cache holds them."""

    def __getitem__(self, i: int) -> dict:
        target, source = drive(0.0, 5), drive(2.0, 5)
        rel = geometry.relative_pose(target, source)[::4]
        return {**super().__getitem__(i), "rel_pose": torch.tensor(rel, dtype=torch.float32, device="cpu"),
                "camera": torch.tensor(recammaster_reference(source, target)[:, :3, :4].reshape(-1, 12),
                                       dtype=torch.float32, device="cpu")}


@pytest.mark.parametrize("camera, x", [("relative", -2.0), ("recammaster_per_frame", 2.0), ("recammaster", 2.0)])
def test_the_trainer_feeds_each_conventions_sign(camera, x, tmp_path):
    trainer = WanTrainer(load_wan_config("smoke", {"model": {"camera": camera}}), 1, tmp_path / camera, PairOf2m())
    got = trainer.latents(collate([PairOf2m()[0]]))["camera"]
    assert got[0, :, 3].tolist() == [x, x]
    assert got[0, :, 11].tolist() == ([0.0, 2.0] if camera == "recammaster" else [0.0, 0.0])   # ego motion
    pixels = {"rel_pose": torch.tensor(geometry.relative_pose(drive(0.0, 5), drive(2.0, 5))[None],
                                       dtype=torch.float32, device="cpu")}
    if camera != "recammaster":   # a pixel sample's rel_pose has every video frame: frames 0 and 4 are read
        torch.testing.assert_close(trainer._camera(pixels, cached=False), got)


def _recammaster_file(model: ReCamDrivingWan, path) -> None:
    """A ReCamMaster checkpoint for the tiny model under DiffSynth's names (distinct values)."""
    from safetensors.torch import save_file

    g, dim, state = torch.Generator().manual_seed(4), model.dim, {}
    for i in range(len(model.transformer.blocks)):
        state[f"blocks.{i}.cam_encoder.weight"] = 0.01 * torch.randn(dim, 12, generator=g, device="cpu")
        state[f"blocks.{i}.cam_encoder.bias"] = torch.zeros(dim, device="cpu")
        state[f"blocks.{i}.projector.weight"] = torch.eye(dim, device="cpu")
        state[f"blocks.{i}.projector.bias"] = torch.zeros(dim, device="cpu")
    save_file(state, str(path))


def test_loading_recammaster_chooses_its_sign_and_the_run_records_it_through_stage_2(tmp_path):
    import yaml

    weights = tmp_path / "recammaster.safetensors"
    _recammaster_file(tiny(1), weights)
    stage1 = WanTrainer(load_wan_config("smoke", {"model": {"recammaster": str(weights)}}), 1, tmp_path / "s1",
                        PairOf2m())
    assert stage1.config["model"]["camera"] == "recammaster_per_frame"
    assert stage1.latents(collate([PairOf2m()[0]]))["camera"][0, :, 3].tolist() == [2.0, 2.0]
    stage1.train(1)
    assert torch.load(tmp_path / "s1" / "last.pt", weights_only=True)["config"]["model"]["camera"] == \
        "recammaster_per_frame"
    assert yaml.safe_load((tmp_path / "s1" / "config.yaml").read_text())["model"]["camera"] == "recammaster_per_frame"
    # stage 2 with the plain config (auto, no ReCamMaster file) keeps the form stage 1 trained with
    stage2 = WanTrainer(load_wan_config("smoke"), 2, tmp_path / "s2", PairOf2m(), init=tmp_path / "s1" / "last.pt")
    assert stage2.config["model"]["camera"] == "recammaster_per_frame"
    stage2.train(1)
    assert yaml.safe_load((tmp_path / "s2" / "config.yaml").read_text())["model"]["camera"] == "recammaster_per_frame"
    # an explicit other form is refused: the frozen camera encoder was trained on this one
    with pytest.raises(ValueError, match="model settings .* differ"):
        WanTrainer(load_wan_config("smoke", {"model": {"camera": "relative"}}), 2, tmp_path / "s2r", PairOf2m(),
                   init=tmp_path / "s1" / "last.pt")
    # relative with ReCamMaster's weights is allowed, with a note on the sign
    opposite = WanTrainer(load_wan_config("smoke", {"model": {"recammaster": str(weights), "camera": "relative"}}),
                          1, tmp_path / "s1r", PairOf2m())
    assert any("opposite sign" in note for note in opposite.notes)


def test_the_adapters_per_frame_pose_format_is_the_inverse_relative_pose(smoke_build):
    from paradrive.data import PairDataset

    plain = PairDataset(smoke_build["build_dir"])
    ours = PairDataset(smoke_build["build_dir"], pose_format="recammaster_per_frame")
    front = [i for i in range(len(plain)) if plain.row(i)["camera"] == "front"]
    others = [i for i in range(len(plain)) if plain.row(i)["camera"] != "front"]
    assert front, "the smoke build has a front camera"
    for i in front[:1] + front[-1:] + others[:1]:
        sample, rel = ours[i], plain[i]["rel_pose"].double().numpy()
        expected = np.stack([np.linalg.inv(rel[k])[:3, :4].reshape(12) for k in range(0, len(rel), 4)])
        np.testing.assert_allclose(sample["camera"].numpy(), expected, atol=1e-5)
        if i in front:   # a forward camera: the target sits +offset along the source camera's x
            assert sample["offset_m"] != 0
            np.testing.assert_allclose(sample["camera"][:, 3].numpy(), sample["offset_m"], atol=1e-3)


def test_a_checkpoint_of_the_earlier_per_sequence_frame_embedding_is_refused_in_one_line(tmp_path):
    from paradrive.train.generate import load_generator

    WanTrainer(load_wan_config("smoke"), 1, tmp_path / "s1", LatentPairs()).train(1)
    old = tmp_path / "old.pt"
    ckpt = torch.load(tmp_path / "s1" / "last.pt", weights_only=True)
    torch.save({**ckpt, "format": "paradrive-train-wan/2"}, old)
    with pytest.raises(ValueError, match=r"^--init .*old.pt: written by an earlier .*train the stages again$"):
        WanTrainer(load_wan_config("smoke"), 2, tmp_path / "s2", LatentPairs(), init=old)
    with pytest.raises(ValueError, match=r"^--checkpoint .*old.pt: written by an earlier"):
        load_generator(old, {})
