"""Benchmark: the trust-region Newton tuner's settings against the simplex's result.

``benchmarks/tuning.py`` measures ``fdjax.tune_newton`` with two settings (the exact Hessian
every step; every 8 steps with SR1 updates between) against scipy's Nelder-Mead given 1500
evaluations per position, and misses the targets of ≥ 20× fewer simulations and ≥ 10× less
wall time.  This script asks whether other settings of the same tuner do better: a larger
initial trust radius (fewer steps on the way down), the exact Hessian more rarely (cheaper
steps), or only at the start (quasi-Newton after it).  Same problem, start and objective as
``tuning.py`` (``tuning.setup``), Nelder-Mead run again in the same process (the baseline of
every ratio here), counted as there: one Nelder-Mead evaluation = 1 simulation; J with its
gradient = 2; with its Hessian = 26 (the start's evaluation carries the Hessian in every
variant); J with its gradient and the Hessian of the margin term alone (``hessian="margins"``:
the open loops on the frequency grid, no simulation) = 2.  Wall time to reach: the steps until
every position has reached the simplex's best × the measured time per step of the six-position
run (all positions advance together).  Where a variant ends above the simplex somewhere, the
last column compares both at the worse of the two bests per position (``tuning.py``'s
``compare_common``: a value both reach; the simplex charged its evaluations and seconds up to it).

Usage:  python benchmarks/tuning_variants.py [--maxfev 1500] [--quick]
        [--out benchmarks/results/tuning_variants.json]
"""

from __future__ import annotations

import os
import platform

import jax
import numpy as np
import scipy
from _timing import jsonable, loadavg, write_results  # benchmarks/ is on sys.path
from tuning import compare, compare_common, derivative_free, newton_local, rerun_problem

ONLY_AT_START = 10**9  # hessian_every: the exact Hessian at the start only

# (name, newton_local settings, steps)
VARIANTS = [
    ("exact Hessian every step, Δ₀ 0.3 (tuning.py)",
     dict(every=1, radius=0.3, max_radius=5.0), 60),
    ("exact Hessian every step, Δ₀ 1", dict(every=1, radius=1.0, max_radius=10.0), 60),
    ("exact Hessian every step, Δ₀ 3", dict(every=1, radius=3.0, max_radius=20.0), 60),
    ("exact Hessian every step, Δ₀ 1, shrink 0.5",
     dict(every=1, radius=1.0, max_radius=10.0, shrink=0.5), 60),
    ("exact Hessian every 8 steps, SR1 between (tuning.py)",
     dict(every=8, radius=0.3, max_radius=5.0), 150),
    ("exact Hessian every 20 steps, SR1 between", dict(every=20, radius=0.3, max_radius=5.0),
     150),
    ("exact Hessian at the start only, SR1 after",
     dict(every=ONLY_AT_START, radius=0.3, max_radius=5.0), 150),
    ("exact Hessian at the start only, SR1 after, Δ₀ 1",
     dict(every=ONLY_AT_START, radius=1.0, max_radius=10.0), 150),
    ("exact Hessian of the margin term every step, SR1 for the rest (hessian='margins')",
     dict(every=1, radius=0.3, max_radius=5.0, hessian="margins"), 150),
    ("the same, Δ₀ 1", dict(every=1, radius=1.0, max_radius=10.0, hessian="margins"), 150),
]


def main():
    args, load0, (drive, par, obj, positions, start) = rerun_problem(
        __doc__.splitlines()[0], "tuning_variants.json")
    nm = derivative_free(par, obj, drive, positions, start, args.maxfev)
    print("nelder-mead", [(d["position_m"], round(d["j_best"], 4), d["evals_to_best"])
                          for d in nm["positions"]], flush=True)
    rows = []
    for name, settings, steps in VARIANTS:
        steps = max(steps // 6, 10) if args.quick else steps
        g = newton_local(par, obj, drive, positions, start, steps, **settings)
        per, totals = compare(g, nm, positions)
        _, common = compare_common(g, nm, positions)
        rows.append({
            "variant": name, "settings": settings, "steps": steps,
            "seconds_per_step": g["seconds_per_step"],
            "j_best": np.asarray(g["j_best"]).tolist(),
            "lower_than_nm_at": int(sum(float(g["j_best"][i]) < d["j_best"]
                                        for i, d in enumerate(nm["positions"]))),
            "steps_to_reach": [r["gradient_steps_to_reach"] for r in per],
            "sims_to_reach": [r["gradient_sims_to_reach"] for r in per],
            "totals": totals,
            # to the worse of the two bests at each position (a value both reach)
            "common_value_totals": common,
        })
        print(name, rows[-1]["steps_to_reach"], {k: totals.get(k) for k in (
            "simulations_ratio", "wall_time_ratio")}, {k: common[k] for k in (
                "simulations_ratio", "wall_time_ratio")}, flush=True)
    result = {
        "benchmark": "tuning_variants", "quick": bool(args.quick),
        "setup": {"as": "benchmarks/tuning.py setup()", "positions_m": positions.tolist(),
                  "maxfev": args.maxfev, "counting": "NM evaluation 1; J + gradient 2; "
                  "J + gradient + Hessian 26 (the start's evaluation has the Hessian); "
                  "J + gradient + the margin term's Hessian 2 (no simulation in that term)"},
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                    "jax": jax.__version__, "scipy": scipy.__version__},
        "loadavg": {"start": load0, "end": loadavg()},
        "nelder_mead": [{k: d[k] for k in ("position_m", "j_best", "evals_to_best",
                                           "seconds_to_best")} for d in nm["positions"]],
        "nelder_mead_seconds_per_eval": nm["seconds_per_eval_median"],
        "variants": rows,
    }
    write_results(args.out, jsonable(result), markdown(result))


def _x(v, fmt):
    return "—" if v is None else format(v, fmt)


def markdown(result):
    nm = result["nelder_mead"]
    pos = result["setup"]["positions_m"]
    lines = [
        "# Trust-region Newton settings against Nelder-Mead's result",
        "",
        f"Machine: {result['machine']['platform']}, {result['machine']['cpu_count']} CPUs, "
        f"jax {result['machine']['jax']}, scipy {result['machine']['scipy']}.  Load average: "
        f"{result['loadavg']}.  Problem: `benchmarks/tuning.py`'s (12 parameters, 6 positions "
        "from the reference controller with k_v halved).  Baseline, run in the same process: "
        f"scipy Nelder-Mead (adaptive, at most {result['setup']['maxfev']} evaluations per "
        f"position, {1e3 * result['nelder_mead_seconds_per_eval']:.1f} ms per evaluation), "
        "charged its evaluations and seconds up to its best.  Counting: "
        f"{result['setup']['counting']}.",
        "",
        "Nelder-Mead's best J: " + ", ".join(
            f"{p:g} m {d['j_best']:.4g} ({d['evals_to_best']} evaluations)"
            for p, d in zip(pos, nm)) + ".",
        "",
        "| variant | steps run | ms per step | steps to reach NM's best, per position | "
        "J best, per position | lower than NM at | sims ratio | wall ratio | "
        "to the worse of the two bests: sims ratio, wall ratio |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["variants"]:
        t = r["totals"]
        lines.append(
            f"| {r['variant']} | {r['steps']} | {1e3 * r['seconds_per_step']:.0f} | "
            + ", ".join(_x(k, "d") for k in r["steps_to_reach"]) + " | "
            + ", ".join(f"{j:.3f}" for j in r["j_best"]) + f" | {r['lower_than_nm_at']} | "
            + (f"{t['simulations_ratio']:.1f}× | {t['wall_time_ratio']:.1f}×"
               if t["all_positions_reached"] else "not reached everywhere | —")
            + f" | {r['common_value_totals']['simulations_ratio']:.1f}×, "
            f"{r['common_value_totals']['wall_time_ratio']:.1f}× |")
    lines += ["", "Targets: ≥ 20× fewer simulations, ≥ 10× less wall time (all positions).", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
