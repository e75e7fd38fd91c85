"""Turn what a user points a build at into scene URIs.

``paradrive build --scenes`` takes, in any mix:

- a scene URI (``waymo:…``, ``nuscenes:…``, ``drivestudio:…``, ``synthetic:…``): kept as is;
- a list file: one URI or path per line; blank lines and lines starting with ``#`` are ignored,
  as is a trailing `` # comment`` (a ``#`` glued to a URI is its scene fragment); paths are
  relative to the list file and must stay inside its folder (a log elsewhere is named by a URI);
- a ``.tfrecord`` file: one ``waymo:`` scene;
- a folder:
  - a nuScenes dataroot (``v1.0-*/scene.json``): one ``nuscenes:<root>?version=<v>#<name>`` per
    scene of every version found;
  - a DriveStudio processed scene (``images/`` plus ``ego_pose/`` or ``extrinsics/``), or a folder
    of them: one ``drivestudio:`` scene each;
  - otherwise every ``*.tfrecord`` below it (one ``waymo:`` scene each), together with any
    DriveStudio scenes among its sub-folders; a link among them that leads out of the folder is
    refused.

Paths in the URIs are absolute, so a build reads the same logs whatever the working folder of a
worker. Duplicates are dropped, first occurrence wins.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from paradrive.errors import ConfigError
from paradrive.ingest.waymo import SUFFIXES as WAYMO_SUFFIXES
from paradrive.uri import KINDS

_TRAILING_COMMENT = re.compile(r"\s+#.*$")


def is_uri(text: str) -> bool:
    kind, sep, _ = text.partition(":")
    return bool(sep) and kind in KINDS


def expand_scene_inputs(items: list[str]) -> list[str]:
    """Scene URIs from URIs, list files and folders of logs (see the module doc)."""
    uris: list[str] = []
    for item in items:
        uris.extend(_expand(str(item).strip(), base=Path.cwd(), depth=0, within=None))
    seen: set[str] = set()
    out = []
    for u in uris:
        if u not in seen:
            seen.add(u)
            out.append(u)
    return out


def _inside(path: Path, folder: Path, what: str) -> None:
    """Refuse ``path`` when it resolves (links followed) outside ``folder``."""
    resolved = path.resolve()
    if not resolved.is_relative_to(folder.resolve()):
        raise ConfigError(f"{what} resolves to {resolved}, outside {folder}; move it there, or "
                          f"name it by a scene URI (waymo:/…, drivestudio:/…)")


def _expand(item: str, base: Path, depth: int, within: Path | None) -> list[str]:
    if not item:
        return []
    if is_uri(item):
        return [item]
    path = Path(item).expanduser()
    if not path.is_absolute():
        path = base / path
    if within is not None:  # a line of a list file: the list's folder is what was given
        _inside(path, within, f"{item!r}")
    if path.is_dir():
        return scenes_in_folder(path)
    if path.is_file():
        if path.suffix in WAYMO_SUFFIXES:
            return [f"waymo:{path.resolve()}"]
        if depth > 4:
            raise ConfigError(f"{path}: scene lists nest more than 4 deep; is a list including itself?")
        return _read_list(path, depth)
    raise ConfigError(f"--scenes {item!r}: not a scene URI (kind one of {', '.join(KINDS)}), "
                      f"nor an existing list file or folder of logs")


def _read_list(path: Path, depth: int) -> list[str]:
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a text scene list (one URI or path per line)") from exc
    uris: list[str] = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = _TRAILING_COMMENT.sub("", raw).strip()
        if not line or line.startswith("#"):
            continue
        try:
            uris.extend(_expand(line, base=path.parent, depth=depth + 1, within=path.parent))
        except ConfigError as exc:
            raise ConfigError(f"{path}:{number}: {exc}") from exc
    return uris


def is_drivestudio_scene(folder: Path) -> bool:
    return (folder / "images").is_dir() and any(
        (folder / d).is_dir() for d in ("ego_pose", "extrinsics"))


def nuscenes_versions(root: Path) -> list[Path]:
    return sorted(p.parent for p in root.glob("v1.0-*/scene.json"))


def nuscenes_scene_uris(root: Path) -> list[str]:
    uris: list[str] = []
    for version_dir in nuscenes_versions(root):
        table = version_dir / "scene.json"
        try:
            records = json.loads(table.read_text())
            names = [r["name"] for r in records]
        except (json.JSONDecodeError, TypeError, KeyError) as exc:
            raise ConfigError(f"{table}: not a nuScenes scene table (a JSON list of records with "
                              f"'name'): {exc}") from exc
        uris.extend(f"nuscenes:{root.resolve()}?version={version_dir.name}#{name}"
                    for name in names)
    return uris


def scenes_in_folder(folder: Path) -> list[str]:
    """Scene URIs of a nuScenes dataroot, DriveStudio folder(s) or a folder of Waymo tfrecords."""
    folder = folder.resolve()
    if nuscenes_versions(folder):
        return nuscenes_scene_uris(folder)
    if is_drivestudio_scene(folder):
        return [f"drivestudio:{folder}"]
    found = [p for p in sorted(folder.rglob("*"))
             if p.is_file() and p.suffix in WAYMO_SUFFIXES and not p.name.startswith(".")]
    scenes = [p for p in sorted(folder.iterdir()) if p.is_dir() and is_drivestudio_scene(p)]
    for p in found + scenes:
        _inside(p, folder, f"{p}")
    uris = [f"waymo:{p}" for p in found] + [f"drivestudio:{p}" for p in scenes]
    if not uris:
        raise ConfigError(f"{folder}: no scenes found; expected *.tfrecord files (Waymo), a "
                          f"nuScenes dataroot (v1.0-*/scene.json) or DriveStudio processed "
                          f"folders (<scene>/images with ego_pose/ or extrinsics/)")
    return uris
