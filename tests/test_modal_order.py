"""Modal identification without a guessed order (paper Sec. 3.2, Table 1).

Oracles: the reference drive's own modes, from the eigen-analysis of its finite-element twin
(``fdjax.drive_modes`` on a 48-element mesh: its frequencies converge O(h²) to those of the
exact distributed FRF that ``drive.frf`` computes; 0.03 % left at 2.4 kHz, 0.54 % with the
default 12 elements); and a closed-form FRF from known poles and residues (Table 1's modes)
with a damped rigid body c₁/s + Q/(s − a), as a drive on damped guideways has.

Compiled programs are shared: every drive case uses 500 or 5000 points, and the refined
model has the same size on grids of one length.
"""

import matplotlib
import numpy as np
import pytest
from test_modal import pair  # a mode's pole and residue from its frequency, ζ, phase, size

import fdjax
from fdjax import cli, plots
from fdjax._modal import ModalFit, StabilisationDiagram, identify_modes, stabilisation_diagram

matplotlib.use("Agg")

TABLE1 = np.array(  # frequency (Hz), damping ratio, resonant phase (deg); Y_table = 115 mm
    [[49, 0.120, -135], [95, 0.170, -155], [130, 0.090, -260], [1030, 0.003, -198],
     [1529, 0.010, -31]]
)
GAINS = np.array([0.5, 0.3, 0.4, 0.02, 0.05])
A_RIGID = -7.0  # rad/s: −c_eq/J_eq of the reference drive is −7.04 rad/s
C1 = 9e-3  # x2/T1 → i_sc/(s(J s + c)) = C1/s − C1/(s − a) (units of H·rad/s)
D = 1e-10


def synthetic_frf(freq):
    """Σ R/(s−λ) + R*/(s−λ*) + C1/s − C1/(s − a) + d, Table 1's modes; the modes' peaks
    against the background c₁|a|/ω² at their frequencies are GAINS/(2ζ)."""
    s = 2j * np.pi * np.asarray(freq)
    h = C1 / s - C1 / (s - A_RIGID) + D + 0j
    scale = C1 * abs(A_RIGID)
    for (f, z, p), g in zip(TABLE1, GAINS):
        lam, res = pair(f, z, p, g * scale)
        h = h + res / (s - lam) + np.conj(res) / (s - np.conj(lam))
    return h


def noisy(h, level, seed=0):
    rng = np.random.default_rng(seed)
    e = rng.standard_normal(h.shape) + 1j * rng.standard_normal(h.shape)
    return h * (1 + level * e / np.sqrt(2))


def phase_error(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + 180) % 360 - 180)


def errors(fit: ModalFit, f_true, z_true, p_true, band):
    """Max relative errors in frequency and damping and max phase error (deg) over the true
    modes in the band; each true mode matched to the nearest identified one."""
    f, z, p = (np.asarray(x) for x in (fit.frequency_hz, fit.damping_ratio, fit.phase_deg))
    ef = ez = ep = 0.0
    for ft, zt, pt in zip(f_true, z_true, p_true):
        if not band[0] <= ft <= band[1]:
            continue
        j = np.argmin(np.abs(f - ft))
        ef, ez = max(ef, abs(f[j] / ft - 1)), max(ez, abs(z[j] / zt - 1))
        ep = max(ep, float(phase_error(p[j], pt)))
    return ef, ez, ep


def modes_in_band(fit, band):
    f = np.asarray(fit.frequency_hz)
    return f[(f >= band[0]) & (f <= band[1])]


@pytest.fixture(scope="module")
def drive_truth():
    drive = fdjax.table1_drive()
    m = fdjax.drive_modes(drive, fdjax.TABLE_1_POSITION_M, n_modes=10,
                          twin=fdjax.TwinOptions(n_elements=48))
    return drive, tuple(np.asarray(x) for x in (m.frequency_hz, m.damping_ratio, m.phase_deg))


# Tolerances: just above the errors measured (printed by the tests, `pytest -s`).
# Drive, noise-free: the twin's own discretisation (0.03 % at 2.4 kHz on 48 elements) and the
# linear 500-point grid's 5 Hz spacing; with 1 % noise the 49 Hz mode (8 % of |h21|, ζ = 0.14)
# dominates every error, most on the linear grid (few points below 100 Hz).
TOL_DRIVE = {  # (grid, points, noisy): (frequency, damping ratio, phase in degrees)
    ("linear", 500, False): (4e-4, 5e-4, 0.06),  # measured 3.4e-4, 3.9e-4, 0.045°
    ("log", 500, True): (3e-3, 0.016, 1.7),  # 2.6e-3, 0.014, 1.46°
    ("log", 5000, False): (6e-5, 5e-4, 0.05),  # 4.4e-5, 4.1e-4, 0.034°
    ("linear", 5000, True): (0.01, 0.035, 5.0),  # 8.9e-3, 0.029, 4.4° (all the 49 Hz mode's)
}
# The real pole −c_eq/J_eq = −7.04 rad/s, below the band: measured 1.1e-4 and 1.6e-3
# noise-free, 0.028 and 0.085 with noise.
TOL_REAL = {False: 3e-3, True: 0.1}
# Synthetic (f, ζ, phase, real pole, background 1/s²): noise-free the model is exact and the
# errors are the solver's (measured 1e-15, 2e-13, 4e-12°, 6e-13, 1e-12); with 1 % noise
# 9e-4, 0.030, 2.8°, 0.27 (the pole below the band), and the 1/s² coefficient far better.
TOL_SYNTHETIC = {False: (1e-12, 1e-11, 1e-9, 1e-11, 1e-10), True: (1.5e-3, 0.04, 3.5, 0.35, 0.05)}
# Identification against the twin's eigen-analysis at the travel's ends: measured 3.4e-4,
# 8.4e-4, 0.04° (the requirement is 0.5 %, 10 %, 5°)
TOL_CLI = (6e-4, 1.5e-3, 0.08)


# Grid × noise cases of the drive's h21 at 115 mm. Two lengths (500, 5000 points) so that
# linear and log grids share their compiled refinement.
DRIVE_CASES = [
    ("linear", 500, (10.0, 2500.0), 0.0),
    ("log", 500, (5.0, 3000.0), 0.01),
    ("log", 5000, (20.0, 2000.0), 0.0),
    ("linear", 5000, (5.0, 3000.0), 0.01),
]


def grid(kind, n, band):
    return np.linspace(*band, n) if kind == "linear" else np.geomspace(*band, n)


@pytest.mark.parametrize("kind, n, band, noise", DRIVE_CASES,
                         ids=[f"{k}-{n}-{int(b[0])}-{int(b[1])}Hz-noise{z}"
                              for k, n, b, z in DRIVE_CASES])
def test_drive_without_order(drive_truth, kind, n, band, noise):
    """identify_modes(freq_hz, frf) alone finds every mode of the drive in the band (the
    49 Hz mode on its damped rigid body included), and no other, on linear and log grids,
    noise-free and with 1 % complex noise."""
    drive, (f_t, z_t, p_t) = drive_truth
    f = grid(kind, n, band)
    h = np.asarray(drive.frf(fdjax.TABLE_1_POSITION_M, f))[0, :, 1, 0]
    if noise:
        h = noisy(h, noise)
    fit = identify_modes(f, h)
    in_band = f_t[(f_t >= band[0]) & (f_t <= band[1])]
    assert modes_in_band(fit, band).size == in_band.size
    ef, ez, ep = errors(fit, f_t, z_t, p_t, band)
    # The damped rigid body is a real pole near −c_eq/J_eq = −7.04 rad/s, not a mode.
    a = float(drive.reflected_damping() / drive.reflected_inertia())
    assert fit.real_poles.shape == (1,)
    er = abs(float(fit.real_poles[0]) / -a - 1)
    print(f"MEASURED drive {kind} {n} {band} {noise}: f {ef:.2e} zeta {ez:.2e} phase {ep:.3f} "
          f"real pole {er:.2e}")
    assert er < TOL_REAL[noise > 0]
    tol = TOL_DRIVE[(kind, n, noise > 0)]
    assert ef < tol[0] and ez < tol[1] and ep < tol[2], (ef, ez, ep)


@pytest.fixture(scope="module")
def synthetic():
    f = np.geomspace(10.0, 2500.0, 500)
    h = synthetic_frf(f)
    return f, h, stabilisation_diagram(f, h)


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_synthetic_without_order(synthetic, noise):
    """Table 1's five modes on a damped rigid body, from the closed form: exact (to the
    solver's tolerance) without noise, and the damped rigid body is the real pole a, never a
    mode."""
    f, h, _ = synthetic
    fit = identify_modes(f, noisy(h, noise) if noise else h)
    assert fit.n_modes == 5  # no mode for the rigid body, none above the band
    assert np.all(np.asarray(fit.damping_ratio) < 0.5)
    ef, ez, ep = errors(fit, *TABLE1.T, (f[0], f[-1]))
    er = abs(float(fit.real_poles[0]) / A_RIGID - 1)
    # Below the band only Q·a + c₀, the background's 1/s² coefficient (here −C1·a), is well
    # determined under noise; Q and a trade against each other.
    c0 = float(fit.rigid_body[0]) + float(fit.real_residues[0] * fit.real_poles[0])
    eq = abs(c0 / (-C1 * A_RIGID) - 1)
    print(f"MEASURED synthetic {noise}: f {ef:.2e} zeta {ez:.2e} phase {ep:.2e} real pole "
          f"{er:.2e} residue {eq:.2e}")
    tol = TOL_SYNTHETIC[noise > 0]
    assert ef < tol[0] and ez < tol[1] and ep < tol[2], (ef, ez, ep)
    assert fit.real_poles.shape == (1,)
    assert er < tol[3] and eq < tol[4], (er, eq)
    if not noise:  # the real pole's residue −C1 (the 1/s term takes +C1, 1/s² nothing)
        assert abs(float(fit.real_residues[0]) / -C1 - 1) < tol[4]


def test_stabilisation_diagram_and_plot(synthetic):
    """The diagram's poles per order, stable flags and selection; its plot."""
    f, h, d = synthetic
    assert isinstance(d, StabilisationDiagram)
    n_o = d.orders.shape[0]
    assert d.poles.shape[0] == d.stable.shape[0] == d.fit_error.shape[0] == n_o
    assert d.n_modes == 5
    np.testing.assert_allclose(d.mode_frequency_hz, TABLE1[:, 0], rtol=1e-6)
    # physical ⊂ stable ⊂ stable in frequency
    assert np.all(d.stable <= d.stable_frequency) and np.all(d.physical <= d.stable)
    assert not d.physical[0].any()  # order 1 has no previous order to be stable against
    # order 5 fits the five modes, but its poles of the mode order 4 lacked are not stable
    # yet: order 6 is the first with all five stable
    assert d.orders[d.selected] == 6 and d.selected_real_poles.shape == (1,)
    fit = identify_modes(f, h, initial=d)
    np.testing.assert_allclose(fit.frequency_hz, TABLE1[:, 0], rtol=1e-8)
    fig = plots.stabilisation_diagram(d)
    ax = fig.axes[0]
    assert ax.get_xlabel() == "frequency (Hz)" and "order" in ax.get_ylabel()
    assert len(fig.axes) == 2  # the FRF magnitude on its twin axis
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any("physical" in t for t in labels) and any("selected" in t for t in labels)


def test_order_free_errors(synthetic):
    """Also: ``refine=False`` without an order returns the diagram's estimate (it was
    ignored, 159 refinement steps), bad ``refine``/``vf_extra_modes`` are refused (they were
    not checked), and the sweep checks its data as a whole, with its own name and shapes (it
    said "`identify_modes(frf=...)` must have shape (n_freq) ... got shape (400,)" for a
    (2, 400) sweep)."""
    f, h, d = synthetic
    est = identify_modes(f, h, refine=False)
    assert int(est.num_steps) == 0
    np.testing.assert_allclose(est.frequency_hz, d.mode_frequency_hz, rtol=1e-12)
    with pytest.raises(TypeError, match=r"`identify_modes\(refine=\.\.\.\)` must be a bool"):
        identify_modes(f, h, refine="no")
    with pytest.raises(ValueError, match=r"`identify_modes\(vf_extra_modes=\.\.\.\)`"):
        identify_modes(f, h, vf_extra_modes=-5)
    sweep = np.stack([h, h])
    with pytest.raises(ValueError, match=r"`identify_modes_batched\(frf=\.\.\.\)` must be a "
                                         r"complex FRF"):
        fdjax.identify_modes_batched(f, sweep.real)
    with pytest.raises(ValueError, match=r"`identify_modes_batched\(frf=\.\.\.\)` must have "
                                         r"shape \(n_positions, n_freq\).* got shape"):
        fdjax.identify_modes_batched(f, sweep[:, :-1])
    with pytest.raises(ValueError, match=r"`identify_modes_batched\(freq_hz=\.\.\.\)` must be "
                                         r"strictly increasing"):
        fdjax.identify_modes_batched(f[::-1], sweep)
    with pytest.raises(ValueError, match=r"`identify_modes\(n_modes=...\)` must be None"):
        identify_modes(f, h, 5, initial=d)
    with pytest.raises(ValueError, match="another frequency grid"):
        identify_modes(f[:-1], h[:-1], initial=d)
    with pytest.raises(ValueError, match=r"`stabilisation_diagram\(freq_tol=...\)` must be "
                                         r"finite and positive, got -0.01"):
        stabilisation_diagram(f, h, freq_tol=-0.01)
    with pytest.raises(ValueError, match=r"`stabilisation_diagram\(max_modes=...\)`"):
        stabilisation_diagram(f, h, max_modes=0)


def test_cli_identification_agrees_with_model():
    """`fdjax modes` (identification, order chosen at every position) against
    `fdjax modes --source model` (eigen-analysis of the twin): the same modes in the same
    columns, within 0.5 % / 10 % / 5° (to what was measured: TOL_CLI)."""
    fit = cli.modes(None, 2, None, "fit")  # the ends of the travel, 100 and 700 mm
    model = cli.modes(None, 2, None, "model")
    assert fit["frequency_hz"].shape == model["frequency_hz"].shape == (2, 5)
    ef = np.abs(fit["frequency_hz"] / model["frequency_hz"] - 1).max()
    ez = np.abs(fit["damping_ratio"] / model["damping_ratio"] - 1).max()
    ep = phase_error(fit["phase_deg"], model["phase_deg"]).max()
    print(f"MEASURED cli: f {ef:.2e} zeta {ez:.2e} phase {ep:.3f}")
    assert ef < TOL_CLI[0] and ez < TOL_CLI[1] and ep < TOL_CLI[2], (ef, ez, ep)
