"""Scene URIs: ``<kind>:<path>[#<scene>][?key=value&…]`` and the scene ids derived from them."""

from __future__ import annotations

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
    ``drivestudio-023``, ``video-<file stem>``."""
    if uri.kind == "synthetic":
        seed = uri.query.get("seed", "7")
        extra = "".join(f"-{k}{v}" for k, v in sorted(uri.query.items()) if k != "seed")
        return safe_name(f"synthetic-{uri.path}-s{seed}{extra}")
    if uri.kind == "waymo":
        stem = Path(uri.path).name
        if uri.scene:
            stem = uri.scene
        stem = re.sub(r"\.tfrecord$", "", stem)
        stem = re.sub(r"^segment-", "", stem)
        stem = re.sub(r"_with_camera_labels$", "", stem)
        return safe_name(f"waymo-{stem}")
    if uri.kind == "video":  # drive.mp4 -> video-drive; a folder of frames by its name
        return safe_name(f"video-{uri.scene or Path(uri.path).stem}")
    if uri.kind == "nuscenes":
        return safe_name(f"nuscenes-{uri.scene or Path(uri.path).name}")
    return safe_name(f"{uri.kind}-{uri.scene or Path(uri.path).name}")
