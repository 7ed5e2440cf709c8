r"""A derivative-free search for the local designs: the adaptive Nelder–Mead simplex, in JAX,
all positions in one ``vmap``.

Gradient descent (:func:`fdjax.tune_local`) goes fast into the nearest valley of the objective;
the simplex explores further (reflections, expansions, contractions, shrinks of n + 1 points
in the n parameters) and on the tuning objective of the reference drive finds designs in other
basins.  The coefficients are those of the adaptive method (Gao & Han 2012, scipy's
``adaptive=True``) for n parameters:

    reflection 1,  expansion 1 + 2/n,  contraction 3/4 − 1/(2n),  shrink 1 − 1/n.

Each scan step evaluates the objective once, at a point chosen by the step's phase (start,
reflect, expand, contract outside, contract inside, shrink), so the loop has one call site of
the simulation (one compilation) and runs under ``vmap``: every position advances one
evaluation per step.  The points are scipy's (``minimize(method="Nelder-Mead",
adaptive=True)`` from the same initial simplex: the same values to ~1e-8 relative over 1500
evaluations on the reference drive's local problem), and the compiled loop computes what does
not depend on θ once per call: there 1500 evaluations at each of six positions took
2.5–2.6 s, scipy's 13.4–15.9 s (``benchmarks/tuning.py``, two runs).
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .. import _checks, _progress
from .._control._controllers import AbstractController
from .._drive._model import BallScrewDrive
from ._local import (
    LocalTuning,
    _check_common,
    _settled,
    _start,
    _terms_at,
    masked_scan,
)
from ._objective import Objective
from ._parameterisation import AbstractParameterisation

__all__ = ["tune_simplex"]

_START, _REFLECT, _EXPAND, _OUTSIDE, _INSIDE, _SHRINK = range(6)


class _State(eqx.Module):
    x: jax.Array       # (n + 1, n) simplex
    f: jax.Array       # (n + 1,) values
    phase: jax.Array   # int
    k: jax.Array       # vertex index of the start and shrink phases
    xr: jax.Array      # reflected point
    fr: jax.Array      # its value
    best_x: jax.Array
    best_f: jax.Array


def _init(x0, step):
    n = x0.shape[0]
    x = jnp.concatenate([x0[None], x0[None] + step * jnp.eye(n, dtype=x0.dtype)])
    f = jnp.full(n + 1, jnp.inf)
    return _State(x, f, jnp.asarray(_START), jnp.asarray(0), x0, jnp.asarray(jnp.inf), x0,
                  jnp.asarray(jnp.inf))


def _step(fun, s: _State):
    n = s.x.shape[1]
    chi, psi, sigma = 1.0 + 2.0 / n, 0.75 - 0.5 / n, 1.0 - 1.0 / n
    # a reflect step starts from the sorted simplex; the other phases keep its order
    order = jnp.argsort(s.f)
    sort = s.phase == _REFLECT
    x = jnp.where(sort, s.x[order], s.x)
    f = jnp.where(sort, s.f[order], s.f)
    c = jnp.mean(x[:-1], axis=0)
    xr_new = 2.0 * c - x[-1]
    xr = jnp.where(sort, xr_new, s.xr)
    candidates = jnp.stack([
        x[s.k],                                           # start: vertex k
        xr,                                               # reflect
        c + chi * (xr - c),                               # expand
        c + psi * (xr - c),                               # contract outside
        c + psi * (x[-1] - c),                            # contract inside
        x[0] + sigma * (x[s.k] - x[0]),                   # shrink vertex k
    ])
    p = candidates[s.phase]
    v = fun(p)
    v = jnp.where(jnp.isfinite(v), v, jnp.inf)

    def replace_worst(xs, fs, point, value):
        return xs.at[-1].set(point), fs.at[-1].set(value)

    ph, k = s.phase, s.k
    # start: vertex k evaluated
    x_s, f_s = x.at[k].set(p), f.at[k].set(v)
    # reflect
    accept_r = (v >= f[0]) & (v < f[-2])
    next_r = jnp.where(accept_r, _REFLECT, jnp.where(v < f[0], _EXPAND,
                                                      jnp.where(v < f[-1], _OUTSIDE, _INSIDE)))
    x_r, f_r = replace_worst(x, f, p, v)
    # expand: the better of the expanded and the reflected point
    x_e, f_e = replace_worst(x, f, jnp.where(v < s.fr, p, xr), jnp.minimum(v, s.fr))
    # contractions: accepted, or the simplex shrinks toward its best vertex
    ok_o, ok_i = v <= s.fr, v < f[-1]
    x_c, f_c = replace_worst(x, f, p, v)

    new_x = jnp.select(
        [ph == _START, (ph == _REFLECT) & accept_r, ph == _EXPAND, (ph == _OUTSIDE) & ok_o,
         (ph == _INSIDE) & ok_i, ph == _SHRINK],
        [x_s, x_r, x_e, x_c, x_c, x_s], x)
    new_f = jnp.select(
        [ph == _START, (ph == _REFLECT) & accept_r, ph == _EXPAND, (ph == _OUTSIDE) & ok_o,
         (ph == _INSIDE) & ok_i, ph == _SHRINK],
        [f_s, f_r, f_e, f_c, f_c, f_s], f)
    last = k >= n
    shrink_next = ((ph == _OUTSIDE) & ~ok_o) | ((ph == _INSIDE) & ~ok_i)
    new_phase = jnp.select(
        [(ph == _START) | (ph == _SHRINK), ph == _REFLECT, shrink_next],
        [jnp.where(last, _REFLECT, ph), next_r, _SHRINK], _REFLECT)
    new_k = jnp.select([(ph == _START) | (ph == _SHRINK), shrink_next],
                       [jnp.where(last, 0, k + 1), 1], 0)
    better = v < s.best_f
    return _State(new_x, new_f, new_phase, new_k, xr, jnp.where(sort, v, s.fr),
                  jnp.where(better, p, s.best_x), jnp.where(better, v, s.best_f)), v


def nelder_mead(fun, x0: Float[ArrayLike, " p"], evaluations: int, step: float = 0.1):
    """The simplex on any scalar function of a vector (traceable): ``evaluations`` evaluations
    from the simplex x₀, x₀ + ``step``·e_j.  Returns (best x, best value, the value of every
    evaluation in order)."""
    state = _init(jnp.asarray(x0, jnp.float64), float(step))
    state, hist = jax.lax.scan(lambda s, _: _step(fun, s), state, None, length=evaluations)
    return state.best_x, state.best_f, hist


@eqx.filter_jit
def _run(par, objective, drive, y, state, length, steps):
    def one(st, p):
        fun = lambda th: objective(par.to_controller(th), drive, p).total  # noqa: E731
        return masked_scan(lambda s, _: _step(fun, s), st, None, length, steps)

    return jax.vmap(one)(state, y)


def tune_simplex(
    parameterisation: AbstractParameterisation,
    objective: Objective,
    drive: BallScrewDrive,
    positions_m: Float[ArrayLike, " n"],
    start: AbstractController | Float[ArrayLike, " p"] | Float[ArrayLike, "n p"],
    *,
    evaluations: int = 3000,
    step: float = 0.1,
    chunk: int = 500,
    progress: bool = False,
) -> LocalTuning:
    r"""Search one design per table position with the adaptive Nelder–Mead simplex (module
    docstring) on the objective J(controller(θ_i), Y_i), all positions in one ``vmap``.

    The simplex starts at θ₀ and θ₀ + ``step``·e_j (j = 1 … p), θ₀ from ``start`` (a controller
    of the parameterisation, or θ of shape (p,) or (n, p), as :func:`fdjax.tune_local`), and
    runs ``evaluations`` evaluations per position.  Non-finite values count as +∞.  Returns a
    :class:`fdjax.LocalTuning` whose ``theta`` and ``best_theta`` are the best point evaluated
    and whose ``history`` is J of every evaluation, (evaluations, n); refine the result by
    gradient (:func:`fdjax.tune_local` from ``best_theta``).

    Args:
        parameterisation, objective, drive, positions_m, start: as :func:`fdjax.tune_local`.
        evaluations: evaluations per position (> p + 1).
        step: the initial simplex's edge in θ (> 0).
        chunk: evaluations per compiled call (the progress bar is drawn between calls); every
            call runs one program, a last call with fewer evaluations computes and drops the
            rest.
        progress: a progress bar with the best J's mean and max after each chunk (stderr).
    """
    fn = "tune_simplex"
    evaluations = _checks.static_int(evaluations, f"{fn}(evaluations=...)", 1)
    pos, objective = _check_common(fn, parameterisation, objective, drive, positions_m,
                                   evaluations, chunk)
    theta = _start(fn, parameterisation, start, pos.size)
    n_par = theta.shape[1]
    if evaluations <= n_par + 1:
        raise ValueError(f"`{fn}(evaluations=...)` must exceed the {n_par + 1} vertices of the "
                         f"simplex, got {evaluations}")
    step = _checks.static_number(step, f"{fn}(step=...)", lambda v: v > 0, "a positive number")
    state = _settled(jax.vmap(lambda x: _init(x, float(step)))(theta))
    y = jnp.asarray(pos)
    history, done, t_steps = [], 0, 0.0
    length = min(chunk, evaluations)  # every call runs this program; the last, k ≤ length
    while done < evaluations:
        k = min(chunk, evaluations - done)
        t0 = time.perf_counter()
        state, hist = _run(parameterisation, objective, drive, y, state, length, jnp.asarray(k))
        jax.block_until_ready(hist)
        if done > 0:  # the first call compiles; a shorter last one counts for its k steps
            t_steps += (time.perf_counter() - t0) * k / length
        history.append(np.asarray(hist)[:, :k].T)
        done += k
        if progress:
            b = np.asarray(state.best_f)
            _progress.bar(fn, done, evaluations,
                          f"best J mean {np.mean(b):.4g}, max {np.max(b):.4g}", "evaluation")
    best = state.best_x
    terms = _terms_at(parameterisation, objective, drive, best, y)
    return LocalTuning(y, best, best, jnp.asarray(np.concatenate(history)), terms, t_steps)
