"""``paradrive train --model wan`` on several processes (data parallel, gloo on CPUs): real
processes started as torchrun starts them, each reading its share of the adapter's epoch order;
the averaged losses are one process's on the same global batch, and a killed two-process run
resumes to the same weights."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from paradrive.data import PairIterableDataset
from paradrive.train.distributed import World
from paradrive.train.wan import WanTrainer, load_wan_config, open_wan_dataset

pytestmark = pytest.mark.slow

STEPS = 4
COMMON = ["--model", "wan", "--config", "smoke", "--steps", str(STEPS), "--set", "train.save_every=2"]


def train_args(build, out, per_process_batch: int) -> list[str]:
    return ["train", "--build", str(build), "--out", str(out), *COMMON, "--set",
            f"train.batch_size={per_process_batch}"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_ranks(args: list[str], world: int, stop_rank0_at: str | None = None) -> list[subprocess.Popen]:
    """The run's processes, with the environment torchrun gives them."""
    port, procs = free_port(), []
    for rank in range(world):
        env = {**os.environ, "RANK": str(rank), "WORLD_SIZE": str(world), "LOCAL_RANK": str(rank),
               "LOCAL_WORLD_SIZE": str(world), "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port),
               "OMP_NUM_THREADS": "1"}
        env.pop("PARADRIVE_STOP_AT", None)
        if rank == 0 and stop_rank0_at:
            env["PARADRIVE_STOP_AT"] = stop_rank0_at
        procs.append(subprocess.Popen([sys.executable, "-m", "paradrive.cli", *args], env=env,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    return procs


def finish(procs: list[subprocess.Popen]) -> list[tuple[int, str, str]]:
    out = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=600)
        out.append((p.returncode, stdout, stderr))
    return out


def trained(path) -> dict[str, torch.Tensor]:
    return torch.load(path, weights_only=True)["model"]


def assert_adam_close(a: torch.Tensor, b: torch.Tensor, name: str) -> None:
    """Weights of two runs whose gradients differ only by the order of a sum: nearly every
    element within float rounding, and none further than AdamW can move it, lr a step for each
    run (a gradient near zero has an update of either sign: m / sqrt(v) is about +-1 for it)."""
    lr = load_wan_config("smoke")["train"]["lr"]
    diff = (a - b).abs()
    close = diff <= 1e-6 + 1e-5 * b.abs()
    assert float(diff.max()) <= 2 * lr * STEPS, (name, float(diff.max()))
    assert float(close.float().mean()) >= 0.99, (name, int((~close).sum()), a.numel())


def losses(run) -> list[float]:
    return [json.loads(line)["loss"] for line in (run / "stage1" / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def two_process_run(wan_builds, tmp_path_factory):
    """An uninterrupted two-process run, started by torchrun itself: the documented launcher."""
    out = tmp_path_factory.mktemp("ddp") / "run"
    result = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                             "-m", "paradrive.cli", *train_args(wan_builds["train"], out, 1)],
                            env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return out, result


def test_each_rank_reads_its_share_of_the_adapters_epoch_order(wan_builds, tmp_path):
    cfg = load_wan_config("smoke", {"train": {"batch_size": 2, "grad_accumulation": 2}})
    trainer = WanTrainer(cfg, 1, tmp_path / "run", open_wan_dataset(wan_builds["train"], cfg))
    for rank in (0, 1):
        trainer.world = World(rank, 2)
        adapter = PairIterableDataset(wan_builds["train"], seed=cfg["seed"], rank=rank, world_size=2)
        steps = trainer._epoch_steps(3)
        assert [i for step in steps for micro in step for i in micro] == \
            adapter.rank_order(3)[:len(steps) * 4].tolist()
        assert all(len(step) == 2 and all(len(m) == 2 for m in step) for step in steps)   # 2 micro-batches of 2


def test_two_processes_average_to_one_process_on_the_same_global_batch(wan_builds, two_process_run, tmp_path):
    ddp, result = two_process_run
    single = tmp_path / "single"
    from paradrive.cli import app

    one = CliRunner().invoke(app, train_args(wan_builds["train"], single, 2))   # one process, batch 2
    assert one.exit_code == 0, one.output
    np.testing.assert_allclose(losses(ddp), losses(single), rtol=1e-6)
    a, b = trained(ddp / "stage1" / "last.pt"), trained(single / "stage1" / "last.pt")
    assert a.keys() == b.keys()
    for name in a:
        assert_adam_close(a[name], b[name], name)
    # rank 0 alone wrote the run folder and printed; the run records its world size
    assert yaml.safe_load((ddp / "stage1" / "config.yaml").read_text())["world_size"] == 2
    lines = [json.loads(line) for line in (ddp / "stage1" / "metrics.jsonl").read_text().splitlines()]
    assert [(m["step"], m["world_size"], m["global_batch"]) for m in lines] == [(s, 2, 2) for s in range(1, 5)]
    assert result.stdout.count("stage 1: 4 steps") == 1 and "2 process(es)" in result.stdout
    assert torch.load(ddp / "stage1" / "last.pt", weights_only=True)["world_size"] == 2


def test_a_killed_two_process_run_resumes_to_the_same_result(wan_builds, two_process_run, tmp_path):
    ddp, _ = two_process_run
    out = tmp_path / "killed"
    procs = start_ranks(train_args(wan_builds["train"], out, 1), 2, stop_rank0_at="train:stage1-saved-2")
    try:
        _, status = os.waitpid(procs[0].pid, os.WUNTRACED)   # rank 0 stops itself right after saving step 2
        assert os.WIFSTOPPED(status), status
        for p in procs:                                      # then the whole run is killed
            p.send_signal(signal.SIGKILL)
        for p in procs:
            p.wait()
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert torch.load(out / "stage1" / "last.pt", weights_only=True)["step"] == 2

    # a resume on one process is refused in one line: the data order depends on the process count
    from paradrive.cli import app

    refused = CliRunner().invoke(app, train_args(wan_builds["train"], out, 1))
    assert refused.exit_code == 2 and "trained on 2 process(es)" in refused.output

    results = finish(start_ranks(train_args(wan_builds["train"], out, 1), 2))
    assert [code for code, _, _ in results] == [0, 0], results[0][2][-3000:]
    a, b = trained(ddp / "stage1" / "last.pt"), trained(out / "stage1" / "last.pt")
    for name in a:
        assert a[name].numpy().tobytes() == b[name].numpy().tobytes(), name
    assert losses(out) == losses(ddp)


def torchrun(args: list[str]) -> subprocess.CompletedProcess:
    result = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                             "-m", "paradrive.cli", *args],
                            env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return result


def test_a_sharded_run_trains_as_ddp_and_writes_the_same_whole_checkpoints(wan_builds, two_process_run, tmp_path):
    """train.fsdp: the weights, gradients and moments sharded over two gloo processes (stage 1: a
    block's frozen and trained weights in one unit). Stopped at step 2 and resumed (the resumed
    moments cut into shards again), it ends where the DDP run does, in the same checkpoint form."""
    ddp, _ = two_process_run
    out = tmp_path / "fsdp"
    args = [*train_args(wan_builds["train"], out, 1), "--set", "train.fsdp=true"]
    torchrun([*args, "--steps", "2"])
    half = torch.load(out / "stage1" / "last.pt", weights_only=True)
    assert half["step"] == 2 and half["config"]["train"]["fsdp"] is True
    assert all(type(t) is torch.Tensor for t in half["model"].values())          # whole tensors, not shards
    torchrun(args)                                                                   # resumes to step 4
    np.testing.assert_allclose(losses(out), losses(ddp), rtol=1e-6)
    mine, theirs = (torch.load(run / "stage1" / "last.pt", weights_only=True) for run in (out, ddp))
    assert mine["model"].keys() == theirs["model"].keys()
    for name in theirs["model"]:
        assert_adam_close(mine["model"][name], theirs["model"][name], name)
    assert mine["optimizer"]["state"].keys() == theirs["optimizer"]["state"].keys()
    for i, moments in theirs["optimizer"]["state"].items():
        for key, value in moments.items():
            torch.testing.assert_close(mine["optimizer"]["state"][i][key], value, rtol=1e-5, atol=1e-7)
