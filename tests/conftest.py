"""Shared fixtures: smoke-profile builds of synthetic scenes, made once per test session (once
for all xdist workers: :func:`built_once`).

Building a scene end to end takes seconds to tens of seconds on 2 cores, so every test that needs
a built scene or a manifest shares these. They are read-only: a test that changes anything in one
copies it first (``copy_tree``); each session fixture checks at the end of the session that no
file in its folder was added, removed or rewritten, and fails naming the files otherwise.
"""

from __future__ import annotations

import fcntl
import importlib.util
import os
import pickle
import shutil
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

SMOKE_SCENES = ("synthetic:demo?seed=7", "synthetic:demo?seed=11")
T = TypeVar("T")


# The files that take minutes, longest first (their tests' seconds on a fresh clone under
# `--durations=0`: 191, 136, 122, 74, 73, 69, 55, 54 and 53 of 1,655 in all): collected first,
# so that `--dist loadfile` hands them out before the short ones and the two workers finish
# together instead of one waiting on the other's last long file (884.7 s before, 859.3 s after).
# Thirteen files by a later run's seconds were no better (957 s against 910 s the run before).
SLOW_FILES = ("test_video_real.py", "test_ingest_video.py", "test_ray_executor.py",
              "test_wan_convert.py", "test_faults.py", "test_wan_distributed.py",
              "test_video_kitti.py", "test_faults_disk.py", "test_wan_latents.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: k for k, name in enumerate(SLOW_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))   # stable: file order kept


def _build(root: Path, uris, stages=None, profile="smoke", build="smoke", overrides=None):
    from paradrive.pipeline import StageRegistry, run_build

    config = StageRegistry().resolve(profile, overrides)
    report = run_build(config, list(uris), root / "data", stages=stages,
                       manifests_dir=root / "manifests", build=build)
    failures = [f"{r.scene_id}/{r.stage}: {r.error}" for r in report.failures()]
    assert not failures, "smoke build failed:\n" + "\n".join(failures)
    return {"root": root, "data_dir": root / "data", "manifests_dir": root / "manifests",
            "build_dir": root / "manifests" / build, "scene_uris": list(uris), "report": report}


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """Every entry under ``root``: its size and modification time (what a write changes)."""
    return {str(p.relative_to(root)): (p.lstat().st_size, p.lstat().st_mtime_ns)
            for p in root.rglob("*")}


def changed_entries(before: dict[str, tuple[int, int]], after: dict[str, tuple[int, int]]) -> list[str]:
    return sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))


def read_only(root: Path, value: T) -> Iterator[T]:
    """Yields ``value``; afterwards fails if anything under ``root`` was added, removed or rewritten."""
    before = snapshot(root)
    yield value
    changed = changed_entries(before, snapshot(root))
    assert not changed, (f"a test changed the shared build under {root} (copy it with copy_tree "
                         f"before changing it): {changed[:10]}")


def built_once(tmp_path_factory, name: str, make: Callable[[Path], dict]) -> dict:
    """``make(root)`` once per test session, whatever the number of xdist workers: the first
    worker to ask makes it in a folder all of them share, holding a lock file; the others wait on
    that lock and take what it made (its result, pickled beside it)."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        return make(tmp_path_factory.mktemp(name))
    shared = tmp_path_factory.getbasetemp().parent   # the session's folder above the workers'
    made = shared / f"{name}.pickle"
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not made.is_file():
            result = make(shared / name)
            made.write_bytes(pickle.dumps(result))
        return pickle.loads(made.read_bytes())


@pytest.fixture(scope="session")
def smoke_scene(tmp_path_factory):
    """One synthetic scene (seed 7) ingested and fitted with the smoke profile."""
    built = built_once(tmp_path_factory, "smoke_scene",
                       lambda root: _build(root, SMOKE_SCENES[:1], stages=["ingest", "fit"]))
    yield from read_only(built["root"], built)


@pytest.fixture(scope="session")
def smoke_build(tmp_path_factory, smoke_scene):
    """Two synthetic scenes (seeds 7 and 11) through every stage, manifest included.

    It starts from a copy of the ``smoke_scene`` data folder, so seed 7's ingest and fit are
    reused (skipped by their fingerprints), not redone, and ``smoke_scene`` stays as it was.
    """
    def make(root: Path) -> dict:
        shutil.copytree(smoke_scene["data_dir"], root / "data", symlinks=True)
        return _build(root, SMOKE_SCENES)

    built = built_once(tmp_path_factory, "smoke_build", make)
    yield from read_only(built["root"], built)


# Real recordings, read in place from ../shared/realdata beside the repository (a user's clone
# lacks it: the tests that need it skip, naming the folder)
def load_bench(name: str):
    """``bench/<name>.py`` as a module, loaded once per process; the bench folder goes at the end
    of ``sys.path`` so that the helpers beside it import (and shadow nothing)."""
    if name in sys.modules:
        return sys.modules[name]
    folder = Path(__file__).resolve().parents[1] / "bench"
    if str(folder) not in sys.path:
        sys.path.append(str(folder))
    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"
FREEWAY = REALDATA / "udacity-freeway"
FREEWAY_VIDEO = FREEWAY / "freeway-shadows-1280x720.mp4"
# the clip's camera height, measured on its frames (docs/scene-layout.md, "A real freeway clip")
FREEWAY_HEIGHT_M = 1.23
FREEWAY_URI = f"video:{FREEWAY_VIDEO}?calib=calibration.json&height_m={FREEWAY_HEIGHT_M}"


@pytest.fixture(scope="session")
def freeway_build(tmp_path_factory):
    """The real freeway clip (160 frames of 1280x720, its calibration beside it) through every
    stage with the smoke profile, once per session (the slowest fixture: every xdist worker
    shares it): its ingest is the default one; the fit sees the frames at the smoke renders'
    160 pixels across (fit.downscale 8, not the smoke profile's 2: 46 s of fit less)."""
    if not FREEWAY_VIDEO.is_file():
        pytest.skip(f"the real freeway clip is not here ({FREEWAY}): a clone without ../shared/realdata")
    built = built_once(tmp_path_factory, "freeway", lambda root: _build(root, [FREEWAY_URI],
                                                                   overrides={"fit": {"downscale": 8}}))
    yield from read_only(built["root"], built)


def ingest_synthetic(root: Path, frames: int, width: int, height: int) -> Path:
    """``synthetic:demo?seed=7`` ingested with the smoke profile at this size; its scene folder."""
    from paradrive.pipeline import StageRegistry, run_build

    config = StageRegistry().resolve("smoke", {"ingest": {
        "synthetic_frames": frames, "synthetic_width": width, "synthetic_height": height}})
    report = run_build(config, ["synthetic:demo?seed=7"], root / "data", stages=["ingest"],
                       manifests_dir=root / "manifests", build="ingest")
    assert not report.failures(), [r.error for r in report.failures()]
    (scene_dir,) = (root / "data" / "scenes").iterdir()
    return scene_dir


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Iterator[Path]:
    """Synthetic street, 8 frames of 80x48, the smoke profile's cameras, with LiDAR and sky
    masks (ingest only)."""
    root = tmp_path_factory.mktemp("tiny_scene")
    scene_dir = ingest_synthetic(root, 8, 80, 48)
    yield from read_only(root, scene_dir)


def picture(path: Path) -> np.ndarray:
    """The pixels (H, W, 3) an image file decodes to: what a viewer would show."""
    from PIL import Image

    with Image.open(path) as img:
        return np.asarray(img.convert("RGB"))


def assert_a_drawing(path: Path, min_width: int, min_height: int, background=(255, 255, 255)) -> np.ndarray:
    """``path`` decodes to a picture of at least that size with something drawn on it: more than
    a few colours and more than 1 % of the pixels off the background. Returns the pixels."""
    pixels = picture(path)
    assert pixels.shape[1] >= min_width and pixels.shape[0] >= min_height, pixels.shape
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 16, f"{path}: a blank or flat picture"
    drawn = np.any(pixels != np.array(background, np.uint8), axis=-1).mean()
    assert drawn > 0.01, f"{path}: {drawn:.1%} of the pixels differ from the background"
    return pixels


@pytest.fixture(scope="session")
def wan_folder(tmp_path_factory) -> Path:
    """A Wan2.1 folder in diffusers' layout with a tiny random VAE, umT5 and tokenizer (read only)."""
    from paradrive.wan.text import make_tiny_text_encoder
    from paradrive.wan.vae import make_tiny_vae

    folder = tmp_path_factory.mktemp("wan")
    make_tiny_vae(seed=0).save_pretrained(folder / "vae")
    make_tiny_text_encoder(folder)
    return folder


@pytest.fixture
def copy_tree(tmp_path):
    """Copy a built tree into this test's own folder before changing anything in it."""

    def _copy(src: Path, name: str = "copy") -> Path:
        dst = tmp_path / name
        shutil.copytree(src, dst, symlinks=True)
        return dst

    return _copy


@pytest.fixture
def stage_config(tmp_path):
    """The stand-in stages (``pipeline_stages``) resolved, with optional overrides by stage."""
    def _config(overrides=None):
        import pipeline_stages
        from paradrive.pipeline import StageRegistry

        folder = pipeline_stages.write_stages(tmp_path / "stages")
        return StageRegistry(folder).resolve(None, overrides or {})
    return _config


@pytest.fixture(scope="module")
def s3_bucket():
    """A local S3 endpoint (moto's server) with an empty bucket "builds"; yields fsspec's options."""
    import boto3
    import s3fs  # noqa: F401  (the test extra's: fsspec's s3:// protocol)
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    # credentials no message can contain by chance: a masked secret that is also a word (the
    # package's name) would be masked wherever that word is printed
    key, secret = "AKIATESTKEY7F3A", "test-secret-7f3a9c"
    options = {"endpoint_url": f"http://{host}:{port}", "key": key, "secret": secret,
               "client_kwargs": {"region_name": "us-east-1"}}
    boto3.client("s3", endpoint_url=options["endpoint_url"], aws_access_key_id=key,
                 aws_secret_access_key=secret, region_name="us-east-1").create_bucket(Bucket="builds")
    try:
        yield options
    finally:
        server.stop()


def stage_params(stage: str, overrides: dict | None = None, profile: str | None = None):
    """A stage's typed ``Params``: the profile's values (paper defaults when None) with
    ``overrides``, as the runner would hand them to the stage."""
    from paradrive.pipeline import StageRegistry

    return StageRegistry().resolve(profile, {stage: dict(overrides or {})}).typed(stage)


@pytest.fixture(scope="session")
def wan_builds(tmp_path_factory, smoke_scene):
    """Seed 7's smoke scene in the smoke profile's 9-frame clips (what the Wan smoke config trains
    on, so a generated video has a clip's frame count), with no setting changed: a training build
    ``train`` and an inference set ``infer`` of the same clips. Its ingest and fit are
    ``smoke_scene``'s, copied."""
    from paradrive.pipeline import StageRegistry, run_build

    root = tmp_path_factory.mktemp("wan_builds")
    shutil.copytree(smoke_scene["data_dir"], root / "data", symlinks=True)
    for build, kind in (("train", "training"), ("infer", "inference")):
        config = StageRegistry().resolve("smoke", {"manifest": {"kind": kind}})
        report = run_build(config, list(SMOKE_SCENES[:1]), root / "data", manifests_dir=root / "manifests",
                           build=build)
        assert not report.failures(), [r.error for r in report.failures()]
    yield from read_only(root, {"train": root / "manifests" / "train", "infer": root / "manifests" / "infer",
                                "root": root})
