"""Benchmark: closed-loop time simulation of a drive, fdjax vs python-control.

The LTI closed loop of the Table 1 drive (``fdjax.table1_drive()``; a DoubleLoop with
k_p = 40, k_v = 1000, k_i = 60 and an MCM with a 120 Hz peak and a 1 kHz notch) around a
20 kHz servo, ``fdjax.Servo(period=5e-5, delay_samples=5)``
(delay τ = d·T = 250 µs, as the reference servo's), on 0.5 s of the reciprocating motion
(``reciprocating(stroke=5e-3, v_max=0.1, a_max=2.0, j_max=200.0, cycles=2)``), outputs at
20 kHz (10,001 samples).  Three cases, each against python-control in the same process:

1. ``one_run``: one simulation at Y = 0.4 m.  Baseline: ``control.forced_response`` of
   ``control.ss(A, B, C, D)`` of the continuous Padé loop of
   ``fdjax.closed_loop(..., method=fdjax.Continuous())`` (system
   built once, outside the timing; input W = (r, ṙ, r̈, 0) sampled on t).  fdjax: a jitted
   function of (loop, plant) → outputs that includes sampling the reference, building the
   loop and discretising it: ``SampledData()`` (exact sampled-data loop, lifted recursion) and
   ``PadeODE`` (the same continuous loop as the baseline, diffrax + ExponentialFOH).
2. ``batch``: 64 positions Y₀ over 0.1–0.695 m (Y₀ + r(t) inside the travel 0.1–0.7 m: the
   stroke is 5 mm, and ``simulate`` reports a run leaving the travel as ``out_of_travel``).
   fdjax: ``jax.vmap`` of ``simulate``
   on the drive (the twin is built at each position inside the timing, sampled-data path).
   Baseline: a loop of 64 ``forced_response`` calls on prebuilt systems (only the calls timed).
3. ``grad``: ∂(RMS scale error)/∂(12 controller parameters: kp, kv, ki, k_ffv, k_ffa, the MCM
   peak's K, ω, ξ, φ and the notch's ω, ζ_n, ζ_d) at six positions (0.1, 0.22, …, 0.7 m), a
   (6, 12) Jacobian.  fdjax: ``jax.vmap(jax.grad(...))`` over the six positions (plants
   prebuilt; loop building, discretisation and simulation inside).  Baseline: forward finite
   differences with python-control, 13 ``forced_response`` calls per position, the closed
   loop rebuilt with ``fdjax.closed_loop`` (continuous) for every perturbed parameter (that
   build is timed
   too and reported separately).  The compiled gradient programs' memory
   (``memory_analysis()``) is reported for the sampled path and for several diffrax adjoints.

Every fdjax timing is of compiled code after a warm-up call, with ``block_until_ready()``;
each figure is the median of repeats (the slow baselines get fewer repeats; see ``repeats``
in the JSON).  The machine's load average is recorded before and after every case.

Usage:  python benchmarks/closed_loop.py [--repeats 7] [--baseline-repeats 3] [--quick]
        [--out benchmarks/results/closed_loop.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import control
import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _timing import (  # benchmarks/ is on sys.path when run as a script
    loadavg,
    median_time,
    write_results,
)

import fdjax

DT, DURATION, DELAY_SAMPLES, POSITION = 5.0e-5, 0.5, 5, 0.4
GRAD_POSITIONS = (0.1, 0.22, 0.34, 0.46, 0.58, 0.7)  # prebuilt twins: no travel check
BATCH_SPAN_M = (0.1, 0.695)  # Y₀ + r(t) stays in the travel [0.1, 0.7] m: the stroke is 5 mm
PARAMS = ("kp", "kv", "ki", "k_ffv", "k_ffa", "peak_K", "peak_omega", "peak_xi", "peak_phi",
          "notch_omega", "notch_zeta_n", "notch_zeta_d")
TARGETS = {"one_run_sampled": 20.0, "one_run_pade_ode": 0.5, "batch_sampled": 30.0,
           "grad_sampled": 50.0, "grad_pade_ode": 3.0}

REF = fdjax.reciprocating(stroke=5e-3, v_max=0.1, a_max=2.0, j_max=200.0, cycles=2)
DRIVE = fdjax.table1_drive()
N_MODES = fdjax.count_modes(DRIVE)
TWIN = fdjax.TwinOptions(kept_modes=N_MODES)




def default_params():
    return {
        "kp": 40.0, "kv": 1.0e3, "ki": 60.0, "k_ffv": 1.0,
        "k_ffa": float(fdjax.rigid_feedforward(DRIVE)[1]),
        "peak_K": 0.3, "peak_omega": 2 * np.pi * 120.0, "peak_xi": 0.15, "peak_phi": 0.4,
        "notch_omega": 2 * np.pi * 1000.0, "notch_zeta_n": 0.05, "notch_zeta_d": 0.5,
    }


def build_loop(p):
    mcm = fdjax.MCM(
        fdjax.PeakFilter(p["peak_K"], p["peak_omega"], p["peak_xi"], p["peak_phi"]),
        fdjax.NotchFilter(p["notch_omega"], p["notch_zeta_n"], p["notch_zeta_d"]),
    )
    return fdjax.DoubleLoop(p["kp"], p["kv"], p["ki"], k_ffv=p["k_ffv"], k_ffa=p["k_ffa"],
                            mcm=mcm)


SERVO = fdjax.Servo(period=DT, delay_samples=DELAY_SAMPLES)  # 20 kHz, τ = 5·T = 250 µs
SAMPLED = fdjax.SampledData()
CONTINUOUS = fdjax.Continuous()  # Padé delay of fdjax.DEFAULT_PADE_ORDER, as PadeODE's


def outputs(sim):
    return jnp.stack([sim.theta1, sim.x2, sim.x3, sim.torque])


# ----------------------------------------------------------------------------- python-control
def reference_inputs(t):
    r, v, a = (np.asarray(x) for x in REF.evaluate(jnp.asarray(t))[:3])
    return np.stack([r, v, a, np.zeros_like(r)])  # (4, n)


def control_system(loop, plant):
    cl = fdjax.closed_loop(loop, plant, servo=SERVO, method=CONTINUOUS)
    return control.ss(*(np.asarray(m) for m in (cl.A, cl.B, cl.C, cl.D)))


def control_run(sys, t, U):
    return control.forced_response(sys, T=t, U=U).outputs  # (4, n)


def control_rms(sys, t, U):
    y = control_run(sys, t, U)
    e = U[0] - y[1]
    return float(np.sqrt(np.mean(e * e)))


def fd_gradients(params, plants, t, U, timing=None, central=False):
    """Finite differences of the python-control RMS scale error, the closed loop rebuilt
    (fdjax.closed_loop) for every perturbed parameter.  Forward (the timed baseline): step
    √eps·max(|p|, 1e-3), 13 forced_response calls per position.  Central (accuracy check
    only, not timed): step eps^(1/3)·max(|p|, 1e-3), 25 calls per position; forced_response's
    round-off (~1e-13 of the RMS, see the JSON) limits forward differences to ~1e-3 relative
    on the weaker parameters."""
    eps = np.finfo(float).eps
    rel = eps ** (1 / 3) if central else np.sqrt(eps)
    G = np.zeros((len(plants), len(PARAMS)))
    f0s = np.zeros(len(plants))
    t_build = t_call = 0.0
    for i, plant in enumerate(plants):
        def f(p):
            nonlocal t_build, t_call
            t0 = time.perf_counter()
            sys = control_system(build_loop(p), plant)
            t1 = time.perf_counter()
            v = control_rms(sys, t, U)
            t_build += t1 - t0
            t_call += time.perf_counter() - t1
            return v

        f0 = f(params)
        f0s[i] = f0
        for j, k in enumerate(PARAMS):
            h = rel * max(abs(params[k]), 1e-3)
            qp, qm = dict(params), dict(params)
            qp[k] = params[k] + h
            qm[k] = params[k] - h
            if central:
                G[i, j] = (f(qp) - f(qm)) / (qp[k] - qm[k])
            else:
                G[i, j] = (f(qp) - f0) / (qp[k] - params[k])  # the step actually taken
    if timing is not None:
        timing.update(build_s=t_build, forced_response_s=t_call)
    return G, f0s


# ----------------------------------------------------------------------------- fdjax
@eqx.filter_jit
def run_sampled(loop, plant):
    sim = fdjax.simulate(loop, plant, REF, SAMPLED, servo=SERVO, duration=DURATION,
                         throw=False)
    return outputs(sim), sim.result._value


def pade_method(adjoint=None):
    return fdjax.PadeODE(dt=DT, adjoint=adjoint)


@eqx.filter_jit
def run_pade(loop, plant):
    sim = fdjax.simulate(loop, plant, REF, pade_method(), servo=SERVO, duration=DURATION,
                         throw=False)
    return outputs(sim), sim.result._value


@eqx.filter_jit
def run_batch(loop, positions):
    def one(p):
        sim = fdjax.simulate(loop, DRIVE, REF, SAMPLED, servo=SERVO, duration=DURATION,
                             position_m=p, twin=TWIN, throw=False)
        return outputs(sim), sim.result._value

    return jax.vmap(one)(positions)


def rms_sampled(p, plant):
    sim = fdjax.simulate(build_loop(p), plant, REF, SAMPLED, servo=SERVO, duration=DURATION,
                         throw=False)
    return sim.rms_error()


def make_rms_pade(adjoint):
    def rms_pade(p, plant):
        sim = fdjax.simulate(build_loop(p), plant, REF, pade_method(adjoint), servo=SERVO,
                             duration=DURATION, throw=False)
        return sim.rms_error()

    return rms_pade


def grad_program(loss, batch="vmap"):
    """(params, stacked plants) → (RMS (pos,), gradient dict of (pos,) arrays).  ``vmap``
    over the positions, or ``lax.map`` (one position after the other, inside one program):
    for the diffrax path lax.map was ~2× faster on CPU than vmap in an earlier run."""
    vg = jax.value_and_grad(loss)
    if batch == "vmap":
        return jax.jit(jax.vmap(vg, in_axes=(None, 0)))
    return jax.jit(lambda P, plants: jax.lax.map(lambda pl: vg(P, pl), plants))


def memory(fn, *args):
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    m = compiled.memory_analysis()
    out = {"compile_s": compile_s}
    for k in ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes",
              "alias_size_in_bytes", "generated_code_size_in_bytes"):
        out[k] = int(getattr(m, k, -1)) if m is not None else None
    return out, compiled


def as_matrix(g):
    return np.stack([np.asarray(g[k]).reshape(-1) for k in PARAMS], 1)  # (pos, param)


def rel_diffs(ad, fd, P, f0, floor=1e-2):
    """Agreement of two (pos, param) gradients.  Log-sensitivities S = p ∂f/∂p / f
    (dimensionless); entries with |S_fd| > ``floor`` are the ones FD resolves to better than
    1e-3 (python-control's RMS carries ~3e-11 relative round-off, i.e. ~2e-6 of noise on S from
    central and ~2e-3 from forward differences; the MCM's |S| are ~1e-4 … 1e-3): max relative
    difference over them, the max absolute difference of S over all entries, the max normwise
    relative difference per position."""
    p = np.array([abs(P[k]) for k in PARAMS])[None, :]
    Sa, Sf = ad * p / f0[:, None], fd * p / f0[:, None]
    mask = np.abs(Sf) > floor
    elem = np.abs(Sa - Sf) / np.where(mask, np.abs(Sf), 1.0)
    norm = np.linalg.norm(ad - fd, axis=1) / np.linalg.norm(fd, axis=1)
    return {"max_rel_resolvable": float(np.max(np.where(mask, elem, 0.0))),
            "resolvable_entries": int(mask.sum()), "log_sensitivity_floor": floor,
            "max_abs_diff_log_sensitivity": float(np.max(np.abs(Sa - Sf))),
            "max_normwise_rel": float(np.max(norm)),
            "sign_agreement_resolvable": int(np.sum((np.sign(ad) == np.sign(fd)) & mask)),
            "entries": int(ad.size)}


def stack(trees):
    return jax.tree.map(lambda *x: jnp.stack(x), *trees)


# ----------------------------------------------------------------------------- cases
def case_one_run(args, loop, plant, t, U):
    load0 = loadavg()
    sys = control_system(loop, plant)
    y_ctrl = control_run(sys, t, U)
    y_s, res_s = run_sampled(loop, plant)
    y_p, res_p = run_pade(loop, plant)
    ok = int(res_s) == 0 and int(res_p) == 0
    stroke = float(np.max(np.abs(U[0])))
    t_s, ts_s = median_time(lambda: run_sampled(loop, plant), args.repeats)
    t_p, ts_p = median_time(lambda: run_pade(loop, plant), args.repeats)
    t_c, ts_c = median_time(lambda: control_run(sys, t, U), args.repeats, warmup=True)
    return {
        "position_m": POSITION, "samples": int(t.shape[0]), "states_continuous": sys.nstates,
        "successful": ok,
        "python_control_s": t_c, "python_control_times": ts_c,
        "sampled_s": t_s, "sampled_times": ts_s, "pade_ode_s": t_p, "pade_ode_times": ts_p,
        "speedup_sampled": t_c / t_s, "speedup_pade_ode": t_c / t_p,
        "max_abs_diff_x2_pade_vs_control_m": float(np.max(np.abs(np.asarray(y_p[1]) - y_ctrl[1]))),
        "max_abs_diff_x2_sampled_vs_control_m":
            float(np.max(np.abs(np.asarray(y_s[1]) - y_ctrl[1]))),
        "stroke_m": stroke, "rms_scale_error_m": float(np.sqrt(np.mean((U[0] - y_ctrl[1]) ** 2))),
        "loadavg_before": load0, "loadavg_after": loadavg(),
    }


def case_batch(args, loop, t, U):
    load0 = loadavg()
    positions = np.linspace(*BATCH_SPAN_M, args.positions)
    systems = [control_system(loop, fdjax.state_space(DRIVE, p)) for p in positions]
    pos = jnp.asarray(positions)
    Y, res = run_batch(loop, pos)
    ok = bool(np.all(np.asarray(res) == 0))
    # agreement with a per-position sampled run (vmap vs loop), and with python-control (O(T))
    y_one, _ = run_sampled(loop, fdjax.state_space(DRIVE, positions[-1]))
    vmap_err = float(np.max(np.abs(np.asarray(Y[-1]) - np.asarray(y_one))))
    yc_last = control_run(systems[-1], t, U)
    t_f, ts_f = median_time(lambda: run_batch(loop, pos), args.repeats)
    # where the batched run spends its time (the sampled loop model's closed loop, and private
    # helpers of fdjax._simulation._lifted: diagnostic)
    from fdjax._simulation._lifted import growth_rate, lifted_outputs

    ss = jax.jit(jax.vmap(lambda p: fdjax.state_space(DRIVE, p, twin=TWIN)))
    plants = ss(pos)
    sl = eqx.filter_jit(jax.vmap(lambda pl: SAMPLED.closed_loop(loop, pl, SERVO)))
    SL = sl(plants)
    Wj = jnp.asarray(U.T)
    scan = jax.jit(jax.vmap(lambda A, B, C, D: lifted_outputs(A, B, C, D, Wj)))
    growth = jax.jit(jax.vmap(lambda A: growth_rate(A, DT)))
    sim_pre = eqx.filter_jit(jax.vmap(lambda pl: outputs(fdjax.simulate(
        loop, pl, REF, SAMPLED, servo=SERVO, duration=DURATION, throw=False))))
    profile = {
        "state_space_s": median_time(lambda: ss(pos), args.repeats)[0],
        "sampled_closed_loop_s": median_time(lambda: sl(plants), args.repeats)[0],
        "growth_rate_s": median_time(lambda: growth(SL.A), args.repeats)[0],
        "lifted_outputs_s": median_time(lambda: scan(SL.A, SL.B, SL.C, SL.D),
                                        args.repeats)[0],
        "simulate_prebuilt_plants_s": median_time(lambda: sim_pre(plants), args.repeats)[0],
        "single_lifted_outputs_s": median_time(
            lambda: jax.jit(lifted_outputs)(SL.A[0], SL.B[0], SL.C[0], SL.D[0], Wj),
            args.repeats)[0],
        "states_sampled": int(SL.A.shape[-1]),
    }
    t_c, ts_c = median_time(lambda: [control_run(s, t, U) for s in systems],
                            args.baseline_repeats, warmup=False)
    return {
        "positions": int(args.positions), "successful": ok,
        "python_control_s": t_c, "python_control_times": ts_c,
        "sampled_s": t_f, "sampled_times": ts_f, "speedup_sampled": t_c / t_f,
        "profile_s": profile,
        "max_abs_diff_vmap_vs_single_run": vmap_err,
        f"max_abs_diff_x2_sampled_vs_control_at_{positions[-1]:.4g}m_m":
            float(np.max(np.abs(np.asarray(Y[-1, 1]) - yc_last[1]))),
        "loadavg_before": load0, "loadavg_after": loadavg(),
    }


def case_grad(args, t, U):
    load0 = loadavg()
    positions = GRAD_POSITIONS if not args.quick else GRAD_POSITIONS[::5]
    p0 = default_params()
    P = {k: jnp.asarray(v) for k, v in p0.items()}
    plants_list = [fdjax.state_space(DRIVE, p) for p in positions]
    plants = stack(plants_list)
    slow = 2  # repeats of the slow diagnostics (adjoint variants), after their warm-up call

    g_s = grad_program(rms_sampled, "vmap")
    mem_s, _ = memory(g_s, P, plants)
    v_s, G_s = g_s(P, plants)
    g_p = grad_program(make_rms_pade(None), "map")
    mem_p, _ = memory(g_p, P, plants)
    v_p, G_p = g_p(P, plants)
    G_s, G_p = as_matrix(G_s), as_matrix(G_p)

    t_s, ts_s = median_time(lambda: g_s(P, plants), args.repeats)
    t_p, ts_p = median_time(lambda: g_p(P, plants), args.repeats)
    fwd_s = jax.jit(jax.vmap(rms_sampled, in_axes=(None, 0)))
    t_fwd_s, _ = median_time(lambda: fwd_s(P, plants), args.repeats)
    fwd_p = jax.jit(lambda P, pl: jax.lax.map(lambda x: make_rms_pade(None)(P, x), pl))
    t_fwd_p, _ = median_time(lambda: fwd_p(P, plants), args.repeats)

    fd_times, splits = [], []
    for _ in range(args.baseline_repeats):
        split = {}
        t0 = time.perf_counter()
        G_fd, f0 = fd_gradients(p0, plants_list, t, U, split)
        fd_times.append(time.perf_counter() - t0)
        splits.append(split)
    t_fd = float(np.median(fd_times))
    G_cd, _ = fd_gradients(p0, plants_list, t, U, central=True)  # accuracy check, not timed

    # other diffrax adjoints (and batching): compiled memory, time, agreement with the default
    adjoints = {}
    variants = [(f"RecursiveCheckpointAdjoint(checkpoints={n})",
                 make_rms_pade(diffrax.RecursiveCheckpointAdjoint(checkpoints=n)), "map")
                for n in ((16,) if args.quick else (16, 128, 1024))]
    variants += [("DirectAdjoint()", make_rms_pade(diffrax.DirectAdjoint()), "map"),
                 ("BacksolveAdjoint()", make_rms_pade(diffrax.BacksolveAdjoint()), "map"),
                 ("RecursiveCheckpointAdjoint() with jax.vmap over positions",
                  make_rms_pade(None), "vmap")]
    for name, loss, batch in variants:
        if name.startswith("DirectAdjoint") and not args.direct:
            adjoints[name] = {"skipped": "not tried (pass --direct): a nested bounded while "
                                         "loop over 10,003 steps"}
            continue
        if "vmap" in name and not args.vmap_pade:
            adjoints[name] = {"skipped": "not timed (pass --vmap-pade); slower than lax.map "
                                         "on CPU in an earlier run (~2×)"}
            continue
        try:
            g = grad_program(loss, batch)
            mem, _ = memory(g, P, plants)
            _, G = g(P, plants)
            G = as_matrix(G)
            tm, tms = median_time(lambda g=g: g(P, plants), slow, warmup=False)
            adjoints[name] = {**mem, "grad_s": tm, "grad_times": tms, "batch": batch,
                              "finite": bool(np.all(np.isfinite(G))),
                              "max_rel_diff_vs_default": float(np.max(np.abs(G - G_p))
                                                               / np.max(np.abs(G_p)))}
        except Exception as exc:  # noqa: BLE001  (report what does not run)
            adjoints[name] = {"error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:300]}"}

    return {
        "positions_m": list(positions), "parameters": list(PARAMS),
        "rms_scale_error_m": {"sampled": np.asarray(v_s).tolist(),
                              "pade_ode": np.asarray(v_p).tolist(),
                              "python_control": f0.tolist()},
        "batching": {"sampled": "jax.vmap over positions",
                     "pade_ode": "jax.lax.map over positions (faster than vmap on CPU)"},
        "sampled_s": t_s, "sampled_times": ts_s, "pade_ode_s": t_p, "pade_ode_times": ts_p,
        "sampled_forward_s": t_fwd_s, "pade_ode_forward_s": t_fwd_p,
        "fd_python_control_s": t_fd, "fd_python_control_times": fd_times,
        "fd_split_s": splits, "fd_calls": 13 * len(positions),
        "fd_includes_closed_loop_build": True,
        "speedup_sampled": t_fd / t_s, "speedup_pade_ode": t_fd / t_p,
        "finite": {"sampled": bool(np.all(np.isfinite(G_s))),
                   "pade_ode": bool(np.all(np.isfinite(G_p)))},
        "agreement_pade_ode_ad_vs_forward_fd": rel_diffs(G_p, G_fd, p0, f0),
        "agreement_pade_ode_ad_vs_central_fd": rel_diffs(G_p, G_cd, p0, f0),
        "agreement_forward_fd_vs_central_fd": rel_diffs(G_fd, G_cd, p0, f0),
        "agreement_sampled_ad_vs_central_fd": rel_diffs(G_s, G_cd, p0, f0),
        "gradient_pade_ode": G_p.tolist(), "gradient_sampled": G_s.tolist(),
        "gradient_fd_python_control": G_fd.tolist(),
        "gradient_central_fd_python_control": G_cd.tolist(),
        "memory": {"sampled (lifted lax.scan), vmap": mem_s,
                   "pade_ode RecursiveCheckpointAdjoint() (default), lax.map": mem_p,
                   **adjoints},
        "loadavg_before": load0, "loadavg_after": loadavg(),
    }


# ----------------------------------------------------------------------------- report
def markdown(result):
    r = result["results"]
    rows = [
        ("one run, sampled-data (jit)", r["one_run"]["sampled_s"],
         r["one_run"]["python_control_s"], "forced_response", "one_run_sampled"),
        ("one run, PadeODE diffrax (jit)", r["one_run"]["pade_ode_s"],
         r["one_run"]["python_control_s"], "forced_response", "one_run_pade_ode"),
        (f"{r['batch']['positions']} positions, vmap sampled-data", r["batch"]["sampled_s"],
         r["batch"]["python_control_s"], f"{r['batch']['positions']}× forced_response",
         "batch_sampled"),
        (f"grad 12 params × {len(r['grad']['positions_m'])} positions, sampled-data",
         r["grad"]["sampled_s"], r["grad"]["fd_python_control_s"],
         f"FD, {r['grad']['fd_calls']}× forced_response + closed_loop", "grad_sampled"),
        (f"grad 12 params × {len(r['grad']['positions_m'])} positions, PadeODE diffrax",
         r["grad"]["pade_ode_s"], r["grad"]["fd_python_control_s"],
         f"FD, {r['grad']['fd_calls']}× forced_response + closed_loop", "grad_pade_ode"),
    ]
    lines = [
        "# Closed-loop simulation benchmark (fdjax vs python-control)",
        "",
        f"Machine: {result['machine']['platform']}, {result['machine']['cpu_count']} CPUs "
        f"(shared), jax {result['machine']['jax']}, python-control "
        f"{result['machine']['python_control']}.  Load average during the run: "
        f"{result['loadavg']}.  Medians of {result['repeats']['fdjax']} repeats (fdjax, after "
        f"warm-up) and {result['repeats']['baseline']} (python-control loops; one run: "
        f"{result['repeats']['fdjax']}).",
        "",
        "| benchmark | fdjax | baseline | ratio | target |",
        "|---|---|---|---|---|",
    ]
    for name, tf, tb, bname, key in rows:
        ratio, target = tb / tf, TARGETS[key]
        ok = "pass" if ratio >= target else "**fail**"
        tgt = f"≥ {target:g}×" if target >= 1 else f"≥ {target:g}× (no slower than 2×)"
        lines.append(f"| {name} | {tf * 1e3:.1f} ms | {tb * 1e3:.0f} ms ({bname}) | "
                     f"{ratio:.1f}× | {tgt} {ok} |")
    g = r["grad"]
    a = g["agreement_pade_ode_ad_vs_central_fd"]
    a2 = g["agreement_pade_ode_ad_vs_forward_fd"]
    c = g["agreement_forward_fd_vs_central_fd"]
    b = g["agreement_sampled_ad_vs_central_fd"]
    lines += [
        "",
        f"Gradients finite: sampled {g['finite']['sampled']}, PadeODE {g['finite']['pade_ode']}. "
        "Agreement on log-sensitivities S = p·∂f/∂p / f, over the entries FD can resolve "
        f"(|S| > {a['log_sensitivity_floor']:g}; {a['resolvable_entries']}/{a['entries']}):",
        "",
        "| comparison | max rel. diff (resolvable) | max abs. diff of S (all) | normwise | signs |",
        "|---|---|---|---|---|",
    ]
    for label, x in (("AD PadeODE vs central FD python-control", a),
                     ("AD PadeODE vs forward FD python-control (timed baseline)", a2),
                     ("forward FD vs central FD (both python-control)", c),
                     ("AD sampled-data vs central FD (other discretisation)", b)):
        lines.append(f"| {label} | {x['max_rel_resolvable']:.1e} | "
                     f"{x['max_abs_diff_log_sensitivity']:.1e} | {x['max_normwise_rel']:.1e} | "
                     f"{x['sign_agreement_resolvable']}/{x['resolvable_entries']} |")
    lines += [
        "",
        "FD baseline split (median repeat): closed-loop building "
        f"{np.median([s['build_s'] for s in g['fd_split_s']]):.2f} s, forced_response "
        f"{np.median([s['forced_response_s'] for s in g['fd_split_s']]):.2f} s.",
        "",
        "Compiled gradient programs (`jax.jit(f).lower(...).compile().memory_analysis()`):",
        "",
        "| program | temp | arguments | output | compile | grad time |",
        "|---|---|---|---|---|---|",
    ]
    for name, m in g["memory"].items():
        if "error" in m or "skipped" in m:
            lines.append(f"| {name} | {m.get('error', m.get('skipped'))} | | | | |")
            continue
        gt = m.get("grad_s", g["sampled_s"] if name.startswith("sampled") else g["pade_ode_s"])
        lines.append(f"| {name} | {m['temp_size_in_bytes'] / 2**20:.1f} MiB | "
                     f"{m['argument_size_in_bytes'] / 2**10:.1f} KiB | "
                     f"{m['output_size_in_bytes'] / 2**10:.1f} KiB | {m['compile_s']:.1f} s | "
                     f"{gt * 1e3:.0f} ms |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--baseline-repeats", type=int, default=3)
    ap.add_argument("--positions", type=int, default=64)
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: 3 repeats, 1 baseline repeat, 8 positions, 2 grad positions")
    ap.add_argument("--direct", action="store_true", help="also try diffrax.DirectAdjoint()")
    ap.add_argument("--vmap-pade", action="store_true",
                    help="also time the diffrax gradient with jax.vmap over positions")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "closed_loop.json"))
    args = ap.parse_args()
    if args.quick:
        args.repeats, args.baseline_repeats, args.positions = 3, 1, 8

    load0 = loadavg()
    loop = build_loop(default_params())
    plant = fdjax.state_space(DRIVE, POSITION)
    t = np.arange(int(round(DURATION / DT)) + 1) * DT
    U = reference_inputs(t)

    rows = {}
    rows["one_run"] = case_one_run(args, loop, plant, t, U)
    print("one_run", {k: v for k, v in rows["one_run"].items() if not k.endswith("times")})
    rows["batch"] = case_batch(args, loop, t, U)
    print("batch", {k: v for k, v in rows["batch"].items() if not k.endswith("times")})
    rows["grad"] = case_grad(args, t, U)
    print("grad", {k: rows["grad"][k] for k in ("sampled_s", "pade_ode_s", "fd_python_control_s",
                                                "speedup_sampled", "speedup_pade_ode")})
    checks = {
        "one_run_sampled": rows["one_run"]["speedup_sampled"],
        "one_run_pade_ode": rows["one_run"]["speedup_pade_ode"],
        "batch_sampled": rows["batch"]["speedup_sampled"],
        "grad_sampled": rows["grad"]["speedup_sampled"],
        "grad_pade_ode": rows["grad"]["speedup_pade_ode"],
    }
    result = {
        "benchmark": "closed_loop",
        "quick": bool(args.quick),
        "repeats": {"fdjax": args.repeats, "baseline": args.baseline_repeats},
        "statistic": "median",
        "setup": {"duration_s": DURATION, "dt_s": DT, "delay_samples": DELAY_SAMPLES,
                  "servo": {"period_s": SERVO.period, "delay_samples": SERVO.delay_samples,
                            "tau_s": SERVO.tau, "k_motor": float(SERVO.k_motor)},
                  "n_modes": int(N_MODES), "params": default_params(),
                  "reference": "reciprocating(stroke=5e-3, v_max=0.1, a_max=2.0, j_max=200.0, "
                               "cycles=2)"},
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpu_count": os.cpu_count(), "jax": jax.__version__,
                    "numpy": np.__version__, "python_control": control.__version__,
                    "diffrax": diffrax.__version__, "device": str(jax.devices()[0])},
        "loadavg": {"start": load0, "end": loadavg()},
        "targets": {k: {"ratio": v, "target": TARGETS[k], "pass": bool(v >= TARGETS[k])}
                    for k, v in checks.items()},
        "results": rows,
    }
    write_results(args.out, result, markdown(result))


if __name__ == "__main__":
    main()
