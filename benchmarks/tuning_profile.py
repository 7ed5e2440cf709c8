"""Benchmark: what an evaluation of the tuning objective costs, and its derivatives against
finite differences.

The problem is ``benchmarks/tuning.py``'s (``setup``): the 12-parameter double loop on
``fdjax.reference_drive()`` at six table positions, 400 margin frequencies, a twin with 6
modes, from the start θ0 of that benchmark.  Each program below is one jitted function of the
six positions' parameters (6, 12) and positions (6,), ``vmap``-ed over the positions and
called alone (the twin, which does not depend on θ, is rebuilt in every call, as it is where
scipy's simplex calls J):

* ``J``: the objective's value; ``margin_term`` and ``simulated_term``: its two parts (the
  open loops at three break points with the margin penalties; the run of the sampled loop
  with its barriers);
* ``J + gradient``: ``jax.value_and_grad``; ``J + Hessian``: ``jax.hessian`` (forward over
  reverse);
* baselines in the same run: the gradient by central differences (J at θ ± h e_k, 24
  evaluations per position in one program, h = 1e-6) and the Hessian by central differences
  of the gradient (24 gradients per position, h = 1e-5); the one-position evaluation of J as
  scipy's simplex calls it.

Compilation apart (the first call), the median of repeats, each call waited for with
``block_until_ready``.  The derivatives are compared with their finite differences.

Usage:  python benchmarks/tuning_profile.py [--repeats 7]
        [--out benchmarks/results/tuning_profile.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _timing import jsonable, loadavg, median_time, write_results
from tuning import setup

import fdjax

H_GRAD = 1e-6  # central differences of J: truncation ~h² J''' vs round-off ~ε J/h
H_HESS = 1e-5  # central differences of the gradient


def programs(par, obj, drive):
    """The timed programs, each a function of (θ (6, 12), Y (6,))."""

    def j(t, y):
        return obj(par.to_controller(t), drive, y).total

    def margin(t, y):
        return obj.margin_term(par.to_controller(t), drive, y)

    def simulated(t, y):
        return obj.simulated_term(par.to_controller(t), drive, y)

    def fd_gradient(t, y):
        steps = H_GRAD * jnp.eye(t.size)
        up = jax.vmap(lambda s: j(t + s, y))(steps)
        down = jax.vmap(lambda s: j(t - s, y))(steps)
        return (up - down) / (2 * H_GRAD)

    def fd_hessian(t, y):
        g = jax.grad(j)
        steps = H_HESS * jnp.eye(t.size)
        up = jax.vmap(lambda s: g(t + s, y))(steps)
        down = jax.vmap(lambda s: g(t - s, y))(steps)
        return (up - down) / (2 * H_HESS)

    per_position = {
        "J": j,
        "margin_term": margin,
        "simulated_term": simulated,
        "J + gradient": jax.value_and_grad(j),
        "J + Hessian": lambda t, y: (j(t, y), jax.hessian(j)(t, y)),
        "gradient by central differences (24 J)": fd_gradient,
        "Hessian by central differences (24 gradients)": fd_hessian,
    }
    return {name: eqx.filter_jit(jax.vmap(f)) for name, f in per_position.items()}, j


def _relative(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "tuning_profile.json"))
    args = ap.parse_args()
    load_start = loadavg()
    drive, par, obj, positions, start = setup()
    obj = obj.resolved(drive)
    theta = jnp.tile(jnp.asarray(par.from_controller(start)), (positions.size, 1))
    y = jnp.asarray(positions)
    progs, j = programs(par, obj, drive)
    rows, values = {}, {}
    for name, fn in progs.items():
        t0 = time.perf_counter()
        values[name] = jax.block_until_ready(fn(theta, y))
        compile_s = time.perf_counter() - t0
        med, times = median_time(lambda fn=fn: fn(theta, y), args.repeats, warmup=False)
        rows[name] = {"compile_s": compile_s, "seconds": med, "times": times}
        print(f"{name}: {1e3 * med:.2f} ms (compile {compile_s:.1f} s)", flush=True)
    one = eqx.filter_jit(j)
    jax.block_until_ready(one(theta[0], y[0]))
    med, times = median_time(lambda: one(theta[0], y[0]), 5 * args.repeats, warmup=False)
    rows["J at one position, called alone (as scipy's simplex calls it)"] = {
        "seconds": med, "times": times}
    grad = values["J + gradient"][1]
    hess = values["J + Hessian"][1]
    agreement = {
        "gradient vs central differences": _relative(
            grad, values["gradient by central differences (24 J)"]),
        "Hessian vs central differences of the gradient": _relative(
            hess, values["Hessian by central differences (24 gradients)"]),
        "J = margin_term + simulated_term": _relative(
            values["margin_term"] + values["simulated_term"], values["J"]),
    }
    ms = {k: 1e3 * v["seconds"] for k, v in rows.items()}
    ratios = {
        "gradient: central differences / reverse mode (both with J)":
            ms["gradient by central differences (24 J)"] / ms["J + gradient"],
        "Hessian: central differences / forward over reverse":
            ms["Hessian by central differences (24 gradients)"] / ms["J + Hessian"],
        "J + gradient / J": ms["J + gradient"] / ms["J"],
        "J + Hessian / J": ms["J + Hessian"] / ms["J"],
    }
    result = {
        "benchmark": "tuning_profile",
        "setup": {"problem": "benchmarks/tuning.py setup(): reference drive, 12 parameters, "
                             "six positions, 400 margin frequencies, 6 modes",
                  "positions_m": positions, "repeats": args.repeats,
                  "h_gradient": H_GRAD, "h_hessian": H_HESS},
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                    "jax": jax.__version__, "fdjax": fdjax.__version__,
                    "loadavg_start": load_start, "loadavg_end": loadavg()},
        "programs_ms": ms, "compile_s": {k: v.get("compile_s") for k, v in rows.items()},
        "times_s": {k: v["times"] for k, v in rows.items()},
        "ratios": ratios, "agreement": agreement,
    }
    write_results(args.out, jsonable(result), markdown(result))


def markdown(r):
    lines = ["# What the tuning objective costs (six positions, one program, 2 cores)", "",
             "| program | ms (median) | compile s |", "|---|---|---|"]
    for k, v in r["programs_ms"].items():
        c = r["compile_s"].get(k)
        lines.append(f"| {k} | {v:.2f} | {'' if c is None else f'{c:.1f}'} |")
    lines += ["", "| ratio | value |", "|---|---|"]
    lines += [f"| {k} | {v:.2f}× |" for k, v in r["ratios"].items()]
    lines += ["", "| agreement (max relative difference) | value |", "|---|---|"]
    lines += [f"| {k} | {v:.1e} |" for k, v in r["agreement"].items()]
    lines += ["", f"load average at the start {r['machine']['loadavg_start']}, at the end "
                  f"{r['machine']['loadavg_end']}", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
