"""Scene locks: while a stage of a scene runs, no other build works on that scene.

Several builds (other names, retries, Ray jobs) may share one data root. Each (scene, stage)
decides whether it is up to date, runs and writes its marker while holding its scene's lock, so
a second build that meets the scene either waits for it and then finds the stage done, or runs
it after the first one finished; two builds never write one scene at once.

- A folder root (local, NFS, a FUSE mount): ``<data>/locks/<scene_id>.lock``, held with
  ``flock``; the holder's build, host, pid and start time are written inside. The kernel drops
  the lock of a process that dies (even by SIGKILL), so the next build takes it at once; the
  record the dead holder left behind tells it to note a takeover. A mount without locks
  (``ENOLCK``) fails the stage with that reason rather than running unguarded.
- A URL root: a lease object ``<root>/locks/<scene_id>.json`` created with the store's
  exclusive create (fsspec mode ``"xb"``: ``If-None-Match`` on S3, ``O_EXCL`` on ``local://``),
  then read back to be sure it is ours. Its expiry is ``LEASE_SECONDS`` after the moment it is
  written (never counted from before a wait), and the holder renews it from a background thread
  every ``LEASE_SECONDS / 3``; a lease past its expiry, or one whose holder is a dead process
  on this host, is taken over. A holder whose renewal finds the lease taken, or its own expiry
  passed (another build may take it from then on), never writes it again: the lease is lost
  (:meth:`HeldLock.check` raises :class:`LeaseLost`), and the runner stops the stage before it
  writes anything more to the data root (at its next progress report, before its upload and
  before its marker); a plain re-run builds the scene.

A build that meets a held lock polls for it up to ``timeout`` seconds (``--lock-timeout``),
then gives up on that scene for this run with :class:`SceneLocked`, naming the holder.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import socket
import threading
import time
import uuid
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from collections.abc import Iterator

from paradrive.errors import NOT_WRITABLE, ParaDriveError, SceneError
from paradrive.contracts.layout import LOCKS_DIR, DataLayout
from paradrive.storage import DataRoot

LOCK_DIR = LOCKS_DIR
DEFAULT_LOCK_TIMEOUT_S = 3600.0  # a waiting build gives up on a held scene after this long
LEASE_SECONDS = 60.0             # a URL root's lease lives this long unless its holder renews it
RENEW_MARGIN = 0.1               # of LEASE_SECONDS: a lease this close to its expiry is not
                                 # renewed (clocks of two hosts differ; a write takes time)
POLL_SECONDS = 0.25              # how often a waiting build looks at the lock again


class LeaseClock:
    """Where leases read the time (their expiry) and wait for the next renewal: the wall clock.
    A test puts in a clock of its own that moves only when it says, so a renewal is never late
    however little CPU its thread gets."""

    def now(self) -> float:
        return time.time()

    def wait(self, stop: threading.Event, seconds: float) -> bool:
        """Wait ``seconds`` or until ``stop`` is set; whether it was set."""
        return stop.wait(seconds)


CLOCK = LeaseClock()


class LeaseLost(SceneError):
    """The scene's lease was taken by another build, or lapsed before its holder renewed it."""


class SceneLocked(ParaDriveError):
    """The scene stayed locked by another build for the whole ``--lock-timeout``."""

    def __init__(self, scene_id: str, holder: Holder | None, waited: float):
        self.holder = holder
        who = holder.describe() if holder else "another build"
        super().__init__(f"scene {scene_id}: locked by {who}; waited {waited:.0f} s "
                         f"(--lock-timeout) and left it for this run; re-run once that build "
                         f"finished it")


@dataclass(frozen=True)
class LockOptions:
    """Who takes the locks (the build's name goes into every record) and how long to wait."""

    build: str = "default"
    timeout: float = DEFAULT_LOCK_TIMEOUT_S


def _proc_stat(pid: int) -> list[str]:
    """Fields 3… of ``/proc/<pid>/stat`` (state, ppid, …); [] where there is none."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[-1].split()
    except OSError:
        return []


def _process_start(pid: int) -> str:
    """When process ``pid`` started (clock ticks since boot); '' where unknown. With the pid it
    names one process: a pid the system gave again to another one differs here."""
    fields = _proc_stat(pid)
    return fields[19] if len(fields) > 19 else ""


@dataclass(frozen=True)
class Holder:
    """What a lock records about the process that holds it."""

    build: str
    host: str
    pid: int
    started_at: float
    process_start: str = ""
    expires_at: float | None = None  # leases only
    token: str = field(default_factory=lambda: uuid.uuid4().hex)

    @classmethod
    def me(cls, build: str) -> Holder:
        pid = os.getpid()
        return cls(build=build, host=socket.gethostname(), pid=pid, started_at=time.time(),
                   process_start=_process_start(pid))

    @classmethod
    def parse(cls, text: str | bytes) -> Holder | None:
        try:
            doc = json.loads(text)
            return cls(**{k: doc[k] for k in cls.__dataclass_fields__ if k in doc})
        except (ValueError, TypeError, KeyError):
            return None

    def dumps(self) -> str:
        return json.dumps(asdict(self))

    def describe(self) -> str:
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.started_at))
        return f"build {self.build} (host {self.host}, pid {self.pid}, since {since})"

    def dead(self) -> bool:
        """True only when certain: a process of this host that is gone (or whose pid was reused)."""
        if self.host != socket.gethostname():
            return False
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:
            pass
        fields = _proc_stat(self.pid)
        if fields and fields[0] == "Z":  # exited, not yet reaped by its parent
            return True
        return bool(self.process_start) and _process_start(self.pid) not in ("", self.process_start)

    def expired(self, now: float | None = None) -> bool:
        return self.expires_at is not None and (now or CLOCK.now()) > self.expires_at


@dataclass
class HeldLock:
    """A lock this process holds; ``took_over`` describes a dead or expired holder it replaced.
    ``discard``: remove the lock file on release (set for a scene that never started, so a
    build of logs that were not there leaves no lock file behind). ``lost``: why a lease is no
    longer this build's ('' while it is). ``read_only``: why this process may only read the
    scene ('' when it may write it): its data root refused the lock file (a read-only mount,
    a folder of another user's); then it holds the lock shared, or none where there is no lock
    file, and must write nothing there."""

    scene_id: str
    holder: Holder
    took_over: str = ""
    discard: bool = False
    lost: str = ""
    read_only: str = ""

    def check(self) -> None:
        """Raise :class:`LeaseLost` once the lease is lost: nothing may be written after."""
        if self.lost:
            raise LeaseLost(self.lost, scene_id=self.scene_id,
                            fix="the stage stopped before writing more; re-run the build (a "
                                "plain re-run builds the scene, or finds it done)")


# -- a folder root: flock ---------------------------------------------------------------------

def _lock_file(root: DataRoot, scene_id: str) -> Path:
    return DataLayout(root.local).lock(scene_id)


@contextlib.contextmanager
def _file_lock(root: DataRoot, scene_id: str, options: LockOptions,
               log: logging.Logger) -> Iterator[HeldLock]:
    path = _lock_file(root, scene_id)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = _locked_file(path, scene_id, options, log)
    except OSError as exc:
        if exc.errno not in NOT_WRITABLE:
            raise
        with _reader_lock(path, scene_id, options, log, exc) as held:
            yield held
        return
    try:
        previous = Holder.parse(os.pread(fd, 1 << 16, 0))
        me = Holder.me(options.build)
        os.ftruncate(fd, 0)
        os.pwrite(fd, me.dumps().encode(), 0)
        took_over = previous.describe() if previous else ""  # it ended without letting go
        held = HeldLock(scene_id, me, took_over)
        try:
            yield held
        finally:
            if held.discard:  # removed while held: a waiter that took the old file tries again
                path.unlink(missing_ok=True)
            os.ftruncate(fd, 0)  # an empty record: let go cleanly
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


@contextlib.contextmanager
def _reader_lock(path: Path, scene_id: str, options: LockOptions, log: logging.Logger,
                 refused: OSError) -> Iterator[HeldLock]:
    """The lock of a scene whose data root refused this process its lock file: shared (a
    writer holding it is waited for, and waits for this reader), or none where the file is not
    there; the lock says the scene may only be read."""
    why = f"{path}: {refused.strerror or refused}"
    held = HeldLock(scene_id, Holder.me(options.build), read_only=why)
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:   # no lock file (nobody ever locked the scene here), or none we may read
        yield held
        return
    try:
        _wait(scene_id, options, log, lambda: _try_flock(fd, fcntl.LOCK_SH), lambda: _read_record(path))
        try:
            yield held
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def _locked_file(path: Path, scene_id: str, options: LockOptions, log: logging.Logger) -> int:
    """An open descriptor of the lock file at ``path``, flocked. A holder may remove the file
    (its scene never started); a build that took the lock of a file no longer at ``path`` lets
    it go and takes the one there now, so two builds never hold one scene through two files."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            _wait(scene_id, options, log, lambda: _try_flock(fd), lambda: _read_record(path))
            with contextlib.suppress(FileNotFoundError):
                if os.stat(path).st_ino == os.fstat(fd).st_ino:
                    return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)


def _try_flock(fd: int, mode: int = fcntl.LOCK_EX) -> bool:
    try:
        fcntl.flock(fd, mode | fcntl.LOCK_NB)
        return True
    except OSError as exc:
        if exc.errno in (errno.EAGAIN, errno.EACCES):
            return False
        raise


def _read_record(path: Path) -> Holder | None:
    try:
        return Holder.parse(path.read_bytes())
    except OSError:
        return None


def _file_holder(path: Path) -> Holder | None:
    """The holder of a folder root's lock file, or None when nobody holds it."""
    fd = os.open(path, os.O_RDONLY)
    try:
        if _try_flock(fd, fcntl.LOCK_SH):
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        return _read_record(path)
    finally:
        os.close(fd)


# -- a URL root: a lease object ---------------------------------------------------------------

class _Lease:
    """The lease object of one scene on a URL root."""

    def __init__(self, root: DataRoot, scene_id: str):
        self.fs, base = root.filesystem()
        self.path = f"{base}/{LOCK_DIR}/{scene_id}.json"

    def read(self) -> Holder | None:
        try:
            return Holder.parse(self.fs.cat_file(self.path))
        except FileNotFoundError:
            return None

    def create(self, holder: Holder) -> Holder | None:
        """Write ``holder`` if no lease exists, expiring ``LEASE_SECONDS`` from now (the moment
        of writing); the lease written when it is ours afterwards, else None."""
        mine = replace(holder, expires_at=CLOCK.now() + LEASE_SECONDS)
        data = mine.dumps().encode()
        try:
            self._create(data)
        except FileExistsError:
            return None
        except (ValueError, NotImplementedError):  # a backend without exclusive create
            if self.fs.exists(self.path):
                return None
            self.fs.pipe_file(self.path, data)
        # Read back: of two racing creators on a store without a true conditional put, the one
        # whose record is there holds it.
        found = self.read()
        return mine if found is not None and found.token == mine.token else None

    def _create(self, data: bytes) -> None:
        try:
            with self.fs.open(self.path, "xb") as f:
                f.write(data)
        except FileNotFoundError:  # a fresh local:// root (no auto_mkdir): make locks/ first
            self.fs.makedirs(self.path.rsplit("/", 1)[0], exist_ok=True)
            with self.fs.open(self.path, "xb") as f:
                f.write(data)

    def renew(self, holder: Holder) -> Holder | None:
        """Our lease with a later expiry, ``LEASE_SECONDS`` from the moment it is written; None
        when it is no longer ours: another build's is there, or ours has expired (from then on
        another build may take it at any moment, so writing it again could overwrite theirs)."""
        found = self.read()
        if found is None or found.token != holder.token or _lapsing(holder):
            return None
        renewed = replace(holder, expires_at=CLOCK.now() + LEASE_SECONDS)
        self.fs.pipe_file(self.path, renewed.dumps().encode())
        return renewed

    def remove_if(self, holder: Holder) -> bool:
        """Delete the lease if it still holds exactly ``holder`` (an expired or dead one, or ours)."""
        found = self.read()
        if found is None or found.token != holder.token:
            return False
        with contextlib.suppress(FileNotFoundError):
            self.fs.rm_file(self.path)
        return True


@contextlib.contextmanager
def _lease_lock(root: DataRoot, scene_id: str, options: LockOptions,
                log: logging.Logger) -> Iterator[HeldLock]:
    lease = _Lease(root, scene_id)
    me = Holder.me(options.build)
    current: list[Holder] = []
    took_over: list[str] = []

    def attempt() -> bool:
        written = lease.create(me)
        if written is None:
            found = lease.read()
            if found is None or not (found.dead() or found.expired()) or not lease.remove_if(found):
                return False
            written = lease.create(me)
            if written is None:
                return False
            took_over.append(found.describe() + (" (lease expired)" if found.expired()
                                                 else " (process gone)"))
        current[:] = [written]
        return True

    _wait(scene_id, options, log, attempt, lease.read)
    held = HeldLock(scene_id, current[0], took_over[-1] if took_over else "")
    stop = threading.Event()
    thread = threading.Thread(target=_keep_alive, args=(lease, held, current, stop, log),
                              name=f"lease-{scene_id}", daemon=True)
    thread.start()
    try:
        yield held
    finally:
        stop.set()
        thread.join()
        if not held.lost:
            with contextlib.suppress(Exception):
                lease.remove_if(current[0])


def _lapsing(holder: Holder) -> bool:
    """Too near its expiry (or past it) to be renewed safely."""
    return holder.expired(CLOCK.now() + RENEW_MARGIN * LEASE_SECONDS)


def _keep_alive(lease: _Lease, held: HeldLock, current: list[Holder], stop: threading.Event,
                log: logging.Logger) -> None:
    """Renew ``held``'s lease every ``LEASE_SECONDS / 3`` until ``stop``; on finding it taken
    or lapsed, mark it lost and write it no more."""
    while not CLOCK.wait(stop, LEASE_SECONDS / 3):
        try:
            renewed = lease.renew(current[0])
        except Exception as exc:  # the store hiccuped: try again at the next beat, if there is time
            if not _lapsing(current[0]):
                log.warning("lease of scene %s: renewal failed: %s", held.scene_id, exc)
                continue
            renewed = None
        if renewed is None:
            found = None
            with contextlib.suppress(Exception):
                found = lease.read()
            taken = found is not None and found.token != current[0].token
            held.lost = (f"its lease was taken by {found.describe()}" if taken and found
                         else "its lease lapsed before it could be renewed (another build may "
                              "hold the scene now)")
            log.error("scene %s: %s; stopping the stage", held.scene_id, held.lost)
            return
        current[0] = renewed


def _lease_holders(root: DataRoot) -> dict[str, Holder]:
    fs, base = root.filesystem()
    try:
        names = fs.find(f"{base}/{LOCK_DIR}")
    except FileNotFoundError:
        return {}
    out = {}
    for name in names:
        if name.endswith(".json"):
            with contextlib.suppress(FileNotFoundError):
                holder = Holder.parse(fs.cat_file(name))
                if holder is not None and not holder.expired() and not holder.dead():
                    out[name.rsplit("/", 1)[1][:-len(".json")]] = holder
    return out


# -- both ---------------------------------------------------------------------------------------

def _wait(scene_id: str, options: LockOptions, log: logging.Logger, attempt, holder) -> None:
    """Call ``attempt()`` until it takes the lock; SceneLocked after ``options.timeout`` seconds."""
    t0 = time.monotonic()
    told = False
    while not attempt():
        waited = time.monotonic() - t0
        if waited >= options.timeout:
            raise SceneLocked(scene_id, holder(), waited)
        if not told:
            found = holder()
            log.warning("scene %s is locked by %s; waiting up to %.0f s", scene_id,
                     found.describe() if found else "another build", options.timeout)
            told = True
        time.sleep(POLL_SECONDS)


@contextlib.contextmanager
def scene_lock(root: DataRoot, scene_id: str, options: LockOptions | None = None,
               log: logging.Logger | None = None) -> Iterator[HeldLock]:
    """Hold the scene's lock for the ``with`` block (see the module doc)."""
    options = options or LockOptions()
    log = log or logging.getLogger("paradrive.locks")
    lock = _lease_lock if root.remote else _file_lock
    with lock(root, scene_id, options, log) as held:
        if held.took_over:
            log.warning("scene %s: took over the lock of %s, which ended without releasing it",
                        scene_id, held.took_over)
        yield held


def held_locks(root: DataRoot) -> dict[str, Holder]:
    """scene_id -> holder, for every scene of ``root`` locked now (``paradrive status``)."""
    if root.remote:
        return _lease_holders(root)
    out = {}
    for path in sorted((root.local / LOCK_DIR).glob("*.lock")):
        with contextlib.suppress(FileNotFoundError):
            holder = _file_holder(path)
            if holder is not None:
                out[path.stem] = holder
    return out


__all__ = ["DEFAULT_LOCK_TIMEOUT_S", "Holder", "HeldLock", "LeaseLost", "LockOptions", "SceneLocked",
           "held_locks", "scene_lock"]
