"""Errors that name the scene, the file and the fix."""

from __future__ import annotations

import errno

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
_NOT_WRITABLE = {errno.EROFS, errno.EACCES, errno.EPERM}


class DiskFullError(OSError):
    """A write that found no room (the disk full, or a file at its size limit), its message
    naming the file and the fix."""


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
    if code in _NOT_WRITABLE:
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
