"""The parameterisation of gradient synthesis: every θ gives an admissible controller."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from compile_events import compilations
from jit_errors import CHECK_FAILED

import fdjax

T = 1.25e-4
BOUNDS = fdjax.MCMBounds.for_servo(fdjax.Servo())


def _physical(mcm):
    pk, nt = mcm.peak.params(), mcm.notch.params()
    return {k: float(v[0]) for k, v in {**{"peak_" + k: v for k, v in pk.items()},
                                         **{"notch_" + k: v for k, v in nt.items()}}.items()}


def _inside(x, lo, hi):
    # the filters store log ω, log ξ, log ζ: exp(log x) returns x to a few ulps
    return lo * (1 - 1e-14) <= x <= hi * (1 + 1e-14)


def _admissible(mcm, b=BOUNDS):
    p = _physical(mcm)
    w_lo, w_hi = 2 * math.pi * b.freq_hz[0], 2 * math.pi * b.freq_hz[1]
    assert _inside(p["peak_omega"], w_lo, w_hi) and _inside(p["notch_omega"], w_lo, w_hi)
    assert p["notch_omega"] * T < math.pi and p["peak_omega"] * T < math.pi
    assert _inside(p["peak_K"], *b.peak_gain)
    assert _inside(p["peak_xi"], *b.peak_damping)
    assert abs(p["peak_phi"]) <= b.peak_phase_max
    assert _inside(p["notch_zeta_d"], *b.notch_damping)
    # ζ_n/ζ_d < 1 (it reaches 1, the identity, only where the logistic function saturates)
    assert _inside(p["notch_zeta_n"] / p["notch_zeta_d"], b.notch_depth_min, 1.0)


def test_round_trip_and_reference():
    theta = jnp.asarray(np.random.default_rng(0).uniform(-4, 4, size=(20, 7)))
    back = jax.vmap(lambda t: BOUNDS.from_mcm(BOUNDS.to_mcm(t)))(theta)
    # logit(σ(θ)) loses about |θ| e^{|θ|} ε: measured 2.4e-13 at |θ| ≤ 4
    np.testing.assert_allclose(back, theta, rtol=0, atol=1e-12)
    ref = fdjax.reference_mcm()
    np.testing.assert_allclose(
        list(_physical(BOUNDS.to_mcm(BOUNDS.from_mcm(ref))).values()),
        list(_physical(ref).values()), rtol=1e-13)
    loop = fdjax.DoubleLoop(mcm=ref)
    par = fdjax.DoubleLoopParameterisation(BOUNDS, loop)
    theta = par.from_controller(loop)
    np.testing.assert_allclose(theta[:5], [0, 0, 0, 1, 1], atol=1e-15)
    # each entry of θ in its place (MCM_PARAMETERS), as the class docstring writes the map:
    # a round trip cannot see the same permutation on both sides
    sig = lambda x: 1.0 / (1.0 + np.exp(-x))  # noqa: E731
    box = lambda x, lo, hi: lo * (hi / lo) ** sig(x)  # noqa: E731
    w = 2 * np.pi * np.asarray(BOUNDS.freq_hz)
    for t in np.random.default_rng(5).uniform(-3, 3, size=(5, 7)):
        zd = box(t[5], *BOUNDS.notch_damping)
        expected = {"peak_K": box(t[0], *BOUNDS.peak_gain), "peak_omega": box(t[1], *w),
                    "peak_xi": box(t[2], *BOUNDS.peak_damping),
                    "peak_phi": BOUNDS.peak_phase_max * np.tanh(t[3]),
                    "notch_omega": box(t[4], *w),
                    "notch_zeta_n": zd * BOUNDS.notch_depth_min ** sig(t[6]), "notch_zeta_d": zd}
        got = _physical(BOUNDS.to_mcm(jnp.asarray(t)))
        for k, v in expected.items():   # measured 3.3e-16
            np.testing.assert_allclose(got[k], v, rtol=2e-15, err_msg=k)
    assert fdjax.MCM_PARAMETERS == ("peak_K", "peak_omega", "peak_xi", "peak_phi",
                                    "notch_omega", "notch_zeta_d", "notch_depth")
    assert par.names == fdjax.GAIN_PARAMETERS + fdjax.MCM_PARAMETERS and len(par.names) == 12
    again = par.to_controller(theta)
    for k in ("kp", "kv", "ki", "k_ffv", "k_ffa"):
        np.testing.assert_allclose(getattr(again, k), getattr(loop, k), rtol=1e-14)



def test_a_non_finite_theta_is_named_by_the_map_the_user_called():
    """A NaN entry of θ was reported as the field of a controller the user never built
    (`DoubleLoop(kp=...)`, `PeakFilter(K=...)`); a loop without an MCM as
    `MCMBounds.from_mcm(mcm=...)`."""
    ref = fdjax.reference_controller(fdjax.reference_drive())
    par = fdjax.DoubleLoopParameterisation(BOUNDS, ref)
    for par_, n, name in ((par, 12, "DoubleLoopParameterisation"),
                          (fdjax.PIDParameterisation(fdjax.reference_pid(), feedforward=False), 6,
                           "PIDParameterisation")):
        with pytest.raises(ValueError, match=rf"^`{name}\.to_controller\(theta=\.\.\.\)` must "
                                             r"be finite, got nan at index 3$"):
            par_.to_controller(jnp.zeros(n).at[3].set(jnp.nan))
    with pytest.raises(ValueError, match=r"^`MCMBounds\.to_mcm\(theta=\.\.\.\)` must be "
                                         r"finite, got inf at index 6$"):
        BOUNDS.to_mcm(jnp.zeros(7).at[6].set(jnp.inf))
    with pytest.raises(TypeError, match=r"^`DoubleLoopParameterisation\.from_controller\(loop="
                                        r"\.\.\.\)\.mcm` must be an fdjax\.MCM"):
        par.from_controller(fdjax.DoubleLoop())


def test_saturated_theta_reads_back_and_bad_filters_raise_under_jit():
    # σ(θ) rounds to 1 in float64 beyond θ ≈ 36.7, so to_mcm puts the filter on a bound: it
    # must read back as a finite θ that gives the same filter (not an error, not inf)
    for k, big in ((0, 40.0), (3, 20.0), (6, 40.0), (6, -40.0), (1, -40.0)):
        theta = jnp.zeros(7).at[k].set(big)
        mcm = BOUNDS.to_mcm(theta)
        back = BOUNDS.from_mcm(mcm)
        assert np.all(np.isfinite(np.asarray(back))) and abs(float(back[k])) <= 36.1
        np.testing.assert_allclose(list(_physical(BOUNDS.to_mcm(back)).values()),
                                   list(_physical(mcm).values()), rtol=1e-14)
    # a filter outside the bounds raises eagerly and under jit, never a silent NaN
    ref = fdjax.reference_mcm()
    bad = fdjax.MCM(fdjax.PeakFilter(100.0, 2 * math.pi * 800, 0.2, 0.1), ref.notch)
    with pytest.raises(ValueError, match=r"must be a filter with the peak gain K inside "
                                         r"\[0\.001, 10\], got 100"):
        BOUNDS.from_mcm(bad)
    with pytest.raises(CHECK_FAILED, match=r"the peak gain K inside \[0\.001, 10\]"):
        jax.block_until_ready(eqx.filter_jit(BOUNDS.from_mcm)(bad))

@pytest.mark.parametrize("scale", [1.0, 30.0, 1e3])
def test_every_theta_is_admissible(scale):
    rng = np.random.default_rng(1)
    for theta in scale * rng.normal(size=(25, 7)):
        mcm = BOUNDS.to_mcm(jnp.asarray(theta))
        _admissible(mcm)
        assert np.all(np.isfinite(np.asarray(mcm.frf(np.array([10.0, 131.0, 3000.0])))))
        mcm.discretize(T)  # the discretisation's own Nyquist check passes


def test_gains_stay_finite_and_positive_for_every_finite_theta():
    """Gains are k_ref e^θ with θ held within ±30: a step of any length (here θ = ±1e3, where
    e^θ is ∞ or 0 in float64) gives a controller, not an error; inside, θ round-trips."""
    drive = fdjax.reference_drive()
    loop = fdjax.reference_controller(drive)
    pid = fdjax.reference_pid(k_ffv=1.0, k_ffa=1.0)
    for par, ref, names in ((fdjax.DoubleLoopParameterisation(BOUNDS, loop), loop,
                             ("kp", "kv", "ki")),
                            (fdjax.PIDParameterisation(pid), pid, ("kp", "ki", "kd"))):
        n = len(names)
        theta0 = np.asarray(par.from_controller(ref))
        for big in (1e3, -1e3):
            c = par.to_controller(theta0 + big)
            ratio = [float(getattr(c, k)) / float(getattr(ref, k)) for k in names]
            np.testing.assert_allclose(ratio, np.exp(np.sign(big) * 30.0), rtol=1e-13,
                                       err_msg=type(par).__name__)
        th = theta0.copy()
        th[:n] += np.array([29.0, -29.0, 5.0])
        np.testing.assert_allclose(np.asarray(par.from_controller(par.to_controller(th)))[:n],
                                   th[:n], atol=1e-12)


def test_gradient_is_finite_and_matches_central_differences():
    f = lambda t: jnp.sum(jnp.abs(BOUNDS.to_mcm(t).frf(jnp.array([50.0, 131.0, 1500.0]))) ** 2)
    theta = jnp.asarray(np.random.default_rng(2).normal(size=7))
    g = jax.grad(f)(theta)
    h = 1e-6
    fd = np.array([(f(theta.at[i].add(h)) - f(theta.at[i].add(-h))) / (2 * h) for i in range(7)])
    # central differences: truncation h² f''' ~ 1e-12 and round-off ε f/h ~ 1e-10 of the
    # largest component (measured 2.9e-10; components near zero carry that absolute error)
    np.testing.assert_allclose(g, fd, rtol=0, atol=2e-9 * np.max(np.abs(fd)))
    assert np.all(np.isfinite(np.asarray(jax.grad(f)(jnp.full(7, 1e3)))))


def test_no_optimiser_step_leaves_the_domain():
    # a loss that pulls the frequencies past the Nyquist frequency and the notch into a lead
    # element, minimised with an absurd learning rate
    def loss(t):
        m = BOUNDS.to_mcm(t)
        return -(m.peak.omega[0] + m.notch.omega[0]) * T - m.notch.zeta_n[0] / m.notch.zeta_d[0]

    opt = optax.adam(100.0)
    theta = jnp.zeros(7)
    state = opt.init(theta)
    step = jax.jit(lambda t, s: (lambda g: opt.update(g, s, t))(jax.grad(loss)(t)))
    with jax.numpy_dtype_promotion("standard"):  # optax's bias correction: float ** int32
        for _ in range(50):
            upd, state = step(theta, state)
            theta = optax.apply_updates(theta, upd)
            _admissible(BOUNDS.to_mcm(theta))


def test_errors_name_the_argument():
    with pytest.raises(ValueError, match=r"`MCMBounds\(freq_hz=\.\.\.\)` must stay below the "
                                         r"Nyquist frequency 4000 Hz"):
        fdjax.MCMBounds(period=T, freq_hz=(10.0, 4500.0))
    with pytest.raises(ValueError, match=r"`MCMBounds\.from_mcm\(mcm=\.\.\.\)` must be a filter "
                                         r"with the notch depth"):
        BOUNDS.from_mcm(fdjax.MCM(fdjax.PeakFilter(0.5, 800.0, 0.3, -1.0),
                                  fdjax.NotchFilter(9000.0, 0.6, 0.5)))
    with pytest.raises(ValueError, match=r"a filter with the peak frequency ω \(rad/s\) inside"):
        BOUNDS.from_mcm(fdjax.MCM(fdjax.PeakFilter(0.5, 3e4, 0.3, -1.0),
                                  fdjax.NotchFilter(9000.0, 0.05, 0.5)))
    with pytest.raises(ValueError, match=r"must have shape \(7,\), got \(6,\)"):
        BOUNDS.to_mcm(jnp.zeros(6))
    with pytest.raises(TypeError, match=r"must be an fdjax.MCMBounds"):
        fdjax.DoubleLoopParameterisation(None)
    with pytest.raises(ValueError, match=r"k_ffv sets the scale of its parameter"):
        fdjax.DoubleLoopParameterisation(BOUNDS, fdjax.DoubleLoop(k_ffv=0.0))
    with pytest.raises(TypeError, match=r"`MCMBounds\.for_servo\(period=\.\.\.\)` is set from "
                                        r"the servo"):
        fdjax.MCMBounds.for_servo(fdjax.Servo(), period=1e-4)
    with pytest.raises(TypeError, match=r"`PIDParameterisation\(servo=\.\.\.\)` must be an "
                                        r"fdjax\.Servo, got str"):
        fdjax.PIDParameterisation(fdjax.reference_pid(k_ffv=1.0, k_ffa=1.0), servo="8 kHz")


def test_tuners_refuse_filters_their_servo_cannot_sample():
    """Bounds built for a 16 kHz servo let the filters reach 7.2 kHz, above the Nyquist
    frequency of the objective's 8 kHz servo: every tuner and the certificate refuse them before
    compiling, naming the argument that carries them (a run would otherwise fail in the
    middle, in the filters' discretisation)."""
    drive = fdjax.reference_drive()
    fast = fdjax.MCMBounds.for_servo(fdjax.Servo(period=1 / 16000))
    par = fdjax.DoubleLoopParameterisation(fast, fdjax.reference_controller(drive))
    obj = fdjax.Objective(fdjax.tuning_motion(), np.geomspace(5.0, 3900.0, 16))
    start = fdjax.reference_controller(drive)
    nyq = r"lets the filters reach 7200 Hz, not below the Nyquist frequency 4000 Hz"
    for tuner in (fdjax.tune_local, fdjax.tune_newton, fdjax.tune_simplex, fdjax.tune_robust):
        with pytest.raises(ValueError, match=rf"`{tuner.__name__}\(parameterisation=\.\.\.\)` "
                                             + nyq):
            tuner(par, obj, drive, [0.3], start)
    pid = fdjax.PIDParameterisation(fdjax.reference_pid(k_ffv=1.0, k_ffa=1.0),
                                    servo=fdjax.Servo(period=1 / 16000))
    with pytest.raises(ValueError, match=r"`tune_local\(parameterisation=\.\.\.\)` lets the "
                                         r"filters reach 7200 Hz"):
        fdjax.tune_local(pid, obj, drive, [0.3], fdjax.reference_pid(k_ffv=1.0, k_ffa=1.0))
    sched = fdjax.ScheduledLoop(start, fdjax.ATANetwork(drive.travel_m, width=3), fast)
    with pytest.raises(ValueError, match=r"`train_schedule\(schedule=\.\.\.\)` " + nyq):
        fdjax.train_schedule(sched, obj, drive)
    with pytest.raises(ValueError, match=r"`certify\(controller=\.\.\.\)` " + nyq):
        fdjax.certify(sched, drive, [0.3])


# ------------------------------------------------------------------ smooth margin penalties
F_HZ = np.geomspace(1.0, 3000.0, 4000)


def _loop(k):
    """A delayed integrator with a lag: L = k e^{−iωτ}/(iω (1 + iω/a)), τ = 250 µs."""
    s = 2j * np.pi * F_HZ
    return k * np.exp(-s * 2.5e-4) / (s * (1 + s / (2 * np.pi * 400.0)))


def test_distances_are_the_margins():
    from fdjax._tune import gain_distance, modulus_distance, phase_distance

    L = _loop(800.0)
    m = fdjax.stability_margins(F_HZ, L)
    # the grid's minima are the margins to the grid's resolution (4000 points over 3.5 decades:
    # relative spacing 2e-3, the distance is flat to second order at its minimum)
    np.testing.assert_allclose(np.min(modulus_distance(L)), m.modulus_margin, rtol=1e-5)
    # at the margin itself the Nyquist curve touches the forbidden ray / arc
    gm_db, pm = float(m.gain_margin_db), float(m.phase_margin_deg)
    assert float(np.min(gain_distance(L, gm_db + 0.5))) < 1e-3
    assert float(np.min(gain_distance(L, gm_db - 0.5))) > 1e-3
    assert float(np.min(phase_distance(L, pm + 1.0))) < 2e-3
    assert float(np.min(phase_distance(L, pm - 1.0))) > 1e-3
    # distances against a brute-force oracle: the nearest of many points of the segment and
    # the arc (points spaced 7.5e-6 and 2.6e-5 apart; the nearest grid point's distance is off
    # by second order in the spacing: measured 1.8e-12 and 1.2e-10)
    a = 10 ** (-6 / 20)
    seg = -np.linspace(a, 1 / a, 200001)
    arc = np.exp(1j * (np.pi + np.linspace(-np.pi / 6, np.pi / 6, 20001)))
    pts = np.concatenate([L[::97], [-10.0 + 0.3j, -1.0 - 0.2j, -3.0, -0.2 + 0.1j]])
    np.testing.assert_allclose(gain_distance(pts, 6.0),
                               np.min(np.abs(pts[:, None] - seg[None]), axis=1), atol=1e-11)
    np.testing.assert_allclose(phase_distance(pts, 30.0),
                               np.min(np.abs(pts[:, None] - arc[None]), axis=1), atol=1e-9)


def test_gain_margin_penalty_counts_both_directions_as_the_exact_margin_does():
    """A loop that crosses the negative real axis at |L| = 10 (a gain reduction of 20 dB
    destabilises it, as at the low frequencies of a conditionally stable loop) and at
    |L| = 0.25 (12 dB up) has a gain margin of 12 dB: no gain-margin penalty at 6 dB; scaled
    by 5 (crossings at 50 and 1.25, margin 1.9 dB) it is penalised."""
    from fdjax._tune import gain_distance, margin_penalty

    t = np.linspace(0.0, 1.0, 4001)
    # phase zero (on the negative real axis) at t = 1/4 and 3/4 only, |L| 20 → 0.1
    r = np.exp(np.interp(t, [0.0, 0.25, 0.75, 1.0], np.log([20.0, 10.0, 0.25, 0.1])))
    L = -r * np.exp(0.8j * np.sin(2 * np.pi * (t - 0.25)))
    m = fdjax.stability_margins(np.linspace(1.0, 100.0, t.size), L)
    # the crossing at t = 1/4 is a grid point, where the interpolant is exact
    np.testing.assert_allclose(float(m.gain_margin_db), 20 * np.log10(4.0), rtol=1e-12)
    assert float(np.min(gain_distance(L, 6.0))) > 0.15  # measured 0.171
    # the gain and phase terms (the modulus requirement dropped): measured 0.005; a crossing
    # inside the segment costs at least (ln 2)²
    assert float(margin_penalty(L, modulus_margin=0.01)) < 0.01
    assert float(np.min(gain_distance(5.0 * L, 6.0))) < 1e-3
    assert float(margin_penalty(5.0 * L, modulus_margin=0.01)) > np.log(2) ** 2


def test_penalty_settings_are_checked():
    """A zero width made the penalty vanish without a word, a zero β made it infinite; a NaN
    in L gave a NaN penalty, an infinite L NaN (inf − inf in the shift), a scalar L JAX's
    "axis -1 is out of bounds"."""
    L = jnp.array([0.5 + 0.1j, -0.3 + 0.2j, -0.9 + 0.05j])
    for bad, message in (([0.5 + 0.1j, np.nan], r"must be finite .* got \(nan\+0j\) at index 1"),
                         (np.full(3, np.inf + 0j), r"must be finite"),
                         (0.5 + 0j, r"must be the open loop on a frequency grid .* got shape "
                                    r"\(\)")):
        with pytest.raises(ValueError, match=r"`margin_penalty\(L=\.\.\.\)` " + message):
            fdjax.margin_penalty(bad)
    for kw, name in (({"beta": 0.0}, "beta"), ({"width": 0.0}, "width"),
                     ({"width": np.inf}, "width"), ({"beta": -3.0}, "beta")):
        with pytest.raises(ValueError, match=rf"`margin_penalty\({name}=\.\.\.\)` must be finite "
                                             r"and positive"):
            fdjax.margin_penalty(L, **kw)
    with pytest.raises(ValueError, match=r"`soft_min\(beta=\.\.\.\)` must be finite and positive"):
        fdjax._tune.soft_min(jnp.ones(3), 0.0)
    # under jit the settings are traced, and checked there too
    traced = jax.jit(lambda b, w: fdjax.margin_penalty(L, beta=b, width=w))(200.0, 0.05)
    np.testing.assert_allclose(traced, fdjax.margin_penalty(L, beta=200.0, width=0.05),
                               rtol=1e-14)
    for name, value in (("beta", -1.0), ("width", 0.0)):
        with pytest.raises(CHECK_FAILED, match=rf"`margin_penalty\({name}=\.\.\.\)` must be "
                                               r"finite and positive"):
            jax.jit(lambda v: fdjax.margin_penalty(L, **{name: v}))(value)
    with pytest.raises(CHECK_FAILED,
                       match=r"`soft_min\(beta=\.\.\.\)` must be finite and positive"):
        jax.jit(lambda b: fdjax._tune.soft_min(jnp.ones(3), b))(0.0)
    # the requirements are numbers in their ranges
    for name, value, expected in (("modulus_margin", np.nan, r"in \(0, 1\]"),
                                  ("gain_margin_db", -6.0, "finite and non-negative"),
                                  ("phase_margin_deg", 400.0, r"in \[0, 180\) degrees")):
        with pytest.raises(ValueError, match=rf"`margin_penalty\({name}=\.\.\.\)` must be "
                                             + expected):
            fdjax.margin_penalty(L, **{name: value})


def test_penalty_grows_with_gain_and_stays_finite():
    from fdjax._tune import margin_penalty, soft_min

    d = np.array([0.3, 0.7, 0.31])
    assert float(soft_min(d, 200.0)) <= 0.3 and float(soft_min(d, 200.0)) > 0.3 - np.log(3) / 200
    # −(1/β) ln Σ e^{−β d} = min d − (1/β) ln(1 + e^{−2} + e^{−80}) (exactly, measured)
    np.testing.assert_allclose(float(soft_min(d, 200.0)),
                               0.3 - np.log1p(np.exp(-2.0) + np.exp(-80.0)) / 200, rtol=1e-15)
    # the penalty in NumPy from the distances (checked against brute force above):
    # Σ_j softplus((d_j − d̃_j)/w)², d̃ the smooth minimum, requirements m, w/4, w/4
    from fdjax._tune import gain_distance, modulus_distance, phase_distance

    def numpy_penalty(L, m=0.5, g=6.0, p=30.0, beta=200.0, w=0.05):
        total = 0.0
        for dist, req in ((modulus_distance(L), m), (gain_distance(L, g), w / 4),
                          (phase_distance(L, p), w / 4)):
            dist = np.asarray(dist)
            smooth = dist.min() - np.log(np.sum(np.exp(-beta * (dist - dist.min())))) / beta
            total += np.logaddexp(0.0, (req - smooth) / w) ** 2
        return total

    for k in (200.0, 1200.0, 2400.0):   # measured 2e-15 relative at most
        np.testing.assert_allclose(float(margin_penalty(_loop(k))), numpy_penalty(_loop(k)),
                                   rtol=1e-13)
    np.testing.assert_allclose(float(margin_penalty(_loop(800.0), modulus_margin=0.7, beta=50.0,
                                                    width=0.1)),
                               numpy_penalty(_loop(800.0), m=0.7, beta=50.0, w=0.1), rtol=1e-13)
    ks = np.array([200.0, 400.0, 800.0, 1200.0, 1600.0, 2400.0])
    pen = np.array([float(margin_penalty(_loop(k))) for k in ks])
    margins = fdjax.stability_margins(F_HZ, np.stack([_loop(k) for k in ks]))
    mm = np.asarray(margins.modulus_margin)
    bad = (mm < 0.5) | (np.asarray(margins.gain_margin_db) < 6) | (
        np.asarray(margins.phase_margin_deg) < 30)
    assert np.all(np.diff(pen) > 0)            # more gain, less margin, more penalty
    # softplus(0)² = (ln 2)² at the requirement; a margin 2 widths clear costs < softplus(−2)²
    assert np.all(pen[mm > 0.6] < 0.02) and np.all(pen[bad] > np.log(2) ** 2)
    assert np.any(bad) and np.any(mm > 0.6)
    # through the critical point itself (the gain margin is the factor to it: L(k_crit) passes
    # through −1 on the grid, min |1 + L| measured 1.6e-3): finite value and gradient
    g = jax.grad(lambda k: margin_penalty(k * jnp.asarray(_loop(1.0))))
    k_crit = 200.0 * float(margins.gain_margin[0])
    assert np.min(np.abs(1 + _loop(k_crit))) < 1e-2
    assert np.isfinite(float(margin_penalty(_loop(k_crit)))) and float(
        margin_penalty(_loop(k_crit))) > pen[-1]
    assert np.isfinite(float(g(k_crit))) and float(g(k_crit)) > 0


# ------------------------------------------------------------------------------ the objective
def test_objective_is_finite_penalising_and_differentiable():

    drive = fdjax.reference_drive()
    ref = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    obj = fdjax.Objective(ref, np.geomspace(5.0, 3900.0, 400),
                          twin=fdjax.TwinOptions(kept_modes=6))
    par = fdjax.DoubleLoopParameterisation(BOUNDS, fdjax.reference_controller(drive))
    theta0 = par.from_controller(fdjax.reference_controller(drive))
    terms_of = eqx.filter_jit(lambda o, th, y: o(par.to_controller(th), drive, y))
    J = lambda th, y: terms_of(obj, th, y)  # noqa: E731
    good = J(theta0, 0.3)
    assert bool(good.stable) and float(good.growth_rate) < 0
    sim = fdjax.simulate(par.to_controller(theta0), drive, ref, position_m=0.3,
                         twin=fdjax.TwinOptions(kept_modes=6))
    # the same run fused into the objective's program: round-off, measured 1.7e-11
    np.testing.assert_allclose(good.rms_error_m, sim.rms_error(), rtol=3e-11)
    # k_v × 10: unstable; a large, finite value with a finite gradient
    hot = theta0.at[1].add(math.log(10.0))
    bad = J(hot, 0.3)
    assert not bool(bad.stable) and float(bad.growth_rate) > 0
    assert np.isfinite(float(bad.total)) and float(bad.total) > 100 * float(good.total)
    grad = jax.jit(jax.grad(lambda th: J(th, 0.3).total))
    assert np.all(np.isfinite(np.asarray(grad(hot))))
    # gains as far as the parameterisation lets them go (e^±30 about the reference): finite
    # gradients (all four were NaN: a diverging run's state overflowed, 0·∞ in the reverse
    # pass; and the third's open loops, |L| ~ 1e27, gave −∞ in the smooth minimum under jit)
    for shift in ([0.0, 9.2, 0.0], [30.0, 0.0, 30.0], [30.0, 30.0, 30.0], [-30.0, 30.0, -30.0]):
        far = theta0.at[:3].add(jnp.asarray(shift))
        assert np.all(np.isfinite(np.asarray(grad(far)))), shift
        assert np.isfinite(float(J(far, 0.3).total)), shift
    # the gradient of a stable design against central differences (step 1e-5 in θ, order one)
    g = np.asarray(grad(theta0))
    h = 1e-5
    for i in (0, 1, 2, 4, 5, 8, 10):
        fd = (float(J(theta0.at[i].add(h), 0.3).total)
              - float(J(theta0.at[i].add(-h), 0.3).total)) / (2 * h)
        # measured 1e-10–6.4e-8 (θ5): central differences' truncation at h = 1e-5
        np.testing.assert_allclose(g[i], fd, rtol=5e-7, atol=1e-8 * np.max(np.abs(g)))
    # the margin term is margin_penalty of the three open loops, with the objective's width
    # and sharpness (here the sharp penalties of tuning_objective: w = 0.01, β = 10/w)
    sharp = dataclasses.replace(obj, margin_width=0.01, margin_sharpness=1000.0)
    assert fdjax.tuning_objective(margin_width=0.01).margin_sharpness == 1000.0
    with compilations() as names:  # widths and weights are traced: nothing compiles
        terms = terms_of(sharp, theta0, 0.3)
    assert names == [], names
    plant = fdjax.state_space(drive, 0.3, twin=fdjax.TwinOptions(kept_modes=6))
    loops = fdjax.open_loop(par.to_controller(theta0), plant, obj.freq_hz)
    wide_pen, sharp_pen = (
        sum(float(fdjax.margin_penalty(L, width=w, beta=b))
            for L in (loops.plant_input, loops.speed, loops.position))
        for w, b in ((0.05, 200.0), (0.01, 1000.0)))
    # the same open loops, computed apart from the simulation: round-off
    np.testing.assert_allclose(float(good.margin_penalty), wide_pen, rtol=1e-9)
    np.testing.assert_allclose(float(terms.margin_penalty), sharp_pen, rtol=1e-9)
    np.testing.assert_allclose(terms.rms_error_m, good.rms_error_m, rtol=1e-12)
    # the reference controller, tuned for the largest stable k_v, breaks requirements (its
    # position loop's gain margin is below 6 dB): the sharp penalties grow faster past them
    assert sharp_pen > 10 * wide_pen


def test_objective_names_itself_in_errors():
    ref = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    obj = fdjax.Objective(ref, np.geomspace(5.0, 3900.0, 64))
    with pytest.raises(ValueError, match=r"`Objective\(position_m=\.\.\.\)` must be inside "
                                         r"the travel \[0.1, 0.7\] m, got 115"):
        obj(fdjax.DoubleLoop(), fdjax.reference_drive(), 115.0)  # mm typed as m
    with pytest.raises(TypeError, match=r"`Objective\(drive=\.\.\.\)` must be an fdjax"):
        obj(fdjax.DoubleLoop(), None, 0.3)
    with pytest.raises(ValueError, match=r"`Objective\(output=\.\.\.\)` must be 'scale' or"):
        fdjax.Objective(ref, np.geomspace(5.0, 3900.0, 64), output="x3")
    for name in ("margin_width", "margin_sharpness"):
        with pytest.raises(ValueError, match=rf"`Objective\({name}=\.\.\.\)` must be finite and "
                                             r"positive, got 0.0"):
            fdjax.Objective(ref, np.geomspace(5.0, 3900.0, 64), **{name: 0.0})
    grid = np.geomspace(5.0, 3900.0, 64)
    for kw, msg in (
        ({"margin_weight": -1.0}, r"margin_weight=\.\.\.\)` must be finite and non-negative, "
                                  r"got -1"),
        ({"margin_weight": np.inf}, r"margin_weight=\.\.\.\)` must be finite and non-negative, "
                                    r"got inf"),
        # static settings fix what is compiled: NaN growth rates made J NaN and "stable"
        ({"max_growth_rate": np.nan}, r"max_growth_rate=\.\.\.\)` must be finite \(1/s\), "
                                      r"got nan"),
        ({"gain_margin_db": np.nan}, r"gain_margin_db=\.\.\.\)` must be finite and non-negative"),
        ({"phase_margin_deg": -5.0}, r"phase_margin_deg=\.\.\.\)` must be in \[0, 180\) degrees"),
        ({"modulus_margin": 1.5}, r"modulus_margin=\.\.\.\)` must be in \(0, 1\]"),
        ({"error_bound_m": -1.0}, r"error_bound_m=\.\.\.\)` must be finite and positive \(m\)"),
        ({"duration": 0.0}, r"duration=\.\.\.\)` must be finite and positive \(s\)"),
    ):
        with pytest.raises(ValueError, match=r"`Objective\(" + msg):
            fdjax.Objective(ref, grid, **kw)
    # one position per call: the objective is vmapped over positions, not given an array
    with pytest.raises(ValueError, match=r"`Objective\.margin_term\(position_m=\.\.\.\)` must be "
                                         r"one table position \(a scalar"):
        obj.margin_term(fdjax.DoubleLoop(), fdjax.reference_drive(), np.array([0.3]))
    # a grid given as a list is the float64 array a grid given as an array is
    listed = fdjax.Objective(ref, list(grid.astype(np.float32)))
    assert isinstance(listed.freq_hz, jax.Array) and listed.freq_hz.dtype == jnp.float64
    with pytest.raises(ValueError, match=r"`Objective\(error_scale_m=\.\.\.\)` must be a "
                                         r"scalar, got shape \(2,\)"):
        fdjax.Objective(ref, np.geomspace(5.0, 3900.0, 64), error_scale_m=[1e-6, 1e-5])
    # the grid where it is given, not at the first evaluation (nor inside a tuner's jit)
    with pytest.raises(ValueError, match=r"`Objective\(freq_hz=\.\.\.\)` must be below the "
                                         r"servo's Nyquist frequency 4000 Hz .*got 4015.43"):
        fdjax.Objective(ref, np.geomspace(5.0, 5000.0, 64))
    with pytest.raises(ValueError, match=r"`Objective\(freq_hz=\.\.\.\)` must be finite and "
                                         r"positive, got 0 at index 0"):
        fdjax.Objective(ref, np.linspace(0.0, 3000.0, 64))
    with pytest.raises(ValueError, match=r"`Objective\(freq_hz=\.\.\.\)` must be strictly "
                                         r"increasing"):
        fdjax.Objective(ref, np.geomspace(3000.0, 5.0, 64))
    # a servo at 16 kHz allows the grid up to its own Nyquist frequency
    fdjax.Objective(ref, np.geomspace(5.0, 7900.0, 64), servo=fdjax.Servo(period=1 / 16000))
