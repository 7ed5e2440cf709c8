"""The ``fdjax`` command line.

    fdjax reproduce [--out DIR] [--quick]
                                the whole chain on the reference drive: the figures and
                                summary.json (the numbers the README quotes); Fig. 18 tunes
                                the controllers afresh (fdjax.synthesise, minutes), --quick
                                evaluates the designs shipped with fdjax instead
    fdjax demo    [--out DIR]   ``reproduce --quick`` (what ``make demo`` runs)
    fdjax figures [--out DIR]   the paper's figures (Figs. 2, 3, 5, 10-12, 14, 16, 17)
    fdjax modes   [--out DIR] [--positions N] [--n-modes N] [--source fit|model]
                                modes of h21 over the travel: a table; CSV and JSON with --out
    fdjax tune    [--out DIR] [--quick]
                                gradient synthesis: six local MCMs, PID baselines, the ATA
                                network by backpropagation and end to end, Fig. 18, the
                                certificates; writes DIR/schedule.eqx (fdjax.load_schedule)
    fdjax --version             the installed version

Every --out folder is created, or refused, before any computation starts.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

# Only the standard library at module level: `fdjax --help` and argparse's errors answer before
# numpy, JAX or matplotlib load; each command imports what it needs.


def _peaks(f, a, fmin, fmax):
    import numpy as np

    k = np.flatnonzero((a[1:-1] > a[:-2]) & (a[1:-1] > a[2:])) + 1
    return f[k[(f[k] >= fmin) & (f[k] <= fmax)]]


def three_mass_figures(out: str) -> np.ndarray:
    """Figs. 2, 3 and 5 of the 3M2S; returns its natural frequencies (Hz)."""
    import numpy as np

    import fdjax
    from fdjax import plots

    model = fdjax.three_mass()
    fn = np.asarray(model.modes()[0])
    f3 = np.geomspace(10.0, 1000.0, 4000)
    plots.plot_three_mass_frf(f3, np.asarray(model.frf(f3)), fn).savefig(
        os.path.join(out, "fig2_three_mass_frf.png"), dpi=120)
    # Fig. 3: the column F1 of the receptance read at each resonance (imaginary part: the
    # resonant response) and far below (real part: the rigid-body motion)
    fr = fn[1:]
    at = np.asarray(model.frf(np.concatenate([[0.5], fr])))[:, :, 0]
    shapes = np.stack([at[0].real, at[1].imag, at[2].imag])
    labels = ["rigid motion"] + [f"mode {k + 1}: {x:.1f} Hz" for k, x in enumerate(fr)]
    plots.plot_deflection_shapes(shapes, labels).savefig(
        os.path.join(out, "fig3_deflection_shapes.png"), dpi=120)
    fv = np.linspace(60.0, 250.0, 4000)
    Hv = np.asarray(model.frf(fv))
    plots.plot_velocity_nyquist(fv, Hv[:, 0, 0], Hv[:, 1, 0]).savefig(
        os.path.join(out, "fig5_velocity_nyquist.png"), dpi=120)
    return fn


def drive_figures(out: str, n_positions: int = 61) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Figs. 10, 11 and 12 of the reference drive; returns (positions, freq, H)."""
    import numpy as np

    import fdjax
    from fdjax import plots

    drive = fdjax.reference_drive()
    lo, hi = drive.travel_m
    pos = np.linspace(lo, hi, n_positions)
    f = np.geomspace(5.0, 3000.0, 1500)
    H = np.asarray(drive.frf(pos, f))
    fam = np.linspace(0, n_positions - 1, 7).round().astype(int)
    plots.plot_frf_family(pos[fam], f, H[fam]).savefig(
        os.path.join(out, "fig10_frf_family.png"), dpi=110)
    plots.plot_frf_cloud(pos, f, H[:, :, 1, 0]).savefig(
        os.path.join(out, "fig11_h21_cloud.png"), dpi=120)
    p12 = pos[:: max(1, n_positions // 31)]
    modes = fdjax.track_drive_modes(fdjax.drive_modes(drive, p12, n_modes=6))
    plots.plot_resonant_phase(p12, modes.frequency_hz, modes.phase_deg).savefig(
        os.path.join(out, "fig12_resonant_phase.png"), dpi=110)
    return pos, f, H


def loop_figures(out: str, pos, f, H) -> None:
    """Fig. 14: the speed loop of :func:`fdjax.reference_controller` without and with its MCM
    over the travel, as the reference servo runs it (``SampledData()``, 8 kHz, d = 2).

    Without the MCM the screw's torsional mode (1260 Hz), which the motor encoder sees, loops
    around −1: at this k_v the loop needs the notch."""
    import numpy as np

    import fdjax
    from fdjax import plots
    from fdjax._control._reference import reference_controller, reference_servo

    drive = fdjax.reference_drive()
    servo = reference_servo()
    # 115 mm (where the controller is tuned) and six positions to the screw end
    fam_m = np.array([FIG16_POSITION_M, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7])
    f_s = np.geomspace(20.0, 0.995 * 0.5 / servo.period, 3000)
    c = reference_controller(drive)
    how = dict(servo=servo, position_m=fam_m)
    without = fdjax.open_loop(_with_mcm(c, fdjax.MCM()), drive, f_s, **how)
    with_mcm = fdjax.open_loop(c, drive, f_s, **how)
    plots.plot_peak_filter_effect(
        f_s, fam_m, without.speed, with_mcm.speed, loop_label="speed loop $L_v$",
        radius=2.5, band_hz=(1150.0, 1350.0), filter_label="MCM",
    ).savefig(os.path.join(out, "fig14_peak_filter.png"), dpi=90)


def _with_mcm(controller, mcm):
    """The double loop with another MCM (same gains)."""
    import equinox as eqx

    return eqx.tree_at(lambda c: c.mcm, controller, mcm)


FIG16_POSITION_M = 0.115  # the paper's Figs. 16-17 are at Y_table = 115 mm


def simulation_figures(out: str) -> dict:
    """Figs. 16-17: PID and the double loop with MCM, each without and with feed-forward
    control (FFC), tracking the short-stroke reciprocating motion at Y_table = 115 mm; the
    sampled-data loop of the reference servo (8 kHz, d = 2).  Returns the RMS scale errors (m)."""
    import fdjax
    from fdjax import DoubleLoop, plots
    from fdjax._control._reference import (
        reference_controller,
        reference_pid,
        reference_servo,
        rigid_feedforward,
    )

    drive = fdjax.reference_drive()
    servo = reference_servo()
    ref = fdjax.reciprocating(cycles=2)
    method = fdjax.SampledData()
    run = dict(servo=servo, position_m=FIG16_POSITION_M, duration=0.5)
    k_ffv, k_ffa = rigid_feedforward(drive, servo)
    pid_runs = {
        "PID w/o FFC": fdjax.simulate(reference_pid(), drive, ref, method, **run),
        "PID w/ FFC": fdjax.simulate(reference_pid(k_ffv=k_ffv, k_ffa=k_ffa), drive, ref,
                                     method, **run),
    }
    c = reference_controller(drive, servo)
    no_ffc = DoubleLoop(c.kp, c.kv, c.ki, k_ffv=0.0, k_ffa=0.0, mcm=c.mcm)
    mcm_runs = {
        "P/PI + MCM w/o FFC": fdjax.simulate(no_ffc, drive, ref, method, **run),
        "P/PI + MCM w/ FFC": fdjax.simulate(c, drive, ref, method, **run),
    }
    rate = 1e-3 / servo.period
    where = f"$Y_{{table}}$ = {FIG16_POSITION_M * 1e3:.0f} mm, sampled data at {rate:.0f} kHz"
    plots.plot_tracking(pid_runs, title=f"Tracking with PID control, {where} (paper Fig. 16)",
                        ).savefig(os.path.join(out, "fig16_pid_tracking.png"), dpi=100)
    plots.plot_tracking(mcm_runs, title=f"Tracking with the double loop and MCM, {where} "
                        "(paper Fig. 17)").savefig(os.path.join(out, "fig17_mcm_tracking.png"),
                                                   dpi=100)
    return {k: float(v.rms_error()) for k, v in {**pid_runs, **mcm_runs}.items()}


def table_1_comparison(drive) -> dict:
    """The reference drive's five lowest flexible modes of h21 at 115 mm against Table 1."""
    from types import SimpleNamespace

    import numpy as np

    import fdjax
    from fdjax._drive._updating import TOLERANCES, meets, modal_errors

    T = fdjax.TABLE_1
    m = fdjax.drive_modes(drive, fdjax.TABLE_1_POSITION_M, n_modes=6)
    lowest = SimpleNamespace(**{k: np.asarray(getattr(m, k))[:5]
                                for k in ("frequency_hz", "damping_ratio", "phase_deg")})
    errors = modal_errors(lowest, T)
    ok = meets(errors)
    rows = []
    for k in range(5):
        f, z, ph = (float(np.asarray(x)[k]) for x in (m.frequency_hz, m.damping_ratio,
                                                      m.phase_deg))
        tf, tz, tph = (float(np.asarray(x)[k]) for x in (T.frequency_hz, T.damping_ratio,
                                                         T.phase_deg))
        met = dict(zip(("frequency", "damping", "phase"), (bool(x) for x in ok[:, k])))
        rows.append({"mode": k + 1, "frequency_hz": f, "table_1_frequency_hz": tf,
                     "damping_ratio": z, "table_1_damping_ratio": tz, "phase_deg": ph,
                     "table_1_phase_deg": tph,
                     "phase_difference_deg": float(np.asarray(errors[2])[k]), "met": met})
    tol = dict(zip(("frequency", "damping", "phase_deg"), TOLERANCES))
    return {"position_m": float(fdjax.TABLE_1_POSITION_M), "tolerance": tol,
            "modes": rows, "targets_met": int(ok.sum()), "targets": 15}


def _margins_json(m) -> dict:
    import numpy as np

    return {k: np.asarray(getattr(m, k)).tolist() for k in (
        "gain_margin", "phase_margin_deg", "modulus_margin", "gain_crossover_hz",
        "phase_crossover_hz")}


def loop_summary(pos, f, H) -> dict:
    """Margins of the reference controller over the travel, of the speed loop (broken at the
    speed feedback, position loop open) and of the position loop (broken at the scale, speed
    loop closed), in two loop models:

    * ``sampled``: the loop as the reference servo runs it (``SampledData()``: ZOH twin at each
      position, discrete law, two whole samples of delay), on a grid up to just below Nyquist;
    * ``continuous``: the continuous loop with the exact delay e^{−iωτ}, τ = d·T = 250 µs
      (``Continuous()``), on the exact FRF ``H`` (the grid ``f``).
    """
    import numpy as np

    import fdjax
    from fdjax._control._reference import reference_controller, reference_servo

    drive = fdjax.reference_drive()
    servo = reference_servo()
    c = reference_controller(drive, servo)
    nyquist = 0.5 / servo.period
    f_s = np.geomspace(5.0, 0.995 * nyquist, 3000)
    sampled = fdjax.loop_margins(c, drive, f_s, servo=servo,
                                 method=fdjax.SampledData(), position_m=pos)
    # where the sampled loop is unstable: its eigenvalues (the margins alone do not prove it)
    stable = fdjax.check_stability(c, drive, servo=servo, method=fdjax.SampledData(),
                                   position_m=pos).stable
    continuous = fdjax.loop_margins(c, H, f, servo=servo,
                                    method=fdjax.Continuous(), screw_ratio=drive.screw.ratio)

    def loops(m, model, grid):
        return {"model": model, "freq_hz": [float(grid[0]), float(grid[-1])],
                "speed": _margins_json(m.speed), "position": _margins_json(m.position)}

    rate = f"{1e-3 / servo.period:.0f} kHz, d = {servo.delay_samples}"
    return {
        "positions_m": np.asarray(pos).tolist(),
        "servo": {"period_s": servo.period, "delay_samples": servo.delay_samples,
                  "tau_s": servo.tau, "k_motor": float(servo.k_motor),
                  "current_limit_a": float(servo.current_limit)},
        "sampled": {**loops(sampled, f"SampledData(): the loop as the servo runs it ({rate}), "
                            "on the twin at each position", f_s),
                    "stable": [bool(v) for v in np.asarray(stable)]},
        "continuous": loops(continuous, f"Continuous(): exact delay e^(-i w tau), tau = "
                            f"{servo.tau * 1e6:.0f} us, on the exact FRF", f),
    }


def discretisation_summary() -> dict:
    """The reference MCM at the servo rate: largest relative error below Nyquist/4."""
    import numpy as np

    from fdjax._control._reference import reference_mcm, reference_servo

    mcm = reference_mcm()
    period = reference_servo().period
    f = np.linspace(0.5, 1 / (8 * period), 4000)
    gc = np.asarray(mcm.frf(f))
    err = {m: float(np.max(np.abs(np.asarray(mcm.discretize(period, m).frf(f)) - gc)
                           / np.abs(gc))) for m in ("fitted", "tustin")}
    return {"servo_rate_hz": 1 / period, "band_hz": [0.5, float(f[-1])],
            "max_relative_error": err}


def _db(gain: float) -> float:
    import math

    return 20.0 * math.log10(gain) if gain > 0 else -math.inf


def _where(flags: list[bool], positions_m: list[float]) -> str:
    """The positions where ``flags`` holds, as runs over the grid: "from 500 mm",
    "up to 200 mm", "at 300–400 mm", "at 250 mm", "at every position"."""
    n, runs, k = len(flags), [], 0
    while k < n:
        if not flags[k]:
            k += 1
            continue
        j = k
        while j + 1 < n and flags[j + 1]:
            j += 1
        a, b = (f"{positions_m[i] * 1e3:.0f} mm" for i in (k, j))
        if k == 0 and j == n - 1:
            runs.append("at every position")
        elif j == n - 1:
            runs.append(f"from {a}")
        elif k == 0:
            runs.append(f"up to {b}")
        else:
            runs.append(f"at {a}" if k == j else f"at {a[:-3]}–{b}")
        k = j + 1
    return ", ".join(runs)


def _loop_line(name: str, m: dict, positions_m: list[float]) -> str:
    """One model of :func:`loop_summary` in a line: the least margins over the positions
    (gain margins in dB), and where the closed loop is unstable when ``m`` holds its
    eigenvalues' verdict (``stable``, the sampled loop), else where a gain margin is below
    0 dB (the continuous loop on the exact FRF has no realisation to take eigenvalues from;
    for the reference controller this agrees on the 13-position grid with the eigenvalues of
    the continuous loop with a Padé delay (order 8), unstable from 515–520 mm, not with the
    sampled loop's, unstable from 470–475 mm)."""
    parts = []
    for loop in ("speed", "position"):
        gm, pm = m[loop]["gain_margin"], m[loop]["phase_margin_deg"]
        parts.append(f"{loop} loop GM ≥ {_db(min(gm)):.1f} dB, PM ≥ {min(pm):.1f}°")
    if "stable" in m:
        bad = [not ok for ok in m["stable"]]
        where = f"; unstable {_where(bad, positions_m)} (eigenvalues)" if any(bad) else ""
    else:
        bad = [min(gs, gp) < 1.0 for gs, gp in zip(m["speed"]["gain_margin"],
                                                  m["position"]["gain_margin"])]
        where = f"; gain margin below 0 dB {_where(bad, positions_m)}" if any(bad) else ""
    return f"{name}: " + "; ".join(parts) + where


def reproduce(out: str, quick: bool = False) -> dict:
    """The whole chain on the reference drive: every figure, and ``summary.json``.

    ``quick`` evaluates the designs shipped with fdjax (:data:`SHIPPED_DESIGNS`) for Fig. 18
    instead of tuning them afresh (:func:`fdjax.synthesise`, minutes), checks their
    certificates on Fig. 18's 10 mm grid instead of every 1 mm (no ``certificate_*.csv``, no
    ``convergence.png``, no ``local_designs.csv``), and sweeps 13 table positions instead of
    61 for Figs. 10-12, the margins (``double_loop``) and the printed peaks of |h21|.
    Everything else (Figs. 2, 3, 5, 14, 16, 17, Table 1, the tracking errors, Fig. 18's 61
    positions) is the same."""
    import numpy as np

    import fdjax
    from fdjax._control._reference import reference_servo

    start = time.perf_counter()
    os.makedirs(out, exist_ok=True)
    fn = three_mass_figures(out)
    print("3M2S (paper Sec. 2): natural frequencies " + ", ".join(f"{x:.1f} Hz" for x in fn[1:]))
    drive = fdjax.reference_drive()
    servo = reference_servo()
    pos, f, H = drive_figures(out, n_positions=13 if quick else 61)
    table_1 = table_1_comparison(drive)
    print(f"Reference drive vs Table 1 at 115 mm: {table_1['targets_met']} of 15 targets met "
          "(frequency ±3 %, damping ±25 %, phase ±15°)")
    loop_figures(out, pos, f, H)
    loop = loop_summary(pos, f, H)
    print(f"Reference controller over the travel, least margins at {len(pos)} positions "
          "(gain margins in dB):")
    for model, name in (("sampled", "sampled, as the servo runs it"),
                        ("continuous", "continuous, exact delay")):
        print("  " + _loop_line(name, loop[model], loop["positions_m"]))
    rms = simulation_figures(out)
    print(f"Reciprocating motion at {FIG16_POSITION_M * 1e3:.0f} mm, RMS scale error (µm): "
          + ", ".join(f"{k} {v * 1e6:.3g}" for k, v in rms.items()))
    if quick:
        print("Gradient synthesis: the designs shipped with fdjax (made by `fdjax tune`); "
              "`fdjax reproduce` without --quick tunes them afresh", flush=True)
        shipped, _ = fdjax.load_designs(SHIPPED_DESIGNS)
        control = control_report(out, shipped, certify_step_mm=None,
                                 metadata={"source": "shipped designs"})
    else:
        syn = fdjax.synthesise(progress=True)
        control = control_report(out, syn.controllers, synthesis=syn, certify_step_mm=1.0)
    disc = discretisation_summary()
    err = disc["max_relative_error"]
    print(f"Reference MCM at {1e-3 / servo.period:.0f} kHz, error below Nyquist/4: fitted "
          f"{err['fitted'] * 100:.2f} %, Tustin {err['tustin'] * 100:.1f} %")
    print("Reference drive, peaks of |h21| = |x2/T1| (Hz):")
    for p in (0, len(pos) // 2, len(pos) - 1):
        pk = _peaks(f, np.abs(H[p, :, 1, 0]), 20.0, 3000.0)
        print(f"  Y_table = {pos[p] * 1e3:5.0f} mm: " + ", ".join(f"{x:7.1f}" for x in pk))
    summary = {
        "fdjax_version": fdjax.__version__,
        "quick": quick,
        "three_mass": {"natural_frequencies_hz": fn[1:].tolist()},
        "table_1": table_1,
        "double_loop": loop,
        "tracking": {"position_m": FIG16_POSITION_M, "servo_rate_hz": 1 / servo.period,
                     "delay_samples": servo.delay_samples, "method": "SampledData()",
                     "motion": "reciprocating, 5 mm, 0.1 m/s, 2 m/s², 200 m/s³, 2 cycles",
                     "rms_scale_error_m": rms},
        "mcm_discretisation": disc,
        "control": control,
        "figures": sorted(n for n in os.listdir(out) if n.endswith(".png")),
        "seconds": time.perf_counter() - start,
    }
    with open(os.path.join(out, "summary.json"), "w") as fh:
        json.dump(summary, fh, indent=1)
    print(f"figures and summary.json written to {out}/ in {summary['seconds']:.0f} s")
    return summary


# Where the designs shipped with fdjax live (written by `fdjax tune`; what
# `fdjax.load_designs()` reads without a folder).
SHIPPED_DESIGNS = os.path.join(os.path.dirname(__file__), "data", "reference_designs")
FIG18_POSITIONS_M = tuple(round(0.1 + 0.01 * k, 10) for k in range(61))


def _write_csv(path: str, cols: dict) -> None:
    keys = list(cols)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(keys)
        for row in zip(*(cols[k] for k in keys)):
            w.writerow(["" if v is None else v for v in row])


def _finite_or_none(values) -> list:
    import math

    return [None if v is None or not math.isfinite(float(v)) else float(v) for v in values]


def control_report(out: str, controllers: dict, *, certify_step_mm: float | None,
                   synthesis=None, metadata: dict | None = None) -> dict:
    """Fig. 18 and its table for ``controllers`` (:data:`fdjax.CONTROLLERS`): RMS error,
    stability and the sampled margins every 10 mm; the robust MCM and the scheduled
    controllers certified every
    ``certify_step_mm`` (None: on the Fig. 18 grid only); the schedule files, the designs, the
    filter tables; the convergence curves when ``synthesis`` is given.  Returns the summary's
    ``control`` entry."""
    import numpy as np

    import fdjax
    from fdjax import plots
    from fdjax._tune._synthesis import DESIGN_POSITIONS_M, LABELS

    drive = fdjax.reference_drive()
    os.makedirs(out, exist_ok=True)
    meta = {"drive": "fdjax.reference_drive()", "servo": "fdjax.Servo() (8 kHz, d = 2)",
            "objective": "fdjax.tuning_objective(margin_width=0.01), after searches with "
                         "margin_width=0.05: RMS scale error of a 1 mm reciprocating stroke + "
                         "margin, stability and current penalties",
            "feedforward": False, **(metadata or {})}
    fdjax.save_designs(out, controllers, metadata=meta)
    fdjax.save_schedule(os.path.join(out, "schedule.eqx"), controllers["mcm_ata_e2e"],
                        drive=drive, metadata={**meta, "trained": "end to end"})
    fdjax.save_schedule(os.path.join(out, "schedule_bp.eqx"), controllers["mcm_ata"],
                        drive=drive,
                        metadata={**meta, "trained": "backpropagation on the local designs"})
    y = np.asarray(FIG18_POSITIONS_M)
    table = controllers["mcm_ata_e2e"].filter_table(y)
    _write_csv(os.path.join(out, "filters.csv"), table)
    with open(os.path.join(out, "filters.json"), "w") as fh:
        json.dump(table, fh, indent=1)
    print(f"Fig. 18: {len(controllers)} controllers at {y.size} positions (RMS, stability, "
          "sampled margins)", flush=True)
    ev = fdjax.evaluate(controllers, drive, y, progress=False)
    plots.plot_rms_over_travel(
        y * 1e3, ev, labels=LABELS, design_mm=[v * 1e3 for v in DESIGN_POSITIONS_M],
        title="RMS tracking error over the travel, feedback only (paper Fig. 18)",
    ).savefig(os.path.join(out, "fig18_rms_over_travel.png"), dpi=100)
    control = {"positions_mm": (y * 1e3).round(6).tolist(),
               "motion": "1 mm reciprocating stroke, 50 mm/s, 2 m/s², 400 m/s³ (0.1 s)",
               "feedforward": False}
    for name, r in ev.items():
        control[name] = {"label": LABELS.get(name, name),
                         "rms_error_um": _finite_or_none(r["rms_error_um"]),
                         "stable": r["stable"],
                         "gain_margin_db": _finite_or_none(r["gain_margin_db"]),
                         "phase_margin_deg": _finite_or_none(r["phase_margin_deg"]),
                         "modulus_margin": _finite_or_none(r["modulus_margin"]),
                         "modulus_margin_required": float(r["certificate"].requirements[2])}
        rows = r["certificate"].rows()
        _write_csv(os.path.join(out, f"fig18_{name}.csv"),
                   {"position_mm": rows.pop("position_mm"),
                    "rms_error_um": control[name]["rms_error_um"], **rows})
    certs = {}
    for name in ("mcm_robust", "mcm_interp", "mcm_ata", "mcm_ata_e2e"):
        if certify_step_mm is None:
            cert = ev[name]["certificate"]
        else:
            lo, hi = drive.travel_m
            n = int(round((hi - lo) * 1e3 / certify_step_mm)) + 1
            cert = fdjax.certify(controllers[name], drive, np.linspace(lo, hi, n))
            _write_csv(os.path.join(out, f"certificate_{name}.csv"), cert.rows())
        certs[name] = {"step_mm": certify_step_mm or 10.0, "certified": cert.ok,
                       "message": cert.message}
        print(f"  {name}: {cert.message}", flush=True)
    control["certificates"] = certs
    if synthesis is not None:
        names = [f"{v * 1e3:.0f} mm" for v in synthesis.local.positions_m]
        plots.plot_convergence({
            "local designs": (synthesis.local.history, names),
            "common gains": (synthesis.shared.history, names[1:]),
            "robust PID (worst position)": (synthesis.pid_robust.worst, None),
            "robust MCM (worst position)": (synthesis.mcm_robust.worst, None),
            "end to end (batch)": (synthesis.e2e.history, None),
        }).savefig(os.path.join(out, "convergence.png"), dpi=90)
        _write_csv(os.path.join(out, "local_designs.csv"), synthesis.local_table())
        control["seconds"] = synthesis.seconds
    with open(os.path.join(out, "control.json"), "w") as fh:
        json.dump(control, fh, indent=1)
    for name in control:
        if isinstance(control[name], dict) and "rms_error_um" in control[name]:
            r = control[name]
            rms = [v for v in r["rms_error_um"] if v is not None]
            worst = f"{max(rms):.1f}" if rms else "—"
            n_bad = sum(not s for s in r["stable"])
            mm = [v for v in r["modulus_margin"] if v is not None]
            need = r["modulus_margin_required"]
            n_low = sum(v < need for v in mm)
            low = f" (below {need:g} at {n_low} positions)" if n_low else ""
            print(f"  {r['label']:<30s} worst RMS {worst:>7s} µm, unstable at {n_bad} of "
                  f"{len(r['stable'])} positions, least modulus margin {min(mm):.3f}{low}",
                  flush=True)
    return control


# `fdjax tune --quick`: a tenth of `fdjax.synthesise`'s default steps, except the common gains
# (a fifth), the network's training (half) and the end-to-end training (a sixth).
QUICK_TUNE_STEPS = dict(local_steps=30, shared_steps=20, pid_steps=30, network_steps=2000,
                        e2e_steps=10, simplex_evaluations=300, refine_steps=10, robust_steps=12)


def tune(out: str, quick: bool = False) -> dict:
    """``fdjax tune``: the local tunings, the baselines, the network by backpropagation and end
    to end (:func:`fdjax.synthesise`), then Fig. 18, the certificates and the files of
    :func:`control_report`.  ``quick``: fewer optimiser steps (:data:`QUICK_TUNE_STEPS`),
    certificates on Fig. 18's 10 mm grid instead of every 1 mm (the tuners' compilation, the
    same either way, takes most of the time)."""
    import fdjax

    start = time.perf_counter()
    steps = QUICK_TUNE_STEPS if quick else {}
    syn = fdjax.synthesise(progress=True, **steps)
    control = control_report(out, syn.controllers, synthesis=syn,
                             certify_step_mm=None if quick else 1.0,
                             metadata={"quick": quick})
    control["seconds_total"] = time.perf_counter() - start
    with open(os.path.join(out, "control.json"), "w") as fh:
        json.dump(control, fh, indent=1)
    print(f"schedule, designs, tables and figures written to {out}/ in "
          f"{control['seconds_total']:.0f} s")
    return control


# The band `fdjax modes` identifies in, and reports the model's modes in.
MODES_BAND_HZ = (10.0, 3000.0)
# Screw elements of the twin whose eigen-analysis `fdjax modes --source model` reports.
MODES_TWIN_ELEMENTS = 48


def modes(out: str | None, n_positions: int, n_modes: int | None, source: str) -> dict:
    """Modes of h21 over the travel, identified from the FRF (``fit``) or the twin (``model``).

    ``fit`` chooses the order at every position from its stabilisation diagram
    (:func:`fdjax.identify_modes_batched` without ``n_modes``; a real pole models the damped
    rigid body) and reports the modes inside the band; ``model`` reports the twin's modes
    inside the band.  ``n_modes`` keeps the lowest ``n_modes`` of them.  Both are tracked
    over the positions (frequency and mode-shape continuity).
    """
    import numpy as np

    import fdjax

    drive = fdjax.reference_drive()
    lo, hi = drive.travel_m
    pos = np.linspace(lo, hi, n_positions)
    f_lo, f_hi = MODES_BAND_HZ
    if source == "fit":  # seconds to minutes of work: say so before it starts
        # measured on 2 cores: 17 s for 13 positions, 45 s for 61, 142 s for 200
        seconds = 10 + 0.7 * n_positions
        took = f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min"
        print(f"identifying the modes at {n_positions} positions from their FRFs (about "
              f"{took} on 2 cores) ...", file=sys.stderr, flush=True)
    if source == "fit":
        f = np.geomspace(f_lo, f_hi, 2000)
        H = np.asarray(drive.frf(pos, f))[:, :, 1, 0]
        result = fdjax.identify_modes_batched(f, H)
        if n_modes is not None:
            found = result.frequency_hz.shape[1]
            if n_modes > found:
                print(f"--n-modes {n_modes}: the identification found {found} modes in "
                      f"{f_lo:g}-{f_hi:g} Hz; reporting those", file=sys.stderr)
            result = _lowest(result, n_modes)
        result = fdjax.track_modes(result)
    else:
        # The default twin mesh (12 screw elements) meets 0.5 % below 2 kHz; the band reaches
        # 3 kHz, where the screw's modes need a finer mesh: 48 elements converge them (O(h²)).
        twin = fdjax.TwinOptions(n_elements=MODES_TWIN_ELEMENTS)
        m = fdjax.drive_modes(drive, pos, n_modes=max(12, n_modes or 0), twin=twin)
        n_band = int(np.min(np.sum(np.asarray(m.frequency_hz) <= f_hi, axis=1)))
        result = fdjax.track_drive_modes(_lowest(m, n_band if n_modes is None else n_modes))
    fr, z, ph = (np.asarray(x) for x in (result.frequency_hz, result.damping_ratio,
                                         result.phase_deg))
    rows = [
        {"position_mm": round(float(pos[i]) * 1e3, 3), "mode": k + 1,
         "frequency_hz": float(fr[i, k]), "damping_ratio": float(z[i, k]),
         "phase_deg": float(ph[i, k])}
        for i in range(len(pos)) for k in range(fr.shape[1])
    ]
    how = ("identified from the FRF" if source == "fit" else
           f"eigen-analysis of the twin, {MODES_TWIN_ELEMENTS} screw elements")
    print(f"Modes of h21 = x2/T1 ({how}); f in Hz, zeta, resonant phase in degrees:")
    print(" Y (mm) " + "".join(f"| mode {k + 1}:   f   zeta    phase " for k in range(fr.shape[1])))
    for i in range(len(pos)):
        print(f"{pos[i] * 1e3:7.0f} " + "".join(
            f"| {fr[i, k]:11.1f} {z[i, k]:6.4f} {ph[i, k]:7.1f} " for k in range(fr.shape[1])))
    if out:
        os.makedirs(out, exist_ok=True)
        with open(os.path.join(out, "modes.csv"), "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        with open(os.path.join(out, "modes.json"), "w") as fh:
            json.dump({"entry": "h21 = x2/T1", "source": source, "modes": rows}, fh, indent=1)
        print(f"written {out}/modes.csv and {out}/modes.json")
    return {"positions_m": pos, "frequency_hz": fr, "damping_ratio": z, "phase_deg": ph}


def _lowest(result, n: int):
    """The lowest ``n`` modes (by frequency, NaN last) of a position batch of modal results."""
    import equinox as eqx
    import jax.numpy as jnp

    order = jnp.argsort(jnp.nan_to_num(result.frequency_hz, nan=jnp.inf), axis=1)[:, :n]
    n_all = result.frequency_hz.shape[1]

    def take(x):
        if not (hasattr(x, "ndim") and x.ndim >= 2 and x.shape[1] == n_all):
            return x
        idx = order.reshape(order.shape + (1,) * (x.ndim - 2))
        return jnp.take_along_axis(x, idx, axis=1)

    fields = ("frequency_hz", "damping_ratio", "phase_deg", "residues", "poles", "amplitude",
              "prominence", "shapes")
    for name in fields:
        if hasattr(result, name):
            result = eqx.tree_at(lambda m, k=name: getattr(m, k), result,
                                 take(getattr(result, name)))
    return result


def _count(what: str, minimum: int, maximum: int | None = None):
    """An argparse type for a count option; its error says what is counted (argparse prefixes
    the option's name)."""

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            n = None
        if n is None or n < minimum or (maximum is not None and n > maximum):
            top = "" if maximum is None else f" and ≤ {maximum}"
            raise argparse.ArgumentTypeError(
                f"expected {what}, an integer ≥ {minimum}{top}; got {text!r}"
            )
        return n

    return parse


COMMANDS = ("reproduce", "demo", "figures", "modes", "tune")
MODES_MAX_POSITIONS = 601  # one every millimetre of the reference drive's travel
MODES_MAX_MODES = 100      # what fdjax.drive_modes computes at most


class _Version(argparse.Action):
    """``--version``: the installed package's version, looked up only when asked (``--help``
    stays free of it)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=argparse.SUPPRESS, nargs=0,
                         help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from importlib.metadata import PackageNotFoundError, version

        try:
            v = version("fdjax")
        except PackageNotFoundError:  # run from a source tree that pip has not installed
            import fdjax

            v = fdjax.__version__
        print(f"{parser.prog} {v}")
        parser.exit()


# The files each command writes whose names are fixed, checked before the work starts (the
# others are named from what the work computes).
OUT_FILES = {"modes": ("modes.csv", "modes.json"),
             "reproduce": ("summary.json", "control.json", "schedule.eqx", "schedule.json"),
             "tune": ("control.json", "schedule.eqx", "schedule.json")}
OUT_FILES["demo"] = OUT_FILES["reproduce"]


def _out_problem(path: str, files: tuple = ()) -> str | None:
    """Why ``path`` cannot be the output folder, or ``files`` be written in it; None when it
    can (the folder is created if missing)."""
    if not path:
        return "an empty path; give a directory"
    if os.path.exists(path) and not os.path.isdir(path):
        return "exists and is not a directory"
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        # name the part of the path that stands in the way when it is a file
        head = os.path.dirname(os.path.normpath(path))
        while head and not os.path.lexists(head):
            head = os.path.dirname(head)
        if head and os.path.exists(head) and not os.path.isdir(head):
            return f"cannot create it: {head} is not a directory"
        return f"cannot create it: {exc.strerror or exc}"
    if not os.access(path, os.W_OK | os.X_OK):
        return "the directory is not writable"
    for name in files:
        target = os.path.join(path, name)
        if os.path.isdir(target):
            return f"{target} is a directory, where the command writes a file"
        if os.path.exists(target) and not os.access(target, os.W_OK):
            return f"{target} exists and is not writable"
    return None


def _out_option(p: argparse.ArgumentParser, default: str | None, help: str | None = None):
    p.add_argument("--out", metavar="DIR", default=default,
                   help=help or f"output folder, created if missing (default {default})")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fdjax", description=__doc__.replace("``", ""),
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     allow_abbrev=False)
    parser.add_argument("--version", action=_Version, help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="{" + ",".join(COMMANDS)
                                + "}")
    p = sub.add_parser("reproduce", help="the whole chain: figures, Fig. 18 and summary.json",
                       allow_abbrev=False)
    _out_option(p, "build/reproduce")
    p.add_argument("--quick", action="store_true",
                   help="evaluate the designs shipped with fdjax (fdjax/data/reference_designs) "
                        "for Fig. 18 instead of tuning them afresh (minutes), certify them every "
                        "10 mm instead of every 1 mm, and sweep 13 table positions instead of 61 "
                        "(Figs. 10-12, the margins, the |h21| peaks)")
    p = sub.add_parser("demo", help="reproduce --quick (what make demo runs)", allow_abbrev=False)
    _out_option(p, "build/demo")
    p = sub.add_parser("figures", help="the paper's Figs. 2, 3, 5, 10-12, 14, 16, 17",
                       allow_abbrev=False)
    _out_option(p, "build/figures")
    p = sub.add_parser("modes", help="modes of h21 over the travel (a table; CSV and JSON with "
                       "--out)", allow_abbrev=False)
    _out_option(p, None, "folder for modes.csv and modes.json (default: print the table only)")
    p.add_argument("--positions", type=_count("the number of table positions spread over the "
                                              "travel (a count, not a position in m or mm)", 2,
                                              MODES_MAX_POSITIONS),
                   default=13, metavar="N",
                   help="how many table positions, spread evenly over the travel (a count, "
                        f"not a position; default 13, at most {MODES_MAX_POSITIONS}: one every "
                        "mm); --source fit identifies 13 in about 20 s on 2 cores, 200 in "
                        "2.5 min; model takes seconds")
    p.add_argument("--n-modes", type=_count("the number of modes", 1, MODES_MAX_MODES),
                   default=None,
                   metavar="N", help="report the lowest N modes (default: every mode in "
                   "10-3000 Hz; with --source fit the identification chooses its order "
                   "itself)")
    p.add_argument("--source", choices=("fit", "model"), default="fit",
                   help="identify from the FRF (fit, default) or eigen-analysis of the twin "
                        f"with {MODES_TWIN_ELEMENTS} screw elements (model)")
    p = sub.add_parser("tune", help="gradient synthesis of the scheduled MCM (paper Fig. 18)",
                       allow_abbrev=False)
    _out_option(p, "build/tune")
    p.add_argument("--quick", action="store_true",
                   help="fewer optimiser steps (a tenth in most stages; the common gains a "
                        "fifth, the network training half, end to end a sixth) and "
                        "certificates every 10 mm instead of every 1 mm: a check of the whole "
                        "pipeline, with poorer designs; compiling the tuners takes most of "
                        "the time, so it takes about as long as the full run (7 min on 2 "
                        "cores)")
    return parser


def _subparser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[command]


def main(argv=None) -> int:
    """Run the command line on ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    parser = _parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    word = next((a for a in argv if not a.startswith("-")), None)
    lead = argv if word is None else argv[:argv.index(word)]
    stray = [a for a in lead if a.startswith("-") and a.split("=")[0] not in
             ("-h", "--help", "--version")]
    if stray:  # an option before the command: a typo of --version, or a command's option
        import difflib

        opt = stray[0].split("=")[0]
        owners = [c for c in COMMANDS if any(opt in a.option_strings for a in
                                              _subparser(parser, c)._actions)]
        close = difflib.get_close_matches(opt, ["--help", "--version"], n=1)
        hint = (f"; it is an option of {', '.join(owners)}: give it after the command, e.g. "
                f"'fdjax {owners[0]} {stray[0]} ...'" if owners else
                f"; did you mean {close[0]!r}?" if close else
                "; before a command fdjax takes --help and --version only")
        parser.error(f"unknown option {stray[0]!r} before the command{hint} (commands: "
                     f"{', '.join(COMMANDS)})")
    if word is not None and word not in COMMANDS and not any(a in ("-h", "--help", "--version")
                                                             for a in argv[:argv.index(word)]):
        import difflib

        close = difflib.get_close_matches(word, COMMANDS, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        parser.error(f"unknown command {word!r}{hint} (commands: {', '.join(COMMANDS)})")
    args, extra = parser.parse_known_args(argv)
    if extra:  # argparse's message, with the closest option of the command when one is close
        import difflib

        options = [o for a in _subparser(parser, args.command)._actions for o in a.option_strings
                   if o.startswith("--") and o != "--help"]
        typed = [a for a in extra if a.startswith("--")]
        close = difflib.get_close_matches(typed[0].split("=")[0], options, n=1) if typed else []
        hint = f"; did you mean {close[0]!r}?" if close else ""
        if args.command == "demo" and "--quick" in extra:
            hint = "; demo is already 'fdjax reproduce --quick'"
        _subparser(parser, args.command).error(
            f"unrecognized arguments: {' '.join(extra)}{hint} (options of {args.command!r}: "
            f"{', '.join(options)})")
    # the output folder before any work: a bad --out fails now, not after minutes of computing
    if getattr(args, "out", None) is not None:
        problem = _out_problem(args.out, OUT_FILES.get(args.command, ()))
        if problem is not None:
            _subparser(parser, args.command).error(f"--out {args.out}: {problem}")
    if args.command == "reproduce":
        reproduce(args.out, quick=args.quick)
    elif args.command == "demo":
        reproduce(args.out, quick=True)
    elif args.command == "figures":
        three_mass_figures(args.out)
        pos, f, H = drive_figures(args.out)
        loop_figures(args.out, pos, f, H)
        simulation_figures(args.out)
        print(f"figures written to {args.out}/")
    elif args.command == "modes":
        modes(args.out, args.positions, args.n_modes, args.source)
    elif args.command == "tune":
        tune(args.out, quick=args.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
