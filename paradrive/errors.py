"""Errors that name the scene, the file and the fix."""

from __future__ import annotations


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
