"""The control architecture: one law per controller, from which every path follows.

A controller defined only here (a lead-compensated position loop) runs through the open loops,
the continuous and sampled margins, the closed loops, the stability check and both simulations,
under ``jit``, ``vmap`` and ``grad``.  The sampled margins of the double loop are checked against
python-control's ``stability_margins`` of the same discrete loop built from python-control's own
pieces (``sample_system`` ZOH plant, Tustin PI and filter sections, z^-d, backward difference).
The servo's hardware is apart from the tunable leaves; compiled entry points trace once.
"""

import control
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.signal as sig
from jit_errors import CHECK_FAILED
from scipy.optimize import linear_sum_assignment
from table1 import table1_loop  # the Table 1 drive's hand-set double loop

import fdjax
from fdjax import _analysis
from fdjax._simulation import _simulate

EPS = np.finfo(np.float64).eps
TWO_PI = 2 * np.pi
SERVO = fdjax.Servo()  # 8 kHz, d = 2
T = SERVO.period
N_MODES = 4  # a reduced twin: python-control's polynomial margins are exact at this order
TWIN4 = fdjax.TwinOptions(kept_modes=N_MODES)
TWIN6, TWIN8 = fdjax.TwinOptions(kept_modes=6), fdjax.TwinOptions(kept_modes=8)
PADE = 4
FREQ_C = np.geomspace(1.0, 4000.0, 2000)
FREQ_D = np.geomspace(1.0, 0.999 / (2 * T), 2000)  # below Nyquist


class Lead(fdjax.AbstractBlock):
    r"""k (1 + s/ω_z)/(1 + s/ω_p) = k (ω_p/ω_z)(1 + (ω_z − ω_p)/(s + ω_p))."""

    k: jax.Array
    wz: jax.Array
    wp: jax.Array

    def continuous(self):
        r = self.wp / self.wz
        return fdjax.LTI(
            -self.wp.reshape(1, 1), jnp.ones((1, 1)),
            (self.k * r * (self.wz - self.wp)).reshape(1, 1), (self.k * r).reshape(1, 1),
        )


class LeadLoop(fdjax.AbstractController):
    """u = Lead(s)(r − x2) + k_ffv ṙ: a position loop on the scale with a lead filter."""

    log_k: jax.Array
    log_wz: jax.Array
    log_wp: jax.Array
    k_ffv: jax.Array

    def law(self, position_m):
        lead = Lead(jnp.exp(self.log_k), jnp.exp(self.log_wz), jnp.exp(self.log_wp))
        one = jnp.ones(())
        return fdjax.Law((fdjax.Path({"r": one, "x2": -one}, (lead,)),
                          fdjax.Path({"r_dot": self.k_ffv})))


def lead_loop(k=1.7e4, fc=10.0, k_ffv=0.0):
    w = TWO_PI * fc
    return LeadLoop(jnp.log(jnp.asarray(k)), jnp.log(jnp.asarray(w / 3)),
                    jnp.log(jnp.asarray(3 * w)), jnp.asarray(k_ffv))


def lead_tf(ctl):
    k, wz, wp = (float(jnp.exp(x)) for x in (ctl.log_k, ctl.log_wz, ctl.log_wp))
    return control.tf([k / wz, k], [1 / wp, 1])


@pytest.fixture(scope="module")
def drive():
    return fdjax.table1_drive()


@pytest.fixture(scope="module")
def twin(drive):
    return fdjax.state_space(drive, 0.4, twin=TWIN4)


def plant_ss(twin, rows=(1,)):
    A, B, C, D = (np.asarray(x) for x in (twin.A, twin.B, twin.C, twin.D))
    return control.ss(A, B[:, :1], C[list(rows)], D[list(rows), :1])


def delay_d(d=SERVO.delay_samples):
    return control.tf([1.0], [1.0] + [0.0] * d, T)


def margins_of(m):
    return [float(m.gain_margin), float(m.phase_margin_deg), float(m.modulus_margin),
            TWO_PI * float(m.phase_crossover_hz), TWO_PI * float(m.gain_crossover_hz),
            TWO_PI * float(m.modulus_hz)]


def control_margins(sys):
    """python-control's margins of ``sys``.  For a discrete loop its polynomial method is
    unreliable here (the rigid body and the PI put poles at z = 1; it reports spurious crossings
    near 1 rad/s with a gain margin of 1.03 where the loop's |L| is 1e4), so its FRD method is
    used on its own response of the same discrete system, 20 000 points below Nyquist with
    smooth interpolation (measured agreement with the model-refined margins: 1e-13)."""
    if sys.isdtime(strict=True):
        omega = np.geomspace(TWO_PI * FREQ_D[0], TWO_PI * FREQ_D[-1], 20000)
        sys = control.frd(sys, omega, smooth=True)
    return control.stability_margins(sys)


def assert_margins(mine, sys, rtol, rtol_modulus_freq):
    ref = control_margins(sys)
    got = margins_of(mine)
    np.testing.assert_allclose(got[:5], ref[:5], rtol=rtol)
    # the modulus margin is a minimum: its value is second-order, its place first-order
    # sensitive to where it is found
    np.testing.assert_allclose(got[5], ref[5], rtol=rtol_modulus_freq)


# ---------------------------------------------------------------- a controller defined here
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_new_controller_runs_every_path(drive, twin):
    ctl = lead_loop()
    k_m, tau = float(SERVO.k_motor), SERVO.tau
    # open loop from the exact FRF, by the equations
    H = np.asarray(drive.frf(0.4, FREQ_C))[0]
    s = 2j * np.pi * FREQ_C
    ol = fdjax.open_loop(ctl, drive.frf(0.4, FREQ_C)[0], FREQ_C, method=fdjax.Continuous(),
                         screw_ratio=drive.screw.ratio)
    L = np.asarray([complex(np.squeeze(lead_tf(ctl)(x))) for x in s]) * k_m * np.exp(-s * tau)
    np.testing.assert_allclose(ol.position, L * H[:, 1, 0], rtol=1e-12)
    assert ol.speed is None
    np.testing.assert_allclose(ol.plant_input, ol.position, rtol=1e-15)
    # continuous margins (Padé delay) against python-control
    L_c = plant_ss(twin) * control.ss(control.tf(*control.pade(tau, PADE))) * k_m * control.ss(
        lead_tf(ctl))
    m = fdjax.loop_margins(ctl, twin, FREQ_C, method=fdjax.Continuous(PADE))
    assert m.speed is None
    assert_margins(m.position, L_c, 1e-9, 1e-6)
    # sampled margins against python-control's discrete loop from its own pieces; from the
    # drive at the twin's position (the same twin, built in the program): the program
    # test_new_controller_under_jit_vmap_grad and test_one_compilation_for_new_positions run
    # too, compiled once (the sampled margins on a given twin: test_sampled_margins_*)
    L_d = (control.sample_system(plant_ss(twin), T, "zoh") * delay_d() * k_m
           * control.sample_system(lead_tf(ctl), T, "tustin"))
    md = fdjax.loop_margins(ctl, drive, FREQ_D, position_m=0.4, twin=TWIN4)
    assert_margins(md.position, L_d, 1e-9, 1e-6)
    # closed loops: poles against python-control's feedback (from the drive, as test_one_
    # compilation_for_new_positions builds the sampled one)
    for method, ref in ((fdjax.Continuous(PADE), control.feedback(L_c, 1)),
                        (fdjax.SampledData(), control.feedback(L_d, 1))):
        cl = fdjax.closed_loop(ctl, drive, method=method, position_m=0.4, twin=TWIN4)
        assert (cl.dt is None) == isinstance(method, fdjax.Continuous)
        lam, lam_ref = np.linalg.eigvals(np.asarray(cl.A)), control.poles(ref)
        # as many poles as python-control's loop, and the sampled loop's one more (below)
        assert lam.size == lam_ref.size + isinstance(method, fdjax.SampledData)
        cost = np.abs(lam[:, None] - lam_ref[None, :])
        i, j = linear_sum_assignment(cost)
        # measured 3.1e-12 (continuous) and 2.2e-13 (sampled) relative
        assert np.all(cost[i, j] <= 1e-10 * np.maximum(np.abs(lam_ref[j]), 1.0)), cost[i, j]
        # the sampled loop keeps the previous encoder angle, unread by this law: a pole at 0
        extra = np.delete(lam, i)
        assert np.all(np.abs(extra) < 1e-12), extra
    for y in (0.1, 0.4, 0.7):  # one position per call, as test_one_compilation_... checks it
        st = fdjax.check_stability(ctl, drive, position_m=y)
        assert bool(st.stable), st.message
    # both simulations against python-control / SciPy runs of the same closed loops (from the
    # drive at the twin's position, as test_new_controller_under_jit_vmap_grad runs them: the
    # same compiled programs)
    ref = fdjax.reciprocating(stroke=2e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    sim = fdjax.simulate(ctl, drive, ref, position_m=0.4, twin=TWIN4)
    r = np.asarray(sim.reference[:, 0])
    y = control.forced_response(control.feedback(L_d, 1), U=r).outputs
    # measured 5.5e-15 of the stroke
    np.testing.assert_allclose(sim.x2, y, rtol=0, atol=1e-13 * np.max(np.abs(r)))
    # the continuous closed loop: r → x2 as python-control's feedback of the same loop
    # (python-control's tf2ss of the Padé factors, then lsim without balancing, lose ~1e-6 in
    # the time domain, so the transfer functions are compared, and the run against lsim of the
    # loop's own matrices)
    cl = fdjax.closed_loop(ctl, drive, method=fdjax.Continuous(PADE), position_m=0.4, twin=TWIN4)
    f = np.geomspace(1.0, 2000.0, 25)
    ref_tf = control.feedback(L_c, 1)
    want = np.array([complex(np.squeeze(ref_tf(2j * np.pi * x))) for x in f])
    np.testing.assert_allclose(np.asarray(cl.frf(f))[:, 1, 0], want, rtol=1e-9, atol=1e-15)
    ode = fdjax.simulate(ctl, drive, ref, fdjax.PadeODE(pade_order=PADE), position_m=0.4,
                         twin=TWIN4)
    r_c = np.asarray(ode.reference[:, 0])
    W = np.stack([r_c, *np.asarray(ode.reference[:, 1:]).T, np.zeros_like(r_c)], 1)
    _, y_c, _ = sig.lsim(tuple(np.asarray(x) for x in (cl.A, cl.B, cl.C, cl.D)), W,
                         np.asarray(ode.t))
    # measured 6.8e-13 of the stroke (5.0e-13 at dt = 5e-5 s; the ODE solver's tolerances)
    np.testing.assert_allclose(ode.x2, y_c[:, 1], rtol=0, atol=1e-11 * np.max(np.abs(r)))


def test_new_controller_under_jit_vmap_grad(drive):
    ctl = lead_loop(k_ffv=5.0)
    ref = fdjax.reciprocating(stroke=2e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    pos = jnp.array([0.15, 0.4, 0.65])

    def rms(c, p, method=fdjax.SampledData()):
        return fdjax.simulate(c, drive, ref, method, position_m=p, twin=TWIN4,
                              throw=False).rms_error()

    eager = np.array([float(rms(ctl, p)) for p in pos])
    np.testing.assert_allclose(jax.jit(jax.vmap(rms, (None, 0)))(ctl, pos), eager, rtol=1e-12)
    # margins over positions under vmap equal one at a time (the reduced twin, one position
    # per call: the program of test_new_controller_runs_every_path's sampled margins)
    mv = jax.vmap(lambda p: fdjax.loop_margins(ctl, fdjax.state_space(drive, p, twin=TWIN4),
                                               FREQ_D).position.phase_margin_deg)(pos)
    one = [float(fdjax.loop_margins(ctl, drive, FREQ_D, position_m=p,
                                    twin=TWIN4).position.phase_margin_deg) for p in pos]
    np.testing.assert_allclose(mv, one, rtol=1e-10)
    # grad through the sampled simulation against central differences (in log k: h = 1e-5)
    g = eqx.filter_grad(lambda c: rms(c, 0.4))(ctl)
    h = 1e-5
    bump = lambda d: eqx.tree_at(lambda c: c.log_k, ctl, ctl.log_k + d)
    fd = (rms(bump(h), 0.4) - rms(bump(-h), 0.4)) / (2 * h)
    # central differences: truncation h²·f'''/6 and round-off ε/h, both near 1e-10 here
    # (measured 5.7e-10; 2.7e-10 with 8 kept modes)
    np.testing.assert_allclose(g.log_k, fd, rtol=1e-8)
    # and through the Padé ODE (diffrax's adjoint through the user's block), in log k and in
    # the block's pole (measured 2.6e-8 and 1.3e-7 against central differences at h = 1e-5)
    pade = fdjax.PadeODE(pade_order=PADE)
    gp = eqx.filter_grad(lambda c: rms(c, 0.4, pade))(ctl)
    for get in (lambda c: c.log_k, lambda c: c.log_wp):
        move = lambda d, get=get: eqx.tree_at(get, ctl, get(ctl) + d)  # noqa: E731
        fd = (rms(move(h), 0.4, pade) - rms(move(-h), 0.4, pade)) / (2 * h)
        np.testing.assert_allclose(get(gp), fd, rtol=1e-6)


# ---------------------------------------------------------------- sampled margins
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.parametrize("which", ["lead", "mcm"])
def test_sampled_law_response_is_its_realisation(which):
    """The open loops read the sampled law's response block by block (a filter's sections in
    closed form, a user's block from its own realisation); the closed loop runs the realisation
    assembled from the same discrete blocks.  Both are one law."""
    if which == "lead":
        law = lead_loop().law(0.4)
    else:
        mcm = fdjax.MCM(fdjax.PeakFilter(0.5, TWO_PI * 115.0, 0.5, np.radians(-75.0)),
                        fdjax.NotchFilter(TWO_PI * 1190.0, 0.05, 0.5))
        law = table1_loop(mcm=mcm).law(0.4)
    sampled = law.discretised(T, "fitted")
    z = jnp.asarray(np.exp(2j * np.pi * FREQ_D * T))
    K = sampled.transfer(z)
    R = sampled.realisation()
    want = np.asarray(R.transfer(z))[:, 0, :]
    # the realisation solved per frequency against the factors' product: round-off (measured
    # 2.4e-14 entry by entry, 4e-15 of the largest entry; the integrators make |K| ~1e6 at 1 Hz)
    np.testing.assert_allclose(np.asarray(K), want, rtol=1e-13, atol=1e-14 * np.abs(want).max())
    assert R.dt == pytest.approx(T)


@pytest.mark.parametrize("with_mcm", [False, True])
def test_sampled_margins_match_python_control(twin, with_mcm):
    """The double loop as it runs at 8 kHz, built from python-control's pieces, broken at the
    speed feedback, at the scale and at the plant input."""
    peak = fdjax.PeakFilter(0.5, TWO_PI * 115.0, 0.5, np.radians(-75.0))
    notch = fdjax.NotchFilter(TWO_PI * 1190.0, 0.05, 0.5)
    mcm = fdjax.MCM(peak, notch) if with_mcm else fdjax.MCM()
    loop = table1_loop(mcm=mcm)
    kp, kv, ki = (float(x) for x in (loop.kp, loop.kv, loop.ki))
    k_m, isc = float(SERVO.k_motor), float(twin.screw_ratio)
    # every piece as a state space: python-control's products of transfer functions lose the
    # loop near z = 1 (the rigid body's and the PI's poles) to polynomial round-off
    ss, sample = control.ss, control.sample_system
    plant = sample(plant_ss(twin, rows=(0, 1)), T, "zoh")  # (θ1, x2)
    G = ss(delay_d()) * k_m * ss(sample(control.tf([kv, kv * ki], [1, 0]), T, "tustin"))
    if with_mcm:
        def section(num, den, w0):
            return ss(sample(control.tf(num, den), T, "tustin", prewarp_frequency=w0))

        K, w, xi, phi = 0.5, TWO_PI * 115.0, 0.5, np.radians(-75.0)
        den = [1.0, 2 * xi * w, w * w]
        G = G * (1 + section([K * np.cos(phi), K * w * np.sin(phi), 0.0], den, w))
        w, zn, zd = TWO_PI * 1190.0, 0.05, 0.5
        G = G * section([1.0, 2 * zn * w, w * w], [1.0, 2 * zd * w, w * w], w)
    bd = ss(control.tf([1.0, -1.0], [1.0, 0.0], T)) * (isc / T)  # backward-difference speed
    L_v = bd * plant[0, 0] * G
    inner = control.feedback(G * plant, bd * ss([], [], [], [[1.0, 0.0]], T))  # v_cmd → (θ1, x2)
    L_p = kp * inner[1, 0]
    L_u = G * (kp * plant[1, 0] + bd * plant[0, 0])
    m = fdjax.loop_margins(loop, twin, FREQ_D, method=fdjax.SampledData("tustin"))
    for mine, ref in ((m.speed, L_v), (m.position, L_p), (m.plant_input, L_u)):
        assert_margins(mine, ref, 1e-9, 1e-6)
    # the continuous-time margins of the same loop are optimistic: they leave out the ZOH, the
    # backward difference and the discretised filters
    mc = fdjax.loop_margins(loop, twin, FREQ_C, method=fdjax.Continuous())
    assert float(mc.speed.gain_margin_db) > float(m.speed.gain_margin_db) + 1.0


# ---------------------------------------------------------------- hardware apart from tunables
def test_gradients_touch_only_the_tunables(drive):
    loop = fdjax.DoubleLoop(mcm=fdjax.MCM(fdjax.PeakFilter(0.3, TWO_PI * 120.0, 0.15, 0.4)))
    ref = fdjax.reciprocating(stroke=2e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    loss = lambda c: fdjax.simulate(c, drive, ref, position_m=0.3, twin=TWIN8).rms_error()
    g = eqx.filter_grad(loss)(loop)
    names = {jax.tree_util.keystr(k) for k, _ in jax.tree_util.tree_leaves_with_path(g)}
    assert names == {".log_kp", ".log_kv", ".log_ki", ".k_ffv", ".k_ffa", ".mcm.peak.K",
                     ".mcm.peak.log_omega", ".mcm.peak.log_xi", ".mcm.peak.phi"}, names
    assert all(np.isfinite(x) for x in jax.tree_util.tree_leaves(g))
    opt = optax.adam(1e-2)
    with jax.numpy_dtype_promotion("standard"):  # optax's step count is int32
        state = opt.init(eqx.filter(loop, eqx.is_array))
        updates, _ = opt.update(g, state)
    stepped = eqx.apply_updates(loop, updates)
    assert float(stepped.kv) != float(loop.kv)


# ---------------------------------------------------------------- one compilation
def _traces(fn):
    return eqx.debug.get_num_traces(fn)


def test_one_compilation_for_new_positions(drive):
    # the lead loop's programs as test_new_controller_runs_every_path compiles them (once for
    # the file)
    loop = lead_loop()
    ref = fdjax.reciprocating(stroke=2e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    cases = [
        (_simulate._simulate_traced,
         lambda p: fdjax.simulate(loop, drive, ref, position_m=p, twin=TWIN4)),
        (_analysis._loop_margins_traced,
         lambda p: fdjax.loop_margins(loop, drive, FREQ_D, position_m=p, twin=TWIN4)),
        (_analysis._closed_loop_traced,
         lambda p: fdjax.closed_loop(loop, drive, position_m=p, twin=TWIN4)),
        (_analysis._stability_traced,
         lambda p: fdjax.check_stability(loop, drive, position_m=p)),
    ]
    for traced, call in cases:
        call(0.2)
        before = _traces(traced)
        for p in (0.25, 0.3, jnp.asarray(0.35), 0.5, 0.6):  # Python floats and arrays
            jax.block_until_ready(call(p))
        assert _traces(traced) == before, traced


# ---------------------------------------------------------------- failures under jit and vmap
def test_failures_carry_their_message_under_jit_and_vmap(drive):
    # the default PID (gain margin ≈ 9 over the travel) with every gain × 15: unstable.  Every
    # run below uses a PID of the same structure and the same reference, so that each mode
    # (eager, jit, vmap, moving) compiles once.
    hot = fdjax.PIDLoop(kp=15 * 1.5e3, ki=15 * 5.0e3, kd=15 * 100.0)
    fine = fdjax.PIDLoop()
    ref = fdjax.reciprocating(stroke=2e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    sim = lambda c, p, **kw: fdjax.simulate(c, drive, ref, position_m=p, twin=TWIN6, **kw)
    with pytest.raises(RuntimeError, match=r"closed loop unstable at table position 0.3 m: pole "
                                           r"at [0-9.]+ Hz growing at"):
        sim(hot, 0.3)
    # a reference that leaves the travel (2 mm from 0.699 m): eager names the position reached
    with pytest.raises(ValueError, match=r"from table position 0.699 m reaches 0.701 m, outside "
                                         r"the travel \[0.1, 0.7\] m"):
        sim(fine, 0.699)
    jitted = jax.jit(lambda c, p: sim(c, p).x2)
    with pytest.raises(CHECK_FAILED, match="the closed loop is unstable"):
        jax.block_until_ready(jitted(hot, 0.3))
    with pytest.raises(CHECK_FAILED, match="the reference motion takes the table outside"):
        jax.block_until_ready(jitted(fine, 0.699))
    # a start position outside the travel, under jit
    with pytest.raises(CHECK_FAILED,
                       match=r"`simulate\(position_m=\.\.\.\)` must be inside the travel"):
        jax.block_until_ready(jitted(fine, 0.9))
    res = jax.vmap(lambda p: sim(hot, p, throw=False).result._value)(jnp.array([0.2, 0.3]))
    assert np.all(np.asarray(res) == fdjax.RESULTS.unstable._value)
    with pytest.raises(CHECK_FAILED, match="the reference motion takes the table outside"):
        jax.block_until_ready(jax.jit(jax.vmap(
            lambda p: sim(fine, p, moving=True).x2))(jnp.array([0.3, 0.699])))
    # check_stability with throw under jit
    with pytest.raises(CHECK_FAILED, match="the closed loop is unstable"):
        jax.block_until_ready(jax.jit(
            lambda p: fdjax.check_stability(hot, drive, position_m=p, twin=TWIN6,
                                            throw=True).growth_rate)(0.3))


def test_result_pytree_is_the_same_eager_and_jitted(drive):
    # (the eager run: the program of the tests above)
    ref = fdjax.reciprocating(stroke=2e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    run = lambda p: fdjax.simulate(lead_loop(), drive, ref, position_m=p, twin=TWIN4)
    a, b = run(0.3), jax.jit(run)(0.3)
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    # the same program, fused into the caller's: round-off of the recursion (measured 0 with
    # this loop; 1.2e-14 absolute on a 1e-2 signal with the Table 1 double loop)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-11 * np.max(np.abs(y)))
