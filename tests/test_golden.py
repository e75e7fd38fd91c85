"""The smoke build's records are the contract: a refactor must not change a byte of them.

``tests/golden/smoke/`` holds ``scene.json``, ``fit.json``, ``renders.json``, ``clips.json`` of
seed 7, the build's ``index.json`` and its manifest rows (one JSON line per row). Timings, the
creation time and the temporary root are masked. On the environment the golden files were made
on (same CPU vector unit, torch, pyarrow and av), the rest must match byte for byte. Elsewhere,
values that depend on floating-point summation order or an encoder's version (PSNR, SSIM,
Gaussian counts, file sizes and hashes) are compared loosely (within 5 %, counts also within three
times their square root), and everything else exactly.

Regenerate after an intended contract change: ``PARADRIVE_UPDATE_GOLDEN=1 pytest tests/test_golden.py``.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import pyarrow.parquet as pq
import pytest

GOLDEN = Path(__file__).parent / "golden" / "smoke"
SCENE_ID = "synthetic-demo-s7"
SCENE_FILES = ("scene.json", "gs/fit.json", "renders/renders.json", "clips/clips.json")
VOLATILE = ("seconds", "cpu_seconds", "peak_rss_mb", "created_at")
# values that move with the CPU's summation order or the encoder/writer version
MEASURED = ("psnr", "ssim", "train_psnr", "train_ssim", "num_gaussians", "duplicated", "split",
            "pruned", "sha256", "bytes", "shard_bytes", "media_bytes", "condition_psnr",
            "condition_ssim", "fit_train_psnr", "fit_train_ssim", "paradrive", "pyarrow")
_VOLATILE_RE = re.compile(r'("(?:' + "|".join(VOLATILE) + r')": )("[^"]*"|[-0-9.eE+]+)')


def _environment() -> dict:
    import av
    import pyarrow
    import torch

    return {"cpu": torch.backends.cpu.get_cpu_capability(), "torch": torch.__version__,
            "pyarrow": pyarrow.__version__, "av": av.__version__}


def _masked(text: str, root: Path) -> str:
    return _VOLATILE_RE.sub(r'\1"*"', text).replace(str(root), "<root>")


def _rows_text(build_dir: Path, root: Path) -> str:
    rows = []
    for shard in sorted(build_dir.glob("pairs-*.parquet")):
        rows += pq.read_table(shard).to_pylist()
    return _masked("".join(json.dumps(r) + "\n" for r in rows), root)


def _texts(smoke_build) -> dict[str, str]:
    root, build_dir = smoke_build["root"], smoke_build["build_dir"]
    scene_dir = smoke_build["data_dir"] / "scenes" / SCENE_ID
    texts = {f"{SCENE_ID}/{name}": _masked((scene_dir / name).read_text(), root)
             for name in SCENE_FILES}
    texts["index.json"] = _masked((build_dir / "index.json").read_text(), root)
    texts["pairs.jsonl"] = _rows_text(build_dir, root)
    return texts


def _loads(name: str, text: str):
    if name.endswith(".jsonl"):
        return [json.loads(line) for line in text.splitlines()]
    return json.loads(text)


def _close(golden, actual, path: str) -> None:
    key = path.rsplit(".", 1)[-1].split("[")[0]
    if isinstance(golden, dict):
        assert isinstance(actual, dict) and list(actual) == list(golden), f"{path}: keys differ"
        for k in golden:
            _close(golden[k], actual[k], f"{path}.{k}")
    elif isinstance(golden, list):
        assert isinstance(actual, list) and len(actual) == len(golden), f"{path}: length differs"
        for i, (g, a) in enumerate(zip(golden, actual)):
            _close(g, a, f"{path}[{i}]")
    elif key in MEASURED or key.endswith(("_sha256", "_bytes")):
        assert type(actual) is type(golden), f"{path}: type differs"
        if isinstance(golden, (int, float)) and not isinstance(golden, bool) and golden:
            # a count of events (Gaussians pruned, split) also moves by about its square root
            counts = 3 * math.sqrt(abs(golden)) if isinstance(golden, int) else 0.0
            assert math.isclose(actual, golden, rel_tol=0.05, abs_tol=counts), \
                f"{path}: {actual} vs {golden}"
    else:
        assert actual == golden, f"{path}: {actual!r} != {golden!r}"


def test_smoke_build_records_match_the_golden_files(smoke_build):
    texts = _texts(smoke_build)
    if os.environ.get("PARADRIVE_UPDATE_GOLDEN"):
        for name, text in texts.items():
            (GOLDEN / name).parent.mkdir(parents=True, exist_ok=True)
            (GOLDEN / name).write_text(text)
        (GOLDEN / "environment.json").write_text(json.dumps(_environment(), indent=2) + "\n")
    same_environment = json.loads((GOLDEN / "environment.json").read_text()) == _environment()
    for name, text in texts.items():
        golden = (GOLDEN / name).read_text()
        if same_environment:
            assert text == golden, f"{name} differs from tests/golden/smoke/{name}"
        else:
            _close(_loads(name, golden), _loads(name, text), name)


def test_golden_comparison_catches_a_renamed_key_and_a_changed_value():
    golden = {"a": 1, "checkpoints": [{"iteration": 25, "psnr": 20.0}]}
    with pytest.raises(AssertionError, match="keys differ"):
        _close(golden, {"b": 1, "checkpoints": golden["checkpoints"]}, "fit.json")
    with pytest.raises(AssertionError, match="iteration"):
        _close(golden, {"a": 1, "checkpoints": [{"iteration": 26, "psnr": 20.0}]}, "fit.json")
    _close(golden, {"a": 1, "checkpoints": [{"iteration": 25, "psnr": 20.1}]}, "fit.json")
    with pytest.raises(AssertionError, match="psnr"):
        _close(golden, {"a": 1, "checkpoints": [{"iteration": 25, "psnr": 22.0}]}, "fit.json")
    pruned = {"densify": {"pruned": 53}}
    _close(pruned, {"densify": {"pruned": 50}}, "fit.json")  # within 3 sqrt(53) of 53
    with pytest.raises(AssertionError, match="pruned"):
        _close(pruned, {"densify": {"pruned": 80}}, "fit.json")
