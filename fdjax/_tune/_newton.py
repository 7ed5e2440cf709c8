r"""Local tuning by trust-region Newton steps with the exact Hessian, all positions in one
``vmap``.

The local objective J(θ, Y) of a 12-parameter double loop is small and stiff: the margin
penalties are steep walls (Hessian eigenvalues ~10⁴) around a curved, partly concave valley
(eigenvalues ~10 down to below zero).  First-order steps crawl along such a valley; a Newton step
with the exact Hessian follows it.  At each iteration and position, with g = ∇J and H = ∇²J at
θ (``jax.hessian``: forward over reverse, one column per parameter),

    p = argmin { g·p + ½ pᵀH p : ‖p‖ ≤ Δ }                     (the trust-region subproblem)

is solved exactly from the eigen-decomposition H = V diag(w) Vᵀ: p(λ) = −V (Vᵀg)/(w + λ), with
λ = 0 when H is positive definite and the Newton step lies inside the region, else the λ ≥
max(0, −w_min) with ‖p(λ)‖ = Δ (bisection in log λ), plus a component along the eigenvector of
w_min in the "hard case" (Moré & Sorensen 1983).  The step is accepted when the actual decrease
is more than 10⁻⁴ of the model's, ρ = (J(θ) − J(θ + p)) / (−g·p − ½ pᵀHp); the radius shrinks to
a fraction of ‖p‖ when ρ < 1/4 and doubles when ρ > 3/4 on the region's edge.  The exact
Hessian costs p forward-over-reverse columns; with ``hessian_every`` = m it is evaluated every
m-th step only and updated between by the symmetric rank-one (SR1) formula from the steps and
the gradients.

With ``hessian="margins"`` the model's Hessian is split along the objective's structure: the
margin penalties J_m (the walls, computed from the open loops on the frequency grid, without a
simulation) by their exact Hessian at every step, the rest, J − J_m (the simulated tracking
error and the barriers), by an SR1 estimate B from zero, updated with s and Δ(∇J − ∇J_m):
H ≈ ∇²J_m + B.  Each step then runs one simulation with its gradient per position.

:func:`shape_loops` runs the same steps (the exact Hessian every ``hessian_every`` steps, SR1
between) on the part of J that needs no run (the margin term and the growth-rate barrier) less
a pull on the feedback gains' logarithms: the gains go to the highest the margins allow,
without a simulation; its result is a start for :func:`tune_newton`.

The steps run in compiled loops (whole cycles of ``hessian_every`` steps per call where a cycle
fits in a call's ``chunk`` of steps, else calls of gradient steps and the exact step alone), so
that what does not depend on θ, the twins at the positions, their zero-order holds and
responses on the frequency grid and the reference's samples, is computed once per call instead
of at every evaluation (on the reference drive's 12-parameter problem a step with the exact
Hessian then costs about half, one with the gradient alone about 0.45× of the same step called
alone; ``benchmarks/tuning.py``).  The start is evaluated by the first call, as a zero first
step, not by a program of its own (which took two fifths of a first call's compilation).
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import _checks, _progress
from .._control._controllers import AbstractController
from .._drive._model import BallScrewDrive
from ._local import LocalTuning, _check_common, _settled, _start, _terms_at
from ._objective import Objective
from ._parameterisation import AbstractParameterisation

__all__ = ["tune_newton", "trust_region_step", "shape_loops", "LoopShaping"]

_ACCEPT = 1e-4
_BISECTIONS = 100
_DEFAULT_CHUNK = 10  # steps per compiled call


def trust_region_step(
    g: Float[ArrayLike, " p"], H: Float[ArrayLike, "p p"], radius: Float[ArrayLike, ""]
) -> tuple[Float[Array, " p"], Float[Array, ""]]:
    r"""The exact solution p of min { g·p + ½ pᵀHp : ‖p‖ ≤ Δ } (module docstring) and the
    model's decrease −(g·p + ½ pᵀHp).  H is symmetrised; it may be indefinite.

    p is characterised by (H + λI) p = −g, H + λI positive semi-definite, λ ≥ 0 and
    λ (Δ − ‖p‖) = 0 (Moré & Sorensen 1983); the bisection meets ‖p‖ = Δ to ~1e-15 relative.
    Pure and differentiable-free (``jit``, ``vmap``); g and H are checked finite, the radius
    finite and positive, under ``jit`` too."""
    g = jnp.asarray(g, jnp.float64)
    H = jnp.asarray(H, jnp.float64)
    if g.ndim != 1 or H.shape != (g.shape[0], g.shape[0]):
        raise ValueError(f"`trust_region_step(g=..., H=...)` must have shapes (p,) and (p, p), "
                         f"got {g.shape} and {H.shape}")
    g = _checks.finite(g, "trust_region_step(g=...)")
    H = _checks.finite(H, "trust_region_step(H=...)")
    where = "trust_region_step(radius=...)"
    delta = _checks.positive(_checks.real_scalar(radius, where), where)
    return _trust_region_step(g, H, delta)


def _trust_region_step(g, H, delta):
    """:func:`trust_region_step` without its checks, for the tuner's loop (its radii are
    positive by construction)."""
    w, V = jnp.linalg.eigh(0.5 * (H + H.T))
    gt = V.T @ g

    def p_of(lam):
        return -V @ (gt / (w + lam))

    scale = jnp.maximum(jnp.abs(w).max(), 1e-300)
    lo = jnp.maximum(0.0, -w[0]) + 1e-14 * scale
    inside = (w[0] > 0) & (jnp.linalg.norm(p_of(0.0)) <= delta)
    hi = lo + jnp.linalg.norm(g) / delta + scale

    def bisect(_, ab):
        a, b = ab
        m = jnp.sqrt(a * b)
        long = jnp.linalg.norm(p_of(m)) > delta
        return jnp.where(long, m, a), jnp.where(long, b, m)

    _, lam = jax.lax.fori_loop(0, _BISECTIONS, bisect, (lo, hi))
    p = p_of(lam)
    # the hard case: g (nearly) orthogonal to the least eigenvector of an indefinite H, so that
    # ‖p(λ)‖ < Δ even as λ → −w_min: the rest of the way to the boundary goes along that
    # eigenvector, ‖p + τ v‖ = Δ
    v = V[:, 0]
    pv = p @ v
    tau = -pv + jnp.sqrt(pv * pv + jnp.maximum(delta * delta - p @ p, 0.0))
    hard = (w[0] < 0) & (jnp.linalg.norm(p_of(lo)) < delta)
    p = jnp.where(hard, p + tau * v, p)
    p = jnp.where(inside, p_of(0.0), p)
    return p, -(g @ p + 0.5 * p @ (0.5 * (H + H.T)) @ p)


def _values(par, objective, drive, y, theta):
    """J, ∇J and ∇²J at every position (traced)."""
    def one(th, p):
        def f(t):
            v, g = jax.value_and_grad(lambda q: objective(par.to_controller(q), drive, p).total)(t)
            return g, (v, g)

        H, (v, g) = jax.jacfwd(f, has_aux=True)(th)
        return v, g, H

    return jax.vmap(one)(theta, y)


def _values_and_gradients(par, objective, drive, y, theta):
    """J and ∇J at every position (traced)."""
    return jax.vmap(jax.value_and_grad(
        lambda th, p: objective(par.to_controller(th), drive, p).total))(theta, y)


def _values_split(par, objective, drive, y, theta):
    """J, ∇J, and the gradient and Hessian of its margin term J_m at every position (traced):
    J_m from the open loops alone, J − J_m from one run and its gradient."""
    def one(th, p):
        def m(t):
            v, g = jax.value_and_grad(
                lambda q: objective.margin_term(par.to_controller(q), drive, p))(t)
            return g, (v, g)

        Hm, (vm, gm) = jax.jacfwd(m, has_aux=True)(th)
        vs, gs = jax.value_and_grad(
            lambda q: objective.simulated_term(par.to_controller(q), drive, p))(th)
        return vs + vm, gs + gm, gm, Hm

    return jax.vmap(one)(theta, y)


def _sr1(H, s, y):
    """The symmetric rank-one update of H with the step s and the change of gradient y,
    H + r rᵀ/(r·s), r = y − H s; skipped when |r·s| ≤ 1e-8 ‖r‖ ‖s‖ (or not finite)."""
    r = y - H @ s
    den = r @ s
    ok = jnp.isfinite(den) & (jnp.abs(den) > 1e-8 * jnp.linalg.norm(r) * jnp.linalg.norm(s))
    return jnp.where(ok, H + jnp.outer(r, r) / jnp.where(ok, den, 1.0), H)


def _accept(theta, j, g, H, delta, step, pred, j_t, g_t, H_t, shrink, max_radius, exact: bool,
            quasi, first=False):
    """The trial's verdict and the new radius; the model's Hessian: the trial's exact one
    where ``exact`` and the step is accepted, else the SR1 update where ``quasi`` (a boolean,
    traced or not).  ``first`` (traced or not): the trial is the start itself (a zero step),
    taken as it is, the radius kept."""
    ok = jnp.isfinite(j_t) & jnp.all(jnp.isfinite(g_t), axis=1) & jnp.all(
        jnp.isfinite(H_t), axis=(1, 2))
    rho = jnp.where(ok & (pred > 0), (j - j_t) / jnp.where(pred > 0, pred, 1.0), -1.0)
    size = jnp.linalg.norm(step, axis=1)
    new_delta = jnp.where(rho < 0.25, shrink * size,
                          jnp.where((rho > 0.75) & (size > 0.8 * delta),
                                    jnp.minimum(2.0 * delta, max_radius), delta))
    delta = jnp.where(first, delta, new_delta)
    acc = (rho > _ACCEPT) | first
    pick = lambda a, b: jnp.where(acc.reshape(acc.shape + (1,) * (a.ndim - 1)), a, b)  # noqa: E731
    H_q = jnp.where(quasi, jax.vmap(_sr1)(H, step, g_t - g), H)
    H_new = jnp.where(acc[:, None, None], H_t, H_q) if exact else H_q
    return (pick(theta + step, theta), pick(j_t, j), pick(g_t, g), H_new,
            jnp.maximum(delta, 1e-12), acc)


class _Newton(eqx.Module):
    """The iterate of every position: θ, J, ∇J, the model's Hessian H (with
    ``hessian="margins"``: the margin term's, and B the SR1 estimate of the rest, and ∇J_m),
    the trust radius Δ."""

    theta: Array
    j: Array
    g: Array
    H: Array
    delta: Array
    B: Array
    g_m: Array


def _step(par, objective, drive, y, st: _Newton, kind: str, quasi, shrink, max_radius,
          first=False):
    """One trust-region step at every position; ``kind``: "exact" (the trial's J, ∇J and
    ∇²J), "gradient" (J and ∇J; the Hessian by SR1 where ``quasi``) or "split" (the margin
    term's Hessian, SR1 for the rest).  ``first`` (a traced boolean; "exact" and "split"):
    the step is zero and the iterate takes the start's values, its radius kept (the tuner's
    start, evaluated in the program of the steps).  Returns the new iterate and J at the
    trial."""
    step, pred = jax.vmap(_trust_region_step)(st.g, st.H + st.B, st.delta)
    step = jnp.where(first, 0.0, step)
    trial = st.theta + step
    B, g_m = st.B, st.g_m
    if kind == "split":
        j_t, g_t, g_mt, H_t = _values_split(par, objective, drive, y, trial)
        B = jnp.where(first, B, jax.vmap(_sr1)(B, step, (g_t - g_mt) - (st.g - st.g_m)))
    elif kind == "exact":
        j_t, g_t, H_t = _values(par, objective, drive, y, trial)
    else:
        j_t, g_t = _values_and_gradients(par, objective, drive, y, trial)
        H_t = st.H
    theta, j, g, H, delta, acc = _accept(st.theta, st.j, st.g, st.H, st.delta, step, pred, j_t,
                                         g_t, H_t, shrink, max_radius, kind != "gradient",
                                         quasi, first)
    if kind == "split":
        g_m = jnp.where(acc[:, None], g_mt, g_m)
    return _Newton(theta, j, g, H, delta, B, g_m), j_t


def _loop_step(par, objective, drive, y, kind, quasi, shrink, max_radius, first=False):
    """A ``fori_loop`` body: one :func:`_step` of ``kind``, its trial's J written to row k of
    the history; carry (iterate, history, k)."""
    def body(_, carry):
        st, hist, k = carry
        st, j_t = _step(par, objective, drive, y, st, kind, quasi, shrink, max_radius, first)
        return st, hist.at[k].set(j_t), k + 1
    return body


@eqx.filter_jit
def _run_cycles(par, objective, drive, y, st, cycles, shrink, max_radius, every, split: bool,
                quasi, rows: int, start):
    """``cycles`` cycles of ``every`` − 1 gradient steps and one step with the exact Hessian
    (or, with ``split``, where ``every`` is 1, one step with the margins' Hessian), in one
    compiled loop: what does not depend on θ (the twins, their zero-order holds and responses
    on the grid, the reference) is computed once, not at every step.  With ``start``, a cycle
    of one zero step comes first: it evaluates J, ∇J and the Hessian at ``st.theta`` (the
    tuner's start; ``st``'s other values are placeholders).  Returns the iterate and J at
    every trial, (rows, n) (the first cycles·every rows filled, after J at the start with
    ``start``).  ``cycles``, ``every``, ``quasi`` (SR1 updates of the model's Hessian, with
    ``every`` > 1) and ``start`` are traced: one program for any ``hessian_every`` and count
    of cycles that fit in ``rows`` with the start's row."""

    def cycle(c, carry):
        first = start & (c == 0)
        if split:
            return _loop_step(par, objective, drive, y, "split", quasi, shrink, max_radius,
                              first)(0, carry)
        carry = jax.lax.fori_loop(0, jnp.where(first, 0, every - 1), _loop_step(
            par, objective, drive, y, "gradient", quasi, shrink, max_radius), carry)
        return _loop_step(par, objective, drive, y, "exact", quasi, shrink, max_radius,
                          first)(0, carry)

    hist = jnp.zeros((rows,) + st.j.shape, st.j.dtype)
    st, hist, _ = jax.lax.fori_loop(0, cycles + start.astype(cycles.dtype), cycle,
                                    (st, hist, jnp.asarray(0)))
    return st, hist


@eqx.filter_jit
def _run_gradient_steps(par, objective, drive, y, st, steps, shrink, max_radius, rows: int):
    """``steps`` (traced, at most ``rows``) gradient steps with SR1 updates, one compiled
    loop: the steps after the last whole cycle of :func:`_run_cycles`, or, with
    ``hessian_every`` above the chunk, the steps between the exact ones."""
    body = _loop_step(par, objective, drive, y, "gradient", True, shrink, max_radius)
    hist = jnp.zeros((rows,) + st.j.shape, st.j.dtype)
    st, hist, _ = jax.lax.fori_loop(0, steps, body, (st, hist, jnp.asarray(0)))
    return st, hist


def _check_trust(fn, radius, max_radius, shrink):
    """The trust region's settings of ``fn``, each named in its error."""
    for name, value, ok, want in (
            ("radius", radius, lambda v: v > 0, "a positive number"),
            ("max_radius", max_radius, lambda v: v >= radius, f"a number ≥ radius = {radius!r}"),
            ("shrink", shrink, lambda v: 0 < v < 1, "a number in (0, 1)")):
        _checks.static_number(value, f"{fn}({name}=...)", ok, want)


def tune_newton(
    parameterisation: AbstractParameterisation,
    objective: Objective,
    drive: BallScrewDrive,
    positions_m: Float[ArrayLike, " n"],
    start: AbstractController | Float[ArrayLike, " p"] | Float[ArrayLike, "n p"],
    *,
    steps: int = 60,
    radius: float = 0.3,
    max_radius: float = 5.0,
    shrink: float = 0.25,
    hessian_every: int = 1,
    hessian: str = "full",
    chunk: int = _DEFAULT_CHUNK,
    progress: bool = False,
) -> LocalTuning:
    r"""Tune one controller per table position by trust-region Newton steps with the exact
    Hessian of the objective (module docstring), all positions in one ``vmap``:

        θ_i ← θ_i + p_i,  p_i = argmin_{‖p‖ ≤ Δ_i} ∇J·p + ½ pᵀ∇²J p,   J = J(controller(θ_i), Y_i).

    Each step evaluates J, its gradient and its Hessian once per position (the Hessian's p
    columns are forward-mode derivatives of the reverse-mode gradient: 2p + 2 passes, p = 12
    for :class:`fdjax.DoubleLoopParameterisation`; on the reference drive a step with it
    costs as much as five to ten with the gradient alone, 69–90 against 8–15 ms for six
    positions).  On the 12-parameter local problem it reaches lower objectives than
    first-order steps, and than the adaptive simplex given 1500 evaluations per position;
    with ``hessian_every=8`` in less wall time than the simplex compiled as this tuner is
    (:func:`fdjax.tune_simplex`, 1.1–1.7× over the runs), with the exact Hessian at every
    step in more (``benchmarks/tuning.py``); it stops in the minimum its trust region leads to, and
    a simplex run for 8× longer ends lower at five of six positions
    (``benchmarks/tuning_converged.py``).  In ``benchmarks/tuning_variants.py`` an initial
    ``radius`` of 3 reached the simplex's best as well in about as many steps (1 missed one
    position), ``hessian_every`` = 20 reached it too, at one position only with its last
    step, "the start only" missed it at three positions (from a start of :func:`shape_loops`
    it reaches it at all six, with 31× fewer simulations and 13× less wall time than the
    simplex), and
    ``hessian="margins"`` took 10× fewer simulations than the simplex but saved less time than
    the exact Hessian.  For many parameters (a network) use
    :func:`fdjax.train_schedule`.  The Hessian is exact for the tracking error and the margin
    penalties; the growth-rate barrier's second derivative holds the dominant eigenspace
    fixed (its gradient is exact), which the acceptance test ρ absorbs.

    Args:
        parameterisation, objective, drive, positions_m, start: as :func:`fdjax.tune_local`.
        steps: Newton steps (≥ 1), each one evaluation of J with its derivatives per position.
        radius: the initial trust radius Δ in θ (> 0; θ is of order one).
        max_radius: the largest trust radius (≥ ``radius``).
        shrink: a rejected or poor step (ρ < 1/4) sets Δ to ``shrink``·‖p‖ (0 < shrink < 1).
        hessian_every: the exact Hessian at the start and at the trial of every
            ``hessian_every``-th step (steps k = m, 2m, …); the other steps evaluate J and its
            gradient only (2 passes instead of 2p + 2) and update the model's Hessian by the
            symmetric rank-one formula H + r rᵀ/(r·s), r = Δ∇J − H s, s the step (SR1 keeps
            the negative curvature a trust region uses).  1: the exact Hessian every step.
        hessian: ``"full"``: the model's Hessian is that of J (above).  ``"margins"``: the
            exact Hessian of the margin penalties alone (:meth:`fdjax.Objective.margin_term`:
            the steep walls, from the open loops on the frequency grid, no simulation) at
            every step, plus an SR1 estimate, from zero, of the rest of J (the simulated
            tracking error and the barriers) from the changes of its gradient, ∇J − ∇J_m.
            Each step then runs the simulation once with its gradient (2 passes); with
            ``hessian_every`` = 1 only.
        chunk: steps per compiled call, rounded up to whole cycles of ``hessian_every``
            steps; with ``hessian_every`` > ``chunk``, calls of at most ``chunk`` gradient
            steps and the step with the exact Hessian alone (the progress bar is drawn between
            calls).  The steps of a call run in one compiled loop, which computes what does not
            depend on θ (the twins, their zero-order holds and responses on the frequency grid,
            the reference) once per call; a chunk below 10 runs in the programs of a chunk of
            10 (no new compilation).
        progress: a progress bar with the objective's mean and max after each call (stderr).

    Returns:
        A :class:`fdjax.LocalTuning`: ``theta`` and ``best_theta`` the accepted point (the
        lowest J seen), ``history`` J at the start and at every step's trial point, (steps + 1,
        n), ``evaluations`` ones, (steps, n) (one evaluation with the gradient per step and
        position, and the Hessian on every ``hessian_every``-th), ``seconds`` the steps' wall
        time, measured over the calls after the first of each program (which may compile)
        and scaled to all steps at their rate (0.0 when no call is such).
    """
    fn = "tune_newton"
    pos, objective = _check_common(fn, parameterisation, objective, drive, positions_m, steps,
                                   chunk)
    _check_trust(fn, radius, max_radius, shrink)
    hessian_every = _checks.static_int(hessian_every, f"{fn}(hessian_every=...)", 1)
    if hessian not in ("full", "margins"):
        raise ValueError(f"`{fn}(hessian=...)` must be 'full' or 'margins', got {hessian!r}")
    split = hessian == "margins"
    if split and hessian_every != 1:
        raise ValueError(f"`{fn}(hessian_every=...)` must be 1 with hessian='margins' (the "
                         f"margins' Hessian is exact at every step), got {hessian_every!r}")
    theta = jnp.asarray(_start(fn, parameterisation, start, pos.size))
    y = jnp.asarray(pos)
    p = theta.shape[1]
    # J, ∇J and the model's Hessian at the start are evaluated by the first call of the steps'
    # program (a zero first step), not in a program of their own: until then placeholders.
    # With "margins", H is the margins' Hessian (exact) and B the rest of J's (SR1 from zero).
    # No weak types: the first call's iterate is typed as the calls' results, one program.
    zeros = jnp.zeros((pos.size, p, p))
    st = _settled(_Newton(theta, jnp.zeros(pos.size), jnp.zeros((pos.size, p)), zeros,
                          jnp.full(pos.size, float(radius)), zeros, jnp.zeros((pos.size, p))))
    trust = dict(shrink=jnp.asarray(float(shrink)), max_radius=jnp.asarray(float(max_radius)))
    every = hessian_every
    # whole cycles of `every` steps per call where they fit in a chunk; else calls of gradient
    # steps and the exact step alone
    cycles_per_call = -(-chunk // every) if every <= chunk else 0
    # the cycles' history: a call of whole cycles (every ≤ chunk) fills the start's row and
    # cycles·every ≤ chunk + every − 1 ≤ 2·chunk − 1 rows, the exact step alone or the start
    # alone one: 2·chunk rows, one program for any hessian_every and count of steps.  A chunk
    # below the default runs in the default chunk's programs (its histories are sized for
    # it), and the gradient steps' history in one program for any hessian_every.
    grad_rows = max(chunk, _DEFAULT_CHUNK)  # the gradient steps' history
    rows = 2 * grad_rows

    def cycles(st, n_cycles, every, split, quasi, start):
        return _run_cycles(parameterisation, objective, drive, y, st, jnp.asarray(n_cycles),
                           every=jnp.asarray(every), split=split, quasi=jnp.asarray(quasi),
                           rows=rows, start=jnp.asarray(start), **trust)

    history = []
    seen, t_later, later_steps = set(), 0.0, 0
    done = 0
    started = not (cycles_per_call and steps >= every)
    if started:  # the first call runs gradient steps: the start alone first
        st, hist = cycles(st, 0, 1, False, False, True)
        history.append(np.asarray(hist)[:1])
        seen.add("exact")
    while done < steps:
        t0 = time.perf_counter()
        exact_at = done + (every - 1 - done % every)  # the next step with the exact Hessian
        if cycles_per_call and done % every == 0 and steps - done >= every:
            n_cycles = min(cycles_per_call, (steps - done) // every)
            st, hist = cycles(st, n_cycles, every, split, every > 1, not started)
            n, program = n_cycles * every, "cycles"
        elif done == exact_at:  # one cycle of one step: the exact step alone
            st, hist = cycles(st, 1, 1, False, True, False)
            n, program = 1, "exact"
        else:
            n = min(exact_at, steps, done + chunk) - done
            st, hist = _run_gradient_steps(parameterisation, objective, drive, y, st,
                                           jnp.asarray(n), rows=grad_rows, **trust)
            program = "gradient"
        # (a write past the history would be dropped)
        assert n + (not started) <= (grad_rows if program == "gradient" else rows)
        history.append(np.asarray(hist)[:n + (not started)])  # waits for the steps
        started = True
        if program in seen:  # the first call of each program may compile it
            t_later += time.perf_counter() - t0
            later_steps += n
        seen.add(program)
        done += n
        if progress:
            jj = np.asarray(st.j)
            _progress.bar(fn, done, steps, f"J mean {np.mean(jj):.4g}, max {np.max(jj):.4g}")
    t_steps = t_later * steps / later_steps if later_steps else 0.0
    theta = st.theta
    terms = _terms_at(parameterisation, objective, drive, theta, y)
    return LocalTuning(y, theta, theta, jnp.asarray(np.concatenate(history)), terms, t_steps,
                       jnp.ones((steps, pos.size), jnp.int32))


# ------------------------------------------------------------------ loop shaping on the margins
_SHAPED_GAINS = ("kp", "kv", "ki")
# the feed-forward gains act on the reference alone: neither the open loops nor the closed
# loop's poles depend on them, so S does not, and the shaping leaves them out of its steps
_FEEDFORWARD = ("k_ffv", "k_ffa")


class LoopShaping(eqx.Module):
    """Result of :func:`shape_loops`.

    Attributes:
        positions_m: the positions (m), (n,).
        theta: the shaped parameters per position, (n, p): a start for a tuner.
        history: S(θ) at the start and at every step's trial point, (steps + 1, n).
        margin_term: the objective's margin term at ``theta``, (n,).
        seconds: wall time of the call (s), compilation included where its program is new
            (steps in another block of ten, other shapes).
    """

    positions_m: Float[Array, " n"]
    theta: Float[Array, "n p"]
    history: Float[Array, "steps n"]
    margin_term: Float[Array, " n"]
    seconds: float = eqx.field(static=True)


def _shaping_objective(par, objective, drive, weights, free, theta_full):
    """S at one position as a function of the shaped parameters ``free`` (the others, the
    feed-forward gains, held at ``theta_full``'s)."""
    def s(sub, p):
        t = theta_full.at[free].set(sub)
        return objective.unsimulated_term(par.to_controller(t), drive, p) - weights @ t
    return s


def _shaping_values(par, objective, drive, y, theta, weights, free, full, hessian=True):
    """S, its gradient and (``hessian``) its Hessian at every position in the shaped
    parameters θ[free] (traced; no simulation); without the Hessian, zeros in its place."""
    def one(sub, th_full, p):
        s = _shaping_objective(par, objective, drive, weights, free, th_full)
        if not hessian:
            v, g = jax.value_and_grad(s)(sub, p)
            return v, g, jnp.zeros((sub.size, sub.size))

        def f(t):
            v, g = jax.value_and_grad(s)(t, p)
            return g, (v, g)

        H, (v, g) = jax.jacfwd(f, has_aux=True)(sub)
        return v, g, H

    return jax.vmap(one)(theta, full, y)


@eqx.filter_jit
def _run_shaping(par, objective, drive, y, theta, weights, steps, every, radius, shrink,
                 max_radius, rows: int, free: tuple[int, ...]):
    """``steps`` (traced, at most ``rows`` − 1) trust-region steps on S in θ[free], one compiled
    loop: cycles of ``every`` (traced) steps, SR1 updates of the model's Hessian at the first
    every − 1 and S's exact Hessian at the last, then the steps left over with SR1 updates.
    Returns θ, J_m at θ and S at the start and every trial, (rows, n)."""
    free = jnp.asarray(free)
    full = theta
    values = lambda th, hessian: _shaping_values(  # noqa: E731
        par, objective, drive, y, th, weights, free, full, hessian)
    sub = theta[:, free]
    j, g, H = values(sub, True)
    delta = jnp.full(y.shape, radius)
    hist = jnp.zeros((rows,) + y.shape, j.dtype).at[0].set(j)

    def step(k, carry, exact):
        sub, j, g, H, delta, hist = carry
        p, pred = jax.vmap(_trust_region_step)(g, H, delta)
        j_t, g_t, H_t = values(sub + p, exact)
        sub, j, g, H, delta, _ = _accept(sub, j, g, H, delta, p, pred, j_t, g_t, H_t,
                                         shrink, max_radius, exact, not exact)
        return sub, j, g, H, delta, hist.at[k + 1].set(j_t)

    def cycle(c, carry):
        carry = jax.lax.fori_loop(0, every - 1, lambda i, cr: step(c * every + i, cr, False),
                                  carry)
        return step(c * every + every - 1, carry, True)

    carry = jax.lax.fori_loop(0, steps // every, cycle, (sub, j, g, H, delta, hist))
    done = (steps // every) * every
    sub, *_, hist = jax.lax.fori_loop(0, steps - done, lambda i, cr: step(done + i, cr, False),
                                      carry)
    theta = theta.at[:, free].set(sub)
    margins = jax.vmap(lambda th, p: objective.margin_term(par.to_controller(th), drive, p))(
        theta, y)
    return theta, margins, hist


def shape_loops(
    parameterisation: AbstractParameterisation,
    objective: Objective,
    drive: BallScrewDrive,
    positions_m: Float[ArrayLike, " n"],
    start: AbstractController | Float[ArrayLike, " p"] | Float[ArrayLike, "n p"],
    *,
    steps: int = 40,
    gain_weight: float = 0.03,
    hessian_every: int = 2,
    radius: float = 0.3,
    max_radius: float = 5.0,
    shrink: float = 0.25,
) -> LoopShaping:
    r"""Move the feedback gains of a start to the highest the margin penalties allow, without a
    simulation: a start for :func:`tune_newton` (classical loop shaping, paper Sec. 4.2: as
    much loop gain as the stability margins admit).  At every position, trust-region steps (as
    :func:`tune_newton`'s) minimise

        S(θ) = J_u(θ, Y) − w Σ_{k ∈ {k_p, k_v, k_i}} θ_k,

    J_u the part of the objective that needs no run (:meth:`fdjax.Objective.unsimulated_term`:
    the margin penalties from the open loops on the frequency grid, and the barrier on the
    sampled closed loop's least stable pole, which keeps the loop stable where the margins'
    distances alone could not tell) and θ_k the gains' logarithms: a design settles where the
    penalties' slope meets w, a little inside the margin requirements, its gains lowered where
    the start violates them and raised where it has room.  The filters move with the gains.
    The feed-forward gains (``k_ffv``, ``k_ffa``) act on the reference alone, so S does not
    depend on them: the steps leave them out and they stay as the start has them.  The model's
    Hessian is S's exact Hessian at the start and at every ``hessian_every``-th step, updated
    between by SR1 (as :func:`tune_newton`'s ``hessian_every``).  No step runs the
    simulation, so the tracking error plays no part: the tuner that follows weighs it.

    On the reference drive's 12-parameter problem (``benchmarks/tuning.py``: the reference
    controller with k_v halved, six positions), the default 40 steps with the exact Hessian
    every second step bring J from 9.8–285 to 1.75–3.96 in 0.96 s, and :func:`tune_newton`
    with the exact Hessian at the start only (``hessian_every`` above ``steps``) then reaches
    the adaptive simplex's best J at every position within 47 steps: 31× fewer simulations
    than the simplex and 13× less wall time, shaping included.  From the start itself the same
    tuner stops above it at three positions.  The outcome depends on ``steps``,
    ``hessian_every`` and ``radius`` (with 30 or 35 steps, or the exact Hessian at every
    step, it stopped above the simplex's best at 0.7 m within 100 steps) and on round-off, as
    every search on this objective does.

    Args:
        parameterisation, objective, drive, positions_m, start: as :func:`fdjax.tune_newton`.
            The parameterisation must name ``kp``, ``kv`` and ``ki`` among its parameters
            (:class:`fdjax.DoubleLoopParameterisation`).
        steps: trust-region steps (≥ 1).
        gain_weight: w (> 0), the pull on each gain's logarithm against the penalties.
        hessian_every: S's exact Hessian every this many steps (≥ 1; 1: at every step),
            SR1 updates between.
        radius, max_radius, shrink: the trust region's, as :func:`fdjax.tune_newton`'s.

    Returns:
        A :class:`fdjax.LoopShaping`.
    """
    fn = "shape_loops"
    pos, objective = _check_common(fn, parameterisation, objective, drive, positions_m, steps,
                                   1)
    _checks.static_number(gain_weight, f"{fn}(gain_weight=...)", lambda v: v > 0,
                          "a positive number")
    _check_trust(fn, radius, max_radius, shrink)
    names = parameterisation.names
    missing = [n for n in _SHAPED_GAINS if n not in names]
    if missing:
        raise ValueError(f"`{fn}(parameterisation=...)` must have the gains "
                         f"{', '.join(_SHAPED_GAINS)} among its parameters, got "
                         f"{type(parameterisation).__name__} with {', '.join(names)}")
    _checks.static_int(hessian_every, f"{fn}(hessian_every=...)", 1)
    weights = jnp.asarray([float(gain_weight) if n in _SHAPED_GAINS else 0.0 for n in names])
    free = tuple(i for i, n in enumerate(names) if n not in _FEEDFORWARD)
    theta = jnp.asarray(_start(fn, parameterisation, start, pos.size))
    y = jnp.asarray(pos)
    # the history's rows: one program for every count of steps in a block of ten
    rows = -(-steps // _DEFAULT_CHUNK) * _DEFAULT_CHUNK + 1
    t0 = time.perf_counter()
    th, margins, hist = jax.block_until_ready(_run_shaping(
        parameterisation, objective, drive, y, theta, weights, jnp.asarray(steps),
        jnp.asarray(min(hessian_every, steps + 1)), jnp.asarray(float(radius)),
        jnp.asarray(float(shrink)), jnp.asarray(float(max_radius)), rows, free))
    return LoopShaping(y, th, hist[:steps + 1], margins, time.perf_counter() - t0)
