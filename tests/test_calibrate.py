"""Modal characteristics of the model and model updating (issue 3, point 3)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import fdjax
from fdjax._drive import ModalData, drive_modes, update_model


@pytest.fixture(scope="module")
def drive():
    return fdjax.table1_drive()


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
    assert abs(peak / f[k] - 1) < 2 * float(m.damping_ratio[k]) ** 2 + 2e-3  # FE mesh + damped peak
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
    np.testing.assert_allclose(float(g), float(fd), rtol=5e-7)  # measured 9.1e-8
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
    data = ModalData(m.frequency_hz[:5], m.damping_ratio[:5], m.phase_deg[:5])
    bounds = {"nut.stiffness": (1e8, 1.5e9), "carriage.pitch_stiffness": (1e6, 1e8),
              "rotary.coupling_damping": (1e-2, 10.0)}
    res = update_model(drive, data, bounds, 0.2, max_steps=100)
    assert bool(res.success)
    for p, v in zip(paths, true):
        # noise-free data: the fit ends at the solver's tolerance (measured 2.1e-9)
        np.testing.assert_allclose(res.parameters[p], v, rtol=1e-7, err_msg=p)
    assert np.all(res.within((1e-6, 1e-5, 1e-3)))
    assert res.at_bound == {p: False for p in paths}
    # the true nut stiffness above its upper bound: the fit ends on that bound, and says so
    # (the same shapes: the compiled solve is reused)
    low = dict(bounds, **{"nut.stiffness": (1e8, 5e8)})
    capped = update_model(drive, data, low, 0.2, max_steps=100)
    assert capped.at_bound == {"nut.stiffness": True, "carriage.pitch_stiffness": False,
                               "rotary.coupling_damping": False}, capped.parameters
    # measured 4.99999996e8 after 63 steps, with the solver reporting success
    np.testing.assert_allclose(capped.parameters["nut.stiffness"], 5e8, rtol=1e-7)


def test_update_model_bad_input(drive):
    data = ModalData([100.0], [0.05], [-90.0])
    with pytest.raises(ValueError, match=r"no drive parameter 'nut.stifness'"):
        update_model(drive, data, {"nut.stifness": (1e8, 1e9)}, 0.2)
    with pytest.raises(ValueError, match=r"lo < hi"):
        update_model(drive, data, {"nut.stiffness": (1e9, 1e8)}, 0.2)
    # bounds outside what the drive may be: through the parameter's own constructor
    with pytest.raises(ValueError, match=r"`update_model\(parameters=\.\.\.\)` bound -2e\+09 for "
                                         r"'nut\.stiffness' is not a value the drive may take: "
                                         r"`NutJoint\(stiffness=\.\.\.\)` must be finite and "
                                         r"positive"):
        update_model(drive, data, {"nut.stiffness": (-2e9, -1e9)}, 0.2)
    with pytest.raises(ValueError, match=r"bound 0\.07 for 'screw\.bore_diameter' is not a value "
                                         r"the drive may take: `Screw\(bore_diameter=\.\.\.\)` "
                                         r"must be smaller than the diameter"):
        update_model(drive, data, {"screw.bore_diameter": (0.01, 0.07)}, 0.2)
    # more modes than the drive has oscillatory poles (an overdamped pitch mode, a coarse
    # mesh): refused, not filled with duplicates
    stiff = eqx.tree_at(lambda d: d.carriage.pitch_damping, drive,
                        jnp.asarray(1e6, jnp.float64))
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"`drive_modes\(n_modes=\.\.\.\)` asks "
                                                      r"for more modes than the drive has "
                                                      r"oscillatory poles"):
        drive_modes(stiff, 0.3, n_modes=12, twin=fdjax.TwinOptions(n_elements=4))
    with pytest.raises(ValueError, match=r"drive_modes\(position_m=\.\.\.\)` must be inside the "
                                         r"travel \[0.1, 0.7\] m, got 0.9 at index 1"):
        drive_modes(drive, [0.2, 0.9], n_modes=2)
    with pytest.raises(ValueError, match=r"equal lengths"):
        ModalData([100.0, 200.0], [0.05], [-90.0])


# The identification's grid: 10 Hz–2 kHz, the band in which the FE twin is verified (0.5 %,
# test_statespace); its lowest flexible modes are Table 1's 49/95/131 Hz, heavily damped
# (ζ 0.08–0.14) and overlapping, and its five modes below 2 kHz are fitted with 7 terms: one for
# the twin's 2.42 kHz mode just above the band and one (ζ ≈ 1, below 1 Hz) that absorbs the
# damped rigid body's real pole at −c_eq/J_eq = −7.04 rad/s (1.12 Hz), which the fit's
# rigid-body terms c₀/s² + c₁/s cannot represent.
FIT_FREQ = np.geomspace(10.0, 2000.0, 2000)
FIT_POSITIONS = np.array([0.1, fdjax.TABLE_1_POSITION_M, 0.4])
# Vector-fitting starts (vf_iterations, vf_extra_modes).  The fit is a non-convex least-squares
# problem and that spare ζ ≈ 1 term makes its landscape rough: from one start it lands, at
# round-off-dependent positions and grids, in a local minimum where the spare term sits inside
# the band or a mode is lost (measured: 14 of 48 single fits over 8 grids × 2 positions × 3
# starts, e.g. the default start at 0.1 m on 10–2500 Hz: the spare term at 12.3 Hz, ζ₁ +8.7 %,
# fit error 7.2e-3).  All starts minimise the same objective, so the best of three by fit
# error is that objective's better minimum (16 of 16 over the same grids).
FIT_STARTS = ((10, 3), (5, 3), (20, 4))
# Relative weighted RMS fit error of the good minimum: measured 1.2e-5 (0.1 m), 2.4e-5 (0.4 m);
# the local minima above have ≥ 2.9e-3.
FIT_ERROR_MAX = 1e-4


@pytest.fixture(scope="module")
def identified(drive):
    """The best of FIT_STARTS per position (ModalFit with a leading position axis)."""
    H = np.asarray(drive.frf(FIT_POSITIONS, FIT_FREQ))[:, :, 1, 0]
    fits = [
        fdjax.identify_modes_batched(FIT_FREQ, H, 7, vf_iterations=i, vf_extra_modes=e,
                                     max_steps=1000, throw=False)
        for i, e in FIT_STARTS
    ]
    # a start that ends on a degenerate model (non-finite fit, reported by its result) is
    # not the best
    err = np.stack([np.asarray(f.fit_error) for f in fits])
    best = np.argmin(np.where(np.isfinite(err), err, np.inf), axis=0)
    for f, e in zip(fits, err):  # a non-finite fit is never reported as a success
        assert np.all(np.isfinite(e) | np.asarray(f.result != optx.RESULTS.successful))

    def pick(*xs):  # per position, that position's entry of the best start's fit
        return jnp.stack([xs[b][p] for p, b in enumerate(best)])

    fit = jax.tree_util.tree_map(pick, *fits)
    # The good minimum, converged (in it the spare term's valley is flat: 200–350 LM steps).
    assert np.all(np.asarray(fit.fit_error) < FIT_ERROR_MAX), np.asarray(fit.fit_error)
    assert np.all(np.asarray(fit.result == optx.RESULTS.successful))
    return fit


def _exact_poles(drive, pos, start):
    """Poles of the exact (continuous) drive: zeros of 1/h21(ω) in complex ω by Newton from
    ``start`` (rad/s, per position and mode), and the last relative Newton step."""

    def one(y, lam):
        g = lambda w: 1.0 / drive.receptance(y, w)[1, 0]
        dg = jax.grad(g, holomorphic=True)
        step = lambda w: w - g(w) / dg(w)
        w = jax.lax.fori_loop(0, 30, lambda _, w: step(w), lam / 1j)
        return 1j * w, jnp.abs(step(w) - w) / jnp.abs(w)

    return jax.jit(jax.vmap(jax.vmap(one, (None, 0)), (0, 0)))(pos, start)


def test_identified_modes_agree_with_eigen_analysis(drive, identified):
    """Three routes to the same modes: a multi-mode fit of the exact FRF h21 (identify_modes),
    the eigen-analysis of the FE twin (drive_modes) and Newton on the exact model's poles."""
    pos = FIT_POSITIONS[[0, 2]]
    fit = jax.tree_util.tree_map(lambda x: x[np.array([0, 2])], identified)
    model = drive_modes(drive, pos, n_modes=6)
    below = slice(0, 5)  # the five modes below 2 kHz; fit index 0 is the spare ζ ≈ 1 term
    ff, zf, pf = (np.asarray(x)[:, 1:6] for x in (fit.frequency_hz, fit.damping_ratio,
                                                  fit.phase_deg))
    fm, zm, pm = (np.asarray(x)[:, below] for x in (model.frequency_hz, model.damping_ratio,
                                                     model.phase_deg))
    lam, last = _exact_poles(drive, jnp.asarray(pos), model.poles[:, below])
    assert float(jnp.max(last)) < 1e-12  # Newton converged
    fe, ze = np.abs(np.asarray(lam)) / (2 * np.pi), -np.real(lam) / np.abs(lam)

    # the fit against the exact poles: measured ≤ 4.6e-5 (f) and ≤ 3.3e-4 (ζ, the heavily
    # damped, overlapped mode 1); a residual fit error of ~2e-5 moves the broad mode 1 most
    np.testing.assert_allclose(ff, fe, rtol=2e-4)
    np.testing.assert_allclose(zf, ze, rtol=1e-3)
    # the twin against the exact poles: its 12-element discretisation, measured ≤ 9.5e-4 (f)
    # and ≤ 3.1e-3 (ζ of the screw's axial mode, 1493 Hz at 0.1 m); the twin is verified within
    # 0.5 % in frequency below 2 kHz (test_statespace)
    np.testing.assert_allclose(fm, fe, rtol=5e-3)
    np.testing.assert_allclose(zm, ze, rtol=1e-2)
    # hence fit against twin within the twin's own error
    np.testing.assert_allclose(ff, fm, rtol=5e-3)
    np.testing.assert_allclose(zf, zm, rtol=1e-2)
    dphi = (pf - pm + 180) % 360 - 180
    # measured ≤ 4.8° (the screw's axial mode at 0.4 m, ζ 0.04, 1611 Hz, where the twin's
    # frequency is 0.08 % low)
    assert np.max(np.abs(dphi)) < 6.0


# ---------------------------------------------------------------- Table 1 calibration
# The shipped reference drive against the paper's Table 1 (h21 at Y_table = 115 mm); the
# shortfall documented in table1_drive's docstring and the README: (quantity, mode) → the
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


def test_table1_drive_meets_table_1_or_the_documented_shortfall(drive, identified):
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
    # cross-check: the same modes identified from the exact FRF (no model internals), the
    # best of the vector-fitting starts (see FIT_STARTS) at Y_table = 115 mm
    assert FIT_POSITIONS[1] == y
    fi, zi, pi = (np.asarray(x)[1, 1:6] for x in (identified.frequency_hz, identified.damping_ratio,
                                                   identified.phase_deg))
    np.testing.assert_allclose(fi, np.asarray(m.frequency_hz[:5]), rtol=5e-3)
    tf, tz, tp = (np.asarray(x) for x in (T.frequency_hz, T.damping_ratio, T.phase_deg))
    _check_against_table_1(fi / tf - 1, zi / tz - 1, (pi - tp + 180) % 360 - 180)
