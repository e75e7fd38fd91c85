"""Scene URIs: ``<kind>:<path>[#<scene>][?key=value&…]`` and the scene ids derived from them."""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import parse_qsl

from paradrive.errors import ConfigError

KINDS = ("synthetic", "waymo", "nuscenes", "drivestudio", "video")


@dataclass(frozen=True)
class SceneURI:
    kind: str
    path: str
    scene: str | None = None
    query: dict[str, str] = field(default_factory=dict)
    text: str = ""

    @property
    def scene_id(self) -> str:
        return scene_id_for(self)


def parse_uri(text: str) -> SceneURI:
    """Split a scene URI into kind, path, fragment (scene name) and query parameters.

    ``synthetic:demo?seed=7&frames=160`` -> kind 'synthetic', path 'demo', query {seed, frames}.
    The fragment may come before or after the query.
    """
    text = text.strip()
    kind, sep, rest = text.partition(":")
    if not sep or kind not in KINDS:
        raise ConfigError(
            f"scene URI {text!r}: expected '<kind>:<path>' with kind one of {', '.join(KINDS)}, "
            f"e.g. 'synthetic:demo?seed=7'")
    query: dict[str, str] = {}
    scene = None
    # Query and fragment may appear in either order; paths never contain '?' or '#'.
    m = re.match(r"^(?P<path>[^?#]*)(?P<tail>.*)$", rest)
    assert m is not None  # the pattern matches any string
    path, tail = m.group("path"), m.group("tail")
    for part in re.findall(r"[?#][^?#]*", tail):
        if part.startswith("?"):
            query.update(parse_qsl(part[1:], keep_blank_values=True))
        else:
            scene = part[1:] or None
    if not path:
        raise ConfigError(f"scene URI {text!r}: the path after '{kind}:' is empty")
    return SceneURI(kind=kind, path=path, scene=scene, query=query, text=text)


def safe_name(text: str) -> str:
    """A file-name-safe token: letters, digits, '-', '_' and '.' only."""
    name = re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-.")
    return name or "scene"


def scene_id_for(uri: SceneURI) -> str:
    """The scene id: ``synthetic-demo-s7``, ``waymo-<segment>``, ``nuscenes-scene-0061``,
    ``drivestudio-023``, ``video-<file stem>``. A name with characters beyond ASCII keeps what
    a file name can hold of it and gains a short hash of the whole name (``video-東京.mp4`` ->
    ``video-<hash>``), so two such names never meet in one id."""
    return _named(uri.kind, scene_name(uri))


def scene_name(uri: SceneURI) -> str:
    """What names the scene in its id, before it is made file-safe: the fragment when there is
    one, else the file's stem (a Waymo segment without its ``segment-`` prefix and suffixes)."""
    if uri.kind == "synthetic":
        seed = uri.query.get("seed", "7")
        extra = "".join(f"-{k}{v}" for k, v in sorted(uri.query.items()) if k != "seed")
        return f"{uri.path}-s{seed}{extra}"
    if uri.kind == "waymo":
        stem = uri.scene or Path(uri.path).name
        stem = re.sub(r"\.tfrecord$", "", stem)
        stem = re.sub(r"^segment-", "", stem)
        return re.sub(r"_with_camera_labels$", "", stem)
    if uri.kind == "video":  # drive.mp4 -> video-drive; a folder of frames by its name
        return uri.scene or Path(uri.path).stem
    return uri.scene or Path(uri.path).name


def short_hash(text: str) -> str:
    """Eight hex digits of the sha256 of ``text``: what tells two scene names apart."""
    return hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()[:8]


def _named(kind: str, name: str) -> str:
    scene_id = safe_name(f"{kind}-{name}")
    return scene_id if name.isascii() else f"{scene_id}-{short_hash(name)}"


def with_name(text: str, name: str) -> str:
    """The scene URI ``text`` with its fragment (the scene's name) set to ``name``; its kind,
    path and query stay as written."""
    uri = parse_uri(text)
    _, _, rest = uri.text.partition(":")
    queries = "".join(part for part in re.findall(r"[?#][^?#]*", rest[len(uri.path):])
                      if part.startswith("?"))
    return f"{uri.kind}:{uri.path}{queries}#{name}"
