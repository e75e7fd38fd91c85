"""Every path of a scene folder and of a build folder, in one place.

A scene lives at ``<data>/scenes/<scene_id>/``::

    scene.json                                    the canonical scene (ingest)
    images/<camera>/<frame:06d>.<ext>             undistorted images
    lidar/<frame:06d>.npy                         world points (optional)
    masks/sky/<camera>/<frame:06d>.png            sky masks (optional)
    masks/dynamic/<camera>/<frame:06d>.png        moving actors' boxes (optional)
    masks/ego/<camera>.png                        what moves with the camera: a hood (video)
    masks/motion/<camera>/<frame:06d>.png         moving things seen in the image motion (video)
    gs/ckpt_<iteration:06d>.ply  gs/fit.json  gs/state.pt      the fit (background and sky)
    gs/actors/ckpt_<iteration:06d>/<actor>.ply    a scene-graph fit's actor nodes, box frame
    renders/renders.json  renders/<camera>/<stream>/<frame:06d>.png  (+ depth/, alpha/)
    clips/clips.json  clips/<camera>/<clip>/<stream>.<mp4|mkv>      the clips
    .paradrive/<stage>.json                       a completed stage's marker

and the data root also holds ``logs/<scene_id>.log`` and ``locks/<scene_id>.lock``. A build
lives at ``<manifests>/<build>/``: ``index.json`` naming its version folder ``v-<nnnnnn>/``
(``pairs-<nnnnn>.parquet``, ``media/``, ``index.json``: its own copy of the index), the earlier
versions a publish keeps for readers, ``ledger.sqlite``, ``.paradrive/build.json`` (the
builder's marker). No other module spells these names.
"""

from __future__ import annotations

import fnmatch
import re
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

    def ego_mask(self, camera: str) -> Path:
        return self.root / "masks" / "ego" / f"{camera}.png"

    def motion_mask(self, camera: str, frame: int) -> Path:
        return self.root / "masks" / "motion" / camera / f"{int(frame):06d}.png"

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
LEDGER = "ledger.sqlite"
VERSION_PREFIX = "v-"
BUILD_MARKER = f"{MARKER_DIR}/build.json"
# what the runner keeps in a build folder before anything is published (ledger, logs, markers)
RUNNER_FILES = (f"{LEDGER}*", "logs", MARKER_DIR)
_VERSION = re.compile(r"v-(\d{6})")


def checked_build_name(build: str) -> str:
    """A build name that is a plain folder name: ``..`` or ``a/b`` would lead out of --manifests."""
    if not isinstance(build, str) or safe_name(build) != build or build.startswith("."):
        raise ConfigError(f"build name {build!r} is not a plain folder name (letters, digits, "
                          f"'-', '_', '.', not starting with '.'); pick a name like 'default'")
    return build


def version_name(number: int) -> str:
    """The folder of a build's ``number``-th publication (``v-000003``)."""
    return f"{VERSION_PREFIX}{int(number):06d}"


def is_version(name: str) -> bool:
    return _VERSION.fullmatch(name) is not None


def version_number(name: str) -> int:
    match = _VERSION.fullmatch(name)
    if match is None:
        raise ValueError(f"{name!r} is not a version folder name")
    return int(match.group(1))


def is_runner_file(name: str) -> bool:
    """A top entry of a build folder that the runner, not the manifest stage, writes."""
    return any(fnmatch.fnmatchcase(name, pattern) for pattern in RUNNER_FILES)


@dataclass(frozen=True)
class BuildLayout:
    """The files of one build folder (``<manifests>/<build>``).

    ``index.json`` is the one pointer readers follow: it names the version folder
    (``v-<nnnnnn>/``) that holds the shards and ``media/`` it describes. A publication writes a
    new version folder and switches ``index.json`` to it by rename."""

    root: Path

    @classmethod
    def of(cls, manifests_dir: str | Path, build: str) -> BuildLayout:
        return cls(Path(manifests_dir) / checked_build_name(build))

    @property
    def index_json(self) -> Path:
        return self.root / INDEX_JSON

    @property
    def marker(self) -> Path:
        """Written when the builder creates the folder; without it nothing here is replaced."""
        return self.root / BUILD_MARKER

    @property
    def publish_lock(self) -> Path:
        """Held (``flock``) by the one run publishing the build (:func:`paradrive.manifest.publishing`)."""
        return self.root / MARKER_DIR / "publish.lock"

    def version(self, name: str) -> Path:
        """A version folder; ``name`` must be one :func:`version_name` makes."""
        if not is_version(name):
            raise ConfigError(f"{self.index_json}: version {name!r} is not a version folder "
                              f"name (v-<6 digits>); re-run the manifest stage")
        return self.root / name

    def version_index(self, name: str) -> Path:
        """The copy of ``index.json`` a version folder keeps: what it held when it was
        published, so a reader can open that version by name while it is kept."""
        return self.version(name) / INDEX_JSON

    def versions(self) -> list[str]:
        """The version folders present, oldest first."""
        if not self.root.is_dir():
            return []
        return sorted((p.name for p in self.root.iterdir() if is_version(p.name)),
                      key=version_number)

    @property
    def ledger(self) -> Path:
        return self.root / LEDGER

    @staticmethod
    def media_uri(scene_id: str, file: str) -> str:
        """Version-relative URI of a scene file (``clips/...`` relative to the scene folder)."""
        return f"{MEDIA_DIR}/{scene_id}/{file}"
