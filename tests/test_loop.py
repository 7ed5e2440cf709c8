"""Double loop (Fig. 13), PID baseline, loop analysis (margins, closed-loop poles), Fig. 14.

Oracles: python-control (``control.stability_margins``, ``control.feedback(...).poles()``,
``control.pade``) on the same loop built from the twin's (A, B, C, D) and controller transfer
functions written here from the equations; closed forms (Padé is all-pass, the outer gain margin
scales as 1/k_p); finite differences; a loop over positions for vmap.

Tolerances are derived: a crossing found by either side is off by δu = r/|f'(u)| in
u = log ω, r the residual of its crossing equation (evaluated here independently, in numpy), and
a margin inherits |d(value)/du|·δu; eigenvalues differ by at most κ(λ)·ε·‖A‖ per side
(κ the eigenvalue condition number).
"""

import control
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jit_errors import CHECK_FAILED
from scipy.optimize import linear_sum_assignment

import fdjax
from fdjax import DoubleLoop, PIDLoop
from fdjax._control._blocks import _pade_coefficients

EPS = np.finfo(np.float64).eps
TWO_PI = 2 * np.pi
FREQ = np.geomspace(1.0, 4000.0, 2000)
POSITIONS = np.linspace(0.1, 0.7, 7)
N_MODES = 4  # a reduced twin: python-control's polynomial margins are exact at this order
PADE = 4
SERVO = fdjax.Servo()  # 8 kHz, τ = 2 periods = 250 µs
CONT = fdjax.Continuous(PADE)  # the continuous loop, delay as its [4/4] Padé approximant
EXACT = fdjax.Continuous()  # exact delay
# The loop algebra and its oracles are checked on the Table 1 drive with its hand-set double
# loop (the reference drive's own loops are tested in tests/test_reference.py).
ISC = float(fdjax.table1_drive().screw.ratio)
FRF_KW = dict(method=EXACT, screw_ratio=ISC)  # an FRF plant: continuous loop, i_sc given

PEAK = dict(K=0.5, omega=TWO_PI * 115.0, xi=0.5, phi=np.radians(-75.0))
NOTCH = dict(omega=TWO_PI * 1190.0, zeta_n=0.05, zeta_d=0.5)
MCM = fdjax.MCM(fdjax.PeakFilter(**PEAK), fdjax.NotchFilter(**NOTCH))
GAINS = dict(kp=40.0, kv=3.0e3, ki=60.0)
LOOPS = {
    "double": DoubleLoop(**GAINS),
    "double+mcm": DoubleLoop(**GAINS, mcm=MCM),
    "pid": PIDLoop(),
}


@pytest.fixture(scope="module")
def drive():
    return fdjax.table1_drive()


@pytest.fixture(scope="module")
def twin(drive):
    return fdjax.state_space(drive, 0.4, twin=fdjax.TwinOptions(kept_modes=N_MODES))


@pytest.fixture(scope="module")
def frf(drive):
    return drive.frf(POSITIONS, FREQ)


# ---------------------------------------------------------------- python-control oracle
def mcm_tf():
    """Eq. (3) and Eq. (4) as python-control transfer functions (from the equations)."""
    K, w, xi, phi = PEAK.values()
    den = np.array([1.0, 2 * xi * w, w * w])
    peak = control.tf(den + K * np.array([np.cos(phi), w * np.sin(phi), 0.0]), den)
    w, zn, zd = NOTCH.values()
    notch = control.tf([1.0, 2 * zn * w, w * w], [1.0, 2 * zd * w, w * w])
    return peak, notch


def ss_of(tf):
    return control.ss(control.tf2ss(tf))


def control_loops(name, loop, ss, n):
    """(L_inner or None, L_outer, closed loop r → x2) in python-control."""
    A, B, C, D, Cv = (np.asarray(x) for x in (ss.A, ss.B, ss.C, ss.D, ss.C_velocity))
    tau, k = SERVO.tau, float(SERVO.k_motor)
    delay = ss_of(control.tf(*control.pade(tau, n)))
    if name == "pid":
        kp, ki, kd, wd = (float(x) for x in (loop.kp, loop.ki, loop.kd, loop.wd))
        pid = control.tf([kp], [1]) + control.tf([ki], [1, 0]) + control.tf([kd, 0], [1 / wd, 1])
        pid = ss_of(pid)
        plant = control.ss(A, B[:, :1], C[1:2], D[1:2, :1])
        L = plant * delay * k * pid
        return None, L, control.feedback(L, 1)
    kp, kv, ki = (float(x) for x in (loop.kp, loop.kv, loop.ki))
    isc = ISC
    G = delay * k * ss_of(control.tf([kv, kv * ki], [1, 0]))
    if name == "double+mcm":
        peak, notch = mcm_tf()
        G = G * ss_of(notch) * ss_of(peak)
    plant = control.ss(A, B[:, :1], np.vstack([Cv[0], C[1]]), np.array([[0.0], [D[1, 0]]]))
    L_v = plant[0, 0] * isc * G
    inner_closed = control.feedback(plant * G, control.ss([], [], [], [[isc, 0.0]]))
    L_p = kp * inner_closed[1, 0]
    return L_v, L_p, control.feedback(L_p, 1)


def response(sys, w):
    return np.asarray([complex(np.squeeze(sys(1j * x))) for x in np.atleast_1d(w)])


def margin_bounds(sys, ref, mine, eval_err):
    """Tolerances on (gm, pm, sm, w_pc, w_gc, w_sm) from both sides' residuals and the
    relative disagreement ``eval_err`` of the two evaluations of L at the crossings."""
    h = 1e-6
    crossing = {
        3: lambda u: np.angle(-response(sys, np.exp(u)))[0],  # phase crossover
        4: lambda u: np.log(np.abs(response(sys, np.exp(u))))[0],  # gain crossover
    }
    tol = [0.0] * 6
    for i, f in crossing.items():
        u_ref, u_mine = np.log(ref[i]), np.log(mine[i])
        slope = (f(u_ref + h) - f(u_ref - h)) / (2 * h)
        du = (abs(f(u_ref)) + abs(f(u_mine))) / abs(slope) + 10 * EPS
        tol[i] = du
        if i == 3:  # gain margin 1/|L|: d log|L|/du
            g = lambda u: np.log(np.abs(response(sys, np.exp(u))))[0]
            tol[0] = abs((g(u_ref + h) - g(u_ref - h)) / (2 * h)) * du + eval_err + 100 * EPS
        else:  # phase margin (°): d arg L/du
            g = lambda u: np.angle(response(sys, np.exp(u)))[0]
            dphase = abs((g(u_ref + h) - g(u_ref - h)) / (2 * h)) * du + eval_err
            tol[1] = np.degrees(dphase) / abs(ref[1]) + 100 * EPS
    # modulus margin: a minimum, so the value is first-order insensitive to where it is found;
    # its location is fixed only to δu = sqrt(2 δ(m²)/|d²m²/du²|) with δ(m²) ≈ 100 ε m².
    m2 = lambda u: np.abs(1 + response(sys, np.exp(u)))[0] ** 2
    u = np.log(ref[5])
    h2 = 1e-4
    curv = abs(m2(u + h2) - 2 * m2(u) + m2(u - h2)) / h2**2
    tol[2] = eval_err * np.sqrt(m2(u) + 1) + 100 * EPS
    tol[5] = np.sqrt(2 * 100 * EPS * m2(u) / curv)
    return tol


# python-control's polynomial root finding overflows harmlessly on the delay's Padé factors
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.parametrize("name", list(LOOPS))
def test_margins_match_python_control(name, twin):
    loop = LOOPS[name]
    L_v, L_p, _ = control_loops(name, loop, twin, PADE)
    m = fdjax.loop_margins(loop, twin, FREQ, method=CONT)
    pairs = [(L_p, m.position, "outer")] + ([] if L_v is None else [(L_v, m.speed, "inner")])
    for sys, mm, which in pairs:
        ref = control.stability_margins(sys)
        w_ref = np.sort(np.asarray(ref[3:]))
        # python-control evaluates its margins on the transfer-function form (polynomials),
        # which adds its own rounding to the values
        L_ss = response(sys, w_ref)
        eval_err = np.max(np.abs(response(control.tf(sys), w_ref) / L_ss - 1)) + 100 * EPS
        mine = [float(x) for x in (mm.gain_margin, mm.phase_margin_deg, mm.modulus_margin)]
        mine += [TWO_PI * float(x) for x in
                 (mm.phase_crossover_hz, mm.gain_crossover_hz, mm.modulus_hz)]
        tol = margin_bounds(sys, ref, mine, eval_err)
        for k, (a, b, t) in enumerate(zip(mine, ref, tol)):
            assert np.isfinite(a), (name, k)
            # 4: first-order estimates; + 1e-12: the floor of python-control's polynomial
            # evaluation at the crossings (measured 7.4e-13 on the double loop's outer gain
            # margin, where the estimate gives 7e-14)
            assert abs(a / b - 1) <= 4 * t + 1e-12, (name, k, a, b, t)
            assert abs(a / b - 1) <= 1e-6, (name, k, a, b)  # the requirement


def eig_bounds(A):
    """κ(λ)·ε·‖A‖ per eigenvalue (first-order perturbation bound of a backward-stable eig)."""
    import scipy.linalg as sla

    lam, yl, xr = sla.eig(A, left=True, right=True)
    kappa = 1.0 / np.abs(np.sum(yl.conj() * xr, axis=0))
    return lam, kappa * EPS * np.linalg.norm(A, 2)


@pytest.mark.parametrize("name", list(LOOPS))
def test_closed_loop_poles_match_python_control(name, twin):
    loop = LOOPS[name]
    *_, cl_ref = control_loops(name, loop, twin, PADE)
    cl = fdjax.closed_loop(loop, twin, method=CONT)
    lam, bound = eig_bounds(np.asarray(cl.A))
    lam_ref, bound_ref = eig_bounds(cl_ref.A)
    assert lam.shape == lam_ref.shape
    np.testing.assert_allclose(np.sort(np.asarray(cl.poles()).real)[::-1],
                               np.sort(lam.real)[::-1], rtol=1e-12, atol=0)
    cost = np.abs(lam[:, None] - lam_ref[None, :])
    i, j = linear_sum_assignment(cost)
    assert np.all(cost[i, j] <= 10 * (bound[i] + bound_ref[j])), (cost[i, j], bound[i])
    assert np.all(cost[i, j] <= 1e-9 * np.abs(lam_ref[j]) + 1e-9)


def ss_response(mats, s, w):
    """C (sI − A)⁻¹ B w + D w at each s (numpy), mats = (A, B, C, D) with C, D one output row."""
    A, B, C, D = mats
    return np.array([C @ np.linalg.solve(x * np.eye(A.shape[0]) - A, B @ w(x)) + D @ w(x)
                     for x in s])


def rounding_sensitivity(fn, mats, rng, samples=4):
    """max |δy/y| when every matrix entry is perturbed by a relative ε: the error scale of any
    backward-stable evaluation of y = fn(mats)."""
    y = fn(mats)
    worst = 0.0
    for _ in range(samples):
        pert = [m * (1 + EPS * rng.uniform(-1, 1, np.shape(m))) for m in mats]
        worst = max(worst, np.max(np.abs(fn(pert) / y - 1)))
    return worst


@pytest.mark.parametrize("name", ["double+mcm", "pid"])
def test_closed_loop_tracking_frf(name, twin):
    """r → x2 of the closed-loop state space equals the loop algebra written from the plant:

    double loop: x2/r = g_x k D (G_MCM C_v (k_p + k_ffv s) + k_ffa s²) / ((1 + L_v)(1 + L_p)),
    PID:         x2/r = g_x k D (C_pid + k_ffv s + k_ffa s²) / (1 + L),
    D the Padé delay, with non-zero feed-forward gains so that every input path is checked
    (the state space has r, ṙ, r̈ as separate inputs: H_r + s H_ṙ + s² H_r̈).  Tolerance: the
    sensitivity of both sides to ε-perturbations of their matrices (the closed loop's x2 and the
    twin's x2/T1 are sums whose modal and residual parts nearly cancel at high frequency)."""
    f = np.geomspace(2.0, 3000.0, 40)
    s = 2j * np.pi * f
    num, den = control.pade(250e-6, PADE)
    D = np.polyval(num, s) / np.polyval(den, s)
    twin_mats = [np.asarray(x) for x in (twin.A, twin.B[:, 0], twin.C, twin.D[:, 0])]
    Cv = np.asarray(twin.C_velocity[0])
    if name == "pid":
        loop = PIDLoop(k_ffv=30.0, k_ffa=2.0)
        kp, ki, kd, wd = (float(x) for x in (loop.kp, loop.ki, loop.kd, loop.wd))
        k = float(SERVO.k_motor)
        C = kp + ki / s + kd * s / (1 + s / wd)

        def expected(mats):
            A, B, Cm, Dm = mats
            g_x = ss_response((A, B[:, None], Cm[1], Dm[1:2]), s, lambda x: np.ones(1))
            return g_x * k * D * (C + 30.0 * s + 2.0 * s**2) / (1 + C * k * D * g_x)
    else:
        loop = DoubleLoop(mcm=MCM, k_ffv=0.9, k_ffa=2.5)
        kp, kv, ki = (float(x) for x in (loop.kp, loop.kv, loop.ki))
        k, isc = float(SERVO.k_motor), ISC
        peak, notch = mcm_tf()
        M = response(peak, TWO_PI * f) * response(notch, TWO_PI * f)

        def expected(mats):
            A, B, Cm, Dm = mats
            g_x = ss_response((A, B[:, None], Cm[1], Dm[1:2]), s, lambda x: np.ones(1))
            g_v = ss_response((A, B[:, None], Cv, np.zeros(1)), s, lambda x: np.ones(1))
            G = M * kv * (1 + ki / s) * k * D
            L_v = G * isc * g_v
            L_p = kp * g_x * G / (1 + L_v)
            out = g_x * k * D * (M * kv * (1 + ki / s) * (kp + 0.9 * s) + 2.5 * s**2)
            return out / ((1 + L_v) * (1 + L_p))

    cl = fdjax.closed_loop(loop, twin, method=CONT)
    H = np.asarray(cl.frf(f))[:, 1]
    # the inputs (r, ṙ, r̈) are separate channels: a reference r(t) drives them as (1, s, s²)
    got = H[:, 0] + s * H[:, 1] + s**2 * H[:, 2]
    cl_mats = [np.asarray(x) for x in (cl.A, cl.B, cl.C[1], cl.D[1])]
    unit = np.eye(4)

    def closed(mats):  # column by column, then combined, as above
        return sum(c * ss_response(mats, s, lambda x, j=j: unit[j]) for j, c in
                   enumerate((1.0, s, s**2)))

    rng = np.random.default_rng(0)
    tol = 10 * (rounding_sensitivity(closed, cl_mats, rng)
                + rounding_sensitivity(expected, twin_mats, rng)) + 100 * EPS
    np.testing.assert_allclose(closed(cl_mats), got, rtol=tol)  # numpy = jax
    np.testing.assert_allclose(got, expected(twin_mats), rtol=tol)


def test_exact_delay_is_the_pade_limit(frf):
    """The Padé approximant is all-pass: the inner loop's |L_v| and gain crossover are the same
    for every order, and the phase margin moves by exactly the approximant's phase error there.
    The gain margins converge to the exact-delay ones as the order grows (on the drive's FRF)."""
    loop = LOOPS["double"]
    H = frf[-1]
    margins = lambda n: (lambda ol: (fdjax.stability_margins(FREQ, ol.speed),
                                     fdjax.stability_margins(FREQ, ol.position)))(
        fdjax.open_loop(loop, H, FREQ, method=fdjax.Continuous(n), screw_ratio=ISC))
    exact = margins(None)
    w = TWO_PI * float(exact[0].gain_crossover_hz)
    errors = []
    for n in (2, 6):
        m = margins(n)
        num, den = control.pade(SERVO.tau, n)
        pade_phase = np.angle(np.polyval(num, 1j * w) / np.polyval(den, 1j * w)
                              * np.exp(1j * w * SERVO.tau))
        np.testing.assert_allclose(m[0].gain_crossover_hz, exact[0].gain_crossover_hz, rtol=1e-13)
        # the grid interpolates the phase between samples: the difference of two phases that
        # differ by a smooth function is exact to its curvature × Δu² ≪ 1e-9 rad here
        np.testing.assert_allclose(m[0].phase_margin_deg - exact[0].phase_margin_deg,
                                   np.degrees(pade_phase), atol=1e-9)
        errors.append([abs(float(x.gain_margin) / float(y.gain_margin) - 1)
                       for x, y in zip(m, exact)])
    errors = np.array(errors)
    assert np.all(np.diff(errors, axis=0) < 0), errors
    assert np.all(errors[-1] < 1e-6), errors


def test_pade_realisation_matches_control():
    tau = 250e-6
    w = TWO_PI * np.geomspace(10.0, 2e4, 7)
    for n in (1, 3, PADE, 8):
        num, den = control.pade(tau, n)
        den = np.asarray(den, float)
        c = _pade_coefficients(n)
        np.testing.assert_allclose(c / c[0], den[::-1] / den[-1] / tau ** np.arange(n + 1),
                                   rtol=1e-13)
        sys = fdjax.pade(tau, n)
        A, B, C, D = (np.asarray(x) for x in (sys.A, sys.B, sys.C, sys.D))
        got = np.array([(C @ np.linalg.solve(1j * x * np.eye(n) - A, B) + D).item() for x in w])
        expect = np.polyval(num, 1j * w) / np.polyval(den, 1j * w)
        cond = max(np.linalg.cond(1j * x * np.eye(n) - A) for x in w)
        np.testing.assert_allclose(got, expect, rtol=100 * EPS * cond)
        np.testing.assert_allclose(np.abs(got), 1.0, rtol=100 * EPS * cond)


# ---------------------------------------------------------------- equations, transforms
def test_open_loops_follow_the_equations(frf):
    """L_v = C_v G_MCM k e^{−iωτ} i_sc iω h11 and L_p = k_p h21 C_v G_MCM k e^{−iωτ}/(1 + L_v)
    and the PID loop C_pid k e^{−iωτ} h21, written here in numpy from the drive FRF."""
    H = np.asarray(frf)
    s = 2j * np.pi * FREQ
    loop = LOOPS["double+mcm"]
    kp, kv, ki = (float(x) for x in (loop.kp, loop.kv, loop.ki))
    k, isc, tau = float(SERVO.k_motor), ISC, SERVO.tau
    peak, notch = mcm_tf()
    G = (response(peak, TWO_PI * FREQ) * response(notch, TWO_PI * FREQ) * kv * (1 + ki / s)
         * k * np.exp(-s * tau))
    L_v = G * isc * s * H[..., 0, 0]
    L_p = kp * H[..., 1, 0] * G / (1 + L_v)
    ol = fdjax.open_loop(loop, frf, FREQ, **FRF_KW)
    np.testing.assert_allclose(ol.speed, L_v, rtol=1e-12)
    np.testing.assert_allclose(ol.position, L_p, rtol=1e-12)
    pid = LOOPS["pid"]
    kp, ki, kd, wd = (float(x) for x in (pid.kp, pid.ki, pid.kd, pid.wd))
    C = kp + ki / s + kd * s / (1 + s / wd)
    ol = fdjax.open_loop(pid, frf, FREQ, **FRF_KW)
    assert ol.speed is None
    np.testing.assert_allclose(ol.position, C * k * np.exp(-s * tau) * H[..., 1, 0], rtol=1e-12)
    np.testing.assert_allclose(ol.plant_input, ol.position, rtol=1e-15)  # one loop


def test_grid_margins_converge_at_second_order(twin):
    """Margins from a sampled FRF (no model) approach the refined ones as the grid is refined
    (log-frequency interpolation: O(Δu²) per crossing)."""
    loop = LOOPS["double"]
    exact = fdjax.loop_margins(loop, twin, FREQ, method=CONT)
    err = []
    for n in (250, 4000):
        f = np.geomspace(1.0, 4000.0, n)
        # the twin's speed output has no feed-through (C_velocity): give the FRF the same θ1
        A, B, C, D, Cv = (np.asarray(x) for x in (twin.A, twin.B, twin.C, twin.D, twin.C_velocity))
        X = np.linalg.solve(2j * np.pi * f[:, None, None] * np.eye(A.shape[0]) - A, B)
        H = C @ X + D
        H[:, 0, 0] = (X[:, :, 0] @ Cv[0]) / (2j * np.pi * f)
        g = fdjax.loop_margins(loop, H, f, method=CONT, screw_ratio=ISC)
        rel = lambda a, k: abs(float(getattr(getattr(g, a), k))
                               / float(getattr(getattr(exact, a), k)) - 1)
        err.append([rel(a, "gain_crossover_hz") + rel(a, "gain_margin")
                    for a in ("speed", "position")])

    ratio = np.array(err[0]) / np.array(err[1])
    # 16× finer: 256 for an exact second-order error; the crossings' positions relative to the
    # grid points make it irregular, so ask for order ≥ 1.5 (measured: 350 and 82)
    assert np.all(ratio > 16**1.5), ratio
    assert np.all(np.array(err[1]) < 1e-5), err


def test_two_crossings_between_grid_points_are_found():
    """A resonance can carry arg L past −180° (or |L| above 1) and back between two grid
    points: the grid sees no crossing.  The model's extremum between them is refined first,
    then the two crossings beside it and the least |1 + L| near it.  Three loops in one call,
    each a Gaussian bump b(u) in log ω of width 0.004 halfway between two grid points (2 %
    steps), tilted by T(u) = tanh((u − u_c)/0.004) so that the right crossing of each pair
    (b = 1/2, (u − u_c)/0.004 = √ln 2) holds the better margin:
    0. arg(−L) = 10° − 20° b crosses zero, |L| = e^{0.3 T}/2 < 1;
    1. log|L| = −0.1 + 0.2 b crosses zero, arg L = −90° − 0.5 T rad;
    2. L = −(0.95 + 0.04 b) e^{i(0.3 − 0.35 b)}: a phase crossover pair at b = 6/7 and |1 + L|
       down to 0.016 at the bump (0.296 at every grid point).
    Measured: the crossings and margins to 1e-15, the modulus margin to 6e-15 of a 8e-12-spaced
    grid's least value around it.  The old search found neither pair nor that minimum."""
    from fdjax._control._margins import model_margins

    u = np.log(TWO_PI * np.geomspace(1.0, 4000.0, 420))
    k = np.searchsorted(u, np.log(TWO_PI * 173.0))
    u_c, width = 0.5 * (u[k - 1] + u[k]), 0.004  # halfway between two grid points
    cpx = jax.lax.complex

    def L_fn(h, w):
        x = (jnp.log(w) - u_c) / width
        b, t = h * jnp.exp(-x * x), jnp.tanh(x)
        return (0.5 * jnp.exp(cpx(0.3 * t, np.pi + np.radians(10.0) - np.radians(20.0) * b)),
                jnp.exp(cpx(-0.1 + 0.2 * b, -0.5 * np.pi - 0.5 * t)),
                -jnp.exp(cpx(jnp.log(0.95 + 0.04 * b), 0.3 - 0.35 * b)))

    margins = jax.jit(lambda h: model_margins(jnp.asarray(u), L_fn(h, jnp.exp(jnp.asarray(u))),
                                              L_fn, h))
    m0, m1, m2 = margins(1.0)
    x_r, t_r = np.sqrt(np.log(2.0)), np.tanh(np.sqrt(np.log(2.0)))
    right = np.exp(u_c + width * x_r) / TWO_PI
    np.testing.assert_allclose(float(m0.gain_margin), 2.0 * np.exp(-0.3 * t_r), rtol=1e-13)
    np.testing.assert_allclose(float(m0.phase_crossover_hz), right, rtol=1e-13)
    np.testing.assert_allclose(float(m1.phase_margin_deg), 90.0 - np.degrees(0.5 * t_r),
                               rtol=1e-13)
    np.testing.assert_allclose(float(m1.gain_crossover_hz), right, rtol=1e-13)
    assert np.isinf(float(m0.phase_margin_deg)) and np.isinf(float(m1.gain_margin))
    # loop 2: b = 6/7 at the crossings, |L| = 0.95 + 0.04·6/7 there
    np.testing.assert_allclose(float(m2.gain_margin), 1.0 / (0.95 + 0.24 / 7), rtol=1e-13)
    # the least |1 + L| on a fine grid, then on a finer one around its least point
    fine = u_c + width * np.linspace(-3.0, 3.0, 60_001)
    dist = lambda x: np.abs(1.0 + np.asarray(L_fn(1.0, jnp.exp(jnp.asarray(x)))[2]))  # noqa
    j = int(np.argmin(dist(fine)))
    least = dist(np.linspace(fine[j - 1], fine[j + 1], 100_001)).min()
    assert 0.01 < least < 0.02 and dist(u[k - 1 : k + 1]).min() > 0.29
    # (|1 + L| = 0.016 cancels 1 against 0.98: its round-off is ~60 ε relative; measured 6e-15)
    np.testing.assert_allclose(float(m2.modulus_margin), least, rtol=1e-13)
    # bumps that stay short of zero hide nothing
    m0, m1, m2 = margins(0.4)
    assert np.isinf(float(m0.gain_margin)) and np.isinf(float(m1.phase_margin_deg))


def test_grid_modulus_margin_next_to_an_unresolved_resonance():
    """The reference controller's continuous speed loop passes 0.07 from −1 at the screw's
    2.78 kHz axial mode, a resonance narrower than a 1500-point grid's spacing (12 Hz).  The
    parabola through three grid values of |1 + L|² dives below zero there, and the margin
    came out 0 although no grid point is nearer than 0.093; the estimate on the crossings'
    interpolant is 0.0775 against 0.0736 from a 10 mHz grid (measured; the dense grid has the
    coarse one's length, so that the FRF and the open loop are compiled for one shape)."""
    drive = fdjax.reference_drive()
    c = fdjax.reference_controller(drive)
    kw = {"method": EXACT, "screw_ratio": drive.screw.ratio}
    coarse, dense = np.geomspace(5.0, 3000.0, 1500), np.linspace(2770.0, 2785.0, 1500)
    H = drive.frf(0.1, coarse)
    got = fdjax.loop_margins(c, H, coarse, **kw).speed
    grid = np.abs(1 + np.asarray(fdjax.open_loop(c, H, coarse, **kw).speed))
    truth = np.abs(1 + np.asarray(fdjax.open_loop(c, drive.frf(0.1, dense), dense, **kw).speed))
    mm, least = float(got.modulus_margin[0]), float(truth.min())
    assert 0.07 < least < 0.08 and grid.min() > 0.09, (least, grid.min())
    # never above the grid's own least value, and within 10 % of the resolved one
    assert least <= mm <= grid.min() and mm < 1.1 * least, (mm, least)
    assert abs(float(got.modulus_hz[0]) - dense[truth.argmin(-1)][0]) < 12.0


def test_vmap_over_positions_equals_loop(drive, frf):
    loop = LOOPS["double"]
    opts = fdjax.TwinOptions(kept_modes=N_MODES)
    twins = [fdjax.state_space(drive, p, twin=opts) for p in POSITIONS[::3]]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *twins)
    mb = jax.vmap(lambda ss: fdjax.loop_margins(loop, ss, FREQ, method=CONT))(batch)
    for i, ss in enumerate(twins):
        m = fdjax.loop_margins(loop, ss, FREQ, method=CONT)
        for a, b in zip(jax.tree_util.tree_leaves(m), jax.tree_util.tree_leaves(mb)):
            np.testing.assert_allclose(b[i], a, rtol=1e-10)
    # a stacked StateSpace is mapped over inside
    ol = fdjax.open_loop(loop, batch, FREQ, method=CONT)
    for i, ss in enumerate(twins):
        one = fdjax.open_loop(loop, ss, FREQ, method=CONT)
        np.testing.assert_allclose(ol.position[i], one.position, rtol=1e-12)
    # FRF arrays: a batch of positions equals one position at a time
    mf = fdjax.loop_margins(loop, frf, FREQ, **FRF_KW)
    for i in (0, 6):
        ol = fdjax.open_loop(loop, frf[i], FREQ, **FRF_KW)
        for m, L in ((mf.speed, ol.speed), (mf.position, ol.position)):
            one = fdjax.stability_margins(FREQ, L)
            for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(m)):
                np.testing.assert_allclose(b[i], a, rtol=1e-12)


def test_grad_of_margins_matches_finite_differences(twin):
    """d/d(kp, kv, ki) of the margins: forward mode through the refined crossings vs central
    differences (step h = 1e-6 relative: truncation ~h², round-off ~η/h with η ~ 1e-13 the
    accuracy of a refined margin, so agreement to ~1e-6).  The outer gain margin is exactly
    proportional to 1/k_p (the phase crossover does not depend on k_p)."""
    base = LOOPS["double"]

    def margins(x):
        kp, kv, ki = x
        m = fdjax.loop_margins(DoubleLoop(kp=kp, kv=kv, ki=ki), twin, FREQ, method=CONT)
        return jnp.stack([m.position.gain_margin, m.speed.phase_margin_deg, m.speed.gain_margin,
                          m.position.phase_margin_deg, m.speed.modulus_margin])

    x0 = jnp.array([float(base.kp), float(base.kv), float(base.ki)])
    J = np.asarray(jax.jacfwd(margins)(x0))
    v0 = np.asarray(margins(x0))
    assert np.isclose(J[0, 0], -v0[0] / float(x0[0]), rtol=1e-9)
    for j in range(3):
        h = 1e-6 * float(x0[j])
        e = jnp.zeros(3).at[j].set(h)
        fd = (np.asarray(margins(x0 + e)) - np.asarray(margins(x0 - e))) / (2 * h)
        # each margin against its own scale (one atol from the largest, the phase margin's,
        # let a small margin's derivative be 3 % off); measured ≤ 3.8e-8 relative
        scale = np.abs(v0) / float(x0[j])
        assert np.all(np.abs(J[:, j] - fd) <= 1e-6 * np.abs(fd) + 1e-9 * scale), (j, J[:, j], fd)


def test_grad_of_loop_gain_wrt_mcm(frf):
    """∂|L_v(ω0)|/∂K of the peak filter: reverse mode vs the closed form d|aK + b|/dK."""
    f0 = 115.0
    k = int(np.argmin(np.abs(FREQ - f0)))

    def mag(K):
        mcm = fdjax.MCM(fdjax.PeakFilter(K, PEAK["omega"], PEAK["xi"], PEAK["phi"]))
        return jnp.abs(fdjax.open_loop(DoubleLoop(**GAINS, mcm=mcm), frf[2], FREQ,
                                       **FRF_KW).speed[k])

    g = jax.grad(mag)(0.5)
    # L_v = L0 (1 + K q): |L0 (1 + K q)|' = Re(conj(L) L0 q)/|L|
    L0 = np.asarray(fdjax.open_loop(DoubleLoop(**GAINS), frf[2], FREQ, **FRF_KW).speed[k])
    w, xi, phi = TWO_PI * FREQ[k], PEAK["xi"], PEAK["phi"]
    s, wc = 1j * w, PEAK["omega"]
    q = s * (s * np.cos(phi) + wc * np.sin(phi)) / (s * s + 2 * xi * wc * s + wc * wc)
    L = L0 * (1 + 0.5 * q)
    np.testing.assert_allclose(g, np.real(np.conj(L) * L0 * q) / np.abs(L), rtol=1e-10)


# ---------------------------------------------------------------- defaults and stability
def test_unstable_gain_is_reported_with_its_position(drive, frf):
    """The default PID loop with its gains scaled 8.8× (its gain margin is 9.0 at 0.1 m falling
    to 8.6 at 0.7 m): unstable towards the screw end only.  Nyquist (gain margin < 1) and the
    poles agree, and the result names the position."""
    loop = PIDLoop(kp=8.8 * 1.5e3, ki=8.8 * 5.0e3, kd=8.8 * 100.0)
    m = fdjax.loop_margins(loop, frf, FREQ, **FRF_KW)
    st = fdjax.check_stability(loop, drive, position_m=POSITIONS, method=EXACT)
    unstable_poles = ~np.asarray(st.stable)
    assert unstable_poles[-1] and not unstable_poles[0]
    np.testing.assert_array_equal(unstable_poles, np.asarray(m.position.gain_margin) < 1)
    assert "closed loop unstable at table position 0.7 m" in st.message
    one = fdjax.check_stability(loop, fdjax.state_space(drive, 0.7), method=EXACT)  # the twin
    assert not bool(one.stable) and float(one.growth_rate) > 0
    np.testing.assert_allclose(one.poles, st.poles[-1], rtol=1e-10)
    with pytest.raises(RuntimeError, match="unstable at table position 0.7 m"):
        fdjax.check_stability(loop, drive, position_m=0.7, method=EXACT, throw=True)


class _SpeedOnly(fdjax.AbstractController):
    """u = −k_v v_m: a speed loop and nothing on the table position."""

    kv: jax.Array

    def law(self, position_m):
        return fdjax.Law((fdjax.Path({"v_m": -self.kv}),))


def test_a_loop_without_position_feedback_is_marginally_stable_by_both_models():
    """Without a position loop the table position keeps a pole at s = 0: the sampled loop's
    eigenvalue came out at z = 1 − 1.4e-14 (stable, decaying at 1.1e-10 1/s), the continuous
    one's at s = 0 exactly (unstable, damping NaN).  Both now give growth 0, damping 0 and
    'marginally stable'; the loop's other poles are all stable (the speed loop's gain margin is
    2.5), and gain_headroom says it has none to measure.  The reference drive."""
    drive = fdjax.reference_drive()
    ctl = _SpeedOnly(jnp.asarray(150.0))
    for method in (fdjax.SampledData(), fdjax.Continuous()):
        st = fdjax.check_stability(ctl, drive, position_m=0.4, method=method)
        assert not bool(st.stable)
        assert (float(st.growth_rate), float(st.min_damping)) == (0.0, 0.0)
        assert st.message == ("closed loop marginally stable at table position 0.4 m: a pole at "
                              "0 Hz neither decays nor grows, a state no feedback acts on (such "
                              "as the table position of a controller without a position loop)")
        # every other pole decays (the slowest at -20.2 and -27.8 1/s)
        s = np.asarray(method.poles_to_s(st.poles[1:], fdjax.Servo()))
        assert np.all(s.real[np.isfinite(s)] < -15.0)
        with pytest.raises(ValueError, match=r"`gain_headroom\(controller=\.\.\.\)`: closed "
                                             r"loop marginally stable .* no gain headroom"):
            fdjax.gain_headroom(ctl, drive, position_m=0.4, method=method)
    # a PID on the scale keeps its slow pole (-3.24 1/s) off s = 0: stable, as before; with a
    # five-thousandth of that integral gain its slowest pole is at -6.67e-4 1/s, stable by both
    # models alike (a threshold relative to the largest |s| had called the sampled one
    # marginal: a dead-beat pole's s = ln(1e-300)/T set the scale)
    pid = fdjax.check_stability(PIDLoop(kp=1.5e3, ki=5.0e3, kd=100.0), drive, position_m=0.4)
    assert bool(pid.stable) and float(pid.growth_rate) == pytest.approx(-3.239, rel=1e-3)
    for method in (fdjax.SampledData(), fdjax.Continuous()):
        slow = fdjax.check_stability(PIDLoop(ki=1.0), drive, position_m=0.4, method=method)
        assert bool(slow.stable), method
        assert float(slow.growth_rate) == pytest.approx(-6.67e-4, rel=2e-3), method


def test_default_acceleration_feedforward_is_the_rigid_body_inertia():
    """k_ffa = J_eq/(k_motor i_sc), J_eq = rᵀMr for the rigid-body mode r of the FE model of
    the reference drive (the default's)."""
    drive = fdjax.reference_drive()
    fe = fdjax.fe_matrices(drive, 0.4)
    n = fdjax.DEFAULT_ELEMENTS
    r = np.zeros(fe.mass.shape[0])
    r[: n + 2] = 1.0  # motor and every screw rotation node
    r[2 * n + 3] = float(drive.screw.ratio)  # the carriage follows at i_sc
    J_eq = r @ np.asarray(fe.mass) @ r
    loop = DoubleLoop()
    isc = float(drive.screw.ratio)
    # the default's inertia is quoted to 6 digits (1.30769e-2): half a unit in the last, 3.8e-6
    np.testing.assert_allclose(float(loop.k_ffa), J_eq / (float(SERVO.k_motor) * isc), rtol=4e-6)


# ---------------------------------------------------------------- errors
@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: DoubleLoop(kp=-1.0),
         r"`DoubleLoop\(kp=\.\.\.\)` must be finite and positive, got -1"),
        (lambda: DoubleLoop(kv=0.0),
         r"`DoubleLoop\(kv=\.\.\.\)` must be finite and positive, got 0"),
        (lambda: fdjax.Servo(k_motor=np.nan), r"`Servo\(k_motor=\.\.\.\)` must be finite and pos"),
        (lambda: fdjax.Servo(delay_samples=0),
         r"`Servo\(delay_samples=\.\.\.\)` must be an integer"),
        (lambda: fdjax.Servo(period=1.25e-1 * 10), r"`Servo\(period=\.\.\.\)` must be a number"),
        (lambda: fdjax.Continuous(pade_order=0),
         r"`Continuous\(pade_order=\.\.\.\)` must be an integer"),
        (lambda: DoubleLoop(k_ffa=np.inf), r"`DoubleLoop\(k_ffa=\.\.\.\)` must be finite"),
        (lambda: DoubleLoop(ki=[1.0, 2.0]), r"`DoubleLoop\(ki=\.\.\.\)` must be a real scalar"),
        (lambda: PIDLoop(wd=-5.0), r"`PIDLoop\(wd=\.\.\.\)` must be finite and positive, got -5"),
        (lambda: fdjax.pade(250e-6, 0),
         r"`pade\(order=\.\.\.\)` must be an integer between 1 and 16, got 0"),
        (lambda: fdjax.pade(-1e-4, 3), r"`pade\(tau=\.\.\.\)` must be finite and positive"),
        # named for pade, not for the LTI it builds; a delay in µs given as seconds
        (lambda: fdjax.pade([1e-3, 2e-3], 2), r"`pade\(tau=\.\.\.\)` must be a real scalar"),
        (lambda: fdjax.pade(250.0, 2), r"`pade\(tau=\.\.\.\)` must be a delay in seconds of at "
                                       r"most 1 s, got 250: in µs\? 250 µs is 0\.00025 s"),
        # a law without paths (open_loop had answered L = 0), or with something else in them
        (lambda: fdjax.Law(()), r"`Law\(paths=\.\.\.\)` must be a non-empty tuple of "
                                r"fdjax\.Path .* got tuple of 0"),
        (lambda: fdjax.Law((fdjax.Path({"r": 1.0}), 3)), r"got tuple of 2: Path, int"),
        # a filter the servo cannot sample, named for the function called (it named
        # MCM.discretize)
        (lambda: fdjax.to_python_control(DoubleLoop(mcm=fdjax.MCM(None, fdjax.NotchFilter(
            2 * np.pi * 4500, 0.05, 0.5)))),
         r"`to_python_control\(controller=\.\.\.\)` cannot be run by the servo \(period "
         r"0\.000125 s, Nyquist frequency 4000 Hz\): .*up to 4500 Hz"),
    ],
)
def test_bad_parameters(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_a_field_that_is_not_a_number_is_named():
    """The fields checked in their converters name themselves (k_motor gave NumPy's "could not
    convert string to float"); a boolean is not a number of 1 (a Rod of length True had been
    1 m, pade(True) a delay of 1 s); pade's bound on the delay holds under jit too."""
    with pytest.raises(TypeError, match=r"`Servo\(k_motor=\.\.\.\)` must be a number or an "
                                        r"array of numbers, got 'a'"):
        fdjax.Servo(k_motor="a")
    with pytest.raises(ValueError, match=r"`Servo\(k_motor=\.\.\.\)` must be a number, got "
                                         r"booleans"):
        fdjax.Servo(k_motor=True)
    with pytest.raises(ValueError, match=r"`pade\(tau=\.\.\.\)` must be a real scalar, got bool"):
        fdjax.pade(True, 2)
    with pytest.raises(CHECK_FAILED, match=r"`pade\(tau=\.\.\.\)` must be a delay in seconds of "
                                           r"at most 1 s"):
        jax.block_until_ready(jax.jit(lambda t: fdjax.pade(t, 2).A)(250.0))


def test_bad_analysis_inputs(drive, frf):
    loop = LOOPS["double"]
    with pytest.raises(ValueError, match=r"`loop_margins\(plant=\.\.\.\)` must be a BallScrewDrive "
                                         r"\(with position_m\), a StateSpace, or an FRF array of "
                                         r"shape \(\.\.\., n_freq, 3, 2\) with n_freq = 2000"):
        fdjax.loop_margins(loop, frf[:, :10], FREQ, **FRF_KW)
    with pytest.raises(ValueError, match=r"`Continuous\(pade_order=\.\.\.\)` must be an integer"):
        fdjax.Continuous(pade_order=2.0)
    with pytest.raises(ValueError, match=r"`loop_margins\(freq_hz=\.\.\.\)` must be strictly"):
        fdjax.loop_margins(loop, frf, FREQ[::-1], **FRF_KW)
    with pytest.raises(ValueError, match=r"`open_loop\(plant=\.\.\.\)` must be finite"):
        fdjax.open_loop(loop, frf.at[0, 5, 1, 0].set(jnp.nan), FREQ, **FRF_KW)
    with pytest.raises(ValueError, match=r"`open_loop\(screw_ratio=\.\.\.\)` is required"):
        fdjax.open_loop(loop, frf, FREQ, method=EXACT)
    with pytest.raises(ValueError,
                       match=r"`open_loop\(method=\.\.\.\)`: the sampled loop needs the plant"):
        fdjax.open_loop(loop, frf, FREQ, screw_ratio=ISC)
    with pytest.raises(ValueError, match=r"`loop_margins\(freq_hz=\.\.\.\)` must be below the "
                                         r"servo's Nyquist frequency 4000 Hz"):
        fdjax.loop_margins(loop, drive, FREQ, position_m=0.4)
    with pytest.raises(ValueError, match=r"`open_loop\(position_m=\.\.\.\)` is required"):
        fdjax.open_loop(loop, drive, FREQ, method=EXACT)
    with pytest.raises(ValueError, match=r"`check_stability\(position_m=\.\.\.\)` is required"):
        fdjax.check_stability(loop, drive)
    with pytest.raises(ValueError, match=r"`check_stability\(position_m=\.\.\.\)` must be inside "
                                         r"the travel \[0.1, 0.7\] m, got 0.9"):
        fdjax.check_stability(loop, drive, position_m=0.9)
    with pytest.raises(TypeError, match=r"`check_stability\(controller=\.\.\.\)` must be an fdjax "
                                        r"controller"):
        fdjax.check_stability(fdjax.MCM(), drive, position_m=0.3)
    with pytest.raises(TypeError, match=r"`DoubleLoop\(mcm=\.\.\.\)` must be an fdjax.MCM"):
        DoubleLoop(mcm="notch")
    with pytest.raises(ValueError, match=r"`stability_margins\(L=\.\.\.\)` must have shape"):
        fdjax.stability_margins(FREQ, np.ones(5, complex))


def test_bad_gain_under_jit_raises():
    build = eqx.filter_jit(lambda kp: DoubleLoop(kp=kp).kp)
    with pytest.raises(CHECK_FAILED,
                       match=r"DoubleLoop\(kp=\.\.\.\)` must be finite and positive"):
        jax.block_until_ready(build(jnp.asarray(-3.0)))


# ---------------------------------------------------------------- figure
def test_fig14_peak_filter_effect(frf, tmp_path):
    from fdjax.plots import plot_peak_filter_effect

    with_pf = fdjax.open_loop(LOOPS["double+mcm"], frf, FREQ, **FRF_KW)
    without = fdjax.open_loop(LOOPS["double"], frf, FREQ, **FRF_KW)
    fig = plot_peak_filter_effect(FREQ, POSITIONS, without.speed, with_pf.speed,
                                  band_hz=(100.0, 145.0))
    assert len(fig.axes) == 4
    fig.savefig(tmp_path / "fig14.png", dpi=60)
    assert (tmp_path / "fig14.png").stat().st_size > 10_000
