"""Shared storage is not trusted code: no pickle from the data root, no paths out of a build or
a scene folder, no secrets in what a build writes, no scene that escapes the data root."""

from __future__ import annotations

import json
import logging
import pathlib
import re
import shutil
import subprocess

import pytest

from conftest import stage_params
import torch

from paradrive.io import PathEscapeError, UnsafeFileError


class Payload:
    """Unpickling this runs ``Path(marker).touch()``: what a crafted file on shared storage does."""

    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (self.marker,))


def crafted_file(path: pathlib.Path, marker: pathlib.Path, **fields) -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({**fields, "payload": Payload(marker)}, path)
    return path


def test_the_crafted_file_runs_its_code_when_unpickled(tmp_path):
    """The payload the tests below refuse is live: plain pickle loading writes the marker."""
    marker = tmp_path / "ran"
    torch.load(crafted_file(tmp_path / "x.pt", marker), weights_only=False)
    assert marker.exists()


# --------------------------------------------------------------------------- pickle: fit state

def _fit_params() -> dict:
    from paradrive.contracts.specs import StageRegistry

    return StageRegistry().resolve("smoke", {"fit": {
        "checkpoints": [2, 4], "threads": 1, "init_points": 500, "sky_points": 100,
        "eval_views": 2, "state_interval": 2, "keep_state": True}}).typed("fit")


def test_a_pickled_fit_state_is_refused_and_the_fit_starts_over(tiny_scene, tmp_path, caplog):
    from paradrive.gs.fit import STATE_VERSION
    from paradrive.stages.fit import fit_scene

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    marker = tmp_path / "ran"
    state = crafted_file(scene / "gs" / "state.pt", marker, version=STATE_VERSION, step=3)
    with caplog.at_level(logging.WARNING, logger="paradrive.gs.fit"):
        doc = fit_scene(scene, _fit_params())
    assert not marker.exists()
    assert any(str(state) in r.getMessage() and "starting over" in r.getMessage()
               and "pickle" in r.getMessage() for r in caplog.records)
    assert doc.complete and [c.iteration for c in doc.checkpoints] == [2, 4]
    # the state the fit wrote in its place holds tensors and plain data only
    saved = torch.load(state, weights_only=True)
    assert saved["version"] == STATE_VERSION and saved["step"] == 4
    assert isinstance(saved["rng"]["numpy"]["keys"], torch.Tensor)


# --------------------------------------------------------------------------- pickle: trainer

def _tiny_train_config() -> dict:
    from paradrive.train import load_config

    return load_config("smoke", {"data": {"num_frames": 4, "height": 32, "width": 48},
                                 "model": {"dim": 32, "depth": 2, "heads": 2},
                                 "train": {"batch_size": 2}})


def test_a_pickled_trainer_checkpoint_is_refused_on_resume_init_and_sampling(tmp_path):
    from paradrive.train import Trainer, load_for_sampling
    from paradrive.train.trainer import CHECKPOINT_FORMAT

    marker = tmp_path / "ran"
    last = crafted_file(tmp_path / "stage1" / "last.pt", marker, format=CHECKPOINT_FORMAT, stage=1)
    pairs = [{}, {}]  # never read: the checkpoint is refused first
    with pytest.raises(UnsafeFileError, match="last.pt: holds Python objects.*refused"):
        Trainer(_tiny_train_config(), 1, tmp_path / "stage1", pairs)
    with pytest.raises(UnsafeFileError, match="last.pt"):
        Trainer(_tiny_train_config(), 2, tmp_path / "stage2", pairs, init=last)
    with pytest.raises(UnsafeFileError, match="last.pt"):
        load_for_sampling(last, device="cpu")
    assert not marker.exists()


def test_a_trainer_checkpoint_loads_without_pickle(tmp_path):
    from paradrive.train import Trainer

    class Pairs(torch.utils.data.Dataset):
        def __len__(self) -> int:
            return 2

    trainer = Trainer(_tiny_train_config(), 1, tmp_path / "run", Pairs())
    trainer.save()
    ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    assert ckpt["config"] == trainer.config and ckpt["torch_rng"].dtype == torch.uint8
    assert Trainer(_tiny_train_config(), 1, tmp_path / "run", Pairs()).step == 0


# --------------------------------------------------------------------------- paths out of a build

OPENED: list[str] = []


def _record_opens(event: str, args: tuple) -> None:
    if event == "open" and isinstance(args[0], (str, pathlib.Path)):
        OPENED.append(str(args[0]))


@pytest.fixture(scope="module")
def watch_opens():
    """Every file this process opens from Python code (a real audit hook, sys.addaudithook)."""
    import sys

    if _record_opens not in getattr(watch_opens, "installed", ()):
        sys.addaudithook(_record_opens)
        watch_opens.installed = (_record_opens,)
    return OPENED


@pytest.fixture(scope="module")
def clip_build(tmp_path_factory):
    """One scene x 24 pairs (the middle clip), media copied into the build."""
    from paradrive.stages.manifest import build_manifest
    from test_manifest import scenes_entry, write_clip_scene

    data = tmp_path_factory.mktemp("data")
    scene = write_clip_scene(data, "synthetic-a", clips=("middle",))
    build_dir = tmp_path_factory.mktemp("manifests") / "b"
    build_manifest(build_dir, [scenes_entry(scene)], stage_params("manifest", {"media": "copy"}))
    return build_dir


def _outside_file(tmp_path: pathlib.Path) -> pathlib.Path:
    secret = tmp_path / "outside" / "secret.mp4"
    secret.parent.mkdir(parents=True)
    secret.write_bytes(b"not part of any build")
    return secret


def tampered(build: pathlib.Path, dst: pathlib.Path, row: int, column: str, uri: str) -> str:
    """A copy of ``build`` whose ``row`` has ``column`` = ``uri`` (index checksums updated, so
    only the URI is wrong); returns that row's pair_id."""
    import hashlib

    import pyarrow.parquet as pq

    shutil.copytree(build, dst)
    index = json.loads((dst / "index.json").read_text())
    entry = index["shards"][0]
    shard = dst / index["version"] / entry["file"]
    table = pq.read_table(shard)
    values = table.column(column).to_pylist()
    values[row] = uri
    table = table.set_column(table.schema.get_field_index(column), column,
                             pa_array(values, table.schema.field(column).type))
    pq.write_table(table, shard)
    data = shard.read_bytes()
    entry.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    (dst / "index.json").write_text(json.dumps(index))
    return table.column("pair_id")[row].as_py()


def pa_array(values, type_):
    import pyarrow as pa

    return pa.array(values, type=type_)


@pytest.mark.parametrize("kind", ["absolute", "dotdot"])
def test_a_uri_out_of_the_build_fails_in_the_adapter_and_verify_without_reading_it(
        clip_build, tmp_path, kind, watch_opens):
    from paradrive.data import PairDataset
    from paradrive.inspection import verify_build

    secret = _outside_file(tmp_path)
    build = tmp_path / "b"
    uri = str(secret) if kind == "absolute" else "../outside/secret.mp4"
    pair_id = tampered(clip_build, build, 3, "target_uri", uri)
    watch_opens.clear()

    with pytest.raises(PathEscapeError, match=rf"row {re.escape(pair_id)} column target_uri.*must be relative"):
        PairDataset(build, verify_checksums=True)
    result = verify_build(build)
    assert not result["ok"]
    (problem,) = [p for p in result["problems"] if "target_uri" in p]
    assert problem.startswith("unsafe:") and pair_id in problem and repr(uri) in problem
    assert str(secret) not in [str(pathlib.Path(p).resolve()) for p in watch_opens]


def test_inspect_verify_exits_1_naming_the_row_of_an_escaping_uri(clip_build, tmp_path):
    import typer
    from typer.testing import CliRunner

    from paradrive.commands.inspect import register

    build = tmp_path / "b"
    pair_id = tampered(clip_build, build, 0, "source_uri", "/etc/hostname")
    app = typer.Typer()
    app.callback()(lambda: None)
    register(app)
    res = CliRunner().invoke(app, ["inspect", str(build), "--verify"], env={"COLUMNS": "400"})
    assert res.exit_code == 1
    assert f"row {pair_id} column source_uri" in res.output and "unsafe" in res.output


def test_a_media_link_leading_out_of_the_build_is_refused_when_read(clip_build, tmp_path,
                                                                   watch_opens):
    from paradrive.data import PairDataset
    from paradrive.inspection import verify_build

    secret = _outside_file(tmp_path)
    build = tmp_path / "b"
    shutil.copytree(clip_build, build)
    ds = PairDataset(build)
    link = build / ds.index.version / ds.row(0)["target_uri"]
    link.unlink()
    link.symlink_to(secret)
    watch_opens.clear()
    with pytest.raises(PathEscapeError, match=rf"row {re.escape(ds.pair_ids[0])} column target_uri.*outside"):
        ds[0]
    assert any(p.startswith("unsafe:") and "outside" in p for p in verify_build(build)["problems"])
    assert str(secret) not in [str(pathlib.Path(p).resolve()) for p in watch_opens]


def test_a_symlink_build_reads_its_links_into_the_scene_folder(tmp_path):
    """``media: symlink`` links lead out of the build by design, to the scene's own clip."""
    from paradrive.data import PairDataset
    from paradrive.inspection import verify_build
    from paradrive.stages.manifest import build_manifest
    from test_manifest import scenes_entry, write_clip_scene

    scene = write_clip_scene(tmp_path / "data", "synthetic-a", clips=("middle",),
                             offsets=(1.0,), conditions=(100,))
    build = tmp_path / "b"
    build_manifest(build, [scenes_entry(scene)], stage_params("manifest", {"media": "symlink"}))
    ds = PairDataset(build, verify_checksums=True)
    assert ds[0]["target"].shape[0] == 8
    assert verify_build(build)["ok"]
    # a link in that build to a file that is not the scene's own clip is still refused
    link = build / ds.index.version / ds.row(0)["condition_uri"]
    link.unlink()
    link.symlink_to(_outside_file(tmp_path))
    with pytest.raises(PathEscapeError, match="column condition_uri"):
        ds[0]


def test_a_shard_listed_outside_the_build_is_refused(clip_build, tmp_path):
    from paradrive.data import PairDataset

    build = tmp_path / "b"
    shutil.copytree(clip_build, build)
    index = json.loads((build / "index.json").read_text())
    index["shards"][0]["file"] = "../elsewhere.parquet"
    (build / "index.json").write_text(json.dumps(index))
    with pytest.raises(PathEscapeError, match="index.json: shard 0.*'../elsewhere.parquet'"):
        PairDataset(build)


# --------------------------------------------------------------------------- paths out of a scene

def test_eval_refuses_a_scene_whose_image_path_leads_out(tiny_scene, tmp_path):
    from paradrive.errors import SceneError
    from paradrive.evaluation import evaluate_scene
    from paradrive.contracts.specs import StageRegistry

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    doc = json.loads((scene / "scene.json").read_text())
    doc["frames"][2]["cameras"]["front"]["image"] = "../../../outside.jpg"
    (scene / "scene.json").write_text(json.dumps(doc))
    render = StageRegistry().resolve("smoke").typed("render")
    with pytest.raises(SceneError, match=r"frame 2 camera front image: path '../../../outside.jpg' "
                                         r"must be relative"):
        evaluate_scene(scene, render)


def test_an_image_link_leading_out_of_the_scene_is_refused(tiny_scene, tmp_path):
    from paradrive.errors import SceneError
    from paradrive.scene import load_scene

    scene_dir = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene_dir)
    scene = load_scene(scene_dir)
    image = scene.image_path(0, "front")
    image.unlink()
    image.symlink_to(_outside_file(tmp_path))
    with pytest.raises(SceneError, match="frame 0 camera front image.*outside"):
        scene.load_image(0, "front")


# --------------------------------------------------------------------------- secrets

SECRET = "SECRETb7f3e1"  # every credential below contains it


def _paradrive(*args, env: dict) -> subprocess.CompletedProcess:
    """The real command line (the ledger records sys.argv, so CliRunner would not do)."""
    import os
    import sys

    repo = pathlib.Path(__file__).resolve().parents[1]
    return subprocess.run([sys.executable, "-m", "paradrive.cli", *map(str, args)], cwd=repo,
                          capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(repo), "COLUMNS": "250", **env})


def _files_holding(text: str, *folders: pathlib.Path) -> list[str]:
    return [str(p) for folder in folders for p in folder.rglob("*")
            if p.is_file() and text.encode() in p.read_bytes()]


@pytest.mark.slow
def test_a_build_with_credentials_writes_them_nowhere(s3_bucket, tmp_path):
    import pipeline_stages
    from paradrive.storage import DataRoot

    options = {**s3_bucket, "key": f"{SECRET}-key", "secret": f"{SECRET}-secret"}
    flags = [arg for name, value in options.items()
             for arg in ("--storage-option", f"{name}={json.dumps(value)}")]
    env = {"AWS_SESSION_TOKEN": f"{SECRET}-session", "PARADRIVE_CACHE": str(tmp_path / "cache")}
    url = "s3://builds/secrets"
    res = _paradrive("build", "--scene", "synthetic:demo?seed=1",
                     "--scene", "synthetic:demo?seed=4&colour=red", "--profile", "smoke",
                     *pipeline_stages.tiny_real_sets(), "--data", url, *flags,
                     "--manifests", tmp_path / "manifests", "--build", "b", env=env)
    assert res.returncode == 3, res.stdout + res.stderr  # one scene built, one failed
    # an unreachable endpoint whose URL carries a password: every scene fails naming the URL
    unreachable = {**options, "endpoint_url": f"http://someone:{SECRET}-pw@127.0.0.1:9",
                   "config_kwargs": {"retries": {"max_attempts": 1}, "connect_timeout": 1}}
    bad = _paradrive("build", "--scene", "synthetic:demo?seed=1", "--profile", "smoke",
                     "--data", "s3://builds/unreachable", "--manifests", tmp_path / "manifests",
                     "--build", "bad", *[arg for name, value in unreachable.items() for arg in
                                         ("--storage-option", f"{name}={json.dumps(value)}")],
                     env=env)
    assert bad.returncode == 1 and "s3://builds/unreachable/scenes/synthetic-demo-s1" in bad.stdout

    remote = DataRoot.of(url, storage_options=s3_bucket)
    fs, base = remote.filesystem()
    fetched = tmp_path / "bucket"
    for name in fs.find(base):
        target = fetched / name[len(base) + 1:]
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(fs.cat_file(name))
    # the four places the builds write: the search below means something only where files are
    written = [fetched / "logs", tmp_path / "cache", tmp_path / "manifests" / "b",
               tmp_path / "manifests" / "bad"]
    assert [str(f) for f in written if not any(p.is_file() for p in f.rglob("*"))] == []
    assert any((fetched / "logs").rglob("*.log"))
    assert (tmp_path / "manifests" / "b" / "index.json").is_file()
    assert any(fetched.rglob(".paradrive/*.json"))  # the markers are among what is searched
    assert _files_holding(SECRET, fetched, tmp_path / "cache", tmp_path / "manifests") == []
    assert SECRET not in res.stdout + res.stderr + bad.stdout + bad.stderr
    # what the ledger recorded still says what ran
    from paradrive.pipeline.ledger import Ledger

    (run,) = Ledger.for_build(tmp_path / "manifests", "b").runs()
    assert "--storage-option key=***" in run["command"] and "endpoint_url=" in run["command"]


def test_credentials_are_masked_in_urls_options_and_command_lines(monkeypatch):
    from paradrive.redact import redact, redact_argv, redact_options
    from paradrive.storage import DataRoot

    assert redact(f"connect to https://me:{SECRET}@minio:9000/b failed") == \
        "connect to https://***@minio:9000/b failed"
    assert redact(f"token {SECRET}-abc rejected", {"client_kwargs": {"aws_session_token":
                                                                   f"{SECRET}-abc"}}) == \
        "token *** rejected"
    monkeypatch.setenv("FSSPEC_S3_SECRET", f"{SECRET}-env")
    assert redact(f"signature of {SECRET}-env") == "signature of ***"
    assert redact_options({"key": "AKIA1", "endpoint_url": f"http://u:{SECRET}@h",
                           "client_kwargs": {"region_name": "eu", "password": "p"}}) == \
        {"key": "***", "endpoint_url": "http://***@h",
         "client_kwargs": {"region_name": "eu", "password": "***"}}
    assert redact_argv(["paradrive", "build", "--storage-option", f"secret={SECRET}",
                        f"--storage-option=token={SECRET}", "--storage-option", "anon=true",
                        "--data", f"ftp://u:{SECRET}@host/d"]) == \
        ["paradrive", "build", "--storage-option", "secret=***", "--storage-option=token=***",
         "--storage-option", "anon=true", "--data", "ftp://***@host/d"]
    root = DataRoot.of(f"ftp://u:{SECRET}@host/d", storage_options={"password": SECRET})
    for shown in (str(root), repr(root), root.scene_location("s"), str(root.local)):
        assert SECRET not in shown, shown


# --------------------------------------------------------------------------- scenes out of the data

def test_list_file_lines_leading_out_of_its_folder_are_refused(tmp_path):
    from paradrive.errors import ConfigError
    from paradrive.pipeline.scenes import expand_scene_inputs

    outside = tmp_path / "elsewhere" / "segment-9.tfrecord"
    outside.parent.mkdir()
    outside.write_bytes(b"")
    lists = tmp_path / "lists"
    (lists / "logs").mkdir(parents=True)
    (lists / "logs" / "segment-1.tfrecord").write_bytes(b"")
    for number, line in ((2, "../elsewhere/segment-9.tfrecord"), (2, str(outside))):
        listing = lists / "scenes.txt"
        listing.write_text(f"logs/segment-1.tfrecord\n{line}\n")
        with pytest.raises(ConfigError, match=rf"scenes.txt:{number}: '{re.escape(line)}' resolves "
                                              rf"to {re.escape(str(outside))}, outside {lists}"):
            expand_scene_inputs([str(listing)])
    # the same log named by a URI is the user's explicit choice
    listing.write_text(f"logs/segment-1.tfrecord\nwaymo:{outside}\n")
    assert expand_scene_inputs([str(listing)]) == [f"waymo:{lists / 'logs' / 'segment-1.tfrecord'}",
                                                   f"waymo:{outside}"]


def test_a_log_linked_into_a_folder_of_logs_from_outside_is_refused(tmp_path):
    from paradrive.errors import ConfigError
    from paradrive.pipeline.scenes import expand_scene_inputs

    outside = tmp_path / "elsewhere" / "segment-9.tfrecord"
    outside.parent.mkdir()
    outside.write_bytes(b"")
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "segment-1.tfrecord").write_bytes(b"")
    (logs / "segment-9.tfrecord").symlink_to(outside)
    with pytest.raises(ConfigError, match=r"segment-9.tfrecord resolves to .*elsewhere.*outside"):
        expand_scene_inputs([str(logs)])


def test_a_drivestudio_folder_linking_out_is_refused_at_ingest(tmp_path):
    from paradrive.errors import SceneError
    from paradrive.ingest.drivestudio import read
    from paradrive.uri import parse_uri

    scene = tmp_path / "processed" / "023"
    (scene / "images").mkdir(parents=True)
    (scene / "ego_pose").mkdir()
    (scene / "extrinsics").mkdir()
    (scene / "intrinsics").symlink_to(tmp_path)
    with pytest.raises(SceneError, match=r"scene drivestudio-023: 1 link\(s\) in the scene folder "
                                         r"lead out of it, e.g. intrinsics"):
        read(parse_uri(f"drivestudio:{scene}"), tmp_path / "out", {}, "drivestudio-023")


@pytest.mark.parametrize("scene_id", ["..", "../x", "a/b", "/etc"])
def test_a_scene_id_that_is_not_a_file_name_is_refused(tmp_path, scene_id):
    from paradrive.errors import ConfigError
    from paradrive.pipeline.runner import scene_dir_for
    from paradrive.uri import parse_uri

    with pytest.raises(ConfigError, match="not a plain file name"):
        scene_dir_for(tmp_path, scene_id)
    # ids derived from URIs never are
    assert parse_uri("drivestudio:/x/..#../..").scene_id == "drivestudio"
    assert scene_dir_for(tmp_path, parse_uri("nuscenes:/d#../../etc").scene_id).parent == \
        tmp_path / "scenes"


def test_a_trainer_checkpoint_naming_code_to_import_is_refused_for_sampling(tmp_path):
    from paradrive.train import Trainer, load_for_sampling

    class Pairs(torch.utils.data.Dataset):
        def __len__(self) -> int:
            return 2

    Trainer(_tiny_train_config(), 1, tmp_path / "run", Pairs()).save()
    ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    marker = tmp_path / "ran"
    # plain strings, loadable without pickle, that would call write_text(path=marker) on import
    ckpt["config"]["autoencoder"] = {"kind": "paradrive.io:write_text",
                                     "options": {"path": str(marker), "text": "ran"}}
    torch.save(ckpt, tmp_path / "foreign.pt")
    with pytest.raises(UnsafeFileError, match="foreign.pt: its autoencoder is code imported by name"):
        load_for_sampling(tmp_path / "foreign.pt", device="cpu")
    assert not marker.exists()
