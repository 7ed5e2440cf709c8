"""Modal characteristics of the model and model updating (issue 3, point 3)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fdjax
from fdjax._calibrate import ModalData, drive_modes, update_model


@pytest.fixture(scope="module")
def drive():
    return fdjax.reference_drive()


def test_modes_agree_with_the_exact_frf(drive):
    """Each mode's pole is a resonance of the exact FRF and its term sums to the FRF."""
    m = drive_modes(drive, 0.3, n_modes=6)
    # the screw's first torsional mode (1034 Hz, ζ ≈ 0.006) is isolated and dominates h21 there
    k = 3
    assert float(m.prominence[k]) > 0.9
    f = np.asarray(m.frequency_hz)
    grid = np.linspace(0.8 * f[k], 1.2 * f[k], 4001)
    h = np.abs(np.asarray(drive.frf([0.3], grid))[0, :, 1, 0])
    peak = grid[np.argmax(h)]
    assert abs(peak / f[k] - 1) < 2 * float(m.damping[k]) ** 2 + 2e-3  # FE mesh + damped peak
    # resonant phase: phase of the mode's own term at ω_r; for the dominant mode the whole FRF
    # is that term plus a smooth background, so the FRF phase at ω_r is close
    hr = np.asarray(drive.frf([0.3], f[k : k + 1]))[0, 0, 1, 0]
    ph = np.degrees(np.angle(hr))
    assert abs(((ph - float(m.phase_deg[k]) + 180) % 360) - 180) < 10.0


def test_modes_are_differentiable(drive):
    def f0(k):
        d = eqx.tree_at(lambda d: d.nut.stiffness, drive, k)
        return drive_modes(d, 0.3, n_modes=3).frequency_hz[0]

    k = jnp.asarray(float(drive.nut.stiffness))
    g = jax.grad(f0)(k)
    h = 1e-4 * float(k)
    fd = (f0(k + h) - f0(k - h)) / (2 * h)
    np.testing.assert_allclose(float(g), float(fd), rtol=1e-5)
    assert float(g) > 0  # a stiffer nut raises the axial mode


def test_model_updating_recovers_known_parameters(drive):
    """Perturb three parameters, take the true model's modes as data, recover the parameters."""
    paths = ["nut.stiffness", "carriage.pitch_stiffness", "rotary.coupling_damping"]
    true = [8.0e8, 6.0e6, 0.8]
    truth = eqx.tree_at(
        lambda d: [d.nut.stiffness, d.carriage.pitch_stiffness, d.rotary.coupling_damping],
        drive, [jnp.asarray(v) for v in true],
    )
    m = drive_modes(truth, 0.2, n_modes=6)
    data = ModalData(m.frequency_hz[:5], m.damping[:5], m.phase_deg[:5])
    bounds = {"nut.stiffness": (1e8, 1.5e9), "carriage.pitch_stiffness": (1e6, 1e8),
              "rotary.coupling_damping": (1e-2, 10.0)}
    res = update_model(drive, data, bounds, 0.2, max_steps=100)
    assert bool(res.success)
    for p, v in zip(paths, true):
        np.testing.assert_allclose(res.parameters[p], v, rtol=1e-4, err_msg=p)
    assert np.all(res.within((1e-6, 1e-5, 1e-3)))


def test_update_model_bad_input(drive):
    data = ModalData([100.0], [0.05], [-90.0])
    with pytest.raises(ValueError, match=r"no drive parameter 'nut.stifness'"):
        update_model(drive, data, {"nut.stifness": (1e8, 1e9)}, 0.2)
    with pytest.raises(ValueError, match=r"lo < hi"):
        update_model(drive, data, {"nut.stiffness": (1e9, 1e8)}, 0.2)
    with pytest.raises(ValueError, match=r"drive_modes\(position_m=\.\.\.\)` must be inside the "
                                         r"travel \[0.1, 0.7\] m, got 0.9 at index 1"):
        drive_modes(drive, [0.2, 0.9], n_modes=2)
    with pytest.raises(ValueError, match=r"equal lengths"):
        ModalData([100.0, 200.0], [0.05], [-90.0])


def test_identified_modes_agree_with_eigen_analysis(drive):
    """Two independent routes to the same modes: a multi-mode fit of the exact FRF h21
    (identify_modes) and the eigen-analysis of the FE twin (drive_modes)."""
    pos = np.array([0.1, 0.4])
    f = np.geomspace(10.0, 2500.0, 2000)
    H = np.asarray(drive.frf(pos, f))[:, :, 1, 0]
    # 7 terms: the lowest (ζ ≈ 1, below 2 Hz) absorbs the rigid-body background
    fit = fdjax.identify_modes_batched(f, H, 7)
    model = drive_modes(drive, pos, n_modes=6)
    below = slice(0, 5)  # the FE twin is verified within 0.5 % below 2 kHz (test_statespace)
    ff = np.asarray(fit.frequency_hz)[:, 1:][:, below]
    fm = np.asarray(model.frequency_hz)[:, below]
    np.testing.assert_allclose(ff, fm, rtol=5e-3)
    np.testing.assert_allclose(np.asarray(fit.damping)[:, 1:][:, below],
                               np.asarray(model.damping)[:, below], rtol=0.02)
    dphi = np.asarray(fit.phase_deg)[:, 1:][:, below] - np.asarray(model.phase_deg)[:, below]
    dphi = (dphi + 180) % 360 - 180
    # measured ≤ 4.5° (the screw's axial mode at 0.4 m, ζ 0.04, 1610 Hz)
    assert np.max(np.abs(dphi)) < 6.0


# ---------------------------------------------------------------- Table 1 calibration
# The shipped reference drive against the paper's Table 1 (h21 at Y_table = 115 mm); the
# shortfall documented in reference_drive's docstring and the README: (quantity, mode) → the
# documented range of the relative error (frequency, damping) or the phase error (°).
TOLERANCES = (0.03, 0.25, 15.0)
MET = np.array([  # rows: frequency, damping, phase; columns: modes 1–5
    [True, True, True, True, True],
    [True, False, True, False, True],
    [True, False, False, True, True],
])
SHORTFALL = {
    ("damping", 1): (-0.60, -0.50),  # −55 %: 0.076 against 0.170
    ("damping", 3): (0.80, 1.00),  # +92 %: 0.0058 against 0.003
    ("phase", 1): (-130.0, -115.0),  # −122°: −277° against −155° (in phase with the rigid body)
    ("phase", 2): (150.0, 170.0),  # +160°: −100° against −260° (in phase, not out of phase)
}


def _check_against_table_1(f_err, z_err, p_err):
    met = np.stack([np.abs(f_err) <= TOLERANCES[0], np.abs(z_err) <= TOLERANCES[1],
                    np.abs(p_err) <= TOLERANCES[2]])
    np.testing.assert_array_equal(met, MET)
    errors = {"damping": z_err, "phase": p_err}
    for (quantity, k), (lo, hi) in SHORTFALL.items():
        assert lo <= errors[quantity][k] <= hi, (quantity, k + 1, errors[quantity][k])


def test_reference_drive_meets_table_1_or_the_documented_shortfall(drive):
    """11 of 15 Table 1 targets met; the four misses are exactly the documented shortfall."""
    T, y = fdjax.TABLE_1, fdjax.TABLE_1_POSITION_M
    # the model's modes paired with the table as update_model pairs them (no steps taken)
    res = update_model(drive, T, {"nut.damping": (50.0, 200.0)}, y, max_steps=0)
    f_err, z_err = np.asarray(res.frequency_error), np.asarray(res.damping_error)
    p_err = np.asarray(res.phase_error_deg)
    _check_against_table_1(f_err, z_err, p_err)
    # they are the five lowest flexible modes of h21, all visible in the FRF
    m = drive_modes(drive, y, n_modes=6)
    # rtol: eig round-off between two compiled programs
    np.testing.assert_allclose(res.modes.frequency_hz, m.frequency_hz[:5], rtol=1e-9)
    assert np.all(np.asarray(m.prominence[:5]) > 0.05)
    # cross-check: the same modes identified from the exact FRF (no model internals)
    f = np.geomspace(10.0, 2000.0, 2000)
    h = np.asarray(drive.frf([y], f))[0, :, 1, 0]
    fit = fdjax.identify_modes(f, h, 7)  # + one term (ζ ≈ 1) for the rigid-body background
    fi, zi, pi = (np.asarray(x)[1:6] for x in (fit.frequency_hz, fit.damping, fit.phase_deg))
    np.testing.assert_allclose(fi, np.asarray(m.frequency_hz[:5]), rtol=5e-3)
    tf, tz, tp = (np.asarray(x) for x in (T.frequency_hz, T.damping, T.phase_deg))
    _check_against_table_1(fi / tf - 1, zi / tz - 1, (pi - tp + 180) % 360 - 180)
