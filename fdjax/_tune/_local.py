r"""Local tuning (paper Sec. 4.2): one design per table position, all positions in one
``vmap``-ed optax run.

At each position Y_i the controller's vector θ_i (:class:`DoubleLoopParameterisation`) descends
J(θ_i, Y_i) (:class:`Objective`) independently; the positions share one compiled program, the
steps run in a ``lax.scan`` in chunks (a progress bar between chunks).
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Float, Int

from .. import _checks, _progress
from .._control._controllers import AbstractController
from .._drive._model import BallScrewDrive
from ._objective import Objective, ObjectiveTerms
from ._optimisers import checked_optimiser, optimiser_or
from ._parameterisation import AbstractParameterisation, check_sampled_by

__all__ = ["LocalTuning", "RobustTuning", "tune_local", "tune_robust", "tune_shared_gains",
           "smooth_max", "descend", "Descent"]


class LocalTuning(eqx.Module):
    """Result of :func:`tune_local`.

    Attributes:
        positions_m: the design positions (m), (n,).
        theta: the final normalised parameters per position, (n, p).
        best_theta: per position the parameters of the lowest objective seen, (n, p).
        history: the objective J at every step and position, (steps, n);
            :func:`fdjax.tune_newton`'s has the start's J first, (steps + 1, n).
        terms: the objective's terms at ``best_theta`` (batched over the positions).
        seconds: wall time of the steps without the first call, which compiles (s): the
            steps after the first chunk (a last, shorter chunk runs the same program, its time
            scaled to its steps), 0.0 for a run of one chunk; :func:`fdjax.tune_newton`
            the calls after the first of each of its programs, scaled to all steps at their
            rate.
        evaluations: evaluations of the objective with its gradient per step and position,
            (steps, n): 1 per step for Adam, the line search's trials for L-BFGS (and the
            start's evaluation on the first step); None where not counted.
    """

    positions_m: Float[Array, " n"]
    theta: Float[Array, "n p"]
    best_theta: Float[Array, "n p"]
    history: Float[Array, "steps n"]
    terms: ObjectiveTerms
    seconds: float = eqx.field(static=True)
    evaluations: Int[Array, "steps n"] | None = None


def tune_local(
    parameterisation: AbstractParameterisation,
    objective: Objective,
    drive: BallScrewDrive,
    positions_m: Float[ArrayLike, " n"],
    start: AbstractController | Float[ArrayLike, " p"] | Float[ArrayLike, "n p"],
    *,
    steps: int = 200,
    optimiser: optax.GradientTransformation | None = None,
    chunk: int = 25,
    progress: bool = False,
) -> LocalTuning:
    r"""Tune one controller per table position by gradient descent on the objective.

        θ_i ← optimiser step on ∇_θ J(controller(θ_i), Y_i),   i = 1 … n   (``vmap``),

    from ``start``: a controller (the same at every position, e.g.
    :func:`fdjax.reference_controller`) or its parameters per position, (n, p).  Each position
    keeps the lowest objective it has seen (``best_theta``).  Unstable candidates get a large,
    finite J with a finite gradient (:class:`Objective`); from an unstable start the barrier
    alone may need many steps, so start each position from a stable design (e.g. the design of
    the neighbouring position: continuation along the travel).

    Args:
        parameterisation: the map θ ↦ controller (:class:`fdjax.DoubleLoopParameterisation`,
            :class:`fdjax.PIDParameterisation`).
        objective: J(controller, Y).
        drive: the drive.
        positions_m: design positions (m), 1-D, inside the travel.
        start: the starting controller, or starting parameters, (p,) for every position or (n, p).
        steps: optimiser steps (≥ 1).
        optimiser: an optax transformation (default ``optax.adam(0.02)``); one with a line
            search (``optax.lbfgs()``) gets the value and the objective it needs.  The
            compiled steps are reused by a later call with the same optimiser object (and
            the same shapes): make it once, e.g. ``opt = optax.lbfgs()``.
        chunk: steps per compiled call (the progress bar is drawn between calls); every call
            runs one program, a last call with fewer steps computes and drops the rest.
        progress: a progress bar with the objective's mean and max after each chunk (stderr).
    """
    fn = "tune_local"
    pos, objective = _check_common(fn, parameterisation, objective, drive, positions_m,
                                   steps, chunk)
    theta = _start(fn, parameterisation, start, pos.size)
    opt = optimiser_or(optimiser, f"{fn}(optimiser=...)", "adam", 0.02)
    y = jnp.asarray(pos)
    with jax.numpy_dtype_promotion("standard"):
        state = _settled(jax.vmap(opt.init)(theta))
    best = theta
    best_j = _settled(jnp.full(pos.size, jnp.inf))
    history, evaluations = [], []
    t_steps = 0.0
    done = 0
    length = min(chunk, steps)  # every call runs this program; the last, k ≤ length steps
    while done < steps:
        k = min(chunk, steps - done)
        t0 = time.perf_counter()
        theta, state, best, best_j, (hist, evals) = _run(
            parameterisation, objective, drive, y, theta, state, best, best_j, opt, length,
            jnp.asarray(k))
        jax.block_until_ready(hist)
        if done > 0:  # the first call compiles; a shorter last one counts for its k steps
            t_steps += (time.perf_counter() - t0) * k / length
        history.append(np.asarray(hist)[:k])
        evaluations.append(np.asarray(evals)[:k])
        done += k
        if progress:
            h = history[-1][-1]
            _progress.bar(fn, done, steps, f"J mean {np.mean(h):.4g}, max {np.max(h):.4g}")
    terms = _terms_at(parameterisation, objective, drive, best, y)
    evaluations = np.concatenate(evaluations)
    if optax.tree_utils.tree_get(state, "grad") is not None:
        evaluations[0] += 1  # a line search's start: evaluated once before its first trial
    return LocalTuning(y, theta, best, jnp.asarray(np.concatenate(history)), terms, t_steps,
                       jnp.asarray(evaluations))


def masked_scan(step, carry, xs, length: int, active):
    """``lax.scan(step, carry, xs, length=length)`` whose carry changes in the first ``active``
    iterations only (traced: a chunked run's last, shorter chunk runs the program of the
    others, its extra iterations computed and dropped); the outputs of all ``length``."""
    def body(c, x):
        i, xi = x
        new, out = step(c, xi)
        keep = i < active
        return jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), new, c), out

    return jax.lax.scan(body, carry, (jnp.arange(length), xs), length=length)


@eqx.filter_jit
def _terms_at(par, objective, drive, theta, y):
    """The objective's terms of the designs ``theta`` (n, p) at the positions ``y`` (n,), one
    compiled program (a later call with new values compiles nothing)."""
    return jax.vmap(lambda th, p: objective(par.to_controller(th), drive, p))(theta, y)


def _all_finite(tree):
    leaves = jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_inexact_array))
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves] + [jnp.asarray(True)]))


def _guarded(value_fn, fallback):
    """``value_fn`` for an optimiser's line search: +∞ at a non-finite trial point, which is
    never handed to the parameterisation (it raises on a non-finite gain); evaluated at
    ``fallback`` instead, so that the value and its gradient stay finite."""
    def fn(q):
        ok = _all_finite(q)
        safe = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), q, fallback)
        return jnp.where(ok, value_fn(safe), jnp.inf)

    return fn


def _keep_finite(new, new_state, old, old_state):
    """The step's parameters and optimiser state, or the previous ones where the step left
    finite numbers (an L-BFGS step after convergence: a curvature pair s·y = 0)."""
    ok = _all_finite(new) & _all_finite(new_state)
    pick = lambda a, b: jnp.where(ok, a, b)  # noqa: E731
    return (jax.tree_util.tree_map(pick, new, old),
            jax.tree_util.tree_map(pick, new_state, old_state))


def _settled(tree):
    """``tree`` with the types a compiled step returns: no weak types.  An optimiser's initial
    state holds weak-typed scalars (optax.lbfgs's line-search counters) that its updated state
    does not, and a chunk would compile once for the first call and again for the next."""
    return jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, x.dtype) if isinstance(x, jax.Array) and x.weak_type else x,
        tree)


@eqx.filter_jit
def _run(par, objective, drive, y, theta, state, best, best_j, opt, length, steps):
    def loss(th, p):
        return objective(par.to_controller(th), drive, p).total

    value_and_grad = jax.vmap(jax.value_and_grad(loss))
    # an optimiser with a line search (optax.lbfgs) keeps the value and the gradient at the
    # point it accepts: they are this step's, no second evaluation
    stored = optax.tree_utils.tree_get(state, "grad") is not None
    if stored:  # the first call: nothing stored yet (the optimiser starts at J = ∞)
        def first(st):
            j0, g0 = value_and_grad(theta, y)
            return optax.tree_utils.tree_set(st, value=j0, grad=g0)

        state = jax.lax.cond(jnp.any(jnp.isinf(optax.tree_utils.tree_get(state, "value"))),
                             first, lambda st: st, state)

    def step(carry, _):
        th, st, b, bj = carry
        if stored:
            j, g = optax.tree_utils.tree_get(st, "value"), optax.tree_utils.tree_get(st, "grad")
        else:
            j, g = value_and_grad(th, y)
        better = j < bj
        b = jnp.where(better[:, None], th, b)
        bj = jnp.where(better, j, bj)
        with jax.numpy_dtype_promotion("standard"):
            # the value and the objective go along for optimisers with a line search
            # (optax.lbfgs); the others ignore them
            upd, st_new = jax.vmap(lambda g_, s_, t_, j_, p_: opt.update(
                g_, s_, t_, value=j_, grad=g_,
                value_fn=_guarded(lambda q: loss(q, p_), t_)))(g, st, th, j, y)
            th, st = jax.vmap(_keep_finite)(optax.apply_updates(th, upd), st_new, th, st)
        if stored:  # the line search's trials; the start is counted by the caller
            n = optax.tree_utils.tree_get(st, "num_linesearch_steps").astype(jnp.int32)
        else:  # one evaluation per step
            n = jnp.ones_like(j, jnp.int32)
        return (th, st, b, bj), (j, n)

    (theta, state, best, best_j), hist = masked_scan(
        step, (theta, state, best, best_j), None, length, steps)
    return theta, state, best, best_j, hist


def _check_common(fn, parameterisation, objective, drive, positions_m, steps, chunk):
    _checks.instance(parameterisation, AbstractParameterisation, f"{fn}(parameterisation=...)",
                     "an fdjax parameterisation (DoubleLoopParameterisation, PIDParameterisation)")
    _checks.instance(objective, Objective, f"{fn}(objective=...)")
    _checks.instance(drive, BallScrewDrive, f"{fn}(drive=...)")
    pos = np.asarray(_checks.real_array(positions_m, f"{fn}(positions_m=...)"))
    if pos.ndim != 1 or pos.size == 0:
        raise ValueError(f"`{fn}(positions_m=...)` must be a non-empty 1-D array, got shape "
                         f"{pos.shape}")
    lo, hi = drive.travel_m
    _checks.inside(pos, lo, hi, f"{fn}(positions_m=...)")
    for name, value in (("steps", steps), ("chunk", chunk)):
        _checks.static_int(value, f"{fn}({name}=...)", 1)
    check_sampled_by(parameterisation.highest_frequency_hz, objective.servo,
                     f"{fn}(parameterisation=...)")
    return pos, objective.resolved(drive, fn)


def _start(fn, parameterisation, start, n=None):
    """The start's θ, (n, p) (``n=None``: one θ, (p,)), from a controller of the
    parameterisation or θ; errors name ``fn(start=...)``."""
    n_par = len(parameterisation.names)
    if isinstance(start, AbstractController):
        try:
            start = parameterisation.from_controller(start)
        except TypeError as e:  # a controller of another kind: name the tuner's argument
            raise TypeError(f"`{fn}(start=...)` must be a controller of the parameterisation "
                            f"({type(parameterisation).__name__}) or θ, got "
                            f"{type(start).__name__}: {e}") from None
        except ValueError as e:  # a controller outside the parameterisation's bounds
            raise ValueError(f"`{fn}(start=...)` must lie inside the parameterisation's "
                             f"bounds: {e}") from None
    theta = jnp.asarray(start, jnp.float64)
    shapes = f"({n_par},)" if n is None else f"({n_par},) or ({n}, {n_par})"
    if n is not None and theta.shape == (n_par,):  # one θ for every position
        theta = jnp.broadcast_to(theta, (n, n_par))
    if theta.shape != ((n_par,) if n is None else (n, n_par)):
        raise ValueError(f"`{fn}(start=...)` must be a controller of the parameterisation or "
                         f"have shape {shapes}, got {theta.shape}")
    return _checks.finite(theta, f"{fn}(start=...)")


def smooth_max(values: Float[ArrayLike, " n"], sharpness: float) -> Float[Array, ""]:
    r"""A smooth maximum, (1/β) ln((1/n) Σ e^{β v_i}): between the mean (β → 0) and the
    maximum (β → ∞), below the maximum by at most ln(n)/β; β a finite positive number."""
    sharpness = _checks.check(sharpness, lambda b: (b > 0) & (b < np.inf),
                              "smooth_max(sharpness=...)", "a finite positive number")
    v = jnp.asarray(values)
    if v.ndim != 1 or v.shape[0] == 0:
        raise ValueError(f"`smooth_max(values=...)` must be a non-empty 1-D array, got shape "
                         f"{v.shape}")
    return (jax.nn.logsumexp(sharpness * v) - jnp.log(v.shape[0])) / sharpness


class RobustTuning(eqx.Module):
    """Result of :func:`tune_robust`: one design for all positions.

    Attributes:
        positions_m: the positions the design is tuned at (m), (n,).
        theta: the final normalised parameters, (p,).
        best_theta: the parameters of the lowest robust objective seen, (p,).
        history: the robust objective at every step, (steps,).
        worst: max over the positions of J at every step, (steps,).
        terms: the objective's terms at ``best_theta`` at each position.
        seconds: wall time of the steps after the first chunk, which compiles (s; 0.0 for a
            run of one chunk).
        evaluations: evaluations of the objective with its gradient at every position at
            every step, (steps,): 1 for Adam, the line search's trials for L-BFGS.
    """

    positions_m: Float[Array, " n"]
    theta: Float[Array, " p"]
    best_theta: Float[Array, " p"]
    history: Float[Array, " steps"]
    worst: Float[Array, " steps"]
    terms: ObjectiveTerms
    seconds: float = eqx.field(static=True)
    evaluations: Int[Array, " steps"] | None = None


class _RobustLoss(eqx.Module):
    par: AbstractParameterisation
    objective: Objective
    drive: BallScrewDrive
    positions: Array
    sharpness: float = eqx.field(static=True)

    def __call__(self, theta):
        c = self.par.to_controller(theta)
        j = jax.vmap(lambda y: self.objective(c, self.drive, y).total)(self.positions)
        return smooth_max(j, self.sharpness), jnp.max(j)


def tune_robust(
    parameterisation: AbstractParameterisation,
    objective: Objective,
    drive: BallScrewDrive,
    positions_m: Float[ArrayLike, " n"],
    start: AbstractController | Float[ArrayLike, " p"] | Float[ArrayLike, "n p"],
    *,
    steps: int = 200,
    optimiser: optax.GradientTransformation | None = None,
    sharpness: float = 2.0,
    chunk: int = 25,
    progress: bool = False,
) -> RobustTuning:
    r"""Tune one controller for all positions: the best single design with the margins at
    every position (the robust baseline of paper Fig. 18),

        θ ← optimiser step on ∇_θ smax_β(J(controller(θ), Y_1), …, J(controller(θ), Y_n)),

    ``smax_β`` the :func:`smooth_max` of sharpness β (the worst position dominates; β → 0 is
    the mean).  Every J carries the margin penalties at its position, so the design keeps the
    margins everywhere it is tuned.  ``start``: a controller of the parameterisation or its θ.
    Other arguments as :func:`tune_local`.
    """
    fn = "tune_robust"
    pos, objective = _check_common(fn, parameterisation, objective, drive, positions_m,
                                   steps, chunk)
    sharpness = _checks.static_positive(sharpness, f"{fn}(sharpness=...)")
    theta = _start(fn, parameterisation, start)
    loss = _RobustLoss(parameterisation, objective, drive, jnp.asarray(pos), float(sharpness))
    opt = optimiser_or(optimiser, f"{fn}(optimiser=...)", "adam", 0.02)
    res = descend(loss, theta, opt, steps, chunk=chunk, progress=fn if progress else None)
    y = jnp.asarray(pos)
    terms = _terms_at(parameterisation, objective, drive,
                      jnp.broadcast_to(res.best, (y.size, *jnp.shape(res.best))), y)
    return RobustTuning(y, res.params, res.best, res.history, res.aux, terms, res.seconds,
                        res.evaluations)


class Descent(eqx.Module):
    """Result of :func:`descend`: final and best parameters, the loss and its auxiliary value
    at every step, wall time of the steps after the first (compiling) chunk, and the
    evaluations of the loss with its gradient at every step (1, plus the line search's trials
    for an optimiser with one, e.g. ``optax.lbfgs()``)."""

    params: object
    best: object
    history: Float[Array, " steps"]
    aux: Array
    seconds: float = eqx.field(static=True)
    evaluations: Int[Array, " steps"] | None = None


def descend(loss, params, optimiser, steps: int, *, chunk: int = 25, key=None,
            progress: str | None = None) -> Descent:
    """Minimise ``loss(params) -> (value, aux)`` (or ``loss(params, key)`` when ``key`` is
    given: a fresh key per step) by ``steps`` steps of ``optimiser``; ``loss`` is an
    ``eqx.Module`` (its arrays are traced, one compilation for new values).  The steps run in
    a ``lax.scan`` of ``chunk`` steps per compiled call; with ``progress`` (a name) a progress bar
    after each chunk on stderr.  Keeps the parameters of the lowest value seen.  A step that
    would leave non-finite parameters or optimiser state is refused (the previous ones are
    kept), and a line search's trial at a non-finite point gets +∞ without evaluating
    ``loss``.  The compiled steps are reused by a later call with the same ``optimiser``
    object and the same shapes."""
    steps = _checks.static_int(steps, "descend(steps=...)", 1)
    chunk = _checks.static_int(chunk, "descend(chunk=...)", 1)
    optimiser = checked_optimiser(optimiser, "descend(optimiser=...)")
    with jax.numpy_dtype_promotion("standard"):
        state = _settled(optimiser.init(params))
    best, best_v = params, _settled(jnp.asarray(jnp.inf))
    hist, auxs, evals, t_steps, done = [], [], [], 0.0, 0
    length = min(chunk, steps)  # every call runs this program; the last, k ≤ length steps
    while done < steps:
        k = min(chunk, steps - done)
        keys = None if key is None else jax.random.split(jax.random.fold_in(key, done),
                                                         length)
        t0 = time.perf_counter()
        params, state, best, best_v, (v, aux, n) = _descend_chunk(
            loss, params, state, best, best_v, optimiser, keys, length, jnp.asarray(k))
        jax.block_until_ready(v)
        if done > 0:  # the first call compiles; a shorter last one counts for its k steps
            t_steps += (time.perf_counter() - t0) * k / length
        hist.append(np.asarray(v)[:k])
        auxs.append(np.asarray(aux)[:k])
        evals.append(np.asarray(n)[:k])
        done += k
        if progress:
            _progress.bar(progress, done, steps,
                          f"objective {float(hist[-1][-1]):.4g} (best {float(best_v):.4g})")
    return Descent(params, best, jnp.asarray(np.concatenate(hist)),
                   jnp.asarray(np.concatenate(auxs)), t_steps,
                   jnp.asarray(np.concatenate(evals)))


@eqx.filter_jit
def _descend_chunk(loss, params, state, best, best_v, opt, keys, length, steps):
    def step(carry, k):
        p, st, b, bv = carry
        f = loss if k is None else (lambda q: loss(q, k))
        (v, aux), g = eqx.filter_value_and_grad(f, has_aux=True)(p)
        better = v < bv
        b = jax.tree_util.tree_map(lambda x, y: jnp.where(better, x, y), p, b)
        bv = jnp.where(better, v, bv)
        with jax.numpy_dtype_promotion("standard"):
            upd, st_new = opt.update(g, st, p, value=v, grad=g,
                                     value_fn=_guarded(lambda q: f(q)[0], p))
            p, st = _keep_finite(eqx.apply_updates(p, upd), st_new, p, st)
        # this step's evaluation, and a line search's trials (optax.lbfgs)
        trials = optax.tree_utils.tree_get(st, "num_linesearch_steps")
        n = jnp.asarray(1, jnp.int32) + (0 if trials is None else trials.astype(jnp.int32))
        return (p, st, b, bv), (v, aux, n)

    (params, state, best, best_v), out = masked_scan(
        step, (params, state, best, best_v), keys, length, steps)
    return params, state, best, best_v, out


class _SharedGainsLoss(eqx.Module):
    par: AbstractParameterisation
    objective: Objective
    drive: BallScrewDrive
    positions: Array
    n_shared: int = eqx.field(static=True)
    sharpness: float = eqx.field(static=True)

    def __call__(self, params):
        shared, own = params
        theta = jnp.concatenate(
            [jnp.broadcast_to(shared, (own.shape[0], self.n_shared)), own], axis=1)
        j = jax.vmap(lambda th, y: self.objective(self.par.to_controller(th), self.drive,
                                                  y).total)(theta, self.positions)
        return 0.5 * (jnp.mean(j) + smooth_max(j, self.sharpness)), j


def tune_shared_gains(
    parameterisation: AbstractParameterisation,
    objective: Objective,
    drive: BallScrewDrive,
    positions_m: Float[ArrayLike, " n"],
    start: Float[ArrayLike, "n p"] | Float[ArrayLike, " p"],
    *,
    n_shared: int = 5,
    steps: int = 200,
    optimiser: optax.GradientTransformation | None = None,
    sharpness: float = 2.0,
    chunk: int = 25,
    progress: bool = False,
) -> LocalTuning:
    r"""Local designs that share their first ``n_shared`` parameters (the gains of a
    :class:`fdjax.DoubleLoopParameterisation`): what a schedule of the filters alone needs,
    one gain set and one MCM per position (paper Sec. 4.2),

        (θ_g, θ_1 … θ_n) ← optimiser step on ∇ ½ (mean_i J_i + smax_β J_i),
        J_i = J(controller(θ_g, θ_i), Y_i),

    from ``start`` (n, p), e.g. the designs of :func:`tune_local` (the shared part starts at
    their mean), or one design (p,) for every position.  Returns a :class:`LocalTuning` whose
    rows share the first ``n_shared`` entries; ``history`` is J per position at every step.
    """
    fn = "tune_shared_gains"
    pos, objective = _check_common(fn, parameterisation, objective, drive, positions_m,
                                   steps, chunk)
    theta = _start(fn, parameterisation, start, pos.size)
    n_par = theta.shape[1]
    n_shared = _checks.static_int(n_shared, f"{fn}(n_shared=...)", 1, n_par - 1)
    sharpness = _checks.static_positive(sharpness, f"{fn}(sharpness=...)")
    params = (jnp.mean(theta[:, :n_shared], axis=0), theta[:, n_shared:])
    loss = _SharedGainsLoss(parameterisation, objective, drive, jnp.asarray(pos), n_shared,
                            float(sharpness))
    opt = optimiser_or(optimiser, f"{fn}(optimiser=...)", "adam", 0.02)
    res = descend(loss, params, opt, steps, chunk=chunk, progress=fn if progress else None)

    def rows(p):
        return jnp.concatenate([jnp.broadcast_to(p[0], (pos.size, n_shared)), p[1]], axis=1)

    best = rows(res.best)
    y = jnp.asarray(pos)
    terms = _terms_at(parameterisation, objective, drive, best, y)
    evaluations = jnp.broadcast_to(res.evaluations[:, None], (steps, pos.size))
    return LocalTuning(y, rows(res.params), best, res.aux, terms, res.seconds, evaluations)
