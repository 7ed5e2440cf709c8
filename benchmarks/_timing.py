"""Timing shared by the benchmark scripts: median of repeats after a warm-up, results blocked."""

import time

import jax
import numpy as np


def median_time(fn, repeats, warmup=True):
    """(median seconds, all times) of ``fn()`` over ``repeats`` calls, each waited for with
    ``jax.block_until_ready``; one untimed call first (compilation) unless ``warmup=False``."""
    if warmup:
        jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), [float(t) for t in times]
