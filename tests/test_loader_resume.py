"""PairLoader: a loop over a build with two DataLoader workers, killed for real mid-epoch, resumes
in a new process exactly after the samples it had received: none again, none lost."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap

import pytest

from paradrive.data import PairIterableDataset, PairLoader

OPTIONS = {"seed": 3, "batch_size": 2, "num_frames": 2, "frame_offset": 1, "output_size": (16, 24),
           "dtype": "uint8"}
EPOCH = 1
KILL_AFTER = 9   # batches received before the kill

# The loop a trainer runs: after each batch it writes what it has seen and the loader's state,
# together and atomically, then says how many batches it has received on stdout.
LOOP = textwrap.dedent("""
    import hashlib, json, os, sys
    from paradrive.data import PairIterableDataset, PairLoader

    build, options, saved, resume = sys.argv[1], json.loads(sys.argv[2]), sys.argv[3], sys.argv[4]
    options["output_size"] = tuple(options["output_size"])
    loader = PairLoader(PairIterableDataset(build, **options), num_workers=2)
    loader.dataset.set_epoch({epoch})
    if resume != "-":
        with open(resume) as f:
            loader.load_state_dict(json.load(f)["state"])
    seen = []
    for k, batch in enumerate(loader):
        for i, pair_id in enumerate(batch["pair_id"]):
            frames = batch["source"][i].numpy().tobytes() + batch["target"][i].numpy().tobytes()
            seen.append([pair_id, hashlib.sha256(frames).hexdigest()])
        with open(saved + ".tmp", "w") as f:
            json.dump({{"state": loader.state_dict(), "seen": seen}}, f)
        os.replace(saved + ".tmp", saved)
        print(k + 1, flush=True)
""").format(epoch=EPOCH)


def _loop(tmp_path, build, saved, resume="-"):
    script = tmp_path / "loop.py"
    script.write_text(LOOP)
    options = dict(OPTIONS, output_size=list(OPTIONS["output_size"]))
    return subprocess.Popen([sys.executable, str(script), str(build), json.dumps(options), str(saved), str(resume)],
                            stdout=subprocess.PIPE, text=True)


def _uninterrupted(build):
    """The epoch read whole in this process, without workers: (pair_id, frames' digest) in order."""
    loader = PairLoader(PairIterableDataset(build, **OPTIONS), num_workers=0)
    loader.dataset.set_epoch(EPOCH)
    out = []
    for batch in loader:
        for i, pair_id in enumerate(batch["pair_id"]):
            frames = batch["source"][i].numpy().tobytes() + batch["target"][i].numpy().tobytes()
            out.append([pair_id, hashlib.sha256(frames).hexdigest()])
    assert loader.state_dict()["samples_consumed"] == len(loader.dataset)
    return out


def test_a_loop_with_two_workers_killed_mid_epoch_resumes_exactly_after_what_it_received(smoke_build, tmp_path):
    build = smoke_build["build_dir"]
    saved = tmp_path / "saved.json"
    killed = _loop(tmp_path, build, saved)
    assert killed.stdout is not None
    for line in killed.stdout:                     # wait on the loop's own report of each batch
        if int(line) >= KILL_AFTER:
            break
    os.kill(killed.pid, signal.SIGKILL)
    killed.wait(timeout=600)
    killed.stdout.close()
    assert killed.returncode == -signal.SIGKILL
    before = json.loads(saved.read_text())
    consumed = before["state"]["samples_consumed"]
    assert consumed == len(before["seen"]) >= KILL_AFTER * OPTIONS["batch_size"]   # the loader counted them itself
    whole = _uninterrupted(build)
    assert consumed < len(whole), "the kill came after the epoch ended; lower KILL_AFTER"

    resumed_at = tmp_path / "resumed.json"
    resumed = _loop(tmp_path, build, resumed_at, resume=saved)
    out, _ = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, out
    after = json.loads(resumed_at.read_text())
    seen = before["seen"] + after["seen"]
    assert seen == whole                            # in order: nothing again, nothing lost
    assert len({pair_id for pair_id, _ in seen}) == len(whole) == len(PairIterableDataset(build, **OPTIONS))
    assert after["state"]["samples_consumed"] == len(whole)


def test_the_loader_refuses_a_batch_size_the_dataset_does_not_cut_by(smoke_build):
    ds = PairIterableDataset(smoke_build["build_dir"], **OPTIONS)
    with pytest.raises(ValueError, match="same batch_size"):
        PairLoader(ds, batch_size=3)
    with pytest.raises(ValueError, match="persistent_workers"):
        PairLoader(ds, num_workers=1, persistent_workers=True)


def test_a_new_epoch_starts_counting_at_zero(smoke_build):
    loader = PairLoader(PairIterableDataset(smoke_build["build_dir"], **OPTIONS), num_workers=0)
    batches = iter(loader)
    next(batches)
    next(batches)
    assert loader.state_dict()["samples_consumed"] == 2 * OPTIONS["batch_size"]
    loader.dataset.set_epoch(5)
    state = loader.state_dict()
    assert (state["epoch"], state["samples_consumed"]) == (5, 0)
