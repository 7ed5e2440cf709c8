"""Reference motions: piecewise-constant-jerk Trajectory, jerk-limited moves, reciprocating strokes.

Oracles: the closed forms of the double-S profile derived by hand below (durations, peaks),
scipy's PPoly integrating the jerk exactly (independent of the knot-state recurrence), and the
analytic derivatives of a cubic. Tolerances are rounding bounds: a state is a sum of at most
k + 4 rounded terms, and a time τ = t − t_i carries an absolute error ε·T, so a quantity x with
rate ẋ is off by at most (k + 4)·ε·(|x| + |ẋ|·T) ("err" below).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jit_errors import CHECK_FAILED
from scipy.interpolate import PPoly

from fdjax._trajectory import Trajectory, concatenate, jerk_limited, reciprocating

EPS = np.finfo(np.float64).eps

# (distance, v_max, a_max, j_max) for each regime of the double-S profile.
FULL = (0.1, 0.1, 2.0, 200.0)  # v j = 20 ≥ a² = 4 and d ≥ v(v/a + a/j) = 6 mm: all limits reached
A_NOT = (0.01, 0.01, 2.0, 200.0)  # v j = 2 < a² = 4: triangular acceleration, cruise at v
V_NOT = (5e-3, 0.1, 2.0, 200.0)  # 2a³/j² = 0.4 mm ≤ d < 6 mm: a reached, v not (the defaults)
NEITHER = (2e-4, 0.1, 2.0, 200.0)  # d < 2a³/j²: neither a nor v reached
REGIMES = {"full": FULL, "a_not_reached": A_NOT, "v_not_reached": V_NOT, "neither": NEITHER}


def expected(d, v, a, j):
    """Hand-derived (T, v_peak, a_peak) of a rest-to-rest double-S move of length d > 0."""
    if (d, v, a, j) == FULL:
        return d / v + v / a + a / j, v, a
    if (d, v, a, j) == A_NOT:
        return d / v + 2 * np.sqrt(v / j), v, np.sqrt(v * j)
    if (d, v, a, j) == V_NOT:
        # v_p²/a + v_p a/j = d, T = 2(a/j + v_p/a)
        vp = (-(a * a / j) + np.sqrt((a * a / j) ** 2 + 4 * d * a)) / 2
        return a / j + np.sqrt((a / j) ** 2 + 4 * d / a), vp, a
    tj = np.cbrt(d / (2 * j))  # d = 2 j T_j³
    return 4 * tj, j * tj**2, j * tj


def scales(traj, v, a, j):
    """Rounding bounds (err_r, err_v, err_a) for a trajectory with limits v, a, j."""
    c = (traj.num_segments + 4) * EPS
    T = float(traj.duration)
    R = float(np.max(np.abs(traj.knot_states()[0])))
    return c * (R + v * T), c * (v + a * T), c * (a + j * T)


N = 1001  # one grid size everywhere, so each trajectory structure compiles `evaluate` once


def dense(traj):
    """N times: a grid over [−0.05 T, 1.05 T] plus every knot."""
    T = float(traj.duration)
    tk = np.asarray(traj.t_knots)
    return np.sort(np.concatenate([np.linspace(-0.05 * T, 1.05 * T, N - tk.size), tk]))


@pytest.mark.parametrize("name", list(REGIMES))
def test_regime_duration_and_peaks(name):
    d, v, a, j = REGIMES[name]
    traj = jerk_limited(d, v, a, j)
    T, vp, ap = expected(d, v, a, j)
    # The implementation and the closed form are different float expressions of the same number
    # (measured ≤ 4.4e-16 T over the four regimes)
    assert abs(float(traj.duration) - T) <= 8 * EPS * T
    _, vk, ak = (np.asarray(x) for x in traj.knot_states())
    err_r, err_v, err_a = scales(traj, v, a, j)
    assert abs(vk[3] - vp) <= err_v + 1e-12 * vp  # end of the acceleration phase
    assert abs(ak[1] - ap) <= err_a + 1e-12 * ap  # end of the first jerk phase
    assert np.all(np.asarray(traj.jerk)[[0, 6]] == j)
    assert np.all(np.asarray(traj.jerk)[[2, 4]] == -j)


@pytest.mark.parametrize("name", list(REGIMES))
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_limits_and_final_state(name, sign):
    d, v, a, j = REGIMES[name]
    start = 0.25
    traj = jerk_limited(sign * d, v, a, j, start=start)
    err_r, err_v, err_a = scales(traj, v, a, j)
    r, vel, acc, jrk = (np.asarray(x) for x in traj.evaluate(dense(traj)))
    assert np.max(np.abs(vel)) <= v + err_v
    assert np.max(np.abs(acc)) <= a + err_a
    assert np.max(np.abs(jrk)) <= j
    # Monotone move: the position stays between start and the goal.
    assert np.all(sign * (r - start) >= -err_r) and np.all(sign * (r - start) <= d + err_r)
    rk, vk, ak = (np.asarray(x) for x in traj.knot_states())
    assert abs(rk[-1] - (start + sign * d)) <= 1e-12 * d
    assert abs(vk[-1]) <= err_v and abs(ak[-1]) <= err_a
    # After the end the axis rests exactly.
    after = [np.asarray(x) for x in traj.evaluate(traj.duration + np.array([1e-9, 1.0]))]
    assert np.all(after[0] == rk[-1]) and all(np.all(x == 0) for x in after[1:])
    before = [np.asarray(x) for x in traj.evaluate(np.array([-1.0, -1e-9]))]
    assert np.all(before[0] == start) and all(np.all(x == 0) for x in before[1:])


def test_limits_reached_in_long_move():
    d, v, a, j = FULL
    traj = jerk_limited(d, v, a, j)
    err_r, err_v, err_a = scales(traj, v, a, j)
    _, vel, acc, jrk = (np.asarray(x) for x in traj.evaluate(dense(traj)))
    assert np.max(np.abs(vel)) >= v - err_v
    assert np.max(np.abs(acc)) >= a - err_a
    assert np.max(np.abs(jrk)) == j
    # Cruise at v_max for d/v − v/a − a/j.
    durations = np.diff(np.asarray(traj.t_knots))
    assert abs(durations[3] - (d / v - v / a - a / j)) <= 1e-12 * (d / v)


def test_moves_on_a_limits_boundary():
    """On the boundaries between regimes (v j = a², where the acceleration just reaches a; h
    = 2a³/j², where the move just reaches a without cruising) the constant-acceleration
    time is zero, and its rounding a few ulps below zero must not make the knots decrease
    (it did: 384 of 3000 random boundary cases were refused).  The move ends at rest at its
    distance and its total time is the closed form's."""
    rng = np.random.default_rng(0)
    for k in range(300):
        a, j = rng.uniform(0.5, 5.0), rng.uniform(10.0, 1000.0)
        v = a * a / j if k % 2 else rng.uniform(0.05, 1.0)
        h = 2.0 * a**3 / j**2 if k % 3 else v * (a / j + v / a)
        traj = jerk_limited(h, v, a, j)
        r, vel, acc, _ = (float(np.asarray(x)[0]) for x in traj.evaluate(
            np.array([float(traj.t_knots[-1])])))
        assert abs(r - h) <= 1e-12 * h and abs(vel) <= 1e-12 * v and abs(acc) <= 1e-12 * a
    # the paper's-scale examples that were refused: T = 4 T_j and 2 T_a at the boundary
    for h, v, a, j, total in ((0.02, 1.0, 1.0, 10.0, 0.4), (0.16, 1.0, 2.0, 10.0, 0.8)):
        assert abs(float(jerk_limited(h, v, a, j).t_knots[-1]) - total) <= 1e-15, (h, total)
    # on the boundary h = 2a³/j² (a reached for an instant): out and back, 4 a/j each
    edge = reciprocating(stroke=1e-3, v_max=1.0, a_max=5.0, j_max=500.0)
    assert abs(float(edge.duration) - 8 * 5.0 / 500.0) <= 4 * EPS * 0.08
    r, vel, acc, _ = (np.asarray(x) for x in edge.evaluate(np.array([0.04, 0.08])))
    err_r, err_v, err_a = scales(edge, 1.0, 5.0, 500.0)
    assert abs(r[0] - 1e-3) <= err_r and abs(r[1]) <= err_r
    assert np.all(np.abs(vel) <= err_v) and np.all(np.abs(acc) <= err_a)
    # limits far above what a move reaches: neither is reached, T = 4 (h/(2j))^{1/3} (the
    # boundary 2a³/j² overflowed in Python's power and raised OverflowError)
    for h, v, a, j in ((1e-3, 0.1, 1e120, 200.0), (1e-3, 1e200, 1e120, 200.0),
                       (1e-3, 0.1, 1e200, 1.0)):
        traj = jerk_limited(h, v, a, j)
        np.testing.assert_allclose(float(traj.duration), 4 * (h / (2 * j)) ** (1 / 3),
                                   rtol=1e-15)
    # a reached, v not, with a⁴/j² beyond floating point (a²/j = 1e20 is not): T = a/j +
    # √(a²/j² + 4h/a) (it gave a NaN duration)
    h, a, j = 1e-3, 1e160, 1e300
    traj = jerk_limited(h, 1e100, a, j)
    np.testing.assert_allclose(float(traj.duration), a / j + np.sqrt((a / j) ** 2 + 4 * h / a),
                               rtol=1e-15)


def test_mirror_dwell_and_null_move():
    d, v, a, j = V_NOT
    fwd = jerk_limited(d, v, a, j, start=0.1)
    back = jerk_limited(-d, v, a, j, start=0.1)
    t = dense(fwd)
    # Negating the jerk negates every integral exactly (sign flips are exact in floating point).
    np.testing.assert_array_equal(
        np.asarray(back.evaluate(t)[0]) - 0.1, -(np.asarray(fwd.evaluate(t)[0]) - 0.1)
    )
    dwell = 0.03
    held = jerk_limited(d, v, a, j, dwell=dwell)
    T = expected(d, v, a, j)[0]
    assert abs(float(held.duration) - (T + dwell)) <= 1e-12 * T
    r, vel, acc, _ = (np.asarray(x) for x in held.evaluate(np.linspace(T + 1e-9, T + dwell, 9)))
    err_r, err_v, err_a = scales(held, v, a, j)
    assert np.all(np.abs(r - d) <= 1e-12 * d + err_r)
    assert np.all(np.abs(vel) <= err_v) and np.all(np.abs(acc) <= err_a)
    null = jerk_limited(0.0, v, a, j, start=0.2, dwell=0.1)
    assert float(null.duration) == 0.1
    r, vel, acc, jrk = (np.asarray(x) for x in null.evaluate(np.linspace(-0.1, 0.3, 9)))
    assert np.all(r == 0.2) and not np.any(vel) and not np.any(acc) and not np.any(jrk)


@pytest.mark.parametrize("name", list(REGIMES))
def test_against_ppoly_oracle(name):
    """scipy integrates the piecewise-constant jerk thrice with continuity imposed at the knots."""
    d, v, a, j = REGIMES[name]
    traj = jerk_limited(d, v, a, j, start=-0.05, dwell=0.01)
    tk, jk = np.asarray(traj.t_knots), np.asarray(traj.jerk)
    keep = np.diff(tk) > 0
    x = np.concatenate([[0.0], tk[1:][keep]])
    jerk_pp = PPoly(jk[keep][None, :], x)
    acc_pp = jerk_pp.antiderivative(1)
    vel_pp = jerk_pp.antiderivative(2)
    pos_pp = jerk_pp.antiderivative(3)
    t = np.linspace(0.0, float(traj.duration), N)
    r, vel, acc, _ = (np.asarray(y) for y in traj.evaluate(t))
    err_r, err_v, err_a = scales(traj, v, a, j)
    np.testing.assert_allclose(r, -0.05 + pos_pp(t), rtol=0, atol=2 * err_r)
    np.testing.assert_allclose(vel, vel_pp(t), rtol=0, atol=2 * err_v)
    np.testing.assert_allclose(acc, acc_pp(t), rtol=0, atol=2 * err_a)


def test_a_long_motion_against_ppoly_oracle():
    """Five reciprocating cycles with dwells (80 segments): above 64 segments `evaluate`
    finds the segment by binary search instead of comparing with every knot; against scipy's
    piecewise polynomial on a grid, at every knot and one ulp either side of it (zero-length
    segments included).  Measured: 2.6e-16, 7.6e-16, 2.2e-15 of err_r, err_v, err_a's scales;
    the bounds are the per-move ones doubled, as above."""
    v, a, j = 0.1, 2.0, 200.0
    traj = reciprocating(stroke=5e-3, v_max=v, a_max=a, j_max=j, cycles=5, dwell=0.01)
    assert traj.num_segments > 64
    tk, jk = np.asarray(traj.t_knots), np.asarray(traj.jerk)
    keep = np.diff(tk) > 0
    x = np.concatenate([[0.0], tk[1:][keep]])
    jerk_pp = PPoly(jk[keep][None, :], x)
    acc_pp, vel_pp, pos_pp = (jerk_pp.antiderivative(n) for n in (1, 2, 3))
    T = float(traj.duration)
    t = np.clip(np.sort(np.concatenate([np.linspace(0.0, T, N), tk, np.nextafter(tk, -np.inf),
                                        np.nextafter(tk, np.inf)])), 0.0, T)
    r, vel, acc, jrk = (np.asarray(y) for y in traj.evaluate(t))
    err_r, err_v, err_a = scales(traj, v, a, j)
    np.testing.assert_allclose(r, float(traj.r0) + pos_pp(t), rtol=0, atol=2 * err_r)
    np.testing.assert_allclose(vel, vel_pp(t), rtol=0, atol=2 * err_v)
    np.testing.assert_allclose(acc, acc_pp(t), rtol=0, atol=2 * err_a)
    inside = (t > 0) & (t < T) & ~np.isin(t, tk)  # off the knots the jerk is the segment's
    np.testing.assert_array_equal(jrk[inside], jerk_pp(t[inside]))


@pytest.mark.parametrize("name", list(REGIMES))
def test_continuity_at_knots(name):
    """Evaluated one ulp either side of a knot, r, v, a differ by rate × 2 ulp + rounding."""
    d, v, a, j = REGIMES[name]
    traj = jerk_limited(d, v, a, j)
    err_r, err_v, err_a = scales(traj, v, a, j)
    tk = np.asarray(traj.t_knots)  # at 0 and T the move meets the rest states
    left = [np.asarray(x) for x in traj.evaluate(np.nextafter(tk, -np.inf))]
    right = [np.asarray(x) for x in traj.evaluate(np.nextafter(tk, np.inf))]
    gap = 2 * np.spacing(tk)
    assert np.all(np.abs(left[0] - right[0]) <= v * gap + 2 * err_r)
    assert np.all(np.abs(left[1] - right[1]) <= a * gap + 2 * err_v)
    assert np.all(np.abs(left[2] - right[2]) <= j * gap + 2 * err_a)


@pytest.mark.parametrize("name", ["full", "v_not_reached", "neither"])
def test_central_differences(name):
    """r ∈ C², ⃛r = j piecewise constant, |j| ≤ J. By Taylor with integral remainder,
    |(r(t+h) − r(t−h))/2h − v| ≤ J h²/6 and |(v(t+h) − v(t−h))/2h − a| ≤ J h/2 everywhere,
    plus rounding 2·err/2h; inside one segment (a(t+h) − a(t−h))/2h = j exactly."""
    d, v, a, j = REGIMES[name]
    traj = jerk_limited(d, v, a, j)
    err_r, err_v, err_a = scales(traj, v, a, j)
    h = 1e-5
    t = dense(traj)
    rp, vp, ap, _ = (np.asarray(x) for x in traj.evaluate(t + h))
    rm, vm, am, _ = (np.asarray(x) for x in traj.evaluate(t - h))
    _, vel, acc, _ = (np.asarray(x) for x in traj.evaluate(t))
    assert np.all(np.abs((rp - rm) / (2 * h) - vel) <= j * h**2 / 6 + err_r / h)
    assert np.all(np.abs((vp - vm) / (2 * h) - acc) <= j * h / 2 + err_v / h)
    tk = np.asarray(traj.t_knots)
    long = np.append(np.diff(tk) > 4 * h, False)
    mid = np.append((tk[:-1] + tk[1:]) / 2, tk[-1])  # N.B. k + 1 entries, like the knots
    ap, am = (np.asarray(traj.evaluate(mid + s)[2]) for s in (h, -h))
    jrk = np.asarray(traj.evaluate(mid)[3])
    assert np.all(np.abs((ap - am) / (2 * h) - jrk)[long] <= err_a / h)


def test_reciprocating():
    stroke, v, a, j = 4e-3, 0.08, 1.5, 150.0
    cycles, dwell, start = 3, 0.02, 0.3
    traj = reciprocating(stroke, v, a, j, cycles=cycles, dwell=dwell, start=start)
    # 2a³/j² = 0.3 mm ≤ 4 mm < v(v/a + a/j) = 5.07 mm: the v-not-reached regime.
    T = a / j + np.sqrt((a / j) ** 2 + 4 * stroke / a)
    period = 2 * T + 2 * dwell
    assert traj.num_segments == 16 * cycles
    assert abs(float(traj.duration) - cycles * period) <= 1e-12 * cycles * period
    # Knot-time rounding perturbs each segment length by δh ≤ ε·T; over k segments that moves
    # a by ≤ k·ε·T·j, v by ≤ k·ε·T·(a + j·T) and r by ≤ k·ε·T·(v + a·T + j·T²).
    Tt = float(traj.duration)
    c = traj.num_segments * EPS * Tt
    tol, tol_v, tol_a = c * (v + a * Tt + j * Tt**2), c * (a + j * Tt), c * j
    ends = np.asarray(traj.t_knots)[16 * np.arange(1, cycles + 1)]
    outs = np.asarray(traj.t_knots)[16 * np.arange(cycles) + 8]
    holds = np.linspace(T, T + dwell, 5)  # the axis rests at the far end for `dwell` s
    special = np.concatenate([ends, outs, holds])
    t = np.concatenate([special, dense(traj)[special.size :]])  # one evaluation of size N
    r, vel, acc, _ = (np.asarray(x) for x in traj.evaluate(t))
    n = cycles
    assert np.all(np.abs(r[:n] - start) <= tol + 1e-12 * stroke)
    assert np.all(np.abs(vel[:n]) <= tol_v) and np.all(np.abs(acc[:n]) <= tol_a)
    assert np.all(np.abs(r[n : special.size] - (start + stroke)) <= tol + 1e-12 * stroke)
    np.testing.assert_allclose(ends, period * np.arange(1, cycles + 1), rtol=1e-12)
    assert np.max(np.abs(vel)) <= v and np.max(np.abs(acc)) <= a + tol_a


def test_long_reciprocating_runs_keep_their_segments():
    """A move keeps its segments' exact lengths however late it plays: after 1000 cycles of
    0.3 m strokes (1450 s) every cycle ends at its start, at rest, to round-off (measured
    2.1e-18 m, 1.0e-17 m/s and exactly 0 m/s²: each cycle repeats the first's arithmetic).
    Lengths recovered as differences of knot times, ~ε·t off each, had left the axis 1.4 µm
    away at the end (3.4 µm at the worst cycle's end), at 1.5e-8 m/s."""
    traj = reciprocating(stroke=0.3, v_max=0.5, a_max=5.0, j_max=200.0, cycles=1000)
    h = np.asarray(traj.durations)
    # (by construction; what follows relies on it) the last cycle's segments are the first's
    np.testing.assert_array_equal(h[-16:], h[:16])
    r, v, a = (np.asarray(x) for x in traj.knot_states())
    # a few roundings of the stroke (ε·0.3 m = 7e-17 m) and of the peak speed
    assert np.max(np.abs(r[16::16])) <= 1e-15, np.max(np.abs(r[16::16]))
    assert np.max(np.abs(v[16::16])) <= 1e-15 and np.max(np.abs(a[16::16])) == 0.0
    # the knot times are the durations' running sum (as np.cumsum adds them)
    np.testing.assert_array_equal(np.asarray(traj.t_knots)[1:], np.cumsum(h))
    # knot times given by hand are kept to their rounding
    tk = np.array([0.0, 0.1, 0.3, 0.7])
    mine = Trajectory(t_knots=tk, jerk=[1.0, 0.0, -1.0])
    np.testing.assert_allclose(np.asarray(mine.t_knots), tk, rtol=2 * EPS, atol=0)
    np.testing.assert_array_equal(np.asarray(mine.durations), np.diff(tk))


def test_reciprocating_defaults():
    """5 mm at 0.1 m/s, 2 m/s², 200 m/s³: T = a/j + √(a²/j² + 4h/a) = 0.01 + √0.0101 s."""
    traj = reciprocating()
    T = 0.01 + np.sqrt(0.0101)
    assert abs(float(traj.duration) - 2 * T) <= 1e-12 * T
    assert 0.2 < float(traj.duration) < 0.25
    samples = np.asarray(traj.sample(np.linspace(0.0, 0.5, N)))
    assert samples.shape == (N, 3)
    assert np.max(samples[:, 0]) <= 5e-3 * (1 + 1e-12) and samples[-1, 0] == samples[-2, 0]


def test_concatenate_and_rest_check():
    d, v, a, j = V_NOT
    one = jerk_limited(d, v, a, j, start=0.1)
    two = jerk_limited(2 * d, v, a, j, start=1.0)  # its r0 is ignored: moves are relative
    both = concatenate(one, two)
    T1 = float(one.duration)
    t = np.linspace(0.0, float(two.duration), N)
    np.testing.assert_allclose(
        np.asarray(both.evaluate(T1 + t)[0]),
        np.asarray(two.evaluate(t)[0]) - 1.0 + 0.1 + d,
        rtol=0,
        atol=4 * (scales(both, v, a, j)[0] + scales(two, v, a, j)[0]),
    )
    single = concatenate(one)
    np.testing.assert_array_equal(np.asarray(single.t_knots), np.asarray(one.t_knots))
    assert float(both.duration) == pytest.approx(T1 + float(two.duration), rel=1e-15)
    ramp = Trajectory(t_knots=[0.0, 1.0], jerk=[1.0])
    with pytest.raises(ValueError, match=r"`concatenate\(\*trajectories\)`: trajectory 0 must end"):
        concatenate(ramp, one)
    # a piece whose durations were edited to what no constructor makes
    bad = eqx.tree_at(lambda t: t.durations, two, two.durations.at[3].set(-1.0))
    with pytest.raises(ValueError, match=r"`concatenate\(\*trajectories\)` must be made of "
                                         r"segments of finite, non-negative durations, .*got "
                                         r"-1 at index 11"):
        concatenate(one, bad)
    # finite durations whose sum is not: the knot time where it overflows is named
    far = Trajectory(t_knots=[0.0, 1e308], jerk=[0.0])
    with pytest.raises(ValueError, match=r"finite knot times \(their running sum\), got "
                                         r"1e\+308 at index 1$"):
        concatenate(far, far)
    with pytest.raises(ValueError, match=r"needs at least one Trajectory"):
        concatenate()
    with pytest.raises(ValueError, match=r"takes Trajectory objects, got str at position 1"):
        concatenate(one, "two")


def test_sample_shape_and_values():
    traj = jerk_limited(*FULL)
    t = np.linspace(0.0, 1.0, 9)
    s = np.asarray(traj.sample(t))
    assert s.shape == (9, 3) and s.dtype == np.float64
    r, vel, acc, _ = traj.evaluate(t)
    np.testing.assert_array_equal(s, np.stack([r, vel, acc], -1))
    assert np.asarray(traj.sample(np.zeros((2, 4)))).shape == (2, 4, 3)
    assert np.asarray(traj.evaluate(0.5)[0]).shape == ()
    # Integer times are accepted (cast to float64) under strict promotion.
    np.testing.assert_array_equal(
        np.asarray(traj.evaluate(jnp.arange(2))[0]),
        np.asarray(traj.evaluate(np.array([0.0, 1.0]))[0]),
    )


def test_jit_vmap_no_retrace():
    traj = jerk_limited(*FULL)
    t = jnp.linspace(-0.1, 1.2, 9)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(tr, t):
        return tr.evaluate(t)

    eager = traj.evaluate(t)
    err = scales(traj, *FULL[1:])
    for got, want, e in zip(run(traj, t), eager, (*err, 0.0)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=2 * e)
    other = jerk_limited(0.05, 0.1, 2.0, 200.0, start=0.1)  # same structure: no new trace
    run(other, t)
    mapped = jax.vmap(traj.evaluate)(t)
    looped = [traj.evaluate(ti) for ti in t]
    for n in range(4):
        np.testing.assert_allclose(
            np.asarray(mapped[n]),
            np.array([np.asarray(x[n]) for x in looped]),
            rtol=0,
            atol=2 * (*err, 0.0)[n],
        )
    # vmap over trajectories of the same structure.
    stacked = jax.tree_util.tree_map(lambda x, y: jnp.stack([x, y]), traj, other)
    r = jax.vmap(lambda tr: tr.evaluate(0.5)[0])(stacked)
    np.testing.assert_allclose(
        np.asarray(r), [traj.evaluate(0.5)[0], other.evaluate(0.5)[0]], rtol=1e-14
    )


def test_grad_wrt_time_is_velocity():
    traj = jerk_limited(*V_NOT)
    err_r, err_v, err_a = scales(traj, *V_NOT[1:])
    t = jnp.asarray(dense(traj))
    dr = jax.vmap(jax.grad(lambda s: traj.evaluate(s)[0]))(t)
    dv = jax.vmap(jax.grad(lambda s: traj.evaluate(s)[1]))(t)
    _, vel, acc, _ = traj.evaluate(t)
    np.testing.assert_allclose(np.asarray(dr), np.asarray(vel), rtol=0, atol=2 * err_v)
    inside = (t > 0) & (t < traj.duration)
    np.testing.assert_allclose(
        np.asarray(dv)[inside], np.asarray(acc)[inside], rtol=0, atol=2 * err_a
    )


def test_grad_wrt_leaves():
    """r is linear in (r0, jerk): ∂r/∂r0 = 1 and ∂r(t; c·jerk)/∂c = r(t) − r0. Time scaling
    t_knots → s·t_knots, jerk → jerk/s³ gives r_s(t) = r(t/s), so ∂r_s(t)/∂s|₁ = −t·v(t)."""
    d, v, a, j = V_NOT
    traj = jerk_limited(d, v, a, j, start=0.2)
    err_r, err_v, _ = scales(traj, v, a, j)
    t = jnp.linspace(0.0, 0.105, 9)  # inside the move, so t/s stays in range for s near 1
    r, vel, _, _ = traj.evaluate(t)

    @eqx.filter_jit
    def grads(traj):
        g = eqx.filter_grad(lambda tr: jnp.sum(tr.evaluate(t)[0]))(traj)
        dc = jax.jacfwd(lambda c: Trajectory(traj.t_knots, c * traj.jerk, traj.r0).evaluate(t)[0])(
            1.0
        )
        ds = jax.jacfwd(
            lambda s: Trajectory(s * traj.t_knots, traj.jerk / s**3, traj.r0).evaluate(t)[0]
        )(1.0)
        return g.r0, dc, ds

    g_r0, dc, ds = grads(traj)
    assert float(g_r0) == t.shape[0]
    np.testing.assert_allclose(np.asarray(dc), np.asarray(r) - 0.2, rtol=0, atol=2 * err_r)
    np.testing.assert_allclose(
        np.asarray(ds),
        -np.asarray(t) * np.asarray(vel),
        rtol=0,
        atol=8 * err_v * float(traj.duration),
    )


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda: jerk_limited(np.nan, 0.1, 2.0, 200.0),
            r"`jerk_limited\(distance=\.\.\.\)` must be finite \(no NaN or inf\), got nan",
        ),
        (
            lambda: jerk_limited(0.1, -1, 2.0, 200.0),
            r"`jerk_limited\(v_max=\.\.\.\)` must be finite and positive, got -1",
        ),
        (
            lambda: jerk_limited(0.1, 0.1, 0.0, 200.0),
            r"`jerk_limited\(a_max=\.\.\.\)` must be finite and positive, got 0",
        ),
        (
            lambda: jerk_limited(0.1, 0.1, 2.0, np.inf),
            r"`jerk_limited\(j_max=\.\.\.\)` must be finite and positive, got inf",
        ),
        (
            lambda: jerk_limited(0.1, 0.1, 2.0, 200.0, dwell=-0.1),
            r"`jerk_limited\(dwell=\.\.\.\)` must be finite and non-negative, got -0.1",
        ),
        (
            lambda: jerk_limited(0.1, 0.1, 2.0, 200.0, start=np.inf),
            r"`jerk_limited\(start=\.\.\.\)` must be finite",
        ),
        (
            lambda: jerk_limited(1j, 0.1, 2.0, 200.0),
            r"`jerk_limited\(distance=\.\.\.\)` must be real",
        ),
        (
            lambda: jerk_limited([0.1, 0.2], 0.1, 2.0, 200.0),
            r"`jerk_limited\(distance=\.\.\.\)` must be a scalar, got shape \(2,\)",
        ),
        (
            lambda: jax.jit(lambda d: jerk_limited(d, 0.1, 2.0, 200.0).duration)(0.1),
            r"`jerk_limited\(distance=\.\.\.\)` must be a concrete number",
        ),
        (
            lambda: reciprocating(cycles=0),
            r"`reciprocating\(cycles=\.\.\.\)` must be an integer at least 1, got 0",
        ),
        (lambda: reciprocating(cycles=1.5), r"`reciprocating\(cycles=\.\.\.\)` must be an integer"),
        (
            lambda: reciprocating(cycles=True),
            r"`reciprocating\(cycles=\.\.\.\)` must be an integer",
        ),
        (lambda: reciprocating(stroke=np.inf), r"`reciprocating\(stroke=\.\.\.\)` must be finite"),
        (
            lambda: reciprocating(j_max=-5.0),
            r"`reciprocating\(j_max=\.\.\.\)` must be finite and positive, got -5",
        ),
        (
            lambda: reciprocating(dwell=-1.0),
            r"`reciprocating\(dwell=\.\.\.\)` must be finite and non-negative, got -1",
        ),
        (
            lambda: Trajectory(t_knots=[0.0, 1.0, 0.5], jerk=[1.0, 1.0]),
            r"`Trajectory\(t_knots=\.\.\.\)` must be finite, non-decreasing and start at 0, "
            r"got 0.5 at index 2",
        ),
        (
            lambda: Trajectory(t_knots=[0.1, 1.0], jerk=[1.0]),
            r"`Trajectory\(t_knots=\.\.\.\)` must be .*start at 0, got 0.1 at index 0",
        ),
        (
            lambda: Trajectory(t_knots=[0.0, 1.0], jerk=[1.0, 2.0]),
            r"`Trajectory\(jerk=\.\.\.\)` must have one entry per segment "
            r"\(len\(t_knots\) - 1 = 1\)",
        ),
        (
            lambda: Trajectory(t_knots=[0.0], jerk=[]),
            r"`Trajectory\(t_knots=\.\.\.\)` must hold at least two knots",
        ),
        (
            lambda: Trajectory(t_knots=[[0.0, 1.0]], jerk=[1.0]),
            r"`Trajectory\(t_knots=\.\.\.\)` must be a 1-D array, got shape \(1, 2\)",
        ),
        (
            lambda: Trajectory(t_knots=[0.0, 1.0], jerk=[np.nan]),
            r"`Trajectory\(jerk=\.\.\.\)` must be finite",
        ),
        (
            lambda: Trajectory(t_knots=[0.0, 1.0], jerk=[1.0], r0=[0.0]),
            r"`Trajectory\(r0=\.\.\.\)` must be a scalar, got shape \(1,\)",
        ),
        (
            lambda: jerk_limited(*FULL).evaluate(1j),
            r"`Trajectory.evaluate\(t=\.\.\.\)` must be real",
        ),
    ],
)
def test_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize("call, match", [
    (lambda: Trajectory("abc", [1.0]), r"`Trajectory\(t_knots=\.\.\.\)` must be a number or "
                                       r"an array of numbers, got 'abc'"),
    (lambda: Trajectory([0.0, 1.0], [1.0], None), r"`Trajectory\(r0=\.\.\.\)` must be a number"),
    (lambda: jerk_limited(*FULL).evaluate("0.1"),
     r"`Trajectory\.evaluate\(t=\.\.\.\)` must be a number or an array of numbers, got '0.1'"),
    (lambda: jerk_limited(*FULL).sample(None), r"`Trajectory\.sample\(t=\.\.\.\)` must be a "
                                               r"number or an array of numbers, got None"),
])
def test_what_is_not_numbers_is_named(call, match):
    with pytest.raises(TypeError, match=match):
        call()


def test_errors_under_jit():
    """Knots traced inside jit are checked when the program runs (eqx.error_if)."""

    @eqx.filter_jit
    def position(t_knots):
        return Trajectory(t_knots, jnp.ones(2, jnp.float64)).evaluate(0.5)[0]

    assert float(position(jnp.array([0.0, 1.0, 2.0]))) == pytest.approx(0.5**3 / 6, rel=1e-14)
    with pytest.raises(CHECK_FAILED,
                       match=r"Trajectory\(t_knots=\.\.\.\)` must be finite, non-decr"):
        jax.block_until_ready(position(jnp.array([0.0, 1.0, 0.5])))


def _random_trajectory(seed: int, k: int = 24) -> Trajectory:
    """Random knots (with zero-length segments) and jerks: extremes inside segments, where the
    velocity has one, two or no roots, and at knots."""
    rng = np.random.default_rng(seed)
    h = rng.uniform(0.0, 0.05, k) * (rng.uniform(size=k) > 0.15)
    jerk = rng.normal(0.0, 300.0, k) * (rng.uniform(size=k) > 0.2)  # some j = 0 segments
    return Trajectory(np.concatenate([[0.0], np.cumsum(h)]), jerk, rng.normal(0.2, 0.05))


@pytest.mark.parametrize(
    "traj",
    [
        reciprocating(),
        reciprocating(stroke=-3e-3, cycles=2, dwell=0.01, start=0.3),
        jerk_limited(0.3, *FULL[1:], start=0.1),
        jerk_limited(-0.2, *A_NOT[1:]),
        *[_random_trajectory(s) for s in range(4)],
    ],
)
def test_position_range_is_exact(traj):
    """(min r, max r) against a dense sampling of r(t) over [−0.01, T + 0.01].

    No sample may lie outside the exact range (this catches a missed interior extremum), and
    the sampled extremes fall short of it by at most what the nearest sample, within Δt/2 of
    the extremum t*, can miss: |v(t*)| Δt/2 + max|a| (Δt/2)²/2, where v(t*) = 0 unless the
    extremum is at a knot (or at rest before 0 / after T).
    """
    lo, hi = (float(x) for x in traj.position_range())
    T = float(traj.duration)
    t = np.linspace(-0.01, T + 0.01, 400_001)
    r, v, a, _ = (np.asarray(x) for x in traj.evaluate(t))
    dt = t[1] - t[0]
    gap = np.max(np.abs(v)) * dt / 2 + np.max(np.abs(a)) * dt**2 / 8
    rnd = 64 * EPS * max(abs(lo), abs(hi))  # round-off of the cubic and the knot recurrence
    assert lo <= r.min() + rnd and hi >= r.max() - rnd
    assert r.min() - lo <= gap + rnd and hi - r.max() <= gap + rnd


def test_position_range_interior_extremum_closed_form():
    """One segment from rest with jerk j over h, then a segment with a = a₁, v = v₁ and jerk
    −j: the velocity v₁ + a₁τ − jτ²/2 vanishes at τ* = (a₁ + √(a₁² + 2jv₁))/j, where
    r = r₁ + v₁τ* + a₁τ*²/2 − jτ*³/6 is the maximum (it overshoots the knots)."""
    j, h = 100.0, 0.1
    traj = Trajectory([0.0, h, 4 * h], [j, -j], 0.5)
    a1, v1, r1 = j * h, j * h**2 / 2, 0.5 + j * h**3 / 6
    tau = (a1 + np.sqrt(a1**2 + 2 * j * v1)) / j
    assert tau < 3 * h
    r_max = r1 + v1 * tau + a1 * tau**2 / 2 - j * tau**3 / 6
    lo, hi = traj.position_range()
    np.testing.assert_allclose(float(hi), r_max, rtol=4 * EPS)
    assert float(lo) == 0.5
    rk = np.asarray(traj.knot_states()[0])
    assert float(hi) > rk.max() + 1e-3  # strictly inside a segment, above every knot
    # its gradient, through the interior root (the envelope theorem: r'(τ*) = 0, so only the
    # explicit dependences count): ∂/∂h₀ = j(h + τ*)²/2, ∂/∂h₁ = 0, ∂/∂j₀ = h³/6 + τ*h²/2 +
    # τ*²h/2, ∂/∂j₁ = τ*³/6, ∂/∂r0 = 1; measured 3.7e-16 relative
    g = eqx.filter_jit(eqx.filter_grad(lambda tr: tr.position_range()[1]))(traj)
    np.testing.assert_allclose(np.asarray(g.durations), [j * (h + tau) ** 2 / 2, 0.0],
                               rtol=1e-13, atol=0)
    np.testing.assert_allclose(
        np.asarray(g.jerk), [h**3 / 6 + tau * h**2 / 2 + tau**2 * h / 2, tau**3 / 6],
        rtol=1e-13)
    assert float(g.r0) == 1.0


def test_position_range_under_jit_grad_and_no_retrace():
    traj = reciprocating()

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def extent(tr):
        return tr.position_range()

    for start in (0.0, 0.2, 0.4):
        lo, hi = extent(Trajectory(traj.t_knots, traj.jerk, start))
        np.testing.assert_allclose([float(lo), float(hi)], [start, start + 5e-3], atol=1e-15)
    # d(max r)/d(jerk scale c): r scales with c, so d hi/dc = hi − r0 at c = 1
    g = jax.grad(lambda c: Trajectory(traj.t_knots, c * traj.jerk, 0.1).position_range()[1])(1.0)
    np.testing.assert_allclose(float(g), 5e-3, rtol=1e-14)  # measured 3.5e-16


def test_a_move_in_mm_is_refused():
    """A distance or stroke longer than any ball-screw axis (``LONGEST_TRAVEL_M`` = 20 m either
    way) was given in mm: refused with its value in metres (300. used to plan a 300 m move).
    Up to 20 m a move is planned as before; a value that is too long even in mm is refused
    without the hint."""
    msg = r" must be inside the longest travel of a ball-screw axis \[-20, 20\] m, got "
    with pytest.raises(ValueError, match=r"^`jerk_limited\(distance=\.\.\.\)`" + msg +
                       r"300; move lengths are in metres: 300 mm is 0\.3 m$"):
        jerk_limited(300.0, 0.1, 2.0, 200.0)
    with pytest.raises(ValueError, match=r"^`reciprocating\(stroke=\.\.\.\)`" + msg +
                       r"-25; move lengths are in metres: -25 mm is -0\.025 m$"):
        reciprocating(stroke=-25.0)
    with pytest.raises(ValueError, match=r"^`jerk_limited\(distance=\.\.\.\)`" + msg + r"30000$"):
        jerk_limited(3e4, 0.1, 2.0, 200.0)
    rk, _, _ = jerk_limited(-20.0, 1.0, 2.0, 200.0, start=1.0).knot_states()
    assert float(rk[-1]) == pytest.approx(-19.0, rel=1e-12)


def test_start_and_dwell_may_be_traced_and_the_limits_are_named_when_too_small():
    """``start`` and ``dwell`` are leaves (r0, a rest duration): under ``vmap`` and ``grad``
    they give what the eager call gives, and a reciprocating cycle lasts 2·dwell longer per unit
    of dwell (exactly: the duration is a sum of segments); the limits and the stroke, which fix
    the segments, still must be concrete.  A limit so small that the durations overflow is
    named with the function called, not reported as a non-finite result of another."""
    starts = jnp.array([0.1, 0.2])
    ends = jax.vmap(lambda s: reciprocating(start=s, cycles=2).evaluate(0.05)[0])(starts)
    eager = [float(reciprocating(start=float(s), cycles=2).evaluate(0.05)[0]) for s in starts]
    np.testing.assert_array_equal(np.asarray(ends), eager)
    assert float(jax.grad(lambda w: reciprocating(dwell=w, cycles=3).duration)(0.01)) == 6.0
    assert float(jax.grad(lambda w: jerk_limited(*FULL, dwell=w).duration)(0.0)) == 1.0
    with pytest.raises(CHECK_FAILED, match=r"`reciprocating\(dwell=\.\.\.\)` must be finite "
                                           r"and non-negative"):
        jax.block_until_ready(jax.jit(lambda w: reciprocating(dwell=w).duration)(-1.0))
    with pytest.raises(ValueError, match=r"`reciprocating\(v_max=\.\.\.\)` must be a concrete"):
        jax.jit(lambda v: reciprocating(v_max=v).duration)(0.1)
    with pytest.raises(ValueError, match=r"`reciprocating\(v_max=\.\.\., a_max=\.\.\., "
                                         r"j_max=\.\.\.\)` are too small for a move of 0\.005 m"
                                         r": its durations overflow \(got v_max="):
        reciprocating(v_max=1e-320)
    with pytest.raises(ValueError, match=r"`jerk_limited\(v_max=\.\.\., a_max=\.\.\., "
                                         r"j_max=\.\.\.\)` are too small for a move of 0\.1 m"):
        jerk_limited(0.1, 0.1, 2.0, 1e-320)


def test_concatenate_refuses_a_moving_piece_under_jit_too():
    """A piece that does not end at rest is refused when its durations are traced too (it was
    joined silently: the velocity jumped from 0.61 m/s to 0 at the join); pieces at rest join
    under jit as they do eagerly."""
    ramp = Trajectory(t_knots=[0.0, 1.0], jerk=[1.0])
    one = jerk_limited(5e-3, 0.1, 2.0, 200.0)
    t = jnp.array([0.5, 1.1, 2.0])
    run = eqx.filter_jit(lambda a, b: concatenate(a, b).evaluate(t)[0])
    with pytest.raises(CHECK_FAILED, match=r"`concatenate\(\*trajectories\)`: every trajectory "
                                           r"but the last must end at rest"):
        jax.block_until_ready(run(ramp, one))
    two = jerk_limited(-5e-3, 0.1, 2.0, 200.0)
    np.testing.assert_array_equal(np.asarray(run(one, two)),
                                  np.asarray(concatenate(one, two).evaluate(t)[0]))


def test_derivatives_at_the_end_of_a_moving_trajectory_are_its_rates():
    """r(t) = t³ on [0, 1], held after: at t = T exactly, dr/dt and dv/dt equal the v and a that
    ``evaluate`` gives (3 and 6: the clamp to [0, T] is a selection; jnp.clip had split the
    derivative in half, 1.5 and 3)."""
    cube = Trajectory(t_knots=[0.0, 1.0], jerk=[6.0])
    _, v, a, _ = cube.evaluate(1.0)
    assert (float(v), float(a)) == (3.0, 6.0)
    assert float(jax.grad(lambda s: cube.evaluate(s)[0])(1.0)) == 3.0
    assert float(jax.grad(lambda s: cube.evaluate(s)[1])(1.0)) == 6.0
    assert float(jax.grad(lambda s: cube.evaluate(s)[0])(1.5)) == 0.0  # held after T
