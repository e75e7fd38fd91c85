"""Scene inputs as users give them: a synthetic street's every value checked before any work and
its generation bounded; one street given twice refused, whatever its name or how its numbers are
written; file names with ``#``, ``?``, ``%``, spaces and letters beyond ASCII found from a folder
and named by a percent-encoded URI; a scene list saved with a byte-order mark; and a scene id too
long for the files named after it refused up front."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.errors import ConfigError
from paradrive.pipeline.scenes import SceneInput, check_present, distinct_scenes, expand_scene_inputs
from paradrive.stages.ingest import NAME_MAX, check_uri, scene_file_names
from paradrive.uri import make_uri, parse_uri, quote_name

REPO = Path(__file__).resolve().parents[1]
# a subprocess that has not finished by then has hung: the test fails
HUNG_S = 300
TINY = ["--profile", "smoke", "--set", "ingest.synthetic_frames=2", "--set", "ingest.synthetic_width=16",
        "--set", "ingest.synthetic_height=16"]
# every character a file name may hold that a URI must take care of
AWKWARD = "a#b ?c%d é東"


def _cli(*args: str) -> subprocess.CompletedProcess:
    """``paradrive <args>`` in a process of its own; one that runs past HUNG_S fails the test."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "400"}
    try:
        return subprocess.run([sys.executable, "-m", "paradrive.cli", *args], cwd=REPO, env=env,
                              capture_output=True, text=True, timeout=HUNG_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"paradrive {' '.join(args)} did not finish in {HUNG_S} s")


def _invoke(*args: str):
    return CliRunner().invoke(app, list(args), env={"COLUMNS": "400"})


def _one_line(output: str) -> str:
    line = output.strip()
    assert "\n" not in line, output
    return line


# --------------------------------------------------------------------------- A: values up front

@pytest.mark.parametrize("command", ["plan", "build"])
@pytest.mark.parametrize("query, shown, allowed", [
    ("seed=1&speed=inf", "speed=inf", "[0, 70] m/s"),
    ("seed=1&speed=1e6", "speed=1e6", "[0, 70] m/s"),
    ("speed=nan", "speed=nan", "[0, 70] m/s"),
])
def test_a_speed_no_street_takes_exits_2_naming_the_uri_value_and_range(tmp_path, command, query,
                                                                        shown, allowed):
    # in a process of its own: these once looped for ever (plan too), growing in memory
    uri = f"synthetic:x?{query}"
    args = [command, "--scene", uri, "--data", str(tmp_path / "data")]
    if command == "build":
        args += [*TINY, "--manifests", str(tmp_path / "m")]
    res = _cli(*args)
    assert res.returncode == 2, res.stdout + res.stderr
    line = _one_line(res.stdout + res.stderr)
    assert line.startswith(f"error: synthetic URI {uri!r}: {shown} is outside {allowed}; "), line
    assert "accepted keys: seed [0, 4294967295]; frames [1, 3000];" in line
    assert not (tmp_path / "data").exists() and not (tmp_path / "m").exists()   # before any work


@pytest.mark.parametrize("query, message", [
    ("seed=-1", "seed=-1 is outside [0, 4294967295]"),
    ("seed=4294967296", "seed=4294967296 is outside [0, 4294967295]"),
    ("seed=1.5", "seed=1.5 is not a whole number"),
    ("frames=0", "frames=0 is outside [1, 3000]"),
    ("frames=1e9", "frames=1e9 is outside [1, 3000]"),
    ("frames=many", "frames=many is not a number"),
    ("width=0", "width=0 is outside [1, 3840] px"),
    ("height=99999", "height=99999 is outside [1, 2160] px"),
    ("curvature=0.5", "curvature=0.5 is outside [-0.01, 0.01] 1/m"),
    ("curvature=-inf", "curvature=-inf is outside [-0.01, 0.01] 1/m"),
    ("speed=-1", "speed=-1 is outside [0, 70] m/s"),
    ("traffic=2", "traffic=2 is not 0 or 1"),
    ("cameras=rear", "cameras=rear is not any of front, front_left"),
    ("frames=3000&speed=70&curvature=0.01", "3000 frames at 70.0 m/s on curvature 0.01 turn more "
                                            "than 160 deg"),
])
def test_every_synthetic_value_is_checked_before_any_work(tmp_path, query, message):
    uri = f"synthetic:x?{query}"
    res = _invoke("plan", "--scene", uri, "--data", str(tmp_path / "data"))
    assert res.exit_code == 2, res.output
    assert _one_line(res.output).startswith(f"error: synthetic URI {uri!r}: {message}"), res.output
    with pytest.raises(ConfigError, match="accepted keys"):
        check_uri(uri)


def test_values_at_the_ends_of_their_ranges_are_taken(tmp_path):
    for uri in ("synthetic:x?seed=0&frames=1&width=1&height=1&curvature=-0.01&speed=0&traffic=0",
                "synthetic:x?seed=4294967295&frames=3000&width=3840&height=2160&curvature=0&speed=70"
                "&traffic=1&cameras=front,front_left,front_right,back_left,back_right,back"):
        check_uri(uri)
    # ingest's defaults are checked too where the check is given them
    with pytest.raises(ConfigError, match="its frames is ingest.synthetic_frames=5000, outside"):
        check_present(["synthetic:x?seed=1"], ingest={"synthetic_frames": 5000})


def test_the_street_is_generated_in_bounded_time_at_the_ends_of_every_range():
    """At the ends of every range the street is laid out and its poses and labelled tracks are
    computed (or refused): in a process of its own, with a limit that counts as a failure."""
    script = textwrap.dedent("""
        import json
        import numpy as np
        from paradrive.synthetic import SyntheticStreet, raycast, traffic
        from paradrive.synthetic.street import CAMERA_NAMES, build_layout

        out = {}
        def describe(name, **kw):
            try:
                s = SyntheticStreet(**kw)
            except ValueError as exc:
                out[name] = {"refused": str(exc)}
                return
            ego = s.ego2world()
            out[name] = {"frames": s.frames, "x_end": float(ego[-1, 0, 3]), "boxes": len(s.layout.boxes),
                         "actors": len(s.actors()), "stamps": int(s.timestamps_us()[-1]),
                         "cameras": sorted(s.cameras), "c2w": [len(s.c2w(c)) for c in s.cameras]}
        describe("longest", seed=2**32 - 1, frames=3000, speed_mps=70.0, width=3840, height=2160,
                 cameras=CAMERA_NAMES)
        describe("standing", seed=0, frames=3000, speed_mps=0.0, width=1, height=1)
        describe("least", seed=0, frames=1, speed_mps=0.0, width=1, height=1, traffic=False)
        describe("left", frames=1, speed_mps=70.0, curvature=0.01)
        describe("right", frames=300, speed_mps=0.5, curvature=-0.01)
        describe("too_far", frames=3000, speed_mps=70.0, curvature=0.01)
        s = SyntheticStreet(seed=0, frames=1, width=1, height=1)
        out["pixel"] = s.render_frame("front", 0)["rgb"].shape
        for name, call in (("layout_inf", lambda: build_layout(7, raycast.RoadArc(0.0), 0.0, np.inf)),
                           ("cars_inf", lambda: traffic.lane_cars(np.random.default_rng(0), 0.0, 1.0, 8.0,
                                                                  0.0, np.inf, None))):
            try:
                call()
                out[name] = "ran"
            except ValueError as exc:
                out[name] = str(exc)
        print(json.dumps(out))
    """)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    try:
        res = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True,
                             text=True, timeout=HUNG_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the street at the ends of its ranges was not generated in {HUNG_S} s")
    assert res.returncode == 0, res.stderr
    got = json.loads(res.stdout.strip().splitlines()[-1])
    longest = got["longest"]
    assert longest["frames"] == 3000 and longest["x_end"] == pytest.approx(70.0 * 2999 / 10)
    assert longest["boxes"] > 20_000 and longest["actors"] > 1000      # a 21 km street, all of it
    assert longest["stamps"] == 299_900_000 and longest["c2w"] == [3000] * 6
    assert got["standing"]["x_end"] == 0.0 and got["standing"]["actors"] > 0
    assert got["least"]["frames"] == 1 and got["pixel"] == [1, 1, 3]
    assert got["left"]["frames"] == 1 and got["right"]["frames"] == 300
    assert "turn more than 160 deg" in got["too_far"]["refused"]
    for name in ("layout_inf", "cars_inf"):
        assert got[name].startswith("synthetic street: cannot lay out objects from s="), got[name]


# --------------------------------------------------------------------------- B: one input, one id

def _refused(*uris: str, ingest=None) -> str:
    with pytest.raises(ConfigError) as err:
        distinct_scenes([SceneInput(u, "--scene") for u in uris], ingest)
    return str(err.value)


def test_one_street_given_twice_is_refused_whatever_its_name_or_numbers():
    message = _refused("synthetic:a?seed=1", "synthetic:a?seed=01")
    assert message.startswith("--scene (synthetic:a?seed=1) and --scene (synthetic:a?seed=01) are "
                              "the same log (one synthetic street, seed=1, speed=8, traffic=1, "), message
    assert message.endswith("its name and how its numbers are written do not change its images); "
                            "give it once")
    assert "(synthetic:zzz?seed=1)" in _refused("synthetic:a?seed=1", "synthetic:zzz?seed=1")
    _refused("synthetic:demo", "synthetic:demo?seed=7")                  # the street's own defaults
    _refused("synthetic:a?seed=1&speed=8.0&traffic=1", "synthetic:b?seed=1")
    _refused("synthetic:a?seed=1&frames=1e2", "synthetic:a?seed=1&frames=100")
    _refused("synthetic:a?cameras=front,front_left", "synthetic:b?cameras=front_left,front")
    _refused("synthetic:a?speed=0", "synthetic:a?speed=0&traffic=0")    # no traffic when it stands
    # different streets, and keys the street does not take, stay apart; ids stay as written
    uris = ["synthetic:a?seed=1", "synthetic:a?seed=2", "synthetic:a?seed=1&speed=9",
            "synthetic:a?seed=1&traffic=0", "synthetic:a?seed=1&fail=fit", "synthetic:a?seed=1&frames=24"]
    assert distinct_scenes([SceneInput(u, u) for u in uris]) == uris
    assert parse_uri("synthetic:a?seed=01").scene_id == "synthetic-a-s01"


def test_the_names_of_one_street_make_the_same_images():
    from paradrive.synthetic import SyntheticStreet

    a, b = (SyntheticStreet(name, seed=1, frames=2, width=32, height=24) for name in ("a", "zzz"))
    assert (a.render_frame("front", 1)["rgb"] == b.render_frame("front", 1)["rgb"]).all()
    c, d = (SyntheticStreet(seed=1, frames=2, width=32, height=24, speed_mps=0.0, traffic=t)
            for t in (True, False))
    assert len(c.actors()) == len(d.actors()) and (c.layout.boxes == d.layout.boxes).all()
    assert (c.render_frame("front", 1)["rgb"] == d.render_frame("front", 1)["rgb"]).all()


def test_a_default_written_out_is_the_same_street_with_the_build_s_parameters():
    from paradrive.pipeline import StageRegistry

    smoke = StageRegistry().resolve("smoke").params["ingest"]
    assert smoke["synthetic_frames"] == 24
    pair = ["synthetic:a?seed=1", "synthetic:a?seed=1&frames=24"]
    with pytest.raises(ConfigError, match=r"^synthetic:a\?seed=1 and synthetic:a\?seed=1&frames=24 "
                                          r"are the same log \(one synthetic street, seed=1, frames=24"):
        check_present(pair, ingest=smoke)
    check_present(pair, ingest=StageRegistry().resolve(None).params["ingest"])   # 200 frames: two
    _refused("synthetic:a?seed=1&cameras=front,front_left,front_right", "synthetic:b?seed=1",
             ingest=smoke)


def test_a_build_of_one_street_under_two_names_exits_2_naming_both(tmp_path):
    res = _invoke("build", "--scene", "synthetic:a?seed=1", "--scene", "synthetic:zzz?seed=01", *TINY,
                  "--data", str(tmp_path / "data"), "--manifests", str(tmp_path / "m"))
    assert res.exit_code == 2, res.output
    line = _one_line(res.output)
    assert line.startswith("error: --scene (synthetic:a?seed=1) and --scene (synthetic:zzz?seed=01) "
                           "are the same log (one synthetic street, seed=1,"), line
    assert not (tmp_path / "data").exists() and not (tmp_path / "m").exists()


# --------------------------------------------------------------------------- C: names as users have them

@pytest.fixture(scope="module")
def awkward_log(tmp_path_factory) -> Path:
    """A small real Waymo record whose file name holds #, ?, %, a space and letters beyond ASCII."""
    from paradrive.ingest import export
    from paradrive.synthetic import SyntheticStreet

    folder = tmp_path_factory.mktemp("logs") / "drives"
    folder.mkdir()
    street = SyntheticStreet("demo", seed=3, frames=2, width=48, height=32,
                             cameras=("front", "front_left", "front_right"))
    path = folder / f"{AWKWARD}.tfrecord"
    export.export_waymo(street, path, lidar=False)
    return path


def test_names_with_awkward_characters_read_back_as_the_same_file():
    for name in (f"/logs/{AWKWARD}.tfrecord", "/logs/50%off.tfrecord", "/logs/a%41.tfrecord",
                 " lead and trail ", "/logs/line\nbreak\udcff.tfrecord"):
        uri = make_uri("waymo", name)
        assert parse_uri(uri).path == name, uri
    assert quote_name(f"/logs/{AWKWARD}.tfrecord") == "/logs/a%23b %3Fc%25d é東.tfrecord"
    # a '%' that is no escape stays as written; one that is, is the byte it spells
    assert parse_uri("waymo:/logs/50%off.tfrecord").path == "/logs/50%off.tfrecord"
    assert parse_uri("waymo:/logs/a%2541.tfrecord#b%23c").path == "/logs/a%41.tfrecord"
    assert parse_uri("waymo:/logs/a%2541.tfrecord#b%23c").scene == "b#c"


def test_a_log_with_an_awkward_name_builds_from_its_folder(awkward_log, tmp_path):
    uris = expand_scene_inputs([str(awkward_log.parent)])
    assert uris == [f"waymo:{quote_name(str(awkward_log))}"]
    assert parse_uri(uris[0]).path == str(awkward_log)
    data = tmp_path / "data"
    res = _invoke("build", "--scenes", str(awkward_log.parent), "--stages", "ingest", "--profile",
                  "smoke", "--data", str(data), "--manifests", str(tmp_path / "m"))
    assert res.exit_code == 0, res.output
    scene_id = parse_uri(uris[0]).scene_id
    assert scene_id.startswith("waymo-a-b-c-d-") and (data / "scenes" / scene_id / "scene.json").is_file()
    scene = json.loads((data / "scenes" / scene_id / "scene.json").read_text())
    assert len(scene["frames"]) == 2 and scene["source"] == uris[0]


def test_a_log_with_an_awkward_name_is_found_by_its_percent_encoded_uri(awkward_log, tmp_path):
    encoded = f"waymo:{awkward_log.parent}/a%23b%20%3Fc%25d%20%C3%A9%E6%9D%B1.tfrecord"
    written = f"waymo:{awkward_log.parent}/a%23b %3Fc%25d é東.tfrecord"
    check_present([encoded, written])
    assert parse_uri(encoded).scene_id == parse_uri(written).scene_id
    res = _invoke("plan", "--scene", encoded, "--data", str(tmp_path / "data"))
    assert res.exit_code == 0, res.output
    # the folder's URI and the encoded one are one log
    res = _invoke("plan", "--scenes", str(awkward_log.parent), "--scene", encoded, "--data",
                  str(tmp_path / "data"))
    assert res.exit_code == 2 and "are the same log" in _one_line(res.output), res.output


def test_a_plain_percent_that_is_no_escape_names_the_file_as_written(tmp_path):
    log = tmp_path / "50%off.tfrecord"
    log.write_bytes(b"")
    check_present([f"waymo:{log}"])
    assert expand_scene_inputs([str(log)]) == [f"waymo:{tmp_path}/50%25off.tfrecord"]


@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16"])
def test_a_scene_list_saved_with_a_byte_order_mark_is_read_without_it(tmp_path, encoding):
    listing = tmp_path / "list.txt"
    listing.write_text("synthetic:a?seed=1\r\n# a comment\r\nsynthetic:b?seed=2\r\n", encoding=encoding)
    assert listing.read_bytes()[:2] in (b"\xef\xbb", b"\xff\xfe", b"\xfe\xff")
    assert expand_scene_inputs([str(listing)]) == ["synthetic:a?seed=1", "synthetic:b?seed=2"]
    res = _invoke("plan", "--scenes", str(listing), "--data", str(tmp_path / "data"))
    assert res.exit_code == 0, res.output


def test_the_longest_id_is_what_the_file_names_derived_from_it_allow():
    longest = max(len(n.encode()) for n in scene_file_names("x" * 100))
    limit = 100 - (longest - NAME_MAX)
    assert longest - 100 == 19 and limit == 236      # '.<id>.lock.tmp-<8 hex digits>'
    check_uri(f"synthetic:{'a' * (limit - len('synthetic--s7'))}?seed=7")
    with pytest.raises(ConfigError, match="is 237 characters"):
        check_uri(f"synthetic:{'a' * (limit + 1 - len('synthetic--s7'))}?seed=7")


def test_an_id_at_the_limit_builds_and_one_over_it_exits_2_before_any_work(tmp_path):
    name = "a" * (236 - len("synthetic--s7"))
    res = _invoke("build", "--scene", f"synthetic:{name}?seed=7", "--stages", "ingest", *TINY,
                  "--data", str(tmp_path / "ok"), "--manifests", str(tmp_path / "okm"))
    assert res.exit_code == 0, res.output
    assert (tmp_path / "ok" / "scenes" / f"synthetic-{name}-s7" / "scene.json").is_file()
    uri = f"synthetic:{name}a?seed=7"
    res = _invoke("build", "--scene", uri, *TINY, "--data", str(tmp_path / "data"), "--manifests",
                  str(tmp_path / "m"))
    assert res.exit_code == 2, res.output
    line = _one_line(res.output)
    assert line == (f"error: scene URI {uri!r}: its scene id synthetic-{name}a-s7 is 237 characters, "
                    f"and a file named after it (.<id>.lock.tmp-<random>) would be 256 bytes, over "
                    f"the 255-byte limit on a file name; shorten the id to at most 236 characters: "
                    f"give the street a shorter name (synthetic:<name>?...)")
    assert not (tmp_path / "data").exists() and not (tmp_path / "m").exists()


def test_a_log_named_too_long_for_its_id_is_refused_with_the_fix(tmp_path):
    log = tmp_path / f"{'7' * 240}.tfrecord"       # 249 bytes: the file system holds the log
    log.write_bytes(b"")
    res = _invoke("plan", "--scenes", str(tmp_path), "--data", str(tmp_path / "data"))
    assert res.exit_code == 2, res.output
    line = _one_line(res.output)
    assert line.startswith(f"error: scene URI 'waymo:{log}': its scene id waymo-{'7' * 240} is 246 "
                           f"characters"), line
    assert line.endswith("shorten the id to at most 236 characters: rename the file, or give the "
                         "scene a shorter name with '#<name>' at the end of the URI"), line
    short = _invoke("plan", "--scene", f"waymo:{log}#short", "--data", str(tmp_path / "data"))
    assert short.exit_code == 0, short.output
