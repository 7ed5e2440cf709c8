"""The figures draw the numbers they are given: each test reads the data back from the axes and
compares it with the inputs (in the units of the axis labels), and refuses what it cannot draw.
Small synthetic data: no simulation, no drive."""

import jax.numpy as jnp
import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from fdjax import RESULTS, Simulation, plots  # noqa: E402

F = np.geomspace(10.0, 3000.0, 40)
POS = np.array([0.1, 0.4, 0.7])


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _loop(scale):
    s = 2j * np.pi * F
    return scale * 2e4 * (1 + s / 300.0) / (s * (1 + s / 3000.0) ** 2)


def _run(n=200, failed_at=None, code=RESULTS.successful):
    """A synthetic run: r a ramp, x2 lagging it by a sine."""
    t = np.linspace(0.0, 0.1, n)
    r = 1e-3 * t / 0.1
    x2 = r - 2e-6 * np.sin(2 * np.pi * 20 * t)
    x3 = r - 3e-6 * np.sin(2 * np.pi * 20 * t)
    ref = np.stack([r, np.full(n, 1e-2), np.zeros(n)], axis=-1)
    zeros = np.zeros(n)
    return Simulation(
        t=jnp.asarray(t), reference=jnp.asarray(ref), theta1=jnp.asarray(zeros),
        x2=jnp.asarray(x2), x3=jnp.asarray(x3), torque=jnp.asarray(zeros),
        current=jnp.asarray(zeros), error_scale=jnp.asarray(r - x2),
        error_tool=jnp.asarray(r - x3), position_m=jnp.asarray(0.3 + r), result=code,
        failed_at=jnp.asarray(n if failed_at is None else failed_at), growth_rate=None,
    )


def test_bode_and_nyquist_panels_draw_the_loops():
    """Fig. 14's magnitude is 20·log10|L| in dB (a 10·log10 would pass a count of lines), its
    Nyquist loci are Re L and Im L, per position and case."""
    without = np.stack([_loop(a) for a in (1.0, 1.2, 1.5)])
    with_ = 0.8 * without
    fig = plots.plot_peak_filter_effect(F, POS, without, with_, band_hz=(50.0, 80.0))
    nyq_without, nyq_with, mag, _ = fig.axes
    for ax, L in ((nyq_without, without), (nyq_with, with_)):
        for p in range(POS.size):
            np.testing.assert_array_equal(ax.lines[p].get_xydata(),
                                          np.stack([L[p].real, L[p].imag], -1))
    # per position: without (dashed), then with (solid)
    drawn = [line.get_ydata() for line in mag.lines if line.get_linestyle() in ("--", "-")
             and len(line.get_xdata()) == F.size]
    expected = [20 * np.log10(np.abs(L[p])) for p in range(POS.size) for L in (without, with_)]
    np.testing.assert_allclose(drawn, expected, rtol=1e-15)
    assert mag.get_ylabel() == "|L| (dB)"


def test_tracking_draws_the_error_in_micrometres_and_marks_a_failed_run():
    """The error panels draw 1e6·(r − x2) in µm with its RMS in the legend; a run that stopped
    is drawn up to where it stopped (its outputs are held after), titled in red with why, and
    without an RMS (a diverged run's held output had drawn a 4936 µm error and 'RMS 3.08e+03
    µm')."""
    ok, stopped = _run(), _run(failed_at=99, code=RESULTS.diverged)
    fig = plots.plot_tracking({"good": ok, "bad": stopped}, title="runs", tool=True)
    ax_r, ax_ok, ax_bad = fig.axes
    e2 = np.asarray(ok.error_scale)
    np.testing.assert_allclose(ax_ok.lines[0].get_ydata(), 1e6 * e2, rtol=1e-15)
    np.testing.assert_allclose(ax_ok.lines[1].get_ydata(), 1e6 * np.asarray(ok.error_tool),
                               rtol=1e-15)
    rms = np.sqrt(np.mean(e2**2)) * 1e6
    assert ax_ok.lines[0].get_label() == f"$e_2 = r - x_2$, RMS {rms:.3g} µm"
    assert ax_ok.get_ylabel() == "error (µm)"
    np.testing.assert_allclose(ax_r.lines[1].get_ydata(), 1e3 * np.asarray(ok.x2), rtol=1e-15)
    assert len(ax_bad.lines[0].get_xdata()) == 100  # samples 0..failed_at
    assert ax_bad.lines[0].get_label() == "$e_2 = r - x_2$"
    assert ax_bad.get_title(loc="left").startswith("bad: the closed-loop run diverged")
    assert ax_bad._left_title.get_color() == "C3"  # the title set with loc="left"
    with pytest.raises(TypeError, match=r"`plot_tracking\(runs=\.\.\.\)` must map labels to "
                                        r"fdjax\.simulate's results, got int for 'x'"):
        plots.plot_tracking({"x": 1}, title="")
    with pytest.raises(TypeError, match=r"must be a dict \{label: Simulation\}, got list"):
        plots.plot_tracking([ok], title="")
    import jax
    batch = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), ok)
    with pytest.raises(ValueError, match=r"must hold one run per label, got a batch of shape "
                                         r"\(2,\) for 'b'"):
        plots.plot_tracking({"b": batch}, title="")


def test_frf_family_and_cloud_draw_their_entries():
    """Panel (i, j) of Fig. 10 draws |H[p, :, i, j]| for every position p; Fig. 11's image is
    |ω² h| (the accelerance), or |h| without it, over (position in mm, frequency)."""
    rng = np.random.default_rng(0)
    H = rng.normal(size=(3, F.size, 3, 2)) + 1j * rng.normal(size=(3, F.size, 3, 2))
    fig = plots.plot_frf_family(POS, F, H)
    for k, ax in enumerate(fig.axes):
        i, j = divmod(k, 2)
        for p in range(POS.size):
            np.testing.assert_array_equal(ax.lines[p].get_ydata(), np.abs(H[p, :, i, j]))
    h = H[:, :, 1, 0]
    for acc in (True, False):
        fig = plots.plot_frf_cloud(POS, F, h, accelerance=acc)
        image = np.asarray(fig.axes[0].collections[0].get_array()).reshape(h.shape)
        expected = np.abs(h) * ((2 * np.pi * F) ** 2 if acc else 1.0)
        np.testing.assert_allclose(image, expected, rtol=1e-15)


def test_three_mass_panels_draw_the_first_column():
    """Fig. 2 draws |h_k1| for k = 1, 2, 3 on the top row."""
    rng = np.random.default_rng(1)
    H = rng.normal(size=(F.size, 3, 3)) + 1j * rng.normal(size=(F.size, 3, 3))
    fig = plots.plot_three_mass_frf(F, H)
    for k in range(3):
        np.testing.assert_array_equal(fig.axes[k].lines[0].get_ydata(), np.abs(H[:, k, 0]))


@pytest.mark.parametrize("call, match", [
    (lambda: plots.plot_deflection_shapes(np.eye(3) * (1 + 1j), ["a", "b", "c"]),
     r"`plot_deflection_shapes\(shapes=\.\.\.\)` must be real, got dtype complex128: .*\.imag"),
    (lambda: plots.plot_velocity_nyquist(F, _loop(1.0), _loop(2.0), labels=("only one",)),
     r"`plot_velocity_nyquist\(labels=\.\.\.\)` must hold two titles .* got 1"),
    (lambda: plots.plot_velocity_nyquist(F, np.full(F.size, np.nan + 0j), _loop(1.0)),
     r"`plot_velocity_nyquist\(h_collocated=\.\.\.\)` must be finite and non-zero, got "
     r"\(nan\+0j\) at index 0 and 39 more"),
    (lambda: plots.plot_three_mass_frf(F, np.full((F.size, 3, 3), np.nan)),
     r"`plot_three_mass_frf\(H=\.\.\.\)` must be finite and non-zero"),
    (lambda: plots.plot_peak_filter_effect(F, [0.1], np.zeros((1, F.size)) + 0j,
                                           _loop(1.0)[None]),
     r"`plot_peak_filter_effect\(L_without=\.\.\.\)` must be finite and non-zero, got 0j? at "
     r"index \(0, 0\)"),
    (lambda: plots.plot_peak_filter_effect(F, [0.1], _loop(1.0)[None], _loop(1.0)[None],
                                           radius=-1.0),
     r"`plot_peak_filter_effect\(radius=\.\.\.\)` must be finite and positive, got -1"),
    (lambda: plots.plot_peak_filter_effect(F, [0.1], _loop(1.0)[None], _loop(1.0)[None],
                                           band_hz=(80.0, 50.0)),
     r"`plot_peak_filter_effect\(band_hz=\.\.\.\)` must be \(f_lo, f_hi\) in Hz with "
     r"0 < f_lo < f_hi, got \[80\., 50\.\]"),
    (lambda: plots.plot_resonant_phase([0.1, 0.2], [[-50.0], [50.0]], [[-90.0], [-95.0]]),
     r"`plot_resonant_phase\(frequency_hz=\.\.\.\)` must be positive and finite \(Hz; NaN "
     r"marks a mode missing at a position\), got -50 at index \(0, 0\)"),
    (lambda: plots.plot_rms_over_travel([100, 200], {"a": {"rms_error_um": [1.0, -1.0],
                                                           "stable": [True, True],
                                                           "modulus_margin": [0.6, 0.6]}}),
     r"`plot_rms_over_travel\(results=\.\.\.\)\['a'\]\['rms_error_um'\]` must be finite and "
     r"non-negative"),
    (lambda: plots.plot_rms_over_travel([100, 200], {"a": {"rms_error_um": [1.0, 1.0],
                                                           "stable": ["False", "True"],
                                                           "modulus_margin": [0.6, 0.6]}}),
     r"must give 'stable' as booleans, got <U5 for 'a'"),
    (lambda: plots.plot_rms_over_travel([100, 200], {"a": {"rms_error_um": [1.0, 1.0],
                                                           "stable": [True, True],
                                                           "modulus_margin": [0.6, 0.6]}},
                                        design_mm=[0.115, 0.4]),
     r"`plot_rms_over_travel\(design_mm=\.\.\.\)` must be table positions in mm, .* 0\.4 m "
     r"is 400 mm"),
])
def test_figures_refuse_what_they_cannot_draw(call, match):
    """Complex deflection shapes (their real part had been drawn, with a ComplexWarning), NaN
    or zero responses (gaps, −∞ dB), a negative Nyquist radius (inverted axes), a reversed
    band, negative frequencies, negative RMS errors, 'stable' as strings (all truthy), design
    positions in metres: refused with the argument named."""
    with pytest.raises(ValueError, match=match):
        call()
