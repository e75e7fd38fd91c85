"""A URL as the data root: stages run on a node's copy of a scene; the remote folder is the truth.

fsspec's in-memory filesystem (``memory://``) stands for an object store within one process; the
``local://`` protocol is a filesystem without whole-object writes (uploads go through a temporary
name and a rename). The Ray tests build to S3 (``test_ray_executor``).
"""

from __future__ import annotations

import json
import shutil
import uuid
from pathlib import Path

import pytest

from paradrive.errors import ConfigError
from paradrive.pipeline import run_build
from paradrive.storage import DataRoot, SceneMirror, is_url, matches

import pipeline_stages

SCENES = [f"synthetic:street?seed={s}" for s in (1, 2)]
IDS = ["synthetic-street-s1", "synthetic-street-s2"]
BOOKKEEPING = (".paradrive", "logs", "calls.log", ".sync")


@pytest.fixture
def memory_root(tmp_path):
    """A fresh memory:// root (the in-memory filesystem is shared by the whole process)."""
    url = f"memory://bucket-{uuid.uuid4().hex[:8]}/run"
    yield DataRoot.of(url, cache_dir=str(tmp_path / "cache"))
    fs, base = DataRoot.of(url).filesystem()
    fs.rm(base.rsplit("/", 1)[0], recursive=True)


def remote_tree(root: DataRoot, under: str = "scenes") -> dict[str, bytes]:
    """Every remote file under ``under`` (relative path -> bytes), bookkeeping left out."""
    fs, base = root.filesystem()
    prefix = f"{base}/{under}".lstrip("/") + "/"
    out = {}
    for name in fs.find(f"{base}/{under}"):
        rel = name.lstrip("/")[len(prefix):]
        if not any(part.startswith(BOOKKEEPING) for part in rel.split("/")):
            out[rel] = fs.cat_file(name)
    return out


def local_tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not any(part.startswith(BOOKKEEPING)
                                       for part in p.relative_to(folder).parts)}


def build(config, scenes, root, manifests: Path):
    return run_build(config, scenes, root, manifests_dir=manifests, build="b")


def test_urls_and_folders_are_told_apart(tmp_path):
    assert is_url("s3://bucket/x") and is_url("memory://x") and is_url("gs://b")
    assert not is_url("data") and not is_url("/abs/data") and not is_url("file:///abs/data")
    assert DataRoot.of(f"file://{tmp_path}/data").location == str(tmp_path / "data")
    assert DataRoot.of("data").local == Path("data").resolve()
    root = DataRoot.of("s3://bucket/run/", cache_dir=str(tmp_path))
    assert root.location == "s3://bucket/run" and root.remote
    assert root.local.parent == tmp_path / "data" and root.local.name.startswith("bucket-run-")
    assert DataRoot.of("s3://other/run", cache_dir=str(tmp_path)).local != root.local


def test_outputs_match_files_and_folders():
    assert matches("images/000001.jpg", ["images"]) and matches("gs/ckpt_000100.ply", ["gs/ckpt_*.ply"])
    assert not matches("images2/a.jpg", ["images"]) and not matches("scene.json.bak", ["scene.json"])


def test_a_build_to_a_url_equals_a_build_to_a_folder(stage_config, memory_root, tmp_path):
    folder = build(stage_config(), SCENES, tmp_path / "folder" / "data",
                   tmp_path / "folder" / "manifests")
    remote = build(stage_config(), SCENES, memory_root, tmp_path / "url" / "manifests")
    assert folder.exit_code == remote.exit_code == 0
    expected = local_tree(tmp_path / "folder" / "data" / "scenes")
    assert remote_tree(memory_root) == expected and len(expected) == 2 * 12
    assert (tmp_path / "url/manifests/b/pairs.jsonl").read_bytes() == \
        (tmp_path / "folder/manifests/b/pairs.jsonl").read_bytes()
    fs, base = memory_root.filesystem()
    markers = sorted(p.rsplit("/", 1)[1] for p in fs.find(f"{base}/scenes/{IDS[0]}/.paradrive"))
    assert markers == ["clip.json", "fit.json", "ingest.json", "render.json"]
    log = fs.cat_file(f"{base}/logs/{IDS[0]}.log").decode()
    assert "clip: done" in log and "uploaded to memory://" in log


def test_a_rerun_decides_from_the_remote_folder_even_with_an_empty_cache(stage_config, memory_root,
                                                                         tmp_path):
    build(stage_config(), SCENES, memory_root, tmp_path / "manifests")
    shutil.rmtree(memory_root.local)
    report = build(stage_config(), SCENES, memory_root, tmp_path / "manifests")
    assert {r.status for r in report.results} == {"skipped"}
    assert pipeline_stages.calls(memory_root.local) == []
    # a skip downloads markers only
    assert not (memory_root.local / "scenes" / IDS[0] / "images").exists()
    assert (memory_root.local / "scenes" / IDS[0] / ".paradrive" / "fit.json").is_file()


def test_a_changed_parameter_redoes_its_stage_and_the_later_ones_on_the_remote(
        stage_config, memory_root, tmp_path):
    build(stage_config(), SCENES[:1], memory_root, tmp_path / "manifests")
    before = remote_tree(memory_root)
    report = build(stage_config({"render": {"offsets_m": [2.0, -2.0]}}), SCENES[:1], memory_root,
                   tmp_path / "manifests")
    assert [(r.stage, r.status) for r in report.results] == [
        ("ingest", "skipped"), ("fit", "skipped"), ("render", "done"), ("clip", "done"),
        ("manifest", "done")]
    after = remote_tree(memory_root)
    sid = IDS[0]
    assert f"{sid}/renders/+2m.txt" in after and after[f"{sid}/clips/clips.json"] != \
        before[f"{sid}/clips/clips.json"]
    assert after[f"{sid}/gs/ckpt_000002.txt"] == before[f"{sid}/gs/ckpt_000002.txt"]


def test_a_failed_stage_uploads_nothing_and_the_rerun_finishes_it(stage_config, memory_root,
                                                                   tmp_path):
    broken = memory_root.local / f"broken-{IDS[1]}-render"
    broken.parent.mkdir(parents=True)
    broken.write_text("render fails until this file goes\n")
    report = build(stage_config(), SCENES, memory_root, tmp_path / "manifests")
    assert report.exit_code == 3
    tree = remote_tree(memory_root)
    assert f"{IDS[1]}/gs/fit.json" in tree  # fit landed
    assert not any(rel.startswith(f"{IDS[1]}/renders") for rel in tree)
    fs, base = memory_root.filesystem()
    assert not fs.exists(f"{base}/scenes/{IDS[1]}/.paradrive/render.json")
    broken.unlink()
    n = len(pipeline_stages.calls(memory_root.local))
    assert build(stage_config(), SCENES, memory_root, tmp_path / "manifests").exit_code == 0
    ran = [(stage, sid) for event, stage, sid in pipeline_stages.calls(memory_root.local)[n:]
           if event == "end"]
    assert ran == [("render", IDS[1]), ("clip", IDS[1]), ("manifest", "build")]


def test_outputs_without_their_marker_are_not_done(stage_config, memory_root, tmp_path):
    """A worker killed between uploading a stage's files and its marker: the stage runs again."""
    build(stage_config(), SCENES[:1], memory_root, tmp_path / "manifests")
    fs, base = memory_root.filesystem()
    fs.rm_file(f"{base}/scenes/{IDS[0]}/.paradrive/clip.json")
    # the cache still holds the marker, as the dead worker's node would
    assert (memory_root.local / "scenes" / IDS[0] / ".paradrive" / "clip.json").is_file()
    n = len(pipeline_stages.calls(memory_root.local))
    report = build(stage_config(), SCENES[:1], memory_root, tmp_path / "manifests")
    assert [(r.stage, r.status) for r in report.results][2:4] == [("render", "skipped"),
                                                                  ("clip", "done")]
    assert [c[:2] for c in pipeline_stages.calls(memory_root.local)[n:]] == [
        ("start", "clip"), ("end", "clip"), ("end", "manifest")]
    assert fs.exists(f"{base}/scenes/{IDS[0]}/.paradrive/clip.json")


def test_a_changed_remote_file_is_downloaded_again_and_an_unchanged_one_is_not(memory_root):
    fs, base = memory_root.filesystem()
    fs.pipe_file(f"{base}/scenes/s/a.txt", b"one")
    fs.pipe_file(f"{base}/scenes/s/b/c.txt", b"two")
    mirror = SceneMirror(memory_root, "s")
    mirror.refresh()
    assert mirror.pull() == 2 and (mirror.local / "b" / "c.txt").read_bytes() == b"two"
    mirror = SceneMirror(memory_root, "s")  # the record survives the process
    mirror.refresh()
    assert mirror.pull() == 0
    fs.pipe_file(f"{base}/scenes/s/a.txt", b"three")
    mirror.refresh()
    assert mirror.pull() == 1 and (mirror.local / "a.txt").read_bytes() == b"three"


def test_push_uploads_what_changed_deletes_what_was_removed_and_the_marker_last(tmp_path,
                                                                              monkeypatch):
    """On a filesystem without whole-object writes every upload goes through a temporary name."""
    root = DataRoot.of(f"local://{tmp_path / 'remote'}", cache_dir=str(tmp_path / "cache"))
    mirror = SceneMirror(root, "s")
    assert not mirror.whole_objects
    remote = tmp_path / "remote" / "scenes" / "s"
    (remote / "renders").mkdir(parents=True)
    (remote / "renders" / "old.png").write_bytes(b"old")
    (remote / "keep.txt").write_bytes(b"keep")
    mirror.refresh()
    mirror.pull()
    before = mirror.snapshot()
    shutil.rmtree(mirror.local / "renders")  # the stage replaced its folder
    (mirror.local / "renders").mkdir()
    (mirror.local / "renders" / "new.png").write_bytes(b"new")
    (mirror.local / ".paradrive").mkdir()
    (mirror.local / ".paradrive" / "render.json").write_text("{}")
    moves = []
    real_mv = mirror.fs.mv
    monkeypatch.setattr(mirror.fs, "mv", lambda a, b, **kw: (moves.append((a, b)),
                                                             real_mv(a, b, **kw)))
    assert mirror.push(before, last=[".paradrive/render.json"]) == (2, 1)
    assert sorted(p.relative_to(remote).as_posix() for p in remote.rglob("*") if p.is_file()) == [
        ".paradrive/render.json", "keep.txt", "renders/new.png"]
    assert [b.rsplit("/", 2)[-2:] for _, b in moves] == [["renders", "new.png"],
                                                         [".paradrive", "render.json"]]
    assert all(".tmp-" in a for a, _ in moves)


def test_drop_cache_keeps_no_scene_copy(stage_config, tmp_path):
    url = f"memory://bucket-{uuid.uuid4().hex[:8]}/run"
    root = DataRoot.of(url, cache_dir=str(tmp_path / "cache"), drop_cache=True)
    assert build(stage_config(), SCENES[:1], root, tmp_path / "manifests").exit_code == 0
    assert not (root.local / "scenes" / IDS[0] / "images").exists()
    assert len(remote_tree(root)) == 12


def test_a_url_without_its_backend_is_a_usage_error_that_names_the_package():
    with pytest.raises(ConfigError, match="install the fsspec backend"):
        DataRoot.of("nosuchproto://bucket/x").filesystem()


def test_the_cli_takes_a_url_and_storage_options(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from paradrive.cli import app

    folder = pipeline_stages.write_stages(tmp_path / "stages")
    monkeypatch.setenv("PARADRIVE_STAGES", str(folder))
    url = f"memory://bucket-{uuid.uuid4().hex[:8]}/run"
    args = ["build", "--scene", SCENES[0], "--data", url, "--cache", str(tmp_path / "cache"),
            "--manifests", str(tmp_path / "manifests"), "--build", "b"]
    res = CliRunner().invoke(app, args, env={"COLUMNS": "250"})
    assert res.exit_code == 0, res.output
    assert len(remote_tree(DataRoot.of(url))) == 12
    res = CliRunner().invoke(app, args[:3] + ["--data", str(tmp_path / "d"), "--storage-option",
                                              "anon=true"], env={"COLUMNS": "250"})
    assert res.exit_code == 2 and "apply to a URL --data" in res.output
    res = CliRunner().invoke(app, args + ["--storage-option", "anon"], env={"COLUMNS": "250"})
    assert res.exit_code == 2 and "write KEY=VALUE" in res.output
    doc = json.loads((tmp_path / "manifests" / "b" / "index.json").read_text())
    assert doc["rows"] == 2


def test_a_scene_of_a_url_root_is_brought_whole_for_local_readers(stage_config, memory_root,
                                                                  tmp_path):
    """What ``paradrive eval --data s3://…`` reads: the scene as a folder in the cache."""
    from paradrive.storage import local_scene

    build(stage_config(), SCENES[:1], memory_root, tmp_path / "manifests")
    shutil.rmtree(memory_root.local)
    folder = local_scene(memory_root, IDS[0])
    assert local_tree(folder) == {k[len(IDS[0]) + 1:]: v for k, v in remote_tree(memory_root).items()}

    unreachable = DataRoot.of("s3://no-such-bucket/x", cache_dir=str(tmp_path / "c"), storage_options={
        "endpoint_url": "http://127.0.0.1:9", "key": "k", "secret": "s",
        "config_kwargs": {"retries": {"max_attempts": 1}, "connect_timeout": 1}})
    with pytest.raises(ConfigError, match="refresh of s3://no-such-bucket/x/scenes/scene failed.*"
                                          "check the URL, the credentials and the network"):
        local_scene(unreachable, "scene")
    # a build to it fails each scene with that reason instead of stopping
    report = build(stage_config(), SCENES[:1], unreachable, tmp_path / "m2")
    assert report.exit_code == 1
    assert "s3://no-such-bucket/x/scenes/synthetic-street-s1" in report.failures()[0].error
