"""Local tuning (one design per position, vmapped optax runs), the simplex baseline and the
descent loop of gradient synthesis."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from compile_events import compilations

import fdjax
from fdjax._tune._local import _terms_at

BOUNDS = fdjax.MCMBounds.for_servo(fdjax.Servo())


# ------------------------------------------------------------------------------ local tuning
def _problem():
    """The file's problem from the reference controller: (drive, start, parameterisation, 1 mm
    stroke, objective on 64 frequencies with 4 kept modes); its tuners share the objective's
    compiled programs."""
    drive = fdjax.reference_drive()
    start = fdjax.reference_controller(drive)
    par = fdjax.DoubleLoopParameterisation(BOUNDS, start)
    ref = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    obj = fdjax.Objective(ref, np.geomspace(5.0, 3900.0, 64),
                          twin=fdjax.TwinOptions(kept_modes=4))
    return drive, start, par, ref, obj


def test_local_tuning_improves_every_position():
    """Two positions in one vmapped Adam run from the reference controller: the objective
    falls at both (measured 108 → 2.3 and 516 → 8.3 in 20 steps of a 1 mm stroke), and the
    best designs are stable (eigenvalues).  The file's tuners share one objective (64
    frequencies, 4 kept modes), so that they share its compiled programs."""
    drive, start, par, ref, obj = _problem()
    pos = np.array([0.115, 0.3])
    r = fdjax.tune_local(par, obj, drive, pos, start, steps=20, chunk=10)
    print("J", np.asarray(r.history)[0], "->", np.asarray(r.terms.total))
    h = np.asarray(r.history)
    assert h.shape == (20, 2)
    np.testing.assert_array_equal(np.asarray(r.evaluations), np.ones((20, 2)))  # one a step
    best = np.asarray(r.terms.total)
    # the terms are those of best_theta, the lowest J of the history (another program:
    # round-off, measured 2e-16 alone and 7.7e-13 in the suite, whose XLA flags differ)
    np.testing.assert_allclose(best, np.min(h, axis=0), rtol=1e-11)
    assert np.all(best < 0.5 * h[0]), (h[0], best)
    assert np.all(np.asarray(r.terms.stable))
    # J falls mostly through the margin penalties; the tracking error falls too (measured
    # 2.45 → 2.14 and 2.64 → 2.41 µm, 0.87× and 0.91×): the start's terms from the program
    # that gave the result's
    theta0 = np.stack([np.asarray(par.from_controller(start))] * 2)
    rms0 = np.asarray(_terms_at(par, obj.resolved(drive), drive, theta0, pos).rms_error_m)
    rms = np.asarray(r.terms.rms_error_m)
    assert np.all(rms < 0.95 * rms0), (rms0, rms)
    for i, p in enumerate(pos):
        c = par.to_controller(r.best_theta[i])
        assert bool(fdjax.check_stability(c, drive, position_m=p).stable)
    with pytest.raises(ValueError, match=r"`tune_local\(positions_m=\.\.\.\)` must be inside"):
        fdjax.tune_local(par, obj, drive, np.array([115.0]), start)
    with pytest.raises(ValueError, match=r"`tune_local\(start=\.\.\.\)` must be a controller"):
        fdjax.tune_local(par, obj, drive, pos, np.zeros((3, 12)))


def test_local_tuning_refuses_a_non_finite_step_at_its_position_only():
    """tune_local's own guard, per position: an optimiser whose step leaves finite numbers
    from its third step on, at the position that starts with the higher k_p only.  There the
    parameters stay where they were (the history flat from the third step, θ finite); the
    other position runs on bit for bit as in a run where no step is refused (same shapes,
    same optimiser: nothing compiles for the second run)."""
    drive, start, par, ref, obj = _problem()
    theta0 = np.asarray(par.from_controller(start))

    def init(p):   # (steps taken, whether this position's steps turn non-finite)
        return jnp.zeros((), jnp.int32), p[0] > theta0[0] + 0.05

    def update(g, state, params=None, **_):
        count, spoilt = state
        u = jnp.where(spoilt & (count >= 2), jnp.nan, -1e-4 * g)
        return u, (count + 1, spoilt)

    opt = optax.GradientTransformationExtraArgs(init, update)
    pos = np.array([0.115, 0.3])
    higher = theta0 + np.eye(theta0.size)[0] * 0.1
    bad = fdjax.tune_local(par, obj, drive, pos, np.stack([theta0, higher]), steps=4, chunk=4,
                           optimiser=opt)
    good = fdjax.tune_local(par, obj, drive, pos, np.stack([theta0, theta0]), steps=4, chunk=4,
                            optimiser=opt)
    h = np.asarray(bad.history)
    assert np.all(np.isfinite(h)) and np.all(np.isfinite(np.asarray(bad.theta)))
    assert h[1, 1] != h[0, 1] and np.all(h[2:, 1] == h[2, 1])     # two steps, then refused
    np.testing.assert_array_equal(h[:, 0], np.asarray(good.history)[:, 0])
    np.testing.assert_array_equal(np.asarray(bad.theta)[0], np.asarray(good.theta)[0])


def test_local_tuning_by_lbfgs_keeps_the_positions_apart():
    """L-BFGS (a line search on the objective at each position) in the vmapped run: the
    objective falls at every position, and each position's run depends on its own objective
    only: 300 mm paired with 115 mm and paired with 200 mm runs the same steps (equal to
    round-off, measured 0 difference; a line search shared by the pair would step each by the
    pair's step length).  Both runs have the same shapes and the same optimiser object: the
    second compiles nothing (counted by JAX's compilation events)."""
    import optax

    drive, start, par, ref, obj = _problem()
    opt = optax.lbfgs()  # one object: its compiled steps are reused
    runs = []
    for y in (0.115, 0.2):
        with compilations() as names:
            runs.append(fdjax.tune_local(par, obj, drive, np.array([y, 0.3]), start, steps=4,
                                         chunk=4, optimiser=opt))
        assert ("jit(_run)" in names) == (y == 0.115), names  # the steps: compiled by the first
    for r in runs:
        h = np.asarray(r.history)
        assert np.all(np.asarray(r.terms.total) < 0.5 * h[0]), (h[0], r.terms.total)
    a, b = runs
    # the partners differ (their own runs differ), the 300 mm runs do not
    assert not np.allclose(np.asarray(a.history)[:, 0], np.asarray(b.history)[:, 0])
    np.testing.assert_allclose(np.asarray(a.history)[:, 1], np.asarray(b.history)[:, 1],
                               rtol=1e-12)
    np.testing.assert_allclose(a.best_theta[1], b.best_theta[1], rtol=1e-12, atol=1e-12)
    # evaluations: the line search's trials, at least one per step, and the start's
    n = np.asarray(a.evaluations)
    assert n.shape == (4, 2) and np.all(n >= 1) and np.all(n[0] >= 2), n
    np.testing.assert_array_equal(n[:, 1], np.asarray(b.evaluations)[:, 1])


def test_start_is_one_design_for_every_position_or_one_per_position():
    from fdjax._tune._local import _start

    drive = fdjax.reference_drive()
    ref = fdjax.reference_controller(drive)
    par = fdjax.DoubleLoopParameterisation(BOUNDS, ref)
    theta = np.asarray(par.from_controller(ref))
    rows = np.stack([theta, theta + 0.1, theta - 0.1])
    np.testing.assert_array_equal(_start("tune_local", par, theta, 3), np.tile(theta, (3, 1)))
    np.testing.assert_array_equal(_start("tune_local", par, ref, 3), np.tile(theta, (3, 1)))
    np.testing.assert_array_equal(_start("tune_local", par, rows, 3), rows)
    with pytest.raises(ValueError, match=r"have shape \(12,\) or \(2, 12\), got \(3, 12\)"):
        _start("tune_local", par, rows, 2)


def test_tuners_name_their_arguments_before_compiling():
    """Bad settings are refused up front, naming the tuner: a controller outside the bounds or
    of another kind as the start, a smooth maximum's sharpness that is not a finite positive
    number (0 made the loss NaN, and every step was refused without a word)."""
    drive = fdjax.reference_drive()
    ref = fdjax.reference_controller(drive)
    par = fdjax.DoubleLoopParameterisation(BOUNDS, ref)
    obj = fdjax.tuning_objective()
    pos = np.array([0.2, 0.4])
    far = fdjax.DoubleLoop(mcm=fdjax.MCM(fdjax.PeakFilter(100.0, 5e3, 0.2, 0.1),
                                         ref.mcm.notch))
    for fn in (fdjax.tune_local, fdjax.tune_robust, fdjax.tune_shared_gains):
        name = fn.__name__
        with pytest.raises(ValueError, match=rf"`{name}\(start=\.\.\.\)` must lie inside the "
                                             r"parameterisation's bounds: .*peak gain K"):
            fn(par, obj, drive, pos, far, steps=1)
        with pytest.raises(TypeError, match=rf"`{name}\(start=\.\.\.\)` must be a controller "
                                            r"of the parameterisation"):
            fn(par, obj, drive, pos, fdjax.PIDLoop(), steps=1)
    for fn in (fdjax.tune_robust, fdjax.tune_shared_gains):
        for bad in (0.0, -1.0, float("inf"), float("nan"), True, "2"):
            with pytest.raises(ValueError, match=rf"`{fn.__name__}\(sharpness=\.\.\.\)` must be "
                                                 r"a finite positive number"):
                fn(par, obj, drive, pos, ref, steps=1, sharpness=bad)
    sched = fdjax.ScheduledLoop(ref, fdjax.ATANetwork((0.1, 0.7), width=4), BOUNDS)
    with pytest.raises(ValueError, match=r"`train_schedule\(sharpness=\.\.\.\)` must be a "
                                         r"finite positive number, got inf"):
        fdjax.train_schedule(sched, obj, drive, steps=1, sharpness=float("inf"))
    narrow = fdjax.ScheduledLoop(ref, fdjax.ATANetwork((0.2, 0.6), width=4), BOUNDS)
    with pytest.raises(ValueError, match=r"the network's travel \[0\.2, 0\.6\] m must cover the "
                                         r"drive's \[0\.1, 0\.7\] m"):
        fdjax.train_schedule(narrow, obj, drive, steps=1)
    with pytest.raises(ValueError, match=r"`train_schedule\(positions_m=\.\.\.\)` must be inside "
                                         r"the network's travel \[0\.2, 0\.6\] m, got 0\.65"):
        fdjax.train_schedule(narrow, obj, drive, steps=1, positions_m=[0.3, 0.65])
    with pytest.raises(ValueError, match=r"`smooth_max\(sharpness=\.\.\.\)` must be a finite "
                                         r"positive number, got 0"):
        fdjax.smooth_max(jnp.ones(3), 0.0)
    # (logsumexp(β x) − ln n)/β: 2 + ln(1 + e^-1000)/1000 − ln 2/1000
    np.testing.assert_allclose(fdjax.smooth_max(jnp.array([1.0, 2.0]), jnp.asarray(1e3)),
                               2.0 - np.log(2.0) / 1e3, rtol=1e-14)


# ------------------------------------------------------------------------------ the simplex
def test_simplex_is_scipys_adaptive_nelder_mead():
    """Evaluation for evaluation the same values as scipy's adaptive Nelder–Mead from the same
    initial simplex (4-D Rosenbrock, 600 evaluations; measured 3.4e-13, round-off)."""
    import scipy.optimize

    from fdjax._tune._simplex import nelder_mead

    x0 = np.array([-1.2, 1.0, 0.7, -0.3])
    seen = []

    def f(x):
        v = float(np.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2))
        seen.append(v)
        return v

    scipy.optimize.minimize(f, x0, method="Nelder-Mead", options=dict(
        adaptive=True, initial_simplex=np.vstack([x0, x0 + 0.1 * np.eye(4)]), maxfev=600,
        xatol=0.0, fatol=0.0))
    rosen = lambda x: jnp.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2)  # noqa: E731
    bx, bf, hist = jax.jit(lambda x: nelder_mead(rosen, x, 600, 0.1))(jnp.asarray(x0))
    m = min(len(seen), 600)
    assert m >= 590
    np.testing.assert_allclose(np.asarray(hist)[:m], seen[:m], rtol=1e-11, atol=1e-12)
    assert float(bf) == pytest.approx(min(seen[:600]), rel=1e-12)
    np.testing.assert_allclose(float(rosen(bx)), float(bf), rtol=1e-14)


def test_tune_simplex_improves_every_position_and_names_its_arguments():
    """Two positions in one vmapped simplex from the reference controller (120 evaluations):
    J falls at both and ``terms`` are those of ``best_theta``."""
    drive, start, par, ref, obj = _problem()
    pos = np.array([0.115, 0.3])
    r = fdjax.tune_simplex(par, obj, drive, pos, start, evaluations=120, chunk=60)
    h = np.asarray(r.history)
    assert h.shape == (120, 2)
    best = np.asarray(r.terms.total)
    np.testing.assert_allclose(best, np.min(h, axis=0), rtol=1e-10)
    assert np.all(best < 0.5 * h[0]), (h[0], best)  # h[0]: the start itself
    with pytest.raises(ValueError, match=r"`tune_simplex\(evaluations=\.\.\.\)` must exceed"):
        fdjax.tune_simplex(par, obj, drive, pos, start, evaluations=10)
    with pytest.raises(ValueError, match=r"`tune_simplex\(positions_m=\.\.\.\)` must be inside"):
        fdjax.tune_simplex(par, obj, drive, np.array([300.0]), start)
    with pytest.raises(TypeError, match=r"`tune_simplex\(start=\.\.\.\)` must be a controller "
                                        r"of the parameterisation \(DoubleLoopParameterisation\) "
                                        r"or θ, got PIDLoop"):
        fdjax.tune_simplex(par, obj, drive, pos, fdjax.PIDLoop())


def test_descend_counts_every_evaluation_of_the_loss():
    """`Descent.evaluations` is what the optimiser spent: one per step for Adam, one plus the
    line search's trials for L-BFGS; checked against a counter the loss itself increments
    (a host callback, executed once per evaluation in the compiled loop)."""
    calls = []

    class Rosenbrock(eqx.Module):
        def __call__(self, p):
            jax.debug.callback(lambda: calls.append(1))
            v = (1.0 - p[0]) ** 2 + 100.0 * (p[1] - p[0] ** 2) ** 2
            return v, v

    for opt, per_step in ((optax.adam(0.01), {1}), (optax.lbfgs(), None)):
        calls.clear()
        res = fdjax.descend(Rosenbrock(), jnp.array([-1.2, 1.0]), opt, 30, chunk=10)
        n = np.asarray(res.evaluations)
        assert n.shape == (30,) and int(n.sum()) == len(calls)
        if per_step is not None:
            assert set(n.tolist()) == per_step
        else:  # measured 70 evaluations in 30 steps, J 3.3e-4 from 24.2
            assert n.min() >= 2 and float(res.history[-1]) < 1e-2


def test_descend_compiles_once_for_every_chunk():
    """The steps compile once however many chunks run: the optimiser's initial state has the
    types of the state a chunk returns (optax.lbfgs's starts weak-typed).  Counted by the
    loss's Python body, which runs only while a chunk is traced."""
    traces = []

    class Rosenbrock(eqx.Module):
        def __call__(self, p):
            traces.append(1)
            v = (1.0 - p[0]) ** 2 + 100.0 * (p[1] - p[0] ** 2) ** 2
            return v, v

    for make in (lambda: optax.adam(0.01), optax.lbfgs):
        counts = []
        for steps in (5, 20):  # one chunk; four (a new optimiser: nothing compiled yet)
            traces.clear()
            fdjax.descend(Rosenbrock(), jnp.array([-1.2, 1.0]), make(), steps, chunk=5)
            counts.append(len(traces))
        assert counts[0] == counts[1] > 0, counts  # weak-typed starts: [1, 2] and [3, 6]


def test_a_shorter_last_chunk_runs_the_same_program(capsys):
    """A last chunk shorter than the others was a program of its own: a second compilation
    (about 50 s for the tuning objective), counted in ``seconds`` (1.85 s of 1.87 s for 12
    steps in chunks of 5).  It now runs the others' program, its extra steps computed and
    dropped: the loss is traced once (its body runs only while a chunk is traced, and sleeps
    0.5 s there, so ``seconds`` stays far below one trace), and the steps are those of one
    chunk of 12 (equal to the last digit: the same arithmetic)."""
    import time

    traces = []

    class Slow(eqx.Module):
        def __call__(self, p):
            traces.append(1)
            time.sleep(0.5)
            v = jnp.sum((p - 1.0) ** 2) + jnp.sum(p ** 4)
            return v, v

    fdjax.descend(Slow(), jnp.zeros(2), optax.adam(0.1), 10, chunk=5)  # a new optimiser
    whole = len(traces)  # the traces of one program (two chunks of 5)
    traces.clear()
    res = fdjax.descend(Slow(), jnp.zeros(2), optax.adam(0.1), 12, chunk=5, progress="d")
    assert len(traces) == whole, (whole, len(traces))  # 5 + 5 + 2: one program too
    # the progress bar's last objective is the 12th step's, not a dropped one's
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"objective {float(res.history[-1]):.4g} " in last, last
    assert np.asarray(res.history).shape == (12,) and np.asarray(res.evaluations).shape == (12,)
    assert 0.0 < res.seconds < 0.25, res.seconds  # the later chunks' steps alone
    one = fdjax.descend(Slow(), jnp.zeros(2), optax.adam(0.1), 12, chunk=12)
    np.testing.assert_array_equal(np.asarray(res.history), np.asarray(one.history))
    np.testing.assert_array_equal(np.asarray(res.params), np.asarray(one.params))


def test_default_optimisers_compile_once():
    """The tuners' default optimisers are one object each (an optax transformation compares
    by identity, and a compiled step is keyed on it): a second call with new values compiles
    nothing."""
    from fdjax._tune._optimisers import default_optimiser

    assert default_optimiser("adam", 0.02) is default_optimiser("adam", 0.02)
    y = np.linspace(0.1, 0.7, 6)
    targets = np.tile(np.linspace(-1.0, 1.0, 7), (6, 1))
    net = fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(1))
    for k, shift in enumerate((0.0, 0.3)):
        with compilations() as names:
            fdjax.fit_network(net, y, targets + shift, steps=20)
        assert ("jit(_fit)" in names) == (k == 0), names


def test_a_non_finite_step_is_refused_not_raised():
    """An optimiser step that leaves finite numbers (an L-BFGS step after convergence, where a
    curvature pair has s·y = 0) is refused: the parameters and the state stay where they
    were, and a line search's trial at a non-finite point gets +∞ without reaching the loss
    (whose parameterisation raises on a non-finite gain)."""

    class Checked(eqx.Module):
        def __call__(self, p):
            p = eqx.error_if(p, ~jnp.all(jnp.isfinite(p)), "non-finite parameters")
            v = jnp.sum((p - 1.0) ** 2)
            return v, v

    trials = []

    def nan_after(k):
        def init(p):
            return jnp.zeros((), jnp.int32)

        def update(g, count, params=None, *, value_fn=None, **_):
            bad = count >= k
            trial = jnp.where(bad, jnp.nan, params)  # a line search's trial point
            v = value_fn(trial)
            jax.debug.callback(lambda x: trials.append(float(x)), v)
            u = jnp.where(bad, jnp.nan, -0.25 * g)
            return u, count + 1

        return optax.GradientTransformationExtraArgs(init, update)

    res = fdjax.descend(Checked(), jnp.array([3.0, -1.0]), nan_after(3), 8, chunk=4)
    h = np.asarray(res.history)
    assert np.all(np.isfinite(h)) and np.all(np.isfinite(np.asarray(res.params)))
    # three steps of p ← p − ½(p − 1), then refused: the parameters stay put
    # (exact in binary: a refused step leaves the parameters bit for bit)
    np.testing.assert_array_equal(np.asarray(res.params), 1.0 + np.array([2.0, -2.0]) / 8)
    np.testing.assert_array_equal(h[3:], np.full(h[3:].shape, h[3]))
    assert trials[:3] == h[:3].tolist() and all(t == np.inf for t in trials[3:])
