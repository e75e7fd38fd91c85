"""Shared fixtures: smoke-profile builds of synthetic scenes, made once per test session.

Building a scene end to end takes seconds to tens of seconds on 2 cores, so every test that needs
a built scene or a manifest shares these (read-only: copy before mutating).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

SMOKE_SCENES = ("synthetic:demo?seed=7", "synthetic:demo?seed=11")


def _build(root: Path, uris, stages=None, profile="smoke", build="smoke"):
    from paradrive.pipeline import StageRegistry, run_build

    config = StageRegistry().resolve(profile)
    report = run_build(config, list(uris), root / "data", stages=stages,
                       manifests_dir=root / "manifests", build=build)
    failures = [f"{r.scene_id}/{r.stage}: {r.error}" for r in report.failures()]
    assert not failures, "smoke build failed:\n" + "\n".join(failures)
    return {"root": root, "data_dir": root / "data", "manifests_dir": root / "manifests",
            "build_dir": root / "manifests" / build, "scene_uris": list(uris), "report": report}


@pytest.fixture(scope="session")
def smoke_scene(tmp_path_factory):
    """One synthetic scene (seed 7) ingested and fitted with the smoke profile."""
    root = tmp_path_factory.mktemp("smoke_scene")
    return _build(root, SMOKE_SCENES[:1], stages=["ingest", "fit"])


@pytest.fixture(scope="session")
def smoke_build(smoke_scene):
    """Two synthetic scenes (seeds 7 and 11) through every stage, manifest included.

    It grows the ``smoke_scene`` data folder, so seed 7's ingest and fit are reused (skipped by
    their fingerprints), not redone.
    """
    return _build(smoke_scene["root"], SMOKE_SCENES)


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
def tiny_scene(tmp_path_factory) -> Path:
    """Synthetic street, 8 frames of 80x48, the smoke profile's cameras, with LiDAR and sky
    masks (ingest only)."""
    return ingest_synthetic(tmp_path_factory.mktemp("tiny_scene"), 8, 80, 48)


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
    pytest.importorskip("s3fs")
    boto3 = pytest.importorskip("boto3")
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    options = {"endpoint_url": f"http://{host}:{port}", "key": "paradrive", "secret": "paradrive",
               "client_kwargs": {"region_name": "us-east-1"}}
    boto3.client("s3", endpoint_url=options["endpoint_url"], aws_access_key_id="paradrive",
                 aws_secret_access_key="paradrive", region_name="us-east-1").create_bucket(Bucket="builds")
    try:
        yield options
    finally:
        server.stop()


def stage_params(stage: str, overrides: dict | None = None, profile: str | None = None):
    """A stage's typed ``Params``: the profile's values (paper defaults when None) with
    ``overrides``, as the runner would hand them to the stage."""
    from paradrive.pipeline import StageRegistry

    return StageRegistry().resolve(profile, {stage: dict(overrides or {})}).typed(stage)
