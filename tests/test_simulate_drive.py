"""Closed-loop time simulation of the drive: instability and divergence reported with the
position, gradients against central differences, positions batched, the moving table
(its continuous path against a stiff solver is in tests/test_simulate.py, beside the sampled
one, whose run it shares).

Oracles: the closed loop's poles (eigenvalues), central differences, runs one position at a
time and the frozen table.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jit_errors import CHECK_FAILED
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
def mcm():
    return fdjax.MCM(
        fdjax.PeakFilter(0.3, 2 * np.pi * 120.0, 0.15, 0.4),
        fdjax.NotchFilter(2 * np.pi * 1000.0, 0.05, 0.5),
    )


@pytest.fixture(scope="module")
def reference():
    return reciprocating(stroke=2e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)


def _rel(a, b):
    return np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b)))


def _hot_pid(drive, factor):
    """The default PID with every gain scaled to ``factor`` (> 1) times its gain headroom at
    0.7 m, the largest common factor of its gains that the eigenvalues of the closed loop call
    stable (to 1e-4): unstable there by construction.  (The headroom is the program
    check_stability compiles below anyway; that it equals the gain margin is test_reference's
    and test_control's check.)"""
    base = fdjax.PIDLoop()
    gm = float(fdjax.gain_headroom(base, drive, position_m=Y_END, servo=SERVO, rtol=1e-4))
    g = factor * gm
    hot = fdjax.PIDLoop(base.kp * g, base.ki * g, base.kd * g, base.wd)
    assert not bool(fdjax.check_stability(hot, drive, position_m=Y_END, servo=SERVO).stable)
    return hot


def test_unstable_loop_is_reported_with_position(drive, reference):
    hot = _hot_pid(drive, 1.5)
    for method in (fdjax.SampledData(), fdjax.PadeODE()):
        with pytest.raises(RuntimeError, match=r"unstable at table position 0\.698 m: pole at"):
            fdjax.simulate(hot, drive, reference, method, servo=SERVO, position_m=Y_END,
                           duration=0.05)
        sim = fdjax.simulate(hot, drive, reference, method, servo=SERVO, position_m=Y_END,
                             duration=0.05, throw=False)
        assert sim.result == fdjax.RESULTS.unstable
        # Gelfand's formula on the transition matrix gives the growth rate of the eigenvalues
        # of check_stability (s = ln z / T for the sampled loop): measured 1.3e-9 (sampled)
        # and 1.1e-9 1/s (Padé) at growth rates of 22.6 and 23.2 1/s
        st = fdjax.check_stability(hot, drive, position_m=Y_END, servo=SERVO,
                                   method=PADE6 if isinstance(method, fdjax.PadeODE) else method)
        assert float(st.growth_rate) > 0
        np.testing.assert_allclose(sim.growth_rate, st.growth_rate, rtol=0, atol=1e-7)
    # the default loop is stable there and runs to the end
    fine = fdjax.simulate(fdjax.PIDLoop(), drive, reference, servo=SERVO, position_m=Y_END,
                          duration=0.05)
    assert fine.result == fdjax.RESULTS.successful and float(fine.growth_rate) < 0


def test_instability_and_divergence_under_jit(drive, reference):
    """Under jit and vmap the pole check still works (growth rate of the transition matrix),
    and a run that leaves the error bound stops there with finite outputs."""
    # 2 % past the gain margin at the screw end: stable at 0.1 m, unstable at 0.698 m, so a
    # batch that handed one verdict or growth rate to every position would fail
    hot = _hot_pid(drive, 1.02)
    twin = fdjax.TwinOptions(kept_modes=fdjax.count_modes(drive))
    pos = jnp.array([0.1, Y_END])
    st = fdjax.check_stability(hot, drive, position_m=pos, servo=SERVO)
    stable = st.stable
    np.testing.assert_array_equal(np.asarray(stable), [True, False])
    soft = fdjax.PIDLoop()
    # one batched program for both runs (controller and bound as arguments); the PadeODE path
    # makes the same check, eagerly, in the test above
    batch = jax.jit(jax.vmap(lambda c, p, eb: fdjax.simulate(
        c, drive, reference, fdjax.SampledData(), servo=SERVO, position_m=p, duration=0.05,
        twin=twin, error_bound=eb, throw=False), in_axes=(None, 0, None)))
    sims = batch(hot, pos, 0.01)
    # the same verdict as the closed-loop poles of check_stability, position by position
    np.testing.assert_array_equal(sims.result == fdjax.RESULTS.unstable, ~np.asarray(stable))
    np.testing.assert_array_equal(sims.result == fdjax.RESULTS.successful, np.asarray(stable))
    assert "unstable at table position 0.698 m: growing at" in sims.message
    np.testing.assert_array_equal(np.asarray(sims.growth_rate) < 0, np.asarray(stable))
    np.testing.assert_allclose(sims.growth_rate, st.growth_rate, rtol=0, atol=1e-7)
    # a stable loop whose error leaves a (deliberately tiny) bound stops there, at each position
    div = batch(soft, jnp.array([0.4, Y_END]), 1e-7)
    np.testing.assert_array_equal(div.result == fdjax.RESULTS.diverged, [True, True])
    lines = div.message.splitlines()
    for i in range(2):
        k = int(div.failed_at[i])
        assert 0 < k < div.t.shape[-1]
        e = div.error_scale[i]
        assert abs(float(e[k - 1])) <= 1e-7 < abs(float(e[k]))
        np.testing.assert_array_equal(div.x2[i, k:], div.x2[i, k - 1])  # frozen, finite
        assert "diverged" in lines[i]
    assert "table position 0.4 m" in lines[0]
    # with throw: one program for both failures (controller, position and bound as arguments)
    run = jax.jit(lambda c, p, eb: fdjax.simulate(c, drive, reference, servo=SERVO,
                                                  position_m=p, duration=0.05, twin=twin,
                                                  error_bound=eb).x2)
    with pytest.raises(CHECK_FAILED, match="the closed loop is unstable"):
        jax.block_until_ready(run(hot, Y_END, 0.01))
    with pytest.raises(CHECK_FAILED, match="the closed-loop run diverged"):
        jax.block_until_ready(run(soft, 0.4, 1e-7))


def test_gradients_match_central_differences(drive, mcm, reference):
    """d RMS(e2)/d(controller and plant parameters), sampled and ODE paths."""
    twin = fdjax.TwinOptions(kept_modes=fdjax.count_modes(drive))

    def rms(p, method):
        loop = fdjax.DoubleLoop(
            kp=p["kp"], kv=p["kv"], ki=p["ki"], k_ffa=p["k_ffa"],
            mcm=fdjax.MCM(fdjax.PeakFilter(p["K"], 2 * np.pi * 120.0, 0.15, p["phi"]),
                          mcm.notch),
        )
        d = eqx.tree_at(lambda x: x.nut.stiffness, drive, p["k_nut"])
        sim = fdjax.simulate(loop, d, reference, method, servo=SERVO, position_m=POS,
                             duration=0.05, twin=twin, throw=False)
        return sim.rms_error()

    p0 = dict(kp=jnp.asarray(40.0), kv=jnp.asarray(1e3), ki=jnp.asarray(60.0),
              k_ffa=jnp.asarray(0.3), K=jnp.asarray(0.3), phi=jnp.asarray(0.4),
              k_nut=jnp.asarray(drive.nut.stiffness))
    for method, names in ((fdjax.SampledData(), list(p0)),
                          (fdjax.PadeODE(), ["kp", "K", "k_nut"])):
        g = jax.jit(jax.grad(lambda p, m=method: rms(p, m)))(p0)
        f = lambda p, m=method: rms(p, m)  # eager: the simulation's own compiled program
        for k in names:
            v = p0[k]
            # central difference: truncation O(h²) ≈ 1e-7 relative; round-off of the loss
            # (exp of the badly scaled Padé loop, ~1e-9 relative) / h stays below 1e-6
            h = 3e-4 * abs(float(v))
            fp = float(f({**p0, k: v + h}))
            fm = float(f({**p0, k: v - h}))
            fd = (fp - fm) / (2 * h)
            assert abs(float(g[k]) - fd) <= 1e-5 * abs(fd) + 1e-9 * float(f(p0)) / abs(float(v)), (
                type(method).__name__, k, float(g[k]), fd)


def test_vmap_over_positions_equals_loop(drive, mcm, reference):
    # the loop, run and twin of the sampled gradient test above: one position at a time is
    # the program compiled there
    loop = table1_loop(mcm=mcm)
    twin = fdjax.TwinOptions(kept_modes=fdjax.count_modes(drive))
    pos = jnp.array([0.115, 0.4, Y_END])

    def run(p):
        return fdjax.simulate(loop, drive, reference, servo=SERVO, position_m=p,
                              duration=0.05, twin=twin, throw=False)

    batched = jax.vmap(run)(pos)
    for i, p in enumerate(pos):
        one = run(p)
        np.testing.assert_allclose(batched.x2[i], one.x2, rtol=1e-12, atol=1e-18)
    assert batched.x2.shape == (3, 1001)
    # inside jit the default duration is read from a closed-over trajectory's knots
    short = jerk_limited(1e-4, 0.1, 2.0, 200.0)
    x2 = jax.jit(lambda p: fdjax.simulate(loop, drive, short, servo=SERVO, position_m=p,
                                          twin=twin, throw=False).x2)(0.3)
    assert x2.shape == (round(float(short.duration) / DT) + 1,)


def test_shared_discretisation_is_the_loop_built_apart(drive, mcm):
    """SampledData().sharing(...) holds one design's discrete law and ZOH plant: its closed loop
    is the one built apart (to round-off: computed eagerly here, inside one program there), and
    a moving table, rebuilt at every position, refuses it."""
    loop = table1_loop(mcm=mcm)
    plant = fdjax.state_space(drive, 0.4, twin=TWIN8)
    shared = fdjax.SampledData().sharing(loop, plant, SERVO)
    a = fdjax.closed_loop(loop, plant, servo=SERVO, method=shared)
    b = fdjax.closed_loop(loop, plant, servo=SERVO)
    for x, y in zip((a.A, a.B, a.C, a.D), (b.A, b.B, b.C, b.D)):
        # measured 2.3e-12 relative at most, on entries ~1e-8 of a transition matrix ~1
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-11, atol=1e-15)
    ref = reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    with pytest.raises(ValueError, match=r"rebuilds the loop at every position"):
        fdjax.simulate(loop, drive, ref, shared, servo=SERVO, position_m=0.4, moving=True,
                       twin=TWIN8, duration=0.01)


def test_a_moving_run_that_rests_on_an_unstable_loop_is_unstable():
    """The reference controller's loop is unstable at rest from 0.5 m.  A moving run that
    starts there, or ends there, is reported unstable with the position and the loop's growth
    rate, as the frozen run is (it used to say "ok": the error had not yet passed its bound);
    one that stays where the loop is stable is ok, with the frozen loop's growth rate."""
    drive_ = fdjax.reference_drive()
    ref = fdjax.reference_controller(drive_)
    kw = dict(moving=True, twin=fdjax.TwinOptions(kept_modes=6), throw=False)
    move = jerk_limited(0.1, 0.3, 2.0, 400.0)  # 0.45 → 0.55 m in 0.49 s
    # the moving runs that stay put last as long as this move: one compiled moving run for all
    dur = float(move.duration)
    frozen = fdjax.simulate(ref, drive_, jerk_limited(1e-4, 0.05, 2.0, 400.0), position_m=0.6,
                            duration=0.02, twin=kw["twin"], throw=False)
    start = fdjax.simulate(ref, drive_, jerk_limited(1e-4, 0.05, 2.0, 400.0), position_m=0.6,
                           duration=dur, **kw)
    assert start.result == fdjax.RESULTS.unstable == frozen.result
    # the loop at rest at the end, 0.1 mm on: within 0.1 % of the frozen one's (measured 17.62
    # and 17.63 1/s)
    np.testing.assert_allclose(start.growth_rate, frozen.growth_rate, rtol=1e-3)
    assert "closed loop unstable at table position 0.6" in start.message
    end = fdjax.simulate(ref, drive_, move, position_m=0.45, **kw)
    assert end.result == fdjax.RESULTS.unstable and float(end.growth_rate) > 0
    np.testing.assert_allclose(end.unstable_at_m, 0.55, rtol=1e-12)
    assert "unstable at table position 0.55 m (the loop at rest there)" in end.message
    with pytest.raises(RuntimeError, match=r"unstable at table position 0\.55 m \(the loop at "
                                           r"rest there\): pole at .* Hz growing"):
        fdjax.simulate(ref, drive_, move, position_m=0.45, moving=True, twin=kw["twin"])
    ok = fdjax.simulate(ref, drive_, jerk_limited(1e-4, 0.05, 2.0, 400.0), position_m=0.3,
                        duration=dur, **kw)
    assert ok.result == fdjax.RESULTS.successful and float(ok.growth_rate) < 0


class _SpeedPI(fdjax.AbstractController):
    """u = PI(ṙ − v_m): a speed loop and nothing on the table position."""

    def law(self, position_m):
        return fdjax.Law((fdjax.Path({"r_dot": 1.0, "v_m": -1.0}, (fdjax.PI(150.0, 10.0),)),))


def test_runs_agree_with_the_eigenvalues_on_marginal_and_unstable_loops():
    """On the reference drive (twin of 4 modes):

    * a loop with a pole at s = 0 (no position feedback) runs to the end and is not called
      unstable (the growth estimate lies 1e-10 above the spectral radius, and 'growth ≥ 0' had
      raised "unstable ... growing at 1.8e-10 1/s"); its message names Y₀, not Y₀ + r(0);
    * an unstable continuous run's state is held below overflow: the gradient of its RMS
      error is finite (it was NaN, 0·∞ in the reverse pass, while the value was finite);
    * the moving table calls an unstable loop unstable, as the frozen run does (it said
      'diverged');
    * a filter above Nyquist is named eagerly with the moving table too, and a duration of
      True is not 1 s."""
    from fdjax._simulation._lifted import MARGINAL

    drive, tw = fdjax.reference_drive(), fdjax.TwinOptions(kept_modes=4)
    ref = jerk_limited(1e-3, 0.05, 2.0, 200.0, start=0.005)
    for method in (fdjax.SampledData(), fdjax.PadeODE()):
        run = fdjax.simulate(_SpeedPI(), drive, ref, method, position_m=0.4, twin=tw)
        assert run.result == fdjax.RESULTS.successful, run.message
        assert abs(float(run.growth_rate)) * 1.25e-4 < MARGINAL
        assert run.message == "simulation ok at table position 0.4 m"
    traj = jerk_limited(1e-3, 0.05, 2.0, 200.0)
    twin = fdjax.state_space(drive, 0.4, twin=tw)

    def rms(log_kv, plant, method, **kw):
        c = eqx.tree_at(lambda c: c.log_kv, fdjax.DoubleLoop(), log_kv)
        s = fdjax.simulate(c, plant, traj, method, duration=0.03, throw=False, **kw)
        return s.rms_error(), s.result

    (v, result), g = jax.value_and_grad(rms, has_aux=True)(jnp.log(1e8), twin, fdjax.PadeODE())
    assert result == fdjax.RESULTS.unstable and np.isfinite(float(v)), float(v)
    assert np.isfinite(float(g)), float(g)
    _, moving = rms(jnp.log(1e8), drive, fdjax.SampledData(), position_m=0.4, moving=True,
                    twin=tw)
    assert moving == fdjax.RESULTS.unstable
    notch = fdjax.DoubleLoop(mcm=fdjax.MCM(None, fdjax.NotchFilter(2 * np.pi * 5000, 0.05, 0.5)))
    with pytest.raises(ValueError, match=r"`simulate\(controller=\.\.\.\)` has a filter at 5000 "
                                         r"Hz, not below the Nyquist frequency 4000 Hz"):
        fdjax.simulate(notch, drive, traj, position_m=0.4, moving=True, twin=tw)
    with pytest.raises(ValueError, match=r"`simulate\(duration=\.\.\.\)` must be a number, got "
                                         r"the boolean True"):
        fdjax.simulate(notch, drive, traj, position_m=0.4, duration=True)
