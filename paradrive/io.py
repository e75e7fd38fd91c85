"""File writing that never leaves half-written outputs: write to a temporary name, then rename."""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import json
import os
import shutil
import signal
import uuid
from pathlib import Path
import posixpath
from typing import Any
from collections.abc import Callable, Iterator

from paradrive.errors import (ConfigError, DiskFullError, FileSizeLimitError, ParaDriveError, file_size_limit,
                              size_limit_fix)


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
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it into place, else remove it.

    Works for files and directories (an existing directory at ``path`` is replaced).
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
        code = _no_room_code(exc, tmp)
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        if code is not None:
            raise no_room_error(code, path) from exc
        raise


NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def _no_room_code(exc: BaseException, tmp: Path) -> int | None:
    """ENOSPC, EDQUOT or EFBIG when ``exc`` is a write that found no room in ``tmp`` (a file or a
    folder of them): its errno, or for a library's short write that gives none (Pillow's
    "N requested and M written") a file of ``tmp`` at this process's size limit, or a full disk."""
    if not isinstance(exc, OSError) or isinstance(exc, DiskFullError):
        return None
    if exc.errno is not None:
        return exc.errno if exc.errno in NO_ROOM else None
    limit = file_size_limit()
    files = [tmp] if tmp.is_file() else [p for p in tmp.rglob("*") if p.is_file()] if tmp.is_dir() else []
    if limit is not None and any(f.stat().st_size >= limit for f in files):
        return errno.EFBIG
    with contextlib.suppress(OSError):
        if shutil.disk_usage(tmp.parent).free == 0:
            return errno.ENOSPC
    return None


def no_room_error(code: int, path: Path) -> DiskFullError:
    """The error of a write of ``path`` that found no room (``code``: ENOSPC, EDQUOT or EFBIG),
    naming the file and the fix; nothing half-written is kept by the writers that raise it."""
    if code == errno.EFBIG:
        return FileSizeLimitError(code, f"{size_limit_fix(path.parent)} (while writing {path}; "
                                        f"nothing half-written was kept)")
    what = "disk quota exceeded" if code == errno.EDQUOT else "disk full"
    return DiskFullError(code, f"{what} while writing {path}; free space on {path.parent} and re-run "
                               f"(nothing half-written was kept)")


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


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
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
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    return len(found)


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
