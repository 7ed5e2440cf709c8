"""Model updating: the Table 1 drive (`fdjax.table1_drive()`), calibrated to the paper's Table 1.

The paper's Table 1 lists the modes of h21 = x2/T1 at Y_table = 115 mm.  ``fdjax.table1_drive()``
ships the calibrated parameters; this script checks them and reproduces the last stage of the
fit with :func:`fdjax.update_model` (bounded Levenberg–Marquardt on the modal residuals through
the eigen-analysis of the finite-element twin), inside the physically plausible bounds below.

How the shipped values were found (≈ 40 min of multi-start runs of ``update_model``):
  1. frequencies only (damping and phase tolerances relaxed to 100 and 10⁴°) over the stiffness
     and inertia parameters, from random starts inside the bounds: the three heavily damped low
     modes come out as the saddle's pitch–axial pair and the coupling mode, which needs a heavy
     saddle, a soft jaw coupling and a large screw-side inertia;
  2. all parameters with the table's tolerances, from the best frequency fit, then a free-end
     (fixed–fixed) axial stiffness and free-end inertia to place modes 4 and 5;
  3. rounded to two digits (the shipped ``table1_drive()``).
The bounds matter more than the optimiser: with a 100 N·m/rad "belt" coupling and a 3 kg·m²
pitch inertia (implausible) an earlier fit met 13 of 15 targets; inside these bounds the best fit
meets 11 (see the README, "Calibration to Table 1", for the shortfall and why).

Run: ``python examples/calibrate_table1.py`` (≈ 30 s on 2 CPU cores).  Point
``fdjax.update_model`` at your own ``fdjax.ModalData`` to update a model of your drive.
"""

import time

import numpy as np

import fdjax

# Physically plausible bounds of the fitted parameters (SI units), with the reason for each.
BOUNDS = {
    # servo motors of ~5–40 N·m for this axis, rotor plus motor-side hub
    "rotary.motor_inertia": (1.5e-3, 1.5e-2),
    # elastomer jaw couplings (soft end) to metal bellows / disc couplings (stiff end)
    "rotary.coupling_stiffness": (2.0e3, 5.0e4),
    # coupling-mode damping ratio from ~0 (bellows) to ~0.2 (elastomer)
    "rotary.coupling_damping": (1.0e-3, 5.0),
    # screw-side coupling hub, bearing rings and lock nut, up to a steel hub for a 50 mm shaft
    "rotary.drive_end_inertia": (1.0e-4, 2.5e-3),
    # rotational friction of preloaded bearings (linearised, small amplitude)
    "rotary.drive_end_damping": (1.0e-3, 1.0),
    # linearised small-amplitude friction of motor bearings and seal (0.05 N·m·s/rad is
    # 5 N·m at 100 rad/s: the most a motor's seal and bearings plausibly add)
    "rotary.motor_damping": (1.0e-3, 0.05),
    # free-end bearing rings and lock nut
    "rotary.free_end_inertia": (5.0e-5, 5.0e-4),
    # from a 250 kg table to a 700 kg saddle carrying the X table and workpiece
    "carriage.mass": (250.0, 700.0),
    # J = m (a² + h²)/12 of a 0.75 m × 0.25 m, 700 kg saddle (36.5 kg·m²) ± 50 %
    "carriage.pitch_inertia": (18.0, 55.0),
    # catalogue leads 5–20 mm
    "screw.lead": (0.005, 0.020),
    # effective diameter of 32–50 mm screws (root diameter less the thread)
    "screw.diameter": (0.025, 0.045),
    # Kelvin–Voigt retardation of steel: negligible (1e-8 s) to ζ ≈ 3 % at 1 kHz
    "screw.retardation": (1.0e-8, 1.0e-5),
    # guideway blocks (4 × 1e8–2e9 N/m at ±0.1–0.3 m) with saddle and bed bending in series
    "carriage.pitch_stiffness": (5.0e6, 7.0e8),
    # pitch-mode damping ratio ~0.1–30 %
    "carriage.pitch_damping": (1.0e2, 1.0e5),
    # equivalent viscous damping of guideway joints at vibration amplitudes (pre-sliding)
    "carriage.axial_damping": (1.0e2, 5.0e4),
    # nut axis and linear scale below the pitch centre (screw and scale at the saddle base)
    "carriage.nut_height": (-0.15, -0.02),
    "carriage.scale_height": (-0.20, -0.02),
    # preloaded single/double nuts of 32–50 mm screws (catalogue 100–1500 N/µm)
    "nut.stiffness": (1.0e8, 1.5e9),
    "nut.damping": (1.0e2, 3.0e4),
    # thrust-bearing pair with support block and housing (the housing softens the bearing)
    "axial.drive_end_stiffness": (1.0e8, 2.0e9),
    "axial.drive_end_damping": (1.0e2, 5.0e4),
    "axial.drive_end_mass": (0.5, 5.0),
    # fixed–fixed screw: the free-end support's axial stiffness
    "axial.free_end_stiffness": (1.0e7, 5.0e8),
}

TOLERANCES = (0.03, 0.25, 15.0)  # frequency (relative), damping (relative), phase (°)


def report(title, res):
    T = res.target
    met = res.within(TOLERANCES)
    print(f"\n{title}: {int(met.sum())} of {met.size} targets met")
    print("mode | Table 1 f, zeta, phase | model f, zeta, phase | df %, dzeta %, dphase deg | met")
    for i in range(T.frequency_hz.shape[0]):
        print(
            f"  {i + 1}  | {float(T.frequency_hz[i]):6.0f} {float(T.damping_ratio[i]):.3f} "
            f"{float(T.phase_deg[i]):6.0f} | {float(res.modes.frequency_hz[i]):7.1f} "
            f"{float(res.modes.damping_ratio[i]):.4f} {float(res.modes.phase_deg[i]):7.1f} | "
            f"{100 * float(res.frequency_error[i]):+5.1f} "
            f"{100 * float(res.damping_error[i]):+6.1f} "
            f"{float(res.phase_error_deg[i]):+7.1f} | "
            f"{''.join('yn'[int(not x)] for x in met[:, i])}"
        )


if __name__ == "__main__":
    import argparse

    # no options: --help describes the script, anything else is refused
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False).parse_args()
    drive = fdjax.table1_drive()
    target, pos = fdjax.TABLE_1, fdjax.TABLE_1_POSITION_M
    # the shipped drive as it is: no steps, only the residuals
    t0 = time.perf_counter()
    shipped = fdjax.update_model(drive, target, BOUNDS, pos, tolerances=TOLERANCES, max_steps=0)
    report("shipped table1_drive()", shipped)
    # the last stage of the fit, from the shipped (rounded) values
    res = fdjax.update_model(drive, target, BOUNDS, pos, tolerances=TOLERANCES, max_steps=150)
    report(f"update_model polish ({int(res.steps)} steps, {time.perf_counter() - t0:.0f} s)", res)
    print("\nparameter: shipped -> polished (bounds); * = at a bound")
    for p, (lo, hi) in BOUNDS.items():
        v0, v = float(shipped.parameters[p]), float(res.parameters[p])
        at = "*" if min(abs(np.log(abs(v / lo))), abs(np.log(abs(v / hi)))) < 0.02 else " "
        print(f"  {p:28s} {v0:11.4g} -> {v:11.4g} {at} ({lo:.3g}, {hi:.3g})")
    # cross-check: the modes identified from the exact FRF (no model internals).  Seven terms
    # for the five modes below 2 kHz: one more for the 2.4 kHz mode above the band and one
    # (ζ ≈ 1, below 1 Hz) that absorbs the damped rigid body's real pole at −c_eq/J_eq (1.1 Hz),
    # which the fit's c₀/s² + c₁/s cannot represent.  That spare term makes the least-squares
    # problem non-convex, so the best of three vector-fitting starts (by fit error) is taken,
    # as in tests/test_calibrate.py.
    f = np.geomspace(10.0, 2000.0, 2000)
    h = np.asarray(drive.frf([pos], f))[0, :, 1, 0]
    fits = [
        fdjax.identify_modes(f, h, 7, vf_iterations=i, vf_extra_modes=e, max_steps=1000,
                             throw=False)
        for i, e in ((10, 3), (5, 3), (20, 4))
    ]
    fit = min(fits, key=lambda x: float(x.fit_error))
    print(f"\nidentify_modes on the exact h21 (10–2000 Hz, 7 terms, best of 3 starts, fit "
          f"error {float(fit.fit_error):.1e}): mode, f, zeta, phase")
    rows = zip(*(np.asarray(x)[1:6] for x in (fit.frequency_hz, fit.damping_ratio, fit.phase_deg)))
    for i, (a, b, c) in enumerate(rows):
        print(f"  {i + 1}  {a:8.1f} {b:.4f} {c:7.1f}")
