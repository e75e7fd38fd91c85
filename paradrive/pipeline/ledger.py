"""The status ledger of a build: what every (scene, stage) did, in ``<manifests>/<build>/ledger.sqlite``.

One SQLite file in WAL mode, so the driver and any number of worker processes may write it at the
same time (each write is one short ``BEGIN IMMEDIATE`` transaction; a writer waits up to
``timeout`` seconds for the lock). Tables (``SCHEMA_VERSION`` = 1)::

    meta(key PRIMARY KEY, value)                 schema_version, build, created_at, data_root
                                                 (where the last run wrote its scenes)
    scenes(scene_id PRIMARY KEY, scene_uri, position, active, registered_at)
        active = 1: the scene belongs to the build as last registered (a run over a
        different scene list retires the others; --retry-failed keeps the list)
    tasks(scene_id, stage, PRIMARY KEY (scene_id, stage),
          scene_uri, position, state, attempts, started_at, finished_at, seconds,
          peak_rss_mb, error, fingerprint, updated_at)
        state: pending | running | done | skipped | failed | blocked
        attempts: times a build ran the stage (a skip because it was up to date is no attempt;
                  Ray's own retries after a worker died count within one attempt)
        seconds / peak_rss_mb: of the run that produced the outputs (a later skip keeps them),
                  or of the run that failed
    events(id PRIMARY KEY, run_id, scene_id, stage, state, at, seconds, error)
        every transition, for the history of a scene; state 'takeover' (error: the holder)
        when the stage took over the scene lock of a build that died holding it
    runs(run_id PRIMARY KEY, started_at, finished_at, executor, scenes, command, exit_code)

Build-scoped stages (the manifest) are rows with ``scene_id = scene_uri = 'build:<name>'``.
Times are Unix seconds (float).

The ledger is a record, the markers are the truth: a ledger file that is not a database (garbage,
a torn copy) is moved aside (``ledger.sqlite.corrupt-<time>``) and rebuilt from the markers of
the build and of the scenes its index names. A ledger that cannot be written (a read-only
``--manifests``, a full disk) is a :class:`LedgerError`, one line naming the file and the fix;
``paradrive status`` reads a ledger it cannot write (``readonly``).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import sqlite3
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from collections.abc import Iterable, Iterator

from paradrive.errors import ConfigError, ParaDriveError
from paradrive.contracts.layout import LEDGER, MARKER_DIR, BuildLayout
from paradrive.contracts.records import StageMarker
from paradrive.redact import redact, redact_argv
from paradrive.uri import parse_uri

SCHEMA_VERSION = 1
LEDGER_FILE = LEDGER
STATES = ("pending", "running", "done", "skipped", "failed", "blocked")
FINISHED = ("done", "skipped")
STAGE_SLOTS = range(100)  # positions of scene stages; build stages come after them
BROKEN = ("failed", "blocked")

_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS scenes (
    scene_id TEXT PRIMARY KEY,
    scene_uri TEXT NOT NULL,
    position INTEGER NOT NULL,
    active INTEGER NOT NULL DEFAULT 1,
    registered_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS tasks (
    scene_id TEXT NOT NULL,
    stage TEXT NOT NULL,
    scene_uri TEXT NOT NULL,
    position INTEGER NOT NULL DEFAULT 0,
    state TEXT NOT NULL CHECK (state IN ({", ".join(repr(s) for s in STATES)})),
    attempts INTEGER NOT NULL DEFAULT 0,
    started_at REAL,
    finished_at REAL,
    seconds REAL,
    peak_rss_mb REAL,
    error TEXT NOT NULL DEFAULT '',
    fingerprint TEXT NOT NULL DEFAULT '',
    updated_at REAL NOT NULL,
    PRIMARY KEY (scene_id, stage));
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id INTEGER,
    scene_id TEXT NOT NULL,
    stage TEXT NOT NULL,
    state TEXT NOT NULL,
    at REAL NOT NULL,
    seconds REAL,
    error TEXT NOT NULL DEFAULT '');
CREATE TABLE IF NOT EXISTS runs (
    run_id INTEGER PRIMARY KEY AUTOINCREMENT,
    started_at REAL NOT NULL,
    finished_at REAL,
    executor TEXT NOT NULL DEFAULT '',
    scenes INTEGER NOT NULL DEFAULT 0,
    command TEXT NOT NULL DEFAULT '',
    exit_code INTEGER);
CREATE INDEX IF NOT EXISTS tasks_state ON tasks (state);
CREATE INDEX IF NOT EXISTS events_scene ON events (scene_id, stage);
"""


def build_label(build: str) -> str:
    return f"build:{build}"


class LedgerError(ParaDriveError):
    """The ledger file cannot be opened or written; the message names it and the fix."""


def ledger_error(path: Path, exc: BaseException) -> LedgerError:
    """What went wrong with the ledger at ``path``, as one line that says what to do."""
    text = str(exc)
    low = text.lower()
    if "full" in low or getattr(exc, "errno", None) == errno.ENOSPC or _nearly_full(path.parent):
        fix = f"disk full; free space on {path.parent} and re-run (the markers keep what is done)"
    elif "readonly" in low or "read-only" in low or "unable to open" in low \
            or isinstance(exc, OSError):  # the folder cannot be made or written
        fix = (f"cannot write there; make {path.parent} writable or pass a writable --manifests "
               f"(the build folder holds the ledger)")
    elif "locked" in low:
        fix = "another process holds it too long; re-run once that build is done"
    else:
        fix = f"move {path.name} aside and re-run (it is rebuilt from the markers)"
    return LedgerError(f"ledger {path}: {text}; {fix}")


class Ledger:
    """The ledger of one build. Cheap to create; picklable (each process opens its own connection)."""

    def __init__(self, path: str | Path, build: str | None = None, *, timeout: float = 60.0,
                 readonly: bool = False):
        self.path = Path(path)
        self.build = build or self.path.parent.name
        self.timeout = timeout
        self.readonly = readonly
        self.recovered = ""  # where a corrupt ledger was moved before this one was rebuilt
        self.run_id: int | None = None
        self._conn: sqlite3.Connection | None = None
        self._pid: int | None = None
        self._ids: dict[str, str] = {}
        try:
            self._init_schema()
        except sqlite3.OperationalError as exc:
            self.close()
            raise ledger_error(self.path, exc) from exc
        except sqlite3.DatabaseError as exc:  # not a database at all: the markers hold the truth
            self.close()
            if readonly:
                raise ledger_error(self.path, exc) from exc
            self._recover(exc)
        except OSError as exc:  # the build folder itself cannot be made
            raise ledger_error(self.path, exc) from exc

    @classmethod
    def for_build(cls, manifests_dir: str | Path, build: str) -> Ledger:
        return cls(Path(manifests_dir) / build / LEDGER_FILE, build)

    @classmethod
    def open_existing(cls, manifests_dir: str | Path, build: str) -> Ledger:
        """The ledger of a build that ran before; ConfigError when there is none."""
        path = Path(manifests_dir) / build / LEDGER_FILE
        if not path.is_file():
            builds = sorted(p.parent.name for p in Path(manifests_dir).glob(f"*/{LEDGER_FILE}"))
            raise ConfigError(f"no ledger for build '{build}' at {path}; builds with a ledger "
                              f"under {manifests_dir}: {', '.join(builds) or 'none'}")
        return cls.for_reading(path, build)

    @classmethod
    def for_reading(cls, path: Path, build: str | None = None) -> Ledger:
        """The ledger at ``path``, read-only where its folder cannot be written (a read-only
        mount of a finished build), recovered like any other where it is corrupt."""
        return cls(path, build, readonly=not os.access(path.parent, os.W_OK) or _read_only_mount(path))

    # -- connection -------------------------------------------------------------------------

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_conn"] = None
        state["_pid"] = None
        return state

    def _connection(self) -> sqlite3.Connection:
        # A connection never crosses a fork: a child (or a Ray worker) opens its own.
        if self._conn is None or self._pid != os.getpid():
            conn = self._read_only() if self.readonly else sqlite3.connect(
                self.path, timeout=self.timeout, isolation_level=None)
            conn.row_factory = sqlite3.Row
            conn.execute(f"PRAGMA busy_timeout = {int(self.timeout * 1000)}")
            conn.execute("PRAGMA synchronous = NORMAL")
            self._conn, self._pid = conn, os.getpid()
        return self._conn

    def _read_only(self) -> sqlite3.Connection:
        """A connection that writes nothing: read-only with the write-ahead log where SQLite can
        use it there, else as an immutable file (no process can write that folder either)."""
        conn = sqlite3.connect(f"file:{self.path}?mode=ro", timeout=self.timeout,
                               isolation_level=None, uri=True)
        try:
            conn.execute("SELECT count(*) FROM meta").fetchone()
            return conn
        except sqlite3.OperationalError:
            conn.close()
        return sqlite3.connect(f"file:{self.path}?immutable=1", timeout=self.timeout,
                               isolation_level=None, uri=True)

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        try:
            conn = self._connection()
            conn.execute("BEGIN IMMEDIATE")
        except sqlite3.OperationalError as exc:
            raise ledger_error(self.path, exc) from exc
        try:
            yield conn
            conn.execute("COMMIT")
        except BaseException as exc:
            if conn.in_transaction:
                conn.execute("ROLLBACK")
            if isinstance(exc, sqlite3.OperationalError):  # a full disk, a file made read-only
                raise ledger_error(self.path, exc) from exc
            raise

    def close(self) -> None:
        if self._conn is not None and self._pid == os.getpid():
            self._conn.close()
        self._conn = None

    def _init_schema(self) -> None:
        if self.readonly:
            self._check_version()
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        conn = self._connection()
        mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
        if mode.lower() != "wal":  # e.g. a file system without shared memory (some NFS)
            conn.execute("PRAGMA journal_mode = DELETE")
        with self._write() as c:
            for statement in _SCHEMA.split(";"):
                if statement.strip():
                    c.execute(statement)
            c.execute("INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
            c.execute("INSERT OR IGNORE INTO meta VALUES ('build', ?)", (self.build,))
            c.execute("INSERT OR IGNORE INTO meta VALUES ('created_at', ?)", (str(time.time()),))
        self._check_version()

    def _check_version(self) -> None:
        found = self.meta().get("schema_version")
        if found != str(SCHEMA_VERSION):
            raise ConfigError(f"{self.path}: ledger schema_version {found} is not {SCHEMA_VERSION}; "
                              f"move the old ledger aside and re-run the build (outputs are kept)")

    def _recover(self, exc: sqlite3.DatabaseError) -> None:
        """Move the unreadable file aside, start a new ledger and fill it from the markers."""
        aside = self.path.with_name(f"{self.path.name}.corrupt-{time.strftime('%Y%m%d-%H%M%S')}")
        try:
            for suffix in ("", "-wal", "-shm"):
                old = self.path.with_name(self.path.name + suffix)
                if old.exists():
                    os.replace(old, aside.with_name(aside.name + suffix))
            self._init_schema()
            rebuilt = self._rebuild_from_markers()
        except (OSError, sqlite3.Error) as again:
            raise ledger_error(self.path, again) from exc
        self.recovered = (f"ledger {self.path}: not a database ({exc}); moved aside to "
                          f"{aside.name} and rebuilt from the markers of {rebuilt} scene(s)")
        logging.getLogger(__name__).warning("%s", self.recovered)

    def _rebuild_from_markers(self) -> int:
        """Rows for the scenes the build's index names, from their stages' markers (done, with
        the seconds each took), and for the build's own stages; returns how many scenes."""
        layout = BuildLayout(self.path.parent)
        try:
            scenes = json.loads(layout.index_json.read_text()).get("scenes", [])
        except (OSError, ValueError, AttributeError):
            scenes = []
        now = time.time()
        with self._write() as c:
            for i, scene in enumerate(scenes):
                sid, uri = scene.get("scene_id"), scene.get("scene_uri") or scene.get("scene_id")
                if not sid:
                    continue
                c.execute("INSERT OR IGNORE INTO scenes VALUES (?, ?, ?, 1, ?)", (sid, uri, i, now))
                self._insert_done(c, sid, uri, Path(str(scene.get("scene_dir", ""))) / MARKER_DIR, 0)
            label = build_label(self.build)
            self._insert_done(c, label, label, self.path.parent / MARKER_DIR, len(STAGE_SLOTS))
        return len(scenes)

    @staticmethod
    def _insert_done(c, sid: str, uri: str, marker_dir: Path, first: int) -> None:
        # an unreadable marker (or the builder's own, not a stage's) counts as not done
        markers = [m for m in map(StageMarker.read, marker_dir.glob("*.json")) if m is not None]
        needs = {m.stage: list(m.upstream_runs or {}) for m in markers}

        def depth(stage: str, seen: frozenset = frozenset()) -> int:  # pipeline order
            return 1 + max((depth(n, seen | {stage}) for n in needs.get(stage, [])
                            if n not in seen), default=0)

        markers.sort(key=lambda m: (depth(m.stage), m.stage))
        for pos, m in enumerate(markers, first):
            c.execute("INSERT OR IGNORE INTO tasks (scene_id, stage, scene_uri, position, state, "
                      "attempts, seconds, fingerprint, updated_at) "
                      "VALUES (?, ?, ?, ?, 'done', 1, ?, ?, ?)",
                      (sid, m.stage, uri, pos, m.seconds, m.fingerprint, time.time()))

    # -- writing ----------------------------------------------------------------------------

    def _scene_id(self, scene: str) -> str:
        """A scene id from a scene URI, a scene id or a build label."""
        if scene not in self._ids:
            sid = scene
            if not scene.startswith("build:"):
                try:
                    sid = parse_uri(scene).scene_id
                except ConfigError:
                    sid = scene
            self._ids[scene] = sid
        return self._ids[scene]

    def begin_run(self, executor: str = "", scenes: int = 0, command: str | None = None) -> int:
        command = " ".join(redact_argv(sys.argv)) if command is None else redact(command)
        with self._write() as c:
            cur = c.execute("INSERT INTO runs (started_at, executor, scenes, command) VALUES (?, ?, ?, ?)",
                            (time.time(), executor, scenes, command))
            self.run_id = int(cur.lastrowid or 0)
        return self.run_id

    def set_data_root(self, location: str) -> None:
        """Where the build writes its scenes (``paradrive status`` looks there for scene locks)."""
        with self._write() as c:
            c.execute("INSERT INTO meta VALUES ('data_root', ?) ON CONFLICT (key) DO UPDATE SET "
                      "value = excluded.value", (location,))

    def takeovers(self) -> list[dict]:
        """Every scene lock this build took over from a dead or expired holder (one query: the
        events of every run are many more)."""
        rows = self._connection().execute("SELECT * FROM events WHERE state = 'takeover' ORDER BY id")
        return [dict(r) for r in rows]

    def end_run(self, exit_code: int) -> None:
        """Close the run's row; best effort (a run that failed on its ledger has said why)."""
        if self.run_id is None:
            return
        try:
            with self._write() as c:
                c.execute("UPDATE runs SET finished_at = ?, exit_code = ? WHERE run_id = ?",
                          (time.time(), exit_code, self.run_id))
        except LedgerError as exc:
            logging.getLogger(__name__).warning("%s", exc)

    def register(self, scene_uris: Iterable[str], scene_stages: Iterable[str],
                 build_stages: Iterable[str] = (), *, replace: bool = True) -> None:
        """Mark every (scene, stage) of this run pending.

        ``replace``: these scenes are the whole build (others are retired from the status view);
        False for a run over a subset (``--retry-failed``). Rows left 'running' by a run that
        was killed become pending like the rest.
        """
        now = time.time()
        uris = list(scene_uris)
        scene_stages, build_stages = list(scene_stages), list(build_stages)
        with self._write() as c:
            if replace:
                c.execute("UPDATE scenes SET active = 0")
            start = c.execute("SELECT COALESCE(MAX(position) + 1, 0) FROM scenes").fetchone()[0]
            for i, uri in enumerate(uris):
                sid = self._scene_id(uri)
                c.execute("INSERT INTO scenes (scene_id, scene_uri, position, active, registered_at) "
                          "VALUES (?, ?, ?, 1, ?) ON CONFLICT (scene_id) DO UPDATE SET "
                          "scene_uri = excluded.scene_uri, active = 1"
                          + (", position = excluded.position" if replace else ""),
                          (sid, uri, i if replace else start + i, now))
                for pos, stage in enumerate(scene_stages):
                    self._upsert_pending(c, sid, stage, uri, pos, now)
            label = build_label(self.build)
            for pos, stage in enumerate(build_stages):
                self._upsert_pending(c, label, stage, label, len(scene_stages) + pos, now)

    @staticmethod
    def _upsert_pending(c, sid: str, stage: str, uri: str, pos: int, now: float) -> None:
        c.execute("INSERT INTO tasks (scene_id, stage, scene_uri, position, state, updated_at) "
                  "VALUES (?, ?, ?, ?, 'pending', ?) ON CONFLICT (scene_id, stage) DO UPDATE SET "
                  "state = 'pending', scene_uri = excluded.scene_uri, "
                  "position = excluded.position, updated_at = excluded.updated_at",
                  (sid, stage, uri, pos, now))

    def start(self, scene: str, stage: str) -> None:
        """A stage of a scene (URI or id, or 'build:<name>') was handed to a worker."""
        sid, now = self._scene_id(scene), time.time()
        uri = scene
        with self._write() as c:
            c.execute("INSERT INTO tasks (scene_id, stage, scene_uri, state, attempts, started_at, "
                      "updated_at) VALUES (?, ?, ?, 'running', 1, ?, ?) "
                      "ON CONFLICT (scene_id, stage) DO UPDATE SET state = 'running', "
                      "attempts = attempts + 1, started_at = excluded.started_at, "
                      "updated_at = excluded.updated_at",
                      (sid, stage, uri, now, now))
            self._event(c, sid, stage, "running", now)

    def record(self, result) -> None:
        """A :class:`~paradrive.pipeline.runner.StageResult` came back."""
        sid, stage, state, now = result.scene_id, result.stage, result.status, time.time()
        error = redact(result.error) if result.error else ""  # the scan of the environment: per error only
        if state not in STATES:
            raise ValueError(f"ledger: unknown state {state!r} for {sid}/{stage}")
        with self._write() as c:
            row = c.execute("SELECT state FROM tasks WHERE scene_id = ? AND stage = ?",
                            (sid, stage)).fetchone()
            if row is None:
                c.execute("INSERT INTO tasks (scene_id, stage, scene_uri, state, updated_at) "
                          "VALUES (?, ?, ?, 'pending', ?)", (sid, stage, sid, now))
            if state == "skipped":
                # Up to date: no attempt; keep the time and memory of the run that made the outputs.
                c.execute("UPDATE tasks SET state = 'skipped', error = '', fingerprint = ?, "
                          "attempts = MAX(attempts - ?, 0), finished_at = ?, updated_at = ? "
                          "WHERE scene_id = ? AND stage = ?",
                          (result.fingerprint, int(row is not None and row["state"] == "running"),
                           now, now, sid, stage))
            elif state == "blocked":
                c.execute("UPDATE tasks SET state = 'blocked', error = ?, updated_at = ? "
                          "WHERE scene_id = ? AND stage = ?", (error, now, sid, stage))
            else:
                seconds = float(result.seconds or 0.0)
                c.execute("UPDATE tasks SET state = ?, error = ?, fingerprint = ?, seconds = ?, "
                          "peak_rss_mb = ?, started_at = ?, finished_at = ?, updated_at = ?, "
                          "attempts = MAX(attempts, 1) WHERE scene_id = ? AND stage = ?",
                          (state, error, result.fingerprint or "", seconds,
                           float(result.peak_rss_mb or 0.0), now - seconds, now, now, sid, stage))
            self._event(c, sid, stage, state, now, result.seconds, error)
            if getattr(result, "took_over", ""):
                self._event(c, sid, stage, "takeover", now,
                            error=f"took over the scene lock of {result.took_over}")

    def _event(self, c, sid: str, stage: str, state: str, at: float, seconds: float | None = None,
               error: str = "") -> None:
        c.execute("INSERT INTO events (run_id, scene_id, stage, state, at, seconds, error) "
                  "VALUES (?, ?, ?, ?, ?, ?, ?)", (self.run_id, sid, stage, state, at, seconds, error))

    # -- reading ----------------------------------------------------------------------------

    def meta(self) -> dict[str, str]:
        return {r["key"]: r["value"] for r in self._connection().execute("SELECT * FROM meta")}

    def tasks(self, *, active_only: bool = True) -> list[dict]:
        """Every (scene, stage) row, in build order (scenes, then stages in pipeline order)."""
        sql = ("SELECT t.*, COALESCE(s.position, 1e12) AS scene_position FROM tasks t "
               "LEFT JOIN scenes s ON s.scene_id = t.scene_id")
        if active_only:
            sql += " WHERE s.active = 1 OR t.scene_id LIKE 'build:%'"
        sql += " ORDER BY scene_position, t.scene_id, t.position, t.stage"
        return [dict(r) for r in self._connection().execute(sql)]

    def task(self, scene_id: str, stage: str) -> dict | None:
        row = self._connection().execute("SELECT * FROM tasks WHERE scene_id = ? AND stage = ?",
                                         (scene_id, stage)).fetchone()
        return dict(row) if row else None

    def events(self, scene_id: str | None = None) -> list[dict]:
        if scene_id is None:
            rows = self._connection().execute("SELECT * FROM events ORDER BY id")
        else:
            rows = self._connection().execute("SELECT * FROM events WHERE scene_id = ? ORDER BY id",
                                              (scene_id,))
        return [dict(r) for r in rows]

    def runs(self) -> list[dict]:
        return [dict(r) for r in self._connection().execute("SELECT * FROM runs ORDER BY run_id")]

    def scene_uris(self, *, active_only: bool = True) -> list[str]:
        sql = "SELECT scene_uri FROM scenes" + (" WHERE active = 1" if active_only else "")
        return [r[0] for r in self._connection().execute(sql + " ORDER BY position, scene_id")]

    def last_run(self) -> dict | None:
        row = self._connection().execute("SELECT * FROM runs ORDER BY run_id DESC LIMIT 1").fetchone()
        return dict(row) if row else None

    def scene_ids(self) -> set[str]:
        """The active scenes that have stage rows."""
        rows = self._connection().execute(
            "SELECT DISTINCT t.scene_id FROM tasks t JOIN scenes s ON s.scene_id = t.scene_id "
            "WHERE s.active = 1")
        return {r[0] for r in rows}

    def scene_states(self, rows: list[dict] | None = None) -> dict[str, str]:
        """scene_id -> done | failed | running | pending, over the active scenes (``rows``: the
        :meth:`tasks` already read)."""
        states: dict[str, list[str]] = {}
        for row in self.tasks() if rows is None else rows:
            if not row["scene_id"].startswith("build:"):
                states.setdefault(row["scene_id"], []).append(row["state"])
        return {sid: scene_state(s) for sid, s in states.items()}

    def failed_scene_uris(self) -> list[str]:
        """URIs of the active scenes with a failed (or blocked) stage, in build order."""
        seen, uris = set(), []
        for row in self.tasks():
            if (row["state"] in BROKEN and not row["scene_id"].startswith("build:")
                    and row["scene_id"] not in seen):
                seen.add(row["scene_id"])
                uris.append(row["scene_uri"])
        return uris

    def unfinished_build_stages(self) -> list[str]:
        """This build's build-scoped stages (the manifest publish, encode) that a run asked for
        and that did not finish: failed, blocked, or left running or pending by a run that
        stopped (``--retry-failed`` runs them again), in pipeline order."""
        label = build_label(self.build)
        return [row["stage"] for row in self.tasks()
                if row["scene_id"] == label and row["state"] not in FINISHED]

    def summary(self) -> dict:
        """What ``paradrive status`` shows, as plain data (also its ``--json``). Two queries
        whatever the build's size: the task rows (read once) and the last run."""
        rows = self.tasks()
        scene_rows = [r for r in rows if not r["scene_id"].startswith("build:")]
        states = self.scene_states(rows)
        counts = {s: 0 for s in ("done", "failed", "running", "pending")}
        for s in states.values():
            counts[s] += 1
        stages: dict[str, dict] = {}
        for r in rows:
            st = stages.setdefault(r["stage"], {"stage": r["stage"], "position": r["position"],
                                                **{s: 0 for s in STATES}, "seconds_total": 0.0,
                                                "seconds_max": 0.0, "runs": 0,
                                                "peak_rss_mb_max": 0.0})
            st[r["state"]] += 1
            if r["state"] in (*FINISHED, "failed") and r["seconds"]:  # a failed run's time counts too
                st["seconds_total"] += r["seconds"]
                st["seconds_max"] = max(st["seconds_max"], r["seconds"])
                st["runs"] += 1
            st["peak_rss_mb_max"] = max(st["peak_rss_mb_max"], r["peak_rss_mb"] or 0.0)
        for st in stages.values():
            st["seconds_mean"] = st["seconds_total"] / st["runs"] if st["runs"] else 0.0
        per_scene: dict[str, dict] = {}
        for r in scene_rows:
            sc = per_scene.setdefault(r["scene_id"], {"scene_id": r["scene_id"],
                                                      "scene_uri": r["scene_uri"],
                                                      "state": states[r["scene_id"]],
                                                      "seconds": 0.0, "stages": {}})
            sc["seconds"] += (r["seconds"] or 0.0) if r["state"] in (*FINISHED, "failed") else 0.0
            sc["stages"][r["stage"]] = r["state"]
        slowest = sorted(per_scene.values(), key=lambda s: -s["seconds"])[:10]
        failures = [{"scene_id": r["scene_id"], "scene_uri": r["scene_uri"], "stage": r["stage"],
                     "attempts": r["attempts"], "seconds": r["seconds"],
                     "peak_rss_mb": r["peak_rss_mb"], "error": r["error"]}
                    for r in rows if r["state"] == "failed"]
        build_rows = [{"stage": r["stage"], "state": r["state"], "seconds": r["seconds"],
                       "error": r["error"]} for r in rows if r["scene_id"].startswith("build:")]
        return {"build": self.build, "ledger": str(self.path), "scenes": len(states),
                "counts": counts, "stages": sorted(stages.values(), key=lambda s: s["position"]),
                "slowest": [{"scene_id": s["scene_id"], "seconds": round(s["seconds"], 3),
                             "state": s["state"]} for s in slowest],
                "failures": failures, "build_stages": build_rows,
                "scene_table": list(per_scene.values()),
                "last_run": self.last_run()}


def _nearly_full(folder: Path) -> bool:
    """SQLite reports some writes on a full disk as a plain 'disk I/O error': look at the disk."""
    try:
        return shutil.disk_usage(folder).free < 1 << 20
    except OSError:
        return False


def _read_only_mount(path: Path) -> bool:
    """True on a file system mounted read-only (root's permission bits allow everything)."""
    try:
        return bool(os.statvfs(path.parent).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def scene_state(stage_states: list[str]) -> str:
    if any(s in BROKEN for s in stage_states):
        return "failed"
    if all(s in FINISHED for s in stage_states):
        return "done"
    if any(s == "running" for s in stage_states):
        return "running"
    return "pending"


def dumps(summary: dict) -> str:
    return json.dumps(summary, indent=2, default=str)
