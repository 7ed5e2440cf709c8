"""Benchmark: the local tunings against two derivative-free tuners, Nelder-Mead and CMA-ES.

The problem, the counting and the gradient tuners are ``benchmarks/tuning.py``'s (12
parameters, six positions 0.1–0.7 m, from the reference controller with k_v halved).  Besides
scipy's adaptive Nelder-Mead (simplex step 0.1), the covariance matrix adaptation evolution
strategy (CMA-ES, the ``cma`` package, ``pip install cma``: default population, initial step
σ0 = 0.1 and 0.3 in θ, seed 1) gets the same number of evaluations per position, one position
after the other, on the same jitted J(θ, Y).  All run in one process.  For each baseline:
its best J per position and the simulations and wall time the gradient tuners (trust-region
Newton with the exact Hessian, and with the Hessian every 8 steps and SR1 between) take to
reach it, as ``benchmarks/tuning.py`` counts them (an evaluation of J = 1 simulation; J with
its gradient 2; with its Hessian too 2 + 2·12; a baseline is charged its evaluations and
seconds up to its own best).

Usage:  python benchmarks/tuning_cmaes.py [--maxfev 1500] [--quick]
        [--out benchmarks/results/tuning_cmaes.json]
"""

from __future__ import annotations

import os
import platform
import time

import equinox as eqx
import jax
import numpy as np
import scipy
from _timing import jsonable, loadavg, write_results
from tuning import TARGETS, compare, derivative_free, newton_local, rerun_problem

SIGMAS = (0.1, 0.3)
SEED = 1


def cma_es(par, obj, drive, positions, start, maxfev, sigma0):
    """CMA-ES per position on the jitted J(θ, Y), from θ0 = par.from_controller(start); every
    evaluation and its time recorded (the format of ``tuning.derivative_free``)."""
    import cma

    j_fn = eqx.filter_jit(lambda th, y: obj(par.to_controller(th), drive, y).total)
    theta0 = np.asarray(par.from_controller(start), np.float64)
    jax.block_until_ready(j_fn(jax.numpy.asarray(theta0), jax.numpy.asarray(positions[0])))
    out = []
    for p in positions:
        y = jax.numpy.asarray(p)
        es = cma.CMAEvolutionStrategy(theta0, sigma0, {"maxfevals": maxfev, "verbose": -9,
                                                       "seed": SEED})
        trace, stamps, bad = [], [], 0
        t0 = time.perf_counter()
        while not es.stop():
            xs = es.ask()
            fs = []
            for x in xs:
                v = float(j_fn(jax.numpy.asarray(x), y))
                if not np.isfinite(v):
                    bad, v = bad + 1, 1e30
                fs.append(v)
                trace.append(v)
                stamps.append(time.perf_counter() - t0)
            es.tell(xs, fs)
        total = time.perf_counter() - t0
        tr = np.asarray(trace)
        k_best = int(np.argmin(tr))
        out.append({
            "position_m": float(p), "j_start": float(j_fn(jax.numpy.asarray(theta0), y)),
            "j_best": float(tr[k_best]), "evals": int(tr.size), "evals_to_best": k_best + 1,
            "seconds": total, "seconds_to_best": float(stamps[k_best]),
            "non_finite_evals": bad, "message": str(dict(es.stop())), "trace": tr,
            "trace_seconds": np.asarray(stamps),
        })
    return {"sigma0": sigma0, "population": int(es.popsize), "maxfev": int(maxfev),
            "positions": out}


def _summary(name, baseline, grads, positions):
    rows = {}
    for gname, g in grads.items():
        per, totals = compare(g, baseline, positions)
        rows[gname] = {
            "steps_to_reach": [r["gradient_steps_to_reach"] for r in per],
            "sims_to_reach": [r["gradient_sims_to_reach"] for r in per],
            "totals": totals}
    return {"baseline": name,
            "j_best": [d["j_best"] for d in baseline["positions"]],
            "evals_to_best": [d["evals_to_best"] for d in baseline["positions"]],
            "seconds_to_best": [d["seconds_to_best"] for d in baseline["positions"]],
            "gradient": rows}


def main():
    args, load0, (drive, par, obj, positions, start) = rerun_problem(
        __doc__.splitlines()[0], "tuning_cmaes.json")
    baselines = {"Nelder-Mead (scipy, adaptive, step 0.1)":
                 derivative_free(par, obj, drive, positions, start, args.maxfev)}
    for s in SIGMAS:
        baselines[f"CMA-ES (cma, σ0 {s:g})"] = cma_es(par, obj, drive, positions, start,
                                                       args.maxfev, s)
    for name, b in baselines.items():
        print(name, [(d["position_m"], round(d["j_best"], 4), d["evals_to_best"])
                     for d in b["positions"]], flush=True)
    k = 6 if args.quick else 1
    n_exact, n_sr1 = max(60 // k, 10), max(150 // k, 10)
    grads = {f"exact Hessian every step ({n_exact} steps)":
             newton_local(par, obj, drive, positions, start, n_exact),
             f"exact Hessian every 8 steps, SR1 between ({n_sr1} steps)":
             newton_local(par, obj, drive, positions, start, n_sr1, every=8)}
    rows = [_summary(name, b, grads, positions) for name, b in baselines.items()]
    for r in rows:
        print(r["baseline"], {g: {q: v["totals"].get(q) for q in ("simulations_ratio",
                                                                  "wall_time_ratio")}
                              for g, v in r["gradient"].items()}, flush=True)
    import cma
    result = {
        "benchmark": "tuning_cmaes", "quick": bool(args.quick),
        "setup": {"as": "benchmarks/tuning.py setup()", "positions_m": positions.tolist(),
                  "maxfev": args.maxfev, "counting": "baseline evaluation 1; J + gradient 2; "
                  "J + gradient + Hessian 26 (the start's evaluation has the Hessian)"},
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                    "jax": jax.__version__, "scipy": scipy.__version__,
                    "cma": cma.__version__},
        "loadavg": {"start": load0, "end": loadavg()},
        "gradient": {g: {"seconds_per_step": v["seconds_per_step"],
                         "j_best": np.asarray(v["j_best"]).tolist()}
                     for g, v in grads.items()},
        "baselines": rows, "targets": TARGETS,
    }
    write_results(args.out, jsonable(result), markdown(result))


def _ratio(v):
    return "—" if v is None else f"{v:.1f}×"


def markdown(result):
    m = result["machine"]
    lines = [
        "# Local tunings against Nelder-Mead and CMA-ES", "",
        f"Machine: {m['platform']}, {m['cpu_count']} CPUs, jax {m['jax']}, scipy "
        f"{m['scipy']}, cma {m['cma']}.  Load average: {result['loadavg']}.  Problem: "
        f"`benchmarks/tuning.py`'s (12 parameters, positions "
        f"{', '.join(f'{y:.2f}' for y in result['setup']['positions_m'])} m); each baseline "
        f"at most {result['setup']['maxfev']} evaluations per position, "
        f"charged its evaluations and seconds up to its best.  Counting: "
        f"{result['setup']['counting']}.", "",
        "| baseline | its best J, per position | evaluations to its best | gradient tuner | "
        "steps to reach it, per position | sims ratio | wall ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result["baselines"]:
        first = True
        for g, v in r["gradient"].items():
            t = v["totals"]
            steps = ", ".join("—" if s is None else str(s) for s in v["steps_to_reach"])
            head = (f"{r['baseline']} | {', '.join(f'{j:.3f}' for j in r['j_best'])} | "
                    f"{', '.join(str(e) for e in r['evals_to_best'])}") if first else " | | "
            lines.append(f"| {head} | {g} | {steps} | "
                         f"{_ratio(t.get('simulations_ratio'))} | "
                         f"{_ratio(t.get('wall_time_ratio'))} |")
            first = False
    lines += ["", "Targets: ≥ 20× fewer simulations, ≥ 10× less wall time (all positions; "
              "— where a position's value is not reached)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
