"""ReCamDriving on diffusers' Wan2.1 transformer (paradrive.wan.recam), with tiny random weights:
the camera and frame inputs start neutral, stage 2 starts from Wan2.1's cross attention (or, with
its output zeroed, where stage 1 ended), each stage trains exactly the paper's parameters, and
ReCamMaster's weights land where they belong. The paper's equations term by term are in
tests/test_paper_equations.py."""

from __future__ import annotations

import pytest
import torch

from paradrive.errors import ConfigError
from paradrive.wan.recam import (ReCamDrivingWan, load_recammaster, load_transformer, make_tiny_transformer,
                                 map_recammaster_state_dict, recammaster_key, stage_parameter_names,
                                 trainable_parameters)

B, C, T, H, W = 2, 16, 2, 6, 10


def inputs(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {"x_t": torch.randn(B, C, T, H, W, generator=g), "t": torch.rand(B, generator=g),
            "source_latents": torch.randn(B, C, T, H, W, generator=g),
            "camera": torch.randn(B, T, 12, generator=g), "text_embedding": torch.randn(B, 5, 32, generator=g),
            "condition_latents": torch.randn(B, C, T, H, W, generator=g)}


def model(stage: int = 1, seed: int = 0, **options) -> ReCamDrivingWan:
    """The tiny model on the transformer drawn from ``seed`` (``options``: ReCamDrivingWan's)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return ReCamDrivingWan(make_tiny_transformer(seed), rendering=stage == 2, max_frames=T, **options)


def run(m: ReCamDrivingWan, x: dict) -> torch.Tensor:
    cond = x["condition_latents"] if m.rendering else None
    return m(x["x_t"], x["t"], x["source_latents"], x["camera"], x["text_embedding"], cond)


def test_a_fresh_stage1_model_is_the_pretrained_wan_transformer_on_target_then_source_frames():
    """Camera encoder zero, projector identity, frame embedding zero: the pretrained model's own
    prediction, read at Wan's timestep 1000 * (1 - t) and turned from noise - data to data - noise."""
    m, x = model(), inputs()
    with torch.no_grad():
        ours = run(m, x)
        wan = m.transformer(torch.cat([x["x_t"], x["source_latents"]], dim=2), 1000 * (1 - x["t"]),
                            x["text_embedding"], return_dict=False)[0]
    torch.testing.assert_close(ours, -wan[:, :, :T], rtol=1e-5, atol=1e-5)


def test_the_camera_reaches_the_target_prediction_once_its_encoder_is_trained():
    m, x = model(), inputs()
    with torch.no_grad():
        before = run(m, {**x, "camera": x["camera"] + 1.0})
        assert torch.equal(before, run(m, x))   # zero-initialised: the camera changes nothing yet
        for add in m.recam:
            add.cam_encoder.weight.normal_()
        assert not torch.allclose(run(m, {**x, "camera": x["camera"] + 1.0}), run(m, x))


def test_poses_enter_the_camera_encoder_in_float32_under_bf16_autocast():
    add = model().recam[0]
    with torch.no_grad():
        add.cam_encoder.weight.normal_()
        camera = torch.full((1, 1, 12), 100.25)   # bf16 has no 100.25 (its spacing at 100 m is 0.5 m)
        exact = torch.nn.functional.linear(camera, add.cam_encoder.weight, add.cam_encoder.bias)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            got = add.camera(camera, torch.float32)
    torch.testing.assert_close(got, exact)


@pytest.mark.parametrize("zero_out", [False, True])
def test_a_fresh_stage2_model_reads_the_rendering_from_the_start_unless_its_cross_output_is_zeroed(zero_out):
    """The paper's start (the cross attention a copy of Wan2.1's) sees the rendering at once; the
    zeroed output projection (beyond the paper) computes exactly what the stage-1 weights did."""
    stage1, x = model(1), inputs()
    with torch.no_grad():
        for p in stage1.parameters():
            p.add_(0.01 * torch.randn_like(p))   # a trained stage-1 model, not the initial one
        stage2 = model(2, cross_attn_zero_out=zero_out)
        stage2.load_state_dict(stage1.state_dict(), strict=False)
        if zero_out:
            torch.testing.assert_close(run(stage2, x), run(stage1, x))
        else:
            assert not torch.allclose(run(stage2, x), run(stage1, x), atol=1e-3)
            other = {**x, "condition_latents": x["condition_latents"].flip(-1)}
            assert not torch.allclose(run(stage2, other), run(stage2, x), atol=1e-3)


def _expected(m: ReCamDrivingWan, stage: int, ffn: bool = False) -> set[str]:
    """The paper's sets, spelled out module by module for the tiny two-block model (``ffn``: stage
    2 with every block's FFN too, beyond the paper)."""
    blocks = range(len(m.transformer.blocks))
    if stage == 1:
        names = {"frame_embed"}
        for i in blocks:
            names |= {f"transformer.blocks.{i}.attn1.{p}" for p in (
                "to_q.weight", "to_q.bias", "to_k.weight", "to_k.bias", "to_v.weight", "to_v.bias",
                "to_out.0.weight", "to_out.0.bias", "norm_q.weight", "norm_k.weight")}
            names |= {f"recam.{i}.{mod}.{p}" for mod in ("cam_encoder", "projector") for p in ("weight", "bias")}
        return names
    names = set()
    for i in blocks:
        names |= {n for n, _ in m.named_parameters()
                  if n.startswith((f"recam.{i}.render_attn.", f"recam.{i}.cross_attn.",
                                   f"recam.{i}.render_norm.", f"recam.{i}.cross_norm."))
                  or (ffn and n.startswith(f"transformer.blocks.{i}.ffn."))}
    return names


@pytest.mark.parametrize("stage, ffn", [(1, False), (2, False), (2, True)])
def test_each_stage_trains_exactly_the_papers_parameters_and_nothing_else(stage, ffn):
    m, x = model(stage), inputs()
    expected = _expected(m, stage, ffn)
    assert stage_parameter_names(m, stage, ffn) == expected
    if stage == 2:   # nothing of stage 1 nor of the rest of the transformer
        assert not any(".attn1." in n or "cam_encoder" in n or "projector" in n or n == "frame_embed"
                       for n in expected)
        # per block: 2 attentions (10 tensors each), 2 norms (2 each); with ffn its 4 tensors too
        assert len(expected) == 2 * (2 * 10 + 2 * 2 + (4 if ffn else 0))
        assert any(".ffn." in n for n in expected) == ffn
    params = trainable_parameters(m, stage, ffn)
    before = {n: p.detach().clone() for n, p in m.named_parameters()}
    optimizer = torch.optim.AdamW(params, lr=1e-2)
    for _ in range(2):   # after one step the zero-initialised outputs let every gradient through
        optimizer.zero_grad(set_to_none=True)
        run(m, x).square().mean().backward()
        got = {n for n, p in m.named_parameters() if p.grad is not None}
        optimizer.step()
    assert got == expected
    assert all(float(p.grad.abs().sum()) > 0 for n, p in m.named_parameters() if n in expected), \
        [n for n, p in m.named_parameters() if n in expected and float(p.grad.abs().sum()) == 0]
    changed = {n for n, p in m.named_parameters() if not torch.equal(p, before[n])}
    assert changed == expected


def test_gradient_checkpointing_computes_the_same_loss_and_gradients():
    x = inputs()
    results = []
    for enabled in (False, True):
        m = model(2)
        m.enable_gradient_checkpointing(enabled)
        trainable_parameters(m, 2)
        loss = run(m, x).square().mean()
        loss.backward()
        results.append((loss.detach(), {n: p.grad for n, p in m.named_parameters() if p.grad is not None}))
    torch.testing.assert_close(results[0][0], results[1][0])
    assert results[0][1].keys() == results[1][1].keys()
    for name, grad in results[0][1].items():
        torch.testing.assert_close(grad, results[1][1][name], msg=name)


def _recammaster_state(m: ReCamDrivingWan, prefix: str = "") -> dict[str, torch.Tensor]:
    """A checkpoint as ReCamMaster saves it (DiffSynth's names), with distinct values."""
    dim, state = m.dim, {}
    g = torch.Generator().manual_seed(3)
    for i in range(len(m.transformer.blocks)):
        state[f"{prefix}blocks.{i}.cam_encoder.weight"] = torch.randn(dim, 12, generator=g)
        state[f"{prefix}blocks.{i}.cam_encoder.bias"] = torch.randn(dim, generator=g)
        state[f"{prefix}blocks.{i}.projector.weight"] = torch.randn(dim, dim, generator=g)
        state[f"{prefix}blocks.{i}.projector.bias"] = torch.randn(dim, generator=g)
        for proj in "qkvo":
            state[f"{prefix}blocks.{i}.self_attn.{proj}.weight"] = torch.randn(dim, dim, generator=g)
            state[f"{prefix}blocks.{i}.self_attn.{proj}.bias"] = torch.randn(dim, generator=g)
        state[f"{prefix}blocks.{i}.self_attn.norm_q.weight"] = torch.randn(dim, generator=g)
        state[f"{prefix}blocks.{i}.self_attn.norm_k.weight"] = torch.randn(dim, generator=g)
        state[f"{prefix}blocks.{i}.cross_attn.q.weight"] = torch.randn(dim, dim, generator=g)  # not ours
        state[f"{prefix}blocks.{i}.ffn.0.weight"] = torch.randn(4 * dim, dim, generator=g)      # not ours
    state[f"{prefix}head.head.weight"] = torch.randn(64, dim, generator=g)                        # not ours
    return state


def test_recammaster_keys_map_onto_the_camera_encoder_projector_and_self_attention():
    assert recammaster_key("blocks.3.cam_encoder.weight") == "recam.3.cam_encoder.weight"
    assert recammaster_key("blocks.3.projector.bias") == "recam.3.projector.bias"
    assert recammaster_key("blocks.0.self_attn.q.weight") == "transformer.blocks.0.attn1.to_q.weight"
    assert recammaster_key("blocks.0.self_attn.o.bias") == "transformer.blocks.0.attn1.to_out.0.bias"
    assert recammaster_key("blocks.1.self_attn.norm_k.weight") == "transformer.blocks.1.attn1.norm_k.weight"
    assert recammaster_key("pipe.dit.blocks.1.self_attn.v.bias") == "transformer.blocks.1.attn1.to_v.bias"
    assert recammaster_key("blocks.0.cross_attn.q.weight") is None
    assert recammaster_key("head.head.weight") is None
    m = model()
    mapped = map_recammaster_state_dict(_recammaster_state(m))
    assert set(mapped) == stage_parameter_names(m, 1) - {"frame_embed"}


@pytest.mark.parametrize("prefix", ["", "pipe.dit."])
def test_a_recammaster_checkpoint_loads_into_stage1_and_nothing_else_changes(prefix):
    m = model()
    before = {n: p.detach().clone() for n, p in m.state_dict().items()}
    state = _recammaster_state(m, prefix)
    assert load_recammaster(m, state, "ckpt") == 2 * 14
    after = m.state_dict()
    assert torch.equal(after["recam.1.projector.weight"], state[f"{prefix}blocks.1.projector.weight"])
    assert torch.equal(after["transformer.blocks.0.attn1.to_k.bias"], state[f"{prefix}blocks.0.self_attn.k.bias"])
    assert torch.equal(after["transformer.blocks.0.attn1.norm_q.weight"],
                       state[f"{prefix}blocks.0.self_attn.norm_q.weight"])
    untouched = {n for n in after if torch.equal(after[n], before[n])}
    assert untouched == set(after) - (stage_parameter_names(m, 1) - {"frame_embed"})


def test_a_recammaster_checkpoint_of_another_size_is_refused_by_name():
    m = model()
    state = _recammaster_state(m)
    state["blocks.0.projector.weight"] = torch.zeros(8, 8)
    with pytest.raises(ValueError, match=r"recam\.0\.projector\.weight .*another Wan size"):
        load_recammaster(m, state, "ckpt")
    with pytest.raises(ValueError, match="no ReCamMaster key"):
        load_recammaster(m, {"head.head.weight": torch.zeros(1)}, "ckpt")


def test_the_transformer_loads_from_a_wan_diffusers_folder_or_its_transformer_folder(tmp_path):
    tiny = make_tiny_transformer(5)
    tiny.save_pretrained(tmp_path / "Wan2.1-T2V-1.3B-Diffusers" / "transformer")
    for folder in (tmp_path / "Wan2.1-T2V-1.3B-Diffusers", tmp_path / "Wan2.1-T2V-1.3B-Diffusers" / "transformer"):
        loaded = load_transformer(folder).state_dict()
        assert all(torch.equal(loaded[k], v) for k, v in tiny.state_dict().items())
    with pytest.raises(ConfigError, match="no config.json"):
        load_transformer(tmp_path / "empty")
