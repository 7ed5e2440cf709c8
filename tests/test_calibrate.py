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
    f = np.asarray(m.frequency_hz)
    # the first (axial) mode dominates h21 near its resonance: |h21| peaks within ζ·f of it
    grid = np.linspace(0.8 * f[0], 1.2 * f[0], 4001)
    h = np.abs(np.asarray(drive.frf([0.3], grid))[0, :, 1, 0])
    peak = grid[np.argmax(h)]
    assert abs(peak / f[0] - 1) < 2 * float(m.damping[0]) ** 2 + 2e-3  # FE mesh + damped peak
    # resonant phase: phase of the mode's own term at ω_r; for the dominant axial mode the
    # whole FRF is that term plus a smooth background, so the FRF phase at ω_r is close
    hr = np.asarray(drive.frf([0.3], f[:1]))[0, 0, 1, 0]
    ph = np.degrees(np.angle(hr))
    assert abs(((ph - float(m.phase_deg[0]) + 180) % 360) - 180) < 10.0


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
    """Perturb two parameters, take the true model's modes as data, recover the parameters."""
    truth = eqx.tree_at(
        lambda d: [d.nut.stiffness, d.nut.damping],
        drive, [jnp.asarray(3.2e8), jnp.asarray(9.0e3)],
    )
    m = drive_modes(truth, 0.2, n_modes=2)
    data = ModalData(m.frequency_hz[:1], m.damping[:1], m.phase_deg[:1])
    res = update_model(
        drive, data, {"nut.stiffness": (1e8, 1.5e9), "nut.damping": (1e2, 1e5)}, 0.2,
        max_steps=100,
    )
    assert bool(res.success)
    np.testing.assert_allclose(res.parameters["nut.stiffness"], 3.2e8, rtol=1e-4)
    np.testing.assert_allclose(res.parameters["nut.damping"], 9.0e3, rtol=1e-3)
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
    fit = fdjax.identify_modes_batched(f, H, 6)
    model = drive_modes(drive, pos, n_modes=6)
    ff, fm = np.asarray(fit.frequency_hz), np.asarray(model.frequency_hz)
    well_separated = [0, 1, 3, 4, 5]  # mode 3 (pitch, ζ ≈ 0.17) is barely visible in h21
    # the FE twin's natural frequencies are within 0.16 % of the exact model (test_statespace)
    np.testing.assert_allclose(ff[:, well_separated], fm[:, well_separated], rtol=5e-3)
    dphi = np.asarray(fit.phase_deg) - np.asarray(model.phase_deg)
    dphi = (dphi + 180) % 360 - 180
    assert np.max(np.abs(dphi[:, well_separated])) < 5.0
