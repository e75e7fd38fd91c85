"""The feature metrics' networks, with random weights of the real architectures: the weights are
refused before any video is read when missing or wrong, the published parameter layouts load
through a saved file, the features have their documented shapes, and the metric values behave
(FID 0 for the same frames and growing with a shift, CLIP-V 1 for a video with itself)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from paradrive.errors import ConfigError
from paradrive.scoring.features import (FEATURE_METRICS, PUBLISHED_AT, check_weights, clip_v, fid,
                                        load_extractor)
from paradrive.scoring.networks import load_into
from scoring_nets import CLIP_IMAGE, WRITERS


@pytest.fixture(scope="module")
def weights_dir(tmp_path_factory):
    """Random weights of each network, written once for the module: {metric: path}."""
    folder = tmp_path_factory.mktemp("weights")
    cache: dict[str, Path] = {}

    def get(metric: str) -> Path:
        if metric not in cache:
            cache[metric] = WRITERS[metric](folder)
        return cache[metric]
    return get


def _video(t: int, h: int = 48, w: int = 80, seed: int = 0, brightness: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.integers(40, 200, (t, h, w, 3)).astype(np.int16)
    return np.clip(base + brightness, 0, 255).astype(np.uint8)


# --- the weights check --------------------------------------------------------------------------

@pytest.mark.parametrize("metric", FEATURE_METRICS)
def test_a_missing_weights_file_is_refused_naming_it_and_where_it_is_published(metric, tmp_path):
    missing = tmp_path / "nowhere" / "weights.pth"
    with pytest.raises(ConfigError) as err:
        check_weights(metric, missing)
    message = str(err.value)
    assert str(missing) in message and "no such file" in message
    assert PUBLISHED_AT[metric] in message and "https://" in message
    assert "\n" not in message


def test_weights_not_given_are_refused_saying_they_are_never_downloaded():
    with pytest.raises(ConfigError, match=r"--fid-weights \(not given\).*never downloaded.*pytorch-fid"):
        check_weights("fid", None)
    with pytest.raises(ConfigError, match=r"--clip-weights"):
        check_weights("clip_v", None)


def test_a_file_that_is_not_weights_is_refused(tmp_path):
    text = tmp_path / "pt_inception.pth"
    text.write_text("not a weights file")
    with pytest.raises(ConfigError, match="cannot be read as a PyTorch weights file.*pytorch-fid"):
        check_weights("fid", text)
    folder = tmp_path / "a-folder"
    folder.mkdir()
    with pytest.raises(ConfigError, match="not a file"):
        check_weights("iq", folder)


def test_another_networks_weights_are_refused_naming_a_missing_parameter(weights_dir):
    with pytest.raises(ConfigError, match=r"not this network's weights \(no 'Mixed_7c.branch_pool.conv.weight'"):
        check_weights("fid", weights_dir("fvd"))
    with pytest.raises(ConfigError, match="rgb_imagenet.pt"):
        check_weights("fvd", weights_dir("iq"))


def test_a_clip_folder_needs_a_clip_config_and_weights(tmp_path):
    folder = tmp_path / "clip"
    folder.mkdir()
    with pytest.raises(ConfigError, match="has no config.json.*huggingface"):
        check_weights("clip_v", folder)
    (folder / "config.json").write_text(json.dumps({"model_type": "bert"}))
    with pytest.raises(ConfigError, match="model_type is 'bert', not 'clip'"):
        check_weights("clip_v", folder)
    (folder / "config.json").write_text(json.dumps({"model_type": "clip"}))
    with pytest.raises(ConfigError, match="no model.safetensors"):
        check_weights("clip_v", folder)
    with pytest.raises(ConfigError, match="not a folder"):
        check_weights("clip_v", folder / "config.json")


def test_a_variant_with_other_layers_is_refused_when_loading(weights_dir, tmp_path):
    from paradrive.scoring.i3d import InceptionI3d

    state = torch.load(weights_dir("fvd"), weights_only=True)
    state["logits.conv3d.weight"] = state["logits.conv3d.weight"][:157]      # a Charades head
    state["logits.conv3d.bias"] = state["logits.conv3d.bias"][:157]
    charades = tmp_path / "rgb_charades.pt"
    torch.save(state, charades)
    with pytest.raises(ConfigError, match=r"another variant.*'logits.conv3d.weight' is \(157, 1024, 1, 1, 1\)"):
        load_into(InceptionI3d(), check_weights("fvd", charades))


def test_a_legacy_format_file_without_batch_counters_loads(weights_dir, tmp_path):
    """Files saved before torch 1.6 (pytorch-i3d's, pytorch-fid's) are in the legacy format, and
    those from before torch 0.4.1 have no num_batches_tracked; a DataParallel prefix is dropped."""
    from paradrive.scoring.i3d import InceptionI3d

    state = torch.load(weights_dir("fvd"), weights_only=True)
    old = {f"module.{k}": v for k, v in state.items() if not k.endswith("num_batches_tracked")}
    legacy = tmp_path / "rgb_imagenet.pt"
    torch.save(old, legacy, _use_new_zipfile_serialization=False)
    assert legacy.read_bytes()[:1] == b"\x80"
    net = InceptionI3d()
    load_into(net, check_weights("fvd", legacy))
    assert torch.equal(net.state_dict()["Mixed_5c.b1b.conv3d.weight"], state["Mixed_5c.b1b.conv3d.weight"])


# --- the published layouts ----------------------------------------------------------------------

def test_the_fid_inception_has_the_published_parameter_layout():
    from paradrive.scoring.inception import FIDInceptionV3

    state = FIDInceptionV3().state_dict()
    # torchvision's Inception-v3 without the auxiliary head, 1008 classes: pytorch-fid's file
    assert sum(v.numel() for k, v in state.items() if "running" not in k and "num_batches" not in k) == 23_850_960
    assert state["Conv2d_1a_3x3.conv.weight"].shape == (32, 3, 3, 3)
    assert state["Mixed_6e.branch7x7dbl_5.conv.weight"].shape == (192, 192, 1, 7)
    assert state["Mixed_7c.branch3x3dbl_3b.conv.weight"].shape == (384, 384, 3, 1)
    assert state["fc.weight"].shape == (1008, 2048)
    assert not any(k.startswith("AuxLogits") for k in state)


def test_the_i3d_has_the_published_parameter_layout():
    from paradrive.scoring.i3d import InceptionI3d

    state = InceptionI3d().state_dict()
    assert state["Conv3d_1a_7x7.conv3d.weight"].shape == (64, 3, 7, 7, 7)
    assert state["Mixed_4f.b1b.conv3d.weight"].shape == (320, 160, 3, 3, 3)
    assert state["Mixed_5c.b3b.conv3d.weight"].shape == (128, 832, 1, 1, 1)
    assert state["logits.conv3d.weight"].shape == (400, 1024, 1, 1, 1)
    assert "logits.conv3d.bias" in state and "Conv3d_1a_7x7.conv3d.bias" not in state
    assert not any(".b3a." in k for k in state)     # the max-pool branch has no parameters


def test_the_musiq_has_the_published_parameter_layout():
    from paradrive.scoring.musiq import MUSIQ

    state = MUSIQ().state_dict()
    assert state["conv_root.weight"].shape == (64, 3, 7, 7)
    assert state["block1.conv_proj.weight"].shape == (256, 64, 1, 1)
    assert state["embedding.weight"].shape == (384, 256 * 8 * 8)
    assert state["transformer_encoder.posembed_input.position_emb"].shape == (1, 100, 384)
    assert state["transformer_encoder.scaleembed_input.scale_emb"].shape == (3, 384)
    assert state["transformer_encoder.cls"].shape == (1, 1, 384)
    assert state["transformer_encoder.transformer.encoderblock_13.attention.query.bias"].shape == (384,)
    assert state["transformer_encoder.transformer.encoderblock_13.mlp.fc1.weight"].shape == (1152, 384)
    assert state["head.weight"].shape == (1, 384)


@pytest.mark.parametrize("metric", ["fid", "fvd", "iq"])
def test_a_saved_weights_file_loads_back_whole(metric, weights_dir):
    saved = torch.load(weights_dir(metric), weights_only=True)
    extractor = load_extractor(check_weights(metric, weights_dir(metric)), device="cpu")
    loaded = extractor.net.state_dict()
    assert set(loaded) == set(saved)
    assert all(torch.equal(loaded[k], saved[k]) for k in saved)
    assert len(extractor.weights_sha256) == 64


# --- features -----------------------------------------------------------------------------------

def test_fid_features_are_2048_per_frame_zero_for_the_same_frames_and_grow_with_a_shift(weights_dir):
    extractor = load_extractor(check_weights("fid", weights_dir("fid")), device="cpu")
    # the network runs at 299 x 299 whatever the frame size: two frames a video keep it to seconds
    src = [extractor.features(_video(2))]
    assert src[0].shape == (2, 2048) and src[0].dtype == np.float64
    assert fid(src, src) == pytest.approx(0.0, abs=1e-6)
    near, far = ([extractor.features(_video(2, brightness=b))] for b in (10, 50))
    assert 0 < fid(src, near) < fid(src, far)


def test_the_fid_input_is_resized_to_299_and_scaled_to_minus_one_one():
    from paradrive.scoring.inception import preprocess

    x = torch.rand(2, 3, 48, 80, device="cpu")
    y = preprocess(x)
    assert y.shape == (2, 3, 299, 299)
    assert y.min() >= -1 and y.max() <= 1
    assert torch.allclose(preprocess(torch.full((1, 3, 10, 10), 0.5, device="cpu")), torch.zeros(1, 3, 299, 299))


def test_fvd_features_are_the_400_logits_of_the_first_16_frames(weights_dir):
    extractor = load_extractor(check_weights("fvd", weights_dir("fvd")), device="cpu")
    video = _video(20, h=32, w=40)
    feat = extractor.features(video)
    assert feat.shape == (1, 400) and feat.dtype == np.float64
    changed_after = video.copy()
    changed_after[16:] = 0
    assert np.array_equal(extractor.features(changed_after), feat)
    with pytest.raises(ValueError, match="at least 16 frames"):
        extractor.features(video[:15])


def test_the_i3d_pads_as_tf_same_down_to_a_2x7x7_map():
    from paradrive.scoring.i3d import InceptionI3d, _same_padding

    x = torch.zeros(1, 1, 16, 224, 224, device="cpu")
    assert _same_padding(x, (7, 7, 7), (2, 2, 2)).shape == (1, 1, 16 + 5, 224 + 5, 224 + 5)
    assert _same_padding(torch.zeros(1, 1, 5, 7, 7, device="cpu"), (3, 3, 3), (2, 2, 2)).shape == (1, 1, 7, 9, 9)
    net = InceptionI3d().eval()
    with torch.inference_mode():
        assert net.pooled(torch.zeros(1, 3, 16, 224, 224, device="cpu")).shape == (1, 1024, 1, 1, 1)


def test_clip_features_are_unit_embeddings_and_clip_v_of_a_video_with_itself_is_one(weights_dir):
    extractor = load_extractor(check_weights("clip_v", weights_dir("clip_v")), device="cpu")
    video = _video(5)
    emb = extractor.features(video)
    assert emb.shape == (5, 24) and emb.dtype == np.float64
    assert np.allclose(np.linalg.norm(emb, axis=1), 1.0)
    assert clip_v(emb, extractor.features(video)) == pytest.approx(1.0, abs=1e-12)
    assert clip_v(emb, extractor.features(_video(5, seed=3))) < 0.999


def test_clip_frames_are_prepared_as_clips_own_image_processor_does(weights_dir):
    from transformers.models.clip.image_processing_pil_clip import CLIPImageProcessorPil

    from paradrive.scoring.clipv import ClipPreprocess

    folder = weights_dir("clip_v")
    ours = ClipPreprocess.of_folder(folder)
    assert ours.shortest_edge == CLIP_IMAGE and ours.crop == (CLIP_IMAGE, CLIP_IMAGE)
    frames = _video(2, h=45, w=77, seed=5)
    reference = CLIPImageProcessorPil.from_pretrained(str(folder))(images=list(frames), return_tensors="np")
    x = torch.as_tensor(frames, device="cpu").permute(0, 3, 1, 2).float() / 255
    # PIL's and torch's antialiased bicubic agree to within one grey level (18% of these noise
    # pixels are one level off)
    levels = np.abs(ours(x).numpy() - reference["pixel_values"]) * np.array(ours.std).reshape(1, 3, 1, 1) * 255
    assert levels.max() < 1.01 and levels.mean() < 0.25


def test_iq_scores_one_value_per_frame(weights_dir):
    extractor = load_extractor(check_weights("iq", weights_dir("iq")), device="cpu")
    scores = extractor.features(_video(3, h=40, w=72))
    assert scores.shape == (3,) and scores.dtype == np.float64 and np.isfinite(scores).all()
    assert len(set(scores.tolist())) == 3          # each frame its own score
    assert np.allclose(extractor.features(_video(3, h=40, w=72)[1:2]), scores[1:2], rtol=1e-5, atol=1e-6)


def test_musiq_reads_three_scales_with_masks_and_hashed_positions():
    from paradrive.scoring.musiq import _hash_index, multiscale_patches

    patches, spatial, scale, mask = multiscale_patches(torch.zeros(1, 3, 288, 512, device="cpu"))
    # 224 x 126 → 7 x 4 of a 7² grid, 384 x 216 → 12 x 7 of 12², and the frame's own 16 x 9
    assert patches.shape == (1, 49 + 144 + 144, 3 * 32 * 32)
    assert [int(mask[0, a:b].sum()) for a, b in ((0, 49), (49, 193), (193, 337))] == [28, 84, 144]
    assert scale[0, :28].eq(0).all() and scale[0, 49:133].eq(1).all() and scale[0, 193:].eq(2).all()
    assert _hash_index(7, 10, torch.device("cpu")).tolist() == [0, 1, 2, 4, 5, 7, 8]
    assert spatial[0, 193:209].tolist() == [0, 0, 1, 1, 2, 3, 3, 4, 5, 5, 6, 6, 7, 8, 8, 9]   # first row of 16
    assert int(spatial[0, -1]) == 8 * 10 + 9     # row 8 of 9 → cell 8, column 15 of 16 → cell 9


def test_vbench_resizes_frames_to_a_longer_side_of_512():
    from paradrive.scoring.musiq import vbench_resize

    assert vbench_resize(torch.rand(1, 3, 1280, 1920, device="cpu")).shape == (1, 3, 341, 512)
    small = torch.rand(1, 3, 480, 500, device="cpu")
    assert vbench_resize(small) is small
