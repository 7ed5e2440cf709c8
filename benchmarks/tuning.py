"""Benchmark: gradient local tuning (fdjax.tune_local) vs a derivative-free tuner (Nelder-Mead).

Both tuners minimise the same objective J(θ, Y) (``fdjax.Objective``: RMS scale error of the
sampled loop over e_ref plus the smooth margin, growth-rate and current penalties) of the
12-parameter double loop (``fdjax.DoubleLoopParameterisation``: gains and one peak + one notch
MCM) on ``fdjax.reference_drive()``, at six table positions Y = 0.1, 0.22, …, 0.7 m, from the
same start: the reference controller with k_v halved (stable at every position; the reference
itself is unstable from 0.5 m).  Motion ``reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0,
j_max=400.0, cycles=1)``, margins on 400 log-spaced frequencies 5–3900 Hz, twin with 6 modes.

1. ``gradient_local``: ``fdjax.tune_local`` (all positions in one vmapped optax run, chunks
   of 25 steps): Adam 0.02 (``--steps`` steps) and L-BFGS (``optax.lbfgs``, zoom line search,
   ``--lbfgs-steps`` steps; each line-search trial is an evaluation of J and its gradient).
   Compilation is timed separately (a warm-up call of one chunk; the main call then reuses
   the compiled chunk); the time per step is the main call's average (its wall time less the
   final evaluation of the terms, compiled).  ``fdjax.tune_newton`` (``--newton-steps``
   trust-region Newton steps with the exact Hessian, all six positions in one vmapped program
   whose steps run in compiled loops; one evaluation of J, its gradient and its Hessian per
   step; a warm-up call compiles every program the main call runs), and the same with the
   exact Hessian every 8 steps and SR1 updates between (``hessian_every=8``, ``--sr1-steps``
   steps).  And the same tuner after 40 steps of ``fdjax.shape_loops`` (the gains raised as far
   as the margin penalties and the poles' barrier allow, no simulation; S's exact Hessian every
   second step, SR1 between; timed after a warm-up, its seconds added to the tuner's), with the
   exact Hessian at the start only and SR1 updates after (``--shaped-steps`` steps, in one
   compiled call: ``chunk`` = its steps).
2. ``derivative_free``: ``scipy.optimize.minimize(method="Nelder-Mead", adaptive=True)`` on θ
   per position, one position after the other, J a jitted function of (θ, Y) (compiled once,
   outside the timing), initial simplex θ0 + 0.1·e_k, at most ``--maxfev`` evaluations.
   And the same simplex compiled, ``fdjax.tune_simplex`` (the same coefficients and initial
   simplex, all positions in one vmapped ``lax.scan``; compiled by a warm-up call, the median
   of three runs), with each gradient tuner's steps, simulations and wall time to its best.
3. For each position: the first gradient step whose running-minimum J reaches Nelder-Mead's
   best J there, as steps, as simulation equivalents (one evaluation of J with its gradient at
   one position = one forward and one reverse pass = 2) and as wall time (steps × measured
   time per step of the six-position run).  The final gradient designs are checked by
   eigenvalues on the default twin (``fdjax.check_stability``) and by their gain headroom
   (``fdjax.gain_headroom``, dB).

Targets: ≥ 20× fewer simulations and ≥ 10× less wall time than the
derivative-free tuner to reach its result, six local tunings within 60 s after compilation.

4. ``end_to_end``: ``fdjax.train_schedule`` (network and common gains, 8 positions per step)
   from a network fitted to the start's MCM: compile time, time per step, simulations.

Usage:  python benchmarks/tuning.py [--steps 300] [--lbfgs-steps 100] [--newton-steps 60]
        [--sr1-steps 150] [--shaped-steps 100] [--maxfev 1500]
        [--e2e-steps 100] [--quick] [--out benchmarks/results/tuning.json]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time

import equinox as eqx
import jax
import numpy as np
import optax
import scipy
import scipy.optimize
from _timing import (  # benchmarks/ is on sys.path when run as a script
    jsonable,
    loadavg,
    median_time,
    nelder_mead,
    write_results,
)

import fdjax

CHUNK = 25
LEARNING_RATE = 0.02
SIMPLEX_STEP = 0.1
SIMS_PER_GRADIENT_STEP = 2  # one forward and one reverse pass per position
HESSIAN_EVERY = 8  # the quasi-Newton variant: the exact Hessian every 8 steps, SR1 between
SHAPE_STEPS = 40  # fdjax.shape_loops steps (no simulation) before the shaped variant's Newton
SHAPE_EVERY = 2  # fdjax.shape_loops: S's exact Hessian every 2 steps, SR1 between
NEWTON_CHUNK = 10  # tune_newton's default: steps per compiled call, rounded up to whole cycles
SIMPLEX_CHUNK = 500  # tune_simplex: evaluations per compiled call (a divisor of --maxfev)
TARGETS = {"simulations_ratio": 20.0, "wall_time_ratio": 10.0, "six_tunings_s": 60.0}


def setup(n_positions=6):
    """The toolkit's tuning problem (module docstring)."""
    drive = fdjax.reference_drive()
    ref_c = fdjax.reference_controller(drive)
    start = eqx.tree_at(lambda c: c.log_kv, ref_c, ref_c.log_kv + math.log(0.5))
    par = fdjax.DoubleLoopParameterisation(fdjax.MCMBounds.for_servo(fdjax.Servo()), ref_c)
    motion = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    obj = fdjax.Objective(motion, np.geomspace(5.0, 3900.0, 400),
                          twin=fdjax.TwinOptions(kept_modes=6))
    positions = np.linspace(0.1, 0.7, 6)
    if n_positions < 6:
        positions = positions[np.round(np.linspace(0, 5, n_positions)).astype(int)]
    return drive, par, obj, positions, start


def rerun_problem(description, result_name):
    """The command line of the scripts that rerun this problem against Nelder-Mead with other
    tuners (``--maxfev``, ``--quick``, ``--out``): (arguments, load average at the start,
    :func:`setup`'s problem on six positions, or two with ``--quick``)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--maxfev", type=int, default=1500)
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: two positions, maxfev 200, a sixth of the steps")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  result_name))
    args = ap.parse_args()
    if args.quick:
        args.maxfev = 200
    return args, loadavg(), setup(2 if args.quick else 6)


def _outcome(r, per_step):
    """A tuner's run (a LocalTuning) as the benchmark records it: the time per step, the
    history and the best designs' terms."""
    h = np.asarray(r.history)
    return {
        "seconds_per_step": per_step, "steps_per_second": 1.0 / per_step,
        "history": h, "best_theta": np.asarray(r.best_theta),
        "j_best": np.asarray(r.terms.total), "stable_terms": np.asarray(r.terms.stable),
        "rms_error_m": np.asarray(r.terms.rms_error_m),
        "margin_penalty": np.asarray(r.terms.margin_penalty),
        "growth_rate": np.asarray(r.terms.growth_rate),
        "peak_current_a": np.asarray(r.terms.peak_current_a),
        "finite_history": bool(np.all(np.isfinite(h))),
    }


# ----------------------------------------------------------------------------- gradient
def final_terms_seconds(par, obj, drive, r):
    """The time of a tuner's last act, the terms of J at its best designs (one compiled
    evaluation at every position, as the tuners run it): taken off a timed call, so that what
    is left is its steps.  Compiled before it is timed (median of three)."""
    key = (id(par), id(obj), id(drive))
    if key not in _TERMS:
        _TERMS[key] = eqx.filter_jit(jax.vmap(
            lambda th, p: obj(par.to_controller(th), drive, p).total))
    fn = _TERMS[key]
    return median_time(lambda: fn(r.best_theta, r.positions_m), 3)[0]


_TERMS = {}


def gradient_local(par, obj, drive, positions, start, steps, method="adam"):
    """tune_local with compile time, time per step, the history of J and the evaluations of
    J with its gradient per step (1 for Adam, the line search's trials for L-BFGS)."""
    opt = optax.adam(LEARNING_RATE) if method == "adam" else optax.lbfgs()
    # the warm-up compiles every chunk length the main call uses (a shorter last chunk is
    # another program), so that the main call's steps are all compiled code
    tail = steps % CHUNK if steps > CHUNK else 0
    warm_steps = min(CHUNK, steps) + tail
    t0 = time.perf_counter()
    warm = fdjax.tune_local(par, obj, drive, positions, start, steps=warm_steps,
                            optimiser=opt, chunk=CHUNK)
    jax.block_until_ready(warm.history)
    warm_s = time.perf_counter() - t0  # compilation + warm_steps steps + the final terms
    t0 = time.perf_counter()
    r = fdjax.tune_local(par, obj, drive, positions, start, steps=steps, optimiser=opt,
                         chunk=CHUNK)
    jax.block_until_ready((r.history, r.terms.total))
    wall_s = time.perf_counter() - t0  # every step compiled, plus the final terms
    # the final terms: one vmapped evaluation of J at the best θ (compiled in the warm-up)
    terms_s = final_terms_seconds(par, obj, drive, r)
    steps_s = max(wall_s - terms_s, 0.0)
    # the average: a line search's steps are not all alike (more trials late on), so the time
    # per step is the main call's, not a chunk's
    per_step = steps_s / steps
    compile_s = max(warm_s - warm_steps * per_step - terms_s, 0.0)
    return {
        "steps": int(steps), "chunk": CHUNK,
        "optimiser": f"optax.adam({LEARNING_RATE})" if method == "adam" else "optax.lbfgs()",
        "tuner": "tune_local",
        "sims_rows": SIMS_PER_GRADIENT_STEP * np.asarray(r.evaluations),
        "evaluations": np.asarray(r.evaluations),
        "compile_s": compile_s, "warmup_call_s": warm_s, "main_call_wall_s": wall_s,
        "steps_s": steps_s, "final_terms_s": terms_s,
        **_outcome(r, per_step),
    }


def newton_local(par, obj, drive, positions, start, steps, every=1, radius=0.3,
                 max_radius=5.0, shrink=0.25, hessian="full", shape_steps=0,
                 chunk=NEWTON_CHUNK):
    """fdjax.tune_newton: one evaluation of J with its gradient and Hessian per step and
    position (with ``hessian="margins"``: J with its gradient, and the Hessian of the margin
    term alone, which needs no simulation).  A warm-up call of 2 steps compiles the programs;
    the main call is timed whole, its final terms apart; the start's evaluation counts as a
    step (history row 0)."""
    trust = dict(radius=radius, max_radius=max_radius, shrink=shrink, hessian=hessian)
    shape_s = 0.0
    if shape_steps:
        # fdjax.shape_loops first (no simulation): warmed up, then timed; its seconds count in
        # the tuner's wall time
        fdjax.shape_loops(par, obj, drive, positions, start, steps=shape_steps,
                          hessian_every=SHAPE_EVERY)
        shaped = fdjax.shape_loops(par, obj, drive, positions, start, steps=shape_steps,
                                   hessian_every=SHAPE_EVERY)
        start, shape_s = shaped.theta, shaped.seconds
    t0 = time.perf_counter()
    # the warm-up compiles the programs the main call runs (their step counts are traced):
    # a cycle of `every` steps (with every > 10 steps, tune_newton's chunk, gradient steps in
    # calls of 10 and the exact step alone) and the gradient steps after it; with the exact
    # Hessian once in a longer run than the main call's (at the start only), gradient steps
    warm_steps = every + 1 if every <= steps else NEWTON_CHUNK + 1
    warm = fdjax.tune_newton(par, obj, drive, positions, start, steps=warm_steps,
                             hessian_every=every, chunk=chunk, **trust)
    jax.block_until_ready(warm.history)
    warm_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    r = fdjax.tune_newton(par, obj, drive, positions, start, steps=steps, hessian_every=every,
                          chunk=chunk, **trust)
    jax.block_until_ready((r.history, r.terms.total))
    wall_s = time.perf_counter() - t0
    terms_s = final_terms_seconds(par, obj, drive, r)
    steps_s = max(wall_s - terms_s, 0.0)
    per_step = steps_s / (steps + 1)
    h = np.asarray(r.history)
    n_par = len(par.names)
    every_text = ("" if every == 1 else f" every {every} steps, SR1 between" if every <= steps
                  else " at the start only, SR1 after")
    # row 0: the start, with the Hessian; row k: step k, with the Hessian when every | k
    # (the margins' Hessian alone runs no simulation)
    with_h = np.array([k % every == 0 and hessian == "full" for k in range(steps + 1)])
    sims = np.where(with_h, 2 + 2 * n_par, 2)[:, None] * np.ones((1, h.shape[1]), int)
    return {
        "steps": int(steps), "tuner": "tune_newton",
        "chunk": -(-chunk // every) * every if every <= chunk else chunk,
        "optimiser": "trust-region Newton, exact Hessian"
                     + (" of the margin term every step, SR1 for the rest of J"
                        if hessian == "margins" else " every step" if every == 1 else every_text)
                     + f" (radius {radius:g}, max {max_radius:g}, shrink {shrink:g})"
                     + (f", after {shape_steps} steps of fdjax.shape_loops (no simulation; "
                        f"its exact Hessian every {SHAPE_EVERY} steps, SR1 between; "
                        f"{shape_s:.2f} s, counted in the steps' time)" if shape_steps else ""),
        "shape_steps": int(shape_steps), "shape_hessian_every": SHAPE_EVERY, "shape_s": shape_s,
        "tune_chunk": int(chunk),
        "trust_region": trust,
        "hessian_every": int(every), "sims_rows": sims,
        "evaluations": np.ones_like(h, dtype=int),
        "compile_s": max(warm_s - (warm_steps + 1) * per_step - terms_s, 0.0),
        "warmup_call_s": warm_s,
        "main_call_wall_s": wall_s, "steps_s": steps_s + shape_s, "final_terms_s": terms_s,
        **_outcome(r, per_step),
    }


# ----------------------------------------------------------------------------- end to end
def end_to_end(par, obj, drive, start, steps, batch=8):
    """fdjax.train_schedule from a network fitted to the start's MCM at six positions (the
    schedule's network and common feedback gains trained), ``batch`` positions per step:
    compile time apart, time per step, simulation equivalents (2 per position per step)."""
    bounds = par.mcm
    target = np.tile(np.asarray(bounds.from_mcm(start.mcm)), (6, 1))
    net, _ = fdjax.fit_network(fdjax.ATANetwork(drive.travel_m, width=8,
                                                key=jax.random.PRNGKey(0)),
                               np.linspace(0.1, 0.7, 6), target, steps=2000)
    sched = fdjax.ScheduledLoop(par.to_controller(par.from_controller(start)), net, bounds)
    steps = max(steps, 2 * CHUNK)
    t0 = time.perf_counter()
    _, rec = fdjax.train_schedule(sched, obj, drive, steps=steps, batch=batch, chunk=CHUNK,
                                  train_gains=True, optimiser=optax.adam(3e-3))
    wall_s = time.perf_counter() - t0
    per_step = rec.seconds / (steps - CHUNK)  # descend times the chunks after the first
    h = np.asarray(rec.history)
    return {"steps": steps, "batch": batch, "chunk": CHUNK, "optimiser": "optax.adam(3e-3)",
            "wall_s": wall_s, "compile_s": max(wall_s - steps * per_step, 0.0),
            "seconds_per_step": per_step, "steps_s": steps * per_step,
            "simulations": SIMS_PER_GRADIENT_STEP * batch * steps,
            "objective_first": float(h[0]), "objective_last": float(h[-1]),
            "finite_history": bool(np.all(np.isfinite(h)))}


# ----------------------------------------------------------------------------- Nelder-Mead
def derivative_free(par, obj, drive, positions, start, maxfev):
    """Nelder-Mead per position on the jitted J(θ, Y), from θ0 = par.from_controller(start)."""
    j_fn = eqx.filter_jit(lambda th, y: obj(par.to_controller(th), drive, y).total)
    theta0 = np.asarray(par.from_controller(start), np.float64)
    n = theta0.size
    simplex = np.vstack([theta0, theta0 + SIMPLEX_STEP * np.eye(n)])
    y_first = jax.numpy.asarray(positions[0])
    t0 = time.perf_counter()
    jax.block_until_ready(j_fn(jax.numpy.asarray(theta0), y_first))
    compile_s = time.perf_counter() - t0
    t_eval, _ = median_time(lambda: j_fn(jax.numpy.asarray(theta0), y_first), 5)
    out = []
    for p in positions:
        y = jax.numpy.asarray(p)
        res, tr, stamps, bad, total_s = nelder_mead(
            lambda th, y=y: j_fn(jax.numpy.asarray(th), y), theta0, simplex, maxfev)
        k_best = int(np.argmin(tr))
        out.append({
            "position_m": float(p), "j_start": float(tr[0]), "j_best": float(tr[k_best]),
            "theta_best": np.asarray(res.x) if res.fun <= tr[k_best] else None,
            "evals": int(tr.size), "evals_to_best": k_best + 1, "seconds": total_s,
            "seconds_to_best": float(stamps[k_best]), "non_finite_evals": bad,
            "message": str(res.message), "trace": tr,
            "trace_seconds": stamps,
        })
    return {"compile_s": compile_s, "seconds_per_eval_median": t_eval,
            "simplex_step": SIMPLEX_STEP, "maxfev": int(maxfev), "positions": out}


def compiled_simplex(par, obj, drive, positions, start, maxfev, scipy_nm):
    """The same adaptive simplex compiled: ``fdjax.tune_simplex`` (scipy's coefficients and
    initial simplex, all positions in one vmapped ``lax.scan``) with ``maxfev`` evaluations per
    position.  A warm-up call compiles the chunk; the main call is timed whole (the median of
    three), its final terms apart.  Its trace is compared with scipy's (the same algorithm:
    the same points)."""
    chunk = math.gcd(int(maxfev), SIMPLEX_CHUNK)
    t0 = time.perf_counter()
    warm = fdjax.tune_simplex(par, obj, drive, positions, start, evaluations=chunk,
                              step=SIMPLEX_STEP, chunk=chunk)
    jax.block_until_ready(warm.history)
    warm_s = time.perf_counter() - t0

    def run():
        return fdjax.tune_simplex(par, obj, drive, positions, start, evaluations=maxfev,
                                  step=SIMPLEX_STEP, chunk=chunk)

    r = run()
    wall_s, walls = median_time(lambda: (lambda t: (t.history, t.terms.total))(run()), 3,
                                warmup=False)
    terms_s = final_terms_seconds(par, obj, drive, r)
    per_eval = max(wall_s - terms_s, 0.0) / maxfev  # one evaluation at every position
    h = np.asarray(r.history)
    rows = []
    for i, (p, d) in enumerate(zip(positions, scipy_nm["positions"])):
        k = int(np.argmin(h[:, i]))
        sc = np.asarray(d["trace"])
        n = min(sc.size, h.shape[0])
        rows.append({"position_m": float(p), "j_best": float(h[k, i]), "evals_to_best": k + 1,
                     "scipy_j_best": d["j_best"], "scipy_evals_to_best": d["evals_to_best"],
                     "trace_max_rel_diff_from_scipy": float(np.max(
                         np.abs(h[:n, i] - sc[:n]) / np.abs(sc[:n])))})
    k_all = max(r_["evals_to_best"] for r_ in rows)
    return {"tuner": "fdjax.tune_simplex", "evaluations": int(maxfev), "chunk": chunk,
            "warmup_call_s": warm_s, "compile_s": max(warm_s - chunk * per_eval - terms_s, 0.0),
            "main_call_wall_s": wall_s, "main_call_walls_s": walls, "final_terms_s": terms_s,
            "seconds_per_evaluation_all_positions": per_eval,
            "evals_to_best_all": k_all, "seconds_to_best_all": k_all * per_eval,
            "history": h, "positions": rows}


def against_compiled(grad, cs, totals):
    """A gradient tuner against the compiled simplex: the steps to reach its best at each
    position, the simulations (its evaluations to its best, summed, over the tuner's) and the
    wall time (its evaluations to its best at the slowest position × its time per evaluation,
    over the tuner's steps to reach every position × the time per step; for a Newton tuner
    that reaches every position at the step measured against scipy's simplex, that measured
    time)."""
    run_min = np.minimum.accumulate(grad["history"], axis=0)
    sims = _sims(grad)
    steps, grad_sims = [], 0
    for i, d in enumerate(cs["positions"]):
        hit = np.nonzero(run_min[:, i] <= d["j_best"])[0]
        k = int(hit[0]) + 1 if hit.size else None
        steps.append(k)
        grad_sims += 0 if k is None else int(sims[k - 1, i])
    out = {"steps_to_reach": steps, "all_positions_reached": None not in steps}
    if out["all_positions_reached"]:
        k_max = max(steps)
        seconds = k_max * grad["seconds_per_step"]
        measured = (totals.get("gradient_steps_to_reach_all") == k_max
                    and "gradient_seconds_to_reach_all_averaged" in totals)
        if measured:
            seconds = totals["gradient_seconds_to_reach_all"]
        out.update(gradient_sims=grad_sims, gradient_seconds=seconds,
                   gradient_seconds_measured=measured,
                   simulations_ratio=sum(d["evals_to_best"] for d in cs["positions"])
                   / grad_sims,
                   wall_time_ratio=cs["seconds_to_best_all"] / seconds)
    return out


# ----------------------------------------------------------------------------- checks
def verify(par, drive, positions, thetas):
    """Eigenvalue stability on the default twin and the gain headroom (dB) of designs."""
    rows = []
    for p, th in zip(positions, thetas):
        c = par.to_controller(jax.numpy.asarray(th))
        st = fdjax.check_stability(c, drive, position_m=float(p))
        g = float(fdjax.gain_headroom(c, drive, position_m=float(p)))
        rows.append({"position_m": float(p), "stable": bool(np.asarray(st.stable)),
                     "growth_rate_per_s": float(np.asarray(st.growth_rate)),
                     "min_damping": float(np.asarray(st.min_damping)),
                     "gain_headroom": g,
                     "gain_headroom_db": 20 * math.log10(g) if g > 0 else -math.inf,
                     "message": str(st.message)})
    return rows


def _sims(grad):
    """Simulation equivalents spent up to each step, per position: 2 per evaluation of J
    with its gradient (one forward, one reverse pass), 2 + 2p with its Hessian too (p
    forward-over-reverse columns)."""
    return np.cumsum(np.asarray(grad["sims_rows"]), axis=0)


def compare(grad, nm, positions):
    """Per position: the first gradient step whose running-min J reaches NM's best J."""
    h = grad["history"]
    run_min = np.minimum.accumulate(h, axis=0)
    sims = _sims(grad)
    rows = []
    for i, (p, d) in enumerate(zip(positions, nm["positions"])):
        hit = np.nonzero(run_min[:, i] <= d["j_best"])[0]
        k = int(hit[0]) + 1 if hit.size else None  # steps taken
        rows.append({
            "position_m": float(p), "j_start_gradient": float(h[0, i]),
            "j_start_nm": d["j_start"], "j_gradient_best": float(grad["j_best"][i]),
            "j_nm_best": d["j_best"], "nm_evals": d["evals"],
            "nm_evals_to_best": d["evals_to_best"], "nm_seconds": d["seconds"],
            "nm_seconds_to_best": d["seconds_to_best"], "nm_message": d["message"],
            "gradient_steps_to_reach": k,
            "gradient_sims_to_reach": None if k is None else int(sims[k - 1, i]),
            "gradient_seconds_to_reach": None if k is None else k * grad["seconds_per_step"],
            "simulations_ratio": None if k is None
            else d["evals_to_best"] / int(sims[k - 1, i]),
            "wall_time_ratio_amortised": None if k is None
            else d["seconds_to_best"] / (k * grad["seconds_per_step"] / len(positions)),
        })
    reached = all(r["gradient_steps_to_reach"] is not None for r in rows)
    totals = {"all_positions_reached": reached,
              "nm_evals_to_best": sum(r["nm_evals_to_best"] for r in rows),
              "nm_evals": sum(r["nm_evals"] for r in rows),
              "nm_seconds_to_best": sum(r["nm_seconds_to_best"] for r in rows),
              "nm_seconds": sum(r["nm_seconds"] for r in rows)}
    if reached:
        k_max = max(r["gradient_steps_to_reach"] for r in rows)
        sims = sum(r["gradient_sims_to_reach"] for r in rows)
        totals.update(
            gradient_sims_to_reach=sims, gradient_steps_to_reach_all=k_max,
            gradient_seconds_to_reach_all=k_max * grad["seconds_per_step"],
            simulations_ratio=totals["nm_evals_to_best"] / sims,
            wall_time_ratio=totals["nm_seconds_to_best"] / (k_max * grad["seconds_per_step"]))
    return rows, totals


def compare_common(grad, nm, positions):
    """Per position: the cost of each tuner to reach the same value, the worse of the two
    bests (a value both reach): gradient steps (× 2 simulations) and Nelder-Mead evaluations
    until their running minimum is at or below it."""
    h = grad["history"]
    run_min = np.minimum.accumulate(h, axis=0)
    sims = _sims(grad)
    rows = []
    for i, (p, d) in enumerate(zip(positions, nm["positions"])):
        target = max(float(run_min[-1, i]), d["j_best"])
        k = int(np.nonzero(run_min[:, i] <= target)[0][0]) + 1
        nm_min = np.minimum.accumulate(np.asarray(d["trace"]))
        e = int(np.nonzero(nm_min <= target)[0][0]) + 1
        rows.append({"position_m": float(p), "target_j": target, "gradient_steps": k,
                     "gradient_sims": int(sims[k - 1, i]), "nm_evals": e,
                     "nm_seconds": float(np.asarray(d["trace_seconds"])[e - 1]),
                     "simulations_ratio": e / int(sims[k - 1, i])})
    k_max = max(r["gradient_steps"] for r in rows)
    totals = {"gradient_sims": sum(r["gradient_sims"] for r in rows),
              "nm_evals": sum(r["nm_evals"] for r in rows),
              "gradient_seconds_all": k_max * grad["seconds_per_step"],
              "nm_seconds": sum(r["nm_seconds"] for r in rows)}
    totals["simulations_ratio"] = totals["nm_evals"] / totals["gradient_sims"]
    totals["wall_time_ratio"] = totals["nm_seconds"] / totals["gradient_seconds_all"]
    return rows, totals


# ----------------------------------------------------------------------------- report
def _f(x, fmt):
    return "not reached" if x is None else format(x, fmt)


METHODS = {"adam": f"Adam({LEARNING_RATE})", "lbfgs": "L-BFGS (optax.lbfgs, zoom line search)",
           "newton": "trust-region Newton with the exact Hessian (fdjax.tune_newton)",
           "newton_sr1": "trust-region Newton, exact Hessian every 8 steps, SR1 between "
                         "(fdjax.tune_newton(hessian_every=8))",
           "shaped_sr1": f"loop shaping without simulation ({SHAPE_STEPS} steps of "
                         f"fdjax.shape_loops, hessian_every={SHAPE_EVERY}), then trust-region "
                         "Newton with the exact Hessian at the start only, SR1 after"}


def markdown(result):
    nm = result["derivative_free"]
    first = next(iter(result["methods"].values()))
    n_pos = len(first["per_position"])
    lines = [
        "# Tuning benchmark: gradient local tuning vs Nelder-Mead",
        "",
        f"Machine: {result['machine']['platform']}, {result['machine']['cpu_count']} CPUs "
        f"(shared), jax {result['machine']['jax']}, scipy {result['machine']['scipy']}.  Load "
        f"average: {result['loadavg']}.  Problem: `fdjax.reference_drive()`, 12-parameter "
        "double loop + MCM, reference controller with k_v halved as the start, "
        f"{n_pos} positions, J = `fdjax.Objective` (1 mm reciprocating stroke, 400 "
        "frequencies, 6 kept modes).",
        "",
        "Nelder-Mead (`scipy.optimize.minimize`, adaptive, "
        f"simplex step {nm['simplex_step']}, maxfev {nm['maxfev']}): J jitted (compile "
        f"{nm['compile_s']:.1f} s, not counted), {nm['seconds_per_eval_median'] * 1e3:.1f} ms "
        "per evaluation (median), positions one after the other.",
        "",
        "Counting: one Nelder-Mead evaluation = 1 simulation (forward J).  One evaluation of J "
        f"with its gradient at one position = {SIMS_PER_GRADIENT_STEP} simulation equivalents "
        "(1 forward + 1 reverse pass): one per Adam step, one per line-search trial of L-BFGS "
        "(its accepted trial's value and gradient are the next step's), plus the start's.  "
        "One evaluation of J with its gradient and its Hessian (12 forward-over-reverse "
        "columns) = 2 + 2·12 = 26 (trust-region Newton, one per step, the start's counted "
        "as a step; with the Hessian every 8 steps, the others count 2).  "
        "\"Steps to reach\" = the first step at which the running minimum of the gradient "
        "history is ≤ Nelder-Mead's best J at that position; Nelder-Mead is charged its "
        "evaluations (and wall time) up to its own best, not its whole budget.  Gradient "
        "seconds to reach = steps × time per step of the six-position run (all positions "
        "advance together); in the totals of the Newton tuners, when every position reaches "
        "it, the measured time of a run of exactly those steps (median of three).",
    ]
    for method, m in result["methods"].items():
        lines += _method_markdown(method, m, n_pos)
    lines += _compiled_markdown(result, n_pos)
    e = result["end_to_end"]
    lines += ["", "## End to end", "", f"`train_schedule`, network and common gains, batch of "
              f"{e['batch']} positions drawn over the travel, {e['optimiser']}: compile "
              f"{e['compile_s']:.1f} s, {e['seconds_per_step'] * 1e3:.0f} ms per step, "
              f"{e['steps_s']:.1f} s for {e['steps']} steps after compilation "
              f"({e['simulations']} simulation equivalents); batch objective "
              f"{e['objective_first']:.4g} → {e['objective_last']:.4g}."]
    return "\n".join(lines) + "\n"


def _compiled_markdown(result, n_pos):
    nm, cs = result["derivative_free"], result["compiled_simplex"]
    rows = cs["positions"]
    diff = max(r["trace_max_rel_diff_from_scipy"] for r in rows)
    lines = [
        "", "## The same simplex, compiled (`fdjax.tune_simplex`)", "",
        "scipy's Nelder-Mead calls the jitted J once per evaluation, and every call "
        "recomputes what does not depend on θ (the twin at the position, its zero-order hold "
        "and its response on the frequency grid, the reference's samples).  "
        "`fdjax.tune_simplex` runs the same adaptive simplex (the same coefficients and "
        f"initial simplex) for all {n_pos} positions in one vmapped `lax.scan`, "
        f"{cs['chunk']} evaluations per compiled call, which computes that part once: "
        f"{cs['evaluations']} evaluations per position in "
        f"{cs['main_call_wall_s'] - cs['final_terms_s']:.1f} s after a "
        f"{cs['compile_s']:.1f} s compilation (the median of three runs) "
        f"({cs['seconds_per_evaluation_all_positions'] * 1e3:.2f} ms per evaluation of all "
        f"{n_pos} positions, against {nm['seconds_per_eval_median'] * 1e3:.1f} ms for one "
        f"position by scipy).  Its values follow scipy's to {diff:.1e} (largest relative "
        "difference over the traces); its best J "
        + ", ".join(f"{r['j_best']:.4g}" for r in rows) + " after "
        + ", ".join(str(r["evals_to_best"]) for r in rows) + " evaluations (scipy: "
        + ", ".join(str(r["scipy_evals_to_best"]) for r in rows) + "); every position at its "
        f"best after {cs['evals_to_best_all']} evaluations, "
        f"{cs['seconds_to_best_all']:.2f} s.",
        "",
        f"Each tuner against it (the wall time of both compiled, {n_pos} positions together):",
        "",
        "| tuner | steps to reach its best, per position | simulations ratio | gradient s "
        "| wall-time ratio |",
        "|---|---|---|---|---|",
    ]
    for method, m in result["methods"].items():
        a = m["against_compiled_simplex"]
        steps = ", ".join("—" if k is None else str(k) for k in a["steps_to_reach"])
        if a["all_positions_reached"]:
            how = " (measured)" if a["gradient_seconds_measured"] else ""
            lines.append(f"| {METHODS[method]} | {steps} | {a['simulations_ratio']:.1f}× | "
                         f"{a['gradient_seconds']:.2f}{how} | {a['wall_time_ratio']:.1f}× |")
        else:
            lines.append(f"| {METHODS[method]} | {steps} | not reached everywhere | — | — |")
    return lines


def _method_markdown(method, m, n_pos):
    g, t, rows = m["gradient"], m["totals"], m["per_position"]
    lines = [
        "", f"## Gradient: {METHODS[method]}", "",
        f"`{g['tuner']}`, {g['steps']} steps of {g['optimiser']}, all positions in one vmapped "
        f"program; compile {g['compile_s']:.1f} s, {g['seconds_per_step'] * 1e3:.0f} ms "
        f"per step ({g['steps_per_second']:.2f} steps/s, {n_pos} positions per step), "
        f"{g['steps_s']:.1f} s for all steps after compilation "
        f"(+ {g['final_terms_s'] * 1e3:.0f} ms for {g['tuner']}'s final terms); "
        f"{int(np.sum(g['evaluations']))} evaluations of J with its derivatives in all "
        f"({int(np.sum(g['sims_rows']))} simulation equivalents).",
        "",
        "| position | J start | J gradient best | J NM best | NM evals (to best) | NM s (to best) "
        "| grad steps to reach | grad sims to reach | grad s to reach (steps × time per step) "
        "| sims ratio |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['position_m']:.2f} m | {r['j_start_gradient']:.4g} | "
            f"{r['j_gradient_best']:.4g} | {r['j_nm_best']:.4g} | {r['nm_evals']} "
            f"({r['nm_evals_to_best']}) | {r['nm_seconds']:.1f} ({r['nm_seconds_to_best']:.1f})"
            f" | {_f(r['gradient_steps_to_reach'], 'd')} | "
            f"{_f(r['gradient_sims_to_reach'], 'd')} | "
            f"{_f(r['gradient_seconds_to_reach'], '.1f')} | "
            f"{_f(r['simulations_ratio'], '.1f')}{'×' if r['simulations_ratio'] else ''} |")
    lines += ["", "| target | measured | verdict |", "|---|---|---|"]
    for key, label in (("simulations_ratio", "≥ 20× fewer simulations than NM (all positions)"),
                       ("wall_time_ratio", "≥ 10× less wall time than NM (all positions)")):
        v = t.get(key)
        verdict = "missed (not reached at every position)" if v is None else (
            "met" if v >= TARGETS[key] else "missed")
        lines.append(f"| {label} | {_f(v, '.1f')}{'×' if v else ''} | {verdict} |")
    six = g["steps_s"]
    lines.append(f"| six local tunings ({g['steps']} steps) within 60 s after compilation | "
                 f"{six:.1f} s | {'met' if six <= 60 and n_pos == 6 else 'missed'}"
                 f"{'' if n_pos == 6 else ' (quick run: not six positions)'} |")
    if t["all_positions_reached"]:
        lines += ["", f"Totals: NM {t['nm_evals_to_best']} evaluations to its best "
                  f"({t['nm_evals']} in all), {t['nm_seconds_to_best']:.1f} s to its best "
                  f"({t['nm_seconds']:.1f} s in all); gradient {t['gradient_sims_to_reach']} "
                  f"simulation equivalents, {t['gradient_steps_to_reach_all']} steps = "
                  f"{t['gradient_seconds_to_reach_all']:.1f} s until every position has "
                  "reached NM's best"
                  + (" (measured: the median of three runs of exactly those steps)."
                     if "gradient_seconds_to_reach_all_averaged" in t else ".")]
    c_rows, c_tot = m["common_value"], m["common_value_totals"]
    lines += ["", "To the same objective value (the worse of the two tuners' bests at each "
              "position, a value both reach): simulations and wall time of each until its "
              "running minimum is there.", "",
              "| position | J target | grad steps | grad sims | NM evals | NM s | sims ratio |",
              "|---|---|---|---|---|---|---|"]
    for r in c_rows:
        lines.append(f"| {r['position_m']:.2f} m | {r['target_j']:.4g} | "
                     f"{r['gradient_steps']} | {r['gradient_sims']} | {r['nm_evals']} | "
                     f"{r['nm_seconds']:.1f} | {r['simulations_ratio']:.1f}× |")
    how = ("measured: the median of three runs of exactly those steps"
           if c_tot["gradient_seconds_measured"]
           else "steps × the time per step")
    lines += ["", f"All positions: gradient {c_tot['gradient_sims']} simulation equivalents "
              f"and {c_tot['gradient_seconds_all']:.1f} s (six positions together; {how}); "
              f"Nelder-Mead {c_tot['nm_evals']} evaluations and {c_tot['nm_seconds']:.1f} s: "
              f"**{c_tot['simulations_ratio']:.1f}× fewer simulations, "
              f"{c_tot['wall_time_ratio']:.1f}× less wall time**."]
    lines += ["", "Final gradient designs (best θ), eigenvalues on the default twin:", "",
              "| position | stable | growth rate (1/s) | gain headroom |", "|---|---|---|---|"]
    for v in m["verification"]:
        lines.append(f"| {v['position_m']:.2f} m | {v['stable']} | "
                     f"{v['growth_rate_per_s']:.3g} | {v['gain_headroom_db']:.1f} dB |")
    return lines


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300, help="Adam steps")
    ap.add_argument("--lbfgs-steps", type=int, default=100, help="L-BFGS steps")
    ap.add_argument("--newton-steps", type=int, default=60, help="trust-region Newton steps")
    ap.add_argument("--sr1-steps", type=int, default=150,
                    help=f"trust-region Newton steps with the Hessian every {HESSIAN_EVERY}")
    ap.add_argument("--shaped-steps", type=int, default=100,
                    help=f"trust-region Newton steps after {SHAPE_STEPS} steps of "
                         "fdjax.shape_loops (the exact Hessian at the start only, SR1 after)")
    ap.add_argument("--maxfev", type=int, default=1500)
    ap.add_argument("--e2e-steps", type=int, default=100,
                    help="end-to-end training steps (batch of 8 positions)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: 60 (20) steps, maxfev 200, two positions")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "tuning.json"))
    args = ap.parse_args()
    if args.quick:
        args.steps, args.lbfgs_steps, args.maxfev, args.e2e_steps = 60, 20, 200, 50
        args.newton_steps, args.sr1_steps, args.shaped_steps = 10, 16, 16

    load0 = loadavg()
    drive, par, obj, positions, start = setup(2 if args.quick else 6)
    grads = {}
    for method, steps in (("adam", args.steps), ("lbfgs", args.lbfgs_steps)):
        grads[method] = gradient_local(par, obj, drive, positions, start, steps, method)
        print(method, {k: v for k, v in grads[method].items()
                       if not isinstance(v, np.ndarray)}, flush=True)
    for name, steps, every, shape in (("newton", args.newton_steps, 1, 0),
                                      ("newton_sr1", args.sr1_steps, HESSIAN_EVERY, 0),
                                      ("shaped_sr1", args.shaped_steps, args.shaped_steps + 1,
                                       SHAPE_STEPS)):
        # the shaped variant's SR1 steps in one compiled call (chunk = its steps)
        grads[name] = newton_local(par, obj, drive, positions, start, steps, every,
                                   shape_steps=shape,
                                   chunk=steps if shape else NEWTON_CHUNK)
        print(name, {k: v for k, v in grads[name].items()
                     if not isinstance(v, np.ndarray)}, flush=True)
    nm = derivative_free(par, obj, drive, positions, start, args.maxfev)
    print("nelder-mead", [(d["position_m"], d["j_best"], d["evals"], d["seconds"])
                          for d in nm["positions"]], flush=True)
    compiled = compiled_simplex(par, obj, drive, positions, start, args.maxfev, nm)
    print("compiled simplex", {k: v for k, v in compiled.items()
                               if k not in ("history", "positions")}, flush=True)
    e2e = end_to_end(par, obj, drive, start, args.e2e_steps)
    print("end to end", e2e, flush=True)
    methods = {}
    for method, grad in grads.items():
        rows, totals = compare(grad, nm, positions)
        if grad["tuner"] == "tune_newton" and totals["all_positions_reached"]:
            # the wall time to reach every position measured, not averaged: the median of
            # three runs of exactly the steps needed (row k of the history is step k; the
            # start is row 0), the final terms' time taken off
            k = totals["gradient_steps_to_reach_all"] - 1

            def run(k=k, grad=grad):
                th = start
                if grad["shape_steps"]:
                    th = fdjax.shape_loops(par, obj, drive, positions, start,
                                           steps=grad["shape_steps"],
                                           hessian_every=grad["shape_hessian_every"]).theta
                r = fdjax.tune_newton(par, obj, drive, positions, th, steps=max(k, 1),
                                      hessian_every=grad["hessian_every"],
                                      chunk=grad["tune_chunk"])
                return r.history, r.terms.total

            t_run, t_runs = median_time(run, 3, warmup=False)
            measured = t_run - grad["final_terms_s"]
            totals["gradient_seconds_to_reach_all_runs"] = t_runs
            totals["gradient_seconds_to_reach_all_averaged"] = totals[
                "gradient_seconds_to_reach_all"]
            totals["gradient_seconds_to_reach_all"] = measured
            totals["wall_time_ratio"] = totals["nm_seconds_to_best"] / measured
        common, common_totals = compare_common(grad, nm, positions)
        common_totals["gradient_seconds_measured"] = False
        if ("gradient_seconds_to_reach_all_averaged" in totals and max(
                r["gradient_steps"] for r in common) == totals["gradient_steps_to_reach_all"]):
            # the same steps as the run measured above: the same seconds (one definition)
            common_totals["gradient_seconds_all_averaged"] = common_totals[
                "gradient_seconds_all"]
            common_totals["gradient_seconds_all"] = totals["gradient_seconds_to_reach_all"]
            common_totals["wall_time_ratio"] = (common_totals["nm_seconds"]
                                                / common_totals["gradient_seconds_all"])
            common_totals["gradient_seconds_measured"] = True
        methods[method] = {
            "gradient": grad, "per_position": rows, "totals": totals,
            "against_compiled_simplex": against_compiled(grad, compiled, totals),
            "common_value": common, "common_value_totals": common_totals,
            "verification": verify(par, drive, positions, grad["best_theta"]),
            "targets": {
                "simulations_ratio": {"value": totals.get("simulations_ratio"),
                                      "target": TARGETS["simulations_ratio"]},
                "wall_time_ratio": {"value": totals.get("wall_time_ratio"),
                                    "target": TARGETS["wall_time_ratio"]},
                "six_tunings_s": {"value": grad["steps_s"],
                                  "target": TARGETS["six_tunings_s"]},
            }}
        for k, v in methods[method]["targets"].items():
            val = v["value"]
            v["met"] = None if val is None else bool(
                val <= v["target"] if k == "six_tunings_s" else val >= v["target"])
    nm_verification = None
    nm_thetas = [d["theta_best"] for d in nm["positions"]]
    if all(th is not None for th in nm_thetas):
        nm_verification = verify(par, drive, positions, nm_thetas)

    result = {
        "benchmark": "tuning", "quick": bool(args.quick), "statistic": "median",
        "setup": {"drive": "fdjax.reference_drive()",
                  "start": "reference_controller(drive) with k_v × 0.5",
                  "parameterisation": "DoubleLoopParameterisation(MCMBounds.for_servo(Servo()), "
                                      "reference_controller(drive))",
                  "reference": "reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, "
                               "cycles=1)",
                  "objective": "Objective(motion, geomspace(5, 3900, 400), "
                               "twin=TwinOptions(kept_modes=6))",
                  "positions_m": positions.tolist(),
                  "theta_start": np.asarray(par.from_controller(start)).tolist(),
                  "simulations_per_evaluation_per_position": SIMS_PER_GRADIENT_STEP},
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpu_count": os.cpu_count(), "jax": jax.__version__,
                    "numpy": np.__version__, "scipy": scipy.__version__,
                    "optax": optax.__version__, "device": str(jax.devices()[0])},
        "loadavg": {"start": load0, "end": loadavg()},
        "methods": methods, "derivative_free": nm, "nelder_mead_verification": nm_verification,
        "compiled_simplex": compiled,
        "end_to_end": e2e,
    }
    write_results(args.out, jsonable(result), markdown(result))


if __name__ == "__main__":
    main()
