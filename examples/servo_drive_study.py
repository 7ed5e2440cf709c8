"""A drive whose dynamics pose the paper's control problem: the candidate for the next reference.

Tried as a servo engineer would (the sampled loop as it runs at 8 kHz with two periods of
delay, stability from the eigenvalues of the sampled closed loop), this script measures, on the
candidate drive below and its double-loop controller with an MCM:

  (a) its modes of h21 at Y_table = 115 mm against the paper's Table 1;
  (b) how far the speed-loop gain k_v can be raised with the MCM, without it, with the notch
      alone, and with the peak filter centred 30 % above or below mode 3 (other gains held);
  (c) the k_v headroom of that controller held fixed over the travel, and with its seven filter
      parameters re-tuned (Nelder–Mead on the largest stable k_v) at three positions;
  (d) a PID on the scale, all gains scaled together to 6 dB of gain headroom at 115 mm, over the
      travel.

The drive: a heavy Y axis — a 1000 kg saddle with its X table and workpiece on a hollow 63×10
ball screw, held axially at the motor end only (fixed–supported, so the axial stiffness at the
nut falls toward the screw end), driven through a stiff lamina coupling.  Each parameter comes
with its unit, a plausible range and the reason (``PARAMETERS``).

Run: ``python examples/servo_drive_study.py`` (≈ 6 min on 2 CPU cores; ``--quick`` skips the
re-tuning, ≈ 2 min).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import scipy.optimize as so

import fdjax
from fdjax import MCM, DoubleLoop, NotchFilter, PeakFilter, PIDLoop

TWO_PI = 2.0 * math.pi

# (attribute path, value, unit, (plausible low, high), reason)
PARAMETERS = [
    ("screw.length", 0.85, "m", (0.75, 1.0), "bearing span: 600 mm travel, a 150 mm nut, ends"),
    ("screw.diameter", 0.0575, "m", (0.050, 0.060),
     "effective diameter of a 63 mm screw (root ≈ 57 mm)"),
    ("screw.bore_diameter", 0.032, "m", (0.0, 0.040), "bored (coolant) screw, 12 mm wall"),
    ("screw.lead", 0.010, "m", (0.005, 0.020), "catalogue 63×10 screw: i_sc = 1.59 mm/rad"),
    ("screw.retardation", 1.0e-6, "s", (1e-8, 1e-5), "steel: ζ = βω/2 ≈ 0.3 % at 1 kHz"),
    ("rotary.motor_inertia", 3.0e-3, "kg·m²", (1.5e-3, 1.5e-2),
     "rotor of a ~20 N·m servo motor with its hub"),
    ("rotary.coupling_stiffness", 2.0e6, "N·m/rad", (2e5, 3e6),
     "lamina (disc) coupling for 60 mm shafts, stiff end"),
    ("rotary.coupling_damping", 0.15, "N·m·s/rad", (0.01, 1.0), "steel discs: ζ below 1 %"),
    ("rotary.motor_damping", 0.05, "N·m·s/rad", (1e-3, 0.05),
     "motor bearings and seal, linearised (upper end)"),
    ("rotary.drive_end_inertia", 7.7e-4, "kg·m²", (3e-4, 3e-3),
     "screw-side hub, bearing rings, lock nut"),
    ("rotary.drive_end_damping", 1.0e-3, "N·m·s/rad", (1e-3, 1.0),
     "preloaded bearing friction (lower end)"),
    ("rotary.free_end_inertia", 3.0e-4, "kg·m²", (5e-5, 1e-3),
     "free-end bearing rings and lock nut"),
    ("rotary.free_end_damping", 5.0e-3, "N·m·s/rad", (1e-3, 1.0), "free-end bearing friction"),
    ("axial.drive_end_stiffness", 2.0e9, "N/m", (5e8, 3e9),
     "angular-contact thrust set of a 63 mm screw with housing"),
    ("axial.drive_end_damping", 490.0, "N·s/m", (1e2, 5e4), "bearing-housing damping"),
    ("axial.free_end_stiffness", 0.0, "N/m", (0.0, 0.0),
     "fixed–supported: the free end takes no axial load"),
    ("axial.drive_end_mass", 5.0, "kg", (1.0, 10.0), "bearing inner rings, spacer, lock nut, hub"),
    ("carriage.mass", 1000.0, "kg", (250.0, 1500.0), "saddle carrying the X table and workpiece"),
    ("carriage.pitch_inertia", 50.0, "kg·m²", (25.0, 80.0),
     "m(a² + h²)/12 of a 0.75 m × 0.25 m saddle ≈ 52"),
    ("carriage.pitch_stiffness", 5.5e6, "N·m/rad", (5e6, 7e8),
     "blocks with saddle and column bending in series (soft end)"),
    ("carriage.axial_damping", 9.1e4, "N·s/m", (1e2, 1e5),
     "guideways with damping carriages, pre-sliding (upper end)"),
    ("carriage.pitch_damping", 2800.0, "N·m·s/rad", (1e2, 1e5), "ζ ≈ 10 % guideway joint damping"),
    ("carriage.nut_height", -0.12, "m", (-0.20, -0.02), "screw axis below the pitch centre"),
    ("carriage.scale_height", -0.20, "m", (-0.25, -0.02), "linear scale at the saddle base"),
    ("carriage.tool_height", 0.30, "m", (0.0, 0.50), "tool point above the pitch centre"),
    ("nut.stiffness", 4.0e9, "N/m", (1e9, 4e9),
     "preloaded double nut of a 63 mm screw (catalogue top)"),
    ("nut.damping", 5100.0, "N·s/m", (1e2, 3e4), "nut joint damping"),
    ("nut_offset", 0.08, "m", (0.05, 0.15), "nut 80 mm from the thrust bearing at Y_table = 0"),
]


def candidate_drive() -> fdjax.BallScrewDrive:
    """The candidate drive of ``PARAMETERS`` (travel 0.1–0.7 m)."""
    p = {path: value for path, value, *_ in PARAMETERS}

    def part(prefix):
        return {k.split(".", 1)[1]: v for k, v in p.items() if k.startswith(prefix + ".")}

    return fdjax.BallScrewDrive(
        fdjax.Screw(**part("screw")), fdjax.Rotary(**part("rotary")), fdjax.Axial(**part("axial")),
        fdjax.Carriage(**part("carriage")), fdjax.NutJoint(**part("nut")),
        nut_offset=p["nut_offset"], travel_m=(0.1, 0.7),
    )


# The controller, tuned at 115 mm: k_p = 200 1/s (K_v factor 12 m/min/mm), k_i = 60 rad/s; the
# MCM's filters maximise the largest stable k_v there; k_v leaves ≥ 6 dB headroom everywhere the
# filters are re-tuned.
GAINS = dict(kp=200.0, ki=60.0)
KV = 5400.0
FILTERS = dict(K=0.34, f_peak=174.0, xi=0.20, phi_deg=-50.0,
               f_notch=1260.0, zeta_n=0.005, zeta_d=0.34)


def mcm(K, f_peak, xi, phi_deg, f_notch, zeta_n, zeta_d) -> MCM:
    return MCM(PeakFilter(K, TWO_PI * f_peak, xi, math.radians(phi_deg)),
               NotchFilter(TWO_PI * f_notch, zeta_n, zeta_d))


def stable(controller, drive, position_m) -> bool:
    st = fdjax.check_stability(controller, drive, position_m=np.atleast_1d(float(position_m)))
    return bool(np.asarray(st.stable)[0])


KV_GRID = np.geomspace(100.0, 1e5, 22)


def kv_max(filters, drive, position_m) -> float:
    """The largest stable k_v (other gains held): a log grid, then bisection at its top edge.
    0 when no k_v on the grid is stable."""
    def ok(kv):
        return stable(DoubleLoop(GAINS["kp"], kv, GAINS["ki"], mcm=filters), drive, position_m)

    flags = [ok(k) for k in KV_GRID]
    if not any(flags):
        return 0.0
    i = max(j for j, f in enumerate(flags) if f)
    if i == len(KV_GRID) - 1:
        return float(KV_GRID[-1])
    a, b = math.log(KV_GRID[i]), math.log(KV_GRID[i + 1])
    for _ in range(12):
        mid = 0.5 * (a + b)
        a, b = (mid, b) if ok(math.exp(mid)) else (a, mid)
    return math.exp(a)


def stable_range(filters, drive, position_m, lo, hi, n=12) -> bool:
    """Whether every k_v of a log grid over [lo, hi] is stable (no window of instability)."""
    return all(stable(DoubleLoop(GAINS["kp"], k, GAINS["ki"], mcm=filters), drive, position_m)
               for k in np.geomspace(lo, hi, n))


def pid_scale_max(drive, position_m) -> float:
    """The largest stable scale of all PIDLoop() gains together (bisection in log)."""
    base = PIDLoop()

    def ok(s):
        return stable(PIDLoop(s * base.kp, s * base.ki, s * base.kd, base.wd), drive, position_m)

    a, b = math.log(1e-2), math.log(1e3)
    for _ in range(30):
        mid = 0.5 * (a + b)
        a, b = (mid, b) if ok(math.exp(mid)) else (a, mid)
    return math.exp(a)


def retune(drive, position_m, start: dict, max_evals=200) -> tuple[dict, float]:
    """Nelder–Mead on the seven filter parameters for the largest stable k_v at a position."""
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
        return -math.log(max(kv_max(mcm(**f), drive, position_m), 1e-3))

    res = so.minimize(objective, x0, method="Nelder-Mead", options=dict(maxfev=max_evals))
    return unpack(res.x), math.exp(-res.fun)


def main(quick: bool):
    t0 = time.perf_counter()
    drive = candidate_drive()
    for path, value, unit, (lo, hi), why in PARAMETERS:
        assert lo <= value <= hi, path
    y = fdjax.TABLE_1_POSITION_M

    print("(a) modes of h21 at 115 mm against Table 1 (f Hz, ζ, phase °):")
    m = fdjax.drive_modes(drive, y, n_modes=6)
    t1 = fdjax.TABLE_1
    for i in range(5):
        print(f"    model {float(m.frequency_hz[i]):7.1f} {float(m.damping_ratio[i]):.3f} "
              f"{float(m.phase_deg[i]):7.1f}   Table 1 {float(t1.frequency_hz[i]):7.1f} "
              f"{float(t1.damping_ratio[i]):.3f} {float(t1.phase_deg[i]):7.1f}")
    f3 = [float(fdjax.drive_modes(drive, q, n_modes=3).frequency_hz[1]) for q in (0.1, 0.4, 0.7)]
    print(f"    the saddle's axial mode (the peak filter's target) at 0.1/0.4/0.7 m: "
          f"{np.round(f3, 1)} Hz")

    F = FILTERS
    with_mcm = kv_max(mcm(**F), drive, y)
    without = kv_max(MCM(), drive, y)
    notch_only = kv_max(MCM(None, mcm(**F).notch), drive, y)
    up = kv_max(mcm(**{**F, "f_peak": 1.3 * F["f_peak"]}), drive, y)
    down = kv_max(mcm(**{**F, "f_peak": 0.7 * F["f_peak"]}), drive, y)
    print(f"(b) largest stable k_v at 115 mm: MCM {with_mcm:.0f}, none {without:.0f} "
          f"({with_mcm / without:.1f}×), notch alone {notch_only:.0f}; peak +30 % "
          f"{up / with_mcm:.2f}×, −30 % {down / with_mcm:.2f}× of the MCM's")

    positions = np.round(np.arange(0.1, 0.701, 0.05), 3)
    fixed = np.array([kv_max(mcm(**F), drive, q) for q in positions])
    print("(c) fixed controller, k_v headroom (dB) over", positions)
    print("   ", np.round(20 * np.log10(np.maximum(fixed, 1e-9) / KV), 1))
    print(f"    at 115 mm: {20 * math.log10(with_mcm / KV):.1f} dB; "
          f"k_v = {KV:.0f} stable from k_v/4 up: "
          f"{stable_range(mcm(**F), drive, y, KV / 4, KV)}")
    if not quick:
        for q in (0.4, 0.55, 0.7):
            start = {**F, "f_peak": float(fdjax.drive_modes(drive, q, n_modes=3).frequency_hz[1])}
            best, kv_q = retune(drive, q, start)
            print(f"    re-tuned at {q} m: headroom {20 * math.log10(kv_q / KV):.1f} dB, stable "
                  f"over [k_v/4, k_v]: {stable_range(mcm(**best), drive, q, KV / 4, KV)}; "
                  + ", ".join(f"{k} {v:.4g}" for k, v in best.items()))

    s115 = pid_scale_max(drive, y)
    pid = np.array([pid_scale_max(drive, q) for q in positions])
    print("(d) PID at 6 dB gain headroom at 115 mm, headroom (dB) over the travel:")
    print("   ", np.round(20 * np.log10(pid / (s115 / 2)), 2))
    print(f"done in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the re-tuning")
    main(ap.parse_args().quick)
