"""Every path of a scene folder and of a build folder, in one place.

A scene lives at ``<data>/scenes/<scene_id>/``::

    scene.json                                    the canonical scene (ingest)
    images/<camera>/<frame:06d>.<ext>             undistorted images
    lidar/<frame:06d>.npy                         world points (optional)
    masks/sky/<camera>/<frame:06d>.png            sky masks (optional)
    masks/dynamic/<camera>/<frame:06d>.png        moving actors' boxes (optional)
    gs/ckpt_<iteration:06d>.ply  gs/fit.json  gs/state.pt      the fit (background and sky)
    gs/actors/ckpt_<iteration:06d>/<actor>.ply    a scene-graph fit's actor nodes, box frame
    renders/renders.json  renders/<camera>/<stream>/<frame:06d>.png  (+ depth/, alpha/)
    clips/clips.json  clips/<camera>/<clip>/<stream>.<mp4|mkv>      the clips
    .paradrive/<stage>.json                       a completed stage's marker

and the data root also holds ``logs/<scene_id>.log`` and ``locks/<scene_id>.lock``. A build
lives at ``<manifests>/<build>/``: ``index.json``, ``pairs-<nnnnn>.parquet``, ``media/``,
``ledger.sqlite``. No other module spells these names.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from paradrive.errors import ConfigError
from paradrive.uri import safe_name

MARKER_DIR = ".paradrive"
SCENES_DIR = "scenes"
LOGS_DIR = "logs"
LOCKS_DIR = "locks"
# a scene's top folders and the stage that writes each (a scene's footprint is counted by them)
SCENE_FOLDERS = {"images": "ingest", "lidar": "ingest", "masks": "ingest", "gs": "fit",
                 "renders": "render", "clips": "clip"}


def checked_scene_id(scene_id: str) -> str:
    """A scene id that is a plain file name; ``..`` or ``a/b`` could lead out of the data root."""
    if safe_name(scene_id) != scene_id:
        raise ConfigError(f"scene id {scene_id!r} is not a plain file name (letters, digits, "
                          f"'-', '_', '.'); scene ids come from scene URIs, never from paths")
    return scene_id


@dataclass(frozen=True)
class SceneLayout:
    """The files of one scene folder (``root``)."""

    root: Path

    @classmethod
    def of(cls, data_dir: str | Path, scene_id: str) -> SceneLayout:
        return cls(Path(data_dir) / SCENES_DIR / checked_scene_id(scene_id))

    @classmethod
    def at(cls, folder: SceneLayout | str | Path) -> SceneLayout:
        """The layout of a scene folder given as a layout or a path."""
        return folder if isinstance(folder, SceneLayout) else cls(Path(folder))

    @property
    def scene_id(self) -> str:
        return self.root.name

    # -- ingest
    @property
    def scene_json(self) -> Path:
        return self.root / "scene.json"

    def image(self, camera: str, frame: int, ext: str) -> Path:
        return self.root / "images" / camera / f"{int(frame):06d}.{ext}"

    def lidar(self, frame: int) -> Path:
        return self.lidar_dir / f"{int(frame):06d}.npy"

    @property
    def lidar_dir(self) -> Path:
        return self.root / "lidar"

    def sky_mask(self, camera: str, frame: int) -> Path:
        return self.root / "masks" / "sky" / camera / f"{int(frame):06d}.png"

    def dynamic_mask(self, camera: str, frame: int) -> Path:
        return self.root / "masks" / "dynamic" / camera / f"{int(frame):06d}.png"

    # -- fit
    @property
    def gs_dir(self) -> Path:
        return self.root / "gs"

    def checkpoint(self, iteration: int) -> Path:
        return self.gs_dir / f"ckpt_{int(iteration):06d}.ply"

    def actor_checkpoint(self, iteration: int, file: str) -> Path:
        """An actor node of a scene-graph checkpoint (``file`` from :func:`actor_files`)."""
        return self.gs_dir / "actors" / f"ckpt_{int(iteration):06d}" / file

    @property
    def fit_json(self) -> Path:
        return self.gs_dir / "fit.json"

    @property
    def fit_state(self) -> Path:
        return self.gs_dir / "state.pt"

    # -- render
    @property
    def renders_dir(self) -> Path:
        return self.root / "renders"

    @property
    def renders_json(self) -> Path:
        return self.renders_dir / RENDERS_JSON

    # -- clip
    @property
    def clips_dir(self) -> Path:
        return self.root / "clips"

    @property
    def clips_json(self) -> Path:
        return self.clips_dir / CLIPS_JSON

    # -- the runner
    def marker(self, stage: str) -> Path:
        return self.root / MARKER_DIR / f"{stage}.json"


RENDERS_JSON = "renders.json"
CLIPS_JSON = "clips.json"


def actor_files(actor_ids: list[str]) -> list[str]:
    """Checkpoint file names of actor nodes: the id made file-safe, numbered when two collide."""
    names: list[str] = []
    for k, actor_id in enumerate(actor_ids):
        name = safe_name(actor_id)
        names.append(f"{name}.ply" if f"{name}.ply" not in names else f"{name}-{k}.ply")
    return names


def stream_dir(camera: str, stream: str) -> str:
    """A stream's frame folder, relative to ``renders/``."""
    return f"{camera}/{stream}"


def frame_file(position: int, suffix: str = ".png") -> str:
    """A rendered frame's file name: its position in ``scene.json``'s frames."""
    return f"{int(position):06d}{suffix}"


def clip_file(camera: str, clip: str, stream: str, suffix: str) -> str:
    """A clip video, relative to the scene folder (``clips/<camera>/<clip>/<stream><suffix>``)."""
    return f"clips/{camera}/{clip}/{stream}{suffix}"


def clip_depth_dir(camera: str, clip: str, stream: str) -> str:
    """A clip's depth EXR sequence, relative to the scene folder."""
    return f"clips/{camera}/{clip}/depth/{stream}"


@dataclass(frozen=True)
class DataLayout:
    """The data root's own folders beside the scenes."""

    root: Path

    def scene(self, scene_id: str) -> SceneLayout:
        return SceneLayout.of(self.root, scene_id)

    def log(self, scene_id: str) -> Path:
        return self.root / LOGS_DIR / f"{scene_id}.log"

    def lock(self, scene_id: str) -> Path:
        return self.root / LOCKS_DIR / f"{scene_id}.lock"


INDEX_JSON = "index.json"
MEDIA_DIR = "media"
SHARD_PATTERN = "pairs-{:05d}.parquet"
SHARD_GLOB = "pairs-*.parquet"
LEDGER = "ledger.sqlite"


@dataclass(frozen=True)
class BuildLayout:
    """The files of one build folder (``<manifests>/<build>``)."""

    root: Path

    @property
    def index_json(self) -> Path:
        return self.root / INDEX_JSON

    def shard(self, number: int) -> Path:
        return self.root / SHARD_PATTERN.format(int(number))

    @property
    def media_dir(self) -> Path:
        return self.root / MEDIA_DIR

    @property
    def ledger(self) -> Path:
        return self.root / LEDGER

    @staticmethod
    def media_uri(scene_id: str, file: str) -> str:
        """Build-relative URI of a scene file (``clips/...`` relative to the scene folder)."""
        return f"{MEDIA_DIR}/{scene_id}/{file}"
