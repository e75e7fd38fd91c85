"""``paradrive convert``: a smoke build handed to ReCamMaster's trainer, to DiffSynth-Studio's and
to diffusers' pixel layout, each read back the way its reader reads it."""

from __future__ import annotations

import csv
import json
import os
import re
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from paradrive.data import PairDataset
from paradrive.train.convert import collate_pixels, read_pixel_pair, recammaster_matrix, recammaster_text


def convert(*args: str, code: int = 0) -> str:
    import typer
    from typer.testing import CliRunner

    from paradrive.commands.convert import register

    app = typer.Typer()   # the command as paradrive.cli registers it, without the others
    app.callback()(lambda: None)   # keeps "convert" a sub-command, as in paradrive
    register(app)
    result = CliRunner().invoke(app, ["convert", *args])
    assert result.exit_code == code, result.output
    return result.output


def wan_prompt(text: str) -> str:
    """What the Wan prompter of DiffSynth-Studio and ReCamMaster hands its tokenizer
    (clean='whitespace': whitespace runs to one space, stripped); a non-string fails there."""
    assert isinstance(text, str), f"the tokenizer gets {text!r}, not a string"
    return re.sub(r"\s+", " ", text).strip()


def parse_recammaster(text: str) -> np.ndarray:
    """What ReCamMaster's loader does with one stored matrix: parse the bracketed rows, transpose,
    reorder the columns, negate the y column, centimetres to metres."""
    rows = [[float(v) for v in row.replace("[", "").replace("]", "").split()]
            for row in text.strip().split("] [")]
    p = np.array(rows).T
    c2w = p[:, [1, 2, 0, 3]]
    c2w[:3, 1] *= -1.0
    c2w[:3, 3] /= 100.0
    return c2w


def test_a_matrix_survives_recammasters_parse():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = q, [12.5, -3.25, 101.125]
    text = recammaster_text(recammaster_matrix(c2w))
    assert text.count("[") == 4 and text.endswith("] ")
    np.testing.assert_allclose(parse_recammaster(text), c2w, atol=1e-12)


def recammaster_sample(base: Path, k: int, cond_idx: int, frames: int) -> dict:
    """What ReCamMaster's TensorDataset makes of metadata row ``k`` with condition camera
    ``cond_idx`` (it draws one of 1..10 other than the target's): the cached target found from
    metadata.csv, the condition's by the number in its path, both latents joined in time, and the
    camera of the target at frames range(frames)[::4] seen from the condition's first frame."""
    metadata = pd.read_csv(base / "metadata.csv")
    tgt = str(base / "train" / metadata["file_name"][k]) + ".tensors.pth"
    tgt_idx = int(re.search(r"cam(\d+)", tgt).group(1))
    data_tgt = torch.load(tgt, weights_only=True, map_location="cpu")
    data_cond = torch.load(re.sub(r"cam(\d+)", f"cam{cond_idx:02}", tgt), weights_only=True, map_location="cpu")
    cams = json.loads((Path(tgt).parents[1] / "cameras" / "camera_extrinsics.json").read_text())
    steps = list(range(frames))[::4]
    cond0 = parse_recammaster(cams["frame0"][f"cam{cond_idx:02d}"])
    target = [parse_recammaster(cams[f"frame{i}"][f"cam{tgt_idx:02d}"]) for i in steps]
    camera = np.stack([(np.linalg.inv(cond0) @ t)[:3, :] for t in target]).reshape(len(steps), 12)
    return {"latents": torch.cat((data_tgt["latents"], data_cond["latents"]), dim=1),
            "prompt_emb": data_tgt["prompt_emb"], "camera": camera, "target": data_tgt, "condition": data_cond}


def test_recammaster_layout_holds_videos_cameras_and_each_videos_latents_once(smoke_build, wan_folder, tmp_path):
    """Four pairs of one clip (one target, two sources): three encodes, linked into every pair,
    and what ReCamMaster's unmodified loader reads, whichever condition camera it draws."""
    from paradrive.wan.text import empty_prompt_embedding
    from paradrive.wan.vae import encode_video, load_vae

    build, out = smoke_build["build_dir"], tmp_path / "recam"
    text = convert("recammaster", str(build), str(out), "--vae", str(wan_folder), "--num-frames", "9",
                   "--limit", "4")
    assert "4 pairs" in text and "3 distinct videos' latents (3 encoded, 0 from the build's latent cache)" in text
    ds = PairDataset(build, dtype="uint8", pose_format="recammaster")
    metadata = pd.read_csv(out / "metadata.csv")            # as ReCamMaster's data_process reads it
    assert metadata["file_name"].to_list() == [f"{p}/videos/cam02.mp4" for p in ds.pair_ids[:4]]
    assert {wan_prompt(t) for t in metadata["text"].to_list()} == {""}   # the empty prompt, as a string
    assert all((out / "train" / f).is_file() for f in metadata["file_name"])
    assert len(list((out / "latents").iterdir())) == 3                   # one file a distinct video
    inodes = {p.stat().st_ino for p in (out / "train").rglob("*.tensors.pth")}
    assert len(inodes) == 3 and len(list((out / "train").rglob("*.tensors.pth"))) == 4 * 10

    i = 1
    pair = out / "train" / ds.pair_ids[i]
    sample, row = ds[i], ds.row(i)
    assert (pair / "videos" / "cam01.mp4").read_bytes() == _media(ds, row, "source").read_bytes()
    assert (pair / "videos" / "cam02.mp4").read_bytes() == _media(ds, row, "target").read_bytes()
    cams = json.loads((pair / "cameras" / "camera_extrinsics.json").read_text())
    frames = int(row["num_frames"])
    assert sorted(cams, key=lambda k: int(k[5:])) == [f"frame{k}" for k in range(frames)]
    np.testing.assert_allclose(np.stack([parse_recammaster(cams[f"frame{k}"]["cam02"]) for k in range(0, frames, 4)]),
                               row["target_c2w"][::4], atol=1e-9)

    pixels = PairDataset(build, dtype="uint8", num_frames=9, output_size=(480, 832), resize="crop")
    direct = encode_video(load_vae(wan_folder), (pixels[i]["target"].float() / 127.5 - 1).permute(1, 0, 2, 3)[None])[0]
    prompt = empty_prompt_embedding(wan_folder).to(torch.bfloat16).float()
    for cond_idx in (1, 3, 10):   # the source, whichever condition camera the loader draws
        got = recammaster_sample(out, i, cond_idx, frames)
        np.testing.assert_allclose(got["camera"], sample["camera"].numpy(), atol=1e-5)
        assert got["latents"].shape == (16, 2 * 3, 60, 104) and got["latents"].dtype == torch.bfloat16
        assert set(got["target"]) == {"latents", "prompt_emb", "image_emb"} and got["target"]["image_emb"] == {}
        torch.testing.assert_close(got["target"]["latents"].float(), direct, rtol=1e-2, atol=1e-2)
        assert torch.equal(got["condition"]["latents"],
                           torch.load(out / "train" / ds.pair_ids[2] / "videos" / "cam01.mp4.tensors.pth",
                                      weights_only=True)["latents"])          # pairs 1, 2: one source
        assert got["prompt_emb"]["context"].shape[0] == 1
        torch.testing.assert_close(got["prompt_emb"]["context"][0].float(), prompt)


def test_recammaster_refuses_sizes_and_frames_it_cannot_read_before_any_work(smoke_build, tmp_path):
    build = str(smoke_build["build_dir"])
    size = convert("recammaster", build, str(tmp_path / "a"), "--vae", "tiny", "--size", "96x160", code=2)
    assert "30x52 token grid" in size and "480x832" in size and len(size.strip().splitlines()) == 1
    frames = convert("recammaster", build, str(tmp_path / "b"), "--vae", "tiny", code=2)
    assert "clips of 9 frames, and ReCamMaster reads 81" in frames and "--num-frames 9" in frames
    odd = convert("recammaster", build, str(tmp_path / "c"), "--vae", "tiny", "--num-frames", "8", code=2)
    assert "is not 4k + 1" in odd
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_recammaster_takes_the_builds_latent_cache_when_it_fits(cached_480, tmp_path):
    """A cache at 480x832 serves every video: no VAE is loaded, none is encoded, and the export
    holds the cache's latents; a cache at another size is named and the VAE encodes instead."""
    from paradrive.latents import read_latents_index

    build = cached_480
    text = convert("recammaster", str(build), str(tmp_path / "recam"), "--num-frames", "9")
    assert "3 distinct videos' latents (0 encoded, 3 from the build's latent cache)" in text
    cache = PairDataset(build, latents=True, dtype="bfloat16")
    for i in range(len(cache)):
        for cam, role in (("cam02", "target"), ("cam01", "source"), ("cam07", "source")):
            got = torch.load(tmp_path / "recam" / "train" / cache.pair_ids[i] / "videos" / f"{cam}.mp4.tensors.pth",
                             weights_only=True)
            assert torch.equal(got["latents"], cache[i][f"{role}_latents"])
    # the first latent frame alone is the first frame's (Wan's VAE is causal in time)
    one = convert("recammaster", str(build), str(tmp_path / "one"), "--num-frames", "1")
    assert "0 encoded, 3 from" in one
    got = torch.load(tmp_path / "one" / "train" / cache.pair_ids[0] / "videos" / "cam02.mp4.tensors.pth",
                     weights_only=True)["latents"]
    assert torch.equal(got, cache[0]["target_latents"][:, :1])
    assert read_latents_index(build)["size"] == [480, 832]


def test_an_unreadable_cache_is_named_and_a_vae_is_asked_for(smoke_build, tmp_path):
    build = tmp_path / "build"
    shutil.copytree(smoke_build["build_dir"], build, symlinks=True)
    (build / "latents").mkdir()
    (build / "latents" / "index.json").write_text("{ not json")
    refused = convert("recammaster", str(build), str(tmp_path / "r"), "--num-frames", "9", code=2)
    assert "needs --vae" in refused and "latent cache cannot be read" in refused


def _media(ds: PairDataset, row: dict, role: str) -> Path:
    from paradrive.pairs import build_file

    return build_file(ds.build, row[f"{role}_uri"], role, ds.index)


def test_diffsynth_metadata_names_the_videos_an_empty_prompt_and_the_camera(smoke_build, tmp_path):
    build, out = smoke_build["build_dir"], tmp_path / "ds"
    convert("diffsynth", str(build), str(out))
    ds = PairDataset(build, dtype="uint8")
    # DiffSynth-Studio's reader: pandas, then one dict per row
    frame = pd.read_csv(out / "metadata.csv")
    read = [frame.iloc[i].to_dict() for i in range(len(frame))]
    assert {wan_prompt(r["prompt"]) for r in read} == {""}
    with open(out / "metadata.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    listed = json.loads((out / "metadata.json").read_text())
    assert len(rows) == len(listed) == len(ds) == len(read)
    assert list(rows[0]) == ["video", "prompt", "source_video", "condition_video", "offset_m", "camera"]
    for i, (r, j) in enumerate(zip(rows, listed)):
        row = ds.row(i)
        assert wan_prompt(j["prompt"]) == "" and read[i]["video"] == r["video"]
        for column, role in (("video", "target"), ("source_video", "source"), ("condition_video", "condition")):
            assert r[column] == j[column]
            assert (out / r[column]).read_bytes() == _media(ds, row, role).read_bytes()
        camera = np.array(json.loads(r["camera"]))
        assert camera.shape == (1 + (int(row["num_frames"]) - 1) // 4, 12)
        np.testing.assert_allclose(camera, row["rel_pose"][::4][: len(camera), :3, :].reshape(-1, 12), atol=1e-6)
        assert json.loads(r["camera"]) == j["camera"] and float(r["offset_m"]) == j["offset_m"]


def test_pixel_files_give_diffusers_video_batches(smoke_build, tmp_path):
    build, out = smoke_build["build_dir"], tmp_path / "px"
    convert("pixels", str(build), str(out), "--num-frames", "5", "--limit", "3")
    ds = PairDataset(build, dtype="uint8", num_frames=5)
    index = json.loads((out / "index.json").read_text())
    assert [p["pair_id"] for p in index["pairs"]] == ds.pair_ids[:3]
    samples = [read_pixel_pair(out / p["file"]) for p in index["pairs"][:2]]
    assert samples[0]["pair_id"] == ds.pair_ids[0] and samples[0]["offset_m"] == ds[0]["offset_m"]
    batch = collate_pixels(samples)
    frames, h, w = 5, *ds[0]["target"].shape[-2:]
    assert batch["target"].shape == (2, 3, frames, h, w) and batch["target"].dtype == torch.float32
    assert float(batch["target"].min()) >= -1 and float(batch["target"].max()) <= 1
    assert batch["camera"].shape == (2, 2, 12)
    # the same frames as the adapter's samples, collated the same way
    direct = collate_pixels([ds[0], ds[1]])
    assert torch.equal(direct["target"], batch["target"]) and torch.equal(direct["source"], batch["source"])


def test_recammaster_without_a_vae_is_refused_before_any_work(smoke_build, tmp_path):
    out = convert("recammaster", str(smoke_build["build_dir"]), str(tmp_path / "recam"), "--num-frames", "9", code=2)
    assert "needs --vae" in out and "cam01" in out and not (tmp_path / "recam").exists()


def test_the_vae_runs_on_the_device_asked_for(smoke_build, wan_folder, tmp_path):
    # no --text-encoder: the --vae folder holds umT5 too, as paradrive encode takes it
    out = convert("recammaster", str(smoke_build["build_dir"]), str(tmp_path / "recam"), "--vae", str(wan_folder),
                  "--limit", "1", "--device", "cpu", "--num-frames", "1")
    assert "1 pairs" in out
    bad = convert("recammaster", str(smoke_build["build_dir"]), str(tmp_path / "r2"), "--vae", str(wan_folder),
                  "--text-encoder", str(wan_folder), "--device", "tpu", "--num-frames", "9", code=2)
    assert "encode.device" in bad and not (tmp_path / "r2").exists()


@pytest.mark.parametrize("where", ["file", "under a file", "/dev/full", "a folder of other files"])
def test_an_output_that_cannot_be_a_folder_is_refused_in_one_line(where, smoke_build, tmp_path):
    (tmp_path / "file").write_text("keep me")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("keep me too")
    out = {"file": tmp_path / "file", "under a file": tmp_path / "file" / "out", "/dev/full": Path("/dev/full"),
           "a folder of other files": tmp_path / "other"}[where]
    text = convert("diffsynth", str(smoke_build["build_dir"]), str(out), code=2)
    assert text.startswith("error:") and len(text.strip().splitlines()) == 1 and "Traceback" not in text
    assert (tmp_path / "file").read_text() == "keep me"
    assert (tmp_path / "other" / "notes.txt").read_text() == "keep me too"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "other"]   # nothing else written


def test_an_export_that_runs_out_of_room_leaves_nothing_behind(smoke_build, tmp_path):
    """A real write failure: the process's file-size limit (EFBIG, as a full disk fails a write)."""
    out = tmp_path / "px"

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, resource.RLIM_INFINITY))

    # no bytecode writes under the limit: a cut-off .pyc would break later imports
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    result = subprocess.run([sys.executable, "-m", "paradrive.cli", "convert", "pixels", str(smoke_build["build_dir"]),
                             str(out), "--limit", "4"], preexec_fn=limit, env=env, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 1, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "could not write the export" in lines[0] and "file size limit" in lines[0], lines
    assert os.listdir(tmp_path) == []   # neither the export nor its temporary folder
    # an earlier export is replaced whole by a later one, never mixed with it
    convert("pixels", str(smoke_build["build_dir"]), str(out), "--num-frames", "1", "--limit", "2")
    convert("pixels", str(smoke_build["build_dir"]), str(out), "--num-frames", "1", "--limit", "1")
    assert len(list(out.glob("*.safetensors"))) + len(list(out.glob("*/**/*.safetensors"))) == 1


@pytest.fixture(scope="module")
def cached_480(smoke_scene, tmp_path_factory):
    """A build of two pairs of one clip (one target, two sources) with its latent cache at
    ReCamMaster's 480x832 (the paper's encode size), by the tiny VAE."""
    from conftest import SMOKE_SCENES

    from paradrive.pipeline import StageRegistry, run_build

    root = tmp_path_factory.mktemp("cached_480")
    shutil.copytree(smoke_scene["data_dir"], root / "data", symlinks=True)
    config = StageRegistry().resolve("smoke", {"render": {"clips": ["front"], "offsets_m": [1.0, -1.0],
                                                          "condition_checkpoints": [25]},
                                               "encode": {"size": [480, 832]}})
    report = run_build(config, list(SMOKE_SCENES[:1]), root / "data", manifests_dir=root / "manifests", build="b")
    assert not report.failures(), [r.error for r in report.failures()]
    build = root / "manifests" / "b"
    from paradrive.wan.encode import EncodeSettings, encode_build

    encode_build(build, EncodeSettings(vae="tiny", text_encoder=None, device="cpu", dtype="bfloat16",
                                       compute_dtype="float32", batch=1, shard_pairs=72, num_frames=None,
                                       size=(480, 832), resize="crop"))
    return build
