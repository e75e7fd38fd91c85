"""Where scene outputs live: a local folder or an fsspec URL (``s3://bucket/prefix``, ``gs://…``).

Stages work on local files: images, PLYs, EXRs and videos go through libraries that need paths.
With a URL as the data root, each (scene, stage) runs on a local copy of the scene folder (the
node's cache, ``$PARADRIVE_CACHE`` or ``~/.cache/paradrive``) and the remote folder is the truth:

1. list the remote scene folder and fetch its stage markers; a stage whose marker matches and
   whose recorded outputs are listed with their sizes is skipped without downloading anything else;
2. otherwise withdraw the stage's remote marker, then download what the stage reads
   (``reads`` in its YAML, default the whole scene folder) that the cache lacks or holds an older
   version of;
3. run the stage on the cache;
4. upload the files the stage wrote, delete the remote copies of those it removed, and upload its
   marker last.

The marker is the commit: a stage without one is not done, whatever files are there, so a worker
killed mid-upload leaves work that the next run redoes. Object stores write each object whole;
on other filesystems (sftp, ftp, a mounted folder through ``file://``…) every file is uploaded
under a temporary name and renamed, so no half-written file ever carries a final name.
"""

from __future__ import annotations

import contextlib
import fnmatch
import functools
import hashlib
import json
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Iterable

from paradrive.errors import ConfigError
from paradrive.io import is_temporary, temporary_name, write_json
from paradrive.contracts.layout import LOGS_DIR, SCENES_DIR, DataLayout, SceneLayout
from paradrive.redact import redact, redact_options

OBJECT_STORES = frozenset({"s3", "s3a", "gs", "gcs", "az", "abfs", "abfss", "adl", "oss", "memory"})
_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")


class StorageError(OSError):
    """A remote data root could not be read or written (network, credentials, bucket, quota)."""


def _remote_call(method):
    """Any failure of a remote operation becomes a StorageError naming the scene's URL."""
    @functools.wraps(method)
    def wrapper(self: SceneMirror, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except StorageError:
            raise
        except Exception as exc:  # fsspec backends raise their own types (botocore, aiohttp…)
            raise StorageError(redact(f"{method.__name__} of {self.root.scene_location(self.scene_id)} "
                                      f"failed: {type(exc).__name__}: {exc}; check the URL, the "
                                      f"credentials and the network, then re-run",
                                      self.root.storage_options)) from exc
    return wrapper


def is_url(text: str | os.PathLike) -> bool:
    """True for ``proto://…`` other than ``file://`` (a local folder)."""
    text = str(text)
    return bool(_URL.match(text)) and not text.startswith("file://")


def default_cache() -> Path:
    return Path(os.environ.get("PARADRIVE_CACHE") or Path.home() / ".cache" / "paradrive")


@dataclass(frozen=True)
class DataRoot:
    """A build's data root. ``location`` is an absolute local path or a URL.

    ``storage_options`` go to fsspec (``endpoint_url``, ``key``, ``anon``…; credentials usually
    come from the environment instead). ``cache_dir`` is where a URL root's scenes are copied on
    each node (default: ``$PARADRIVE_CACHE`` there, else ``~/.cache/paradrive``);
    ``drop_cache`` removes a scene's copy once its stage is uploaded.
    """

    location: str
    storage_options: dict = field(default_factory=dict)
    cache_dir: str | None = None
    drop_cache: bool = False

    @classmethod
    def of(cls, value: DataRoot | str | os.PathLike, **options) -> DataRoot:
        if isinstance(value, DataRoot):
            return value
        text = str(value)
        if text.startswith("file://"):
            text = text[len("file://"):]
        if is_url(text):
            return cls(text.rstrip("/"), **options)
        return cls(str(Path(text).expanduser().resolve()), **options)

    @property
    def remote(self) -> bool:
        return is_url(self.location)

    @property
    def local(self) -> Path:
        """Where stages read and write: the folder itself, or this node's cache of the URL."""
        if not self.remote:
            return Path(self.location)
        digest = hashlib.sha256(self.location.encode()).hexdigest()[:12]
        name = re.sub(r"[^A-Za-z0-9_.-]+", "-", str(self).split("://", 1)[1]).strip("-")[:48]
        return Path(self.cache_dir or default_cache()).expanduser().resolve() / "data" / f"{name}-{digest}"

    def filesystem(self) -> tuple[Any, str]:
        """(fsspec filesystem, root path inside it); fsspec keeps one instance per options."""
        import fsspec

        try:
            fs, path = fsspec.core.url_to_fs(self.location, **self.storage_options)
        except (ImportError, ValueError) as exc:
            raise ConfigError(redact(f"data root {self.location}: {exc}; install the fsspec backend "
                                     f"for it (s3fs for s3://, gcsfs for gs://, adlfs for az://)",
                                     self.storage_options)) from exc
        return fs, path.rstrip("/")

    def scene_location(self, scene_id: str) -> str:
        """Where the scene lives, to show or record (a URL without its credentials)."""
        return f"{self}/{SCENES_DIR}/{scene_id}" if self.remote else str(SceneLayout.of(self.local, scene_id).root)

    def mirror(self, scene_id: str) -> SceneMirror | None:
        """The scene's remote/local pair for a URL root; None for a local folder."""
        return SceneMirror(self, scene_id) if self.remote else None

    def __str__(self) -> str:
        return redact(self.location, self.storage_options)

    def __repr__(self) -> str:  # options and URLs may hold credentials
        return (f"DataRoot({str(self)!r}, storage_options={redact_options(self.storage_options)!r}, "
                f"cache_dir={self.cache_dir!r}, drop_cache={self.drop_cache!r})")


def local_scene(root: DataRoot, scene_id: str) -> Path:
    """A scene folder to read locally: the folder itself, or a URL root's scene brought to the cache."""
    mirror = root.mirror(scene_id)
    if mirror is not None:
        try:
            mirror.refresh()
            mirror.pull()
        except StorageError as exc:
            raise ConfigError(f"cannot read the scene: {exc}") from exc
    return SceneLayout.of(root.local, scene_id).root


def _token(info: dict) -> str:
    """What identifies one version of a remote file: its size and its etag or modification time."""
    version = (info.get("ETag") or info.get("etag") or info.get("md5") or info.get("mtime")
               or info.get("LastModified") or info.get("last_modified") or info.get("created") or "")
    return f"{info.get('size')}:{version}"


def _is_temporary(rel: str) -> bool:
    return any(is_temporary(part) for part in rel.split("/"))


def file_stats(folder: Path) -> dict[str, tuple[int, int]]:
    """Files under ``folder`` (temporaries left out): relative path -> (size, mtime_ns)."""
    out = {}
    if folder.is_dir():
        for dirpath, _, files in os.walk(folder):
            for f in files:
                p = Path(dirpath) / f
                rel = p.relative_to(folder).as_posix()
                if not _is_temporary(rel):
                    with contextlib.suppress(FileNotFoundError):  # removed while walking
                        st = p.stat()
                        out[rel] = (st.st_size, st.st_mtime_ns)
    return out


def matches(rel: str, patterns: Iterable[str]) -> bool:
    """``rel`` is one of the files ``patterns`` name (a glob, or a folder and everything in it)."""
    return any(fnmatch.fnmatchcase(rel, p) or fnmatch.fnmatchcase(rel, p.rstrip("/") + "/*")
               for p in patterns)


class SceneMirror:
    """One scene folder of a URL data root and its local copy (see the module doc)."""

    def __init__(self, root: DataRoot, scene_id: str):
        self.root = root
        self.scene_id = scene_id
        self.fs, base = root.filesystem()
        self.remote = f"{base}/{SCENES_DIR}/{scene_id}"
        self.local = SceneLayout.of(root.local, scene_id).root
        self.log_remote = f"{base}/{LOGS_DIR}/{scene_id}.log"
        self.log_local = DataLayout(root.local).log(scene_id)
        self.record_path = root.local / ".sync" / f"{scene_id}.json"
        protocol = self.fs.protocol if isinstance(self.fs.protocol, str) else self.fs.protocol[0]
        self.whole_objects = protocol in OBJECT_STORES
        self.listing: dict[str, dict] = {}
        try:
            self.record: dict[str, str] = json.loads(self.record_path.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            self.record = {}

    # -- what is there ------------------------------------------------------------------------

    @_remote_call
    def refresh(self) -> dict[str, dict]:
        """List the remote scene folder: relative path -> fsspec info (temporaries left out)."""
        try:
            found = self.fs.find(self.remote, detail=True)
        except FileNotFoundError:
            found = {}
        prefix = self.remote.strip("/") + "/"
        self.listing = {}
        for name, info in found.items():
            name = name.lstrip("/")  # some filesystems keep a root marker, some do not
            if info.get("type", "file") != "file" or not name.startswith(prefix):
                continue
            rel = name[len(prefix):]
            if not _is_temporary(rel):
                self.listing[rel] = info
        return self.listing

    def exists(self, pattern: str) -> bool:
        """A declared output (glob or folder) is in the last listing."""
        return any(matches(rel, [pattern]) for rel in self.listing)

    # -- down ---------------------------------------------------------------------------------

    @_remote_call
    def pull(self, patterns: list[str] | None = None, *, prune: bool = False) -> int:
        """Bring the listed files (those ``patterns`` name; None = all) whose cached copy is
        missing or older; returns how many were downloaded. ``prune`` also deletes cached files
        that ``patterns`` name but the remote folder no longer has (stage markers)."""
        if prune and patterns is not None:
            for rel in self.snapshot():
                if matches(rel, patterns) and rel not in self.listing:
                    (self.local / rel).unlink(missing_ok=True)
                    self.record.pop(rel, None)
        todo = []
        for rel, info in sorted(self.listing.items()):
            if patterns is not None and not matches(rel, patterns):
                continue
            target = self.local / rel
            if (self.record.get(rel) == _token(info) and target.is_file()
                    and target.stat().st_size == info.get("size")):
                continue
            todo.append(rel)
        if todo:
            temps = [temporary_name(self.local / rel) for rel in todo]
            for t in temps:
                t.parent.mkdir(parents=True, exist_ok=True)
            try:
                self.fs.get([f"{self.remote}/{rel}" for rel in todo], [str(t) for t in temps])
                for rel, t in zip(todo, temps):
                    os.replace(t, self.local / rel)
                    self.record[rel] = _token(self.listing[rel])
            finally:
                for t in temps:
                    t.unlink(missing_ok=True)
                self._save_record()
        return len(todo)

    def sync(self, patterns: list[str]) -> None:
        """List the remote folder, then make the cached copies of ``patterns`` equal the remote's:
        download what changed, delete what the remote no longer has (stage markers)."""
        self.refresh()
        self.pull(patterns, prune=True)

    @_remote_call
    def pull_log(self) -> None:
        """The scene's log so far (a stage appends to it)."""
        with contextlib.suppress(FileNotFoundError):
            info = self.fs.info(self.log_remote)
            if self.record.get("<log>") != _token(info) or not self.log_local.is_file():
                self.log_local.parent.mkdir(parents=True, exist_ok=True)
                tmp = temporary_name(self.log_local)
                try:
                    self.fs.get_file(self.log_remote, str(tmp))
                    os.replace(tmp, self.log_local)
                finally:
                    tmp.unlink(missing_ok=True)
                self.record["<log>"] = _token(info)

    # -- up -----------------------------------------------------------------------------------

    def snapshot(self) -> dict[str, tuple[int, int]]:
        """Local files of the scene: relative path -> (size, mtime_ns)."""
        return file_stats(self.local)

    @_remote_call
    def withdraw(self, rel: str) -> None:
        """Delete one remote file (a stage's marker before the stage runs again)."""
        with contextlib.suppress(FileNotFoundError):
            self.fs.rm_file(f"{self.remote}/{rel}")
        self.listing.pop(rel, None)
        self.record.pop(rel, None)

    @_remote_call
    def remove(self, rels: list[str]) -> None:
        """Delete remote files (outputs a retention policy let go) and forget them."""
        there = [rel for rel in rels if rel in self.listing]
        if there:
            self.fs.rm([f"{self.remote}/{rel}" for rel in there])
        for rel in rels:
            self.listing.pop(rel, None)
            self.record.pop(rel, None)
        self._save_record()

    @_remote_call
    def push(self, before: dict[str, tuple[int, int]], last: list[str]) -> tuple[int, int]:
        """Upload what changed since ``before``, delete what was removed, then ``last`` (the
        marker). Returns (uploaded, deleted)."""
        after = self.snapshot()
        changed = [rel for rel, stat in after.items() if before.get(rel) != stat and rel not in last]
        removed = [rel for rel in before if rel not in after and rel in self.listing]
        self._upload(sorted(changed))
        if removed:
            self.fs.rm([f"{self.remote}/{rel}" for rel in removed])
            for rel in removed:
                self.record.pop(rel, None)
        self._upload([rel for rel in last if rel in after])
        self.refresh()
        for rel in changed + last:
            if rel in self.listing:
                self.record[rel] = _token(self.listing[rel])
        self._save_record()
        return len(changed) + len(last), len(removed)

    @_remote_call
    def push_log(self) -> None:
        if self.log_local.is_file():
            self._put([str(self.log_local)], [self.log_remote])
            with contextlib.suppress(FileNotFoundError):
                self.record["<log>"] = _token(self.fs.info(self.log_remote))
            self._save_record()

    def _upload(self, rels: list[str]) -> None:
        if rels:
            self._put([str(self.local / rel) for rel in rels], [f"{self.remote}/{rel}" for rel in rels])

    def _put(self, lpaths: list[str], rpaths: list[str]) -> None:
        if self.whole_objects:
            self.fs.put(lpaths, rpaths)
            return
        for parent in sorted({r.rsplit("/", 1)[0] for r in rpaths}):
            self.fs.makedirs(parent, exist_ok=True)
        temps = [temporary_name(Path(r)).as_posix() for r in rpaths]
        self.fs.put(lpaths, temps)
        for t, r in zip(temps, rpaths):
            self.fs.mv(t, r)

    # -- the cache ----------------------------------------------------------------------------

    def _save_record(self) -> None:
        write_json(self.record_path, self.record)

    def drop(self) -> None:
        """Remove the scene's local copy (``drop_cache``); the remote folder is untouched."""
        shutil.rmtree(self.local, ignore_errors=True)
        self.record_path.unlink(missing_ok=True)
        self.log_local.unlink(missing_ok=True)


def data_root(data: str, storage_options: list[str], cache: Path | None, drop_cache: bool) -> DataRoot:
    """The build's DataRoot from --data and the storage flags (which need a URL --data)."""
    import json

    options = {}
    for item in storage_options:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            # the argument itself is not repeated: a mistyped one may be a secret
            raise ConfigError("--storage-option: an argument without KEY= (not shown); write "
                              "KEY=VALUE, e.g. endpoint_url=http://host:9000")
        try:
            options[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            options[key.strip()] = value
    if not is_url(data) and (options or drop_cache):
        raise ConfigError(f"--storage-option and --drop-cache apply to a URL --data (s3://…); "
                          f"{data!r} is a folder")
    root = DataRoot.of(data, storage_options=options, cache_dir=str(cache) if cache else None,
                       drop_cache=drop_cache)
    if root.remote:
        root.filesystem()  # a missing backend (s3fs, gcsfs…) is a usage error before any work
    return root
