"""Every tensor knows its device: the fit, the render and a trainer step on a second device.

Most users fit on CUDA, where a CPU tensor meeting a device tensor is an error; these machines
have no GPU. The tests run the real code on :mod:`simulated_device` (see its docstring), which
fails the same way, and, where CUDA is present, on CUDA too.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import numpy as np
import pytest

import torch
from simulated_device import DEVICE, DeviceMismatch, OnDevice, simulated_device, to_cpu
from test_gs_fit import TINY_FIT, _copy_scene, fit_params

from paradrive import geometry, metrics
from paradrive.devices import resolve_backend, resolve_device
from paradrive.errors import ConfigError
from paradrive.gs import fit as fit_module
from paradrive.gs import strategy as strategy_module
from paradrive.stages.fit import fit_scene
from paradrive.gs.fit import render_checkpoint
from paradrive.gs.ply import load_ply
from paradrive.contracts.layout import SceneLayout

# densify at 4, 8, 12, 16; reset at 12; checkpoints at 10 and 20; the kill at 14 lands after both
FIT = {**TINY_FIT, "checkpoints": [10, 20]}
# The stand-in device runs the torch-op rasterizer (what CUDA runs without gsplat), so the CPU
# reference runs it too; the fused CPU kernels are compared with it in test_rasterize_cpu.py.
CPU_REF = {"device": "cpu", "backend": "torch"}
DEVICES = ["simulated"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(autouse=True)
def plain_adam_steps(monkeypatch):
    """The stand-in device has no fused Adam kernel, so it takes torch's plain step; the CPU
    reference takes it too, or the two fits would differ in the last bit for that reason alone
    (the fused step's own device handling is torch's)."""
    monkeypatch.setattr(fit_module, "FUSED_ADAM_DEVICES", ("cuda",))


@pytest.fixture(autouse=True)
def torch_ssim(monkeypatch):
    """The stand-in device's SSIM is torch operations (the native kernels take CPU images only);
    the CPU reference's is too, for the same reason."""
    monkeypatch.setattr(metrics, "_native_kernels", lambda x: None)


def _on(device: str):
    """(context, device name for the stage parameters) of a test device."""
    if device == "simulated":
        return simulated_device(), str(DEVICE)
    return contextlib.nullcontext(), device


def test_a_cpu_tensor_meeting_a_device_tensor_fails_as_it_does_on_cuda():
    with simulated_device():
        a = torch.ones(3, device=DEVICE)
        assert isinstance(a, OnDevice) and a.device == DEVICE
        with pytest.raises(DeviceMismatch):
            a + torch.ones(3)
        with pytest.raises(DeviceMismatch):
            torch.cat([a, torch.zeros(2)])
        with pytest.raises(DeviceMismatch):
            torch.randn(3, generator=torch.Generator(device="cpu"), device=DEVICE)
        with pytest.raises(DeviceMismatch):
            a[torch.tensor([0, 1])] = torch.zeros(2)   # values on the CPU
        # what CUDA allows: CPU scalars, CPU index tensors, explicit copies between devices
        b = a * torch.tensor(2.0)
        c = a[torch.tensor([0, 2])]
        d = torch.arange(3.0).to(DEVICE) + a
        a[torch.tensor([True, False, True])] = 5.0
        assert b.device == c.device == d.device == DEVICE
        assert d.cpu().device.type == "cpu"
        assert to_cpu(d).tolist() == [1.0, 2.0, 3.0]
        assert to_cpu(a).tolist() == [5.0, 1.0, 5.0]


def _fit_on(device: str, scene: Path, **kwargs) -> dict:
    context, name = _on(device)
    with context:
        return fit_scene(scene, fit_params("smoke", **FIT, device=name), **kwargs)


@pytest.mark.parametrize("graph", [False, True], ids=["static", "scene-graph"])
@pytest.mark.parametrize("device", DEVICES)
def test_fit_densifies_resets_checkpoints_and_resumes_on_a_device(device, graph, tiny_scene, tmp_path):
    moving = {"moving_threshold_m": 1.0} if graph else {}   # the actors that move get nodes
    cpu = _copy_scene(tiny_scene, tmp_path / "cpu")
    ref = fit_scene(cpu, fit_params("smoke", **FIT, **CPU_REF), **moving)
    assert bool(ref.actors) == graph
    dev = _copy_scene(tiny_scene, tmp_path / "dev")
    partial = _fit_on(device, dev, stop_after=14, **moving)
    assert not partial.complete and (dev / "gs" / "state.pt").is_file()
    done = _fit_on(device, dev, **moving)

    assert done.complete and done.device.startswith(str(DEVICE if device == "simulated" else device))
    totals = done.densify
    assert totals["duplicated"] + totals["split"] > 0 and totals["reset"] == 1, totals
    assert not (dev / "gs" / "state.pt").exists()   # removed once the fit completed
    for it in FIT["checkpoints"]:
        names = [f"gs/ckpt_{it:06d}.ply"] + [str(SceneLayout(dev).actor_checkpoint(it, n.file).relative_to(dev))
                                             for n in done.actors]
        for name in names:
            if device == "simulated":   # the same arithmetic on the same host: the same bytes
                assert (dev / name).read_bytes() == (cpu / name).read_bytes(), name
            else:                       # gsplat's kernels: the same model up to float noise
                a, b = load_ply(dev / name), load_ply(cpu / name)
                assert a["means"].shape == b["means"].shape, name
                # Adam's normalised steps can turn a float-noise gradient into a whole step for a
                # few Gaussians: most must sit where the CPU put them, and every one near it
                moved = np.linalg.norm(np.asarray(a["means"]) - np.asarray(b["means"]), axis=-1)
                assert np.quantile(moved, 0.9) < 1e-2 and moved.max() < 0.5, (name, moved.max())
        _assert_renders_alike(dev / f"gs/ckpt_{it:06d}.ply", cpu / f"gs/ckpt_{it:06d}.ply", cpu)


def _assert_renders_alike(ply, ref_ply, scene_dir: Path, min_psnr: float = 30.0) -> None:
    """The two checkpoints, rendered by the same CPU rasterizer from the first recorded front
    view, show the same picture (PSNR over ``min_psnr`` dB)."""
    doc = json.loads((scene_dir / "scene.json").read_text())
    cam, frame = doc["cameras"]["front"], doc["frames"][0]
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    c2w = np.reshape(frame["cameras"]["front"]["c2w"], (1, 4, 4))
    a, b = (render_checkpoint(p, c2w, K, cam["width"], cam["height"], **CPU_REF)["rgb"]
            for p in (ply, ref_ply))
    err = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))   # rgb in [0, 1]
    assert 10 * np.log10(1.0 / max(err, 1e-10)) > min_psnr, (ply, err)


@pytest.mark.parametrize("device", DEVICES)
def test_scene_graph_renders_on_a_device_as_on_the_cpu(device, tiny_scene, tmp_path):
    from paradrive.gs.graph import load_model
    from paradrive.gs.views import render_views
    from paradrive.scene import load_scene
    from paradrive.contracts.records import FitRecord

    scene_dir = _copy_scene(tiny_scene, tmp_path / "scene")
    record = fit_scene(scene_dir, fit_params("smoke", **FIT, device="cpu"), moving_threshold_m=1.0)
    scene = load_scene(scene_dir)
    model = load_model(SceneLayout(scene_dir), 20, scene, FitRecord.load(SceneLayout(scene_dir).fit_json))
    assert record.actors and model.dynamic
    cam = scene.cameras["front"]
    shifted = geometry.lateral_shift(scene.c2w("front"), scene.ego2world(), 2.0)
    frames = list(range(len(scene.frames)))
    kwargs = {"frames": frames, "depth": True, "batch_frames": 3}
    ref = list(render_views(model, shifted, cam.K(), cam.width, cam.height, **kwargs, **CPU_REF))
    context, name = _on(device)
    with context:
        out = list(render_views(model, shifted, cam.K(), cam.width, cam.height, device=name, **kwargs))
    for a, b in zip(out, ref):
        for key in ("rgb", "alpha", "depth"):
            np.testing.assert_allclose(a[key], b[key], atol=0 if device == "simulated" else 2)


@pytest.mark.parametrize("device", DEVICES)
def test_checkpoint_renders_on_a_device_as_on_the_cpu(device, tiny_scene, tmp_path):
    scene = _copy_scene(tiny_scene, tmp_path / "scene")
    fit_scene(scene, fit_params("smoke", **FIT, device="cpu"))
    cam = json.loads((scene / "scene.json").read_text())["cameras"]["front"]
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    frames = json.loads((scene / "scene.json").read_text())["frames"][:3]
    c2w = np.stack([np.reshape(f["cameras"]["front"]["c2w"], (4, 4)) for f in frames])
    ply = scene / "gs" / "ckpt_000020.ply"
    ref = render_checkpoint(ply, c2w, K, cam["width"], cam["height"], render_depth=True, **CPU_REF)
    context, name = _on(device)
    with context:
        out = render_checkpoint(ply, c2w, K, cam["width"], cam["height"], render_depth=True,
                                device=name)
    for key in ("rgb", "alpha", "depth"):
        assert isinstance(out[key], np.ndarray)
        np.testing.assert_allclose(out[key], ref[key], atol=0 if device == "simulated" else 2e-2)


def test_a_cpu_tensor_slipped_into_the_fit_fails_on_the_device(tiny_scene, tmp_path, monkeypatch):
    """The bug this guards against: split samples drawn on the CPU and used on the device."""
    def cpu_noise(generator, n, device):
        return torch.randn(2, n, 3, generator=generator)   # forgets to move to ``device``

    monkeypatch.setattr(strategy_module, "split_noise", cpu_noise)
    scene = _copy_scene(tiny_scene, tmp_path / "scene")
    fit_scene(scene, fit_params("smoke", **FIT, device="cpu"), stop_after=9)  # fine on the CPU
    with pytest.raises(DeviceMismatch, match="same device"):
        _fit_on("simulated", _copy_scene(tiny_scene, tmp_path / "dev"))


def test_trainer_steps_on_a_device_compute_what_they_compute_on_the_cpu(tmp_path):
    from test_train import PairTensors, tiny_config

    from paradrive.train import Trainer

    cpu = Trainer(tiny_config(), 1, tmp_path / "cpu", PairTensors(2)).train(2)
    with simulated_device():
        cfg = {**tiny_config(), "device": str(DEVICE)}
        trainer = Trainer(cfg, 1, tmp_path / "dev", PairTensors(2))
        losses = trainer.train(2)
        assert all(p.device == DEVICE for p in trainer.model.parameters())
    assert losses == cpu


def test_device_and_backend_choices_say_what_is_wrong(monkeypatch, caplog):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_backend("auto", torch.device("cpu")) == "cpu"  # the fused CPU kernels
    assert resolve_backend("torch", torch.device("cpu")) == "torch"  # the torch-op reference
    with pytest.raises(ConfigError, match="fused CPU kernels"):
        resolve_backend("cpu", torch.device("cuda"))
    with pytest.raises(ConfigError, match="not a torch device"):
        resolve_device("gpu0")
    with pytest.raises(ConfigError, match="needs a CUDA device"):
        resolve_backend("gsplat", torch.device("cpu"))
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA GPU"):
            resolve_device("cuda")
    # a CUDA machine whose gsplat extension does not load: auto warns and says why, gsplat refuses
    from paradrive import devices

    monkeypatch.setattr(devices, "gsplat_status", lambda: (False, "the extension failed to build"))
    devices._warn_fallback.cache_clear()
    with caplog.at_level("WARNING", logger="paradrive.devices"):
        assert resolve_backend("auto", torch.device("cuda")) == "torch"
    assert "the extension failed to build" in caplog.text
    with pytest.raises(ConfigError, match="the extension failed to build"):
        resolve_backend("gsplat", torch.device("cuda"))
