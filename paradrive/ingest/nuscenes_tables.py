"""The JSON tables of a nuScenes version, read whole or through a one-time SQLite index.

At v1.0-trainval size ``sample_data.json`` alone is over a gigabyte (2.6M rows); parsing every
table for every scene costs minutes and gigabytes per worker. The index holds each table's rows
(their JSON text, in file order) keyed by token, with ``sample_data`` also keyed by sample and
``sample_annotation`` by sample and instance, so one scene reads only its own rows.

- Where: ``<dataroot>/<version>/.paradrive/tables.sqlite``, beside the tables, so every worker and
  node that sees the dataroot shares one index; where that folder cannot be written (a read-only
  dataset mount), ``$PARADRIVE_CACHE/nuscenes/<digest of the version folder>/tables.sqlite``.
- When: built on first use, rebuilt when any table's size or mtime differs from those recorded
  in it. The builder holds ``tables.lock`` (``flock``) so concurrent workers build it once; the
  others wait and then read it. It is written under a temporary name and renamed into place,
  so readers (which open it read-only and immutable) never see a half-written index.
- Memory: tables are parsed row by row from fixed-size chunks of text, never whole.

Both readers give the ingest the same row dicts (the index stores each row's JSON text as the
file has it), so a scene reads identically with and without the index.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import re
import socket
import sqlite3
import uuid
from collections import Counter
from pathlib import Path
from collections.abc import Iterable, Iterator
from typing import Protocol

from paradrive.errors import SceneError
from paradrive.io import atomic_path, is_temporary
from paradrive.storage import default_cache

REQUIRED_TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor")
OPTIONAL_TABLES = ("log", "category", "instance", "sample_annotation")
# columns besides the token that a scene looks rows up by
KEYS = {"sample_data": ("sample_token",), "sample_annotation": ("sample_token", "instance_token")}
INDEX_DIR = ".paradrive"
INDEX_NAME = "tables.sqlite"
FORMAT = "1"                      # bumped when the index's layout changes: older ones are rebuilt
CHUNK_CHARS = 1 << 20             # text read at a time while streaming a table
MAX_ROW_CHARS = 64 << 20          # a "row" that does not parse within this much text is malformed
BATCH_ROWS = 20_000               # rows inserted per statement batch while building

log = logging.getLogger("paradrive.ingest.nuscenes")
_GAP = re.compile(r"[\s,]*")


class MissingKey(SceneError, KeyError):
    """A row of a nuScenes table without a key the reader needs (a KeyError too, so a reader
    that drops a damaged optional record, an actor's box, still does)."""

    def __str__(self) -> str:
        return str(self.args[0])


class Row(dict):
    """A row of a table, as ``json.loads`` gives it, that names itself when it lacks a key:
    ``row["filename"]`` on a row without one raises :class:`MissingKey` naming the table, the
    row's token and the key, with the fix; ``row.get`` is unchanged. The one accessor of every
    table row the reader uses."""

    __slots__ = ("table", "folder", "scene_id")

    def __init__(self, data: dict, table: str, folder: Path, scene_id: str):
        super().__init__(data)
        self.table, self.folder, self.scene_id = table, folder, scene_id

    def __missing__(self, key: str):
        raise MissingKey(f"{self.table}.json row {dict.get(self, 'token')!r} has no key {key!r}",
                         scene_id=self.scene_id, path=self.folder / f"{self.table}.json",
                         fix="the table is incomplete or damaged: re-extract the nuScenes "
                             "metadata archive")

    def __reduce__(self):
        return Row, (dict(self), self.table, self.folder, self.scene_id)


class Tables(Protocol):
    """Rows of a version's tables, as ``json.loads`` gives them (each a :class:`Row`)."""

    def get(self, table: str, token: str) -> dict | None: ...

    def rows(self, table: str) -> list[dict]: ...

    def sample_data_of(self, sample_token: str) -> list[dict]: ...

    def annotations_of(self, sample_tokens: Iterable[str]) -> list[dict]: ...


def malformed(name: str, folder: Path, scene_id: str, problem: str) -> SceneError:
    return SceneError(f"table {name}.json is malformed ({problem})", scene_id=scene_id,
                      path=folder / f"{name}.json", fix="re-extract the nuScenes metadata archive")


def present_tables(folder: Path, scene_id: str) -> list[str]:
    """The tables of ``folder`` to read; SceneError naming a required one that is missing."""
    for name in REQUIRED_TABLES:
        if not (folder / f"{name}.json").is_file():
            raise SceneError(f"table {name}.json is missing", scene_id=scene_id,
                             path=folder / f"{name}.json",
                             fix="point the URI at the nuScenes dataroot and version whose "
                                 "tables are complete (re-extract the metadata archive)")
    return [n for n in REQUIRED_TABLES + OPTIONAL_TABLES if (folder / f"{n}.json").is_file()]


def _duplicate(name: str, folder: Path, scene_id: str, token: str) -> SceneError:
    return malformed(name, folder, scene_id, f"token {token!r} is on two rows")


# --------------------------------------------------------------------------- whole tables

class JsonTables:
    """Every table parsed whole into memory ({table: {token: row}}): the reader without index."""

    def __init__(self, tables: dict[str, dict[str, dict]]):
        self.tables = tables

    @classmethod
    def load(cls, folder: Path, scene_id: str) -> JsonTables:
        tables = {}
        for name in present_tables(folder, scene_id):
            try:
                rows = json.loads((folder / f"{name}.json").read_text())
                by_token: dict[str, dict] = {row["token"]: Row(row, name, folder, scene_id) for row in rows}
            except (json.JSONDecodeError, KeyError, TypeError) as exc:
                raise malformed(name, folder, scene_id, f"{type(exc).__name__}: {exc}") from exc
            if len(by_token) != len(rows):
                counts = Counter(r["token"] for r in rows)
                raise _duplicate(name, folder, scene_id, counts.most_common(1)[0][0])
            tables[name] = by_token
        return cls(tables)

    def get(self, table: str, token: str) -> dict | None:
        return self.tables.get(table, {}).get(token)

    def rows(self, table: str) -> list[dict]:
        return list(self.tables.get(table, {}).values())

    def sample_data_of(self, sample_token: str) -> list[dict]:
        return [sd for sd in self.tables["sample_data"].values() if sd["sample_token"] == sample_token]

    def annotations_of(self, sample_tokens: Iterable[str]) -> list[dict]:
        rows = self.rows("sample_annotation")
        samples = set(sample_tokens)
        instances = {r.get("instance_token") for r in rows if r.get("sample_token") in samples}
        return [r for r in rows if r.get("instance_token") in instances]


# --------------------------------------------------------------------------- streaming parse

def stream_rows(path: Path, chunk_chars: int = CHUNK_CHARS) -> Iterator[tuple[dict, str]]:
    """Each row of a JSON table (a list of objects) with its text, reading ``chunk_chars`` at a
    time; ValueError when the file is not such a list."""
    decoder = json.JSONDecoder()
    with open(path, encoding="utf-8") as f:
        buf, eof = f.read(chunk_chars), False
        pos = _GAP.match(buf).end()  # type: ignore[union-attr]
        if buf[pos:pos + 1] != "[":
            raise ValueError("not a JSON list of rows")
        pos += 1
        while True:
            pos = _GAP.match(buf, pos).end()  # type: ignore[union-attr]
            if buf[pos:pos + 1] == "]":
                if buf[pos + 1:].strip() or f.read(1).strip():
                    raise ValueError(f"text after the list's end (character {pos + 1})")
                return
            if pos < len(buf) and buf[pos] != "{":
                raise ValueError(f"a row is not an object: {buf[pos:pos + 40]!r}")
            try:
                row, end = decoder.raw_decode(buf, pos)
            except json.JSONDecodeError:
                if eof or len(buf) - pos > MAX_ROW_CHARS:
                    raise
                more = f.read(chunk_chars)
                buf, pos, eof = buf[pos:] + more, 0, not more
                continue
            yield row, buf[pos:end]
            pos = end


# --------------------------------------------------------------------------- the index

def _stats(folder: Path, names: list[str]) -> dict[str, list[int]]:
    out = {}
    for name in names:
        st = (folder / f"{name}.json").stat()
        out[name] = [st.st_size, st.st_mtime_ns]
    return out


def index_path(folder: Path) -> Path | None:
    """Where the index of the version folder ``folder`` lives (see the module doc); None when
    neither place can be written."""
    digest = hashlib.sha256(str(folder.resolve()).encode()).hexdigest()[:16]
    for place in (folder / INDEX_DIR, default_cache() / "nuscenes" / f"{folder.name}-{digest}"):
        with contextlib.suppress(OSError):
            place.mkdir(parents=True, exist_ok=True)
            if os.access(place, os.W_OK):
                return place / INDEX_NAME
    return None


class IndexedTables:
    """The rows of one version's tables looked up in its SQLite index."""

    def __init__(self, path: Path, db: sqlite3.Connection, meta: dict[str, str], folder: Path,
                 scene_id: str = ""):
        self.path = path
        self.meta = meta
        self.built_here = False
        self.folder, self.scene_id = folder, scene_id   # whose tables, for the rows' errors
        self._db = db
        self._tables = set(json.loads(meta["tables"]))
        self._cache: dict[tuple[str, str], dict | None] = {}

    @classmethod
    def open_if_current(cls, path: Path, stats: dict[str, list[int]], folder: Path,
                        scene_id: str = "") -> IndexedTables | None:
        """The index at ``path`` of the tables of ``folder`` if it is there, complete and made
        from tables of ``stats``."""
        if not path.is_file():
            return None
        # read-only and immutable: the file is never changed in place, only replaced by a rename
        db = sqlite3.connect(path.resolve().as_uri() + "?mode=ro&immutable=1", uri=True)
        try:
            meta = dict(db.execute("SELECT key, value FROM meta").fetchall())
        except sqlite3.DatabaseError:
            meta = {}  # not an index of ours (or damaged): build it again
        if meta.get("format") != FORMAT or json.loads(meta.get("tables", "null")) != stats:
            db.close()
            return None
        return cls(path, db, meta, folder, scene_id)

    def close(self) -> None:
        self._db.close()

    def _loads(self, table: str, query: str, args: Iterable = ()) -> list[dict]:
        return [Row(json.loads(text), table, self.folder, self.scene_id)
                for (text,) in self._db.execute(query, tuple(args))]

    def get(self, table: str, token: str) -> dict | None:
        key = (table, token)
        if key not in self._cache:
            found = self._loads(table, f'SELECT row FROM "{table}" WHERE token = ?', [token]) \
                if table in self._tables else []
            self._cache[key] = found[0] if found else None
        return self._cache[key]

    def rows(self, table: str) -> list[dict]:
        return (self._loads(table, f'SELECT row FROM "{table}" ORDER BY rowid')
                if table in self._tables else [])

    def sample_data_of(self, sample_token: str) -> list[dict]:
        return self._loads("sample_data",
                           "SELECT row FROM sample_data WHERE sample_token = ? ORDER BY rowid",
                           [sample_token])

    def annotations_of(self, sample_tokens: Iterable[str]) -> list[dict]:
        if "sample_annotation" not in self._tables:
            return []
        samples = list(sample_tokens)
        marks = ", ".join("?" * len(samples))
        return self._loads(
            "sample_annotation",
            "SELECT row FROM sample_annotation WHERE instance_token IN (SELECT instance_token "
            f"FROM sample_annotation WHERE sample_token IN ({marks})) ORDER BY rowid", samples)


def _fill(db: sqlite3.Connection, folder: Path, name: str, scene_id: str) -> int:
    """Stream ``<name>.json`` into its table of the index being built; its row count."""
    keys = KEYS.get(name, ())
    columns = ", ".join(f"{k} TEXT" for k in ("token", *keys))
    db.execute(f'CREATE TABLE "{name}" ({columns}, row TEXT NOT NULL)')
    insert = f'INSERT INTO "{name}" VALUES ({", ".join("?" * (len(keys) + 2))})'
    count, batch = 0, []
    try:
        for row, text in stream_rows(folder / f"{name}.json"):
            batch.append((row["token"], *(row.get(k) for k in keys), text))
            if len(batch) >= BATCH_ROWS:
                db.executemany(insert, batch)
                count, batch = count + len(batch), []
    except (ValueError, KeyError, TypeError) as exc:
        raise malformed(name, folder, scene_id, f"{type(exc).__name__}: {exc}") from exc
    db.executemany(insert, batch)
    try:
        db.execute(f'CREATE UNIQUE INDEX "{name}_token" ON "{name}" (token)')
    except sqlite3.IntegrityError:
        (twice,) = db.execute(f'SELECT token FROM "{name}" GROUP BY token HAVING count(*) > 1').fetchone()
        raise _duplicate(name, folder, scene_id, twice) from None
    for k in keys:
        db.execute(f'CREATE INDEX "{name}_{k}" ON "{name}" ({k})')
    return count + len(batch)


def build_index(folder: Path, path: Path, names: list[str], scene_id: str) -> None:
    """Write the index of the tables ``names`` of ``folder`` at ``path`` (temporary name, then
    rename). The stats are taken first, so a table changed while building makes it stale."""
    stats = _stats(folder, names)
    with atomic_path(path) as tmp:
        db = sqlite3.connect(tmp)
        with contextlib.closing(db):
            db.execute("PRAGMA journal_mode = OFF")
            db.execute("PRAGMA synchronous = OFF")
            db.execute("PRAGMA cache_size = -65536")  # 64 MB: indexes sort in memory, not in spills
            counts = {name: _fill(db, folder, name, scene_id) for name in names}
            meta = {"format": FORMAT, "tables": json.dumps(stats), "rows": json.dumps(counts),
                    "source": str(folder.resolve()), "build_id": uuid.uuid4().hex,
                    "built_by": f"{socket.gethostname()}:{os.getpid()}"}
            db.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT)")
            db.executemany("INSERT INTO meta VALUES (?, ?)", meta.items())
            db.commit()
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def _held(lock: Path, folder: Path) -> Iterator[None]:
    """Hold ``lock`` exclusively (``flock``: a holder that dies lets go); says so when waiting."""
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("waiting for another process to finish the table index of %s", folder)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _remove_leftovers(place: Path) -> None:
    """Temporary files of builders that died (only called while holding the lock)."""
    for p in place.iterdir():
        if is_temporary(p.name) and p.name.startswith(f".{INDEX_NAME}."):
            with contextlib.suppress(OSError):
                p.unlink()


def open_tables(folder: Path, scene_id: str) -> Tables:
    """The tables of the version folder ``folder``, through its index (built or rebuilt first
    when needed, once across concurrent workers); read whole where no index can be written."""
    names = present_tables(folder, scene_id)
    path = index_path(folder)
    if path is None:
        log.warning("scene %s: no place to write the table index of %s (neither %s nor the "
                    "cache is writable); reading the tables whole; set $PARADRIVE_CACHE to a "
                    "writable folder", scene_id, folder, folder / INDEX_DIR)
        return JsonTables.load(folder, scene_id)
    found = IndexedTables.open_if_current(path, _stats(folder, names), folder, scene_id)
    if found is not None:
        return found
    with _held(path.with_suffix(".lock"), folder):
        found = IndexedTables.open_if_current(path, _stats(folder, names), folder, scene_id)
        if found is not None:
            return found
        _remove_leftovers(path.parent)
        log.info("scene %s: indexing the tables of %s into %s", scene_id, folder, path)
        build_index(folder, path, names, scene_id)
    built = IndexedTables.open_if_current(path, _stats(folder, names), folder, scene_id)
    if built is None:
        raise SceneError("the tables changed while their index was being built", scene_id=scene_id,
                         path=folder, fix="re-run once the tables are no longer being written")
    built.built_here = True
    return built
