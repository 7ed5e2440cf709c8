"""Benchmark: FRF sweeps of the ball-screw drive and the 3M2S model, fdjax vs NumPy.

* the drive's H_M on a 256-position × 4096-frequency grid (1,048,576 points × 6 entries);
* the 3M2S receptance on 1,048,576 frequencies (3×3 per point);
* one ``jax.grad`` of a scalar over the whole drive grid relative to its forward pass.

Baselines run in the same process: NumPy with broadcasting over (position, frequency),
implementing the same closed-form algebra as fdjax (substructure receptances by Schur
complements of the line dynamic stiffness, LM-FBS at the nut), and for the 3M2S the natural
NumPy code, ``np.linalg.inv`` of the stacked 3×3 dynamic stiffness.  fdjax timings are of
compiled code after warm-up, with ``block_until_ready()``; every figure is the median of repeats.

Usage:  python benchmarks/frf_sweep.py [--repeats 5] [--out benchmarks/results/frf_sweep.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _timing import median_time  # benchmarks/ is on sys.path when run as a script

import fdjax

N_POS, N_FREQ, N_3M = 256, 4096, 1 << 20




# ----------------------------------------------------------------------------- NumPy baseline
def _np_segment(kz, phase):
    e2 = phase * phase
    den = 1.0 / (e2 - 1.0)
    return 1j * kz * (e2 + 1.0) * den, -2j * kz * phase * den


def _np_line(rod, w, l, supports):
    """NumPy twin of fdjax._drive._rods.line_stiffness for nodes (0, l, L)."""
    Z, mu, eta, beta, L = rod
    zs = Z * (1 + 1j * (eta + w * beta))
    kz, k = w * np.sqrt(mu * zs), w * np.sqrt(mu / zs)
    pl, pL = np.exp(1j * k * l), np.exp(1j * k * L)
    da, ea = _np_segment(kz, pl)
    db, eb = _np_segment(kz, pL / pl)
    diag = [da + supports[0], da + db, db + supports[1]]
    return diag, [ea, eb]


def _np_lines(d, pos, freq):
    """Substructure dynamic stiffness of the drive on the grid, in NumPy: the rotary line
    (θ1, θ0, θl, θL), the axial line (u0, ul, uL), the carriage's axial and pitch terms, the
    transmission ratio and the nut joint's dynamic stiffness."""
    g = lambda x: float(x)  # noqa: E731
    w = 2 * np.pi * freq[None, :]
    l = pos[:, None] + g(d.nut_offset)
    s = d.screw
    polar, area = np.pi * g(s.diameter) ** 4 / 32, np.pi * g(s.diameter) ** 2 / 4
    tors = (g(s.shear_modulus) * polar, g(s.density) * polar, g(s.loss_factor),
            g(s.retardation), g(s.length))
    axi = (g(s.youngs_modulus) * area, g(s.density) * area, g(s.loss_factor),
           g(s.retardation), g(s.length))
    r, a, c, nut = d.rotary, d.axial, d.carriage, d.nut
    iw = 1j * w
    (d0, d1, d2), (e0, e1) = _np_line(
        tors, w, l,
        (iw * g(r.drive_end_damping) - w**2 * g(r.drive_end_inertia),
         iw * g(r.free_end_damping) - w**2 * g(r.free_end_inertia)))
    kc = g(r.coupling_stiffness) + iw * g(r.coupling_damping)
    dm = kc - w**2 * g(r.motor_inertia) + iw * g(r.motor_damping)
    rotary = ([dm, d0 + kc, d1, d2], [-kc, e0, e1])
    axial = _np_line(
        axi, w, l,
        (g(a.drive_end_stiffness) + iw * g(a.drive_end_damping) - w**2 * g(a.drive_end_mass),
         g(a.free_end_stiffness) + iw * g(a.free_end_damping)))
    ya = 1 / (-(w**2) * g(c.mass) + iw * g(c.axial_damping))
    yp = 1 / (g(c.pitch_stiffness) - w**2 * g(c.pitch_inertia) + iw * g(c.pitch_damping))
    heights = (g(c.nut_height), g(c.scale_height), g(c.tool_height))
    kj = g(nut.stiffness) + iw * g(nut.damping)
    return rotary, axial, ya, yp, heights, g(s.lead) / (2 * np.pi), kj


def numpy_drive_frf(d, pos, freq):
    """H_M (n_pos, n_freq, 3, 2) in plain NumPy with broadcasting, fdjax's closed forms."""
    (diag, off), ((a0, a1, a2), (f0, f1)), ya, yp, (hn, h2, h3), isc, kj = _np_lines(d, pos, freq)
    A = [diag[0]]
    for i in range(1, 4):
        A.append(diag[i] - off[i - 1] ** 2 / A[i - 1])
    Bs = [None, None, None, diag[3]]
    for i in range(2, -1, -1):
        Bs[i] = diag[i] - off[i] ** 2 / Bs[i + 1]
    h11 = 1 / (A[0] + Bs[0] - diag[0])
    hll = 1 / (A[2] + Bs[2] - diag[2])
    h1l = hll * (-off[0] / A[0]) * (-off[1] / A[1])
    ha = 1 / (a1 - f0**2 / a0 - f1**2 / a2)
    hs = lambda i, j: ya + yp * i * j  # noqa: E731
    # LM-FBS at the nut, B = [0, −i_sc, −1, 1, 0, 0]
    bracket = isc**2 * hll + ha + hs(hn, hn) + 1 / kj
    u = [-isc * h1l, hs(h2, hn), hs(h3, hn)]  # (Y Bᵀ) rows θ1, x2, x3
    v = [-isc * h1l, hs(hn, h3)]  # (B Y) columns T1, F3
    y0 = [[h11, 0.0], [0.0, hs(h2, h3)], [0.0, hs(h3, h3)]]
    shape = (pos.shape[0], freq.shape[0])
    H = np.empty((*shape, 3, 2), np.complex128)
    for i in range(3):
        for j in range(2):
            H[..., i, j] = y0[i][j] - u[i] * v[j] / bracket
    return H


def _np_tridiag(diag, off):
    n = len(diag)
    shape = np.broadcast_shapes(*[np.shape(x) for x in (*diag, *off)])
    D = np.zeros((*shape, n, n), complex)
    for i in range(n):
        D[..., i, i] = diag[i]
    for i in range(n - 1):
        D[..., i, i + 1] = D[..., i + 1, i] = off[i]
    return D


def numpy_drive_frf_matrix(d, pos, freq):
    """The same H_M written the plain NumPy way: substructure receptances by ``np.linalg.inv``
    of their (batched) dynamic-stiffness matrices, then LM-FBS with batched matrix products."""
    rotary, axial, ya, yp, heights, isc, kj = _np_lines(d, pos, freq)
    YR = np.linalg.inv(_np_tridiag(*rotary))
    YA = np.linalg.inv(_np_tridiag(*axial))
    h = np.array(heights)
    shape = YR.shape[:-2]
    Y = np.zeros((*shape, 6, 6), complex)
    Y[..., :2, :2] = YR[..., [0, 2], :][..., :, [0, 2]]
    Y[..., 2, 2] = YA[..., 1, 1]
    Y[..., 3:, 3:] = (ya[..., None, None] + yp[..., None, None] * np.outer(h, h))
    B = np.array([[0.0, -isc, -1.0, 1.0, 0.0, 0.0]])
    Yj = (1 / kj)[..., None, None]
    YBt = Y @ B.T
    Yc = Y - YBt @ np.linalg.inv(B @ YBt + Yj) @ (B @ Y)
    return Yc[..., [0, 4, 5], :][..., :, [0, 5]]


def numpy_three_mass_frf(model, freq):
    w = 2 * np.pi * freq[:, None, None]
    M, K, C = (np.asarray(x) for x in (model.mass, model.stiffness, model.damping))
    return np.linalg.inv(K - w**2 * M + 1j * w * C)


# ----------------------------------------------------------------------------- runs
def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "frf_sweep.json"))
    args = ap.parse_args()

    drive = fdjax.table1_drive()
    pos_np = np.linspace(0.1, 0.7, N_POS)
    freq_np = np.geomspace(1.0, 2500.0, N_FREQ)
    pos, freq = jnp.asarray(pos_np), jnp.asarray(freq_np)
    points = N_POS * N_FREQ

    # correctness first: fdjax and the baseline agree
    H_fd = np.asarray(drive.frf(pos, freq))
    H_np = numpy_drive_frf(drive, pos_np, freq_np)
    drive_err = float(np.max(np.abs(H_fd - H_np) / (np.abs(H_np) + 1e-300 + np.abs(H_np).max(
        axis=1, keepdims=True) * 1e-12)))

    t_fd, _ = median_time(lambda: drive.frf(pos, freq), args.repeats)
    t_np, _ = median_time(lambda: numpy_drive_frf(drive, pos_np, freq_np), args.repeats)
    H_npm = numpy_drive_frf_matrix(drive, pos_np, freq_np)
    drive_err_m = float(np.max(np.abs(H_fd - H_npm) / np.abs(H_npm)))
    # the matrix baseline takes seconds a call: half the repeats (recorded in the results)
    matrix_repeats = max(1, args.repeats // 2)
    t_npm, _ = median_time(lambda: numpy_drive_frf_matrix(drive, pos_np, freq_np),
                           matrix_repeats)

    # gradient of a scalar of the whole H_M grid (all six entries, each normalised by its
    # median magnitude so every entry counts) with respect to every drive parameter
    scale = np.median(np.abs(H_fd), axis=(0, 1))

    def scalar(d):
        H = d.receptance_entries(pos[:, None], 2 * jnp.pi * freq[None, :])
        return sum(jnp.sum(jnp.abs(H[i][j]) ** 2) / scale[i, j] ** 2
                   for i in range(3) for j in range(2))

    fwd = eqx.filter_jit(scalar)
    grd = eqx.filter_jit(eqx.filter_grad(scalar))
    t_scalar, _ = median_time(lambda: fwd(drive), args.repeats)
    t_grad, _ = median_time(lambda: jax.tree_util.tree_leaves(grd(drive)), args.repeats)

    model = fdjax.three_mass()
    f3_np = np.linspace(1.0, 500.0, N_3M)
    f3 = jnp.asarray(f3_np)
    H3_fd, H3_np = np.asarray(model.frf(f3)), numpy_three_mass_frf(model, f3_np)
    three_err = float(np.max(np.abs(H3_fd - H3_np)) / np.max(np.abs(H3_np)))
    t3_fd, _ = median_time(lambda: model.frf(f3), args.repeats)
    t3_np, _ = median_time(lambda: numpy_three_mass_frf(model, f3_np), args.repeats)

    rows = {
        "drive_frf_256x4096": {
            "points": points,
            "fdjax_s": t_fd, "numpy_s": t_np,
            "fdjax_points_per_s": points / t_fd, "numpy_points_per_s": points / t_np,
            "speedup": t_np / t_fd, "max_rel_diff": drive_err,
            "baseline": "NumPy, same closed-form algebra (Schur complements, scalar LM-FBS)",
        },
        "drive_frf_256x4096_numpy_matrix": {
            "points": points,
            "fdjax_s": t_fd, "numpy_s": t_npm,
            "fdjax_points_per_s": points / t_fd, "numpy_points_per_s": points / t_npm,
            "speedup": t_npm / t_fd, "max_rel_diff": drive_err_m,
            "numpy_repeats": matrix_repeats,
            "baseline": "NumPy, matrix form (np.linalg.inv of substructure dynamic stiffness, "
                        "batched LM-FBS matrix products)",
        },
        "three_mass_frf_1M": {
            "points": N_3M,
            "fdjax_s": t3_fd, "numpy_s": t3_np,
            "fdjax_points_per_s": N_3M / t3_fd, "numpy_points_per_s": N_3M / t3_np,
            "speedup": t3_np / t3_fd, "max_rel_diff": three_err,
        },
        "drive_grad_vs_forward": {
            "scalar": "sum over the grid of |H_ij|^2 / median|H_ij|^2, all six entries",
            "parameters": len(jax.tree_util.tree_leaves(drive)),
            "forward_scalar_s": t_scalar, "grad_s": t_grad, "frf_forward_s": t_fd,
            "ratio": t_grad / t_scalar, "ratio_vs_frf": t_grad / t_fd,
        },
    }
    result = {
        "benchmark": "frf_sweep",
        "repeats": args.repeats,
        "statistic": "median",
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpu_count": os.cpu_count(), "jax": jax.__version__,
                    "numpy": np.__version__, "device": str(jax.devices()[0])},
        "results": rows,
    }
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=2)
    print(f"{'case':32s} {'fdjax Mpt/s':>12s} {'numpy Mpt/s':>12s} {'speed-up':>9s}")
    for k in ("drive_frf_256x4096", "drive_frf_256x4096_numpy_matrix", "three_mass_frf_1M"):
        r = rows[k]
        print(f"{k:32s} {r['fdjax_points_per_s'] / 1e6:12.2f} "
              f"{r['numpy_points_per_s'] / 1e6:12.2f} {r['speedup']:8.1f}×")
    g = rows["drive_grad_vs_forward"]
    print(f"grad of a scalar over the drive grid: {g['grad_s'] * 1e3:.0f} ms = "
          f"{g['ratio']:.2f}× its forward ({g['forward_scalar_s'] * 1e3:.0f} ms), "
          f"{g['ratio_vs_frf']:.2f}× drive.frf ({g['frf_forward_s'] * 1e3:.0f} ms)")
    print(f"agreement: drive {drive_err:.1e}, 3M2S {three_err:.1e} (max relative)")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
