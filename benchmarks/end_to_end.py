"""Benchmark: end-to-end training of the scheduling network by gradient (fdjax.train_schedule,
L-BFGS) vs a derivative-free tuner (Nelder-Mead) on the same objective.

The problem is the last stage of ``fdjax.synthesise``: the schedule trained by backpropagation
on the six local designs (the shipped ``mcm_ata``: an 8-wide ATA network, 151 weights, and the
loop's three feedback gains, 154 parameters in all) is trained further against

    L(θ) = ½ (mean_i J(schedule_θ, Y_i) + smax_2 J(schedule_θ, Y_i)),

J = ``fdjax.tuning_objective(margin_width=0.01)`` (the synthesis's objective), on ``--positions``
positions evenly over the travel (100–700 mm).  One evaluation of L simulates the loop at every
position: it is counted as that many simulations.

1. ``gradient``: ``fdjax.train_schedule(..., positions_m=Y, train_gains=True,
   optimiser=optax.lbfgs())``; its ``Descent.evaluations`` are the evaluations of L with its
   gradient (one per step plus the line search's trials), each counted as 2 simulations per
   position (one forward, one reverse pass).  Compilation is timed apart: a warm-up call of
   the same chunk length first.
2. ``derivative_free``: ``scipy.optimize.minimize(method="Nelder-Mead", adaptive=True)`` on the
   same 154 parameters (flattened), L a jitted function compiled outside the timing, initial
   simplex θ0 + 0.05·e_k, at most ``--maxfev`` evaluations.
3. The cost of each to reach the same value of L (the worse of their bests) and to reach the
   gradient's value at a few fractions of its run; the gradient's seconds are its evaluations
   until then × its wall time per evaluation (the L-BFGS update itself is negligible).

Usage:  python benchmarks/end_to_end.py [--steps 40] [--maxfev 2000] [--positions 7]
        [--quick] [--out benchmarks/results/end_to_end.json]
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
import optax
import scipy
import scipy.optimize
from _timing import (  # benchmarks/ on sys.path
    jsonable,
    loadavg,
    median_time,
    nelder_mead,
    write_results,
)
from jax.flatten_util import ravel_pytree

import fdjax
from fdjax._memory import release

SIMPLEX_STEP = 0.05
SHARPNESS = 2.0
SIMS_PER_GRADIENT = 2  # one forward and one reverse pass per position
LOOPED = 20  # evaluations of L in the compiled loop that times it as a compiled simplex would


def setup(n_positions):
    drive = fdjax.reference_drive()
    designs, _ = fdjax.load_designs()
    schedule = designs["mcm_ata"]
    obj = fdjax.tuning_objective(margin_width=0.01)
    y = np.linspace(*drive.travel_m, n_positions)
    return drive, schedule, obj, y


def trainable(schedule):
    """The parameters train_schedule(train_gains=True) trains: the network's arrays and the
    loop's three feedback gains (the same partition, flattened for Nelder-Mead)."""
    spec = jax.tree_util.tree_map(lambda _: False, schedule)
    spec = eqx.tree_at(lambda s: s.network, spec,
                       jax.tree_util.tree_map(eqx.is_inexact_array, schedule.network))
    spec = eqx.tree_at(lambda s: (s.loop.log_kp, s.loop.log_kv, s.loop.log_ki), spec,
                       (True,) * 3)
    return eqx.partition(schedule, spec)


def gradient(schedule, obj, drive, y, steps, chunk):
    opt = optax.lbfgs()
    kw = dict(positions_m=y, train_gains=True, optimiser=opt, chunk=chunk)
    t0 = time.perf_counter()
    jax.block_until_ready(fdjax.train_schedule(schedule, obj, drive, steps=chunk, **kw)[1]
                          .history)
    warm_s = time.perf_counter() - t0  # compilation + one chunk
    t0 = time.perf_counter()
    _, rec = fdjax.train_schedule(schedule, obj, drive, steps=steps, **kw)
    jax.block_until_ready(rec.history)
    wall_s = time.perf_counter() - t0  # every chunk compiled already
    per_step = wall_s / steps  # the average
    h, n = np.asarray(rec.history), np.asarray(rec.evaluations)
    return {"steps": steps, "chunk": chunk, "optimiser": "optax.lbfgs()",
            "compile_s": max(warm_s - chunk * per_step, 0.0), "warmup_call_s": warm_s,
            "wall_s": wall_s, "seconds_per_step": per_step,
            "seconds_per_evaluation": wall_s / float(np.sum(n)), "history": h,
            "evaluations": n, "simulations": SIMS_PER_GRADIENT * len(y) * np.cumsum(n),
            "finite_history": bool(np.all(np.isfinite(h)))}


def derivative_free(schedule, obj, drive, y, maxfev):
    params, static = trainable(schedule)
    flat0, unravel = ravel_pytree(params)
    yj = jnp.asarray(y)

    @eqx.filter_jit
    def loss(flat):
        s = eqx.combine(unravel(flat), static)
        j = jax.vmap(lambda p: obj(s, drive, p).total)(yj)
        return 0.5 * (jnp.mean(j) + fdjax.smooth_max(j, SHARPNESS))

    t0 = time.perf_counter()
    jax.block_until_ready(loss(flat0))
    compile_s = time.perf_counter() - t0
    t_eval, _ = median_time(lambda: loss(flat0), 5)

    # L inside a compiled loop of evaluations (as a compiled simplex would call it), where XLA
    # may compute what does not depend on the parameters once: a bound on what compiling the
    # baseline's loop would save
    @eqx.filter_jit
    def looped(flat):
        def body(x, _):
            v = loss.__wrapped__(x)
            return x + 1e-12 * v, v  # a new point every evaluation
        return jax.lax.scan(body, flat, None, length=LOOPED)

    t_loop = median_time(lambda: looped(flat0), 3)[0] / LOOPED
    x0 = np.asarray(flat0, np.float64)
    simplex = np.vstack([x0, x0 + SIMPLEX_STEP * np.eye(x0.size)])
    res, tr, stamps, bad, total_s = nelder_mead(lambda x: loss(jnp.asarray(x)), x0, simplex,
                                                maxfev)
    return {"n_parameters": int(x0.size), "compile_s": compile_s,
            "seconds_per_eval_median": t_eval, "seconds_per_eval_in_compiled_loop": t_loop,
            "simplex_step": SIMPLEX_STEP,
            "maxfev": int(maxfev), "evals": int(tr.size), "seconds": total_s,
            "j_start": float(tr[0]), "j_best": float(tr.min()),
            "evals_to_best": int(np.argmin(tr)) + 1, "non_finite_evals": bad,
            "message": str(res.message), "trace": tr,
            "trace_seconds": stamps}


def reach(grad, nm, n_positions, target):
    """Cost of each tuner until its running minimum is ≤ target (None: not reached)."""
    g_min = np.minimum.accumulate(grad["history"])
    k = np.nonzero(g_min <= target)[0]
    n_min = np.minimum.accumulate(nm["trace"])
    e = np.nonzero(n_min <= target)[0]
    row = {"target": float(target)}
    if k.size:
        k = int(k[0])
        # the time of the evaluations spent (the steps' cost: early steps' line searches take
        # more trials than late ones, so steps × the average step would under-count)
        evals = int(np.sum(np.asarray(grad["evaluations"])[:k + 1]))
        row.update(gradient_steps=k + 1, gradient_simulations=int(grad["simulations"][k]),
                   gradient_seconds=evals * grad["seconds_per_evaluation"])
    if e.size:
        e = int(e[0])
        row.update(nm_evals=e + 1, nm_simulations=(e + 1) * n_positions,
                   nm_seconds=float(nm["trace_seconds"][e]))
    if "gradient_steps" in row and "nm_evals" in row:
        row["simulations_ratio"] = row["nm_simulations"] / row["gradient_simulations"]
        row["wall_time_ratio"] = row["nm_seconds"] / row["gradient_seconds"]
    return row


def _f(x, fmt, suffix=""):
    return "not reached" if x is None else format(x, fmt) + suffix


def markdown(r):
    g, nm, n = r["gradient"], r["derivative_free"], len(r["setup"]["positions_m"])
    lines = [
        "# End-to-end benchmark: the scheduling network by gradient vs Nelder-Mead", "",
        f"Machine: {r['machine']['platform']}, {r['machine']['cpu_count']} CPUs (shared), jax "
        f"{r['machine']['jax']}, scipy {r['machine']['scipy']}.  Load average: {r['loadavg']}.",
        "",
        f"Problem: the shipped backpropagation schedule (`mcm_ata`) trained further against "
        f"L = ½(mean + smax₂) of J = `tuning_objective(margin_width=0.01)` on {n} positions "
        f"(100–700 mm); {nm['n_parameters']} parameters (the network's weights and the three "
        f"feedback gains).  One evaluation of L = {n} simulations; one with its gradient = "
        f"{SIMS_PER_GRADIENT * n}.",
        "",
        f"Gradient: `train_schedule(positions_m=..., train_gains=True, optimiser=optax.lbfgs())`,"
        f" {g['steps']} steps, {int(np.sum(g['evaluations']))} evaluations of L with its "
        f"gradient; compile {g['compile_s']:.1f} s, {g['seconds_per_step']:.2f} s per step "
        f"(average; {g['seconds_per_evaluation']:.2f} s per evaluation), {g['wall_s']:.1f} s "
        f"after compilation; L {g['history'][0]:.4g} → "
        f"{np.min(g['history']):.4g}.",
        "",
        f"Nelder-Mead: adaptive, simplex step {nm['simplex_step']}, maxfev {nm['maxfev']}; L "
        f"jitted (compile {nm['compile_s']:.1f} s, not counted), "
        f"{nm['seconds_per_eval_median'] * 1e3:.0f} ms per evaluation (median; "
        f"{nm['seconds_per_eval_in_compiled_loop'] * 1e3:.0f} ms inside a compiled loop of "
        f"{LOOPED} evaluations, where what does not depend on the parameters may be computed "
        "once); "
        f"{nm['evals']} evaluations in {nm['seconds']:.1f} s; L {nm['j_start']:.4g} → "
        f"{nm['j_best']:.4g} (best at evaluation {nm['evals_to_best']}); {nm['message']}",
        "",
        "| L reached | gradient steps | gradient simulations | gradient s | NM evaluations | "
        "NM simulations | NM s | simulations ratio | wall-time ratio |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    t = r.get("timed_to_nm_best")
    for row in r["reach"]:
        lines.append(
            f"| {row['target']:.4g} | {_f(row.get('gradient_steps'), 'd')} | "
            f"{_f(row.get('gradient_simulations'), 'd')} | "
            f"{_f(row.get('gradient_seconds'), '.1f')} | {_f(row.get('nm_evals'), 'd')} | "
            f"{_f(row.get('nm_simulations'), 'd')} | {_f(row.get('nm_seconds'), '.1f')} | "
            f"{_f(row.get('simulations_ratio'), '.1f', '×')} | "
            f"{_f(row.get('wall_time_ratio'), '.1f', '×')} |")
    if t:
        lines += ["", f"Measured directly: the first {t['steps']} steps, run again as one "
                  f"compiled call, take {t['seconds']:.1f} s (L {t['value']:.4g}) against "
                  f"Nelder-Mead's {t['nm_seconds']:.1f} s to its best: "
                  f"**{t['wall_time_ratio']:.1f}× less wall time**."]
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40, help="L-BFGS steps")
    ap.add_argument("--maxfev", type=int, default=2000, help="Nelder-Mead evaluations")
    ap.add_argument("--positions", type=int, default=7, help="positions over the travel")
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: 10 steps, maxfev 300, three positions")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "end_to_end.json"))
    ap.add_argument("--report-only", action="store_true",
                    help="recompute the tables from the measurements already in --out")
    args = ap.parse_args()
    if args.report_only:
        report(args.out)
        return
    if args.quick:
        args.steps, args.maxfev, args.positions = 10, 300, 3
    chunk = 10 if args.steps % 10 == 0 else args.steps
    load0 = loadavg()
    drive, schedule, obj, y = setup(args.positions)
    grad = gradient(schedule, obj, drive, y, args.steps, chunk)
    print("gradient", {k: v for k, v in grad.items() if not isinstance(v, np.ndarray)},
          flush=True)
    release()  # the compiled training programs: memory maps (fdjax._memory)
    nm = derivative_free(schedule, obj, drive, y, args.maxfev)
    print("nelder-mead", {k: v for k, v in nm.items() if not isinstance(v, np.ndarray)},
          flush=True)
    result = {
        "benchmark": "end_to_end", "quick": bool(args.quick), "statistic": "median",
        "setup": {"drive": "fdjax.reference_drive()", "start": "shipped designs' mcm_ata",
                  "objective": "tuning_objective(margin_width=0.01)",
                  "loss": "0.5 (mean + smooth_max(·, 2)) over the positions",
                  "positions_m": y.tolist()},
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                    "jax": jax.__version__, "scipy": scipy.__version__,
                    "optax": optax.__version__},
        "loadavg": {"start": load0, "end": loadavg()},
        "gradient": grad, "derivative_free": nm,
    }
    result["reach"] = reaches(grad, nm, len(y))
    result["timed_to_nm_best"] = timed_to(schedule, obj, drive, y, grad, nm)
    print("timed", result["timed_to_nm_best"], flush=True)
    write_results(args.out, jsonable(result), markdown(result))


def timed_to(schedule, obj, drive, y, grad, nm):
    """The gradient's wall time to Nelder-Mead's best measured directly: the steps it took,
    run again as one compiled chunk (compiled by a first call, then timed)."""
    h = np.minimum.accumulate(np.asarray(grad["history"]))
    hit = np.nonzero(h <= nm["j_best"])[0]
    if not hit.size:
        return None
    k = int(hit[0]) + 1
    kw = dict(positions_m=y, train_gains=True, optimiser=optax.lbfgs(), chunk=k, steps=k)
    release()
    jax.block_until_ready(fdjax.train_schedule(schedule, obj, drive, **kw)[1].history)
    t0 = time.perf_counter()
    _, rec = fdjax.train_schedule(schedule, obj, drive, **kw)
    jax.block_until_ready(rec.history)
    s = time.perf_counter() - t0
    e = int(np.argmax(np.minimum.accumulate(nm["trace"]) <= nm["j_best"])) + 1
    return {"steps": k, "seconds": s, "value": float(np.min(np.asarray(rec.history))),
            "nm_seconds": float(nm["trace_seconds"][e - 1]),
            "wall_time_ratio": float(nm["trace_seconds"][e - 1]) / s}


def reaches(grad, nm, n_positions):
    """The cost of each tuner to the worse of the two bests, and to the gradient's value after
    a tenth, a quarter and half of its steps."""
    h = np.minimum.accumulate(np.asarray(grad["history"]))
    targets = sorted({max(float(h[-1]), nm["j_best"])}
                     | {float(h[max(int(f * len(h)) - 1, 0)]) for f in (0.1, 0.25, 0.5)},
                     reverse=True)
    return [reach(grad, nm, n_positions, t) for t in targets]


def report(out):
    """The derived tables again from a run's measurements (the JSON at ``out``)."""
    import json

    with open(out) as fh:
        r = json.load(fh)
    g, nm = r["gradient"], r["derivative_free"]
    for k in ("history", "evaluations", "simulations"):
        g[k] = np.asarray(g[k])
    for k in ("trace", "trace_seconds"):
        nm[k] = np.asarray(nm[k])
    g.setdefault("seconds_per_evaluation", g["wall_s"] / float(np.sum(g["evaluations"])))
    r["reach"] = reaches(g, nm, len(r["setup"]["positions_m"]))
    write_results(out, jsonable(r), markdown(r))


if __name__ == "__main__":
    main()
