"""The synthesis stages run to completion on a cheap objective: the robust tuner, the tuner of
shared gains, the evaluation of the shipped designs, and the tuning motion.

Every recorded number is recomputed through the public API (:class:`fdjax.Objective`,
:func:`fdjax.simulate`, :func:`fdjax.check_stability`, :func:`fdjax.loop_margins`) or a closed
form.  The tuners share one objective (64 frequencies, 4 kept modes) and two positions, so
that the file compiles each program once."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fdjax

POSITIONS = np.array([0.1, 0.7])  # the travel's ends, where the designs differ most
BETA = 2.0                        # the tuners' default smooth-maximum sharpness


def _smooth_max(v, beta=BETA):
    """(1/β) ln((1/n) Σ e^{β v_i}) of fdjax.smooth_max's docstring, in NumPy."""
    v = np.asarray(v, float)
    m = v.max()
    return m + math.log(np.mean(np.exp(beta * (v - m)))) / beta


@pytest.fixture(scope="module")
def drive():
    return fdjax.reference_drive()


@pytest.fixture(scope="module")
def servo():
    return fdjax.reference_servo()


@pytest.fixture(scope="module")
def objective(servo):
    """fdjax.tuning_objective(kept_modes=4) on 64 frequencies instead of 400."""
    return fdjax.Objective(fdjax.tuning_motion(), np.geomspace(5.0, 3900.0, 64), servo=servo,
                           twin=fdjax.TwinOptions(kept_modes=4), error_scale_m=1e-4,
                           margin_width=0.05, margin_sharpness=200.0)


def _oracle(objective, drive, par):
    """J(par.to_controller(θ_i), Y_i) for rows θ (n, p) and positions Y (n,): the public
    Objective in one compiled program of its own."""
    f = eqx.filter_jit(jax.vmap(lambda th, y: objective(par.to_controller(th), drive, y)))
    return lambda theta, y: f(jnp.asarray(theta), jnp.asarray(y, jnp.float64))


# ------------------------------------------------------------------------------ robust tuning
def test_tune_robust_records_the_smooth_max_of_the_objective(objective, drive, servo):
    """tune_robust on a PID (the robust PID of the synthesis) at two positions, 3 Adam steps:
    its history is smax_β of J over the positions and ``worst`` their max, both recomputed
    by the public Objective at the two parameter vectors the record names (the start, step
    0, and ``best_theta``, the step of the least history); at every step
    worst − ln(n)/β ≤ history ≤ worst (smooth_max's bounds); the best design is lower than
    the start (Adam does not promise a monotone history, the record of the best does), and
    it is a PIDLoop whose stability by the eigenvalues (check_stability) is the objective's
    verdict, with the same growth rate."""
    pid0 = fdjax.reference_pid(k_ffv=1.0, k_ffa=1.0)
    par = fdjax.PIDParameterisation(pid0, servo=servo, feedforward=False)
    r = fdjax.tune_robust(par, objective, drive, POSITIONS, pid0, steps=3, chunk=3)
    # Adam: one evaluation of the objective with its gradient per step
    np.testing.assert_array_equal(np.asarray(r.evaluations), np.ones(3))
    h, worst = np.asarray(r.history), np.asarray(r.worst)
    assert h.shape == (3,) and worst.shape == (3,) and r.best_theta.shape == (6,)
    np.testing.assert_array_equal(np.asarray(r.positions_m), POSITIONS)
    J = _oracle(objective, drive, par)
    y = POSITIONS
    j0 = np.asarray(J(np.tile(par.from_controller(pid0), (2, 1)), y).total)
    jb = np.asarray(J(np.tile(r.best_theta, (2, 1)), y).total)
    k = int(np.argmin(h))
    # the same J in two compiled programs (the tuner's with its gradient): round-off of a
    # lightly damped run, measured ≤ 1.2e-11 relative
    np.testing.assert_allclose(h[0], _smooth_max(j0), rtol=5e-11)
    np.testing.assert_allclose(worst[0], j0.max(), rtol=5e-11)
    np.testing.assert_allclose(h[k], _smooth_max(jb), rtol=5e-11)
    np.testing.assert_allclose(worst[k], jb.max(), rtol=5e-11)
    np.testing.assert_allclose(np.asarray(r.terms.total), jb, rtol=5e-11)
    # smooth_max's bounds hold at every step (n = 2 positions)
    assert np.all(h <= worst) and np.all(h >= worst - math.log(2) / BETA - 1e-12), (h, worst)
    # the record keeps the best it saw: lower than the start (measured 88.5 → 61.1)
    assert _smooth_max(jb) < 0.9 * _smooth_max(j0), (j0, jb)
    assert not np.array_equal(np.asarray(r.theta), np.asarray(par.from_controller(pid0)))
    c = par.to_controller(r.best_theta)
    assert isinstance(c, fdjax.PIDLoop)
    st = fdjax.check_stability(c, drive, position_m=y, twin=objective.twin)
    np.testing.assert_array_equal(np.asarray(st.stable), np.asarray(r.terms.stable))
    # eigenvalues of the closed loop (check_stability) against the spectral radius of the
    # run's transition matrix (the objective): measured 1.3e-10 relative (4.5e-10 1/s)
    np.testing.assert_allclose(np.asarray(st.growth_rate), np.asarray(r.terms.growth_rate),
                               rtol=5e-10)


# -------------------------------------------------------------------------------- shared gains
def test_tune_shared_gains_shares_the_gains_and_records_j_per_position(objective, drive,
                                                                       servo):
    """tune_shared_gains on a feedback double loop at two positions, 3 Adam steps, from two
    designs whose gains differ: the shared gains start at their mean (the history's first row
    is J at (mean gains, own MCM), recomputed by the public Objective); the history is J per
    position; ``best_theta`` is the step whose ½(mean + smax_β) of the history row is least,
    its row is J at ``best_theta``, and that aggregate is below the start's; the gains are
    the same at both positions bit for bit and the MCMs differ; the designs are DoubleLoops
    whose stability by the eigenvalues is the objective's verdict."""
    ref = fdjax.reference_controller(drive, servo)
    soft = eqx.tree_at(lambda c: c.log_kv, ref, ref.log_kv + math.log(0.5))
    par = fdjax.DoubleLoopParameterisation(fdjax.MCMBounds.for_servo(servo), ref,
                                           feedforward=False)
    th0 = np.asarray(par.from_controller(soft))
    dg = np.array([0.1, -0.05, 0.2, 0.0, 0.0])
    start = np.stack([th0, th0])
    start[0, :5] += dg
    start[1, :5] -= dg
    start[1, 5:] += 0.05  # the two MCMs differ from the start
    s = fdjax.tune_shared_gains(par, objective, drive, POSITIONS, start, steps=3, chunk=3)
    np.testing.assert_array_equal(np.asarray(s.evaluations), np.ones((3, 2)))  # Adam
    h = np.asarray(s.history)
    assert h.shape == (3, 2) and s.best_theta.shape == (2, 12)
    J = _oracle(objective, drive, par)
    mean_start = start.copy()
    mean_start[:, :5] = np.mean(start[:, :5], axis=0)
    j0 = np.asarray(J(mean_start, POSITIONS).total)
    jb = np.asarray(J(s.best_theta, POSITIONS).total)
    # the same J in two compiled programs (the tuner's with its gradient): round-off of a
    # lightly damped run, measured ≤ 2.6e-10 relative
    np.testing.assert_allclose(h[0], j0, rtol=1e-9)
    agg = np.array([0.5 * (row.mean() + _smooth_max(row)) for row in h])
    k = int(np.argmin(agg))
    np.testing.assert_allclose(h[k], jb, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(s.terms.total), jb, rtol=1e-9)
    # measured ½(mean + smax) 169 → 70
    assert 0.5 * (jb.mean() + _smooth_max(jb)) < 0.9 * agg[0], (agg, jb)
    for theta in (np.asarray(s.best_theta), np.asarray(s.theta)):
        np.testing.assert_array_equal(theta[0, :5], theta[1, :5])
        assert np.max(np.abs(theta[0, 5:] - theta[1, 5:])) > 1e-3, theta
    loops = [par.to_controller(th) for th in s.best_theta]
    assert all(isinstance(c, fdjax.DoubleLoop) for c in loops)
    for gain in ("kp", "kv", "ki"):
        assert float(getattr(loops[0], gain)) == float(getattr(loops[1], gain))
    assert float(loops[0].mcm.peak.omega[0]) != float(loops[1].mcm.peak.omega[0])
    for i, (c, y) in enumerate(zip(loops, POSITIONS)):
        st = fdjax.check_stability(c, drive, position_m=y, twin=objective.twin)
        assert bool(st.stable) == bool(s.terms.stable[i])
        # eigenvalues against the run's spectral radius: measured ≤ 2.5e-11 relative
        np.testing.assert_allclose(float(st.growth_rate), float(s.terms.growth_rate[i]),
                                   rtol=1e-10)


# ------------------------------------------------------------------------------ evaluation
def _least_over_breaks(m, name, absolute):
    vals = [float(getattr(L, name)) for L in (m.plant_input, m.speed, m.position)
            if L is not None]
    return min(abs(v) for v in vals) if absolute else min(vals)


def test_evaluate_is_simulate_stability_and_loop_margins_at_each_position(drive, servo,
                                                                         monkeypatch):
    """evaluate on two shipped designs (the robust MCM, a fixed double loop, and the
    end-to-end ATA schedule, which evaluate runs in one program with it) and on the reference
    controller (unstable toward the screw end) at three positions: its RMS error is
    simulate(...).rms_error() of the tuning motion in µm (None where unstable), its
    stability is check_stability's and its margins the least over the break points of
    loop_margins on the default 2000-point grid, for the fixed loop each runs there."""
    designs, _ = fdjax.load_designs()
    ref = fdjax.reference_controller(drive, servo)
    controllers = {"mcm_robust": designs["mcm_robust"], "mcm_ata_e2e": designs["mcm_ata_e2e"],
                   "reference": ref}
    y = np.array([0.1, 0.43, 0.7])
    from fdjax._tune import _synthesis

    batches = []   # the positions of each program evaluate runs

    def counted(controllers, drive, ys, **kw):
        batches.append(np.asarray(ys))
        return point_checks(controllers, drive, ys, **kw)

    point_checks = _synthesis.point_checks
    monkeypatch.setattr(_synthesis, "point_checks", counted)
    out = fdjax.evaluate(controllers, drive, y, progress=False)
    assert list(out) == list(controllers)
    # three double loops of the same shapes (the schedule's too, at each position): one program
    assert len(batches) == 1
    np.testing.assert_array_equal(batches[0], np.tile(y, 3))
    f = np.geomspace(5.0, 0.995 * 0.5 / float(servo.period), 2000)
    motion = fdjax.tuning_motion()
    seen_unstable = False
    for name, c in controllers.items():
        e = out[name]
        np.testing.assert_array_equal(e["certificate"].positions_m, y)
        for k, p in enumerate(y):
            fixed = c.controller(p) if isinstance(c, fdjax.ScheduledLoop) else c
            st = fdjax.check_stability(fixed, drive, position_m=p, servo=servo)
            assert e["stable"][k] == bool(st.stable), (name, p)
            sim = fdjax.simulate(fixed, drive, motion, position_m=p, servo=servo, throw=False)
            if e["stable"][k]:
                # the same run in two compiled programs: measured ≤ 3.3e-15 relative
                np.testing.assert_allclose(e["rms_error_um"][k], float(sim.rms_error()) * 1e6,
                                           rtol=1e-12)
            else:
                assert e["rms_error_um"][k] is None
                seen_unstable = True
                continue  # an unstable loop's margins mean nothing
            m = fdjax.loop_margins(fixed, drive, f, position_m=p, servo=servo)
            # crossings refined by Newton steps in two programs: measured ≤ 1.2e-10 relative
            np.testing.assert_allclose(e["modulus_margin"][k],
                                       _least_over_breaks(m, "modulus_margin", False),
                                       rtol=5e-10)
            np.testing.assert_allclose(e["gain_margin_db"][k],
                                       _least_over_breaks(m, "gain_margin_db", True),
                                       rtol=5e-10)
            np.testing.assert_allclose(e["phase_margin_deg"][k],
                                       _least_over_breaks(m, "phase_margin_deg", True),
                                       rtol=5e-10)
    assert seen_unstable and all(out["mcm_robust"]["stable"])  # both branches exercised
    # the schedule's entries are its own, not its group partner's
    assert out["mcm_ata_e2e"]["modulus_margin"] != out["mcm_robust"]["modulus_margin"]


def test_evaluate_names_its_arguments(drive):
    """evaluate refuses, before compiling anything, what is not a non-empty dict of
    controllers, a drive, a servo, a motion, or positions in metres as a 1-D array."""
    ref = fdjax.reference_controller(drive)
    ok = {"ref": ref}
    for bad, got in (([ref], "list"), ({}, "dict")):
        with pytest.raises(TypeError, match=r"`evaluate\(controllers=\.\.\.\)` must be a "
                                            r"non-empty dict of name → controller, got " + got):
            fdjax.evaluate(bad, drive, [0.2], progress=False)
    with pytest.raises(TypeError, match=r"`evaluate\(controllers\['x'\]=\.\.\.\)` must be an "
                                        r"fdjax controller, got int"):
        fdjax.evaluate({"ref": ref, "x": 3}, drive, [0.2], progress=False)
    with pytest.raises(TypeError, match=r"`evaluate\(drive=\.\.\.\)` must be an "
                                        r"fdjax\.BallScrewDrive, got Servo"):
        fdjax.evaluate(ok, fdjax.Servo(), [0.2], progress=False)
    with pytest.raises(TypeError, match=r"`evaluate\(servo=\.\.\.\)` must be an fdjax\.Servo, "
                                        r"got str"):
        fdjax.evaluate(ok, drive, [0.2], servo="8 kHz", progress=False)
    with pytest.raises(TypeError, match=r"`evaluate\(motion=\.\.\.\)` must be an "
                                        r"fdjax\.Trajectory, got function"):
        fdjax.evaluate(ok, drive, [0.2], motion=lambda t: t, progress=False)
    with pytest.raises(ValueError, match=r"`evaluate\(positions_m=\.\.\.\)` must be inside the "
                                         r"travel \[0\.1, 0\.7\] m, got 115 at index 1; table "
                                         r"positions are in metres: 115 mm is 0\.115 m"):
        fdjax.evaluate(ok, drive, [0.2, 115.0], progress=False)
    with pytest.raises(ValueError, match=r"`evaluate\(positions_m=\.\.\.\)` must be a position "
                                         r"or a 1-D array of positions, got shape \(1, 2\)"):
        fdjax.evaluate(ok, drive, [[0.2, 0.3]], progress=False)
    with pytest.raises(TypeError, match=r"`evaluate\(positions_m=\.\.\.\)` must be a number or "
                                        r"an array of numbers, got \['a'\]"):
        fdjax.evaluate(ok, drive, ["a"], progress=False)
    # a schedule outside its network's travel, or with filters the servo cannot sample, is
    # named by the argument that carries it
    bounds = fdjax.MCMBounds.for_servo(fdjax.Servo())
    short = fdjax.ScheduledLoop(ref, fdjax.ATANetwork((0.2, 0.6), width=3), bounds)
    with pytest.raises(ValueError, match=r"`evaluate\(positions_m=\.\.\.\) for evaluate\("
                                         r"controllers\['s'\]=\.\.\.\)` must be inside the "
                                         r"network's travel \[0\.2, 0\.6\] m, got 0\.7"):
        fdjax.evaluate({"s": short}, drive, [0.3, 0.7], progress=False)
    fast = fdjax.MCMBounds.for_servo(fdjax.Servo(period=1 / 16000))
    wide = fdjax.ScheduledLoop(ref, fdjax.ATANetwork((0.1, 0.7), width=3), fast)
    with pytest.raises(ValueError, match=r"`evaluate\(controllers\['w'\]=\.\.\.\)` lets the "
                                         r"filters reach 7200 Hz, not below the Nyquist "
                                         r"frequency 4000 Hz"):
        fdjax.evaluate({"w": wide}, drive, [0.3], progress=False)


def test_evaluate_runs_one_program_per_kind_and_shape_of_controller(drive):
    """Controllers share a compiled program when their trees and array shapes agree: the same
    double loop with other gains does, one with a second peak filter does not (stacking it
    with the first would fail)."""
    from fdjax._tune._synthesis import _program_key

    y = np.array([0.2, 0.5])
    ref = fdjax.reference_controller(drive)
    other = eqx.tree_at(lambda c: c.log_kv, ref, ref.log_kv - 1.0)
    mcm = ref.mcm
    two = eqx.tree_at(lambda c: c.mcm, ref, fdjax.MCM(fdjax.PeakFilter(
        np.repeat(mcm.peak.K, 2), np.repeat(mcm.peak.omega, 2), np.repeat(mcm.peak.xi, 2),
        np.repeat(mcm.peak.phi, 2)), mcm.notch))
    keys = [_program_key(c.fixed_at(y)) for c in (ref, other, two)]
    assert keys[0] == keys[1] and keys[0] != keys[2]


# ------------------------------------------------------------------------------ tuning motion
def test_tuning_motion_is_the_closed_form_double_s_stroke(objective):
    """tuning_motion is a 1 mm stroke out and back at v = 50 mm/s, a = 2 m/s², j = 400 m/s³.
    The double-S closed form (Biagiotti & Melchiorri, as jerk_limited documents): v T_a =
    v(a/j + v/a) = 1.5 mm > h, so no cruise; h ≥ 2a³/j² = 0.1 mm, so a is reached:
    T_j = a/j = 5 ms, T = a/j + √(a²/j² + 4h/a) = 50 ms a stroke, 0.1 s in all, peak speed
    v_p = (√(a⁴/j² + 4ha) − a²/j)/2 = 40 mm/s at T/2, |a| = 2 m/s² on the plateaus, r(T_j) =
    j T_j³/6, r(T/2) = h/2, r(T) = h and back to 0 at rest.  The synthesis objective runs it,
    on 400 frequencies (5 Hz–3.9 kHz)."""
    h, v, a, j = 1e-3, 0.05, 2.0, 400.0
    assert v * (a / j + v / a) > h and h >= 2 * a ** 3 / j ** 2  # the case of the closed form
    tj = a / j
    T = a / j + math.sqrt(a ** 2 / j ** 2 + 4 * h / a)
    vp = (math.sqrt(a ** 4 / j ** 2 + 4 * h * a) - a ** 2 / j) / 2
    m = fdjax.tuning_motion()
    # closed form against the knots' cumulative sum: round-off (measured 0)
    np.testing.assert_allclose(float(m.duration), 2 * T, rtol=1e-14)
    assert abs(2 * T - 0.1) < 1e-15 and abs(vp - 0.04) < 1e-15
    lo, hi = (float(x) for x in m.position_range())
    # round-off of a 1 mm stroke: measured −1.8e-18 m below the start
    np.testing.assert_allclose([lo, hi], [0.0, h], rtol=0, atol=1e-17)
    t = np.array([0.0, tj, T / 2, T, T + tj, 1.5 * T, 2 * T])
    r, vel, acc, jerk = (np.asarray(x) for x in m.evaluate(t))
    want_r = [0.0, j * tj ** 3 / 6, h / 2, h, h - j * tj ** 3 / 6, h / 2, 0.0]
    want_v = [0.0, j * tj ** 2 / 2, vp, 0.0, -j * tj ** 2 / 2, -vp, 0.0]
    # cubic recurrence over the knots: round-off of 1 mm and 40 mm/s (measured ≤ 1.8e-18 m,
    # 4.2e-17 m/s)
    np.testing.assert_allclose(r, want_r, rtol=0, atol=1e-17)
    np.testing.assert_allclose(vel, want_v, rtol=0, atol=2e-16)
    # measured ≤ 1.3e-15 relative (here and on the dense grid)
    np.testing.assert_allclose(acc[[1, 4]], [a, -a], rtol=1e-14)
    # extremes on a dense grid: the peak speed, the acceleration limit, the jerk limit
    tt = np.linspace(0.0, 2 * T, 20001)
    _, vv, aa, jj = (np.asarray(x) for x in m.evaluate(tt))
    np.testing.assert_allclose([vv.max(), -vv.min()], [vp, vp], rtol=1e-14)
    np.testing.assert_allclose([aa.max(), -aa.min()], [a, a], rtol=1e-14)
    assert np.abs(jj).max() == j and vv.max() < v
    full = fdjax.tuning_objective(kept_modes=4)
    assert bool(eqx.tree_equal(full.reference, m))
    np.testing.assert_allclose(np.asarray(full.freq_hz), np.geomspace(5.0, 3900.0, 400),
                               rtol=1e-15)
    # the objective of this file is the synthesis objective on a coarser grid
    same = eqx.tree_at(lambda o: o.freq_hz, full, objective.freq_hz)
    assert bool(eqx.tree_equal(same, objective))
