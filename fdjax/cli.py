"""The ``fdjax`` command line: ``fdjax demo --out DIR``."""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def _peaks(f, a, fmin, fmax):
    k = np.flatnonzero((a[1:-1] > a[:-2]) & (a[1:-1] > a[2:])) + 1
    return f[k[(f[k] >= fmin) & (f[k] <= fmax)]]


def demo(out: str) -> dict:
    """The 3M2S and the reference drive: numbers printed, figures written to ``out``."""
    import fdjax
    from fdjax import plots

    os.makedirs(out, exist_ok=True)
    model = fdjax.three_mass()
    fn, _ = model.modes()
    f3 = np.geomspace(10.0, 1000.0, 4000)
    H3 = np.asarray(model.frf(f3))
    print("3M2S (paper Sec. 2): natural frequencies "
          + ", ".join(f"{x:.1f} Hz" for x in np.asarray(fn)[1:]))
    plots.plot_three_mass_frf(f3, H3, np.asarray(fn)).savefig(
        os.path.join(out, "fig2_three_mass_frf.png"), dpi=120)
    # Fig. 3: deflection shapes, the column F1 of the receptance read at each resonance
    # (imaginary part: the resonant response) and far below (real part: rigid-body motion)
    fr = np.asarray(fn)[1:]
    at = np.asarray(model.frf(np.concatenate([[0.5], fr])))[:, :, 0]
    shapes = np.stack([at[0].real, at[1].imag, at[2].imag])
    plots.plot_deflection_shapes(
        shapes, ["rigid motion"] + [f"mode {k + 1}: {x:.1f} Hz" for k, x in enumerate(fr)]
    ).savefig(os.path.join(out, "fig3_deflection_shapes.png"), dpi=120)
    fv = np.linspace(60.0, 250.0, 4000)
    Hv = np.asarray(model.frf(fv))
    plots.plot_velocity_nyquist(fv, Hv[:, 0, 0], Hv[:, 1, 0]).savefig(
        os.path.join(out, "fig5_velocity_nyquist.png"), dpi=120)

    drive = fdjax.reference_drive()
    pos = np.linspace(0.1, 0.7, 61)
    f = np.geomspace(5.0, 3000.0, 1500)
    H = np.asarray(drive.frf(pos, f))
    print("Reference drive, peaks of |h21| = |x2/T1| (Hz):")
    for p in (0, 30, 60):
        pk = _peaks(f, np.abs(H[p, :, 1, 0]), 20.0, 3000.0)
        print(f"  Y_table = {pos[p] * 1e3:5.0f} mm: " + ", ".join(f"{x:7.1f}" for x in pk))
    fam = np.linspace(0, 60, 7).astype(int)
    plots.plot_frf_family(pos[fam], f, H[fam]).savefig(
        os.path.join(out, "fig10_frf_family.png"), dpi=110)
    plots.plot_frf_cloud(pos, f, H[:, :, 1, 0]).savefig(
        os.path.join(out, "fig11_h21_cloud.png"), dpi=120)
    print(f"figures written to {out}/")
    return {"three_mass_hz": np.asarray(fn)[1:].tolist()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="fdjax", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("demo", help="3M2S and reference-drive FRFs with figures")
    p.add_argument("--out", default="build/demo", help="output folder (default build/demo)")
    args = parser.parse_args(argv)
    if args.command == "demo":
        demo(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
