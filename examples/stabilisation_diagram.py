"""Stabilisation diagram of the Table 1 drive's h21 = x2/T1 at Y_table = 115 mm, 1 % noise.

Usage: python examples/stabilisation_diagram.py [--out PATH]
  (≈ 8 s on 2 CPU cores; writes build/stabilisation_diagram.png under the current directory
  unless --out says otherwise, creating the folder.  The README's figure is regenerated, from the
  repository root, by ``python examples/stabilisation_diagram.py
  --out docs/figures/stabilisation_diagram.png``.)
"""

import argparse
import os
import time

import numpy as np

import fdjax
import fdjax.plots as fp


def main(out):
    t0 = time.perf_counter()
    drive = fdjax.table1_drive()
    freq_hz = np.geomspace(10.0, 2500.0, 1500)
    h21 = np.asarray(drive.frf(0.115, freq_hz))[0, :, 1, 0]  # (position, freq, out, in)
    rng = np.random.default_rng(0)
    noise = (rng.normal(size=h21.shape) + 1j * rng.normal(size=h21.shape)) / np.sqrt(2)
    measured = h21 * (1 + 0.01 * noise)

    diagram = fdjax.stabilisation_diagram(freq_hz, measured)
    fit = fdjax.identify_modes(freq_hz, measured, initial=diagram)
    for f, z, p in zip(fit.frequency_hz, fit.damping_ratio, fit.phase_deg):
        print(f"{float(f):8.1f} Hz   ζ = {float(z):.4f}   phase {float(p):7.1f}°")
    fig = fp.stabilisation_diagram(diagram, title="h21 = x2/T1 at Y_table = 115 mm, 1 % noise")
    folder = os.path.dirname(out)
    if folder:
        os.makedirs(folder, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"written {out}; {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--out", default=os.path.join("build", "stabilisation_diagram.png"),
                    help="where to write the figure (default: build/stabilisation_diagram.png "
                         "under the current directory)")
    main(ap.parse_args().out)
