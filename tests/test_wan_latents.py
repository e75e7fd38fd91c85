"""Wan2.1 latents as a build output: the VAE's shape contract, the empty-prompt embedding, the
encode stage (resume, verification, when it runs) and the adapter's latent samples, with a tiny
random VAE and umT5 saved in Wan2.1's diffusers layout (nothing is downloaded)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("diffusers")
pytest.importorskip("transformers")

from paradrive.errors import ConfigError  # noqa: E402
from paradrive import latents as cache  # noqa: E402
from paradrive.wan.encode import EncodeSettings, encode_build  # noqa: E402
from paradrive.wan.text import empty_prompt_embedding  # noqa: E402
from paradrive.wan.vae import (decode_latents, encode_video, latent_frames, load_vae,  # noqa: E402
                               make_tiny_vae)

ROOT = Path(__file__).resolve().parents[1]
# the smoke clips (9 frames of 160x96) at a quarter of their size: all 9 encoded (4k + 1),
# 3 latent frames of 3x5; the killed encode takes the first frame alone
SETTINGS = dict(text_encoder=None, device="cpu", dtype="bfloat16", compute_dtype="float32", batch=4,
                shard_pairs=20, num_frames=None, size=(24, 40), resize="crop")
KILLED = dict(size=(24, 40), num_frames=1, shard_pairs=40, batch=8)
CLI_SETS = ["--set", "encode.size=[24,40]", "--set", "encode.num_frames=1", "--set", "encode.shard_pairs=40",
            "--set", "encode.batch=8", "--device", "cpu"]


@pytest.fixture(scope="module")
def encoded(smoke_build, wan_folder, tmp_path_factory) -> dict:
    """A copy of the smoke build, encoded."""
    import shutil

    build = tmp_path_factory.mktemp("encoded") / "smoke"
    shutil.copytree(smoke_build["build_dir"], build, symlinks=True)
    doc = encode_build(build, EncodeSettings(vae=str(wan_folder), **SETTINGS))
    return {"build": build, "doc": doc}


def _normalised_mean(vae, video: torch.Tensor) -> torch.Tensor:
    """The posterior mean straight from diffusers, normalised with the config's statistics."""
    mean = torch.tensor(vae.config.latents_mean).view(1, -1, 1, 1, 1)
    std = torch.tensor(vae.config.latents_std).view(1, -1, 1, 1, 1)
    with torch.no_grad():
        return (vae.encode(video).latent_dist.mean - mean) / std


def test_121_frames_give_31_latent_frames_at_an_eighth_of_the_size():
    vae = make_tiny_vae(seed=0)
    video = torch.rand(1, 3, 121, 8, 16, generator=torch.Generator().manual_seed(0)) * 2 - 1
    z = encode_video(vae, video)
    assert z.shape == (1, 16, 31, 1, 2) and z.dtype == torch.float32
    assert latent_frames(121) == 31 and latent_frames(5) == 2 and latent_frames(1) == 1
    assert torch.allclose(z, _normalised_mean(vae, video), atol=1e-6)
    back = decode_latents(vae, z[:, :, :2])
    assert back.shape == (1, 3, 5, 8, 16) and back.abs().max() <= 1.0


def test_the_same_seed_gives_the_same_vae_and_a_whole_wan_folder_loads(wan_folder, tmp_path):
    video = torch.rand(1, 3, 5, 16, 16, generator=torch.Generator().manual_seed(1)) * 2 - 1
    direct = encode_video(make_tiny_vae(seed=0), video)
    assert torch.equal(direct, encode_video(load_vae(wan_folder, "cpu"), video))
    assert torch.equal(direct, encode_video(load_vae(wan_folder / "vae", "cpu"), video))
    assert not torch.equal(direct, encode_video(make_tiny_vae(seed=1), video))
    with pytest.raises(ConfigError, match=f"{tmp_path}.*config.json"):
        load_vae(tmp_path, "cpu")


def test_the_empty_prompt_embedding_is_what_wan_hands_the_transformer(wan_folder):
    from transformers import AutoTokenizer, UMT5EncoderModel

    embedding = empty_prompt_embedding(wan_folder, "cpu")
    assert embedding.shape == (512, 32) and embedding.dtype == torch.float32
    tokenizer = AutoTokenizer.from_pretrained(wan_folder / "tokenizer")
    model = UMT5EncoderModel.from_pretrained(wan_folder / "text_encoder").eval()
    tokens = tokenizer([""], padding="max_length", max_length=512, return_tensors="pt")
    with torch.no_grad():
        hidden = model(tokens.input_ids, tokens.attention_mask).last_hidden_state[0]
    real = int(tokens.attention_mask.sum())
    assert real == 1   # the end-of-sequence token alone
    assert embedding[:real].abs().sum() > 0, "umT5('') is not zeros"
    assert torch.allclose(embedding[:real], hidden[:real], atol=1e-6)
    assert torch.count_nonzero(embedding[real:]) == 0


def test_adapter_latents_equal_a_direct_encode_of_the_same_frames(encoded, wan_folder):
    from paradrive.data import PairDataset

    doc = encoded["doc"]
    assert doc["num_frames"] == 9 and doc["latent_frames"] == latent_frames(9) == 3
    assert doc["latent_shape"] == [16, 3, 3, 5] and doc["dtype"] == "bfloat16"
    pixels = PairDataset(encoded["build"], num_frames=9, output_size=(24, 40), pose_format="recammaster")
    latent = PairDataset(encoded["build"], latents=True)
    vae = load_vae(wan_folder, "cpu")
    for i in (0, len(latent) - 1):
        sample, frames = latent[i], pixels[i]
        assert sample["pair_id"] == frames["pair_id"]
        for role in ("target", "source", "condition"):
            direct = _normalised_mean(vae, frames[role].permute(1, 0, 2, 3)[None])[0]
            got = sample[f"{role}_latents"]
            assert got.shape == (16, 3, 3, 5) and got.dtype == torch.float32
            # stored in bfloat16 (8 significant bits): within its rounding of the direct encode
            torch.testing.assert_close(got, direct, rtol=2 ** -8, atol=1e-5)
            assert torch.equal(got, got.to(torch.bfloat16).float())
        assert torch.allclose(sample["camera"], frames["camera"])
        assert torch.allclose(sample["rel_pose"], frames["rel_pose"][[0, 4, 8]])
        assert sample["text_embedding"].shape == (512, 32)
        assert sample["offset_m"] == frames["offset_m"]
    halves = PairDataset(encoded["build"], latents=True, dtype="bfloat16")[0]
    assert halves["target_latents"].dtype == torch.bfloat16


def test_bfloat16_latents_widen_to_float32_exactly_as_torch_converts_them():
    """The adapter widens stored latents in numpy (one thread, see paradrive.data): every
    bfloat16 pattern, NaNs and infinities included, gives torch's float32 bit for bit."""
    every = torch.arange(-2 ** 15, 2 ** 15, dtype=torch.int32, device="cpu").to(torch.int16).view(torch.bfloat16)
    widened = cache._widened(every.reshape(16, 64, 64), torch.float32).reshape(-1)
    assert widened.dtype == torch.float32
    assert torch.equal(widened.view(torch.int32), every.to(torch.float32).view(torch.int32))


def test_collated_latents_are_batches_of_videos(encoded):
    from paradrive.data import PairDataset

    ds = PairDataset(encoded["build"], latents=True)
    batch = cache.collate_latents([ds[0], ds[1], ds[2]])
    assert batch["target_latents"].shape == (3, 16, 3, 3, 5)
    assert batch["camera"].shape == (3, 3, 12) and batch["rel_pose"].shape == (3, 3, 4, 4)
    assert batch["text_embedding"].shape == (3, 512, 32)
    assert batch["pair_id"] == ds.pair_ids[:3] and batch["offset_m"].shape == (3,)


def test_distinct_videos_are_encoded_once_per_shard(encoded):
    from safetensors import safe_open

    from paradrive.pairs import read_pairs

    doc = encoded["doc"]
    rows = read_pairs(encoded["build"], ["target_sha256", "source_sha256", "condition_sha256"]).to_pydict()
    start = 0
    for entry in doc["shards"]:
        distinct = {sha for column in rows.values() for sha in column[start:start + entry["pairs"]]}
        with safe_open(str(encoded["build"] / "latents" / entry["file"]), framework="pt") as f:
            assert f.get_slice("latents").get_shape()[0] == entry["videos"] == len(distinct)
        start += entry["pairs"]
    assert doc["totals"]["videos"] < 3 * doc["totals"]["pairs"]


def _encode_command(build: Path, wan: Path) -> list[str]:
    return [sys.executable, "-m", "paradrive.cli", "encode", str(build), "--vae", str(wan), *CLI_SETS]


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_killed_encode_resumes_to_the_same_files(smoke_build, wan_folder, copy_tree):
    env = {k: v for k, v in os.environ.items() if k != "PARADRIVE_STOP_AT"}
    env.update(PYTHONPATH=str(ROOT), COLUMNS="500")
    whole = copy_tree(smoke_build["build_dir"], "whole")   # the same settings, never interrupted
    encode_build(whole, EncodeSettings(vae=str(wan_folder), **{**SETTINGS, **KILLED}))
    killed = copy_tree(smoke_build["build_dir"], "killed")
    proc = subprocess.Popen(_encode_command(killed, wan_folder), env={**env, "PARADRIVE_STOP_AT": "encode:shard-1"},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        _, status = os.waitpid(proc.pid, os.WUNTRACED)
        assert os.WIFSTOPPED(status), "the encode ended before its second shard"
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        with contextlib.suppress(ChildProcessError):
            proc.wait()
    assert not cache.has_latents(killed), "no index before every shard landed"
    assert len(list((killed / "latents" / "shards").iterdir())) == 2
    resumed = subprocess.run(_encode_command(killed, wan_folder), env=env, capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    a, b = _files(whole / "latents"), _files(killed / "latents")
    assert sorted(a) == sorted(b) and len(a) > 3
    for name in a:
        if name != "index.json":
            assert a[name] == b[name], name
    index_a, index_b = (json.loads(x["index.json"]) for x in (a, b))
    for doc in (index_a, index_b):
        doc.pop("created_at")
        doc["vae"].pop("path")
        doc["text"].pop("path")
        doc["settings"].pop("vae")
    assert index_a == index_b


def test_verify_catches_a_flipped_byte(encoded, copy_tree):
    from typer.testing import CliRunner

    from paradrive.cli import app

    build = copy_tree(encoded["build"], "smoke")
    assert cache.verify_latents(build)["problems"] == []
    shard = build / "latents" / encoded["doc"]["shards"][0]["file"]
    data = bytearray(shard.read_bytes())
    data[-3] ^= 0x01
    shard.write_bytes(bytes(data))
    problems = cache.verify_latents(build)["problems"]
    assert len(problems) == 1 and problems[0].startswith(f"corrupt: {shard}")
    result = CliRunner().invoke(app, ["inspect", str(build), "--verify"], env={"COLUMNS": "400"})
    assert result.exit_code == 1 and str(shard) in result.output


def test_latents_of_other_pairs_are_refused(encoded, copy_tree):
    from paradrive.data import PairDataset
    from paradrive.errors import ParaDriveError

    build = copy_tree(encoded["build"], "smoke")
    path = cache.latents_index_path(build)
    doc = json.loads(path.read_text())
    doc["pairs"]["shards_sha256"][0] = "0" * 64
    path.write_text(json.dumps(doc))
    with pytest.raises(ParaDriveError, match="encoded from other pairs"):
        PairDataset(build, latents=True)


def test_ranks_and_workers_split_latent_samples_and_resume(encoded):
    from torch.utils.data import DataLoader, DistributedSampler

    from paradrive.data import PairDataset, PairIterableDataset

    build = encoded["build"]
    n = len(PairDataset(build))
    seen = []
    for rank in range(2):
        ds = PairIterableDataset(build, latents=True, seed=3, rank=rank, world_size=2, batch_size=2,
                                 partition="drop")
        loader = DataLoader(ds, batch_size=2, num_workers=2, collate_fn=cache.collate_latents)
        ids = [pid for batch in loader for pid in batch["pair_id"]]
        assert ids == [ds.dataset.pair_ids[i] for i in ds.rank_order()]
        seen += ids
        resumed = PairIterableDataset(build, latents=True, seed=3, rank=rank, world_size=2, batch_size=2,
                                      partition="drop")
        resumed.load_state_dict(ds.state_dict(samples_consumed=4))
        again = [pid for batch in DataLoader(resumed, batch_size=2, num_workers=2,
                                             collate_fn=cache.collate_latents) for pid in batch["pair_id"]]
        assert again == ids[4:]
    assert len(seen) == len(set(seen)) == n - n % 2
    # map-style with a DistributedSampler per rank (accelerate's sharding of a map-style dataset)
    ds = PairDataset(build, latents=True)
    covered = [pid for rank in range(2)
               for batch in DataLoader(ds, batch_size=3, collate_fn=cache.collate_latents,
                                       sampler=DistributedSampler(ds, num_replicas=2, rank=rank, shuffle=True,
                                                                  drop_last=True))
               for pid in batch["pair_id"]]
    assert len(covered) == len(set(covered)) == n - n % 2


def test_the_encode_stage_runs_only_when_asked(smoke_build, wan_folder, copy_tree):
    from paradrive.pipeline import StageRegistry, run_build
    from paradrive.pipeline.build import split_stages

    config = StageRegistry().resolve("smoke")
    assert "encode" not in split_stages(config, None)[1]
    with pytest.raises(ConfigError, match="encode.vae"):
        config.check(["manifest", "encode"])
    asked = StageRegistry().resolve("smoke", {"encode": {"vae": str(wan_folder), "size": [8, 16],
                                                         "num_frames": 1, "batch": 8}})
    assert split_stages(asked, None)[1] == ["manifest", "encode"]
    root = copy_tree(smoke_build["root"], "root")
    runs = [run_build(asked, smoke_build["scene_uris"], root / "data", stages=["encode"],
                      manifests_dir=root / "manifests", build="smoke") for _ in range(2)]
    assert [[r.status for r in report.results] for report in runs] == [["done"], ["skipped"]]
    assert cache.read_latents_index(root / "manifests" / "smoke")["totals"]["pairs"] > 0


def test_a_republish_between_reading_the_index_and_the_rows_changes_nothing(
        smoke_build, wan_folder, copy_tree, monkeypatch):
    """The encode reads its rows from the version whose index it read: a publish that switches
    index.json in between (here to a version whose shards are not there yet) is not seen."""
    import paradrive.wan.encode as encode

    build = copy_tree(smoke_build["build_dir"], "republished")
    real = encode.read_index

    def read_then_republish(build_dir):
        index = real(build_dir)
        doc = json.loads((build / "index.json").read_text())
        (build / "index.json").write_text(json.dumps({**doc, "version": "v-000999"}))
        return index

    monkeypatch.setattr(encode, "read_index", read_then_republish)
    small = {**SETTINGS, "num_frames": 1, "size": (8, 16), "shard_pairs": 72, "batch": 8}
    doc = encode_build(build, EncodeSettings(vae=str(wan_folder), **small))
    assert doc["pairs"]["version"] == real(smoke_build["build_dir"]).version != "v-000999"


def test_encode_on_a_device_computes_what_it_computes_on_the_cpu(smoke_build, wan_folder, copy_tree):
    """On the stand-in device (tests/simulated_device.py) a CPU tensor meeting a device tensor
    fails as on CUDA; the encode (decode, VAE, text encoder) runs there and gives the CPU's latents."""
    from simulated_device import DEVICE, simulated_device

    from paradrive.data import PairDataset

    small = {**SETTINGS, "num_frames": 1, "size": (8, 16), "shard_pairs": 72, "batch": 8}
    cpu, dev = copy_tree(smoke_build["build_dir"], "cpu"), copy_tree(smoke_build["build_dir"], "dev")
    encode_build(cpu, EncodeSettings(vae=str(wan_folder), **small))
    with simulated_device():
        encode_build(dev, EncodeSettings(vae=str(wan_folder), **{**small, "device": str(DEVICE)}))
    a, b = PairDataset(cpu, latents=True), PairDataset(dev, latents=True)
    assert torch.equal(a[0]["text_embedding"], b[0]["text_embedding"])
    for i in range(len(a)):
        for role in ("target", "source", "condition"):
            torch.testing.assert_close(a[i][f"{role}_latents"], b[i][f"{role}_latents"], rtol=2 ** -7, atol=1e-5)


def test_on_ray_the_encode_stage_is_a_task_asking_for_its_gpu(smoke_build, wan_folder, copy_tree):
    """A Ray build hands the encode (the stage declares a GPU) to a task with that request, capped
    to the cluster: this one has no GPU, so the task runs on a worker's CPU, with the warning."""
    from paradrive.pipeline import StageRegistry, run_build
    from paradrive.pipeline.executors.ray import RayExecutor

    asked = StageRegistry().resolve("smoke", {"encode": {"vae": str(wan_folder), "size": [8, 16],
                                                         "num_frames": 1, "batch": 8}})
    root = copy_tree(smoke_build["root"], "root")
    executor = RayExecutor(num_cpus=2)
    report = run_build(asked, smoke_build["scene_uris"], root / "data", stages=["encode"],
                       manifests_dir=root / "manifests", build="smoke", executor=executor)
    [result] = report.results
    assert result.status == "done", result.error
    assert result.summary["worker"]["pid"] != os.getpid()     # a Ray worker, not the driver
    assert result.summary["worker"]["num_gpus"] == 0
    assert any("'encode' declares gpu: 1" in w for w in executor.warnings)
    assert cache.read_latents_index(root / "manifests" / "smoke")["totals"]["pairs"] > 0
