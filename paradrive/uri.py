"""Scene URIs: ``<kind>:<path>[#<scene>][?key=value&…]`` and the scene ids derived from them.

A path or scene name holds any character a file name may, written as it is, except that ``?``
and ``#`` end the path: write them ``%3F`` and ``%23``. A ``%`` and two hex digits is the byte
they spell (``%25`` is ``%`` itself; several spell a UTF-8 character, ``%C3%A9`` is ``é``); any
other ``%`` stays as written. :func:`quote_name` writes a name so that it reads back as it is,
and every URI the builder makes from a file it found is written so."""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import parse_qsl, unquote

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
    The fragment may come before or after the query. Percent escapes in the path and the
    fragment are decoded (see the module doc); the query's values are decoded as a form's.
    """
    text = text.strip()
    kind, raw_path, tail = _split(text)
    query: dict[str, str] = {}
    scene = None
    for part in re.findall(r"[?#][^?#]*", tail):
        if part.startswith("?"):
            query.update(parse_qsl(part[1:], keep_blank_values=True))
        else:
            scene = unquote_name(part[1:]) or None
    if not raw_path:
        raise ConfigError(f"scene URI {text!r}: the path after '{kind}:' is empty")
    return SceneURI(kind=kind, path=unquote_name(raw_path), scene=scene, query=query, text=text)


def _split(text: str) -> tuple[str, str, str]:
    """``(kind, the path as written, the rest)`` of a scene URI: a path never holds a bare
    ``?`` or ``#`` (written ``%3F``, ``%23``)."""
    kind, sep, rest = text.partition(":")
    if not sep or kind not in KINDS:
        raise ConfigError(
            f"scene URI {text!r}: expected '<kind>:<path>' with kind one of {', '.join(KINDS)}, "
            f"e.g. 'synthetic:demo?seed=7'")
    m = re.match(r"^(?P<path>[^?#]*)(?P<tail>.*)$", rest)
    assert m is not None  # the pattern matches any string
    return kind, m.group("path"), m.group("tail")


def unquote_name(text: str) -> str:
    """A path or scene name as a URI writes it, decoded: ``%`` and two hex digits is that byte
    (bytes that are no UTF-8 come back as the file system's own surrogate escapes); any other
    ``%`` is kept."""
    return unquote(text, errors="surrogateescape")


def quote_name(name: str) -> str:
    """``name`` (a path or a scene name) as a URI writes it, so that :func:`parse_uri` reads it
    back unchanged: ``%``, ``#``, ``?``, characters that do not print (controls, a byte that is
    no UTF-8) and spaces at either end become percent escapes; everything else, spaces within
    and letters beyond ASCII included, stays as it is."""
    lead = len(name) - len(name.lstrip())
    end = len(name.rstrip())
    return "".join(_escaped(ch) if ch in "%#?" or not ch.isprintable() or i < lead or i >= end
                   else ch for i, ch in enumerate(name))


def _escaped(ch: str) -> str:
    return "".join(f"%{b:02X}" for b in ch.encode("utf-8", "surrogateescape"))


def make_uri(kind: str, path: str, query: str = "", scene: str | None = None) -> str:
    """The URI of a log found on disk: ``kind:<path>[?query][#scene]``, the path and the name
    written by :func:`quote_name` (``query`` as given, ``key=value&…``)."""
    return (f"{kind}:{quote_name(path)}" + (f"?{query}" if query else "")
            + (f"#{quote_name(scene)}" if scene else ""))


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
    kind, raw_path, tail = _split(text.strip())
    if not raw_path:
        parse_uri(text)  # the error of an empty path
    queries = "".join(part for part in re.findall(r"[?#][^?#]*", tail) if part.startswith("?"))
    return f"{kind}:{raw_path}{queries}#{quote_name(name)}"
