"""3DGS PLY checkpoints: standard layout (names, order, counts), binary little-endian, round trip."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from paradrive.gs.model import new_params, sh0_to_rgb
from paradrive.gs.ply import load_ply, ply_property_names, save_ply


def _params(n: int = 7, degree: int = 3, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    p = new_params(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g),
                   torch.rand(n, 3, generator=g) + 0.1, sh_degree=degree)
    p["quats"] = torch.randn(n, 4, generator=g)
    p["opacities"] = torch.randn(n, generator=g)
    p["shN"] = torch.randn_like(p["shN"])
    return p


def test_property_names_follow_the_3dgs_order():
    names = ply_property_names(3)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:9 + 45] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len(ply_property_names(0)) == 17


def test_ply_is_binary_little_endian_and_reads_with_plyfile(tmp_path):
    from plyfile import PlyData

    p = _params(11)
    path = save_ply(tmp_path / "ckpt_000100.ply", p)
    head = path.read_bytes()[:200].decode("ascii", errors="replace")
    assert head.startswith("ply\nformat binary_little_endian 1.0\nelement vertex 11\n")
    ply = PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"]
    assert v.count == 11
    assert [prop.name for prop in v.properties] == ply_property_names(3)
    assert all(v.data.dtype[name] == np.dtype("<f4") for name in v.data.dtype.names)
    # pre-activation values, f_rest channel-major (all red coefficients, then green, then blue)
    np.testing.assert_array_equal(v["x"], p["means"][:, 0].numpy())
    np.testing.assert_array_equal(v["opacity"], p["opacities"].numpy())
    np.testing.assert_array_equal(v["scale_2"], p["scales"][:, 2].numpy())
    np.testing.assert_array_equal(v["rot_0"], p["quats"][:, 0].numpy())
    np.testing.assert_array_equal(v["f_rest_0"], p["shN"][:, 0, 0].numpy())
    np.testing.assert_array_equal(v["f_rest_1"], p["shN"][:, 1, 0].numpy())
    np.testing.assert_array_equal(v["f_rest_15"], p["shN"][:, 0, 1].numpy())
    np.testing.assert_array_equal(v["f_rest_30"], p["shN"][:, 0, 2].numpy())
    assert np.all(v["nx"] == 0)
    assert not list(tmp_path.glob(".*tmp*")), "temporary file left behind"


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trips_exactly(tmp_path, degree):
    p = _params(9, degree)
    q = load_ply(save_ply(tmp_path / "a.ply", p))
    assert set(q) == set(p)
    for key in p:
        assert q[key].shape == p[key].shape, key
        assert torch.equal(q[key], p[key]), key
    # saving again gives the same bytes
    save_ply(tmp_path / "b.ply", q)
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


def test_load_ply_rejects_a_non_gaussian_ply(tmp_path):
    from plyfile import PlyData, PlyElement

    arr = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(ValueError, match="not a 3DGS PLY"):
        load_ply(tmp_path / "points.ply")


def test_colour_of_band_zero_is_recoverable(tmp_path):
    rgb = torch.tensor([[0.2, 0.5, 0.9]])
    p = new_params(torch.zeros(1, 3), rgb, torch.ones(1, 3))
    q = load_ply(save_ply(tmp_path / "c.ply", p))
    assert torch.allclose(sh0_to_rgb(q["sh0"][:, 0]), rgb, atol=1e-6)
