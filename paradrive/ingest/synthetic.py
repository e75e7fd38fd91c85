"""``synthetic:<name>?seed=…&frames=…`` scenes: render the procedural street into a canonical scene."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from paradrive.actors import first_frames
from paradrive.errors import ConfigError, SceneError
from paradrive.ingest import requested_cameras, select_cameras
from paradrive.ingest.common import image_written
from paradrive.scene import Frame, FrameCamera, Scene, write_image
from paradrive.synthetic.limits import LIMITS
from paradrive.uri import SceneURI

if TYPE_CHECKING:
    from paradrive.contracts.params import IngestParams

# URI query keys and their types; the stage's synthetic_* params are the defaults of frames,
# width, height and curvature, ingest.cameras of cameras, the street's own of the others.
QUERY_KEYS = {"seed": int, "frames": int, "width": int, "height": int, "curvature": float,
              "speed": float, "cameras": str, "traffic": int}
# the street's argument each key sets, where its name is another
ARGUMENTS = {"speed": "speed_mps"}
# the ingest parameter that is a key's default
PARAMS = {"frames": "synthetic_frames", "width": "synthetic_width", "height": "synthetic_height",
          "curvature": "synthetic_curvature"}


def _range(key: str) -> str:
    """A key's values, for messages."""
    if key == "cameras":
        from paradrive.synthetic.street import CAMERA_NAMES

        return f"any of {', '.join(CAMERA_NAMES)}, comma-separated"
    if key == "traffic":
        return "0 or 1"
    return LIMITS[ARGUMENTS.get(key, key)].text


def accepted_keys() -> str:
    """Every key with its values, for messages."""
    return "; ".join(f"{key} {_range(key)}" for key in QUERY_KEYS)


def _usage(uri: SceneURI, what: str) -> ConfigError:
    return ConfigError(f"synthetic URI {uri.text!r}: {what}; accepted keys: {accepted_keys()}")


def _typed(uri: SceneURI, key: str, value: str) -> Any:
    """One key's value, typed and checked against its range (a ConfigError naming the URI, the
    key, the value as given and the range). Numbers count by value: ``01`` is ``1``, ``1e3`` is
    ``1000``."""
    from paradrive.synthetic.street import camera_names

    if key == "cameras":
        try:
            return tuple(sorted(set(camera_names(value))))
        except ValueError:
            raise _usage(uri, f"cameras={value} is not {_range(key)}") from None
    try:
        number = float(value)
    except ValueError:
        raise _usage(uri, f"{key}={value} is not a number") from None
    whole = QUERY_KEYS[key] is int
    if whole and math.isfinite(number) and not number.is_integer():
        raise _usage(uri, f"{key}={value} is not a whole number")
    if key == "traffic":
        if number not in (0.0, 1.0):
            raise _usage(uri, f"traffic={value} is not {_range(key)}")
        return bool(number)
    if not LIMITS[ARGUMENTS.get(key, key)].admits(number):
        raise _usage(uri, f"{key}={value} is outside {_range(key)}")
    return int(number) if whole else number


def query_values(uri: SceneURI) -> dict[str, Any]:
    """The URI's street keys, typed and checked (ConfigError, a usage error: exit 2 before any
    work); keys the street does not take are left to the reader, which refuses them."""
    return {key: _typed(uri, key, value) for key, value in uri.query.items() if key in QUERY_KEYS}


def check(uri: SceneURI, ingest: Mapping[str, Any] | None = None) -> None:
    """Refuse, before any work, a ``synthetic:`` URI whose values no street takes (ConfigError,
    a usage error: exit 2): a value out of its range, NaN or infinite; with ``ingest`` (the
    build's ingest parameters) a default of theirs out of range too; and where the frames are
    known, a drive too long or turning too far."""
    from paradrive.synthetic.street import defaults, drive

    values = query_values(uri)
    given = ingest or {}
    for key, param in PARAMS.items():
        if key not in values and given.get(param) is not None:
            try:
                values[key] = _typed(uri, key, str(given[param]))
            except ConfigError:
                raise ConfigError(f"synthetic URI {uri.text!r}: its {key} is ingest.{param}="
                                  f"{given[param]}, outside {_range(key)}; set ingest.{param} "
                                  f"within it or give {key}= in the URI") from None
    if "frames" not in values:
        return   # the reader checks the drive, with the frames it is given
    try:
        drive(values["frames"], values.get("speed", defaults_by_key()["speed"]),
              float(defaults()["fps"]), values.get("curvature", 0.0))
    except ValueError as exc:
        raise _usage(uri, str(exc).removeprefix("synthetic street: ")) from None


def _camera_default(ingest: Mapping[str, Any]) -> tuple[str, ...] | None:
    """The cameras ``ingest.cameras`` gives a street (None where they cannot be told)."""
    from types import SimpleNamespace

    from paradrive.synthetic.street import CAMERA_NAMES

    if "cameras" not in ingest:
        return None
    asked = SimpleNamespace(cameras=ingest["cameras"], camera_sets=ingest.get("camera_sets") or {})
    try:
        wanted = requested_cameras(asked, "synthetic", scene_id="")  # type: ignore[arg-type]
    except SceneError:
        return None
    return tuple(sorted(set(CAMERA_NAMES if wanted is None else wanted)))


# a key a URI leaves out whose default is not known where an identity is made
_UNSET = "(the build's)"


def street_identity(uri: SceneURI, ingest: Mapping[str, Any] | None = None) -> tuple:
    """What makes the street a URI names, whatever its name and however its numbers are
    written: every key's value (``seed=01`` is ``seed=1``), the street's own defaults where the
    URI gives none, ``ingest``'s (the build's ingest parameters) for frames, width, height,
    curvature and cameras; where those are not given, a key left out stays apart from any value
    given. Keys the street does not take count as written. Two URIs with one identity make
    byte-identical images."""
    values = query_values(uri)
    own = defaults_by_key()
    ingest = ingest or {}
    cameras = _camera_default(ingest)
    out: list[tuple[str, Any]] = []
    for key in QUERY_KEYS:
        if key in values:
            value: Any = values[key]
        elif key in own:
            value = own[key]
        elif key == "cameras" and cameras is not None:
            value = cameras
        elif PARAMS.get(key) in ingest:
            value = _default(uri, key, ingest[PARAMS[key]])
        else:
            value = _UNSET
        out.append((key, value))
    if dict(out)["speed"] == 0.0:   # a street whose ego stands has no traffic, asked for or not
        out = [(k, False if k == "traffic" else v) for k, v in out]
    unknown = sorted((k, v) for k, v in uri.query.items() if k not in QUERY_KEYS)
    return tuple(out) + (("others", tuple(unknown)),)


def _default(uri: SceneURI, key: str, value: Any) -> Any:
    """An ingest parameter's value as the key's (as it stands where it is no such value: the
    check refuses it)."""
    try:
        return _typed(uri, key, str(value))
    except ConfigError:
        return value


def defaults_by_key() -> dict[str, Any]:
    """The street's own defaults of the keys the ingest parameters do not set: seed, speed and
    traffic (read from SyntheticStreet's signature)."""
    from paradrive.synthetic.street import defaults

    own = defaults()
    return {"seed": int(own["seed"]), "speed": float(own["speed_mps"]),
            "traffic": bool(own["traffic"])}


def describe_street(identity: tuple) -> str:
    """An identity in words: ``seed=1, speed=8, traffic=1, frames, … as the build sets them``."""
    values = dict(identity)
    known = [f"{k}={','.join(v) if isinstance(v, tuple) else _plain(v)}"
             for k, v in identity if k != "others" and v != _UNSET]
    known += [f"{k}={v}" for k, v in values["others"]]
    unset = [k for k, v in identity if v == _UNSET]
    return ", ".join(known) + (f", {', '.join(unset)} as the build sets them" if unset else "")


def _plain(value: Any) -> str:
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def street_from_uri(uri: SceneURI, params: IngestParams):
    """The SyntheticStreet a URI names, with the ingest parameters as defaults."""
    from paradrive.synthetic import SyntheticStreet
    from paradrive.synthetic.street import CAMERA_NAMES

    unknown = [key for key in uri.query if key not in QUERY_KEYS]
    if unknown:
        raise SceneError(f"unknown synthetic option {unknown[0]!r} in {uri.text!r}",
                         scene_id=uri.scene_id, fix=f"use one of {', '.join(QUERY_KEYS)}")
    try:
        query = query_values(uri)
    except ConfigError as exc:
        raise SceneError(str(exc), scene_id=uri.scene_id, fix="fix the scene URI") from exc
    kwargs = dict(
        name=uri.path, seed=query.get("seed", defaults_by_key()["seed"]),
        frames=query.get("frames", params.synthetic_frames),
        width=query.get("width", params.synthetic_width),
        height=query.get("height", params.synthetic_height),
        curvature=query.get("curvature", params.synthetic_curvature),
        lidar=params.lidar,
    )
    if "speed" in query:
        kwargs["speed_mps"] = query["speed"]
    if "traffic" in query:  # traffic=0: parked cars only
        kwargs["traffic"] = query["traffic"]
    if "cameras" in query:  # the URI's rig wins, like its other keys
        kwargs["cameras"] = _as_written(uri.query["cameras"])
    else:
        kwargs["cameras"] = tuple(select_cameras(CAMERA_NAMES, params, "synthetic",
                                                 scene_id=uri.scene_id, where=uri.text))
    try:
        return SyntheticStreet(**kwargs)
    except ValueError as exc:
        raise SceneError(str(exc), scene_id=uri.scene_id, path=uri.text,
                         fix="fix the scene URI or the ingest.synthetic_* parameters") from exc


def _as_written(cameras: str) -> tuple[str, ...]:
    """The URI's cameras in its own order (the rig's order is the scene's)."""
    return tuple(c.strip() for c in cameras.split(",") if c.strip())


def read(uri: SceneURI, out_dir: Path, params: IngestParams, scene_id: str) -> Scene:
    street = street_from_uri(uri, params)
    cam_names = list(street.cameras)
    ext, quality = params.image_ext, params.jpeg_quality
    n = street.frames if params.max_frames is None else min(street.frames, params.max_frames)
    ego = street.ego2world()[:n]
    stamps = street.timestamps_us()[:n]
    cameras = {}
    frames = [Frame(index=i, timestamp_us=int(stamps[i]), ego2world=ego[i], cameras={})
              for i in range(n)]
    for name in cam_names:
        spec = cameras[name] = street.cameras[name]
        c2w = street.c2w(name)[:n]
        batch = 8
        for start in range(0, n, batch):
            views = street.render(c2w[start:start + batch], spec.K(), spec.width, spec.height,
                                  frames=np.arange(start, min(start + batch, n)))
            for j in range(len(views["rgb"])):
                i = start + j
                rel = f"images/{name}/{i:06d}.{ext}"
                write_image(out_dir / rel, views["rgb"][j], quality=quality)
                image_written()
                if params.sky_masks:
                    mask = (views["sky"][j].astype(np.uint8) * 255)
                    write_image(out_dir / "masks" / "sky" / name / f"{i:06d}.png", mask)
                frames[i].cameras[name] = FrameCamera(image=rel, c2w=c2w[i])
    if params.lidar:
        for i in range(n):
            pts = street.lidar_points(i).astype(np.float32)
            path = out_dir / "lidar" / f"{i:06d}.npy"
            path.parent.mkdir(parents=True, exist_ok=True)
            np.save(path, pts)
    return Scene(scene_id=scene_id, dataset="synthetic", source=uri.text, fps=float(street.fps),
                 cameras=cameras, frames=frames, actors=first_frames(street.actors(), n),
                 extra={"synthetic": {"name": street.name, "seed": street.seed,
                                      "frames": street.frames, "curvature": street.curvature}})
