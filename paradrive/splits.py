"""Scene splits: named lists of logs (``splits/<name>.txt``) and the scenes of a build they select.

A split file holds one scene a line, ``#`` comments, a dataset prefix where the name alone is
ambiguous::

    waymo:segment-10444454289801298640_4360_000_4380_000_with_camera_labels.tfrecord
    nuscenes:022          # position in the dataroot's own `scene` table, counted from 0
    nuscenes:scene-0061   # or the scene's name

Matching is by log identity, never by path: a Waymo line matches the segment wherever its file
lives (``segment-`` prefix, ``_with_camera_labels`` and ``.tfrecord`` are optional), a nuScenes
index is resolved against the ``scene`` table of the dataroot and version the scene URI names.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from paradrive.errors import ConfigError
from paradrive.io import sha256_file
from paradrive.uri import SceneURI, parse_uri

NONE = "none"
_NUSCENES_INDEX = re.compile(r"^\d{1,4}$")
_NUSCENES_NAME = re.compile(r"^scene-\d+$")


def default_splits_dir() -> Path:
    """``$PARADRIVE_SPLITS`` or the ``splits/`` folder next to the package."""
    env = os.environ.get("PARADRIVE_SPLITS")
    if env:
        return Path(env)
    package = Path(__file__).resolve().parent
    checkout = package.parent / "splits"
    return checkout if checkout.is_dir() else package / "_splits"


def waymo_segment(name: str) -> str:
    """``segment-<id>_with_camera_labels.tfrecord`` -> ``<id>`` (what identifies a segment)."""
    name = Path(name).name
    name = re.sub(r"\.tfrecord$", "", name)
    name = re.sub(r"^segment-", "", name)
    return re.sub(r"_with_camera_labels$", "", name)


@dataclass(frozen=True)
class SplitLine:
    split: str
    file: Path
    number: int
    dataset: str      # waymo | nuscenes
    key: str          # waymo: segment id; nuscenes: 'index:<n>' or 'name:scene-NNNN'
    text: str

    @property
    def where(self) -> str:
        return f"{self.file}:{self.number} ({self.text!r})"


@dataclass
class Split:
    name: str
    file: Path
    sha256: str
    lines: list[SplitLine] = field(default_factory=list)

    def record(self) -> dict:
        return {"name": self.name, "file": self.file.name, "sha256": self.sha256,
                "scenes": len(self.lines)}


def _parse_line(split: str, file: Path, number: int, text: str) -> SplitLine:
    dataset, sep, name = text.partition(":")
    if not sep:  # no prefix: a Waymo file name or a nuScenes index / name tells itself
        name = text
        dataset = "nuscenes" if (_NUSCENES_INDEX.match(text) or _NUSCENES_NAME.match(text)) \
            else "waymo"
    name = name.strip()
    if dataset == "waymo" and name:
        return SplitLine(split, file, number, "waymo", waymo_segment(name), text)
    if dataset == "nuscenes" and _NUSCENES_INDEX.match(name):
        return SplitLine(split, file, number, "nuscenes", f"index:{int(name)}", text)
    if dataset == "nuscenes" and _NUSCENES_NAME.match(name):
        return SplitLine(split, file, number, "nuscenes", f"name:{name}", text)
    raise ConfigError(f"{file}:{number}: {text!r} is not a split line; write "
                      f"'waymo:segment-<id>…tfrecord', 'nuscenes:<index>' or 'nuscenes:scene-NNNN'")


def load_split(name: str, splits_dir: str | Path | None = None) -> Split:
    """The split ``name`` (``splits/<name>.txt``), or a split file given by its path."""
    folder = Path(splits_dir) if splits_dir else default_splits_dir()
    candidate = Path(name).expanduser()
    if candidate.suffix == ".txt" and candidate.is_file():
        file = candidate.resolve()
    else:
        file = folder / f"{name}.txt"
        if "/" in name or not file.is_file():
            known = sorted(p.stem for p in folder.glob("*.txt")) if folder.is_dir() else []
            raise ConfigError(f"unknown split {name!r}: no {file}; known splits: "
                              f"{', '.join(known) or 'none'} (or give a split file's path, "
                              f"or 'none')")
    split = Split(name=file.stem, file=file, sha256=sha256_file(file))
    seen: dict[tuple[str, str], SplitLine] = {}
    for number, raw in enumerate(file.read_text().splitlines(), 1):
        text = re.sub(r"\s+#.*$", "", raw).strip()
        if not text or text.startswith("#"):
            continue
        line = _parse_line(split.name, file, number, text)
        if (line.dataset, line.key) in seen:
            raise ConfigError(f"{line.where} repeats {seen[line.dataset, line.key].where}; "
                              f"remove one of them")
        seen[line.dataset, line.key] = line
        split.lines.append(line)
    return split


def load_splits(names: list[str], splits_dir: str | Path | None = None) -> list[Split]:
    """Splits by name; ``none`` (alone) means no split."""
    names = [n for n in names if n]
    if NONE in names:
        if len(names) > 1:
            raise ConfigError(f"split 'none' turns exclusion off; it cannot be combined with "
                              f"{', '.join(n for n in names if n != NONE)}")
        return []
    return [load_split(n, splits_dir) for n in dict.fromkeys(names)]


def _nuscenes_table(root: str, version: str, cache: dict) -> list[str]:
    key = (root, version)
    if key not in cache:
        table = Path(root) / version / "scene.json"
        try:
            cache[key] = [str(r["name"]) for r in json.loads(table.read_text())]
        except (OSError, json.JSONDecodeError, TypeError, KeyError) as exc:
            raise ConfigError(f"{table}: cannot read the nuScenes scene table to resolve split "
                              f"indices ({exc}); check the dataroot and version") from exc
    return cache[key]


def log_identity(uri: SceneURI, cache: dict) -> set[tuple[str, str]]:
    """The (dataset, key) pairs a split line may use to name this scene."""
    if uri.kind == "waymo":
        return {("waymo", waymo_segment(uri.scene or uri.path))}
    if uri.kind == "nuscenes" and uri.scene:
        names = {("nuscenes", f"name:{uri.scene}")}
        table = _nuscenes_table(uri.path, uri.query.get("version", "v1.0-trainval"), cache)
        if uri.scene in table:
            names.add(("nuscenes", f"index:{table.index(uri.scene)}"))
        return names
    return set()


@dataclass
class Selection:
    """The scenes a build keeps, what it left out and why."""

    uris: list[str]
    splits: list[Split] = field(default_factory=list)
    excluded: list[dict] = field(default_factory=list)

    def record(self) -> dict:
        """What ``index.json`` keeps: the split files (name + sha256) and the excluded scenes."""
        return {"exclude_splits": [s.record() for s in self.splits], "excluded_scenes": self.excluded}


def _matches(uris: list[str], splits: list[Split]) -> dict[str, list[SplitLine]]:
    """uri -> the split lines naming it; a log that two lines of one split name is an error."""
    cache: dict = {}
    found: dict[str, list[SplitLine]] = {}
    for uri in uris:
        ids = log_identity(parse_uri(uri), cache)
        lines = [ln for split in splits for ln in split.lines if (ln.dataset, ln.key) in ids]
        for split in splits:
            same = [ln for ln in lines if ln.split == split.name]
            if len(same) > 1:
                raise ConfigError(f"scene {uri} is named by two lines of split {split.name}: "
                                  f"{' and '.join(ln.where for ln in same)}; keep one")
        if lines:
            found[uri] = lines
    return found


def exclude(uris: list[str], names: list[str], splits_dir: str | Path | None = None) -> Selection:
    """``uris`` without the scenes the splits ``names`` list (a training build's exclusion)."""
    splits = load_splits(names, splits_dir)
    found = _matches(uris, splits)
    kept = [u for u in uris if u not in found]
    excluded = [{"scene_id": parse_uri(u).scene_id, "scene_uri": u, "split": found[u][0].split,
                 "line": found[u][0].text} for u in uris if u in found]
    return Selection(uris=kept, splits=splits, excluded=excluded)


def select(uris: list[str], name: str, splits_dir: str | Path | None = None) -> list[str]:
    """Exactly the scenes of split ``name`` among ``uris``; every line must match one log."""
    found = load_splits([name], splits_dir)
    split = found[0] if found else None
    if split is None:
        raise ConfigError("--split none selects nothing; name a split")
    matches = _matches(uris, [split])
    matched = {(ln.file, ln.number) for lines in matches.values() for ln in lines}
    missing = [ln for ln in split.lines if (ln.file, ln.number) not in matched]
    if missing:
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        raise ConfigError(f"split {split.name}: {len(missing)} line(s) match no log among the "
                          f"{len(uris)} scenes given: {', '.join(ln.where for ln in missing[:3])}"
                          f"{more}; pass the folder that holds them (--scenes)")
    return [u for u in uris if u in matches]


__all__ = ["Selection", "Split", "SplitLine", "default_splits_dir", "exclude", "load_split",
           "load_splits", "log_identity", "select", "waymo_segment"]
