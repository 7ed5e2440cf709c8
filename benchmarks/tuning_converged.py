"""Benchmark: the local tuners of ``benchmarks/tuning.py`` run far longer.

``benchmarks/tuning.py`` gives scipy's Nelder-Mead at most 1500 evaluations per position, and it
stops there still descending; the ratios it reports are the cost of reaching that value.  This
script asks the other question: how low does each tuner get, and at what cost, when it is run
eight times longer (or until scipy's tolerances stop the simplex)?  Same problem, start and
objective as ``tuning.py`` (``tuning.setup``):

1. Nelder-Mead (adaptive, simplex step 0.1, ``--maxfev`` evaluations per position, default
   12000; scipy stops earlier when the simplex has collapsed, xatol 1e-8, fatol 1e-10).
2. ``fdjax.tune_newton`` with the exact Hessian, ``--newton-steps`` (default 200), and with the
   exact Hessian every 8 steps and SR1 updates between, ``--sr1-steps`` (default 300): all six
   positions in one ``vmap``-ed program.

Per position: each tuner's best J, the RMS scale error of its best design, the evaluations
(steps) after which it is within 0.1 % of its own best ("settled"), and which tuner ends
lower.  Then the cost of each Newton variant to reach the simplex's final value (where it
does), and the cost of both to reach the worse of the two final values, counted as in
``tuning.py`` (a Nelder-Mead evaluation = 1 simulation; J with its gradient = 2; with its
Hessian = 26).

Usage:  python benchmarks/tuning_converged.py [--maxfev 12000] [--newton-steps 200]
        [--sr1-steps 300] [--quick] [--out benchmarks/results/tuning_converged.json]
"""

from __future__ import annotations

import argparse
import os
import platform

import equinox as eqx
import jax
import numpy as np
import scipy
from _timing import jsonable, loadavg, write_results  # benchmarks/ is on sys.path
from tuning import (
    HESSIAN_EVERY,
    _f,
    compare,
    compare_common,
    derivative_free,
    newton_local,
    setup,
)

CONVERGED = 1e-3  # "converged": within 0.1 % of the tuner's own best


def _first_within(trace, best):
    """1-based index of the first value of the running minimum within CONVERGED of ``best``."""
    run = np.minimum.accumulate(np.asarray(trace, np.float64), axis=0)
    return int(np.nonzero(run <= best * (1 + CONVERGED))[0][0]) + 1


def _rms_um(par, obj, drive, thetas, positions):
    f = eqx.filter_jit(jax.vmap(lambda th, y: obj(par.to_controller(th), drive, y).rms_error_m))
    return (1e6 * np.asarray(f(jax.numpy.asarray(np.asarray(thetas)),
                               jax.numpy.asarray(positions)))).tolist()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maxfev", type=int, default=12000)
    ap.add_argument("--newton-steps", type=int, default=200)
    ap.add_argument("--sr1-steps", type=int, default=300)
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: two positions, maxfev 300, 10 and 16 Newton steps")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "tuning_converged.json"))
    args = ap.parse_args()
    if args.quick:
        args.maxfev, args.newton_steps, args.sr1_steps = 300, 10, 16
    load0 = loadavg()
    drive, par, obj, positions, start = setup(2 if args.quick else 6)

    grads = {"newton": newton_local(par, obj, drive, positions, start, args.newton_steps, 1),
             "newton_sr1": newton_local(par, obj, drive, positions, start, args.sr1_steps,
                                        HESSIAN_EVERY)}
    for name, g in grads.items():
        print(name, g["j_best"], f"{g['steps_s']:.1f} s", flush=True)
    nm = derivative_free(par, obj, drive, positions, start, args.maxfev)
    print("nelder-mead", [(d["position_m"], d["j_best"], d["evals_to_best"])
                          for d in nm["positions"]], flush=True)

    nm_thetas = [d["theta_best"] for d in nm["positions"]]
    nm_rms = (_rms_um(par, obj, drive, nm_thetas, positions)
              if all(th is not None for th in nm_thetas) else None)
    rows = []
    for i, (p, d) in enumerate(zip(positions, nm["positions"])):
        row = {"position_m": float(p), "nm_j_best": d["j_best"],
               "nm_evals_to_best": d["evals_to_best"],
               "nm_evals_to_converged": _first_within(d["trace"], d["j_best"]),
               "nm_evals": d["evals"], "nm_message": d["message"],
               "nm_rms_um": None if nm_rms is None else nm_rms[i]}
        for name, g in grads.items():
            h = np.asarray(g["history"])[:, i]
            row[f"{name}_j_best"] = float(g["j_best"][i])
            row[f"{name}_steps_to_converged"] = _first_within(h, float(g["j_best"][i]))
        rows.append(row)
    methods = {}
    for name, g in grads.items():
        g["rms_um"] = (1e6 * np.asarray(g["rms_error_m"])).tolist()
        to_nm, to_nm_totals = compare(g, nm, positions)
        common, common_totals = compare_common(g, nm, positions)
        methods[name] = {"gradient": g, "to_nm_best": to_nm, "to_nm_best_totals": to_nm_totals,
                         "common_value": common, "common_value_totals": common_totals,
                         "lower_than_nm_at": int(sum(float(g["j_best"][i]) < d["j_best"]
                                                     for i, d in enumerate(nm["positions"])))}
    result = {
        "benchmark": "tuning_converged", "quick": bool(args.quick),
        "setup": {"as": "benchmarks/tuning.py setup()", "positions_m": positions.tolist(),
                  "maxfev": args.maxfev, "newton_steps": args.newton_steps,
                  "sr1_steps": args.sr1_steps, "hessian_every": HESSIAN_EVERY,
                  "converged_within": CONVERGED},
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                    "jax": jax.__version__, "scipy": scipy.__version__},
        "loadavg": {"start": load0, "end": loadavg()},
        "positions": rows, "methods": methods, "derivative_free": nm,
    }
    md = markdown(result)
    write_results(args.out, jsonable(_compact(result)), md)


def _compact(result, every=50):
    """The result as stored: each simplex trace as its running minimum every ``every``
    evaluations (and at the last), without its time stamps (12 000 values per position)."""
    for d in result["derivative_free"]["positions"]:
        run = np.minimum.accumulate(np.asarray(d.pop("trace"), np.float64))
        d.pop("trace_seconds")
        k = np.unique(np.r_[np.arange(0, run.size, every), run.size - 1])
        d["running_min_evaluations"] = (k + 1).tolist()
        d["running_min"] = run[k].tolist()
    return result


def markdown(result):
    s = result["setup"]
    lines = ["# Local tuners run far longer", "",
             f"Nelder-Mead: at most {s['maxfev']} evaluations per position.  Trust-region "
             f"Newton: {s['newton_steps']} steps with the exact Hessian; {s['sr1_steps']} "
             f"steps with it every {s['hessian_every']} steps and SR1 between.  \"Converged\": "
             "the first evaluation (step; the start counts as one) within "
             f"{100 * s['converged_within']:.1f} % of the tuner's own best.", "",
             "| position | NM best J (RMS µm) | NM evals to converged / best / run | "
             "Newton best J (RMS µm), steps to converged | SR1 best J (RMS µm), steps |",
             "|---|---|---|---|---|"]
    g_n = result["methods"]["newton"]["gradient"]
    g_s = result["methods"]["newton_sr1"]["gradient"]
    for i, r in enumerate(result["positions"]):
        lines.append(
            f"| {r['position_m']:.2f} m | {r['nm_j_best']:.4f} ({_f(r['nm_rms_um'], '.2f')}) | "
            f"{r['nm_evals_to_converged']} / {r['nm_evals_to_best']} / {r['nm_evals']} | "
            f"{r['newton_j_best']:.4f} ({g_n['rms_um'][i]:.2f}), "
            f"{r['newton_steps_to_converged']} | {r['newton_sr1_j_best']:.4f} "
            f"({g_s['rms_um'][i]:.2f}), {r['newton_sr1_steps_to_converged']} |")
    for name, label in (("newton", "exact Hessian"), ("newton_sr1", "Hessian every 8, SR1")):
        m = result["methods"][name]
        reached = [r["gradient_steps_to_reach"] for r in m["to_nm_best"]]
        c = m["common_value_totals"]
        lines += ["", f"Newton ({label}): lower than Nelder-Mead's final value at "
                  f"{m['lower_than_nm_at']} of {len(reached)} positions; reaches it at "
                  f"{sum(k is not None for k in reached)} (steps: "
                  f"{', '.join(_f(k, 'd') for k in reached)}).  To the worse of the two "
                  f"final values: gradient {c['gradient_sims']} simulation equivalents, "
                  f"{c['gradient_seconds_all']:.1f} s (all positions together); Nelder-Mead "
                  f"{c['nm_evals']} evaluations, {c['nm_seconds']:.1f} s: "
                  f"{c['simulations_ratio']:.1f}× fewer simulations, "
                  f"{c['wall_time_ratio']:.1f}× less wall time."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
