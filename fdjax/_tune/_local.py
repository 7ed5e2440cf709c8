r"""Local tuning (paper Sec. 4.2): one design per table position, all positions in one
``vmap``-ed optax run.

At each position Y_i the controller's vector θ_i (:class:`DoubleLoopParameterisation`) descends
J(θ_i, Y_i) (:class:`Objective`) independently; the positions share one compiled program, the
steps run in a ``lax.scan`` in chunks (a progress line between chunks).
"""

from __future__ import annotations

import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Float

from .._control._controllers import DoubleLoop
from .._drive._model import BallScrewDrive
from ._objective import Objective, ObjectiveTerms
from ._parameterisation import DoubleLoopParameterisation

__all__ = ["LocalTuning", "tune_local"]


class LocalTuning(eqx.Module):
    """Result of :func:`tune_local`.

    Attributes:
        positions_m: the design positions (m), (n,).
        theta: the final normalised parameters per position, (n, 12).
        best_theta: per position the parameters of the lowest objective seen, (n, 12).
        history: the objective J at every step and position, (steps, n).
        terms: the objective's terms at ``best_theta`` (batched over the positions).
        seconds: wall time of the steps, compilation apart (s).
    """

    positions_m: Float[Array, " n"]
    theta: Float[Array, "n 12"]
    best_theta: Float[Array, "n 12"]
    history: Float[Array, "steps n"]
    terms: ObjectiveTerms
    seconds: float = eqx.field(static=True)


def tune_local(
    parameterisation: DoubleLoopParameterisation,
    objective: Objective,
    drive: BallScrewDrive,
    positions_m: Float[ArrayLike, " n"],
    start,
    *,
    steps: int = 200,
    optimiser: optax.GradientTransformation | None = None,
    chunk: int = 25,
    progress: bool = False,
) -> LocalTuning:
    r"""Tune one controller per table position by gradient descent on the objective.

        θ_i ← optimiser step on ∇_θ J(controller(θ_i), Y_i),   i = 1 … n   (``vmap``),

    from ``start``: a :class:`fdjax.DoubleLoop` (the same at every position, e.g.
    :func:`fdjax.reference_controller`) or its parameters per position, (n, 12).  Each position
    keeps the lowest objective it has seen (``best_theta``).  Unstable candidates get a large,
    finite J with a finite gradient (:class:`Objective`); from an unstable start the barrier
    alone may need many steps, so start each position from a stable design (e.g. the design of
    the neighbouring position: continuation along the travel).

    Args:
        parameterisation: the map θ ↦ :class:`fdjax.DoubleLoop`.
        objective: J(controller, Y).
        drive: the drive.
        positions_m: design positions (m), 1-D, inside the travel.
        start: the starting controller, or starting parameters (n, 12).
        steps: optimiser steps (≥ 1).
        optimiser: an optax transformation (default ``optax.adam(0.02)``).
        chunk: steps per compiled call (the progress line is printed between calls).
        progress: print the objective's mean and max after each chunk (to stderr).
    """
    fn = "tune_local"
    if not isinstance(parameterisation, DoubleLoopParameterisation):
        raise TypeError(f"`{fn}(parameterisation=...)` must be an "
                        f"fdjax.DoubleLoopParameterisation, got {type(parameterisation).__name__}")
    if not isinstance(objective, Objective):
        raise TypeError(f"`{fn}(objective=...)` must be an fdjax.Objective, got "
                        f"{type(objective).__name__}")
    if not isinstance(drive, BallScrewDrive):
        raise TypeError(f"`{fn}(drive=...)` must be an fdjax.BallScrewDrive, got "
                        f"{type(drive).__name__}")
    pos = np.asarray(positions_m, np.float64)
    if pos.ndim != 1 or pos.size == 0:
        raise ValueError(f"`{fn}(positions_m=...)` must be a non-empty 1-D array, got shape "
                         f"{pos.shape}")
    lo, hi = drive.travel_m
    if not np.all((pos >= lo) & (pos <= hi)):
        raise ValueError(f"`{fn}(positions_m=...)` must be inside the travel [{lo:.6g}, "
                         f"{hi:.6g}] m, got {pos.tolist()}")
    for name, value in (("steps", steps), ("chunk", chunk)):
        if not (isinstance(value, int) and value >= 1):
            raise ValueError(f"`{fn}({name}=...)` must be a positive int, got {value!r}")
    n_par = len(parameterisation.names)
    if isinstance(start, DoubleLoop):
        start = jnp.broadcast_to(parameterisation.from_controller(start), (pos.size, n_par))
    theta = jnp.asarray(start, jnp.float64)
    if theta.shape != (pos.size, n_par):
        raise ValueError(f"`{fn}(start=...)` must be an fdjax.DoubleLoop or have shape "
                         f"({pos.size}, {n_par}), got {theta.shape}")
    opt = optax.adam(0.02) if optimiser is None else optimiser
    y = jnp.asarray(pos)
    with jax.numpy_dtype_promotion("standard"):
        state = jax.vmap(opt.init)(theta)
    best = theta
    best_j = jnp.full(pos.size, jnp.inf)
    history = []
    t_steps = 0.0
    done = 0
    while done < steps:
        k = min(chunk, steps - done)
        t0 = time.perf_counter()
        theta, state, best, best_j, hist = _run(parameterisation, objective, drive, y, theta,
                                                state, best, best_j, opt, k)
        jax.block_until_ready(hist)
        if done > 0:  # the first call compiles
            t_steps += time.perf_counter() - t0
        history.append(np.asarray(hist))
        done += k
        if progress:
            h = history[-1][-1]
            print(f"{fn}: step {done}/{steps}, J mean {np.mean(h):.4g}, max {np.max(h):.4g}",
                  file=sys.stderr, flush=True)
    terms = jax.vmap(lambda th, p: objective(parameterisation.to_controller(th), drive, p))(
        best, y)
    return LocalTuning(y, theta, best, jnp.asarray(np.concatenate(history)), terms, t_steps)


@eqx.filter_jit
def _run(par, objective, drive, y, theta, state, best, best_j, opt, steps):
    def loss(th, p):
        return objective(par.to_controller(th), drive, p).total

    value_and_grad = jax.vmap(jax.value_and_grad(loss))

    def step(carry, _):
        th, st, b, bj = carry
        j, g = value_and_grad(th, y)
        better = j < bj
        b = jnp.where(better[:, None], th, b)
        bj = jnp.where(better, j, bj)
        with jax.numpy_dtype_promotion("standard"):
            upd, st = jax.vmap(opt.update)(g, st, th)
            th = optax.apply_updates(th, upd)
        return (th, st, b, bj), j

    (theta, state, best, best_j), hist = jax.lax.scan(
        step, (theta, state, best, best_j), None, length=steps)
    return theta, state, best, best_j, hist
