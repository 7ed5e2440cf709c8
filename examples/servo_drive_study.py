"""The reference drive poses the paper's control problem: measured as a servo engineer would.

On the sampled loop as it runs (8 kHz, two periods of delay; stability from the eigenvalues of
the sampled closed loop, :func:`fdjax.gain_headroom`), this script measures on
:func:`fdjax.reference_drive` and :func:`fdjax.reference_controller`:

  (a) the modes of h21 at Y_table = 115 mm against the paper's Table 1;
  (b) how far the speed-loop gain k_v can be raised with the MCM, without it, with the notch
      alone, and with the peak filter centred 30 % above or below its mode (other gains held);
  (c) the k_v headroom of that controller held fixed over the travel, and with its seven filter
      parameters re-tuned (Nelder–Mead on the headroom) at three positions;
  (d) :func:`fdjax.reference_pid` (a PID on the scale, all gains scaled together to 6 dB of
      headroom at 115 mm) over the travel.

The drive's parameters, each with its unit, plausible range and reason, are
``fdjax.REFERENCE_PARAMETERS``.

Run: ``python examples/servo_drive_study.py`` (≈ 1 min on 2 CPU cores; ``--quick`` skips the
re-tuning; the figure goes to ``build/headroom_over_travel.png``, or ``--out
docs/figures/headroom_over_travel.png`` for the README's).
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np
import scipy.optimize as so

import fdjax
from fdjax import MCM, DoubleLoop, NotchFilter, PeakFilter

TWO_PI = 2.0 * math.pi
GAINS = dict(kp=200.0, ki=60.0)  # the reference controller's
KV = 5400.0


def mcm(K, f_peak, xi, phi_deg, f_notch, zeta_n, zeta_d) -> MCM:
    return MCM(PeakFilter(K, TWO_PI * f_peak, xi, math.radians(phi_deg)),
               NotchFilter(TWO_PI * f_notch, zeta_n, zeta_d))


def filters_of(m: MCM) -> dict:
    p, n = m.peak, m.notch
    return dict(K=float(p.K[0]), f_peak=float(p.omega[0]) / TWO_PI, xi=float(p.xi[0]),
                phi_deg=math.degrees(float(p.phi[0])), f_notch=float(n.omega[0]) / TWO_PI,
                zeta_n=float(n.zeta_n[0]), zeta_d=float(n.zeta_d[0]))


def kv_max(filters, drive, position_m, kv=KV) -> float:
    """The largest stable k_v (other gains held), from a stable k_v."""
    loop = DoubleLoop(GAINS["kp"], kv, GAINS["ki"], mcm=filters)
    return kv * float(fdjax.gain_headroom(loop, drive, position_m=position_m))


def retune(drive, position_m, start: dict, max_evals=250) -> tuple[dict, float]:
    """Nelder–Mead on the seven filter parameters for the largest k_v headroom at a position."""
    keys = list(start)
    logs = {"f_peak", "xi", "f_notch", "zeta_n", "zeta_d"}
    x0 = np.array([math.log(start[k]) if k in logs else start[k] for k in keys])

    def unpack(x):
        return {k: (math.exp(v) if k in logs else v) for k, v in zip(keys, x)}

    def objective(x):
        f = unpack(x)
        if not (0 <= f["K"] < 2 and 0.03 < f["xi"] < 0.6 and -90 < f["phi_deg"] < 90
                and f["zeta_n"] < 0.5 * f["zeta_d"] < 0.5 and f["f_notch"] < 3900):
            return 1e3
        loop = DoubleLoop(GAINS["kp"], KV, GAINS["ki"], mcm=mcm(**f))
        g = float(fdjax.gain_headroom(loop, drive, position_m=position_m, rtol=3e-3))
        return -math.log(max(g, 1e-6))

    res = so.minimize(objective, x0, method="Nelder-Mead", options=dict(maxfev=max_evals))
    # one restart from the result with a fresh simplex: Nelder–Mead's simplex collapses
    res = so.minimize(objective, res.x, method="Nelder-Mead", options=dict(maxfev=max_evals))
    return unpack(res.x), math.exp(-res.fun)


def main(quick: bool, args_out: str):
    t0 = time.perf_counter()
    drive = fdjax.reference_drive()
    y = fdjax.TABLE_1_POSITION_M

    print("(a) modes of h21 at 115 mm (f Hz, ζ, phase °), and Table 1's:")
    m = fdjax.drive_modes(drive, y, n_modes=5)
    t1 = fdjax.TABLE_1
    for i in range(5):
        print(f"    model {float(m.frequency_hz[i]):7.1f} {float(m.damping_ratio[i]):.3f} "
              f"{float(m.phase_deg[i]):7.1f}   Table 1 {float(t1.frequency_hz[i]):7.1f} "
              f"{float(t1.damping_ratio[i]):.3f} {float(t1.phase_deg[i]):7.1f}")
    f2 = [float(fdjax.drive_modes(drive, q, n_modes=2).frequency_hz[1]) for q in (0.1, 0.4, 0.7)]
    print(f"    the saddle's axial mode (the peak filter's target) at 0.1/0.4/0.7 m: "
          f"{np.round(f2, 1)} Hz")

    F = filters_of(fdjax.reference_controller(drive).mcm)
    with_mcm = kv_max(mcm(**F), drive, y)
    without = kv_max(MCM(), drive, y, kv=300.0)  # no k_v above ≈ 375 is stable without it
    notch_only = kv_max(MCM(None, mcm(**F).notch), drive, y)
    up = kv_max(mcm(**{**F, "f_peak": 1.3 * F["f_peak"]}), drive, y)
    down = kv_max(mcm(**{**F, "f_peak": 0.7 * F["f_peak"]}), drive, y)
    print(f"(b) largest stable k_v at 115 mm: MCM {with_mcm:.0f}, none {without:.0f} "
          f"({with_mcm / without:.1f}×), notch alone {notch_only:.0f}; peak +30 % "
          f"{up / with_mcm:.2f}×, −30 % {down / with_mcm:.2f}× of the MCM's")

    positions = np.round(np.arange(0.1, 0.701, 0.05), 3)
    c = fdjax.reference_controller(drive)
    fixed = fdjax.gain_headroom(c, drive, position_m=positions)
    print("(c) the reference controller held fixed, k_v headroom (dB) over", positions)
    print("   ", np.round(20 * np.log10(np.maximum(fixed, 1e-9)), 1), "(−180: unstable)")
    print(f"    at 115 mm: {20 * math.log10(with_mcm / KV):.1f} dB")
    retuned = {}
    if not quick:
        best = F
        for q in (0.4, 0.55, 0.7):  # continuation along the travel: each from the last design
            start = {**best,
                     "f_peak": float(fdjax.drive_modes(drive, q, n_modes=2).frequency_hz[1])}
            best, g = retune(drive, q, start)
            retuned[q] = g
            print(f"    re-tuned at {q} m: headroom {20 * math.log10(g):.2f} dB; "
                  + ", ".join(f"{k} {v:.5g}" for k, v in best.items()))

    pid = fdjax.gain_headroom(fdjax.reference_pid(), drive, position_m=positions)
    print("(d) reference_pid() (6 dB at 115 mm), headroom (dB) over the travel:")
    print("   ", np.round(20 * np.log10(pid), 2))
    plot(positions, fixed, pid, retuned, args_out)
    print(f"done in {time.perf_counter() - t0:.0f} s")


def plot(positions, fixed, pid, retuned, out):
    """Gain headroom over the travel: the MCM held fixed, re-tuned, and the PID."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def db(g):
        return np.where(np.asarray(g) > 0, 20 * np.log10(np.maximum(g, 1e-300)), np.nan)

    mm = 1e3 * np.asarray(positions)
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    ax.plot(mm, db(fixed), "o-", label="reference controller, MCM tuned at 115 mm, held fixed")
    bad = np.asarray(fixed) == 0
    ax.plot(mm[bad], np.zeros(bad.sum()), "x", color="C0", ms=9, mew=2, label="… unstable")
    if retuned:
        ax.plot([1e3 * q for q in retuned], db(list(retuned.values())), "s", ms=8,
                label="MCM's seven parameters re-tuned there")
    ax.plot(mm, db(pid), "^-", label="PID, all gains set to 6 dB at 115 mm")
    ax.axhline(6.0, color="0.5", ls="--", lw=0.8)
    ax.axvline(115.0, color="0.7", lw=0.8)
    ax.set(xlabel="table position $Y_{table}$ (mm)", ylabel="gain headroom (dB)",
           title="Reference drive: loop-gain headroom over the travel (sampled loop, 8 kHz)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"written {out}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--quick", action="store_true", help="skip the re-tuning")
    ap.add_argument("--out", default="build/headroom_over_travel.png",
                    help="where to write the figure (the README's: "
                         "docs/figures/headroom_over_travel.png)")
    a = ap.parse_args()
    main(a.quick, a.out)
