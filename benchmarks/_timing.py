"""Helpers shared by the benchmark scripts: timing (median of repeats after a warm-up, results
blocked), the machine's load, writing the results."""

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


def loadavg():
    """The 1, 5 and 15 minute load averages (None where /proc is not there)."""
    try:
        with open("/proc/loadavg") as fh:
            return [float(x) for x in fh.read().split()[:3]]
    except OSError:
        return None


def nelder_mead(fun, x0, simplex, maxfev):
    """scipy's adaptive Nelder-Mead on ``fun`` (x ↦ a scalar, e.g. a jitted objective), with
    every value and its time recorded: (result, values, seconds since the start, non-finite
    values, total seconds).  A non-finite value counts as 1e30."""
    import math

    import scipy.optimize

    trace, stamps, bad = [], [], 0

    def f(x):
        nonlocal bad
        v = float(fun(x))
        if not math.isfinite(v):
            bad += 1
            v = 1e30
        trace.append(v)
        stamps.append(time.perf_counter())
        return v

    t0 = time.perf_counter()
    res = scipy.optimize.minimize(f, x0, method="Nelder-Mead",
                                  options={"maxfev": maxfev, "adaptive": True,
                                           "initial_simplex": simplex, "xatol": 1e-8,
                                           "fatol": 1e-10})
    total = time.perf_counter() - t0
    return res, np.asarray(trace), np.asarray(stamps) - t0, bad, total


def jsonable(x):
    """``x`` with numpy arrays and scalars as lists and numbers, non-finite floats as strings."""
    import math

    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return x


def write_results(out, result, markdown):
    """Write ``result`` to the JSON file ``out`` and ``markdown`` beside it (``.md``); print
    the markdown."""
    import json
    import os

    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as fh:
        json.dump(result, fh, indent=2)
    with open(os.path.splitext(out)[0] + ".md", "w") as fh:
        fh.write(markdown)
    print(markdown)
    print(f"wrote {out}")
