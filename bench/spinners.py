"""Other jobs on every core, for the benchmarks' ``--busy`` runs: processes spinning numpy (one
thread each) while a block runs."""

from __future__ import annotations

import contextlib
import multiprocessing
import os

import numpy as np


def _spin(stop) -> None:
    """CPU-bound work in numpy (one thread) until ``stop`` is set: another job on the core."""
    values = np.random.default_rng(os.getpid()).random(1 << 15)
    while not stop.is_set():
        for _ in range(50):
            np.sqrt(np.sin(values, out=values) ** 2 + 1.0, out=values)


@contextlib.contextmanager
def busy_cores(n: int):
    """``n`` processes spinning numpy while the block runs (forked: they need nothing but numpy);
    yields how many run."""
    ctx = multiprocessing.get_context("fork")
    stop = ctx.Event()
    spinners = [ctx.Process(target=_spin, args=(stop,), daemon=True) for _ in range(n)]
    for p in spinners:
        p.start()
    try:
        yield len(spinners)
    finally:
        stop.set()
        for p in spinners:
            p.join(timeout=10)
            if p.is_alive():
                p.kill()
                p.join()


def every_core(on: bool):
    """:func:`busy_cores` on every core where ``on``, none elsewhere."""
    return busy_cores((os.cpu_count() or 1) if on else 0)
