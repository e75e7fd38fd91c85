"""What the ledger of a build says (``paradrive status BUILD`` prints it,
:mod:`paradrive.commands.status`).

:func:`build_status` gathers how many scenes are done / failed / running / pending, time and
memory per stage, the slowest scenes, every failure with its reason, the build's scenes that are
locked now and by which build (read from the data root's scene locks), and the locks the build
took over from a holder that died. Reads ``<manifests>/<build>/ledger.sqlite`` while a build may
still be writing it (WAL readers never block the writers).
"""

from __future__ import annotations

from pathlib import Path
from collections.abc import Sequence
from typing import Any

from paradrive.pipeline.ledger import LEDGER_FILE, Ledger
from paradrive.pipeline.locks import held_locks


def open_ledger(build: str, manifests: Path) -> Ledger:
    """A build name (under ``manifests``) or the path of a build folder / ledger file."""
    path = Path(build)
    if path.name == LEDGER_FILE and path.is_file():
        return Ledger.for_reading(path, path.parent.name)
    if (path / LEDGER_FILE).is_file():
        return Ledger.for_reading(path / LEDGER_FILE, path.name)
    return Ledger.open_existing(manifests, build)


def scene_locks(ledger: Ledger, data: str | None = None, storage_options: Sequence[str] = ()) -> list[dict]:
    """The build's scenes locked now: scene_id and the holder's build, host, pid, start."""
    from paradrive.redact import redact
    from paradrive.storage import StorageError, data_root

    location = data or ledger.meta().get("data_root")
    if not location:
        return []
    ids = ledger.scene_ids()
    root = data_root(location, list(storage_options), None, False)
    try:
        held = held_locks(root)
    except Exception as exc:  # an object store's own errors (botocore, aiohttp…)
        raise StorageError(redact(f"the scene locks under {location} could not be read "
                                  f"({type(exc).__name__}: {exc}); check the credentials "
                                  f"(--storage-option key=… secret=…, or the environment) and "
                                  f"the network", root.storage_options)) from exc
    return [{"scene_id": sid, "build": h.build, "host": h.host, "pid": h.pid,
             "since": h.started_at, "holder": h.describe()}
            for sid, h in sorted(held.items()) if sid in ids]


def build_status(build: str, manifests: Path, data: str | None = None,
                 storage_options: Sequence[str] = ()) -> dict[str, Any]:
    """The ledger's summary of ``build`` (:meth:`Ledger.summary`), with the locks it took over
    (``takeovers``) and its scenes locked now (``locks``, :func:`scene_locks`; where an object
    store cannot be read, none and ``locks_error`` saying why)."""
    from paradrive.storage import StorageError

    ledger = open_ledger(build, manifests)
    summary = ledger.summary()
    summary["takeovers"] = [{k: t[k] for k in ("scene_id", "stage", "at", "error")}
                            for t in ledger.takeovers()]
    try:
        summary["locks"] = scene_locks(ledger, data, storage_options)
    except StorageError as exc:  # the ledger is local: it is shown all the same
        summary["locks"], summary["locks_error"] = [], str(exc)
    return summary


__all__ = ["build_status", "open_ledger", "scene_locks"]
