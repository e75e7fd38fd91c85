"""File writing that never leaves half-written outputs: write to a temporary name, then rename."""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import itertools
import json
import os
import shutil
import signal
import uuid
from pathlib import Path
import posixpath
from typing import Any
from collections.abc import Callable, Iterator

from paradrive.errors import (NO_ROOM, ConfigError, DiskFullError, FileSizeLimitError, ParaDriveError,
                              byte_count, file_size_limit, no_room_code, short_write, size_limit_fix)


class PathEscapeError(ParaDriveError):
    """A path read from a file (a manifest URI, a scene's image) that could lead out of its folder."""


class UnsafeFileError(ParaDriveError):
    """A file whose loading could run its writer's code (pickle, a module named to import)."""


TEMPORARY_MARK = ".tmp-"


def temporary_name(path: Path) -> Path:
    """A sibling of ``path`` that readers ignore (``.<name>.tmp-<random>``); every temporary
    file or folder is named here, so :func:`remove_stale_temporaries` finds them all."""
    path = Path(path)
    return path.with_name(f".{path.name}{TEMPORARY_MARK}{uuid.uuid4().hex[:8]}")


def is_temporary(name: str) -> bool:
    """A name :func:`temporary_name` made (a write that has not landed)."""
    return name.startswith(".") and TEMPORARY_MARK in name


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, size: int | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it into place, else remove it.

    Works for files and directories (an existing directory at ``path`` is replaced). A write
    that finds no room raises :class:`DiskFullError` (see :func:`no_room_error`); ``size``, the
    bytes the write puts down when known, tells it how many more were needed.
    """
    path = Path(path)
    if path.exists() and not (path.is_file() or path.is_dir()):
        # renaming over it would replace a device such as /dev/full (or a pipe) with a file
        raise ParaDriveError(f"{path} is not a file or folder (a device, pipe or socket); refusing "
                             f"to replace it: name a file to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    try:
        yield tmp
        if tmp.is_dir() and path.exists():
            old = temporary_name(path)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException as exc:
        error = out_of_room(exc, path, tmp, size)  # measured before the temporary goes
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        if error is not None:
            raise error from exc
        raise


@contextlib.contextmanager
def no_room_named(folder: str | os.PathLike, tmp: str | os.PathLike | None = None) -> Iterator[None]:
    """A write under ``folder`` (assembled in ``tmp``, when given, which the caller removes)
    that finds no room raises :class:`DiskFullError` naming ``folder``: for writers that manage
    their own temporary (a scene being ingested) or call libraries that write files themselves
    (a publish's Parquet shards)."""
    folder = Path(folder)
    try:
        yield
    except BaseException as exc:
        if isinstance(exc, DiskFullError):   # raised further in: its folder is this one
            exc.folder = str(folder)
        error = out_of_room(exc, folder, None if tmp is None else Path(tmp), None, folder=folder)
        if error is not None:
            raise error from exc
        raise


def landing(path: str | os.PathLike) -> Path:
    """The folder where the output ``path`` lands: the folder holding the first temporary in
    it (``scenes/.x.tmp-…/images/a.jpg`` lands in ``scenes``), else ``path``'s own folder."""
    path = Path(path)
    for i, part in enumerate(path.parts):
        if is_temporary(part):
            return Path(*path.parts[:i])
    return path.parent


def landed_path(path: str | os.PathLike) -> Path:
    """``path`` with each temporary in it named as what it becomes (``.clips.tmp-…`` as
    ``clips``)."""
    return Path(*(p[1:p.index(TEMPORARY_MARK)] if is_temporary(p) else p for p in Path(path).parts))


def tree_bytes(path: Path | None) -> int:
    """The bytes of a file, or of every file under a folder (0: neither)."""
    if path is None:
        return 0
    with contextlib.suppress(OSError):
        if path.is_file():
            return path.stat().st_size
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())
    return 0


def free_bytes(folder: str | os.PathLike) -> int | None:
    """The bytes free to this user on the file system of ``folder`` (or of its nearest folder
    that exists); None when it cannot be told."""
    place = Path(folder)
    while not place.exists() and place != place.parent:
        place = place.parent
    try:
        return shutil.disk_usage(place).free
    except OSError:
        return None


def out_of_room(exc: BaseException, path: Path, tmp: Path | None, size: int | None, *,
                folder: Path | None = None) -> DiskFullError | None:
    """The :class:`DiskFullError` of a write of ``path`` (in ``tmp``; landing in ``folder``,
    default :func:`landing`) that failed for want of room, with what it had written and still
    had to write, or the size of the file it was copying; None for any other failure. One
    raised further in (a file of a folder being assembled) gets this temporary's bytes added."""
    if isinstance(exc, DiskFullError):
        exc.written = (exc.written or 0) + tree_bytes(tmp)
        return None
    code = _no_room_code(exc, tmp)
    if code is None or not isinstance(exc, OSError):
        return None
    written = tree_bytes(tmp)
    missing, copying = _what_failed(exc)
    if size is not None:
        missing = max(missing or 0, size - written) or None
    return no_room_error(code, path, missing=missing, written=written, size=size or copying,
                         folder=folder)


def _what_failed(exc: OSError) -> tuple[int | None, int | None]:
    """What a failed write says of its size: the bytes a short write left unwritten, and the
    size of the file a copy was writing (shutil names its source, then its target)."""
    short = short_write(exc)
    source = exc.filename if exc.filename2 else None
    return (short[0] - short[1] if short else None,
            tree_bytes(Path(os.fsdecode(source))) or None if source else None)


def _no_room_code(exc: BaseException, tmp: Path | None) -> int | None:
    """ENOSPC, EDQUOT or EFBIG when ``exc`` is a write that found no room in ``tmp`` (a file or a
    folder of them): its errno or its text (:func:`~paradrive.errors.no_room_code`); for a
    library's error that gives neither, a file of ``tmp`` at this process's size limit or a
    full disk; a short write ("N requested and M written") with a file at the limit is EFBIG."""
    if not isinstance(exc, OSError) or isinstance(exc, DiskFullError):
        return None
    if exc.errno is not None:
        return exc.errno if exc.errno in NO_ROOM else None
    code = no_room_code(exc)
    if code not in (None, errno.ENOSPC) or tmp is None:
        return code
    limit = file_size_limit()
    files = [tmp] if tmp.is_file() else [p for p in tmp.rglob("*") if p.is_file()] if tmp.is_dir() else []
    if limit is not None and any(f.stat().st_size >= limit for f in files):
        return errno.EFBIG
    if code is not None:
        return code
    with contextlib.suppress(OSError):
        if shutil.disk_usage(tmp.parent).free == 0:
            return errno.ENOSPC
    return None


def no_room_error(code: int, path: Path, *, missing: int | None = None, written: int | None = None,
                  size: int | None = None, folder: Path | None = None) -> DiskFullError:
    """The error of a write of ``path`` (a file, or the folder ``folder`` it lands in) that found
    no room (``code``: ENOSPC, EDQUOT or EFBIG), naming the file as it lands (never its
    temporary name), how much more it needed where known, and the fix; nothing half-written is
    kept by the writers that raise it."""
    shown = landed_path(path)
    place = landing(path) if folder is None else folder
    where = f"in {shown}" if folder is not None and shown == folder else str(shown)
    if code == errno.EFBIG:
        return FileSizeLimitError(code, f"{size_limit_fix(place)} (while writing {where}; "
                                        f"nothing half-written was kept)", folder=place)
    what = "disk quota exceeded" if code == errno.EDQUOT else "disk full"
    need = f" (needs at least {byte_count(missing)} more)" if missing else ""
    return DiskFullError(code, f"{what} while writing {where}{need}; free space on {place} and "
                               f"re-run (nothing half-written was kept)", folder=place,
                         missing=missing, written=written, size=size)


def no_room_message(exc: BaseException, who: str, folder: str | os.PathLike | None = None, *,
                    elsewhere: str = "pass another --data") -> str | None:
    """One line for a write that failed for want of room (:class:`DiskFullError`, or an
    OSError whose errno or text says so): ``who`` (``scene <id>: <stage>``), the folder the
    output lands in, the bytes free there now, how much more than that the write needed (or
    the size of what it was writing) and the fix, free space there or ``elsewhere``; None for
    any other error. ``folder``: where the writer wrote, for an error that names no file."""
    if not isinstance(exc, DiskFullError):
        code = no_room_code(exc)
        if code is None or not isinstance(exc, OSError):
            return None
        target = exc.filename2 or exc.filename
        missing, copying = _what_failed(exc)
        exc = no_room_error(code, Path(os.fsdecode(target or folder or ".")), missing=missing,
                            size=copying, folder=None if target else Path(folder or "."))
        if not (target or folder):
            exc.folder = None
    place = exc.folder or folder
    shown = "the folder it writes" if place is None else str(place)
    if exc.errno == errno.EFBIG:   # the limit and the file it stopped (not free space)
        return f"{who}: {exc.strerror if isinstance(exc, FileSizeLimitError) else size_limit_fix(shown)}"
    free = None if place is None else free_bytes(place)
    # what was written in vain is gone again, so the write needed more than is free now
    need = (f"at least {byte_count(exc.missing)} more than that" if exc.missing
            else f"more than that: it ran out copying a file of {byte_count(exc.size)}" if exc.size
            else f"more than that: it had written {byte_count(exc.written)} when it ran out"
            if exc.written else "more than that")
    room = f": {byte_count(free)} free there and it needs {need}" if free is not None else ""
    what = "disk quota exceeded" if exc.errno == errno.EDQUOT else "disk full"
    return (f"{who}: {what} writing in {shown}{room}; free space there (or {elsewhere}) and "
            f"re-run (nothing half-written was kept)")


def check_output(path: str | os.PathLike, what: str, *, folder: bool = False) -> Path:
    """``path`` when an output can be written there, checked before any work: a ConfigError
    naming ``what`` (``--save``), the path and the fix when it is a folder where a file goes (or a
    file where a folder goes), a device such as /dev/full, or under a folder this user cannot
    write or a path that cannot hold folders. A probe file is made and removed where the first
    missing folder would go; nothing else is created."""
    path = Path(path)
    kind = "folder" if folder else "file"
    if path.exists() and not (path.is_dir() if folder else path.is_file()):
        found = "a folder" if path.is_dir() else "a file" if path.is_file() else "a device, pipe or socket"
        raise ConfigError(f"{what} {path}: is {found}, not a {kind}; name a {kind} to write "
                          f"(e.g. {path / 'out' if path.is_dir() else path.parent / 'out'})")
    existing = path if path.exists() else path.parent
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"{what} {path}: {existing} is a file, not a folder; name a path under "
                          f"a folder")
    probe = temporary_name(existing / "probe")
    try:
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
        probe.unlink()
    except OSError as exc:
        raise ConfigError(f"{what} {path}: cannot write in {existing} ({exc.strerror}); name a "
                          f"{kind} where this user can write") from exc
    return path


def encoded_in_memory(write: Callable[[str], None]) -> bytes | None:
    """The bytes ``write(path)`` puts in a file, written to an anonymous file in memory (Linux
    ``memfd``) and read back; None where there is none. For libraries that write only to a path
    and handle a full disk badly (libjpeg ends the process; libpng truncates the file and
    reports success): what they make is then written by :func:`write_bytes`, whose full disk is
    an error like any other."""
    if not hasattr(os, "memfd_create"):
        return None
    fd = os.memfd_create("paradrive-encode", os.MFD_CLOEXEC)
    try:
        write(f"/proc/self/fd/{fd}")
        size = os.fstat(fd).st_size
        chunks, done = [], 0
        while done < size:
            chunk = os.pread(fd, size - done, done)
            if not chunk:
                break
            chunks.append(chunk)
            done += len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path, size=len(data)) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: object) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def remove_stale_temporaries(directory: str | os.PathLike) -> int:
    """Delete the temporaries a killed process left under ``directory`` and those made for
    ``directory`` itself (its siblings ``.<name>.tmp-*``, e.g. a scene being ingested); returns
    how many. Only for a folder no live process writes (its scene lock held)."""
    directory = Path(directory)
    pattern = f".*{TEMPORARY_MARK}*"
    found = [*directory.parent.glob(f".{glob.escape(directory.name)}{TEMPORARY_MARK}*"),
             *directory.rglob(pattern)]
    for p in found:
        remove_entry(p)
    return len(found)


def remove_entry(path: Path) -> None:
    """Delete ``path``: a folder with what it holds, a file or a link (never what a link leads to)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def load_tensors(path: str | os.PathLike, map_location: Any = "cpu") -> Any:
    """``torch.load`` of tensors and plain containers only (``weights_only=True``).

    A file on shared storage is written by whoever can write there; one that needs pickle to
    load (Python objects, an old format) is refused with :class:`UnsafeFileError`, never run.
    """
    import pickle

    import torch

    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UnsafeFileError(f"{path}: holds Python objects that only pickle can load ({first}); "
                              f"refused, since loading it could run code. Delete it (it was made "
                              f"by an older version or by someone else) and run again") from exc


def check_relative(rel: object, what: str) -> str:
    """``rel`` when it is a relative, normalised POSIX path with no ``..`` (``a/b.mp4``).

    Paths read from shared files decide what gets opened: an absolute one or one with ``..``
    would open any file on the reader's machine. ``what`` names the row and column in the error.
    """
    text = rel if isinstance(rel, str) else ""
    if (not text or "\\" in text or "\0" in text or text.startswith("/")
            or posixpath.normpath(text) != text or ".." in text.split("/")):
        raise PathEscapeError(f"{what}: path {rel!r} must be relative, normalised and inside its "
                              f"folder (no '..', not absolute); the file was damaged or not written "
                              f"by paradrive: re-create it")
    return text


def path_inside(root: str | os.PathLike, rel: object, what: str, *,
                may_lead_out: Callable[[Path], bool] | None = None) -> Path:
    """``root / rel`` after :func:`check_relative`, when it also stays inside ``root`` with every
    symlink resolved; ``may_lead_out(resolved)`` may allow a link that leads elsewhere."""
    path = Path(root) / check_relative(rel, what)
    resolved = path.resolve()
    if resolved.is_relative_to(Path(root).resolve()) or (may_lead_out and may_lead_out(resolved)):
        return path
    raise PathEscapeError(f"{what}: {rel!r} is a link to {resolved}, outside {root}; replace it "
                          f"with the file itself or re-create the folder")


def stop_point(name: str) -> None:
    """Stop this process at a named step (``publish:first-media``, ``fit:checkpoint-25``, ...)
    when ``PARADRIVE_STOP_AT`` names it.

    Tests stop a real build at an exact step this way: the process stops itself (SIGSTOP), the
    test sees it stopped (``waitpid`` with ``WUNTRACED``), then kills or interrupts it."""
    if os.environ.get("PARADRIVE_STOP_AT") == name:
        os.kill(os.getpid(), signal.SIGSTOP)


def counted_stop(prefix: str) -> Callable[[], None]:
    """A :func:`stop_point` for the k-th time something happens in this process: each call of
    the function returned is one more (``render:frame-1``, ``render:frame-2``, ...).

    A test stops a build at its k-th written frame, image or video this way instead of watching
    the folder fill (a burst of writes can end the stage before a watcher looks)."""
    counter = itertools.count(1)

    def point() -> None:
        stop_point(f"{prefix}-{next(counter)}")

    return point
