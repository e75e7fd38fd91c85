"""Reading a published build safely: a ``media: symlink`` build's links may lead only to the
exact clip file of one of its own scenes, whatever ``index.json`` says, and a damaged shard is
reported as corrupt in one line, like any other file."""

from __future__ import annotations

import hashlib
import json
import pathlib
import re
import shutil
import sys

import pyarrow.parquet as pq
import pytest
import typer
from typer.testing import CliRunner

from conftest import stage_params
from paradrive.data import PairDataset
from paradrive.errors import ParaDriveError
from paradrive.commands.inspect import register
from paradrive.inspection import verify_build
from paradrive.io import PathEscapeError
from paradrive.pairs import read_index, version_dir
from paradrive.stages.manifest import build_manifest
from test_manifest import scenes_entry, write_clip_scene
from test_security import OPENED, _record_opens

SECRET = pathlib.Path("/etc/passwd")


@pytest.fixture(scope="module")
def watch_opens():
    """Every file this process opens from Python code (a real audit hook, sys.addaudithook)."""
    sys.addaudithook(_record_opens)   # audit hooks stay for the process: the list is cleared
    return OPENED


@pytest.fixture(scope="module")
def symlink_build(tmp_path_factory):
    """One scene x 2 pairs, its media linked (``media: symlink``) into the scene folder."""
    data = tmp_path_factory.mktemp("data")
    scene = write_clip_scene(data, "synthetic-a", clips=("middle",), offsets=(1.0, 2.0),
                             conditions=(100,))
    build = tmp_path_factory.mktemp("manifests") / "b"
    build_manifest(build, [scenes_entry(scene)], stage_params("manifest", {"media": "symlink"}))
    return build


def inspect(build: pathlib.Path, *args: str):
    app = typer.Typer()
    app.callback()(lambda: None)
    register(app)
    return CliRunner().invoke(app, ["inspect", str(build), *args], env={"COLUMNS": "400"})


def edited(build: pathlib.Path, dst: pathlib.Path, row: dict, index: dict | None = None) -> str:
    """A copy of ``build`` whose first row takes the values of ``row`` and whose index takes
    those of ``index`` (shard checksums updated, so only those values are wrong); its pair id."""
    shutil.copytree(build, dst, symlinks=True)
    doc = json.loads((dst / "index.json").read_text())
    shard = dst / doc["version"] / doc["shards"][0]["file"]
    rows = pq.read_table(shard).to_pylist()
    rows[0].update(row)
    table = pq.read_table(shard).schema.empty_table().from_pylist(rows, schema=pq.read_schema(shard))
    pq.write_table(table, shard)
    data = shard.read_bytes()
    doc["shards"][0].update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    doc.update(index or {})
    (dst / "index.json").write_text(json.dumps(doc))
    return rows[0]["pair_id"]


def _passwd_row() -> dict:
    data = SECRET.read_bytes()
    return {"target_uri": "media/etc/passwd", "target_sha256": hashlib.sha256(data).hexdigest(),
            "target_bytes": len(data)}


def _link(build: pathlib.Path, uri: str, target: pathlib.Path) -> None:
    link = version_dir(build, read_index(build)) / uri
    link.parent.mkdir(parents=True, exist_ok=True)
    link.unlink(missing_ok=True)
    link.symlink_to(target)


def _refused(build: pathlib.Path, pair_id: str, column: str, opened: list) -> None:
    """The adapter and verify both refuse the row's link, and ``/etc/passwd`` is never opened."""
    opened.clear()
    ds = PairDataset(build)
    # (an index edited to name "/" as the data root makes every link of the row refused)
    with pytest.raises(PathEscapeError, match=rf"row {re.escape(pair_id)} column \w+_uri.*outside"):
        ds[ds.pair_ids.index(pair_id)]
    result = verify_build(build)
    assert not result["ok"]
    assert any(p.startswith("unsafe:") and f"row {pair_id} column {column}" in p
               for p in result["problems"])
    assert str(SECRET) not in [str(pathlib.Path(p).resolve()) for p in opened]


@pytest.mark.parametrize("index", [
    {},                                                             # the build as published
    {"media": {"mode": "symlink", "placed": {}, "data_root": "/"}},  # an index edited to allow it
])
def test_a_symlink_build_link_to_etc_passwd_is_refused(symlink_build, tmp_path, watch_opens,
                                                       index):
    build = tmp_path / "b"
    pair_id = edited(symlink_build, build, _passwd_row(), index)
    if index:  # the edited index also lists a scene named like the link's folder
        doc = json.loads((build / "index.json").read_text())
        doc["scenes"].append({**doc["scenes"][0], "scene_id": "etc"})
        (build / "index.json").write_text(json.dumps(doc))
    _link(build, "media/etc/passwd", SECRET)
    _refused(build, pair_id, "target_uri", watch_opens)
    result = inspect(build, "--verify")
    assert result.exit_code == 1 and "unsafe:" in result.output and "verified" not in result.output


def test_a_symlink_build_link_to_another_clip_of_its_scene_is_refused(symlink_build, tmp_path,
                                                                      watch_opens):
    build = tmp_path / "b"
    shutil.copytree(symlink_build, build, symlinks=True)
    ds = PairDataset(build)
    row = ds.row(0)
    other = pathlib.Path(read_index(build).media.data_root) / "scenes/synthetic-a" / \
        row["target_uri"].split("/", 2)[2]
    _link(build, row["condition_uri"], other)   # a real clip, but not the one the row names
    _refused(build, ds.pair_ids[0], "condition_uri", watch_opens)


def test_a_symlink_build_link_moved_under_another_data_root_is_refused(symlink_build, tmp_path):
    build = tmp_path / "b"
    shutil.copytree(symlink_build, build, symlinks=True)
    copy = tmp_path / "copy"
    shutil.copytree(read_index(build).media.data_root, copy)
    ds = PairDataset(build)
    uri = ds.row(0)["source_uri"]
    _link(build, uri, copy / "scenes/synthetic-a" / uri.split("/", 2)[2])  # same name, other root
    with pytest.raises(PathEscapeError, match="column source_uri"):
        ds[0]
    assert verify_build(symlink_build)["ok"]   # the build itself still reads


# --------------------------------------------------------------------------- damaged shards

@pytest.fixture(scope="module")
def copy_build(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    scene = write_clip_scene(data, "synthetic-a", clips=("middle",), offsets=(1.0,),
                             conditions=(100,))
    build = tmp_path_factory.mktemp("manifests") / "b"
    build_manifest(build, [scenes_entry(scene)], stage_params("manifest", {"media": "copy"}))
    return build


def _truncate(build: pathlib.Path, dst: pathlib.Path, *, index_agrees: bool) -> pathlib.Path:
    shutil.copytree(build, dst)
    doc = json.loads((dst / "index.json").read_text())
    shard = dst / doc["version"] / doc["shards"][0]["file"]
    shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 2])
    if index_agrees:  # the checksums say nothing: only reading it shows the damage
        data = shard.read_bytes()
        doc["shards"][0].update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
        (dst / "index.json").write_text(json.dumps(doc))
    return shard


@pytest.mark.parametrize("index_agrees", [False, True])
def test_inspect_verify_reports_a_truncated_shard_as_corrupt_in_one_line(copy_build, tmp_path,
                                                                         index_agrees):
    shard = _truncate(copy_build, tmp_path / "b", index_agrees=index_agrees)
    result = inspect(tmp_path / "b", "--verify")
    assert result.exit_code == 1
    assert "Traceback" not in result.output and "ArrowInvalid" not in result.output.split(";")[-1]
    problems = [line for line in result.output.splitlines() if line.startswith("corrupt:")]
    assert len(problems) == 1 and str(shard) in problems[0] and "re-run the build" in problems[0]
    assert len(result.output.strip().splitlines()) == 2   # the problem and the count


def test_reading_a_truncated_shard_names_it(copy_build, tmp_path):
    shard = _truncate(copy_build, tmp_path / "b", index_agrees=True)
    with pytest.raises(ParaDriveError, match=rf"corrupt: {re.escape(str(shard))}.*re-run the build"):
        PairDataset(tmp_path / "b")
    result = inspect(tmp_path / "b")   # no --verify: a usage error that names the file
    assert result.exit_code == 2 and f"corrupt: {shard}" in result.output
