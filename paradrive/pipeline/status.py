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
    from paradrive.storage import data_root

    location = data or ledger.meta().get("data_root")
    if not location:
        return []
    ids = ledger.scene_ids()
    held = held_locks(data_root(location, list(storage_options), None, False))
    return [{"scene_id": sid, "build": h.build, "host": h.host, "pid": h.pid,
             "since": h.started_at, "holder": h.describe()}
            for sid, h in sorted(held.items()) if sid in ids]


def build_status(build: str, manifests: Path, data: str | None = None,
                 storage_options: Sequence[str] = ()) -> dict[str, Any]:
    """The ledger's summary of ``build`` (:meth:`Ledger.summary`), with the locks it took over
    (``takeovers``) and its scenes locked now (``locks``, :func:`scene_locks`)."""
    ledger = open_ledger(build, manifests)
    summary = ledger.summary()
    summary["takeovers"] = [{k: t[k] for k in ("scene_id", "stage", "at", "error")}
                            for t in ledger.takeovers()]
    summary["locks"] = scene_locks(ledger, data, storage_options)
    return summary


__all__ = ["build_status", "open_ledger", "scene_locks"]
