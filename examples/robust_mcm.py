"""The best single MCM with every margin kept over the travel, beside the schedules.

Fig. 18's robust PID is the best single PID that keeps the margins at every position, and its
robust MCM (``mcm_robust`` of the shipped designs) the best single double loop with its MCM
that the synthesis finds: one design (gains and filters) tuned by ``fdjax.tune_robust``
(L-BFGS on the smooth maximum of the synthesis's objective,
``fdjax.tuning_objective(margin_width=0.01)``, over 13 positions 100–700 mm) from the
end-to-end schedule at 700 mm.  This script runs the same tuning from another start, the
local design at 700 mm of ``examples/screw_end_design.py`` (another basin: higher k_p, lower
k_v, a broad peak filter near 420 Hz), which keeps its margins only near the screw end.

The robust designs are evaluated every 10 mm (RMS error, exact sampled margins) and certified
every 1 mm, beside the shipped schedules.  With ``--schedule`` the synthesis's schedule stages
run again from the new robust design: six MCMs with common gains
(``fdjax.tune_shared_gains``), the ATA network fitted to them (``fdjax.fit_network``) and
trained end to end (``fdjax.train_schedule``, network and gains).

Measured on 2 cores (about 2 minutes; 1 more with ``--from-reference``, 1.5 more with
``--schedule``):

- the shipped robust MCM: 83.59–83.69 µm over the travel, certified at 601 positions (least
  modulus margin 0.523, gain margin 7.04 dB): 1 % below the shipped end-to-end schedule
  (84.34–84.60 µm) and 4.5 % below the backpropagation schedule (87.65 µm);
- from the screw-end design: 81.77–81.87 µm, certified at 601 positions (modulus margin
  0.512, gain margin 6.25 dB): one fixed design 3.2 % below the shipped end-to-end schedule
  (an earlier run reached 80.79–80.88 µm: the search amplifies round-off);
- ``--schedule``: the backpropagation schedule reaches 79.12–79.14 µm (certified at 601
  positions, modulus margin 0.501, gain margin 6.17 dB), 3.3 % below the fixed design it
  started from; trained end to end it returns to 81.29–81.39 µm, trading error for room above
  the margin requirements (its training objective, which carries the margin penalties, falls
  from 1.510 to 0.829);
- ``--from-reference``: the high-gain reference controller (k_v 5400 A·s/m, the peak filter on
  the saddle's axial mode at 174 Hz) has a modulus margin of 0.363 at 115 mm, 0.195 at 300 mm
  and 0.028 at 450 mm; tuned at 115 mm with the margins (150 L-BFGS steps) it goes to
  k_v 795 A·s/m with the peak filter at 653 Hz as a lead (69.40 µm, modulus margin 0.522).

The margin requirements put every tuned design at loop gains where the moving modes cost a
fixed design margin but hardly any error, and the filters' optimum moves little over the
travel (the end-to-end schedule's peak filter 819–826 Hz, its phase 28° → 22°; the notch
broad and deep at 1.26 kHz).  So on this drive a schedule of the filters buys a few per cent
of error over one well-tuned fixed MCM; which basin the search starts in matters more.

Usage:  python examples/robust_mcm.py [--steps 120] [--schedule] [--from-reference]
                                      [--out robust_mcm.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import jax
import numpy as np
import optax

import fdjax
from fdjax import reference_servo

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from screw_end_design import THETA  # noqa: E402

DESIGN_POSITIONS_M = np.linspace(0.1, 0.7, 6)  # the six local designs' positions
ROBUST_POSITIONS_M = np.linspace(0.1, 0.7, 13)
# one optimiser object for every tuning: a compiled step is keyed on it (same object, no
# recompilation)
LBFGS = optax.lbfgs()
FIG18_POSITIONS_M = np.linspace(0.1, 0.7, 61)


def describe(c) -> str:
    pk, nt = c.mcm.peak, c.mcm.notch
    return (f"k_p {c.kp:.1f} 1/s, k_v {c.kv:.1f} A·s/m, k_i {c.ki:.2f} rad/s; peak K "
            f"{float(pk.K[0]):.2f}, {float(pk.omega[0]) / (2 * math.pi):.1f} Hz, ξ "
            f"{float(pk.xi[0]):.3f}, φ {math.degrees(float(pk.phi[0])):.1f}°; notch "
            f"{float(nt.omega[0]) / (2 * math.pi):.1f} Hz, ζn {float(nt.zeta_n[0]):.2e}, "
            f"ζd {float(nt.zeta_d[0]):.3f}")


def from_reference(par, obj, drive, servo):
    """The high-gain reference controller's margins, and where a local tuning at 115 mm with
    the margins takes it."""
    ref = fdjax.reference_controller(drive, servo)
    ys = [0.115, 0.3, 0.45]
    r = fdjax.evaluate({"ref": ref}, drive, ys, servo=servo, progress=False)["ref"]
    print("reference controller (" + describe(ref) + "):")
    for i, y in enumerate(ys):
        print(f"  {y * 1e3:.0f} mm: modulus margin {r['modulus_margin'][i]:.3f}, gain margin "
              f"{r['gain_margin_db'][i]:.2f} dB, phase margin {r['phase_margin_deg'][i]:.1f}°")
    t = fdjax.tune_local(par, obj, drive, [0.115], par.from_controller(ref), steps=150,
                         optimiser=LBFGS, chunk=10)
    c = par.to_controller(t.best_theta[0])
    r = fdjax.evaluate({"c": c}, drive, [0.115], servo=servo, progress=False)["c"]
    print(f"tuned at 115 mm from it (150 L-BFGS steps, feedback only): {r['rms_error_um'][0]:.2f} "
          f"µm, modulus margin {r['modulus_margin'][0]:.3f}\n  {describe(c)}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--steps", type=int, default=120,
                    help="L-BFGS steps of each robust tuning (default 120)")
    ap.add_argument("--schedule", action="store_true",
                    help="also run the schedule stages from the second robust design")
    ap.add_argument("--from-reference", action="store_true",
                    help="also tune at 115 mm from the high-gain reference controller")
    ap.add_argument("--out", default=None, help="write the table as JSON here")
    args = ap.parse_args(argv)
    drive, servo = fdjax.reference_drive(), reference_servo()
    bounds = fdjax.MCMBounds.for_servo(servo)
    par = fdjax.DoubleLoopParameterisation(bounds, fdjax.reference_controller(drive, servo),
                                           feedforward=False)
    obj = fdjax.tuning_objective(servo, margin_width=0.01)
    shipped, _ = fdjax.load_designs()
    if args.from_reference:
        from_reference(par, obj, drive, servo)
    name = "robust, from the screw-end design"
    t0 = time.perf_counter()
    r = fdjax.tune_robust(par, obj, drive, ROBUST_POSITIONS_M, np.asarray(THETA),
                          steps=args.steps, optimiser=LBFGS, chunk=10)
    c = par.to_controller(r.best_theta)
    print(f"{name}: J {float(np.min(r.history)):.4f} after {args.steps} steps "
          f"({time.perf_counter() - t0:.0f} s)\n  {describe(c)}", flush=True)
    print(f"shipped robust MCM:\n  {describe(shipped['mcm_robust'])}", flush=True)
    controllers = {"shipped mcm_robust": shipped["mcm_robust"], name: c}
    if args.schedule:
        th = par.from_controller(c)
        design = np.asarray(DESIGN_POSITIONS_M)
        shared = fdjax.tune_shared_gains(par, obj, drive, design, th, steps=100,
                                         optimiser=LBFGS, chunk=10)
        loop = par.to_controller(shared.best_theta[0])
        net0 = fdjax.ATANetwork(drive.travel_m, width=8, key=jax.random.PRNGKey(0))
        net, _ = fdjax.fit_network(net0, design, shared.best_theta[:, 5:], steps=4000)
        bp = fdjax.ScheduledLoop(loop, net, bounds)
        e2e, rec = fdjax.train_schedule(bp, obj, drive, steps=60,
                                      positions_m=np.linspace(*drive.travel_m, 13),
                                      train_gains=True, optimiser=LBFGS,
                                      chunk=10)
        print(f"end to end: training objective {float(rec.history[0]):.4f} -> "
              f"{float(np.min(rec.history)):.4f}", flush=True)
        controllers["schedule from it, backpropagation"] = bp
        controllers["schedule from it, end to end"] = e2e
    controllers["shipped mcm_ata"] = shipped["mcm_ata"]
    controllers["shipped mcm_ata_e2e"] = shipped["mcm_ata_e2e"]
    res = fdjax.evaluate(controllers, drive, FIG18_POSITIONS_M, servo=servo, progress=False)
    table = {}
    print(f"\n{'controller':50s} {'RMS 100 mm':>10s} {'700 mm':>8s} {'worst':>8s} "
          f"{'MM':>6s} {'GM (dB)':>8s} {'PM (°)':>7s}  every 1 mm")
    for name, r in res.items():
        rms = [v for v in r["rms_error_um"] if v is not None]
        cert = fdjax.certify(controllers[name], drive, servo=servo)
        row = {"rms_error_um": r["rms_error_um"], "modulus_margin": r["modulus_margin"],
               "gain_margin_db": r["gain_margin_db"], "phase_margin_deg": r["phase_margin_deg"],
               "stable": r["stable"], "certified_every_1mm": bool(cert.ok),
               "certificate": cert.message}
        table[name] = row
        worst = f"{max(rms):8.2f}" if len(rms) == len(r["rms_error_um"]) else "unstable"
        print(f"{name:50s} {r['rms_error_um'][0] or math.nan:10.2f} "
              f"{r['rms_error_um'][-1] or math.nan:8.2f} {worst:>8s} "
              f"{min(r['modulus_margin']):6.3f} {min(r['gain_margin_db']):8.2f} "
              f"{min(r['phase_margin_deg']):7.1f}  "
              f"{'certified' if cert.ok else 'NOT certified'}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(table, f, indent=1)


if __name__ == "__main__":
    main()
