"""Benchmark: identify five modes at 61 table positions, fdjax (batched, jit) vs SciPy.

Synthetic Table-1-like FRFs (paper Sec. 3.2, Table 1: 49/95/130/1030/1529 Hz, ζ = 0.12 …
0.003, rigid body c0/s² + c1/s, upper residual, 1 % complex noise) whose modes drift with
the table position as in Figs. 10–12 (the high modes more), on 2000 log-spaced points from
10 to 2500 Hz, 61 positions (Y_table = 100–700 mm in 10 mm steps).

Timed, median of repeats after warm-up, ``block_until_ready()``:

* ``fdjax_refine``: the nonlinear refinement of ``identify_modes_batched`` for all 61
  positions in one jitted call (``jax.lax.map`` over positions, the CPU default), started
  from the vector-fitting poles (``initial=``);
* ``fdjax_refine_vmap``: the same with ``jax.jit(jax.vmap(identify_modes))`` (what a GPU
  wants; on CPU batched small linear algebra does not vectorise, and a vmapped solve
  iterates until its slowest position has converged);
* ``scipy_refine`` (baseline, same process): a loop over the positions of
  ``scipy.optimize.least_squares(method="lm")`` (MINPACK Levenberg–Marquardt, finite-difference
  Jacobian) on the same variable-projection residual, written in NumPy, with the same
  weights, scaling, parametrisation and initial poles;
* ``fdjax_full``: the whole identification (vector fitting + refinement) for the 61
  positions with ``identify_modes_batched``, for reference.

Usage:  python benchmarks/modal_fit.py [--repeats 5] [--out benchmarks/results/modal_fit.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy
import scipy.linalg
import scipy.optimize
from _timing import median_time  # benchmarks/ is on sys.path when run as a script

import fdjax  # noqa: F401  (float64)
from fdjax._modal import identify_modes, identify_modes_batched

N_POS, N_FREQ, N_MODES = 61, 2000, 5
TABLE1 = np.array(
    [[49, 0.120, -135], [95, 0.170, -155], [130, 0.090, -260], [1030, 0.003, -198],
     [1529, 0.010, -31]]
)
GAINS = np.array([0.5, 0.3, 0.4, 0.02, 0.05])
DRIFT = np.array([0.0, 0.02, -0.06, 0.10, -0.15])  # relative frequency change over the stroke
PHASE_DRIFT = np.array([0.0, 5.0, 30.0, 20.0, 60.0])  # degrees over the stroke (Fig. 12)
C0, D, NOISE = -1e-3, 1e-10, 0.01




def synthetic_frfs(freq, positions, seed=0):
    """(n_pos, n_freq) receptances Σ R/(s−λ) + cc + c0/s² + c1/s + d, c1 = −Σ 2 Re R."""
    s = 2j * np.pi * freq
    rng = np.random.default_rng(seed)
    hs, truth = [], []
    for y in positions:
        t = (y - positions[0]) / (positions[-1] - positions[0])
        fn = TABLE1[:, 0] * (1 + DRIFT * t)
        ph = TABLE1[:, 2] + PHASE_DRIFT * t
        wn = 2 * np.pi * fn
        lam = wn * (-TABLE1[:, 1] + 1j * np.sqrt(1 - TABLE1[:, 1] ** 2))
        num = GAINS * abs(C0) * np.exp(1j * np.deg2rad(ph + 90))
        a = num.imag / (2 * wn)
        res = a + 1j * (a * -lam.real - num.real / 2) / lam.imag
        h = C0 / s**2 - 2 * np.sum(res.real) / s + D + 0j
        for lr, rr in zip(lam, res):
            h = h + rr / (s - lr) + np.conj(rr) / (s - np.conj(lr))
        e = rng.standard_normal(freq.size) + 1j * rng.standard_normal(freq.size)
        hs.append(h * (1 + NOISE * e / np.sqrt(2)))
        truth.append(np.stack([fn, TABLE1[:, 1], ph]))
    return np.stack(hs), np.stack(truth)


# ----------------------------------------------------------------------------- SciPy baseline
def numpy_problem(freq, h):
    """The scaled data of fdjax's refinement: s̃ = iω/ω_ref, H/rms|H|, w = 1/|H| normalised."""
    omega = 2 * np.pi * freq
    s = 1j * omega / omega[-1]
    h = h / np.sqrt(np.mean(np.abs(h) ** 2))
    w = 1 / np.abs(h)
    w = w / np.sqrt(np.mean((w * np.abs(h)) ** 2))
    return s, h, w, omega[-1]


def numpy_varpro_residual(u, p0, s, h, w):
    """Same residual as fdjax's: poles λ = −σ₀e^v + iω_d0 e^{ζ₀u}, residues, c0, c1, d by
    weighted linear least squares (semi-normal equations + one refinement step)."""
    u = u.reshape(-1, 2)
    sigma0, wd0 = -p0.real, p0.imag
    zeta0 = np.clip(sigma0 / np.abs(p0), 1e-3, 0.5)
    lam = -sigma0 * np.exp(u[:, 1]) + 1j * wd0 * np.exp(zeta0 * u[:, 0])
    inv = 1 / (s[:, None] - lam[None, :])
    invc = 1 / (s[:, None] - lam.conj()[None, :])
    modal = np.stack([inv + invc, 1j * (inv - invc)], axis=-1).reshape(s.size, -1)
    phi = np.concatenate([modal, np.stack([s**-2, s**-1, np.ones_like(s)], axis=1)], axis=1)
    a = (w[:, None] * phi)
    a = np.concatenate([a.real, a.imag])
    b = np.concatenate([(w * h).real, (w * h).imag])
    scale = np.sqrt(np.sum(a**2, axis=0))
    a = a / scale
    chol = scipy.linalg.cho_factor(a.T @ a + 1e-13 * np.eye(a.shape[1]), lower=True)
    x = scipy.linalg.cho_solve(chol, a.T @ b)
    r = b - a @ x
    x = x + scipy.linalg.cho_solve(chol, a.T @ r)
    return b - a @ x


def scipy_refine(freq, hs, p0s):
    """Per-position MINPACK LM from the same start; returns natural frequencies (Hz)."""
    out = []
    for h, p0 in zip(hs, p0s):
        s, hn, w, omega_ref = numpy_problem(freq, h)
        p = p0 / omega_ref
        sol = scipy.optimize.least_squares(
            numpy_varpro_residual, np.zeros(2 * p.size), method="lm", args=(p, s, hn, w),
            xtol=1e-9, ftol=1e-9, gtol=1e-12,
        )
        u = sol.x.reshape(-1, 2)
        zeta0 = np.clip(-p.real / np.abs(p), 1e-3, 0.5)
        lam = p.real * np.exp(u[:, 1]) + 1j * p.imag * np.exp(zeta0 * u[:, 0])
        out.append(np.sort(np.abs(lam)) * omega_ref / (2 * np.pi))
    return np.stack(out)


# ----------------------------------------------------------------------------- runs
def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "modal_fit.json"))
    args = ap.parse_args()

    freq = np.geomspace(10.0, 2500.0, N_FREQ)
    positions = np.linspace(100.0, 700.0, N_POS)  # Y_table, mm
    hs_np, truth = synthetic_frfs(freq, positions)
    hs = jnp.asarray(hs_np)

    init = jax.block_until_ready(identify_modes_batched(freq, hs, N_MODES, refine=False))
    p0s = np.asarray(init.poles)

    def refine():
        return identify_modes_batched(freq, hs, N_MODES, initial=init)

    refine_vmap = jax.jit(jax.vmap(lambda h, p: identify_modes(freq, h, N_MODES, initial=p)))

    t0 = time.perf_counter()
    fits = jax.block_until_ready(refine())
    compile_refine = time.perf_counter() - t0
    t_refine, times_refine = median_time(refine, args.repeats)
    t_vmap, times_vmap = median_time(lambda: refine_vmap(hs, init), args.repeats)
    t_full, times_full = median_time(lambda: identify_modes_batched(freq, hs, N_MODES),
                                     args.repeats)
    t_scipy, times_scipy = median_time(lambda: scipy_refine(freq, hs_np, p0s), args.repeats)

    f_scipy = scipy_refine(freq, hs_np, p0s)
    f_fd = np.asarray(fits.frequency_hz)
    agree = float(np.max(np.abs(f_fd / f_scipy - 1)))
    f_err = np.abs(f_fd / truth[:, 0] - 1)
    z_err = np.abs(np.asarray(fits.damping_ratio) / truth[:, 1] - 1)
    p_err = np.abs((np.asarray(fits.phase_deg) - truth[:, 2] + 180) % 360 - 180)

    rows = {
        "fdjax_refine_batched_s": t_refine,
        "scipy_refine_loop_s": t_scipy,
        "speedup_refine": t_scipy / t_refine,
        "fdjax_refine_vmap_s": t_vmap,
        "speedup_refine_vmap": t_scipy / t_vmap,
        "fdjax_full_batched_s": t_full,
        "speedup_full_vs_scipy_refine": t_scipy / t_full,
        "fdjax_refine_compile_s": compile_refine,
        "per_position_ms": {"fdjax_refine": 1e3 * t_refine / N_POS,
                            "fdjax_refine_vmap": 1e3 * t_vmap / N_POS,
                            "scipy_refine": 1e3 * t_scipy / N_POS,
                            "fdjax_full": 1e3 * t_full / N_POS},
        "fdjax_lm_steps_max": int(np.max(np.asarray(fits.num_steps))),
        "max_rel_freq_diff_fdjax_vs_scipy": agree,
        "accuracy_vs_truth": {"max_rel_freq_err": float(f_err.max()),
                              "max_rel_damping_err": float(z_err.max()),
                              "max_phase_err_deg": float(p_err.max())},
        "times_s": {"fdjax_refine": times_refine, "fdjax_refine_vmap": times_vmap,
                    "scipy_refine": times_scipy, "fdjax_full": times_full},
        "baseline": "scipy.optimize.least_squares(method='lm', finite-difference Jacobian), "
                    "per position, same NumPy variable-projection residual, same start",
    }
    result = {
        "benchmark": "modal_fit",
        "problem": {"positions": N_POS, "frequencies": N_FREQ, "modes": N_MODES,
                    "band_hz": [10.0, 2500.0], "noise": NOISE},
        "repeats": args.repeats,
        "statistic": "median",
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpu_count": os.cpu_count(), "jax": jax.__version__,
                    "numpy": np.__version__, "scipy": scipy.__version__,
                    "device": str(jax.devices()[0])},
        "results": rows,
    }
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=2)
    print(f"{N_POS} positions × {N_FREQ} frequencies, {N_MODES} modes "
          f"(median of {args.repeats})")
    print(f"{'case':44s} {'total (s)':>10s} {'per pos. (ms)':>14s}")
    for name, t in (("fdjax refinement, identify_modes_batched", t_refine),
                    ("fdjax refinement, jit(vmap(identify_modes))", t_vmap),
                    ("scipy least_squares LM, loop", t_scipy),
                    ("fdjax full, identify_modes_batched", t_full)):
        print(f"{name:44s} {t:10.3f} {1e3 * t / N_POS:14.1f}")
    print(f"speed-up of the refinement vs scipy: {t_scipy / t_refine:.2f}× "
          f"(vmap: {t_scipy / t_vmap:.2f}×); "
          f"fdjax vs scipy frequencies agree to {agree:.1e}")
    print(f"accuracy vs truth: freq {f_err.max():.1e}, damping {z_err.max():.1e}, "
          f"phase {p_err.max():.2f}°")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
