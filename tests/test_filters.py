"""Peak filter (Eq. 3), notch filter (Eq. 4), MCM, their realisations and Tustin versions.

Oracles: the closed forms at the filter frequencies, scipy.signal.freqs / bilinear / sosfilt and
python-control's prewarped bilinear sampling, applied to polynomials written here from the
equations (not from the implementation). Tolerances are rounding-error bounds: a sum or a
polynomial evaluated in floating point is off by at most (number of operations) × ε × (sum of the
magnitudes of its terms), so each bound below is c·ε × a condition number computed from the data.
"""

import control
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal as sig
from jit_errors import CHECK_FAILED

import fdjax
from fdjax._filters import (
    MCM,
    DiscreteFilter,
    NotchFilter,
    PeakFilter,
)
from fdjax._lti import LTI

EPS = np.finfo(np.float64).eps
TWO_PI = 2 * np.pi

# Table 1 of the paper: mode 3 (130 Hz) is the peak filter's target, mode 5 (1529 Hz) the notch's.
F_PEAK, F_NOTCH = 130.0, 1529.0
PEAK2 = dict(
    K=np.array([0.6, -0.3]),
    omega=TWO_PI * np.array([F_PEAK, 49.0]),
    xi=np.array([0.09, 0.12]),
    phi=np.array([1.2, -0.7]),
)
NOTCH2 = dict(
    omega=TWO_PI * np.array([F_NOTCH, 1030.0]),
    zeta_n=np.array([0.01, 0.003]),
    zeta_d=np.array([0.3, 0.1]),
)
FREQ = np.union1d(np.geomspace(1.0, 5000.0, 400), [49.0, F_PEAK, 1030.0, F_NOTCH])

# Jitted entry points keep the file fast (eager mode compiles every small op on first use);
# dt travels as an array so that a new servo period does not recompile.
transfer = eqx.filter_jit(lambda filt, x: filt.transfer(x))
frf = eqx.filter_jit(lambda filt, freq_hz: filt.frf(freq_hz))
_discretize = eqx.filter_jit(lambda filt, dt, method: filt.discretize(dt, method))
_both_frf = eqx.filter_jit(
    lambda filt, dt, f, method: (filt.frf(f), filt.discretize(dt, method).frf(f))
)


state_space = eqx.filter_jit(lambda filt: filt.state_space())


def discretize(filt, dt, method="fitted"):
    return _discretize(filt, jnp.asarray(dt), method)


def sos_rows(disc):
    """All second-order sections of a DiscreteFilter, parallel rows first, (n, 6)."""
    series = np.asarray(disc.series_sos).reshape(-1, 6)
    return np.concatenate([np.asarray(disc.parallel_sos), series])


def both_frf(filt, dt, freq_hz, method="fitted"):
    """Continuous and discrete frequency responses on one grid."""
    return _both_frf(filt, jnp.asarray(dt), freq_hz, method)


# ---------------------------------------------- oracles written from the equations
def peak_sections(K, omega, xi, phi):
    """Eq. (3) term i: K s (s cos φ + ω sin φ) / (s² + 2ξωs + ω²) as polynomial coefficients."""
    K, omega, xi, phi = np.broadcast_arrays(*map(np.atleast_1d, (K, omega, xi, phi)))
    num = [k * np.array([np.cos(p), w * np.sin(p), 0.0]) for k, w, p in zip(K, omega, phi)]
    den = [np.array([1.0, 2 * x * w, w**2]) for w, x in zip(omega, xi)]
    return num, den


def notch_sections(omega, zeta_n, zeta_d):
    omega, zeta_n, zeta_d = np.broadcast_arrays(*map(np.atleast_1d, (omega, zeta_n, zeta_d)))
    num = [np.array([1.0, 2 * z * w, w**2]) for w, z in zip(omega, zeta_n)]
    den = [np.array([1.0, 2 * z * w, w**2]) for w, z in zip(omega, zeta_d)]
    return num, den


def peak_polynomials(**p):
    """G_pf = 1 + Σ n_i/d_i = (Π d + Σ_i n_i Π_{k≠i} d_k) / Π d."""
    nums, dens = peak_sections(**p)
    den = np.array([1.0])
    for d in dens:
        den = np.polymul(den, d)
    num = den.copy()
    for i, n in enumerate(nums):
        term = n
        for k, d in enumerate(dens):
            if k != i:
                term = np.polymul(term, d)
        num = np.polyadd(num, term)
    return num, den


def notch_polynomials(**p):
    nums, dens = notch_sections(**p)
    num, den = np.array([1.0]), np.array([1.0])
    for n, d in zip(nums, dens):
        num, den = np.polymul(num, n), np.polymul(den, d)
    return num, den


def horner_cond(p, x):
    """Σ|p_k||x|^k / |p(x)|: relative rounding error of Horner's rule is ≤ 2·deg·ε × this."""
    return np.polyval(np.abs(p), np.abs(x)) / np.abs(np.polyval(p, x))


def rational_bound(num, den, x):
    """Relative error bound for num(x)/den(x) evaluated by Horner (complex ops count double)."""
    deg = max(len(num), len(den)) - 1
    return 4 * deg * EPS * (horner_cond(num, x) + horner_cond(den, x)) + 2 * EPS


def sections_bound(nums, dens, x, parallel):
    """The same bound for our factored evaluation: sections summed (parallel) or multiplied."""
    terms = [np.polyval(n, x) / np.polyval(d, x) for n, d in zip(nums, dens)]
    errs = [rational_bound(n, d, x) for n, d in zip(nums, dens)]
    if not parallel:
        return sum(errs) + len(nums) * 2 * EPS
    total = 1 + sum(terms)
    mags = 1 + sum(np.abs(t) for t in terms)
    return (sum(e * np.abs(t) for e, t in zip(errs, terms)) + len(terms) * EPS * mags) / np.abs(
        total
    )


def warped(w0, dt, w):
    """Tustin prewarped at w0 maps e^{iωdt} to s = i c tan(ωdt/2), c = w0/tan(w0 dt/2)."""
    return w0 / np.tan(w0 * dt / 2) * np.tan(w * dt / 2)


# ----------------------------------------------------------------------------- closed forms
@pytest.mark.parametrize("zeta_n, zeta_d", [(0.01, 0.3), (0.003, 0.03), (0.2, 0.05), (0.5, 0.5)])
def test_notch_gain_at_centre_is_depth(zeta_n, zeta_d):
    # At s = iω: num = −ω² + 2iζ_nω² + ω² = 2iζ_nω², den = 2iζ_dω², so G = ζ_n/ζ_d, phase 0.
    nf = NotchFilter(TWO_PI * F_NOTCH, zeta_n, zeta_d)
    w = float(nf.omega[0])
    g = complex(nf.transfer(1j * w))
    # With s = iω from the stored ω, s² + ω² cancels exactly (fl(ω·ω) both times), so only the
    # 2ζω·ω products, the division and the log/exp storage of ζ (≤ 2 ε each) remain.
    assert abs(g.real - zeta_n / zeta_d) <= 16 * EPS * zeta_n / zeta_d
    assert g.imag == 0.0
    # Through frf (Hz): s = i·2π·(ω/2π) perturbs ω by ~2ε relatively; the cancellation
    # s² + ω² then leaves ~4ε·ω² against 2ζω², a relative error ≤ 4ε/(2ζ) in num and den.
    g_hz = complex(nf.frf(w / TWO_PI)[0])
    tol = 16 * EPS * (1 + 1 / zeta_n + 1 / zeta_d) * zeta_n / zeta_d
    assert abs(g_hz - zeta_n / zeta_d) <= tol


@pytest.mark.parametrize(
    "K, phi",
    [(0.6, 1.2), (-0.3, -0.7), (1.0, 0.0), (0.25, np.pi / 2), (2.0, np.deg2rad(-260.0))],
)
def test_peak_gain_and_phase_at_centre(K, phi):
    # At s = iω: num = K iω (iω cos φ + ω sin φ) = −K ω² e^{−iφ}, den = 2iξω², so
    # G_pf(iω) = 1 + (K / 2ξ) e^{i(π/2 − φ)}.
    xi = 0.09
    pf = PeakFilter(K, TWO_PI * F_PEAK, xi, phi)
    w = float(pf.omega[0])
    expected = 1 + K / (2 * xi) * np.exp(1j * (np.pi / 2 - phi))
    g = complex(pf.transfer(1j * w))
    # Each of num, den, the ratio and the closed form carries a few ε relative to |K/2ξ|.
    atol = 16 * EPS * (1 + abs(K) / (2 * xi))
    assert abs(g - expected) <= atol
    assert abs(abs(g) - abs(expected)) <= atol
    assert abs(np.angle(g) - np.angle(expected)) <= atol / abs(expected)


def test_peak_filter_is_unity_far_from_centre():
    # Each term is K s sin φ / ω + O(s²/ω²) as s → 0 and K cos φ + O(ω/s) as s → ∞
    # (the O(ω/s) coefficient is K ω (sin φ − 2ξ cos φ), at most |K| ω (1 + 2ξ)).
    pf = PeakFilter(**PEAK2)
    K, w, xi = PEAK2["K"], PEAK2["omega"], PEAK2["xi"]
    s_small, s_big = 1e-3, 1e9
    small, big = np.asarray(transfer(pf, np.array([1j * s_small, 1j * s_big])))
    assert abs(small - 1) <= 2 * np.sum(np.abs(K) * s_small / w)
    assert abs(big - (1 + np.sum(K * np.cos(PEAK2["phi"])))) <= 2 * np.sum(
        np.abs(K) * w * (1 + 2 * xi) / s_big
    )


# ------------------------------------------------------------------------ oracle agreement
@pytest.mark.parametrize("which", ["peak", "notch", "mcm"])
def test_frf_matches_scipy_freqs(which):
    pn, pd = peak_polynomials(**PEAK2)
    nn, nd = notch_polynomials(**NOTCH2)
    s = 1j * TWO_PI * FREQ
    ps, ns = peak_sections(**PEAK2), notch_sections(**NOTCH2)
    ours_bound_p = sections_bound(*ps, s, parallel=True)
    ours_bound_n = sections_bound(*ns, s, parallel=False)
    if which == "peak":
        filt, num, den, ours_bound = PeakFilter(**PEAK2), pn, pd, ours_bound_p
    elif which == "notch":
        filt, num, den, ours_bound = NotchFilter(**NOTCH2), nn, nd, ours_bound_n
    else:
        filt = MCM(PeakFilter(**PEAK2), NotchFilter(**NOTCH2))
        num, den = np.polymul(pn, nn), np.polymul(pd, nd)
        ours_bound = ours_bound_p + ours_bound_n
    _, h = sig.freqs(num, den, worN=TWO_PI * FREQ)
    g = np.asarray(frf(filt, FREQ))
    assert g.shape == FREQ.shape and g.dtype == np.complex128
    tol = rational_bound(num, den, s) + ours_bound
    assert np.all(np.abs(g - h) <= tol * np.abs(h))
    assert tol.max() < 1e-11  # the bound itself is tight: the comparison is not vacuous


STATE_SPACE_CASES = {
    "mcm": (dict(peak=PEAK2, notch=NOTCH2), 8),
    "peak": (dict(peak=PEAK2), 4),
    "notch": (dict(notch=NOTCH2), 4),
}


def build(peak=None, notch=None):
    return MCM(
        None if peak is None else PeakFilter(**peak),
        None if notch is None else NotchFilter(**notch),
    )


@pytest.mark.parametrize("case", list(STATE_SPACE_CASES))
def test_state_space_realisation(case):
    parts, n = STATE_SPACE_CASES[case]
    filt = build(**parts)
    if case != "mcm":  # the standalone filters realise the same way as their MCM wrappers
        filt = filt.peak if case == "peak" else filt.notch
    rng = np.random.default_rng(0)
    s = np.concatenate(
        [1j * TWO_PI * FREQ[::7], -rng.uniform(10, 3000, 20) + 1j * rng.uniform(0, 2e4, 20)]
    )
    ss = state_space(filt)
    g = np.asarray(transfer(filt, s))
    A, B, C, D = (np.asarray(x) for x in (ss.A, ss.B, ss.C, ss.D))
    assert isinstance(ss, LTI) and ss.dt is None
    assert A.shape == (n, n) and B.shape == (n, 1) and C.shape == (1, n) and D.shape == (1, 1)
    assert all(x.dtype == np.float64 for x in (A, B, C, D))

    sys = control.ss(A, B, C, D)
    tols = []
    for sk, gk in zip(s, g):
        M = sk * np.eye(n) - A
        x = np.linalg.solve(M, B)
        ref = (C @ x)[0, 0] + D[0, 0]
        # Backward-stable solve: relative error in x ≲ n ε cond(M); then the dot product C·x.
        tol = (8 * n * EPS * np.linalg.cond(M) * np.abs(C) @ np.abs(x))[0, 0] + 4 * EPS * abs(ref)
        assert abs(gk - ref) <= tol
        assert abs(gk - complex(sys(sk))) <= tol  # python-control's own evaluation
        tols.append(tol / abs(ref))
    assert max(tols) < 1e-9
    if case == "mcm":
        np.testing.assert_allclose(transfer(ss, s)[..., 0, 0], g, rtol=max(tols))  # its own solve

    # Poles are the roots of the section denominators, and the realisation is minimal:
    # Popov–Belevitch–Hautus test, [A − λI, B] and [A − λI; C] of full rank at every eigenvalue.
    poles = np.sort_complex(np.linalg.eigvals(A))
    dens = []
    if "peak" in parts:
        dens += peak_sections(**parts["peak"])[1]
    if "notch" in parts:
        dens += notch_sections(**parts["notch"])[1]
    roots = np.sort_complex(np.concatenate([np.roots(d) for d in dens]))
    # Simple roots of lightly damped quadratics: relative sensitivity ~ ε/ζ for both methods.
    np.testing.assert_allclose(poles, roots, rtol=64 * EPS / 0.003)
    # A non-minimal realisation would have σ_min at rounding level (~ε‖A‖); a minimal one far
    # above it. 1e-6 separates the two by many orders of magnitude either way.
    scale = np.linalg.norm(A, 2)
    for lam in poles:
        ctrb = np.hstack([A - lam * np.eye(n), B * scale])
        obsv = np.vstack([A - lam * np.eye(n), C])
        assert np.linalg.svd(ctrb, compute_uv=False)[-1] > 1e-6 * scale
        assert np.linalg.svd(obsv, compute_uv=False)[-1] > 1e-6 * np.linalg.norm(obsv, 2)


def test_identity_mcm():
    ident = MCM()
    assert state_space(ident).A.shape == (0, 0)
    np.testing.assert_array_equal(ident.frf(FREQ), np.ones_like(FREQ))
    np.testing.assert_array_equal(discretize(ident, 1e-4).apply(np.arange(5.0)), np.arange(5.0))


# ------------------------------------------------------------------------------ discretisation
def single_sections(dt):
    """(filter, num, den, ω0) of one-section filters at the paper's frequencies."""
    out = []
    for f0 in (F_PEAK, F_NOTCH):
        for K, phi in ((0.6, 1.2), (-0.4, -2.0)):
            p = dict(K=K, omega=TWO_PI * f0, xi=0.09, phi=phi)
            (n,), (d,) = peak_sections(**p)
            out.append((PeakFilter(**p), n, d, TWO_PI * f0))
        for zn, zd in ((0.01, 0.3), (0.05, 0.5)):
            p = dict(omega=TWO_PI * f0, zeta_n=zn, zeta_d=zd)
            (n,), (d,) = notch_sections(**p)
            out.append((NotchFilter(**p), n, d, TWO_PI * f0))
    return out


@pytest.mark.parametrize("dt", [1 / 8000, 1 / 16000])
def test_sos_matches_scipy_and_control_bilinear(dt):
    for filt, n, d, w0 in single_sections(dt):
        disc = discretize(filt, dt, "tustin")
        sos = sos_rows(disc)[0]
        assert disc.n_sections == 1
        # scipy: s = 2 fs (z−1)/(z+1); prewarping means 2 fs = w0 / tan(w0 dt/2).
        c = w0 / np.tan(w0 * dt / 2)
        b, a = sig.bilinear(n, d, fs=c / 2)
        ref_scipy = np.concatenate([np.pad(b, (3 - len(b), 0)), a]) / a[0]
        # python-control: its own prewarped Tustin (s = w0/tan(w0 Ts/2) (z−1)/(z+1)).
        sysd = control.sample_system(control.tf(n, d), dt, "bilinear", prewarp_frequency=w0)
        nd_, dd_ = np.ravel(sysd.num[0][0]), np.ravel(sysd.den[0][0])
        ref_control = np.concatenate([np.pad(nd_, (3 - len(nd_), 0)), dd_]) / dd_[0]
        # Each coefficient is a sum of three terms (c², c, 1 scaled) over a0: a few ε of
        # (Σ|terms|)/a0; that sum is at most |n|·(c², c, 1) / a0.
        scale = (np.abs(n) @ [c * c, c, 1] + np.abs(d) @ [c * c, c, 1]) / abs(a[0])
        np.testing.assert_allclose(sos, ref_scipy, rtol=0, atol=16 * EPS * scale)
        np.testing.assert_allclose(sos, ref_control, rtol=0, atol=64 * EPS * scale)


def discrete_bound(disc_sos, z):
    """Relative evaluation bound of one discrete section at z (Horner in z⁻¹)."""
    zi = 1 / z
    b, a = disc_sos[:3][::-1], disc_sos[3:][::-1]
    return rational_bound(b, a, zi)


@pytest.mark.parametrize("dt", [1 / 8000, 1 / 16000])
def test_discrete_equals_continuous_at_the_warped_frequency(dt):
    # Exact identity of the prewarped bilinear map, section by section:
    # G_d(e^{iωdt}) = G(i c tan(ωdt/2)), c = ω0/tan(ω0 dt/2).
    f = np.linspace(1.0, 0.499 / dt, 3000)
    for filt, n, d, w0 in single_sections(dt):
        disc = discretize(filt, dt, "tustin")
        gd = np.asarray(frf(disc, f))
        s = 1j * warped(w0, dt, TWO_PI * f)
        gc = np.asarray(transfer(filt, s))
        sos = sos_rows(disc)[0]
        # Both sides are Horner evaluations, bounded by ε × their condition numbers (the
        # discrete one, Σ|coef| / |den(z)| ~ (c/ω0)²/ζ, also covers the ε-rounding of the sos
        # coefficients themselves). Rounding of c = ω0/tan(ω0dt/2) and of e^{iωdt} moves the
        # evaluation point by a few ε relatively, costing the same condition numbers again.
        if isinstance(filt, PeakFilter):
            gc_term, gd_term = gc - 1, gd - 1
        else:
            gc_term, gd_term = gc, gd
        bound = discrete_bound(sos, np.exp(1j * TWO_PI * f * dt)) + rational_bound(n, d, s)
        tol = 4 * bound
        assert np.all(np.abs(gd_term - gc_term) <= tol * np.abs(gc_term))


@pytest.mark.parametrize("dt", [1 / 8000, 1 / 16000])
def test_prewarp_frequency_is_exact(dt):
    # At ω0 the warp is the identity: the notch keeps its depth ζn/ζd, the peak its lobe
    # 1 + (K/2ξ) e^{i(π/2 − φ)}, up to the evaluation bound of the section at z0 = e^{iω0dt}
    # (see the identity test above).
    for zn, zd in ((0.01, 0.3), (0.003, 0.03)):
        for f0 in (F_PEAK, F_NOTCH):
            nf = NotchFilter(TWO_PI * f0, zn, zd)
            disc = nf.discretize(dt, "tustin")
            z0 = np.exp(1j * float(nf.omega[0]) * dt)
            g = complex(disc.transfer(z0))
            bound = discrete_bound(sos_rows(disc)[0], z0)
            assert abs(g - zn / zd) <= 4 * bound * zn / zd
    K, xi, phi = 0.6, 0.09, 1.2
    pf = PeakFilter(K, TWO_PI * F_PEAK, xi, phi)
    disc = pf.discretize(dt, "tustin")
    z0 = np.exp(1j * float(pf.omega[0]) * dt)
    g = complex(disc.transfer(z0))
    lobe = K / (2 * xi) * np.exp(1j * (np.pi / 2 - phi))
    bound = discrete_bound(np.asarray(disc.parallel_sos)[0], z0)
    assert abs(g - (1 + lobe)) <= 4 * bound * abs(lobe) + 2 * EPS


def relative_error_below_quarter_nyquist(filt, dt, method):
    """max |G_d − G| / |G| over 0 < f ≤ fs/8 (a quarter of the Nyquist frequency)."""
    return float(_relative_error(filt, jnp.asarray(dt), method))


@eqx.filter_jit
def _relative_error(filt, dt, method):
    f = jnp.linspace(0.5, 1 / (8 * dt), 4000)
    gc, gd = filt.frf(f), filt.discretize(dt, method).frf(f)
    return jnp.max(jnp.abs(gd - gc) / jnp.abs(gc))


def random_sections(fs, n, seed):
    """Seeded notch and peak sections over the MCM's range: notches up to 0.2·fs (the 1529 Hz
    target at 8 kHz is 0.19·fs) with ζ_n ∈ [0.001, 1], ζ_d ∈ [0.01, 1]; peaks up to fs/8 with
    |K| ≤ 2, ξ ∈ [0.01, 1], any φ, leaving out those whose response dips below 0.1 (a peak
    filter turned notch: there a relative error says nothing)."""
    rng = np.random.default_rng(seed)
    log_u = lambda a, b: float(np.exp(rng.uniform(np.log(a), np.log(b))))
    notches, peaks = [], []
    while len(peaks) < n:
        notches.append(NotchFilter(TWO_PI * log_u(20, 0.2 * fs), log_u(1e-3, 1), log_u(0.01, 1)))
        pf = PeakFilter(
            rng.uniform(-2, 2),
            TWO_PI * log_u(20, fs / 8),
            log_u(0.01, 1),
            rng.uniform(-np.pi, np.pi),
        )
        if float(jnp.min(jnp.abs(frf(pf, np.geomspace(1.0, fs / 2, 2000))))) >= 0.1:
            peaks.append(pf)
    return notches[:n], peaks


@pytest.mark.parametrize("dt", [1 / 8000, 1 / 16000])
def test_discrete_within_one_percent_below_quarter_nyquist(dt):
    # The default ("fitted") discretisation: poles mapped exactly, numerator fitted on
    # [0, fs/8]. The hand-set MCM of the figures (131 Hz peak, broad 1508 Hz notch), the
    # paper's targets, and 30 random notches, peaks and their products.
    hand = MCM(
        PeakFilter(0.5, TWO_PI * 131.0, 0.3, -np.pi / 3), NotchFilter(TWO_PI * 1508.0, 0.05, 0.5)
    )
    notches, peaks = random_sections(1 / dt, 30, seed=7)
    filters = [hand, MCM(PeakFilter(**PEAK2), NotchFilter(**NOTCH2)), *notches, *peaks]
    filters += [MCM(p, n) for p, n in zip(peaks, notches)]
    errors = [relative_error_below_quarter_nyquist(f, dt, "fitted") for f in filters]
    assert max(errors) < 0.01, (max(errors), int(np.argmax(errors)))
    # Tustin (prewarped at each section's frequency) warps a broad high notch by several per
    # cent: the reason "fitted" is the default. At 8 kHz the hand MCM is off by 12 %.
    assert relative_error_below_quarter_nyquist(hand, dt, "tustin") > 0.05


@pytest.mark.parametrize("dt", [1 / 8000, 1 / 16000])
def test_tustin_within_one_percent_for_low_sections(dt):
    # Below fs/8 a section centred at 130 Hz (ω0 dt ≤ 0.1) is warped by
    # |ω'/ω − 1| ≤ (ω0 dt)²/12 ≈ 1e-3, i.e. ≈ 0.1 % of the ξω0 bandwidth per unit of
    # (ω − ω0)/(ξω0): the response moves by far less than 1 %.
    filters = [
        PeakFilter(0.6, TWO_PI * F_PEAK, 0.09, 1.2),
        PeakFilter(-0.4, TWO_PI * F_PEAK, 0.05, -2.0),
        NotchFilter(TWO_PI * F_PEAK, 0.01, 0.3),
        NotchFilter(TWO_PI * F_PEAK, 0.003, 0.03),
        MCM(PeakFilter(**PEAK2), NotchFilter(TWO_PI * F_PEAK * 1.5, 0.02, 0.4)),
    ]
    for filt in filters:
        assert relative_error_below_quarter_nyquist(filt, dt, "tustin") < 0.01


@pytest.mark.parametrize("dt", [1 / 8000, 1 / 16000])
def test_fitted_is_exact_at_dc_and_at_the_filter_frequency_with_matched_poles(dt):
    for f0 in (F_PEAK, F_NOTCH):
        w0 = TWO_PI * f0
        for zn, zd in ((0.01, 0.3), (0.003, 0.03), (0.2, 1.5)):
            disc = discretize(NotchFilter(w0, zn, zd), dt)
            assert np.asarray(disc.series_sos).shape == (1, 2, 6)
            # Depth ζn/ζd at ω0 and static gain 1: the constraints of the fit, solved by a 3×3
            # elimination and evaluated in a few flops (relative rounding ≲ 1e-12 here).
            depth = complex(disc.transfer(np.exp(1j * w0 * dt)))
            assert abs(depth - zn / zd) <= 1e-11 * zn / zd
            assert abs(complex(disc.transfer(1.0)) - 1) <= 1e-12
            # Poles: z = e^{p dt}, p the roots of s² + 2ζ_d ω0 s + ω0².
            a = np.asarray(disc.series_sos)[0, 1, 3:]
            want = np.sort_complex(np.exp(np.roots([1, 2 * zd * w0, w0 * w0]) * dt))
            np.testing.assert_allclose(np.sort_complex(np.roots(a)), want, rtol=1e-12, atol=1e-14)
            assert np.all(np.abs(np.roots(a)) < 1)
        K, xi, phi = 0.6, 0.09, 1.2
        disc = discretize(PeakFilter(K, w0, xi, phi), dt)
        lobe = K / (2 * xi) * np.exp(1j * (np.pi / 2 - phi))
        g = complex(disc.transfer(np.exp(1j * w0 * dt)))
        assert abs(g - (1 + lobe)) <= 1e-12 * abs(1 + lobe)
        assert abs(complex(disc.transfer(1.0)) - 1) <= 1e-12


def test_fitted_gradient_is_finite_at_the_edges():
    # Critical damping (the cos → cosh switch of the matched poles), K = 0 (an exact fit: the
    # Lawson weights stay put), tiny and huge damping, sections close to Nyquist.
    f = jnp.array([50.0, 300.0, 900.0, 2500.0, 3900.0])

    def loss(p):
        m = MCM(PeakFilter(p[0], p[1], p[2], p[3]), NotchFilter(p[4], p[5], p[6]))
        return jnp.sum(jnp.abs(m.discretize(1 / 8000).frf(f)) ** 2)

    grad = jax.jit(jax.grad(loss))
    w, wn = TWO_PI * F_PEAK, TWO_PI * F_NOTCH
    for p in (
        [0.5, w, 0.3, -1.0, wn, 0.05, 1.0],
        [0.5, w, 1.0, -1.0, wn, 0.05, 0.5],
        [0.0, w, 0.3, -1.0, wn, 0.05, 0.5],
        [0.5, w, 1e-4, -1.0, wn, 1e-5, 1e-4],
        [0.5, TWO_PI * 3900, 0.3, -1.0, TWO_PI * 3950, 0.05, 0.5],
        [0.5, w, 5.0, -1.0, wn, 3.0, 8.0],
        [0.5, w, 0.3, -1.0, wn, 0.3, 0.3],
    ):
        assert np.all(np.isfinite(np.asarray(grad(jnp.asarray(p))))), p


def test_prewarping_places_a_high_notch_where_plain_tustin_misses_it():
    # A section at 1529 Hz has ω0 dt = 1.2 at 8 kHz. Plain Tustin (s = 2/dt (z−1)/(z+1)) moves
    # the notch to (2/dt) atan(ω0 dt/2) ≈ 1376 Hz, so at 1529 Hz it is far from the notch depth;
    # prewarped at ω0 the depth is exact there. The price is the warp elsewhere: below fs/8 the
    # prewarped notch is off by up to ~10 % (the identity test above shows that this is exactly
    # the warp ω → c tan(ωdt/2) and nothing else).
    dt = 1 / 8000
    zn, zd = 0.01, 0.3
    nf = NotchFilter(TWO_PI * F_NOTCH, zn, zd)
    f0 = float(nf.omega[0]) / TWO_PI
    (n,), (d,) = notch_sections(TWO_PI * F_NOTCH, zn, zd)
    b, a = sig.bilinear(n, d, fs=1 / dt)
    _, h = sig.freqz(b, a, worN=[f0], fs=1 / dt)
    assert abs(abs(h[0]) - zn / zd) > 10 * zn / zd
    disc = nf.discretize(dt, "tustin")
    z0 = np.exp(1j * TWO_PI * f0 * dt)
    bound = discrete_bound(sos_rows(disc)[0], z0)
    assert abs(complex(disc.frf(f0)[0]) - zn / zd) <= 4 * bound * zn / zd
    # The plain map puts the exact depth at its own warped frequency (same evaluation bound).
    notch_hz = 2 / dt * np.arctan(TWO_PI * F_NOTCH * dt / 2) / TWO_PI
    _, h = sig.freqz(b, a, worN=[notch_hz], fs=1 / dt)
    z1 = np.exp(1j * TWO_PI * notch_hz * dt)
    assert abs(h[0] - zn / zd) <= 4 * discrete_bound(np.concatenate([b, a]), z1) * zn / zd


# ------------------------------------------------------------------------------- time domain
def oracle_sosfilt(disc, u):
    """u + Σ_p sosfilt(P_p, u), then per series stage Σ_k sosfilt(S_qk, ·) — the structure."""
    par = np.array(disc.parallel_sos)
    y = u + sum((sig.sosfilt(par[p : p + 1], u) for p in range(par.shape[0])), np.zeros_like(u))
    for stage in np.array(disc.series_sos):
        y = sum(sig.sosfilt(row[None], y) for row in stage)
    return y


@pytest.mark.parametrize("dt", [1 / 8000, 1 / 16000])
def test_apply_matches_sosfilt(dt):
    filt = MCM(PeakFilter(**PEAK2), NotchFilter(**NOTCH2))
    disc = discretize(filt, dt)
    n = 3000
    impulse = np.zeros(n)
    impulse[0] = 1.0
    step = np.ones(n)
    h = oracle_sosfilt(disc, impulse)
    # Rounding errors injected at every step are filtered by the (stable) sections; the output
    # error is ≤ c ε Σ|h| max|u| with ‖h‖₁ the impulse response's ℓ¹ norm (≥ each section's).
    l1 = np.sum(np.abs(h)) + sum(
        np.sum(np.abs(sig.sosfilt(np.array(s)[None], impulse))) for s in sos_rows(disc)
    )
    apply = jax.jit(lambda d, u: d.apply(u))
    for u in (impulse, step):
        y = np.asarray(apply(disc, u))
        np.testing.assert_allclose(y, oracle_sosfilt(disc, u), rtol=0, atol=32 * EPS * l1 * l1)
    for part in (PeakFilter(**PEAK2), NotchFilter(**NOTCH2)):
        d = discretize(part, dt)
        np.testing.assert_allclose(apply(d, impulse), oracle_sosfilt(d, impulse), atol=1e-12)


def test_step_by_step_equals_apply_and_dc_gain():
    disc = discretize(MCM(PeakFilter(**PEAK2), NotchFilter(**NOTCH2)), 1 / 8000)
    rng = np.random.default_rng(1)
    u = rng.standard_normal(64)
    state = disc.init_state()
    assert state.shape == (disc.n_sections, 2) and not np.any(state)
    step = jax.jit(lambda d, s, x: d.step(s, x))
    ys = []
    for uk in u:
        state, yk = step(disc, state, uk)
        ys.append(float(yk))
    apply = eqx.filter_jit(lambda d, x: d.apply(x))
    impulse = np.zeros(4000)
    impulse[0] = 1.0
    l1 = np.sum(np.abs(np.asarray(apply(disc, impulse))))
    # Same recursion in a Python loop and in lax.scan: at most rounding, filtered (‖h‖₁).
    np.testing.assert_allclose(
        ys, apply(disc, u), rtol=0, atol=32 * EPS * l1 * l1 * np.abs(u).max()
    )
    # Step response settles to G(z = 1) = G(s = 0) = 1 (peak terms vanish at DC, notches are 1).
    # The slowest pole decays like e^{−ξωt}, ξω ≥ 37/s: after 5 s the transient is < 1e-80. What
    # remains is the rounding of each section's DC gain Σb/Σa (Σa ~ (ω0 dt)² is small) and the
    # rounding accumulated by the recursion.
    n = 40000
    y = apply(disc, np.ones(n))
    rows = sos_rows(disc)
    dc = rows[:, :3].sum(1) / rows[:, 3:].sum(1)
    dc_bound = np.sum(
        4
        * EPS
        * (np.abs(rows[:, :3]).sum(1) + np.abs(dc) * np.abs(rows[:, 3:]).sum(1))
        / np.abs(rows[:, 3:].sum(1))
    )
    assert abs(float(y[-1]) - 1) <= dc_bound + 32 * EPS * l1 * l1


# ------------------------------------------------------------------------- transformations
def mcm_from(theta):
    K, w, xi, phi, wn, zn, zd = (theta[i] for i in range(7))
    return MCM(PeakFilter(K, w, xi, phi), NotchFilter(wn, zn, zd))


THETA = np.array([0.6, TWO_PI * F_PEAK, 0.09, 1.2, TWO_PI * F_NOTCH, 0.05, 0.3])
# Length on which |G| varies with each parameter: resonance widths for the frequencies.
THETA_SCALE = np.array([1.0, 0.09 * THETA[1], 0.09, 1.0, 0.05 * THETA[4], 0.05, 0.3])


@jax.jit
def magnitude(theta, f_hz):
    """|G_MCM(i 2π f)| as a function of the seven physical parameters (the ATA's outputs)."""
    s = (TWO_PI * f_hz).astype(jnp.complex128) * 1j
    return jnp.abs(mcm_from(theta).transfer(s))


@jax.jit
def fitted_magnitude(theta, f_hz):
    """|G_MCM(e^{i 2π f T})| of the fitted discretisation at 8 kHz (what the sampled loop and
    the tuners run): matched poles and the Lawson fit of the numerator."""
    return jnp.abs(mcm_from(theta).discretize(1 / 8000).frf(jnp.atleast_1d(f_hz))[0])


def _check_central_differences(fun, f_eval):
    f_eval = jnp.asarray(f_eval)
    grad = np.asarray(jax.jit(jax.grad(fun))(THETA, f_eval))
    f0 = float(fun(THETA, f_eval))
    for k in range(7):
        h = EPS ** (1 / 3) * THETA_SCALE[k]

        def central(step):
            e = np.zeros(7)
            e[k] = step
            return (float(fun(THETA + e, f_eval)) - float(fun(THETA - e, f_eval))) / (2 * step)

        d1, d2 = central(h), central(2 * h)
        # Truncation error ≈ C h² (so D(2h) − D(h) ≈ 3 C h²); rounding ≈ κ ε |f| / h with
        # κ ≈ 1/ζ_min the evaluation condition number near a resonance.
        tol = abs(d2 - d1) / 3 + 64 * EPS * f0 / (0.05 * h)
        assert abs(grad[k] - d1) <= 2 * tol + 1e-12 * abs(grad[k]), (k, grad[k], d1, tol)


@pytest.mark.parametrize("f_eval", [140.0, 1500.0])
def test_grad_matches_central_differences(f_eval):
    _check_central_differences(magnitude, f_eval)


@pytest.mark.parametrize("f_eval", [140.0, 1500.0])
def test_fitted_discretisation_grad_matches_central_differences(f_eval):
    """The derivatives of the discrete filter in all seven parameters, through the matched
    poles and the eight Lawson reweightings of the numerator's fit (a stop-gradient on the
    weights or the poles would give a finite but wrong gradient)."""
    _check_central_differences(fitted_magnitude, f_eval)


def test_grad_on_leaves_is_chain_rule_and_keeps_positivity():
    s = 1j * TWO_PI * 140.0
    pf = PeakFilter(0.6, TWO_PI * F_PEAK, 0.09, 1.2)
    loss = lambda f: jnp.abs(f.transfer(s))
    g_leaf = eqx.filter_jit(eqx.filter_grad(loss))(pf)
    g_phys = jax.jit(jax.grad(lambda p: loss(PeakFilter(**p))))(pf.params())
    # log parameterisation: ∂L/∂log ω = ω ∂L/∂ω.
    # Two autodiff evaluations of the same expression, near resonance (κ ≈ 1/ξ).
    rtol = 64 * EPS / 0.09
    np.testing.assert_allclose(g_leaf.log_omega, pf.omega * g_phys["omega"], rtol=rtol)
    np.testing.assert_allclose(g_leaf.log_xi, pf.xi * g_phys["xi"], rtol=rtol)
    np.testing.assert_allclose(g_leaf.K, g_phys["K"], rtol=rtol)
    # However large the step, ω and ξ stay positive (no clipping involved).
    # A step of 20 in the log (a plain step in ω or ξ of that relative size would cross zero).
    for lr in (20.0, -20.0):
        g_max = max(float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(g_leaf))
        stepped = eqx.apply_updates(pf, jax.tree.map(lambda g: -lr * g / g_max, g_leaf))
        assert np.all(stepped.omega > 0) and np.all(stepped.xi > 0)
        assert np.isfinite(complex(stepped.transfer(s)))


def test_unconstrained_round_trip():
    pf = PeakFilter(**PEAK2)
    again = PeakFilter.from_unconstrained(pf.K, pf.log_omega, pf.log_xi, pf.phi)
    # exp(log x) is off by ≤ (|log x| + 2) ε relatively: log's absolute error ε|log x| becomes a
    # relative one through exp; log(exp(y)) is off by the same amount absolutely.
    for a, b in zip(jax.tree.leaves(pf), jax.tree.leaves(again)):
        np.testing.assert_allclose(a, b, rtol=0, atol=(np.abs(a).max() + 2) * 2 * EPS)
    nf = NotchFilter(**NOTCH2)
    again = NotchFilter.from_unconstrained(nf.log_omega, nf.log_zeta_n, nf.log_zeta_d)
    tol = lambda x: 2 * (np.abs(np.log(x)).max() + 2) * EPS
    np.testing.assert_allclose(again.zeta_d, NOTCH2["zeta_d"], rtol=tol(NOTCH2["zeta_d"]))
    w = PeakFilter(**pf.params()).omega
    np.testing.assert_allclose(w, PEAK2["omega"], rtol=tol(PEAK2["omega"]))
    assert PeakFilter(1.0, 100.0, 0.1, 0.0).K.shape == (1,)  # scalars → one section
    assert PeakFilter([1.0, 2.0], 100.0, 0.1, 0.0).omega.shape == (2,)  # broadcast


def test_vmap_equals_loop():
    rng = np.random.default_rng(2)
    B = 4
    thetas = THETA * (1 + 0.1 * rng.uniform(-1, 1, (B, 7)))
    batch = eqx.filter_jit(eqx.filter_vmap(mcm_from))(jnp.asarray(thetas))
    assert batch.peak.K.shape == (B, 1)
    u = np.zeros(500)
    u[0] = 1.0

    def responses(m):
        return m.frf(FREQ), m.discretize(1 / 8000).apply(u)

    got_frf, got_y = eqx.filter_jit(eqx.filter_vmap(responses))(batch)
    single = eqx.filter_jit(responses)
    want_frf, want_y = (np.stack(w) for w in zip(*(single(mcm_from(t)) for t in thetas)))
    # Same arithmetic, possibly fused differently: within the evaluation bound (κ ≲ 1/ζ_min).
    np.testing.assert_allclose(got_frf, want_frf, rtol=64 * EPS / 0.045)
    # Impulse responses: rounding differences are filtered like in test_apply_matches_sosfilt.
    l1 = np.max(np.sum(np.abs(want_y), axis=1))
    np.testing.assert_allclose(got_y, want_y, rtol=0, atol=32 * EPS * l1 * l1)


def test_no_retrace_for_new_parameter_values():
    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def response(m):
        return m.frf(FREQ), m.discretize(1 / 8000).frf(FREQ[FREQ < 4000.0])  # below Nyquist

    response(mcm_from(jnp.asarray(THETA)))
    response(mcm_from(jnp.asarray(THETA * 1.05)))


# ---------------------------------------------------------------------------------- errors
W = TWO_PI * F_PEAK


@pytest.mark.parametrize(
    "make, message",
    [
        (
            lambda: PeakFilter(1.0, W, -0.1, 0.0),
            r"`PeakFilter\(xi=...\)` must be finite and positive, got -0.1",
        ),
        (
            lambda: PeakFilter(1.0, -W, 0.1, 0.0),
            r"`PeakFilter\(omega=...\)` must be finite and pos",
        ),
        (lambda: PeakFilter(1.0, np.nan, 0.1, 0.0), r"`PeakFilter\(omega=...\)`.*got nan"),
        (lambda: PeakFilter(np.nan, W, 0.1, 0.0), r"`PeakFilter\(K=...\)` must be finite"),
        (lambda: PeakFilter(1.0, W, 0.1, np.inf), r"`PeakFilter\(phi=...\)` must be finite"),
        (
            lambda: PeakFilter([1.0, 2.0], W, [0.1, 0.2, 0.3], 0.0),
            r"`PeakFilter\(xi=...\)` must be a scalar or have the same length as `K` \(2",
        ),
        (
            lambda: PeakFilter(np.ones((2, 2)), W, 0.1, 0.0),
            r"`PeakFilter\(K=...\)`.*shape \(2, 2\)",
        ),
        (lambda: PeakFilter(1.0 + 1j, W, 0.1, 0.0), r"`PeakFilter\(K=...\)` must be real"),
        (lambda: PeakFilter([], [], [], []), r"`PeakFilter\(K=...\)` must hold at least one"),
        (lambda: NotchFilter(W, -0.01, 0.3), r"`NotchFilter\(zeta_n=...\)` must be finite and pos"),
        (lambda: NotchFilter(W, 0.01, 0.0), r"`NotchFilter\(zeta_d=...\)`.*got 0"),
        (lambda: NotchFilter(np.inf, 0.01, 0.3), r"`NotchFilter\(omega=...\)`.*got inf"),
        (
            lambda: NotchFilter([W, W], [0.1, 0.1, 0.1], 0.3),
            r"`NotchFilter\(zeta_n=...\)` must be a scalar or have the same length as `omega`",
        ),
        (
            lambda: PeakFilter(1.0, W, 0.1, 0.0).discretize(0.0),
            r"`PeakFilter.discretize\(dt=...\)` must be finite and positive, got 0",
        ),
        (
            lambda: NotchFilter(W, 0.1, 0.3).discretize(-1e-4),
            r"`NotchFilter.discretize\(dt=...\)` must be finite and positive, got -0.0001",
        ),
        (
            lambda: MCM(notch=NotchFilter(W, 0.1, 0.3)).discretize(np.nan),
            r"`MCM.discretize\(dt=...\)`.*got nan",
        ),
        (
            lambda: MCM(notch=NotchFilter(TWO_PI * F_NOTCH, 0.1, 0.3)).discretize(1 / 2000),
            r"`MCM.discretize\(dt=...\)` must be below .* Nyquist",
        ),
        (
            lambda: PeakFilter(1.0, W, 0.1, 0.0).discretize(1e-4, "zoh"),
            r"`PeakFilter.discretize\(method=...\)` must be 'fitted' or 'tustin', got 'zoh'",
        ),
        (
            lambda: DiscreteFilter(np.ones((0, 6)), np.ones((1, 2, 5)), 1e-4),
            r"`DiscreteFilter\(series_sos=...\)` must be a real \(n_stages, n_sections, 6\)",
        ),
        (
            lambda: PeakFilter(1.0, W, 0.1, 0.0).discretize([1e-4, 2e-4]),
            r"`PeakFilter.discretize\(dt=...\)` must be a real scalar",
        ),
        (
            lambda: PeakFilter(1.0, W, 0.1, 0.0).frf([-1.0, 2.0]),
            r"`PeakFilter.frf\(freq_hz=...\)` must be finite and positive",
        ),
        (
            lambda: PeakFilter(1.0, W, 0.1, 0.0).discretize(1e-4).apply(np.ones((3, 2))),
            r"`DiscreteFilter.apply\(u=...\)` must be a real 1-D signal",
        ),
        (
            lambda: DiscreteFilter(np.ones((1, 5)), np.ones((0, 6)), 1e-4),
            r"`DiscreteFilter\(parallel_sos=...\)` must be a real \(n_sections, 6\)",
        ),
        (  # above Nyquist the response aliases (|G| at 7900 Hz was |G| at 100 Hz)
            lambda: PeakFilter(1.0, W, 0.1, 0.0).discretize(1.25e-4).frf([100.0, 7900.0]),
            r"`DiscreteFilter.frf\(freq_hz=...\)` must be at most the Nyquist frequency 4000 Hz "
            r"of the sample period 0.000125 s .* got 7900 at index 1",
        ),
        (  # was JAX's "add got incompatible shapes for broadcasting"
            lambda: PeakFilter(1.0, W, 0.1, 0.0).discretize(1e-4).step(np.zeros((3, 2)), 1.0),
            r"`DiscreteFilter.step\(state=...\)` must have shape \(2, 2\), got \(3, 2\)",
        ),
    ],
)
def test_bad_input_names_the_argument(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_mcm_part_types():
    with pytest.raises(TypeError, match=r"`MCM\(peak=...\)` must be a PeakFilter"):
        MCM(peak=NotchFilter(W, 0.1, 0.3))


def test_errors_under_jit():
    f = jax.jit(lambda xi: PeakFilter(1.0, W, xi, 0.0).frf(FREQ))
    f(0.1)
    with pytest.raises(CHECK_FAILED,
                       match=r"`PeakFilter\(xi=...\)` must be finite and positive"):
        jax.block_until_ready(f(-0.1))
    g = jax.jit(lambda dt: NotchFilter(TWO_PI * F_NOTCH, 0.1, 0.3).discretize(dt).dt)
    with pytest.raises(
        Exception, match=r"`NotchFilter.discretize\(dt=...\)` must be below π/ω_max"
    ):
        jax.block_until_ready(g(1 / 2000))
    h = jax.jit(lambda w: NotchFilter(w, 0.1, 0.3).discretize(1 / 2000).dt)
    with pytest.raises(CHECK_FAILED, match=r"below the Nyquist frequency"):
        jax.block_until_ready(h(TWO_PI * F_NOTCH))


_EXPORT_CASES = {
    "reference MCM": lambda: fdjax.reference_mcm(),
    "two peaks, two notches": lambda: MCM(
        PeakFilter([0.5, -0.3], [2 * np.pi * 131, 2 * np.pi * 400], [0.3, 0.1], [-1.0, 0.4]),
        NotchFilter([2 * np.pi * 1508, 2 * np.pi * 900], [0.05, 0.02], [0.5, 0.3]),
    ),
    "notch": lambda: NotchFilter(2 * np.pi * 1000, 0.05, 0.5),
    "identity": lambda: MCM(),
    # four lightly damped peaks near z = 1: the roots of the expanded numerator (an octic) had
    # put the cascade 1.35× off the filter (182× at 16 kHz, zeros outside the unit circle)
    "four low peaks": lambda: MCM(PeakFilter(
        [0.5, -0.3, 0.4, 0.2], 2 * np.pi * np.array([20.0, 25.0, 49.0, 60.0]),
        [0.005, 0.01, 0.02, 0.01], [-1.0, 0.4, 1.0, 2.0])),
}


@pytest.mark.parametrize("method", ["fitted", "tustin"])
@pytest.mark.parametrize("case", list(_EXPORT_CASES))
def test_to_sos_is_what_the_sampled_loop_runs(case, method):
    filt, T = _EXPORT_CASES[case](), 1.25e-4
    d = filt.discretize(T, method)
    sos = filt.to_sos(T, method)
    assert sos.dtype == np.float64 and sos.flags.writeable and sos.shape[1] == 6
    np.testing.assert_array_equal(sos[:, 3], 1.0)
    # scipy's own evaluation of the exported cascade against the filter the loop runs.  The
    # zeros of each stage (eigenvalues of its realisation's A − BC/D) cost round-off: measured
    # ≤ 3.3e-13 relative, 2.7e-11 for the four low peaks (tustin; 8.9e-12 fitted).
    f = np.geomspace(1.0, 3999.0, 400)
    _, h = sig.sosfreqz(sos, worN=2 * np.pi * f * T)
    rtol = 1e-10 if case == "four low peaks" else 1e-12
    np.testing.assert_allclose(h, np.asarray(d.frf(f)), rtol=rtol)
    if method == "tustin" and isinstance(filt, NotchFilter):
        np.testing.assert_allclose(sos, np.asarray(d.series_sos[:, 0]), rtol=1e-14)
    if case == "two peaks, two notches" and method == "fitted":
        # the same signal through scipy's sosfilt and through the loop's own recursion:
        # measured 2.5e-13 of the output's peak
        u = np.random.default_rng(0).normal(size=2000)
        y = np.asarray(d.apply(jnp.asarray(u)))
        np.testing.assert_allclose(sig.sosfilt(sos, u), y, rtol=0, atol=1e-12 * np.max(np.abs(y)))


def test_to_sos_of_stages_with_little_or_no_direct_gain():
    """A stage whose direct gain vanishes is a delay: its export raised numpy's LinAlgError.  One
    whose direct gain nearly cancels (1e-10) lost its zeros in A − BC/D (0.66 relative off):
    the factorisation nearer the stage's own response is taken.  Measured 2.1e-15, 1.1e-14 and
    4.3e-10 against sosfreqz."""
    T = 1.25e-4
    f = np.geomspace(1.0, 3999.0, 400)
    for rows, rtol in ((np.array([[0.0, 0.3, 0.1, 1.0, -1.6, 0.8]]), 1e-13),
                       (np.array([[0.5, 0.3, 0.1, 1.0, -1.6, 0.8],
                                  [-0.5, 0.2, -0.05, 1.0, -1.9, 0.95]]), 1e-13),
                       (np.array([[0.5, 0.3, 0.1, 1.0, -1.6, 0.8],
                                  [-0.5 + 1e-10, 0.2, -0.05, 1.0, -1.9, 0.95]]), 2e-9)):
        d = DiscreteFilter(np.zeros((0, 6)), rows[None], T)
        _, h = sig.sosfreqz(d.to_sos(), worN=2 * np.pi * f * T)
        np.testing.assert_allclose(h, np.asarray(d.frf(f)), rtol=rtol)


def test_discrete_frf_refuses_aliased_frequencies_under_jit():
    """With the filter a jit argument its period is traced: a frequency above Nyquist returned
    the aliased response silently (|G(7900 Hz)| = |G(100 Hz)| at 8 kHz)."""
    d = PeakFilter(1.0, W, 0.1, 0.0).discretize(1.25e-4)
    run = eqx.filter_jit(lambda d, f: d.frf(f))
    np.testing.assert_allclose(run(d, jnp.array([100.0, 3999.0])),
                               d.frf([100.0, 3999.0]), rtol=1e-14)
    with pytest.raises(CHECK_FAILED, match=r"`DiscreteFilter.frf\(freq_hz=...\)` must be at most "
                                           r"the Nyquist frequency"):
        jax.block_until_ready(run(d, jnp.array([100.0, 7900.0])))


def test_to_sos_needs_concrete_values():
    """Named as the user called it (under jit ``MCM.to_sos`` said "`DiscreteFilter.to_sos()`
    needs concrete coefficients")."""
    with pytest.raises(TypeError, match=r"^`MCM.to_sos\(\)` needs concrete values"):
        jax.jit(lambda f: jnp.asarray(f.to_sos(1.25e-4)))(fdjax.reference_mcm())
    with pytest.raises(TypeError, match=r"^`DiscreteFilter.to_sos\(\)` needs concrete"):
        jax.jit(lambda f: jnp.asarray(f.discretize(1.25e-4).to_sos()))(fdjax.reference_mcm())
