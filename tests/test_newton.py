"""Trust-region Newton local tuning: the exact subproblem, and the tuner on the drive."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compile_events import compilations
from jit_errors import CHECK_FAILED

import fdjax
from fdjax._tune._local import _settled
from fdjax._tune._newton import _Newton, _run_cycles, _values, trust_region_step

# J with its gradient and Hessian at each position in a program of its own (not the tuner's):
# the oracle of the tuner's first step
_evaluate = eqx.filter_jit(_values)


def _at(par, obj, drive, y, theta, split=False):
    """J, ∇J and the model's Hessian at each position, as the tuner's steps compute them, in the
    tuner's own program: its loop called with the start alone (no cycle, the zero first step
    that evaluates the start), with the arguments tune_newton gives it for a chunk ≤ 10 (one
    program compiled for the tuner and these checks, not a second of its own).  Returns the
    iterate: ``j``, ``g``, ``H`` (with ``split``: the margin term's Hessian, and ``g_m``)."""
    n, p = theta.shape
    zeros = jnp.zeros((n, p, p))
    st = _settled(_Newton(jnp.asarray(theta), jnp.zeros(n), jnp.zeros((n, p)), zeros,
                          jnp.full(n, 0.3), zeros, jnp.zeros((n, p))))
    st, _ = _run_cycles(par, obj, drive, y, st, jnp.asarray(0), every=jnp.asarray(1),
                        split=split, quasi=jnp.asarray(False), rows=20,
                        start=jnp.asarray(True), shrink=jnp.asarray(0.25),
                        max_radius=jnp.asarray(5.0))
    return st


def _conditions(g, H, delta, p):
    """Moré–Sorensen: p solves the subproblem iff (H + λI)p = −g with λ ≥ 0, λ(Δ − ‖p‖) = 0
    and H + λI positive semi-definite.  Returns λ (from the equation, by least squares), the
    equation's residual, ‖p‖/Δ and the least eigenvalue of H + λI."""
    lam = float(-(p @ (H @ p + g)) / (p @ p))
    res = np.linalg.norm((H + lam * np.eye(len(g))) @ p + g) / np.linalg.norm(g)
    return lam, res, np.linalg.norm(p) / delta, np.linalg.eigvalsh(H + lam * np.eye(len(g)))[0]


def test_trust_region_step_solves_the_subproblem():
    """Definite and indefinite H, interior and boundary solutions, and the hard case (g ⊥ the
    least eigenvector of an indefinite H): every step meets the optimality conditions to
    round-off (measured: residual ≤ 4e-13, ‖p‖/Δ − 1 ≤ 3e-15, least eigenvalue of H + λI ≥
    −4e-16 relative), the model's decrease is what the function returns, and vmap equals the
    loop."""
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    cases = []
    for w in ([1.0, 2.0, 5.0, 10.0, 1e3, 3e4],        # definite (stiff, as the tuning problem)
              [-0.5, 0.1, 1.0, 4.0, 36.0, 3e4]):       # indefinite
        H = Q @ np.diag(w) @ Q.T
        g = rng.normal(size=6)
        for delta in (1e-3, 0.1, 10.0):
            cases.append((g, H, delta))
    H = Q @ np.diag([-2.0, 1.0, 3.0, 4.0, 5.0, 6.0]) @ Q.T
    cases.append((Q[:, 1] + 0.5 * Q[:, 3], H, 5.0))     # hard case: g ⊥ Q[:, 0]
    out = jax.vmap(trust_region_step)(*(jnp.asarray(np.stack(c)) for c in zip(*cases)))
    for k, (g, H, delta) in enumerate(cases):
        p, dec = trust_region_step(g, H, delta)
        p = np.asarray(p)
        np.testing.assert_allclose(p, np.asarray(out[0][k]), rtol=1e-12, atol=1e-15)
        lam, res, ratio, least = _conditions(g, H, delta, p)
        scale = np.abs(np.linalg.eigvalsh(H)).max()
        assert res < 1e-10, (k, res)  # round-off × cond(H + λI), up to 4e6 here
        assert ratio <= 1 + 1e-12, (k, ratio)
        assert lam >= -1e-9 * scale, (k, lam)
        assert abs(lam) * (1 - ratio) <= 1e-9 * scale, (k, lam, ratio)
        assert least >= -1e-12 * scale, (k, least)
        np.testing.assert_allclose(float(dec), -(g @ p + 0.5 * p @ H @ p), rtol=1e-12)
        # no feasible step does better (a thousand random ones on and inside the boundary)
        q = rng.normal(size=(1000, 6))
        q *= delta * rng.uniform(0, 1, size=(1000, 1)) ** (1 / 6) / np.linalg.norm(
            q, axis=1, keepdims=True)
        model = q @ g + 0.5 * np.einsum("ij,jk,ik->i", q, H, q)
        assert np.all(model >= -float(dec) - 1e-12 * (1 + abs(float(dec)))), k
    # the hard case's step lies on the boundary and uses the least eigenvector
    lam, _, ratio, _ = _conditions(*cases[-1][:3], np.asarray(trust_region_step(*cases[-1])[0]))
    assert abs(ratio - 1) < 1e-12 and abs(lam - 2.0) < 1e-9, (ratio, lam)
    # a radius that is not positive, or shapes that do not match, are named
    for radius in (-1.0, 0.0, np.nan):
        with pytest.raises(ValueError, match=r"`trust_region_step\(radius=\.\.\.\)` must be "
                                             r"finite and positive"):
            trust_region_step(np.ones(3), -np.eye(3), radius)
    # and under jit, where the radius is traced
    with pytest.raises(CHECK_FAILED, match=r"`trust_region_step\(radius=\.\.\.\)` must be "
                                           r"finite and positive"):
        jax.jit(trust_region_step)(np.ones(3), -np.eye(3), -1.0)
    with pytest.raises(ValueError, match=r"must have shapes \(p,\) and \(p, p\), got \(3,\) "
                                         r"and \(2, 2\)"):
        trust_region_step(np.ones(3), np.eye(2), 1.0)
    # a NaN or ∞ in g or H gave a NaN step silently
    bad_H = np.eye(3)
    bad_H[1, 2] = np.inf
    for args, name in (((np.array([1.0, np.nan, 0.0]), np.eye(3)), "g"), ((np.ones(3), bad_H),
                                                                          "H")):
        with pytest.raises(ValueError, match=rf"`trust_region_step\({name}=\.\.\.\)` must be "
                                             r"finite \(no NaN or inf\), got"):
            trust_region_step(*args, 1.0)
        with pytest.raises(CHECK_FAILED, match=rf"`trust_region_step\({name}=\.\.\.\)` must be "
                                               r"finite"):
            jax.block_until_ready(jax.jit(trust_region_step)(*args, 1.0))


def _problem():
    """The benchmark's local problem, smaller: from the reference controller with k_v halved
    (stable at every position)."""
    import math

    drive = fdjax.reference_drive()
    ref_c = fdjax.reference_controller(drive)
    start = eqx.tree_at(lambda c: c.log_kv, ref_c, ref_c.log_kv + math.log(0.5))
    par = fdjax.DoubleLoopParameterisation(fdjax.MCMBounds.for_servo(fdjax.Servo()), ref_c)
    ref = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    obj = fdjax.Objective(ref, np.geomspace(5.0, 3900.0, 64), twin=fdjax.TwinOptions(kept_modes=4))
    return drive, start, par, obj


def test_tune_newton_lowers_the_objective_with_the_exact_hessian():
    """Four steps at two positions halve J at both (measured 7.87 → 3.79 and 19.1 → 3.25); every
    accepted J is below the one before; the Hessian the steps use is the derivative of the
    gradient (central differences of the compiled gradient along two parameters, h = 1e-4:
    measured 3e-7 and 6e-7 relative, the differences' truncation error)."""
    drive, start, par, obj = _problem()
    pos = np.array([0.115, 0.3])
    with compilations() as names:
        r = fdjax.tune_newton(par, obj, drive, pos, start, steps=4, chunk=2)
    # the start is evaluated by the first call of the steps' program, not by one of its own
    assert not [n for n in names if "_values" in n], names
    h = np.asarray(r.history)
    assert h.shape == (5, 2) and np.all(np.isfinite(h))
    # J at the start is the objective's (compiled in the loop against op by op: measured
    # 1.7e-11 relative)
    eager = [float(obj(start, drive, float(p)).total) for p in pos]
    np.testing.assert_allclose(h[0], eager, rtol=5e-11)
    assert np.asarray(r.evaluations).shape == (4, 2)
    j = np.asarray(r.terms.total)
    print("J", h[0], "->", j)
    assert np.all(j < 0.5 * h[0]), (h[0], j)
    assert np.all(np.asarray(r.terms.stable))
    accepted = np.minimum.accumulate(h, axis=0)
    np.testing.assert_allclose(accepted[-1], j, rtol=1e-12)
    # new positions and a new start (same shapes) run the programs compiled for the first call
    with compilations() as names:
        again = fdjax.tune_newton(par, obj, drive, np.array([0.2, 0.6]), r.theta, steps=4,
                                  chunk=2)
    assert names == [], names
    assert np.all(np.asarray(again.terms.total) < 0.9 * np.asarray(again.history)[0])
    # the exact Hessian every other step, SR1 updates between: J falls as far in four steps.
    # With a chunk of one step, below hessian_every, the steps run as calls of gradient steps
    # and the exact step alone; the exact step in the program above (a chunk below the
    # default runs in the default chunk's programs): only the gradient steps compile
    with compilations() as names:
        sr1 = fdjax.tune_newton(par, obj, drive, pos, start, steps=4, hessian_every=2, chunk=1)
    assert not [n for n in names if "_run_cycles" in n], names
    assert [n for n in names if "_run_gradient_steps" in n], names
    assert np.all(np.asarray(sr1.terms.total) < 0.6 * np.asarray(sr1.history)[0])  # 0.57, 0.17
    # its start, evaluated alone (the steps' program with no step), is the first run's (the
    # same program, called for the start alone: measured equal)
    np.testing.assert_allclose(np.asarray(sr1.history)[0], h[0], rtol=1e-14)
    # the exact Hessian at the start only (hessian_every past the steps): the start alone,
    # then gradient steps with SR1 updates, in the programs of the run above (the history is
    # sized by the chunk, not by hessian_every: 2·10⁹ rows had been allocated)
    with compilations() as names:
        only = fdjax.tune_newton(par, obj, drive, pos, start, steps=2, hessian_every=10**9,
                                 chunk=1)
    assert not [n for n in names if "_run" in n], names
    np.testing.assert_array_equal(np.asarray(only.history)[0], h[0])
    assert np.all(np.asarray(only.terms.total) < h[0])
    # with a chunk of whole cycles, cycles of two steps run in one compiled loop whose count
    # and hessian_every are traced (the program of the exact Hessian at every step above: the
    # same chunk), and the step after them in the loop of gradient steps: five steps repeat
    # the four above in the programs compiled above, equal to round-off (measured 1.5e-8
    # relative: the trust-region steps amplify it), and three steps compile nothing either
    # (small shape-dependent array ops aside: a history of another length)
    with compilations() as names:
        longer = fdjax.tune_newton(par, obj, drive, pos, start, steps=5, hessian_every=2,
                                   chunk=2)
    assert not [n for n in names if "_run" in n or "_values" in n], names
    with compilations() as names:
        fdjax.tune_newton(par, obj, drive, pos, start, steps=3, hessian_every=2, chunk=2)
    assert not [n for n in names if "_run" in n or "_values" in n], names
    assert np.asarray(longer.history).shape == (6, 2)
    np.testing.assert_allclose(np.asarray(longer.history)[:5], np.asarray(sr1.history),
                               rtol=1e-7)
    # the Hessian against central differences of the gradient, without the growth-rate
    # barrier (its gradient is exact, its second derivative holds the dominant eigenspace
    # fixed: 1–6 % off at 0.3 m, measured); the weight is a leaf, nothing recompiles
    theta = jnp.asarray(r.theta)
    y = jnp.asarray(pos)
    # one step is the trust-region step from the start's J, gradient and Hessian with the
    # initial radius 0.3 (the zero first step before it took the start and kept the radius):
    # here rejected at 0.115 m (J 7.87 → 98.9 at the trial), accepted at 0.3 m
    theta0 = jnp.broadcast_to(par.from_controller(start), (2, 12))
    with compilations() as names:
        j0, g0, H0 = _evaluate(par, obj, drive, y, theta0)  # (with the barrier)
        one = fdjax.tune_newton(par, obj, drive, pos, start, steps=1, chunk=2)
    assert not [n for n in names if "_run" in n], names  # the tuner's program, compiled above
    # the start's J in two compiled programs (measured 1.3e-15 relative)
    np.testing.assert_allclose(np.asarray(j0), h[0], rtol=1e-12)
    trial = np.asarray(one.history)[1]
    assert trial[0] > h[0, 0] and trial[1] < h[0, 1], (h[0], trial)
    for i, accepted in enumerate((False, True)):
        p = np.asarray(trust_region_step(g0[i], H0[i], 0.3)[0])
        want = np.asarray(theta0[i]) + (p if accepted else 0.0)
        # two programs' rounding (measured 9e-16; θ is of order one)
        np.testing.assert_allclose(np.asarray(one.theta[i]), want, rtol=0, atol=1e-13)
    # (a float64 array, as Objective's converter makes it: a weakly typed 0.0 would compile anew)
    obj = eqx.tree_at(lambda o: o.stability_weight, obj, jnp.asarray(0.0, jnp.float64))
    with compilations() as names:
        H = _at(par, obj, drive, y, theta).H
        diffs = {}
        for k in (0, 7):  # k_p's logarithm and the peak filter's frequency
            e = jnp.zeros(12).at[k].set(1e-4)
            diffs[k] = (_at(par, obj, drive, y, theta + e).g, _at(par, obj, drive, y, theta - e).g)
    assert not [n for n in names if "_run" in n], names
    for k, (gp, gm) in diffs.items():
        fd = (np.asarray(gp) - np.asarray(gm)) / 2e-4
        col = np.asarray(H)[:, :, k]
        print("Hessian column", k, "against central differences:",
              np.linalg.norm(fd - col) / np.linalg.norm(col))
        assert np.linalg.norm(fd - col) < 1e-5 * np.linalg.norm(col), (k, fd, col)


def test_tune_newton_with_the_margins_hessian():
    """hessian="margins": the exact Hessian of the margin term alone (no simulation), SR1 for
    the rest of J.  The margin term is the weighted penalty of J's terms; the split program's
    gradient is J's; its Hessian is J's when the simulated terms are weighted out (tracking
    scaled by 1e-9, barriers off: measured 5e-10 relative); four steps at two positions lower J
    at both (measured 7.87 → 4.48 and 19.1 → 4.07)."""
    drive, start, par, obj = _problem()
    pos = np.array([0.115, 0.3])
    y = jnp.asarray(pos)
    theta = jnp.broadcast_to(par.from_controller(start), (2, 12))
    c = par.to_controller(theta[0])
    terms = obj(c, drive, 0.115)
    np.testing.assert_allclose(float(obj.margin_term(c, drive, 0.115)),
                               float(obj.margin_weight * terms.margin_penalty), rtol=1e-12)
    with pytest.raises(TypeError, match=r"`Objective\.simulated_term\(drive=\.\.\.\)` must be"):
        obj.simulated_term(c, "drive", 0.115)
    with pytest.raises(ValueError, match=r"`Objective\.margin_term\(position_m=\.\.\.\)`"):
        obj.margin_term(c, drive, 115.0)
    split = _at(par, obj, drive, y, theta, split=True)
    j, g, g_m, H_m = split.j, split.g, split.g_m, split.H
    full = _at(par, obj, drive, y, theta)  # (the program of test_tune_newton_lowers_...)
    j_full, g_full = full.j, full.g
    print("split against full: J", np.max(np.abs(np.asarray(j / j_full - 1))), "∇J",
          np.max(np.abs(np.asarray(g - g_full))) / np.max(np.abs(np.asarray(g_full))))
    # (the run below starts from these values: its first call evaluates them, as here)
    np.testing.assert_allclose(np.asarray(j), np.asarray(j_full), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(g), np.asarray(g_full), rtol=1e-9, atol=1e-12)
    quiet = eqx.tree_at(lambda o: (o.error_scale_m, o.stability_weight, o.current_weight), obj,
                        tuple(jnp.asarray(v, jnp.float64) for v in (1e3, 0.0, 0.0)))
    with compilations() as names:  # the weights are leaves: the program above
        q = _at(par, quiet, drive, y, theta)
    assert not [n for n in names if "_run" in n], names
    g_q, H_q = q.g, q.H
    assert np.linalg.norm(np.asarray(g_q - g_m)) < 1e-8 * np.linalg.norm(np.asarray(g_m))
    err = np.linalg.norm(np.asarray(H_q - H_m)) / np.linalg.norm(np.asarray(H_m))
    print("margins' Hessian against J's, simulated terms weighted out:", err)
    assert err < 1e-8, err
    with compilations() as names:  # the steps' program, that of the values above
        r = fdjax.tune_newton(par, obj, drive, pos, start, steps=4, hessian="margins")
    assert not [n for n in names if "_run" in n], names
    h = np.asarray(r.history)
    assert h.shape == (5, 2) and np.all(np.isfinite(h))
    np.testing.assert_allclose(h[0], np.asarray(j_full), rtol=5e-11)
    print("J", h[0], "->", np.asarray(r.terms.total))
    assert np.all(np.asarray(r.terms.total) < 0.65 * h[0]), (h[0], r.terms.total)  # 0.57, 0.21
    assert np.all(np.asarray(r.terms.stable))


def test_shape_loops_meets_the_margins_without_a_simulation(monkeypatch):
    """shape_loops minimises S = J_u − w(θ_kp + θ_kv + θ_ki) by trust-region steps, J_u = the
    margin term + the growth-rate barrier of the poles: with S's exact Hessian at every step its
    history starts at S(start) and its accepted values fall to S at the result (compiled
    against op by op: measured 4.0e-11 relative); the margin term falls (measured 3.37 → 0.077
    and 14.6 → 0.141 in six steps: the gains move to where the margins hold; with the exact
    Hessian every second step, SR1 between, to 0.173 and 0.025); J_u does not depend on the
    feed-forward gains (to the last bit) and they stay; the program traces no simulation; J at
    the shaped start is 0.59× and 0.25× J at the start, and four quasi-Newton steps from it
    reach 0.31× and 0.15× (from the start itself 0.58× and 0.17×)."""
    import fdjax._tune._objective as objective_module

    drive, start, par, obj = _problem()
    pos = np.array([0.115, 0.3])
    w = 0.03
    gains = [par.names.index(n) for n in ("kp", "kv", "ki")]

    def margins_eager(theta, y):  # J_u op by op
        return float(obj.unsimulated_term(par.to_controller(theta), drive, y))

    def no_simulation(*args, **kwargs):
        raise AssertionError("shape_loops ran a simulation")

    with monkeypatch.context() as m:  # its program is traced here, for the first time
        m.setattr(objective_module, "simulate", no_simulation)
        sh = fdjax.shape_loops(par, obj, drive, pos, start, steps=6, gain_weight=w,
                               hessian_every=1)
    h = np.asarray(sh.history)
    assert h.shape == (7, 2) and np.all(np.isfinite(h))
    theta0 = np.asarray(par.from_controller(start))
    m0, rel = [], []
    for i, y in enumerate(pos):
        u0, u_end = margins_eager(theta0, y), margins_eager(sh.theta[i], y)
        m0.append(float(obj.margin_term(start, drive, y)))
        rel += [abs(h[0, i] / (u0 - w * theta0[gains].sum()) - 1),
                abs(np.min(h[:, i]) / (u_end - w * np.asarray(sh.theta[i])[gains].sum()) - 1),
                abs(float(sh.margin_term[i]) / float(obj.margin_term(
                    par.to_controller(sh.theta[i]), drive, y)) - 1)]
    print("S and J_m against op by op:", max(rel))
    assert max(rel) < 1e-10, rel
    # J_u is the margin term plus the run's own growth-rate barrier, from the poles alone
    terms = obj(start, drive, 0.3)
    g_w = max(abs(obj.max_growth_rate), 1.0)
    barrier = float(obj.stability_weight * jax.nn.softplus(
        (terms.growth_rate - obj.max_growth_rate) / g_w) ** 2)
    np.testing.assert_allclose(margins_eager(theta0, 0.3) - m0[1], barrier, rtol=1e-9,
                               atol=1e-12)
    assert np.all(np.min(h, axis=0) < h[0])
    # S does not depend on the feed-forward gains (they act on the reference alone): other
    # feed-forward gains give the same J_u to the last bit, and the shaping leaves them where
    # the start has them
    ff = [par.names.index(n) for n in ("k_ffv", "k_ffa")]
    other_ff = theta0.copy()
    other_ff[ff] = theta0[ff] * np.array([1.3, 0.7])
    assert margins_eager(other_ff, 0.3) == margins_eager(theta0, 0.3)
    assert np.all(np.asarray(sh.theta)[:, ff] == theta0[ff])
    moved = np.asarray(sh.theta)[:, gains].sum(axis=1) - theta0[gains].sum()
    print("Σ log-gains moved by", moved, "margin term", m0, "->", np.asarray(sh.margin_term))
    assert np.all(np.asarray(sh.margin_term) < 0.5 * np.asarray(m0))
    # S's exact Hessian every second step, SR1 updates between: the same program (the count
    # is traced), the same first trial (the start's exact Hessian), other trials after it
    with compilations() as names:
        sr1 = fdjax.shape_loops(par, obj, drive, pos, start, steps=6, gain_weight=w,
                                hessian_every=2)
    assert not [n for n in names if "_run" in n], names
    h2 = np.asarray(sr1.history)
    np.testing.assert_allclose(h2[:2], h[:2], rtol=1e-12)  # round-off of two programs' paths
    assert np.all(np.abs(h2[2:] / h[2:] - 1).max(0) > 1e-6)
    print("S, exact Hessian every step:", h.min(0), "; every second:", h2.min(0),
          "margin term", np.asarray(sr1.margin_term))
    assert np.all(h2.min(0) < h2[0]) and np.all(np.asarray(sr1.margin_term) < 0.5 * np.asarray(m0))
    # four steps of the quasi-Newton tuner (the exact Hessian at the start only) from each
    with compilations() as names:
        plain = fdjax.tune_newton(par, obj, drive, pos, start, steps=4, hessian_every=10**9)
        shaped = fdjax.tune_newton(par, obj, drive, pos, sh.theta, steps=4,
                                   hessian_every=10**9)
    # at most the tuner's two programs (the start alone, the gradient steps), for both runs
    assert len([n for n in names if "_run" in n]) <= 2, names
    j_plain, j_shaped = np.asarray(plain.history), np.asarray(shaped.history)
    print("J from the start:", j_plain[0], "->", j_plain.min(0), "; from the shaped start:",
          j_shaped[0], "->", j_shaped.min(0))
    assert np.all(j_shaped[0] < 0.65 * j_plain[0])  # 0.59, 0.25
    assert np.all(j_shaped.min(0) < 0.35 * j_plain[0])  # 0.31, 0.15


@pytest.mark.parametrize("kwargs, match", [
    ({"steps": 0}, r"`shape_loops\(steps=\.\.\.\)` must be an integer at least 1, got 0"),
    ({"gain_weight": 0.0},
     r"`shape_loops\(gain_weight=\.\.\.\)` must be a positive number, got 0.0"),
    ({"shrink": 0.0}, r"`shape_loops\(shrink=\.\.\.\)` must be a number in \(0, 1\), got 0.0"),
    ({"hessian_every": 0},
     r"`shape_loops\(hessian_every=\.\.\.\)` must be an integer at least 1, got 0"),
])
def test_shape_loops_names_its_arguments(kwargs, match):
    drive, start, par, obj = _problem()
    with pytest.raises(ValueError, match=match):
        fdjax.shape_loops(par, obj, drive, np.array([0.2]), start, **kwargs)
    pid = fdjax.PIDParameterisation(fdjax.reference_pid(), feedforward=False)
    with pytest.raises(ValueError, match=r"`shape_loops\(parameterisation=\.\.\.\)` must have "
                                         r"the gains kp, kv, ki among its parameters, got "
                                         r"PIDParameterisation with kp, ki, kd, wd"):
        fdjax.shape_loops(pid, obj, drive, np.array([0.2]), fdjax.reference_pid())


def test_tuners_take_an_objective_whose_twin_counts_its_modes():
    """An Objective left to count the twin's modes (twin=None) runs in the jitted tuners: they
    fix the count for the drive first (``Objective.resolved``), and J inside them is J outside
    (the same state size; measured 9e-12 relative, compiled against op-by-op round-off)."""
    drive, start, par, obj = _problem()
    free = fdjax.Objective(obj.reference, obj.freq_hz)
    fixed = free.resolved(drive)
    assert fixed.twin.kept_modes == fdjax.count_modes(drive) and free.twin is None
    assert fixed.resolved(drive) is fixed
    r = fdjax.tune_simplex(par, free, drive, np.array([0.3]), start, evaluations=14, chunk=14)
    eager = float(free(start, drive, 0.3).total)
    print("J at the start, tuner and eager:", float(r.history[0, 0]), eager)
    np.testing.assert_allclose(float(r.history[0, 0]), eager, rtol=1e-10)


def test_sr1_update_meets_the_secant_equation():
    """H⁺ s = y exactly (to round-off, measured 2e-16 relative), H⁺ symmetric, and a step
    orthogonal to its residual leaves H unchanged."""
    from fdjax._tune._newton import _sr1

    rng = np.random.default_rng(1)
    A = rng.normal(size=(5, 5))
    H = A + A.T
    s, y = rng.normal(size=5), rng.normal(size=5)
    Hn = np.asarray(_sr1(jnp.asarray(H), jnp.asarray(s), jnp.asarray(y)))
    np.testing.assert_allclose(Hn @ s, y, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(Hn, Hn.T, rtol=0, atol=1e-14)
    # the rank-one update itself (BFGS meets the same secant equation): r rᵀ/(r·s)
    r = y - H @ s
    np.testing.assert_allclose(Hn - H, np.outer(r, r) / (r @ s), rtol=1e-13, atol=1e-14)
    r = rng.normal(size=5)
    r -= (r @ s) / (s @ s) * s  # r ⊥ s: r·s is round-off, the update is skipped
    np.testing.assert_array_equal(np.asarray(_sr1(jnp.asarray(H), jnp.asarray(s),
                                                  jnp.asarray(H @ s + r))), H)


def test_trust_radius_follows_the_ratio_of_decreases():
    """Five positions, each trial's ratio ρ = (J − J_trial)/predicted set by hand: a good step
    at the radius doubles it up to max_radius, a good step well inside keeps it, a step that
    raises J or gives NaN is rejected and the radius shrinks to shrink × its length, the
    start's zero step (``first``) is taken with the radius kept; with ``exact`` an accepted
    trial brings its Hessian, a rejected one the SR1 update of the old."""
    from fdjax._tune._newton import _accept, _sr1

    n, p = 5, 2
    theta = jnp.zeros((n, p))
    j = jnp.full(n, 10.0)
    g = jnp.ones((n, p))
    H = jnp.broadcast_to(jnp.eye(p), (n, p, p))
    delta = jnp.array([3.0, 3.0, 3.0, 3.0, 0.7])
    step = jnp.array([[3.0, 0.0], [1.0, 0.0], [0.0, 2.0], [2.0, 0.0], [0.0, 0.0]])
    pred = jnp.array([1.0, 1.0, 1.0, 1.0, 0.0])
    j_t = jnp.array([9.0, 9.0, 10.5, jnp.nan, 10.0])     # ρ = 1, 1, −0.5, NaN, start
    g_t = 2.0 * g
    H_t = 3.0 * H
    first = jnp.array([False] * 4 + [True])
    th, jn, gn, Hn, dn, acc = _accept(theta, j, g, H, delta, step, pred, j_t, g_t, H_t, 0.25,
                                      5.0, True, True, first)
    np.testing.assert_array_equal(acc, [True, True, False, False, True])
    np.testing.assert_allclose(dn, [5.0, 3.0, 0.25 * 2.0, 0.25 * 2.0, 0.7], rtol=1e-15)
    np.testing.assert_array_equal(th, np.where(np.asarray(acc)[:, None], step, 0.0))
    np.testing.assert_array_equal(jn, [9.0, 9.0, 10.0, 10.0, 10.0])
    np.testing.assert_array_equal(gn[2], g[2])
    np.testing.assert_array_equal(Hn[0], H_t[0])
    np.testing.assert_allclose(Hn[2], _sr1(H[2], step[2], g_t[2] - g[2]), rtol=1e-15)


@pytest.mark.parametrize("kwargs, match", [
    ({"steps": 0}, r"`tune_newton\(steps=\.\.\.\)` must be an integer at least 1, got 0"),
    ({"radius": 0.0}, r"`tune_newton\(radius=\.\.\.\)` must be a positive number, got 0.0"),
    ({"radius": 1.0, "max_radius": 0.5},
     r"`tune_newton\(max_radius=\.\.\.\)` must be a number ≥ radius = 1.0, got 0.5"),
    ({"shrink": 1.0}, r"`tune_newton\(shrink=\.\.\.\)` must be a number in \(0, 1\), got 1.0"),
    ({"hessian_every": 0},
     r"`tune_newton\(hessian_every=\.\.\.\)` must be an integer at least 1, got 0"),
    ({"hessian": "margin"},
     r"`tune_newton\(hessian=\.\.\.\)` must be 'full' or 'margins', got 'margin'"),
    ({"hessian": "margins", "hessian_every": 2},
     r"`tune_newton\(hessian_every=\.\.\.\)` must be 1 with hessian='margins'"),
])
def test_tune_newton_names_its_arguments(kwargs, match):
    drive, start, par, obj = _problem()
    with pytest.raises(ValueError, match=match):
        fdjax.tune_newton(par, obj, drive, np.array([0.2]), start, **kwargs)
    with pytest.raises(ValueError, match=r"`tune_newton\(positions_m=\.\.\.\)` must be inside"):
        fdjax.tune_newton(par, obj, drive, np.array([115.0]), start)
