"""The whole Wan loop with the tiny smoke models: build -> encode -> train stage 1 -> train stage 2
-> generate -> eval, through the commands, on the smoke profile and the smoke config with no
setting changed (`encode --vae tiny` is the smoke config's VAE); and the trainer's check of a
latent cache against its own settings (frames, size, VAE)."""

from __future__ import annotations

import json
import shutil

import pytest
from typer.testing import CliRunner

from paradrive.data import PairDataset
from paradrive.pairs import build_file, read_index
from paradrive.video import decode_frames

pytestmark = pytest.mark.slow


def run(*args: str, code: int = 0) -> str:
    from paradrive.cli import app

    result = CliRunner().invoke(app, list(args))
    assert result.exit_code == code, result.output
    return result.output


@pytest.fixture(scope="module")
def encoded(wan_builds, tmp_path_factory):
    """A copy of the smoke training build with its latent cache, as the smoke profile encodes it
    with the smoke config's tiny VAE (9 frames of 48 x 80)."""
    build = tmp_path_factory.mktemp("encoded") / "train"
    shutil.copytree(wan_builds["train"], build, symlinks=True)
    run("encode", str(build), "--profile", "smoke", "--vae", "tiny", "--device", "cpu")
    return build


def train(build, out, stage: int, *extra: str, vae=None, code: int = 0) -> str:
    """``train --model wan --config smoke``: its own tiny VAE and text stand-in unless ``vae``
    names a Wan folder (then its umT5 too)."""
    folders = ["--vae", str(vae), "--text-encoder", str(vae)] if vae is not None else []
    return run("train", "--build", str(build), "--model", "wan", "--config", "smoke", "--out", str(out),
               "--stage", str(stage), *folders, *extra, code=code)


def test_build_encode_train_both_stages_generate_and_eval(encoded, wan_builds, tmp_path):
    runs = tmp_path / "runs"
    assert "note:" not in train(encoded, runs, 1)          # the cache fits: read as it is
    train(encoded, runs, 2)
    videos = tmp_path / "videos"
    out = run("generate", "--build", str(wan_builds["infer"]), "--checkpoint", str(runs / "stage2"),
              "--out", str(videos))
    rows = PairDataset(wan_builds["infer"])
    assert f"{len(rows)} videos" in out and "(stage 2)" in out
    index = read_index(wan_builds["infer"])
    for i in (0, len(rows) - 1):
        row = rows.row(i)
        made = decode_frames(videos / f"{row['pair_id']}.mp4")
        truth = decode_frames(build_file(wan_builds["infer"], row["target_uri"], "target", index))
        assert made.shape == (len(truth), 48, 80, 3)                  # the clip's frames, at the model's size
        assert made.std() > 1.0                                        # a picture, not a flat frame
    run("eval", "--build", str(wan_builds["infer"]), "--videos", str(videos))
    scores = json.loads((videos / "scores.json").read_text())
    assert len(scores["rows"]) == len(rows) and not scores["missing"]


def test_a_latent_cache_of_another_shape_is_refused_in_one_line(encoded, tmp_path):
    out = train(encoded, tmp_path / "r", 1, "--set", "data.input=latents", "--set", "data.num_frames=1",
                "--set", "data.height=32", "--set", "data.width=48", code=2)
    assert "encoded at 9 frames, this run reads 1 (data.num_frames)" in out
    assert "encoded at 48x80, this run reads 32x48" in out and "paradrive encode" in out
    assert "Traceback" not in out and not (tmp_path / "r" / "stage1" / "last.pt").exists()


def test_a_cache_of_another_vae_is_named(encoded, wan_folder, tmp_path):
    import shutil

    from paradrive.wan.vae import make_tiny_vae

    make_tiny_vae(seed=1).save_pretrained(tmp_path / "other-vae")
    for part in ("text_encoder", "tokenizer"):   # a whole Wan2.1 folder whose VAE is another
        shutil.copytree(wan_folder / part, tmp_path / "other-vae" / part)
    out = train(encoded, tmp_path / "r", 1, "--set", "data.input=latents", vae=tmp_path / "other-vae", code=2)
    assert "encoded by the VAE in tiny" in out and f"model.vae {tmp_path / 'other-vae'} is another" in out


def test_auto_input_encodes_on_the_fly_when_the_cache_does_not_fit_and_says_so(encoded, wan_builds, tmp_path):
    out = train(encoded, tmp_path / "r", 1, "--steps", "1", "--set", "data.num_frames=1",
                "--set", "data.height=32", "--set", "data.width=48")
    assert "note:" in out and "encoding the videos on the fly instead (data.input=auto)" in out
    assert "stage 1: 1 steps" in out
    # a model of one-frame clips cannot make the inference set's 9-frame videos: refused before any
    refused = run("generate", "--build", str(wan_builds["infer"]), "--checkpoint", str(tmp_path / "r" / "stage1"),
                  "--out", str(tmp_path / "v"), code=2)
    assert "its clips have [9] frames, the model generates 1" in refused and not (tmp_path / "v").exists()


def test_generate_reports_a_row_it_cannot_read_and_makes_the_others(encoded, wan_builds, tmp_path):
    train(encoded, tmp_path / "runs", 1, "--steps", "1")
    infer = tmp_path / "infer"
    shutil.copytree(wan_builds["infer"], infer, symlinks=True)
    rows = PairDataset(infer)
    # the first row's condition render (the recording, its source, serves every offset of its clip)
    assert rows.row(0)["condition_uri"] not in {rows.row(i)["condition_uri"] for i in (1, 2)}
    broken = build_file(infer, rows.row(0)["condition_uri"], "condition", read_index(infer))
    broken.unlink()
    broken.write_bytes(b"not a video")
    out = run("generate", "--build", str(infer), "--checkpoint", str(tmp_path / "runs" / "stage1"),
              "--out", str(tmp_path / "v"), "--limit", "3", code=3)
    failed = [line for line in out.splitlines() if line.startswith("failed:")]
    assert len(failed) == 1 and rows.pair_ids[0] in failed[0]
    made = sorted(str(p.relative_to(tmp_path / "v")) for p in (tmp_path / "v").rglob("*.mp4"))
    assert made == sorted(f"{pid}.mp4" for pid in rows.pair_ids[1:3])


def test_an_unreadable_cache_is_named_and_auto_reads_the_videos(encoded, tmp_path):
    build = tmp_path / "train"
    shutil.copytree(encoded, build, symlinks=True)
    (build / "latents" / "index.json").write_text("{ not json")
    out = train(build, tmp_path / "r", 1, "--set", "data.input=latents", code=2)
    assert "its latent cache" in out and "cannot be read" in out and "is not valid JSON" in out
    auto = train(build, tmp_path / "a", 1, "--steps", "1")
    assert "cannot be read" in auto and "encoding the videos on the fly" in auto and "stage 1: 1 steps" in auto
