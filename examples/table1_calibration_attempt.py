"""Work in progress (issue 3): the best fit found so far of the reference drive to Table 1.

The paper's Table 1 lists the modes of h21 = x2/T1 at Y_table = 115 mm.  This parameter set,
found with ``fdjax.update_model`` from several starting points, meets 13 of the 15 targets
(frequency within 3 %, damping within 25 %, phase within 15°); the resonant phases of modes 1
and 2 stay 57–143° away and six parameters sit at their plausibility bounds, so it is not yet
the shipped default.  Run: ``python examples/table1_calibration_attempt.py`` (~15 s).
"""

import operator

import equinox as eqx
import jax
import numpy as np

import fdjax

CHANGES = {  # path: value (SI units)
    "rotary.coupling_stiffness": 100.0,      # N·m/rad  timing-belt stage (was 1.5e4 bellows)
    "rotary.coupling_damping": 0.01415,      # N·m·s/rad
    "rotary.motor_inertia": 2.724e-3,        # kg·m²  rotor + motor pulley
    "carriage.pitch_stiffness": 1.457e6,     # N·m/rad
    "carriage.pitch_inertia": 3.0,           # kg·m²
    "carriage.pitch_damping": 860.2,         # N·m·s/rad
    "carriage.axial_damping": 2.649e4,       # N·s/m
    "carriage.scale_height": 0.100,          # m
    "carriage.nut_height": -0.05584,         # m
    "nut.stiffness": 1.0e9,                  # N/m
    "nut.damping": 5276.0,                   # N·s/m
    "axial.drive_end_stiffness": 1.0e8,      # N/m
    "axial.drive_end_damping": 128.2,        # N·s/m
    "screw.retardation": 1.0e-8,             # s
    "rotary.drive_end_damping": 0.01395,     # N·m·s/rad
    "screw.diameter": 0.02819,               # m
    "screw.lead": 0.008556,                  # m/rev
    "screw.length": 0.9382,                  # m
}


def best_drive():
    d = fdjax.reference_drive()
    paths = list(CHANGES)
    return eqx.tree_at(lambda x: [operator.attrgetter(p)(x) for p in paths], d,
                       [jax.numpy.asarray(CHANGES[p], dtype=jax.numpy.float64) for p in paths])


def wrap180(x):
    return x - 360.0 * np.round(x / 360.0)


if __name__ == "__main__":
    drive = best_drive()
    T = fdjax.TABLE_1
    m = fdjax.drive_modes(drive, 0.115, n_modes=12)
    f, z, ph, pr = (np.asarray(a) for a in (m.frequency_hz, m.damping, m.phase_deg, m.prominence))
    vis = np.where(pr >= 0.05)[0]
    print("all model modes of h21 at Y=115 mm (f Hz, zeta, phase deg, prominence):")
    for k in range(8):
        print(f"  {f[k]:8.1f} {z[k]:.4f} {ph[k]:7.1f} {pr[k]:.3f}")
    print("\nmode | target f/zeta/phase | model f/zeta/phase | df% dzeta% dphase | "
          "prominence | ok(f,z,ph)")
    used = set()
    for i in range(5):
        cand = [k for k in vis if k not in used]
        k = min(cand, key=lambda k: abs(np.log(f[k] / T.frequency_hz[i])))
        used.add(k)
        ef = f[k] / T.frequency_hz[i] - 1
        ez = z[k] / T.damping[i] - 1
        ep = wrap180(ph[k] - T.phase_deg[i])
        ok = tuple(bool(x) for x in (abs(ef) <= 0.03, abs(ez) <= 0.25, abs(ep) <= 15))
        print(f"  {i+1}  | {T.frequency_hz[i]:6.0f} {T.damping[i]:.3f} {T.phase_deg[i]:6.0f} | "
              f"{f[k]:7.1f} {z[k]:.4f} {ph[k]:7.1f} | {ef*100:+5.1f} {ez*100:+6.1f} {ep:+7.1f} | "
              f"{pr[k]:.3f} | {ok}")
    # cross-check: modes identified from the FRF itself
    fr = np.linspace(20.0, 2000.0, 4000)
    h = np.asarray(drive.frf([0.115], fr)[0, :, 1, 0])
    try:
        fit = fdjax.identify_modes(fr, h, 6)
        print("\nidentify_modes on the FRF (20–2000 Hz, 6 modes):")
        cols = (fit.frequency_hz, fit.damping, fit.phase_deg)
        for a, b, c in zip(*(np.asarray(x) for x in cols)):
            print(f"  {a:8.1f} {b:.4f} {c:7.1f}")
    except Exception as e:  # cross-check only
        print("identify_modes failed:", e)
