"""Closed-loop time simulation: sampled-data scan and diffrax ODE against independent oracles.

Oracles: a per-sample NumPy/SciPy implementation of the sampled loop (``cont2discrete`` ZOH,
``sosfilt`` sections, a shift register), ``control.forced_response`` on the discrete loop,
``scipy.signal.lsim`` on the continuous Padé loop, central differences for gradients.
"""

import control
import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal as sig
from table1 import table1_loop  # the Table 1 drive's hand-set double loop

import fdjax
from fdjax._trajectory import jerk_limited, reciprocating

POS = 0.115
DT = 5.0e-5  # 20 kHz: τ = 250 µs is 5 samples
SERVO = fdjax.Servo(period=DT, delay_samples=5)
Y_END = 0.698  # near the screw end: the 2 mm stroke of `reference` stays inside the travel
PADE6 = fdjax.Continuous(6)
TWIN8 = fdjax.TwinOptions(kept_modes=8)  # a reduced twin (the moving table rebuilds it per step)


@pytest.fixture(scope="module")
def drive():
    return fdjax.table1_drive()


@pytest.fixture(scope="module")
def plant(drive):
    return fdjax.state_space(drive, POS)


@pytest.fixture(scope="module")
def mcm():
    return fdjax.MCM(
        fdjax.PeakFilter(0.3, 2 * np.pi * 120.0, 0.15, 0.4),
        fdjax.NotchFilter(2 * np.pi * 1000.0, 0.05, 0.5),
    )


@pytest.fixture(scope="module")
def reference():
    return reciprocating(stroke=2e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)


def _inputs(ref, n, dt, force=None):
    t = np.arange(n) * dt
    r, v, a = (np.asarray(x) for x in ref.evaluate(jnp.asarray(t))[:3])
    f = np.zeros(n) if force is None else np.asarray(force)
    return t, np.stack([r, v, a, f], 1)


def _numpy_sampled(loop, plant, W, dt, d, filter_method="fitted", plants=None, isc=None):
    """The sampled-data loop written out sample by sample, from SciPy's pieces.  ``plants``
    (DoubleLoop only): per sample k, the plant for the outputs and the plant over the step
    (a moving table); ``plant`` is then ignored."""
    def matrices(p):
        A, B, C, D = (np.asarray(x) for x in (p.A, p.B, p.C, p.D))
        return A, B, C, D, *sig.cont2discrete((A, B, C, D), dt, method="zoh")[:2]

    if plants is None:
        A, B, C, D, Phi, Gam = matrices(plant)
    else:
        A = np.asarray(plants[0][0].A)
    x = np.zeros(A.shape[0])
    buf = [0.0] * d  # u_{k-1} … u_{k-d}
    km = float(SERVO.k_motor)
    out = []
    if isinstance(loop, fdjax.DoubleLoop):
        df = loop.mcm.discretize(dt, filter_method)
        par, ser = np.array(df.parallel_sos), np.array(df.series_sos)
        zp = [np.zeros(2) for _ in par]
        zs = [[np.zeros(2) for _ in stage] for stage in ser]  # stage q = Σ_k its sections
        z = 0.0
        th_prev = 0.0
        kp, kv, ki = float(loop.kp), float(loop.kv), float(loop.ki)
        for k, w in enumerate(W):
            if plants is not None:
                C, D = (np.asarray(m) for m in (plants[k][0].C, plants[k][0].D))
                Phi, Gam = matrices(plants[k][1])[4:]
            T1 = km * buf[-1]
            y = C @ x + D @ np.array([T1, w[3]])
            v_m = isc * (y[0] - th_prev) / dt
            e = kp * (w[0] - y[1]) + float(loop.k_ffv) * w[1] - v_m
            u_pi = kv * (e + ki * (z + 0.5 * dt * e))  # Tustin integrator
            z += dt * e
            u_f = u_pi
            for i, row in enumerate(par):
                yi, zp[i] = sig.sosfilt(row[None, :], [u_pi], zi=zp[i][None, :])
                zp[i] = zp[i][0]
                u_f = u_f + yi[0]
            for i, stage in enumerate(ser):
                stage_out = 0.0
                for k, row in enumerate(stage):
                    yi, zk = sig.sosfilt(row[None, :], [u_f], zi=zs[i][k][None, :])
                    zs[i][k] = zk[0]
                    stage_out += yi[0]
                u_f = stage_out
            u = u_f + float(loop.k_ffa) * w[2]
            out.append([y[0], y[1], y[2], T1])
            th_prev = y[0]
            x = Phi @ x + Gam @ np.array([T1, w[3]])
            buf = [u] + buf[:-1]
    else:
        pid = sig.cont2discrete(
            (
                np.diag([0.0, -float(loop.wd)]),
                np.ones((2, 1)),
                np.array([[float(loop.ki), -float(loop.kd) * float(loop.wd) ** 2]]),
                np.array([[float(loop.kp) + float(loop.kd) * float(loop.wd)]]),
            ),
            dt,
            method="bilinear",
        )
        Ac, Bc, Cc, Dc = (np.asarray(m) for m in pid[:4])
        xc = np.zeros(2)
        for w in W:
            T1 = km * buf[-1]
            y = C @ x + D @ np.array([T1, w[3]])
            e = w[0] - y[1]
            u = (Cc @ xc + Dc[:, 0] * e)[0] + float(loop.k_ffv) * w[1] + float(loop.k_ffa) * w[2]
            xc = Ac @ xc + Bc[:, 0] * e
            out.append([y[0], y[1], y[2], T1])
            x = Phi @ x + Gam @ np.array([T1, w[3]])
            buf = [u] + buf[:-1]
    return np.array(out)


def _rel(a, b):
    return np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b)))


@pytest.mark.parametrize("kind", ["double", "double-tustin", "pid"])
def test_sampled_matches_per_sample_numpy(plant, mcm, reference, kind):
    loop = table1_loop(mcm=mcm) if kind != "pid" else fdjax.PIDLoop(k_ffv=10.0)
    method = "tustin" if kind == "double-tustin" else "fitted"
    n = 1200
    force = np.where(np.arange(n) > 600, 50.0, 0.0)
    sim = fdjax.simulate(loop, plant, reference, fdjax.SampledData(filter_method=method),
                         servo=SERVO, duration=(n - 1) * DT, disturbance=force)
    _, W = _inputs(reference, n, DT, force)
    ref = _numpy_sampled(loop, plant, W, DT, 5, method, isc=float(plant.screw_ratio))
    got = np.stack([sim.theta1, sim.x2, sim.x3, sim.torque], 1)
    for i in range(4):  # every channel to round-off of the recursion (10k products)
        assert _rel(got[:, i], ref[:, i]) < 1e-10, i  # measured ≤ 6e-12
    assert _rel(sim.error_scale, W[:, 0] - ref[:, 1]) < 1e-10  # measured ≤ 1.1e-11
    assert _rel(sim.current, ref[:, 3] / float(SERVO.k_motor)) < 1e-10


def test_sampled_matches_python_control(plant, mcm, reference):
    loop = table1_loop(mcm=mcm)
    sl = fdjax.closed_loop(loop, plant, servo=SERVO)
    assert float(sl.dt) == DT
    n = 1200  # the length of the per-sample test's runs: its compiled run serves here too
    t, W = _inputs(reference, n, DT)
    sys = control.ss(*(np.asarray(m) for m in (sl.A, sl.B, sl.C, sl.D)), DT)
    resp = control.forced_response(sys, T=t, U=W.T)
    sim = fdjax.simulate(loop, plant, reference, servo=SERVO, duration=(n - 1) * DT)
    got = np.stack([sim.theta1, sim.x2, sim.x3, sim.torque], 0)
    for i in range(4):
        assert _rel(got[i], resp.outputs[i]) < 1e-10, i  # measured ≤ 5.8e-12 (torque)


@pytest.mark.parametrize("kind", ["double", "pid"])
def test_ode_matches_lsim(plant, mcm, reference, kind):
    """The diffrax path (ExponentialFOH) solves the Padé loop as lsim does (first-order hold),
    with a step of the cutting force at the tool from half way (its effect on x3 is of the
    size of the whole signal: a dropped or mis-scaled force channel fails)."""
    loop = table1_loop(mcm=mcm) if kind == "double" else fdjax.PIDLoop()
    n = 3000
    force = np.where(np.arange(n) > n // 2, 50.0, 0.0)
    t, W = _inputs(reference, n, DT, force)
    cl = fdjax.closed_loop(loop, plant, servo=SERVO, method=PADE6)
    _, yout, _ = sig.lsim(
        sig.StateSpace(*(np.asarray(m) for m in (cl.A, cl.B, cl.C, cl.D))), W, t
    )
    sim = fdjax.simulate(loop, plant, reference, fdjax.PadeODE(), servo=SERVO,
                         duration=(n - 1) * DT, disturbance=force)
    got = np.stack([sim.theta1, sim.x2, sim.x3, sim.torque], 1)
    # both take exp of the badly scaled Padé loop (lsim without balancing): measured ≤ 8e-12
    for i in range(4):
        assert _rel(got[:, i], yout[:, i]) < 1e-10, i
    # The tracking error itself (µm on mm) to 1e-9 of its own size.
    assert _rel(sim.error_scale, W[:, 0] - yout[:, 1]) < 1e-9


def test_ode_general_solver_matches_lsim(plant, reference):
    """A stock diffrax solver (Kvaerno5, adaptive) on the same ODE agrees too."""
    loop = table1_loop()
    n = 401
    t, W = _inputs(reference, n, DT)
    cl = fdjax.closed_loop(loop, plant, servo=SERVO, method=PADE6)
    _, yout, _ = sig.lsim(
        sig.StateSpace(*(np.asarray(m) for m in (cl.A, cl.B, cl.C, cl.D))), W, t
    )
    method = fdjax.PadeODE(
        dt=DT, solver=diffrax.Kvaerno5(),
        stepsize_controller=diffrax.ClipStepSizeController(
            diffrax.PIDController(rtol=1e-10, atol=1e-14), step_ts=jnp.asarray(t)
        ),
    )
    sim = fdjax.simulate(loop, plant, reference, method, servo=SERVO, duration=(n - 1) * DT)
    # the solver's rtol is 1e-10; measured 7.6e-14 (x2) and 3.3e-12 (torque)
    assert _rel(sim.x2, yout[:, 1]) < 1e-10
    assert _rel(sim.torque, yout[:, 3]) < 1e-10


def test_sampled_and_pade_agree_at_first_order(plant, reference):
    """Same loop, two delay models: the sampled loop's extra half-sample lags (ZOH, backward
    difference) vanish as T → 0 with τ fixed; the difference is O(T)."""
    loop = table1_loop()
    dur = 0.025
    errs = []
    for T in (1.25e-4, 6.25e-5, 3.125e-5):
        k = round(1.25e-4 / T)
        servo = fdjax.Servo(period=T, delay_samples=2 * k)  # τ = 250 µs
        a = fdjax.simulate(loop, plant, reference, servo=servo, duration=dur)
        b = fdjax.simulate(loop, plant, reference, fdjax.PadeODE(), servo=servo, duration=dur)
        errs.append(float(jnp.max(jnp.abs(a.error_scale[::k] - b.error_scale[::k]))))
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    np.testing.assert_allclose(orders, 1.0, atol=0.05)
    # and the difference is small against the error itself at 8 kHz-class rates
    assert errs[-1] < 0.1 * float(jnp.max(jnp.abs(b.error_scale)))


def test_moving_table_sampled(drive):
    """The sampled path's moving table: at rest the frozen loop on the same basis; moving, the
    per-sample SciPy loop with the plant rebuilt at Y_k (outputs) and at the step's midpoint
    (transition); and the same moving effect as the continuous path's."""
    from fdjax._simulation._moving import MovingPlant

    loop = table1_loop()
    n = 201  # the length of the moving runs below: both runs here are theirs, compiled once
    force = jnp.where(jnp.arange(n) > 40, 100.0, 0.0)
    still = jerk_limited(1e-9, 0.1, 2.0, 200.0)
    kw = dict(servo=SERVO, position_m=0.4, duration=(n - 1) * DT, disturbance=force, twin=TWIN8)
    moving = fdjax.simulate(loop, drive, still, moving=True, **kw)
    frozen = fdjax.simulate(loop, drive, still, **kw)
    assert moving.result == fdjax.RESULTS.successful
    # frozen uses the twin with its static residual D, the moving basis has none: the truncated
    # modes' static flexibility from F3 to x3 is what separates them (measured 1.0e-9 relative)
    assert _rel(moving.x3, frozen.x3) < 5e-9

    fast = jerk_limited(0.02, 1.0, 20.0, 2.0e4)  # Y moves ~1 mm in 10 ms
    dur, y0 = 0.01, 0.3
    methods = {"sampled": fdjax.SampledData(), "pade": fdjax.PadeODE()}
    runs = {
        (m, mv): fdjax.simulate(loop, drive, fast, methods[m], servo=SERVO, position_m=y0,
                                duration=dur, moving=mv, twin=TWIN8)
        for m in methods
        for mv in (True, False)
    }
    a = runs[("sampled", True)]
    assert float(a.position_m[-1]) > y0 + 5e-4  # it did move
    k = a.t.shape[0]
    t = np.arange(k) * DT
    r, r_mid = np.asarray(fast.evaluate(t)[0]), np.asarray(fast.evaluate(t + DT / 2)[0])
    plant = MovingPlant.at_rest(drive, jnp.asarray(y0), TWIN8, 8)
    at = eqx.filter_jit(lambda y: plant.at(y))
    plants = [(at(y0 + r[i]), at(y0 + r_mid[i])) for i in range(k)]
    _, W = _inputs(fast, k, DT)
    ref = _numpy_sampled(loop, None, W, DT, 5, plants=plants, isc=float(drive.screw.ratio))
    got = np.stack([a.theta1, a.x2, a.x3, a.torque], 1)
    for i in range(4):
        assert _rel(got[:, i], ref[:, i]) < 1e-9, i
    # What the motion changes (moving − frozen) is the same in both paths, to their O(T)
    # difference (the loops themselves differ by 4e-3 here; the effect, ~1e-8 m, by 4e-3).
    effect = {
        m: np.asarray(runs[(m, True)].error_scale) - np.asarray(runs[(m, False)].error_scale)
        for m in methods
    }
    assert _rel(effect["sampled"], effect["pade"]) < 2e-2
    # differentiable through the moving table (each sample rematerialised in the reverse pass):
    # the gradient in log k_v against central differences (measured 3e-9 relative at h = 1e-5)
    def rms(c):
        return fdjax.simulate(c, drive, fast, servo=SERVO, position_m=y0, duration=dur,
                              moving=True, twin=TWIN8).rms_error()

    bump = lambda d: eqx.tree_at(lambda c: c.log_kv, loop, loop.log_kv + d)  # noqa: E731
    g = eqx.filter_jit(eqx.filter_grad(rms))(loop).log_kv
    h = 1e-5
    fd = (float(rms(bump(h))) - float(rms(bump(-h)))) / (2 * h)
    np.testing.assert_allclose(float(g), fd, rtol=1e-7)


def test_moving_table(drive):
    """Moving table, continuous path: the exponential midpoint rule agrees with a stiff adaptive
    solver (at rest it is the frozen loop on the same basis: the sampled test above, whose
    continuous moving run this is, compiled once)."""
    loop = table1_loop()
    fast = jerk_limited(0.02, 1.0, 20.0, 2.0e4)  # 20 mm at 20 m/s²: Y moves 1 mm in 10 ms
    dur = 0.01
    a = fdjax.simulate(loop, drive, fast, fdjax.PadeODE(), servo=SERVO, position_m=0.3,
                       duration=dur, moving=True, twin=TWIN8)
    t = jnp.arange(round(dur / DT) + 1, dtype=jnp.float64) * DT
    b = fdjax.simulate(
        loop, drive, fast,
        fdjax.PadeODE(solver=diffrax.Kvaerno5(),
                      stepsize_controller=diffrax.ClipStepSizeController(
                          diffrax.PIDController(rtol=1e-9, atol=1e-13), step_ts=t)),
        servo=SERVO, position_m=0.3, duration=dur, moving=True, twin=TWIN8,
    )
    assert float(a.position_m[-1]) > 0.3 + 5e-4  # it did move
    # Kvaerno5 at rtol 1e-9 against the default solver: measured 3.8e-10
    assert _rel(a.error_scale, b.error_scale) < 3e-9


def test_moving_plant_follows_the_twin_to_second_order(drive):
    """The moving table's plant at Y₀ + Δ (the FE model at Y₀ + Δ projected on the modes at
    Y₀) against the twin built at Y₀ + Δ (its own modes): the same modes at Δ = 0 (measured
    1.8e-13), and a Galerkin error of the lowest six natural frequencies that falls as Δ²
    (Rayleigh quotients on a basis off by O(Δ); measured 6.1e-5, 2.3e-4, 9.0e-4 at Δ = 2, 4,
    8 mm: each doubling ×3.8–4.0)."""
    from fdjax._simulation._moving import MovingPlant

    y0 = 0.3
    plant = MovingPlant.at_rest(drive, jnp.asarray(y0), TWIN8, 8)

    def lowest(ss):
        lam = np.linalg.eigvals(np.asarray(ss.A))
        lam = lam[lam.imag > 1.0]
        return np.sort(np.abs(lam))[:6]

    def error(d):
        here = lowest(plant.at(jnp.asarray(y0 + d)))
        return np.max(np.abs(here / lowest(fdjax.state_space(drive, y0 + d, twin=TWIN8)) - 1))

    assert error(0.0) < 1e-12
    errs = np.array([error(d) for d in (2e-3, 4e-3, 8e-3)])
    order = np.log2(errs[1:] / errs[:-1])
    assert np.all(order > 1.8) and errs[0] < 1e-4, (errs, order)


def test_bad_input_messages(plant, reference):
    with pytest.raises(ValueError,
                       match=r"`Servo\(delay_samples=\.\.\.\)` m"
                             r"ust be an integer between 1 and 64"):
        fdjax.Servo(delay_samples=2.5)
    with pytest.raises(ValueError,
                       match=r"`Servo\(period=\.\.\.\)` must be a number in \(0, 0\.01\] s"):
        fdjax.Servo(period=-1.0)
    with pytest.raises(ValueError,
                       match=r"SampledData\(filter_method=...\)` must be 'fitted' or"):
        fdjax.SampledData(filter_method="zoh")
    with pytest.raises(ValueError, match=r"PadeODE\(pade_order=...\)"):
        fdjax.PadeODE(pade_order=0)
    with pytest.raises(ValueError, match=r"PadeODE\(dt=...\)` must be a positive number"):
        fdjax.PadeODE(dt=-1e-4)
    with pytest.raises(ValueError, match=r"simulate\(disturbance=...\)` must have shape"):
        fdjax.simulate(table1_loop(), plant, reference, duration=0.01,
                       disturbance=np.zeros(3))
    with pytest.raises(ValueError, match=r"simulate\(position_m=..., moving=True\)` need a "
                                         r"BallScrewDrive"):
        fdjax.simulate(table1_loop(), plant, reference, moving=True)
    with pytest.raises(ValueError, match=r"BacksolveAdjoint\(\)\)` is not supported"):
        fdjax.PadeODE(adjoint=diffrax.BacksolveAdjoint())
    with pytest.raises(TypeError, match=r"simulate\(reference=...\)"):
        fdjax.simulate(table1_loop(), plant, object())
    with pytest.raises(TypeError, match=r"`simulate\(method=\.\.\.\)` must be "
                                        r"fdjax.SampledData\(\) or fdjax.PadeODE\(\)"):
        fdjax.simulate(table1_loop(), plant, reference, fdjax.Continuous())
    d = fdjax.table1_drive()
    with pytest.raises(ValueError, match=r"`simulate\(position_m=\.\.\.\)` must be inside the "
                                         r"travel \[0.1, 0.7\] m, got 115"):
        fdjax.simulate(table1_loop(), d, reference, position_m=115.0)
    with pytest.raises(ValueError, match=r"reaches 5.1 m, outside the travel"):
        fdjax.simulate(table1_loop(), d, fdjax.reciprocating(stroke=5.0), position_m=0.1)
