"""Errors that name the scene, the file and the fix."""

from __future__ import annotations

import errno
import re

# exit codes of a build (and of the CLI): every scene landed; no scene landed; a usage or
# configuration error (before any stage ran); some scenes landed, some failed; Ctrl-C and
# SIGTERM, as a shell reports a process those signals ended
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_PARTIAL, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
EXIT_TERMINATED = 143


class Terminated(KeyboardInterrupt):
    """SIGTERM reached a build: it unwinds as Ctrl-C does (every ``with`` and ``finally`` on
    the way cleans up), then exits with :data:`EXIT_TERMINATED`."""


class ParaDriveError(Exception):
    """Base class of every error the builder raises on purpose."""


class SceneError(ParaDriveError):
    """Bad input for one scene: the scene is marked failed with this message, others go on.

    The message reads ``scene <id>: <what> (<file>); <fix>``.
    """

    def __init__(self, message: str, *, scene_id: str | None = None, path: object = None,
                 fix: str | None = None):
        self.scene_id = scene_id
        self.path = None if path is None else str(path)
        self.fix = fix
        self.reason = message
        text = message
        if path is not None:
            text = f"{text} ({path})"
        if fix:
            text = f"{text}; {fix}"
        if scene_id:
            text = f"scene {scene_id}: {text}"
        super().__init__(text)


class ConfigError(ParaDriveError):
    """A stage file, profile or parameter is wrong (typo, wrong type, unknown name)."""


class StageNotImplemented(ParaDriveError):
    """A declared stage whose implementation is missing: fails loudly, never counts as done."""


def validation_message(exc) -> str:
    """The first problem of a pydantic ValidationError: ``field 'a.b': message``."""
    err = exc.errors()[0]
    return f"field '{'.'.join(str(x) for x in err['loc'])}': {err['msg']}"


_NO_SPACE = {errno.ENOSPC, errno.EDQUOT}
NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
NOT_WRITABLE = {errno.EROFS, errno.EACCES, errno.EPERM}


class DiskFullError(OSError):
    """A write that found no room (the disk full, or a file at its size limit), its message
    naming the file and the fix. ``folder``: where the output lands (a temporary's own folder
    is never named); ``missing``: bytes the write still had to put down when it failed, where
    known (a short write says so); ``written``: bytes it had put down in its temporaries, which
    were removed; ``size``: the size of the file it was writing (a copy's source), where known."""

    def __init__(self, code: int, message: str, *, folder: object = None, missing: int | None = None,
                 written: int | None = None, size: int | None = None):
        super().__init__(code, message)
        self.folder = None if folder is None else str(folder)
        self.missing = missing
        self.written = written
        self.size = size


class FileSizeLimitError(DiskFullError):
    """A write that took a file past this process's file size limit (``ulimit -f``) or the
    largest file its file system holds (EFBIG): the disk may have room to spare."""


def file_size_limit() -> int | None:
    """This process's file size limit in bytes (``ulimit -f``; RLIMIT_FSIZE), None when unlimited."""
    import resource

    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return None if soft == resource.RLIM_INFINITY else int(soft)


def size_limit_fix(where: object) -> str:
    """What to do about EFBIG while writing ``where``: the ``ulimit -f`` limit when one is set,
    else the file system's largest file."""
    limit = file_size_limit()
    if limit is None:
        return (f"a file in {where} grew past the largest file its file system holds (not a full "
                f"disk): write to another file system and re-run")
    return (f"file size limit (ulimit -f: {limit:,} bytes) reached writing in {where}, not a full "
            f"disk: raise it (ulimit -f unlimited) and re-run")


_SHORT_WRITE = re.compile(r"(\d+) requested and (\d+) written")
_NO_ROOM_TEXT = {errno.ENOSPC: ("no space left on device", "[errno 28]"),
                 errno.EDQUOT: ("disk quota exceeded", "[errno 122]"),
                 errno.EFBIG: ("file too large", "[errno 27]")}


def short_write(exc: BaseException) -> tuple[int, int] | None:
    """(requested, written) of a library's short write that gives no errno (numpy's
    ``tofile`` and Pillow say "48096 requested and 35808 written"), else None."""
    found = _SHORT_WRITE.search(str(exc)) if isinstance(exc, OSError) else None
    return (int(found[1]), int(found[2])) if found else None


def no_room_code(exc: BaseException) -> int | None:
    """ENOSPC, EDQUOT or EFBIG when ``exc`` is a write that found no room: by its errno, or by
    its text where a library gives none (a short write counts as ENOSPC); None otherwise."""
    if not isinstance(exc, OSError):
        return None
    if exc.errno is not None:
        return exc.errno if exc.errno in NO_ROOM else None
    text = str(exc).lower()
    for code, words in _NO_ROOM_TEXT.items():
        if any(w in text for w in words):
            return code
    return errno.ENOSPC if short_write(exc) else None


def byte_count(n: int) -> str:
    """``48,096 bytes``; ``3,412,345 bytes (3.4 MB)`` from a megabyte on."""
    if n < 1_000_000:
        return f"{n:,} byte{'' if n == 1 else 's'}"
    return f"{n:,} bytes ({f'{n / 1e9:.1f} GB' if n >= 1_000_000_000 else f'{n / 1e6:.1f} MB'})"


def os_error_fix(exc: BaseException, folder: object) -> str:
    """The fix of a write that failed for want of room or rights in ``folder``, as ``; …``
    (empty for other errors)."""
    code = getattr(exc, "errno", None)
    if isinstance(exc, DiskFullError):   # the writer already named the file and the fix
        return ""
    if code == errno.EFBIG:
        return f"; {size_limit_fix(folder)}"
    if code in _NO_SPACE:
        return f"; no room to write in {folder}: free space there (or pass another --data) and re-run"
    if code in NOT_WRITABLE:
        return f"; {folder} cannot be written: pass a --data this user can write, then re-run"
    return ""


# The optional packages and the extra that brings each (pyproject.toml's optional dependencies).
OPTIONAL_EXTRAS = {"diffusers": "wan", "transformers": "wan", "safetensors": "wan",
                   "pycolmap": "video", "gsplat": "gpu", "rerun": "view"}


def missing_extra(exc: ModuleNotFoundError) -> ConfigError | None:
    """A one-line error naming the extra to install, for an optional package that is missing;
    None for any other missing module (a broken installation, not a choice)."""
    top = (exc.name or "").split(".")[0]
    extra = OPTIONAL_EXTRAS.get(top)
    if extra is None:
        return None
    return ConfigError(f"{top} is not installed: this needs the '{extra}' extra "
                       f"(pip install 'paradrive[{extra}]', or scripts/setup.sh build,{extra})")
