"""TCE's RAFT flow (``--flow-weights``): the original release's weights layout loaded strictly,
wrong files refused in one line before any video is read, the network's pieces (all-pairs
correlation, the window lookup, convex upsampling, edge padding) against direct computations,
and ``paradrive eval`` recording the RAFT it ran. Random weights cannot find a shift, so the
known-shift check of TCE is DIS's (``test_scoring_flow``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from scoring_nets import randomised
from test_eval_table import _eval, _rows
from test_inference_sets import inference_build, videos_folder  # noqa: F401  (the fixture)

from paradrive.errors import ConfigError
from paradrive.scoring import raft as R
from paradrive.scoring.flow import FlowSettings, tce

CPU = torch.device("cpu")


def _write(path, shape=R.BASIC, seed=0, edit=None):
    """A random RAFT saved as the release saved its models: a DataParallel state dict, every key
    ``module.``-prefixed."""
    state = {f"module.{k}": v for k, v in randomised(R.Raft(shape), seed).state_dict().items()}
    if edit is not None:
        state = edit(state)
    torch.save(state, path)
    return path


@pytest.fixture(scope="module")
def basic_file(tmp_path_factory):
    return _write(tmp_path_factory.mktemp("raft") / "raft-things-random.pth")


def _frames(h=90, w=150, seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8), rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


@pytest.mark.parametrize("shape", [R.BASIC, R.SMALL], ids=lambda s: s.variant)
def test_a_random_raft_in_the_published_layout_loads_strictly_and_round_trips(tmp_path, shape):
    path = _write(tmp_path / "raft.pth", shape, seed=3)
    saved = torch.load(path, weights_only=True)
    assert all(k.startswith("module.") for k in saved)
    assert {"module.fnet.conv1.weight", "module.cnet.conv1.weight"} <= set(saved)
    net = R.load_raft(path, CPU)
    assert net.shape == shape and not net.training
    loaded = net.state_dict()
    assert set(loaded) == {k.removeprefix("module.") for k in saved}
    assert all(torch.equal(loaded[k.removeprefix("module.")], v) for k, v in saved.items())
    # the published parameter counts: 5.3 M (basic), 1.0 M (small)
    count = sum(v.numel() for k, v in loaded.items() if "running" not in k and "num_batches" not in k)
    assert count == {"basic": 5_257_984, "small": 990_162}[shape.variant]


def _drop(key):
    return lambda state: {k: v for k, v in state.items() if k != key}


@pytest.mark.parametrize("content, says", [
    (None, "no such file"),
    (b"not a torch file", "cannot be read as a PyTorch weights file"),
    (_drop("module.update_block.mask.2.bias"), "lacks 'update_block.mask.2.bias'"),
    (lambda s: {**s, "module.fnet.conv1.weight": torch.zeros(64, 3, 5, 5, device="cpu")},
     "'fnet.conv1.weight' is (64, 3, 5, 5), not (64, 3, 7, 7)"),
    (lambda s: {"upsample_weight.0.weight": torch.zeros(1, device="cpu"),
                "init_conv.weight": torch.zeros(1, device="cpu")}, "SEA-RAFT's weights"),
    (lambda s: {"conv.weight": torch.zeros(1, device="cpu")}, "not RAFT's weights"),
])
def test_a_missing_corrupt_or_other_network_file_is_refused_in_one_line(tmp_path, content, says):
    path = tmp_path / "weights.pth"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        _write(path, edit=content)
    with pytest.raises(ConfigError) as info:
        R.raft_settings(path)
    message = str(info.value)
    assert says in message and "\n" not in message
    assert message.startswith(f"--flow-weights {path}:") and "princeton-vl/RAFT" in message


def test_the_settings_name_the_file_so_dis_and_each_raft_cache_apart(tmp_path, basic_file):
    other = _write(tmp_path / "other.pth", seed=1)
    a, b = R.raft_settings(basic_file), R.raft_settings(other)
    assert a.weights == basic_file and a.crop_px == FlowSettings().crop_px
    assert a.method.startswith("raft-") and a.method.endswith(f"-{R.RAFT_ITERATIONS}it")
    assert len({a.key()["method"], b.key()["method"], FlowSettings().key()["method"]}) == 3
    assert R.flow_of(FlowSettings(), "cpu").__name__ == "dis_flow"


def test_the_correlation_volume_is_every_pair_s_dot_product_over_sqrt_dim():
    g = torch.Generator(device="cpu").manual_seed(0)
    f1 = torch.randn(2, 16, 3, 5, generator=g, device="cpu")
    f2 = torch.randn(2, 16, 3, 5, generator=g, device="cpu")
    corr = R.all_pairs_correlation(f1, f2).reshape(2, 3, 5, 3, 5)
    for n, (y1, x1, y2, x2) in zip((0, 1, 1), ((0, 0, 2, 4), (1, 3, 0, 1), (2, 4, 2, 4))):
        want = float((f1[n, :, y1, x1] * f2[n, :, y2, x2]).sum()) / 4.0
        assert float(corr[n, y1, x1, y2, x2]) == pytest.approx(want, rel=1e-5)
    pyramid = R.correlation_pyramid(R.all_pairs_correlation(f1, f2), 2)
    assert pyramid[1].shape == (30, 1, 2)
    assert float(pyramid[1][7, 0, 1]) == pytest.approx(float(corr[0, 1, 2, 0:2, 2:4].mean()), rel=1e-5)


def test_bilinear_sampling_matches_grid_sample_and_is_zero_outside():
    g = torch.Generator(device="cpu").manual_seed(1)
    maps = torch.randn(3, 6, 7, generator=g, device="cpu")
    points = torch.rand(3, 20, 2, generator=g, device="cpu") * torch.tensor([9.0, 8.0], device="cpu") - 1.5
    got = R.bilinear(maps, points)
    norm = torch.tensor([6.0, 5.0], device="cpu")   # (W - 1, H - 1)
    want = F.grid_sample(maps[:, None], (2 * points / norm - 1)[:, None], align_corners=True)[:, 0, 0]
    assert torch.allclose(got, want, atol=1e-5)
    # a 1-pixel map: its value on the pixel, half of it half a pixel off, nothing a pixel off
    one = torch.full((1, 1, 1), 4.0, device="cpu")
    at = torch.tensor([[[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [0.0, -1.0]]], device="cpu")
    assert R.bilinear(one, at).tolist() == [[4.0, 2.0, 0.0, 0.0]]


def test_the_lookup_reads_each_level_s_window_around_the_match_first_offset_along_x():
    g = torch.Generator(device="cpu").manual_seed(2)
    h, w, r = 8, 8, 2
    corr = torch.randn(h * w, h, w, generator=g, device="cpu")
    pyramid = R.correlation_pyramid(corr, 2)
    coords = R.pixel_grid(h, w, CPU) + torch.tensor([1.0, -2.0], device="cpu").reshape(1, 2, 1, 1)
    out = R.lookup(pyramid, coords, r)
    side = 2 * r + 1
    assert out.shape == (1, 2 * side * side, h, w)
    y, x = 5, 3                              # this pixel's match is (x + 1, y - 2) = (4, 3)
    p = y * w + x
    for i in range(side):
        for j in range(side):
            mx, my = 4 + i - r, 3 + j - r    # level 0, integer: the map's own value
            assert float(out[0, i * side + j, y, x]) == pytest.approx(float(corr[p, my, mx]))
            want = float(R.bilinear(pyramid[1][p:p + 1], torch.tensor(
                [[[2.0 + i - r, 1.5 + j - r]]], device="cpu"))[0, 0])   # level 1: (4, 3) / 2
            assert float(out[0, side * side + i * side + j, y, x]) == pytest.approx(want, abs=1e-6)


def test_convex_upsampling_takes_the_softmax_weighted_neighbours_times_eight():
    h, w = 2, 3
    flow = torch.arange(2 * h * w, dtype=torch.float32, device="cpu").reshape(1, 2, h, w)

    def one_hot(k):
        mask = torch.full((1, 9, 64, h, w), -1e4, device="cpu")
        mask[:, k] = 0.0
        return mask.reshape(1, 576, h, w)

    centre = R.convex_upsample(flow, one_hot(4))
    assert centre.shape == (1, 2, 16, 24)
    assert torch.equal(centre, 8 * flow.repeat_interleave(8, 2).repeat_interleave(8, 3))
    right = R.convex_upsample(flow, one_hot(5))     # neighbour (row 0, column +1): zero past the edge
    shifted = torch.cat([flow[..., 1:], torch.zeros(1, 2, h, 1, device="cpu")], dim=3)
    assert torch.equal(right, 8 * shifted.repeat_interleave(8, 2).repeat_interleave(8, 3))
    even = R.convex_upsample(flow, torch.zeros(1, 576, h, w, device="cpu"))
    # pixel (0, 0): its 3x3 neighbourhood holds 4 pixels inside the flow, 5 zeros outside
    assert float(even[0, 0, 3, 5]) == pytest.approx(8 * float(flow[0, 0, :2, :2].sum()) / 9)


def test_frames_are_edge_padded_to_multiples_of_8_evenly_and_cut_back():
    x = torch.arange(2 * 3 * 90 * 150, dtype=torch.float32, device="cpu").reshape(2, 3, 90, 150)
    padded, pad = R.pad_to_8(x)
    assert padded.shape == (2, 3, 96, 152) and pad == (1, 1, 3, 3)
    assert torch.equal(padded[..., 0, 1:-1], x[..., 0, :])                 # the top rows repeat row 0
    assert torch.equal(padded[..., 3:-3, 0], x[..., :, 0])                 # the left column, column 0
    assert torch.equal(R.unpad(padded, pad), x)
    same, none = R.pad_to_8(x[..., :88, :144])
    assert none == (0, 0, 0, 0) and same.shape[-2:] == (88, 144)


def test_the_flow_is_float32_per_pixel_of_the_frame_and_the_network_s_own(basic_file):
    net = R.load_raft(basic_file, CPU)
    a, b = _frames()
    flow = R.raft_flow(net, CPU, iterations=2)(a, b)
    assert flow.shape == (90, 150, 2) and flow.dtype == np.float32 and np.isfinite(flow).all()
    pair = torch.as_tensor(np.stack([a, b]), device="cpu").permute(0, 3, 1, 2).float()
    padded, pad = R.pad_to_8(pair)
    with torch.inference_mode():
        direct = R.unpad(net(padded[:1], padded[1:], iterations=2), pad)[0].permute(1, 2, 0).numpy()
    assert np.array_equal(flow, direct)
    assert not np.allclose(flow, R.raft_flow(net, CPU, iterations=1)(a, b))   # iterations count
    errors = tce(np.stack([a, b, a]), flow=R.raft_flow(net, CPU, iterations=1))
    assert errors.shape == (2,) and np.isfinite(errors).all()
    with pytest.raises(ValueError, match="56x90 frame is too small for RAFT"):
        R.raft_flow(net, CPU)(a[:, :56], b[:, :56])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU on this machine")
def test_raft_runs_on_cuda_like_on_the_cpu(basic_file):
    a, b = _frames(64, 96)
    cuda = torch.device("cuda")
    on_gpu = R.raft_flow(R.load_raft(basic_file, cuda), cuda, iterations=3)(a, b)
    on_cpu = R.raft_flow(R.load_raft(basic_file, CPU), CPU, iterations=3)(a, b)
    assert on_gpu.dtype == np.float32 and on_gpu.shape == (64, 96, 2)
    assert np.abs(on_gpu - on_cpu).max() < 1e-2 * max(1.0, float(np.abs(on_cpu).max()))


def test_eval_flow_weights_runs_raft_and_records_it(inference_build, tmp_path):  # noqa: F811
    small_file = _write(tmp_path / "raft-small-random.pth", R.SMALL)   # the faster variant
    rows = _rows(inference_build["dir"])[:1]
    videos = videos_folder(inference_build["dir"], rows, "source", tmp_path / "videos")
    doc = _eval(inference_build["dir"], videos, "--metrics", "tce", "--flow-weights", str(small_file),
                "--device", "cpu", "--json", code=3)
    method = R.raft_settings(small_file).method
    assert doc["settings"]["flow"]["method"] == method
    assert json.loads((videos / "scores.json").read_text())["settings"]["flow"]["method"] == method
    (row,) = [r for r in doc["rows"] if r["error"] is None]
    assert row["pair_id"] == rows[0]["pair_id"] and np.isfinite(row["tce"]) and doc["cache"]["misses"] >= 1
    # DIS scores the same video apart: its own cache entry, another TCE
    dis = _eval(inference_build["dir"], videos, "--metrics", "tce", "--json", code=3)
    assert dis["settings"]["flow"]["method"] == FlowSettings().method
    (again,) = [r for r in dis["rows"] if r["error"] is None]
    assert dis["cache"]["misses"] >= 1 and again["tce"] != row["tce"]


def test_eval_refuses_sea_raft_weights_before_any_video_is_read(inference_build, tmp_path):  # noqa: F811
    sea = tmp_path / "Tartan-C-T-TSKH-spring540x960-M.pth"
    torch.save({"upsample_weight.0.weight": torch.zeros(1, device="cpu"),
                "init_conv.weight": torch.zeros(1, device="cpu")}, sea)
    videos = videos_folder(inference_build["dir"], _rows(inference_build["dir"])[:1], "source",
                           tmp_path / "videos")
    out = " ".join(_eval(inference_build["dir"], videos, "--flow-weights", str(sea), code=2).split())
    assert "SEA-RAFT's weights" in out and "princeton-vl/RAFT" in out
    assert not (videos / "scores-cache").exists() and not (videos / "scores.json").exists()
