"""Turn what a user points a build at into scene URIs.

``paradrive build --scenes`` takes, in any mix:

- a scene URI (``waymo:…``, ``nuscenes:…``, ``drivestudio:…``, ``synthetic:…``): kept as is;
- a list file (UTF-8, a byte-order mark at its start skipped; UTF-16 with its mark read too):
  one URI or path per line; blank lines and lines starting with ``#`` are ignored, as is a
  trailing `` # comment`` (a ``#`` glued to a URI is its scene fragment); paths are taken as
  written, relative to the list file, and must stay inside its folder (a log elsewhere is named
  by a URI, where ``#``, ``?`` and ``%`` in a name are written ``%23``, ``%3F``, ``%25``);
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
worker, and written by :func:`paradrive.uri.quote_name`, so a file named with ``#``, ``?``,
``%``, spaces or letters beyond ASCII reads back as the same file.

Every log is given once, and every scene gets an id of its own (:func:`distinct_scenes`): two
inputs that are the same log (one URI twice, one file by two paths or through a link, one
synthetic street or nuScenes scene twice; a synthetic street is what its values make, whatever
its name or how its numbers are written, :func:`paradrive.ingest.synthetic.street_identity`)
are refused before any work, naming where each was given; two different logs whose names give
one scene id (``/a/drive.mp4`` and ``/b/drive.mp4``) each get that id followed by a short hash
of the log's identity (its real path, and the query that cuts it), written into the URI as its
scene name (``video:/b/drive.mp4#drive-<hash>``), so the ledger, the markers and the index all
carry it. A scene id so long that a file named after it would pass the file system's limit on a
name is refused too (:func:`paradrive.stages.ingest.check_uri`).
"""

from __future__ import annotations

import codecs
import json
import os
import re
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from paradrive.errors import ConfigError
from paradrive.uri import KINDS, SceneURI, make_uri, parse_uri, scene_name, short_hash, with_name

_TRAILING_COMMENT = re.compile(r"\s+#.*$")
# kinds whose log is no file: the same id is the same nuScenes scene, the same values the same street
_NAMED_LOGS = ("synthetic", "nuscenes")
# byte-order marks a scene list may start with, and the encoding each says
_BOMS = ((codecs.BOM_UTF8, "utf-8-sig"), (codecs.BOM_UTF16_LE, "utf-16"),
         (codecs.BOM_UTF16_BE, "utf-16"))


@dataclass(frozen=True)
class SceneInput:
    """A scene URI and where it was given (``--scene``, ``list.txt:3``, a folder)."""

    uri: str
    where: str

    def describe(self) -> str:
        return self.where if self.uri in self.where else f"{self.where} ({self.uri})"


def _waymo_suffixes() -> tuple[str, ...]:
    """A Waymo segment's file suffixes; imported when a path is looked at, so a build (and every
    command) starts without the log readers and what they import (torch)."""
    from paradrive.ingest.waymo import SUFFIXES

    return tuple(SUFFIXES)


def is_uri(text: str) -> bool:
    kind, sep, _ = text.partition(":")
    return bool(sep) and kind in KINDS


def expand_scene_inputs(items: list[str], ingest: Mapping[str, Any] | None = None) -> list[str]:
    """Scene URIs from URIs, list files and folders of logs, each log once with an id of its
    own (see the module doc)."""
    return scene_uris([], items, ingest)


def scene_uris(scene: list[str], scenes: list[str],
               ingest: Mapping[str, Any] | None = None) -> list[str]:
    """The scenes of ``--scene`` URIs and ``--scenes`` items (URIs, list files, folders), in
    the order given, through :func:`distinct_scenes` (``ingest``: the build's ingest
    parameters, which give a synthetic street the values its URI leaves out)."""
    given = [SceneInput(str(uri).strip(), "--scene") for uri in scene]
    for item in scenes:
        given.extend(_expand(str(item).strip(), base=Path.cwd(), depth=0, within=None,
                             where=f"--scenes {item}"))
    return distinct_scenes(given, ingest)


def log_key(uri: SceneURI, ingest: Mapping[str, Any] | None = None) -> str:
    """What one log is, whatever path or name it is given by: a synthetic street's values (its
    name and how its numbers are written aside; ``ingest``, the build's ingest parameters, fill
    in what the URI leaves out), a nuScenes scene's id (it names the scene), else the kind, the
    real path of the file or folder (links followed), a folder's segment and the query that cuts
    or scales it."""
    if uri.kind == "synthetic":
        from paradrive.ingest.synthetic import street_identity

        return f"synthetic\0{street_identity(uri, ingest)!r}"
    if uri.kind in _NAMED_LOGS:
        return f"{uri.kind}\0{uri.scene_id}"
    path = os.path.realpath(os.path.expanduser(uri.path))
    # a fragment only names the scene, except for a folder of Waymo segments, where it picks one
    picked = uri.scene if uri.kind == "waymo" and os.path.isdir(path) and uri.scene else ""
    query = "&".join(f"{k}={v}" for k, v in sorted(uri.query.items()))
    return "\0".join((uri.kind, path, picked, query))


def distinct_scenes(inputs: list[SceneInput], ingest: Mapping[str, Any] | None = None) -> list[str]:
    """The URIs of ``inputs``, each log once, no two sharing a scene id (see the module doc).

    Two inputs of one log are a ConfigError naming both (``ingest``: the build's ingest
    parameters, which tell what a synthetic URI that leaves out its frames makes). Two logs
    whose ids meet are renamed ``<name>-<hash of the log>``, every one of them, so the result
    depends on the set of inputs, not their order; where a name cannot be given (a Waymo folder
    with ``#<segment>``) the error names both and the fix."""
    first: dict[str, SceneInput] = {}
    by_id: dict[str, list[tuple[str, SceneInput]]] = defaultdict(list)
    for given in inputs:
        uri = parse_uri(given.uri)
        key = log_key(uri, ingest)
        if key in first:
            raise ConfigError(f"{first[key].describe()} and {given.describe()} are the same log "
                              f"({_what(uri, ingest, parse_uri(first[key].uri))}); give it once")
        first[key] = given
        by_id[uri.scene_id].append((key, given))
    renamed: dict[str, str] = {}
    for scene_id, logs in by_id.items():
        if len(logs) > 1:
            renamed.update((given.uri, _renamed(scene_id, key, given, logs)) for key, given in logs)
    return [renamed.get(given.uri, given.uri) for given in inputs]


def missing_inputs(uris: list[str]) -> list[str]:
    """The URIs whose log is a local file or folder that is not there (a synthetic street has
    none to look for)."""
    missing = []
    for text in uris:
        uri = parse_uri(text)
        if uri.kind != "synthetic" and not os.path.exists(os.path.expanduser(uri.path)):
            missing.append(text)
    return missing


def check_present(uris: list[str], shown: int = 3, ingest: Mapping[str, Any] | None = None) -> None:
    """Refuse, in one line, scene inputs whose own values no ingest takes or whose scene id no
    file system can name (the first of them), then those whose files are not there: how many,
    the first few, and the fix. A build or a plan of logs that do not exist stops before any
    work. With ``ingest`` (the build's ingest parameters) their defaults are checked too, and
    two synthetic URIs that make one street with them are refused naming both."""
    from paradrive.stages.ingest import check_uri

    for uri in uris:
        check_uri(uri, ingest)   # a value no ingest takes is the fix to make first, file there or not
    if ingest is not None:
        distinct_scenes([SceneInput(uri, uri) for uri in uris if uri.startswith("synthetic:")],
                        ingest)
    missing = missing_inputs(uris)
    if not missing:
        return
    names = ", ".join(missing[:shown]) + (f" and {len(missing) - shown} more" if len(missing) > shown
                                          else "")
    raise ConfigError(f"{len(missing)} of {len(uris)} scene input(s) do not exist: {names}; fix "
                      f"their paths or leave them out, then re-run")


def _what(uri: SceneURI, ingest: Mapping[str, Any] | None = None,
          first: SceneURI | None = None) -> str:
    """What makes two inputs one log, for the error naming them."""
    if uri.kind == "synthetic" and first is not None and first.scene_id != uri.scene_id:
        from paradrive.ingest.synthetic import describe_street, street_identity

        return (f"one synthetic street, {describe_street(street_identity(uri, ingest))}: its name "
                f"and how its numbers are written do not change its images")
    if uri.kind in _NAMED_LOGS:
        return f"scene {uri.scene_id}"
    return os.path.realpath(os.path.expanduser(uri.path))


def _renamed(scene_id: str, key: str, given: SceneInput,
             logs: list[tuple[str, SceneInput]]) -> str:
    uri = parse_uri(given.uri)
    if uri.kind == "waymo" and uri.scene and Path(uri.path).expanduser().is_dir():
        others = ", ".join(g.describe() for _, g in logs if g is not given)
        raise ConfigError(f"{given.describe()} and {others} are different logs that give one "
                          f"scene id {scene_id}; name the segment files themselves "
                          f"(waymo:<folder>/<file>.tfrecord) or build them apart")
    return with_name(given.uri, f"{scene_name(uri)}-{short_hash(key)}")


def _inside(path: Path, folder: Path, what: str) -> None:
    """Refuse ``path`` when it resolves (links followed) outside ``folder``."""
    resolved = path.resolve()
    if not resolved.is_relative_to(folder.resolve()):
        raise ConfigError(f"{what} resolves to {resolved}, outside {folder}; move it there, or "
                          f"name it by a scene URI (waymo:/…, drivestudio:/…)")


def _expand(item: str, base: Path, depth: int, within: Path | None, where: str) -> list[SceneInput]:
    if not item:
        return []
    if is_uri(item):
        return [SceneInput(item, where)]
    path = Path(item).expanduser()
    if not path.is_absolute():
        path = base / path
    if within is not None:  # a line of a list file: the list's folder is what was given
        _inside(path, within, f"{item!r}")
    if path.is_dir():
        return [SceneInput(uri, where) for uri in scenes_in_folder(path)]
    if path.is_file():
        if path.suffix in _waymo_suffixes():
            return [SceneInput(make_uri("waymo", str(path.resolve())), where)]
        if depth > 4:
            raise ConfigError(f"{path}: scene lists nest more than 4 deep; is a list including itself?")
        return _read_list(path, depth)
    raise ConfigError(f"--scenes {item!r}: not a scene URI (kind one of {', '.join(KINDS)}), "
                      f"nor an existing list file or folder of logs")


def _list_text(path: Path) -> str:
    """A scene list's text: UTF-8, or the encoding its byte-order mark says (the mark dropped,
    as editors on Windows save one)."""
    data = path.read_bytes()
    encoding = next((name for bom, name in _BOMS if data.startswith(bom)), "utf-8")
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a text scene list (one URI or path per line, UTF-8; byte "
                          f"{exc.start} is not {encoding})") from exc


def _read_list(path: Path, depth: int) -> list[SceneInput]:
    text = _list_text(path)
    inputs: list[SceneInput] = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = _TRAILING_COMMENT.sub("", raw.lstrip("\ufeff")).strip()
        if not line or line.startswith("#"):
            continue
        try:
            inputs.extend(_expand(line, base=path.parent, depth=depth + 1, within=path.parent,
                                  where=f"{path}:{number}"))
        except ConfigError as exc:
            raise ConfigError(f"{path}:{number}: {exc}") from exc
    return inputs


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
        uris.extend(make_uri("nuscenes", str(root.resolve()), f"version={version_dir.name}", name)
                    for name in names)
    return uris


def scenes_in_folder(folder: Path) -> list[str]:
    """Scene URIs of a nuScenes dataroot, DriveStudio folder(s) or a folder of Waymo tfrecords."""
    folder = folder.resolve()
    if nuscenes_versions(folder):
        return nuscenes_scene_uris(folder)
    if is_drivestudio_scene(folder):
        return [make_uri("drivestudio", str(folder))]
    found = [p for p in sorted(folder.rglob("*"))
             if p.is_file() and p.suffix in _waymo_suffixes() and not p.name.startswith(".")]
    scenes = [p for p in sorted(folder.iterdir()) if p.is_dir() and is_drivestudio_scene(p)]
    for p in found + scenes:
        _inside(p, folder, f"{p}")
    uris = [make_uri("waymo", str(p)) for p in found] + [make_uri("drivestudio", str(p))
                                                         for p in scenes]
    if not uris:
        raise ConfigError(f"{folder}: no scenes found; expected *.tfrecord files (Waymo), a "
                          f"nuScenes dataroot (v1.0-*/scene.json) or DriveStudio processed "
                          f"folders (<scene>/images with ego_pose/ or extrinsics/)")
    return uris
