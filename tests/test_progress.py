"""Progress a person can follow: lines in the scene's log inside each long stage, and the
per-stage counts of a build (the console's live display is fed from the same events)."""

from __future__ import annotations

import json
import logging
import re

import pytest

from paradrive.pipeline import run_build
from paradrive.pipeline.progress import StageCounts, StageProgress
from paradrive.contracts.layout import DataLayout

FIT_LINE = re.compile(r"fit: iteration (\d+)/(\d+) \((\d+)%\), loss ([\d.]+), PSNR ([\d.]+) dB(?: \(at \d+\))?, "
                      r"([\d,]+) Gaussians, ([\d.]+|\?) it/s, ETA (\d+:\d\d:\d\d|\?)$")


def _log_lines(data_dir, scene_id: str, pattern: str) -> list[str]:
    text = DataLayout(data_dir).log(scene_id).read_text()
    return [line for line in text.splitlines() if re.search(pattern, line)]


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _lines_of(progress_calls, every_s=30.0) -> tuple[list[str], list]:
    """Run ``progress_calls(progress, clock)`` against a StageProgress writing to a list."""
    records: list[str] = []

    class _Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record.getMessage())

    log = logging.getLogger("test_progress")
    log.propagate, log.level = False, logging.INFO
    handler = _Keep()
    log.addHandler(handler)
    snaps: list = []
    clock = _Clock()
    try:
        progress_calls(StageProgress("scene-a", "fit", log, snaps.append, every_s=every_s, clock=clock),
                       clock)
    finally:
        log.removeHandler(handler)
    return records, snaps


# --------------------------------------------------------------------------- a real smoke build

@pytest.mark.slow
def test_a_smoke_fit_logs_iteration_loss_psnr_gaussians_rate_and_eta(smoke_scene):
    data_dir = smoke_scene["data_dir"]
    scene_dir = data_dir / "scenes" / "synthetic-demo-s7"   # other tests add scenes beside it
    lines = _log_lines(data_dir, scene_dir.name, r"fit: iteration \d+/")
    parsed = [FIT_LINE.search(line) for line in lines]
    assert lines and all(parsed), lines
    steps = [int(m.group(1)) for m in parsed if m]
    total = json.loads((scene_dir / "gs" / "fit.json").read_text())["iterations"]
    assert steps == sorted(steps) and steps[-1] == total and len(steps) >= 10  # every tenth at least
    assert {int(m.group(2)) for m in parsed if m} == {total}
    # the rate is measured from the first line on: only that one may not know it yet
    assert all(m.group(7) != "?" and m.group(8) != "?" for m in parsed[1:] if m)
    last = parsed[-1]
    assert last is not None and last.group(3) == "100" and last.group(8) == "0:00:00"
    assert float(last.group(7)) > 0 and float(last.group(4)) > 0
    # The figures are the fit's own: the last PSNR and Gaussian count are fit.json's final ones.
    final = json.loads((scene_dir / "gs" / "fit.json").read_text())["checkpoints"][-1]
    assert float(last.group(5)) == pytest.approx(final["psnr"], abs=0.006)
    assert int(last.group(6).replace(",", "")) == final["num_gaussians"]
    # The PSNR climbs as the fit goes on.
    first_psnr = float(parsed[0].group(5)) if parsed[0] else 0.0
    assert float(last.group(5)) > first_psnr + 3


@pytest.mark.slow
def test_render_logs_frames_and_clip_logs_streams(smoke_build):
    data_dir = smoke_build["data_dir"]
    for scene_dir in (data_dir / "scenes").iterdir():
        renders = _log_lines(data_dir, scene_dir.name, r"render: frame \d+/")
        clips = _log_lines(data_dir, scene_dir.name, r"clip: stream \d+/")
        assert renders and clips, scene_dir.name
        rendered = json.loads((scene_dir / "renders" / "renders.json").read_text())
        frames = sum(len(cam["frames"]) * len(cam["streams"]) for cam in rendered["cameras"].values())
        assert re.search(rf"render: frame {frames}/{frames} \(100%\), [\d.]+ frames/s, ETA 0:00:00$",
                         renders[-1]), renders[-1]
        written = json.loads((scene_dir / "clips" / "clips.json").read_text())
        streams = sum(len(c["streams"]) for c in written["clips"])
        assert re.search(rf"clip: stream {streams}/{streams} \(100%\), [\d.]+ streams/s, ETA 0:00:00$",
                         clips[-1]), clips[-1]


def test_the_fits_progress_figures_leave_its_checkpoints_unchanged(tiny_scene, tmp_path):
    from paradrive.stages.fit import fit_scene
    from test_gs_fit import TINY_FIT, _copy_scene, fit_params

    params = fit_params("smoke", **TINY_FIT)
    quiet, watched = _copy_scene(tiny_scene, tmp_path / "quiet"), _copy_scene(tiny_scene, tmp_path / "watched")
    fit_scene(quiet, params)
    seen: list[dict] = []

    def every_figure(done, total, **fields):  # computes the PSNR at every call, not only per line
        seen.append({k: v() if callable(v) else float(v) for k, v in fields.items()})

    fit_scene(watched, params, progress=every_figure)
    assert len(seen) == 2 and all(set(f) == {"loss", "psnr", "gaussians"} for f in seen)
    for it in params.checkpoints:
        name = f"ckpt_{it:06d}.ply"
        assert (quiet / "gs" / name).read_bytes() == (watched / "gs" / name).read_bytes(), name
    final = json.loads((watched / "gs" / "fit.json").read_text())["checkpoints"][-1]
    assert seen[-1]["psnr"] == pytest.approx(final["psnr"], abs=1e-9)
    assert seen[-1]["gaussians"] == final["num_gaussians"]


# --------------------------------------------------------------------------- when lines are written

def test_a_long_stage_logs_every_tenth_and_at_least_every_interval():
    def calls(progress, clock):
        for step in range(1, 1001):
            clock.now = step * 1.0     # one unit a second: 1000 s, more than 30 s between tenths
            progress(step, 1000, loss=0.5)

    lines, snaps = _lines_of(calls)
    steps = [int(re.search(r"iteration (\d+)/", line).group(1)) for line in lines]
    assert steps[0] == 1 and steps[-1] == 1000
    assert all(b - a <= 30 for a, b in zip(steps, steps[1:]))          # the interval
    assert {100 * k for k in range(1, 11)} <= set(steps)              # every tenth
    assert len(snaps) == 1000 and snaps[-1].eta_s == 0.0
    assert snaps[500].rate == pytest.approx(1.0) and snaps[500].eta_s == pytest.approx(499.0)


def test_the_rate_and_eta_follow_a_stage_that_slows_down():
    def calls(progress, clock):
        for step in range(1, 1001):   # 10 units a second for 500 units, then 1 a second
            clock.now += 0.1 if step <= 500 else 1.0
            progress(step, 1000)

    _, snaps = _lines_of(calls)
    assert snaps[499].rate == pytest.approx(10.0, rel=0.02)
    assert snaps[-2].rate == pytest.approx(1.0, rel=0.02) and snaps[-2].eta_s == pytest.approx(1.0, rel=0.02)


def test_a_short_stage_still_logs_each_tenth_and_its_end():
    def calls(progress, clock):
        for step in range(10, 301, 10):
            clock.now += 0.01
            progress(step, 300)

    lines, _ = _lines_of(calls)
    steps = [int(re.search(r"iteration (\d+)/", line).group(1)) for line in lines]
    assert steps == [10, 30, 60, 90, 120, 150, 180, 210, 240, 270, 300]


def test_a_costly_figure_is_computed_only_when_a_line_is_written_and_loss_is_averaged():
    computed: list[int] = []

    def calls(progress, clock):
        for step in range(1, 101):
            clock.now = float(step)

            def psnr(step=step):
                computed.append(step)
                return 20.0 + step / 10

            progress(step, 100, loss=float(step), psnr=psnr, gaussians=1234)

    lines, snaps = _lines_of(calls, every_s=1e9)
    assert computed == [int(re.search(r"iteration (\d+)/", line).group(1)) for line in lines]
    assert computed == [1, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100]
    # Between lines the sink sees the last computed PSNR; the loss is the mean since the last line.
    assert snaps[14].fields["psnr"] == pytest.approx(21.0)
    assert "loss 15.5000, PSNR 22.00 dB, 1,234 Gaussians" in lines[2]
    assert lines[-1].startswith("fit: iteration 100/100 (100%), loss 95.5000, PSNR 30.00 dB")


def test_a_costly_figure_keeps_within_its_share_of_the_time():
    computed: list[int] = []

    def calls(progress, clock):
        for step in range(1, 101):
            clock.now += 1.0

            def psnr(step=step):  # two seconds a time
                computed.append(step)
                clock.now += 2.0
                return 20.0

            progress(step, 100, psnr=psnr)

    lines, _ = _lines_of(calls, every_s=1e9)
    assert len(lines) == 11 and all("PSNR 20.00 dB" in line for line in lines)
    assert "iteration 30/100 (30%), PSNR 20.00 dB (at 1)," in lines[3]
    assert "iteration 40/100 (40%), PSNR 20.00 dB," in lines[4]
    # 2 s a time at 5 % of the time: once in 40 s at most, and for the last line
    assert computed == [1, 40, 80, 100]


# --------------------------------------------------------------------------- per-stage counts

def test_stage_counts_follow_a_build_with_a_failed_scene(stage_config, tmp_path):
    config = stage_config()
    scenes = ["synthetic:street?seed=1", "synthetic:street?seed=2&fail=render",
              "synthetic:street?seed=3"]
    counts = StageCounts(["ingest", "fit", "render", "clip"], len(scenes))
    seen: list[str] = []

    def on_start(scene, stage):
        counts.start(scene, stage)
        seen.append(counts.line())

    snaps: list = []
    report = run_build(config, scenes, tmp_path / "data", manifests_dir=tmp_path / "manifests",
                       build="b", on_start=on_start, on_result=counts.result, on_progress=snaps.append)
    assert report.exit_code == 3
    assert seen[0] == "ingest 0/3 (1 running), fit 0/3, render 0/3, clip 0/3"
    assert counts.line() == "ingest 3/3, fit 3/3, render 3/3 (1 failed), clip 3/3 (1 blocked)"
    # The stand-in render reports one step per offset; the local executor hands them on.
    ends = [(s.scene_id, s.done, s.total) for s in snaps if s.stage == "render" and s.done == s.total]
    assert ends == [("synthetic-street-s1", 2, 2), ("synthetic-street-s3", 2, 2)]
    assert "render: frame 2/2 (100%)" in DataLayout(tmp_path / "data").log("synthetic-street-s3").read_text()


def test_the_build_command_shows_per_stage_counts_on_a_terminal(tmp_path, monkeypatch):
    import io

    from rich.console import Console
    from typer.testing import CliRunner

    import paradrive.cli as cli
    import paradrive.commands.build as build_command
    import pipeline_stages

    monkeypatch.setenv("PARADRIVE_STAGES", str(pipeline_stages.write_stages(tmp_path / "stages")))
    screen = io.StringIO()
    monkeypatch.setattr(build_command, "console", Console(file=screen, force_terminal=True, width=200))
    args = ["build", "--scene", "synthetic:street?seed=1", "--scene", "synthetic:street?seed=2",
            "--data", str(tmp_path / "data"), "--manifests", str(tmp_path / "manifests")]
    result = CliRunner().invoke(cli.app, args)
    assert result.exit_code == 0, result.output
    shown = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", screen.getvalue())
    assert "2 done | " in shown and "ingest 2/2, fit 2/2, render 2/2, clip 2/2" in shown
