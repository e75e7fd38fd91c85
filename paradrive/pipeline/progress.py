"""Progress inside a long stage, and per-stage counts of a build, for a person watching it.

A scene stage gets a :class:`StageProgress` as ``ctx.progress`` and calls it as work advances:
``progress(done, total, **fields)`` (the fit per iteration with ``loss``, ``psnr`` and
``gaussians``; render per frame; clip per stream). It keeps the rate and the ETA, writes a line to
the scene's log at least every :data:`LOG_EVERY_S` seconds and at every tenth of the stage
(:data:`LOG_STEPS`; a short stage logs too), and hands every update to a sink (the console of
``paradrive build``) when there is one. A field may be given as a function of no arguments: it is
called only when a line is written (the fit's PSNR costs a render of its evaluation views), and
only as often as keeps it within :data:`FIGURE_BUDGET` of the time (always for the last line);
the lines between repeat its last value, saying at which step it was computed
(``PSNR 20.28 dB (at 90)``).

:class:`StageCounts` turns the executor's start / result events into per-stage counts (running,
done, skipped, failed), the same for a local and a Ray build.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from logging import Logger
from typing import Any

LOG_EVERY_S = 30.0   # a progress line in the scene's log at least this often while a stage runs
LOG_STEPS = 10       # and one at every tenth of the stage
RATE_WINDOW_S = 60.0  # the rate (and so the ETA) is measured over about the last minute
FIGURE_BUDGET = 0.05  # a costly figure (the fit's PSNR) takes at most this share of the stage's time

FIELD_ORDER = ("loss", "psnr", "gaussians")   # shown first, in this order; others after
UNITS = {"fit": ("iteration", "it"), "render": ("frame", "frames"), "clip": ("stream", "streams")}


def format_duration(seconds: float | None) -> str:
    """``h:mm:ss`` (``?`` when unknown)."""
    if seconds is None or not math.isfinite(seconds):
        return "?"
    s = int(round(max(seconds, 0.0)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def _format_field(name: str, value: Any) -> str:
    if name == "loss":
        return f"loss {value:.4f}"
    if name == "psnr":
        return f"PSNR {value:.2f} dB"
    if name == "gaussians":
        return f"{int(value):,} Gaussians"
    return f"{name} {value:.4g}" if isinstance(value, float) else f"{name} {value}"


@dataclass
class Snapshot:
    """Where one (scene, stage) stands: ``done`` of ``total`` units, the rate over about the last
    :data:`RATE_WINDOW_S` seconds (units per second; a fit slows as it densifies), the ETA and the
    stage's own figures (loss, PSNR, ...)."""

    scene_id: str
    stage: str
    done: int
    total: int
    rate: float | None = None
    eta_s: float | None = None
    fields: dict[str, Any] = field(default_factory=dict)
    computed_at: dict[str, int] = field(default_factory=dict)   # figures repeated from an earlier step

    def figures(self) -> str:
        """The stage's figures, rate and ETA: ``loss 0.0831, PSNR 21.34 dB, 7,012 Gaussians,
        14.2 it/s, ETA 0:00:13``."""
        unit = UNITS.get(self.stage, ("step", "steps"))[1]
        names = sorted(self.fields, key=lambda k: FIELD_ORDER.index(k) if k in FIELD_ORDER else len(FIELD_ORDER))
        parts = [_format_field(k, self.fields[k])
                 + (f" (at {self.computed_at[k]})" if k in self.computed_at else "")
                 for k in names if self.fields[k] is not None]
        parts.append(f"{self.rate:.1f} {unit}/s" if self.rate is not None else f"? {unit}/s")
        parts.append(f"ETA {format_duration(self.eta_s)}")
        return ", ".join(parts)

    def line(self) -> str:
        """``fit: iteration 120/300 (40%), loss ..., ETA 0:00:13``."""
        unit = UNITS.get(self.stage, ("step", "steps"))[0]
        share = 100.0 * self.done / self.total if self.total else 100.0
        return f"{self.stage}: {unit} {self.done}/{self.total} ({share:.0f}%), {self.figures()}"


ProgressSink = Callable[[Snapshot], None]


class StageProgress:
    """The ``ctx.progress`` of one (scene, stage): call it as ``progress(done, total, **fields)``.

    ``guard()``, when given, is called first on every call: it raises to stop the stage.
    ``sink`` gets a :class:`Snapshot` on every call (cheap fields only: a function field keeps
    its last computed value); the scene's ``log`` gets :meth:`Snapshot.line` at the intervals
    of the module doc and at the end. ``clock`` is the time source (seconds).
    """

    def __init__(self, scene_id: str, stage: str, log: Logger | None = None,
                 sink: ProgressSink | None = None, *, every_s: float = LOG_EVERY_S,
                 steps: int = LOG_STEPS, clock: Callable[[], float] = time.monotonic,
                 guard: Callable[[], None] | None = None):
        self.scene_id, self.stage, self.log, self.sink = scene_id, stage, log, sink
        self.guard = guard   # raises when the stage must stop (its scene's lease was lost)
        self.every_s, self.steps, self.clock = every_s, max(int(steps), 1), clock
        self.samples: deque[tuple[float, int]] = deque()   # (time, done), the last minute's
        self.logged_at: float | None = None
        self.logged_step = -1
        self.last: dict[str, Any] = {}                 # the function fields' last values ...
        self.cost: dict[str, tuple[float, float]] = {}  # ... when they were computed, in how long
        self.at: dict[str, int] = {}                   # ... and at which step
        self.losses: list[float] = []                  # losses since the last line (their mean is shown)

    def __call__(self, done: int, total: int, **fields: Any) -> None:
        if self.guard is not None:
            self.guard()
        now = self.clock()
        if not self.samples or now - self.samples[-1][0] >= 0.5:
            self.samples.append((now, done))
        while len(self.samples) > 2 and now - self.samples[1][0] >= RATE_WINDOW_S:
            self.samples.popleft()
        step = done * self.steps // total if total > 0 else self.steps
        due = (self.logged_at is None or done >= total or step > self.logged_step
               or now - self.logged_at >= self.every_s)
        if "loss" in fields:
            loss = fields.pop("loss")
            if loss is not None:
                self.losses.append(float(loss))
            fields["loss"] = sum(self.losses) / len(self.losses) if self.losses else None
        for name, value in fields.items():
            if callable(value):
                if due and (done >= total or self._affordable(name, now)):
                    started = self.clock()
                    self.last[name] = float(value())
                    self.cost[name], self.at[name] = (now, self.clock() - started), done
                fields[name] = self.last.get(name)
        snap = self.snapshot(done, total, now, fields)
        snap.computed_at = {k: at for k, at in self.at.items() if at != done and k in fields}
        if due:
            self.logged_at, self.logged_step, self.losses = now, step, []
            if self.log is not None:
                self.log.info("%s", snap.line())
        if self.sink is not None:
            self.sink(snap)

    def _affordable(self, name: str, now: float) -> bool:
        if name not in self.cost:
            return True
        at, seconds = self.cost[name]
        return now - at >= seconds / FIGURE_BUDGET

    def snapshot(self, done: int, total: int, now: float, fields: dict[str, Any]) -> Snapshot:
        t0, done0 = self.samples[0] if self.samples else (now, done)
        rate = (done - done0) / (now - t0) if now > t0 and done > done0 else None
        eta = (total - done) / rate if rate else (0.0 if done >= total else None)
        return Snapshot(self.scene_id, self.stage, int(done), int(total), rate, eta, dict(fields))


class StageCounts:
    """Per-stage counts of a build from its executor's events: ``start(scene, stage)`` when a
    task is handed out (on Ray: submitted to the cluster), ``result(StageResult)`` when it ends."""

    STATES = ("done", "skipped", "failed", "blocked")

    def __init__(self, stages: list[str], scenes: int):
        self.stages, self.scenes = list(stages), scenes
        self.running: Counter[str] = Counter()
        self.ended: dict[str, Counter[str]] = {s: Counter() for s in self.stages}

    def start(self, scene: str, stage: str) -> None:
        if stage in self.ended:
            self.running[stage] += 1

    def result(self, result: Any) -> None:
        stage = result.stage
        if stage not in self.ended or result.scene_id.startswith("build:"):
            return
        if result.status != "blocked" and self.running[stage] > 0:
            self.running[stage] -= 1
        self.ended[stage][result.status] += 1

    def finished(self, stage: str) -> int:
        return sum(self.ended[stage].values())

    def line(self) -> str:
        """``ingest 2/2, fit 1/2 (1 running), render 0/2, clip 0/2``, failures named."""
        parts = []
        for stage in self.stages:
            ended = self.ended[stage]
            text = f"{stage} {self.finished(stage)}/{self.scenes}"
            extra = [f"{self.running[stage]} running"] if self.running[stage] else []
            extra += [f"{ended[s]} {s}" for s in ("failed", "blocked") if ended[s]]
            parts.append(text + (f" ({', '.join(extra)})" if extra else ""))
        return ", ".join(parts)


__all__ = ["LOG_EVERY_S", "LOG_STEPS", "ProgressSink", "Snapshot", "StageCounts", "StageProgress",
           "format_duration"]
