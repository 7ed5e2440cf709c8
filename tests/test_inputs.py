"""Checks of the public API that nothing exercised before (each refusal with its exact message),
and oracles for what they guard: the interpolated MCM, the RMS error of a run, the objective's
total and the mode tracker's MAC tolerance."""

import dataclasses
import math
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fdjax

SERVO = fdjax.Servo()                     # 8 kHz: Nyquist 4 kHz, period 0.000125 s
BOUNDS = fdjax.MCMBounds.for_servo(SERVO)
POSITIONS = np.array([0.1, 0.25, 0.4, 0.7])  # unevenly spaced design positions (m)
THETA = np.array([                           # four distinct designs (normalised), (4, 7)
    [0.5, -0.2, 0.8, 0.0, 1.7, 1.0, -0.7],
    [0.9, 0.3, 0.6, -0.4, 1.2, 0.7, -0.2],
    [-0.3, 0.1, 1.1, 0.5, 2.0, 1.4, -1.1],
    [0.2, -0.6, 0.4, 0.9, 0.8, 0.2, 0.3],
])
LOOP = fdjax.DoubleLoop(150.0, 3000.0, 40.0)


@pytest.fixture(scope="module")
def interpolated():
    return fdjax.InterpolatedLoop(LOOP, POSITIONS, THETA, BOUNDS)


def _same_mcm(a, b, rtol):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb) == 7
    for x, y in zip(la, lb):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=0)


# ------------------------------------------------------------------------- InterpolatedLoop
def test_interpolated_loop_is_exact_at_the_designs_and_linear_between(interpolated):
    """At each design position the controller's MCM is bounds.to_mcm(θ_i); between two
    positions it is to_mcm of θ interpolated linearly with NumPy (np.interp per parameter);
    outside the designs the end designs hold; the gains are the loop's at every position."""
    for i, y in enumerate(POSITIONS):
        c = interpolated.controller(y)
        # θ_i + 0·slope in jnp.interp (θ_{n-1} + 1·Δθ at the last), then the same to_mcm:
        # measured ≤ 2.6e-16 relative (0 but at the last position)
        _same_mcm(c.mcm, BOUNDS.to_mcm(THETA[i]), rtol=1e-15)
        for gain in ("kp", "kv", "ki", "k_ffv", "k_ffa"):
            assert float(getattr(c, gain)) == float(getattr(LOOP, gain))
    for y in (0.13, 0.31, 0.4 + 0.3 * (1 - 1e-9), 0.05, 0.75):
        want = np.array([np.interp(y, POSITIONS, THETA[:, k]) for k in range(7)])
        # the same straight line in jnp and np: measured ≤ 1.9e-16 relative (1.1e-16 absolute
        # near θ = 0) in θ, through exp and tanh into the filter (e.g. ω = ω_lo
        # (ω_hi/ω_lo)^σ(θ)): measured ≤ 2.8e-15 relative
        np.testing.assert_allclose(np.asarray(interpolated.normalised(y)), want, rtol=1e-15,
                                   atol=5e-16)
        _same_mcm(interpolated.controller(y).mcm, BOUNDS.to_mcm(want), rtol=1e-14)
    # the weight is (Y − Y_i)/(Y_{i+1} − Y_i) on the uneven grid: 0.31 is 40 % of the way
    mid = np.asarray(interpolated.normalised(0.31))
    # (Y − Y_i)/ΔY = 0.06/0.15 in floating point: measured ≤ 2.2e-16 relative
    np.testing.assert_allclose(mid, THETA[1] + 0.4 * (THETA[2] - THETA[1]), rtol=1e-15,
                               atol=5e-16)


def test_interpolated_loop_refuses_a_position_in_millimetres(interpolated):
    """A position whose thousandth lies between the designs (and which itself does not) was
    given in mm: refused with the value in metres, by controller, normalised and law alike; a
    NaN, a string and a missing position are refused too."""
    for fn, y in (("controller", 300.0), ("normalised", 250.0), ("controller", 100.0)):
        with pytest.raises(ValueError, match=rf"`InterpolatedLoop\.{fn}\(position_m=\.\.\.\)` "
                                             r"must be a table position in metres \(the designs "
                                             r"lie at 0\.1 … 0\.7 m\), got "
                                             rf"{y:g}; {y:g} mm is {y * 1e-3:g} m"):
            getattr(interpolated, fn)(y)
    with pytest.raises(ValueError, match=r"`InterpolatedLoop\.controller\(position_m=\.\.\.\)` "
                                         r"must be a table position in metres .* got 700; "
                                         r"700 mm is 0\.7 m"):
        interpolated.law(700.0)
    with pytest.raises(ValueError, match=r"`InterpolatedLoop\.controller\(position_m=\.\.\.\)` "
                                         r"must be finite \(no NaN or inf\), got nan"):
        interpolated.controller(np.nan)
    with pytest.raises(TypeError, match=r"`InterpolatedLoop\.normalised\(position_m=\.\.\.\)` "
                                        r"must be a number or an array of numbers, got '0\.3'"):
        interpolated.normalised("0.3")
    with pytest.raises(ValueError, match=r"`InterpolatedLoop\.law\(position_m=\.\.\.\)` needs "
                                         r"the table position \(m\)"):
        interpolated.law(None)
    # in metres, just outside the designs, the end design holds (not a millimetre value)
    _same_mcm(interpolated.controller(0.0999).mcm, BOUNDS.to_mcm(THETA[0]), rtol=1e-15)


@pytest.mark.parametrize("positions, theta, got", [
    (POSITIONS, THETA[:, :6], r"\(4,\) and \(4, 6\)"),
    (POSITIONS, THETA[:3], r"\(4,\) and \(3, 7\)"),
    (POSITIONS, THETA[0], r"\(4,\) and \(7,\)"),
    (POSITIONS, THETA[None], r"\(4,\) and \(1, 4, 7\)"),
    (POSITIONS[:1], THETA[:1], r"\(1,\) and \(1, 7\)"),
    (POSITIONS[None], THETA, r"\(1, 4\) and \(4, 7\)"),
], ids=["theta-6-columns", "theta-3-rows", "theta-1-D", "theta-3-D", "one-design",
        "positions-2-D"])
def test_interpolated_loop_refuses_wrong_shapes(positions, theta, got):
    """Positions (n,) and designs (n, 7) with n ≥ 2, or a ValueError naming both shapes."""
    with pytest.raises(ValueError, match=r"`InterpolatedLoop\(positions_m=\.\.\., theta=\.\.\.\)` "
                                         r"must have shapes \(n,\) and \(n, 7\) with n ≥ 2, got "
                                         + got):
        fdjax.InterpolatedLoop(LOOP, positions, theta, BOUNDS)


def test_interpolated_loop_refuses_other_types_and_unordered_positions():
    """loop must be a DoubleLoop and bounds an MCMBounds (TypeErrors); the positions must
    increase strictly: a repeated or a descending position is refused, naming them."""
    with pytest.raises(TypeError, match=r"`InterpolatedLoop\(loop=\.\.\.\)` must be an "
                                        r"fdjax\.DoubleLoop, got PIDLoop"):
        fdjax.InterpolatedLoop(fdjax.PIDLoop(), POSITIONS, THETA, BOUNDS)
    with pytest.raises(TypeError, match=r"`InterpolatedLoop\(bounds=\.\.\.\)` must be an "
                                        r"fdjax\.MCMBounds, got tuple"):
        fdjax.InterpolatedLoop(LOOP, POSITIONS, THETA, (10.0, 3600.0))
    for y, shown in (([0.1, 0.25, 0.25, 0.7], r"\[0\.1, 0\.25, 0\.25, 0\.7\]"),
                     ([0.1, 0.4, 0.25, 0.7], r"\[0\.1, 0\.4, 0\.25, 0\.7\]"),
                     (POSITIONS[::-1], r"\[0\.7, 0\.4, 0\.25, 0\.1\]")):
        with pytest.raises(ValueError, match=r"`InterpolatedLoop\(positions_m=\.\.\.\)` must be "
                                             r"increasing, got " + shown):
            fdjax.InterpolatedLoop(LOOP, y, THETA, BOUNDS)
    # positions in metres and finite, θ finite, one position per controller
    with pytest.raises(ValueError, match=r"`InterpolatedLoop\(positions_m=\.\.\.\)` must be "
                                         r"inside the longest travel of a ball-screw axis "
                                         r"\[-20, 20\] m, got 100 at index 0 and 3 more; table "
                                         r"positions are in metres: 100 mm is 0\.1 m"):
        fdjax.InterpolatedLoop(LOOP, POSITIONS * 1000, THETA, BOUNDS)
    with pytest.raises(ValueError, match=r"`InterpolatedLoop\(positions_m=\.\.\.\)` must be "
                                         r"inside .* got inf at index 3"):
        fdjax.InterpolatedLoop(LOOP, np.r_[POSITIONS[:3], np.inf], THETA, BOUNDS)
    with pytest.raises(ValueError, match=r"`InterpolatedLoop\(theta=\.\.\.\)` must be finite"):
        fdjax.InterpolatedLoop(LOOP, POSITIONS, np.where(THETA == THETA[0, 0], np.nan, THETA),
                               BOUNDS)
    loop = fdjax.InterpolatedLoop(LOOP, POSITIONS, THETA, BOUNDS)
    with pytest.raises(ValueError, match=r"`InterpolatedLoop\.controller\(position_m=\.\.\.\)` "
                                         r"must be one table position \(a scalar; jax\.vmap over "
                                         r"positions\), got shape \(2,\)"):
        loop.controller(np.array([0.2, 0.3]))


# ------------------------------------------------------------------------------- MCMBounds
_T = 1.25e-4  # 8 kHz


_BAD_BOUNDS = [
    ({"period": 0.0}, r"`MCMBounds\(period=\.\.\.\)` must be in \(0, 1\) s, got 0"),
    ({"period": 1.0}, r"`MCMBounds\(period=\.\.\.\)` must be in \(0, 1\) s, got 1"),
    ({"period": math.nan}, r"`MCMBounds\(period=\.\.\.\)` must be in \(0, 1\) s, got nan"),
    ({"freq_hz": (3600.0, 10.0)},
     r"`MCMBounds\(freq_hz=\.\.\.\)` must satisfy 0 < low < high < inf, got \(3600, 10\)"),
    ({"freq_hz": (0.0, 100.0)},
     r"`MCMBounds\(freq_hz=\.\.\.\)` must satisfy 0 < low < high < inf, got \(0, 100\)"),
    ({"freq_hz": (10.0,)},
     r"`MCMBounds\(freq_hz=\.\.\.\)` must be a \(low, high\) pair of numbers, got \(10\.0,\)"),
    ({"freq_hz": (10.0, 4000.0)},
     r"`MCMBounds\(freq_hz=\.\.\.\)` must stay below the Nyquist frequency 4000 Hz of the "
     r"period 0\.000125 s, got high = 4000 Hz"),
    ({"peak_gain": (10.0, 1e-3)},
     r"`MCMBounds\(peak_gain=\.\.\.\)` must satisfy 0 < low < high < inf, got \(10, 0\.001\)"),
    ({"peak_gain": (1.0, math.inf)},
     r"`MCMBounds\(peak_gain=\.\.\.\)` must satisfy 0 < low < high < inf, got \(1, inf\)"),
    ({"peak_damping": (0.5, 0.5)},
     r"`MCMBounds\(peak_damping=\.\.\.\)` must satisfy 0 < low < high < inf, got \(0\.5, 0\.5\)"),
    ({"peak_damping": "ab"},
     r"`MCMBounds\(peak_damping=\.\.\.\)` must be a \(low, high\) pair of numbers, got 'ab'"),
    ({"notch_damping": (-0.1, 2.0)},
     r"`MCMBounds\(notch_damping=\.\.\.\)` must satisfy 0 < low < high < inf, got \(-0\.1, 2\)"),
    ({"notch_damping": 5.0},
     r"`MCMBounds\(notch_damping=\.\.\.\)` must be a \(low, high\) pair of numbers, got 5\.0"),
    ({"peak_phase_max": 0.0}, r"`MCMBounds\(peak_phase_max=\.\.\.\)` must be a number in "
                              r"\(0, π\] rad, got 0\.0"),
    ({"peak_phase_max": 3.2}, r"`MCMBounds\(peak_phase_max=\.\.\.\)` must be a number in "
                              r"\(0, π\] rad, got 3\.2"),
    ({"peak_phase_max": "a"}, r"`MCMBounds\(peak_phase_max=\.\.\.\)` must be a number in "
                              r"\(0, π\] rad, got 'a'"),
    ({"notch_depth_min": 0.0}, r"`MCMBounds\(notch_depth_min=\.\.\.\)` must be a number in "
                               r"\(0, 1\), got 0\.0"),
    ({"notch_depth_min": 1.0}, r"`MCMBounds\(notch_depth_min=\.\.\.\)` must be a number in "
                               r"\(0, 1\), got 1\.0"),
    ({"notch_depth_min": [0.1, 0.2]}, r"`MCMBounds\(notch_depth_min=\.\.\.\)` must be a number "
                                      r"in \(0, 1\), got \[0\.1, 0\.2\]"),
]


@pytest.mark.parametrize("kwargs, message", _BAD_BOUNDS,
                         ids=[f"{k}={v}" for kw, _ in _BAD_BOUNDS for k, v in kw.items()])
def test_mcm_bounds_refuse_each_bound_out_of_range(kwargs, message):
    """Each bound of MCMBounds out of its range is a ValueError naming it, its value and the
    range (the period first, then each (low, high) pair, the phase and the notch depth)."""
    kwargs = {"period": _T, **kwargs}
    with pytest.raises(ValueError, match=message):
        fdjax.MCMBounds(**kwargs)


def test_mcm_bounds_accept_the_closed_ends_and_for_servo_checks_its_arguments():
    """The closed ends of the ranges are admissible (φ_max = π, a frequency bound just below
    Nyquist) and map θ into them; for_servo refuses a Nyquist fraction outside (0, 1) and a
    servo that is not one."""
    b = fdjax.MCMBounds(period=_T, freq_hz=(10.0, 3999.0), peak_phase_max=math.pi)
    # σ(±40) saturates: the filter sits on the bounds, to exp(log(hi/lo))'s round-off
    # (measured ≤ 5.8e-16 relative)
    hi, lo = b.to_mcm(np.full(7, 40.0)), b.to_mcm(np.full(7, -40.0))
    np.testing.assert_allclose(float(hi.peak.omega[0]), 2 * math.pi * 3999.0, rtol=2e-15)
    np.testing.assert_allclose(float(lo.peak.omega[0]), 2 * math.pi * 10.0, rtol=2e-15)
    np.testing.assert_allclose(float(hi.peak.phi[0]), math.pi, rtol=2e-15)
    np.testing.assert_allclose(float(lo.peak.phi[0]), -math.pi, rtol=2e-15)
    np.testing.assert_allclose(float(hi.notch.zeta_n[0] / hi.notch.zeta_d[0]), 1e-3, rtol=2e-15)
    np.testing.assert_allclose(float(lo.notch.zeta_n[0] / lo.notch.zeta_d[0]), 1.0, rtol=2e-15)
    for frac in (0.0, 1.0, -0.5, "a"):
        with pytest.raises(ValueError, match=r"`MCMBounds\.for_servo\(nyquist_fraction=\.\.\.\)` "
                                             rf"must be a number in \(0, 1\), got {frac!r}"):
            fdjax.MCMBounds.for_servo(SERVO, nyquist_fraction=frac)
    with pytest.raises(ValueError, match=r"`MCMBounds\.for_servo\(freq_min_hz=\.\.\.\)` must be "
                                         r"a positive number below the filters' highest "
                                         r"frequency 3600 Hz, got 4000\.0"):
        fdjax.MCMBounds.for_servo(SERVO, freq_min_hz=4000.0)
    with pytest.raises(TypeError, match=r"`MCMBounds\.for_servo\(servo=\.\.\.\)` must be an "
                                        r"fdjax\.Servo, got float"):
        fdjax.MCMBounds.for_servo(_T)
    assert BOUNDS.period == _T
    np.testing.assert_allclose(BOUNDS.freq_hz, (10.0, 0.9 * 4000.0), rtol=1e-15)


# ------------------------------------------------------------------------------ fit_network
def test_fit_network_refuses_bad_steps_and_networks():
    """fit_network takes an integer of steps, at least 1 (not a bool, a float or a string),
    and an ATANetwork; anything else is refused before anything is compiled."""
    net = fdjax.ATANetwork((0.1, 0.7), width=2)
    y, t = POSITIONS, THETA
    for steps in (0, -3, 2.0, "3", None, True):
        with pytest.raises(ValueError, match=r"`fit_network\(steps=\.\.\.\)` must be an integer "
                                             rf"at least 1, got {re.escape(repr(steps))}"):
            fdjax.fit_network(net, y, t, steps=steps)
    with pytest.raises(TypeError, match=r"`fit_network\(network=\.\.\.\)` must be an "
                                        r"fdjax\.ATANetwork, got DoubleLoop"):
        fdjax.fit_network(LOOP, y, t, steps=5)
    with pytest.raises(TypeError, match=r"`fit_network\(network=\.\.\.\)` must be an "
                                        r"fdjax\.ATANetwork, got ScheduledLoop"):
        fdjax.fit_network(fdjax.ScheduledLoop(LOOP, net, BOUNDS), y, t, steps=5)


# ------------------------------------------------------------------------ stability_margins
def test_an_open_loop_that_vanishes_has_no_gain_margin_to_lose():
    """L ≡ 0 (a law that closes no loop) had a NaN gain margin: the phase of 0/0 counted as a
    crossing.  Now GM = ∞, as python-control gives; zeros inside a loop are no crossing
    either, and the crossing the loop does have is still found."""
    f = np.geomspace(1.0, 1000.0, 200)
    m = fdjax.stability_margins(f, np.zeros(200))
    assert float(m.gain_margin) == np.inf and float(m.phase_margin_deg) == np.inf
    assert float(m.modulus_margin) == 1.0
    L = 0.5 * np.exp(1j * np.linspace(0.0, -4.0, 200))   # crosses −0.5 once
    L[50:60] = 0.0
    np.testing.assert_allclose(float(fdjax.stability_margins(f, L).gain_margin), 2.0,
                               rtol=1e-12)


@pytest.mark.parametrize("freq, exc, message", [
    ([[1.0, 2.0], [3.0, 4.0]], ValueError,
     r"must be a 1-D grid of at least one frequency, got shape \(2, 2\)"),
    ([], ValueError, r"must be a 1-D grid of at least one frequency, got shape \(0,\)"),
    ([1.0, 2.0, 2.0, 3.0], ValueError, r"must be strictly increasing, got \[1\., 2\., 2\., 3\.\]"),
    ([4.0, 3.0, 2.0, 1.0], ValueError, r"must be strictly increasing, got \[4\., 3\., 2\., 1\.\]"),
    ([0.0, 1.0, 2.0, 3.0], ValueError, r"must be finite and positive, got 0 at index 0"),
    ([-1.0, 1.0, 2.0, 3.0], ValueError, r"must be finite and positive, got -1 at index 0"),
    ([1.0, 2.0, math.nan, 4.0], ValueError, r"must be finite and positive, got nan at index 2"),
    ([1.0, 2.0, math.inf, 4.0], ValueError, r"must be finite and positive, got inf at index 2"),
    ([1j, 2.0, 3.0, 4.0], ValueError, r"must be real, got dtype complex128"),
    ("grid", TypeError, r"must be a number or an array of numbers, got 'grid'"),
], ids=["2-D", "empty", "repeated", "decreasing", "zero", "negative", "nan", "inf",
        "complex", "string"])
def test_stability_margins_refuses_a_bad_frequency_grid(freq, exc, message):
    """The grid of stability_margins must be a 1-D, real, finite, positive, strictly increasing
    array of numbers; each failure names the argument and the offending value."""
    L = np.full(max(np.size(freq), 1), -0.5 + 0.1j)
    with pytest.raises(exc, match=r"`stability_margins\(freq_hz=\.\.\.\)` " + message):
        fdjax.stability_margins(freq, L)


# ------------------------------------------------------------------------ track_drive_modes
def _crossing_modes():
    """Two modes at three positions with orthogonal shapes (θ1-like and x2-like residues), in
    ascending frequency at each position: 100/110 Hz, 104/106 Hz, then 103/107 Hz with the
    shape that was the lower mode's still the lower one.  Extrapolated linearly, the lower
    mode is predicted at 108 Hz and the upper at 102 Hz: frequency says the modes crossed,
    the shapes say they did not."""
    f = np.array([[100.0, 110.0], [104.0, 106.0], [103.0, 107.0]])
    a, b = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    shapes = np.broadcast_to(np.stack([a, b]), (3, 2, 3)).astype(complex)
    tag = np.array([[1.0, 2.0]] * 3)  # which shape each entry has, carried by the tracker
    return fdjax.DriveModes(frequency_hz=jnp.asarray(f), damping_ratio=jnp.asarray(tag),
                            phase_deg=jnp.zeros((3, 2)), amplitude=jnp.ones((3, 2)),
                            prominence=jnp.ones((3, 2)), poles=jnp.asarray(2j * np.pi * f),
                            shapes=jnp.asarray(shapes))


def test_track_drive_modes_weighs_the_shapes_by_mac_tol():
    """The tracker's cost is Σ ((f − f̂)/(freq_tol f̂))² + ((1 − MAC)/mac_tol)² (docstring of
    fdjax.track_modes), f̂ the linear extrapolation.  At the third position keeping the
    shapes costs C_keep in frequency alone; crossing costs C_cross in frequency plus
    2/mac_tol² (MAC = 0 twice): crossing wins above mac_tol* = √(2/(C_keep − C_cross)),
    computed here with NumPy; 0.9 and 1.1 mac_tol* give the two answers."""
    modes = _crossing_modes()
    f_hat = np.array([2 * 104.0 - 100.0, 2 * 106.0 - 110.0])  # 108, 102
    cost = lambda f: np.sum(((f - f_hat) / (0.05 * f_hat)) ** 2)  # noqa: E731
    c_keep, c_cross = cost(np.array([103.0, 107.0])), cost(np.array([107.0, 103.0]))
    tol = math.sqrt(2.0 / (c_keep - c_cross))  # 1.07
    keep = fdjax.track_drive_modes(modes, mac_tol=0.9 * tol)
    cross = fdjax.track_drive_modes(modes, mac_tol=1.1 * tol)
    np.testing.assert_array_equal(np.asarray(keep.frequency_hz[2]), [103.0, 107.0])
    np.testing.assert_array_equal(np.asarray(keep.damping_ratio[2]), [1.0, 2.0])
    np.testing.assert_array_equal(np.asarray(cross.frequency_hz[2]), [107.0, 103.0])
    np.testing.assert_array_equal(np.asarray(cross.damping_ratio[2]), [2.0, 1.0])
    np.testing.assert_array_equal(np.asarray(cross.shapes[2, :, :2]).real, [[0, 1], [1, 0]])
    for m in (keep, cross):  # the first two positions agree in both criteria
        np.testing.assert_array_equal(np.asarray(m.frequency_hz[:2]), [[100, 110], [104, 106]])


@pytest.mark.parametrize("value, exc, message", [
    (0.0, ValueError, r"must be finite and positive, got 0"),
    (-0.2, ValueError, r"must be finite and positive, got -0\.2"),
    (math.nan, ValueError, r"must be finite and positive, got nan"),
    (math.inf, ValueError, r"must be finite and positive, got inf"),
    ([0.1, 0.2], ValueError, r"must be a real scalar, got float64 of shape \(2,\)"),
    (0.2j, ValueError, r"must be a real scalar, got complex128 of shape \(\)"),
    ("0.2", TypeError, r"must be a number or an array of numbers, got '0\.2'"),
], ids=["zero", "negative", "nan", "inf", "array", "complex", "string"])
def test_track_drive_modes_refuses_a_bad_mac_tol(value, exc, message):
    """mac_tol divides 1 − MAC in the cost: a finite positive real scalar, or refused with
    the argument's name and value."""
    with pytest.raises(exc, match=r"`track_drive_modes\(mac_tol=\.\.\.\)` " + message):
        fdjax.track_drive_modes(_crossing_modes(), mac_tol=value)


# ------------------------------------------------------------------ simulation and objective
@pytest.fixture(scope="module")
def drive():
    return fdjax.reference_drive()


@pytest.fixture(scope="module")
def loops(drive):
    """The reference controller (unstable at 0.7 m) and its k_v halved (stable at 0.1 m)."""
    ref = fdjax.reference_controller(drive)
    return {"soft": eqx.tree_at(lambda c: c.log_kv, ref, ref.log_kv + math.log(0.5)),
            "reference": ref}


TWIN = fdjax.TwinOptions(kept_modes=4)


@pytest.fixture(scope="module")
def run(drive, loops):
    """The stable loop at 0.1 m on the tuning motion (the run the objective below makes)."""
    return fdjax.simulate(loops["soft"], drive, fdjax.tuning_motion(), position_m=0.1,
                          twin=TWIN)


def test_rms_error_is_the_root_mean_square_of_each_error(run):
    """rms_error() is √(mean e2²) of error_scale = r − x2 and rms_error("tool") that of
    error_tool = r − x3 (NumPy, from the run's reference and outputs); over a batch of runs
    one value per run; any other name is refused."""
    r = np.asarray(run.reference)[:, 0]
    e2, e3 = r - np.asarray(run.x2), r - np.asarray(run.x3)
    np.testing.assert_array_equal(np.asarray(run.error_scale), e2)  # the same subtraction
    np.testing.assert_array_equal(np.asarray(run.error_tool), e3)
    rms2, rms3 = math.sqrt(np.mean(e2 ** 2)), math.sqrt(np.mean(e3 ** 2))
    # summation order of the mean: measured ≤ 3.8e-16 relative
    np.testing.assert_allclose(float(run.rms_error()), rms2, rtol=1e-14)
    np.testing.assert_allclose(float(run.rms_error("scale")), rms2, rtol=1e-14)
    np.testing.assert_allclose(float(run.rms_error("tool")), rms3, rtol=1e-14)
    assert abs(rms3 - rms2) > 1e-3 * rms2  # the two outputs differ: the branch is seen
    doubled = eqx.tree_at(lambda s: (s.error_scale, s.error_tool), run,
                          (2 * run.error_scale, 3 * run.error_tool))
    batch = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), run, doubled)
    np.testing.assert_allclose(np.asarray(batch.rms_error()), [rms2, 2 * rms2], rtol=1e-14)
    np.testing.assert_allclose(np.asarray(batch.rms_error("tool")), [rms3, 3 * rms3],
                               rtol=1e-14)
    for which in ("x3", "Scale", None, 2, ["scale"]):
        with pytest.raises(ValueError, match=r"`Simulation\.rms_error\(which=\.\.\.\)` must be "
                                             rf"'scale' or 'tool', got {re.escape(repr(which))}"):
            run.rms_error(which)


def _softplus(x):
    return np.logaddexp(0.0, x)


def test_objective_total_is_the_documented_sum_of_its_terms(drive, loops, run):
    """J = tracking + w_m P + w_s softplus((g − g_max)/g_w)² + w_c softplus((i − i_max)/
    (0.05 i_max))², g_w = max(|g_max|, 1) (fdjax/_tune/_objective.py), rebuilt with NumPy from
    the ObjectiveTerms fields, with weights that differ from each other and a current limit
    (13 A) and a growth-rate bound (g_max = −40 1/s) that make every term count: for the
    stable loop at 0.1 m the tracking term is e_rms/e_ref and i the peak current; for the
    reference loop at 0.7 m (unstable) the tracking term is error_bound_m/e_ref and i the
    peak current capped at 2 i_max.  The stable run's terms are those of simulate's run, and
    both growth rates are check_stability's (the eigenvalues)."""
    obj = fdjax.Objective(fdjax.tuning_motion(), np.geomspace(5.0, 3900.0, 64), twin=TWIN,
                          error_scale_m=1e-4, margin_weight=3.0, stability_weight=7.0,
                          current_weight=0.5, current_limit_a=13.0, max_growth_rate=-40.0)
    J = eqx.filter_jit(lambda c, y: obj(c, drive, y))
    stable = J(loops["soft"], jnp.asarray(0.1))
    unstable = J(loops["reference"], jnp.asarray(0.7))
    assert bool(stable.stable) and not bool(unstable.stable)
    g_max, i_max, g_w = -40.0, 13.0, 40.0
    for terms in (stable, unstable):
        t = {k: float(getattr(terms, k)) for k in ("total", "rms_error_m", "margin_penalty",
                                                   "growth_rate", "peak_current_a")}
        ok = bool(terms.stable)
        tracking = (t["rms_error_m"] if ok else 0.01) / 1e-4
        i_used = t["peak_current_a"] if ok else min(t["peak_current_a"], 2 * i_max)
        parts = np.array([tracking, 3.0 * t["margin_penalty"],
                          7.0 * _softplus((t["growth_rate"] - g_max) / g_w) ** 2,
                          0.5 * _softplus((i_used - i_max) / (0.05 * i_max)) ** 2])
        # every term is far above the tolerance below: a wrong weight or formula in any shows
        assert np.all(parts > 1e-4 * parts.sum()), parts
        # the same sum in NumPy and XLA: measured 0
        np.testing.assert_allclose(t["total"], parts.sum(), rtol=1e-14)
    assert float(unstable.peak_current_a) > 2 * i_max  # the cap is what the sum above used
    assert float(unstable.growth_rate) > 0 > float(stable.growth_rate)
    # the stable run is simulate's, in another compiled program: measured ≤ 2.4e-13 (RMS),
    # 9.5e-13 (peak current), 3.6e-14 (growth rate) relative
    np.testing.assert_allclose(float(stable.rms_error_m), float(run.rms_error()), rtol=2e-12)
    np.testing.assert_allclose(float(stable.peak_current_a),
                               float(np.max(np.abs(np.asarray(run.current)))), rtol=2e-12)
    np.testing.assert_allclose(float(stable.growth_rate), float(run.growth_rate), rtol=2e-12)
    for terms, c, y in ((stable, loops["soft"], 0.1), (unstable, loops["reference"], 0.7)):
        st = fdjax.check_stability(c, drive, position_m=y, twin=TWIN)
        assert bool(st.stable) == bool(terms.stable)
        # eigenvalues against the run's spectral radius: measured ≤ 9.3e-12 relative
        np.testing.assert_allclose(float(st.growth_rate), float(terms.growth_rate), rtol=3e-11)
    # without current_limit_a the limit is the servo's rating: the same J, bit for bit
    rated = dataclasses.replace(obj, current_limit_a=None, servo=fdjax.Servo(current_limit=13.0))
    assert float(eqx.filter_jit(lambda c, y: rated(c, drive, y).total)(
        loops["soft"], jnp.asarray(0.1))) == float(stable.total)
    with pytest.raises(ValueError, match=r"`Servo\(current_limit=\.\.\.\)` must be finite and "
                                         r"positive \(A\), got -5\.0"):
        fdjax.Servo(current_limit=-5.0)
    with pytest.raises(ValueError, match=r"`Servo\(current_limit=\.\.\.\)` must be finite"):
        fdjax.Servo(current_limit="40")
    assert type(fdjax.Servo(current_limit=np.float32(30.0)).current_limit) is float
    with pytest.raises(TypeError, match=r"`Objective\(servo=\.\.\.\)`"):
        dataclasses.replace(obj, servo="8 kHz")
    with pytest.raises(ValueError, match=r"`Objective\(current_limit_a=\.\.\.\)` must be finite "
                                         r"and positive \(A\), or None"):
        dataclasses.replace(obj, current_limit_a=0.0)


def test_short_grids_objects_and_plants_are_named():
    """A grid too short for the margins names the grid (it used to blame L); the trackers and
    the analysis entry points refuse an object that is not what they take with a TypeError
    naming it."""
    with pytest.raises(ValueError, match=r"`stability_margins\(freq_hz=\.\.\.\)` must have at "
                                         r"least 3 points, got 2"):
        fdjax.stability_margins([1.0, 2.0], np.ones(2, complex))
    with pytest.raises(TypeError, match=r"`track_drive_modes\(modes=\.\.\.\)` must be an "
                                        r"fdjax\.DriveModes .*, got int"):
        fdjax.track_drive_modes(1)
    with pytest.raises(TypeError, match=r"`track_modes\(fits=\.\.\.\)` must be an "
                                        r"fdjax\.ModalFit .*, got int"):
        fdjax.track_modes(1)
    with pytest.raises(TypeError, match=r"`check_stability\(plant=\.\.\.\)` must be a "
                                        r"BallScrewDrive \(with position_m\), a StateSpace, or "
                                        r"an FRF array .*, got str"):
        fdjax.check_stability(LOOP, "drive")
    with pytest.raises(ValueError, match=r"`MCMBounds\.for_servo\(freq_min_hz=\.\.\.\)` must "
                                         r"be a positive number below the filters' highest "
                                         r"frequency 3600 Hz, got 4000\.0"):
        fdjax.MCMBounds.for_servo(SERVO, freq_min_hz=4000.0)
