r"""Stability margins of an open loop L (negative feedback), with python-control's conventions
(``control.stability_margins``).

Of all phase crossovers (L on the negative real axis) the gain margin 1/|L| closest to 1 in the
log sense; of all gain crossovers (|L| = 1) the phase margin ``PM = (arg L mod 360°) − 180°``
smallest in magnitude; the modulus margin ``min_ω |1 + L(iω)|`` (the inverse peak sensitivity).

Crossings and the least |1 + L| are found on the frequency grid (log-frequency interpolation
of log L within a grid interval) and, when L is a model (a function of ω), refined by
safeguarded Newton steps on the model's own L to round-off; the result is differentiable
through the refined crossing (implicit function theorem: one last Newton step carries the
gradient).  On a model, a pair of crossings that no grid point separates (a resonance that
carries |L| above 1, or arg L past −180°, and back between two grid points) is found from the
extremum of |L| or arg L between them.  The same algorithm serves continuous loops (L(iω))
and sampled ones (L(e^{iωT}), ω below the Nyquist frequency).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["Margins", "grid_margins", "model_margins"]

_TWO_PI = 2.0 * math.pi
_N_CANDIDATES = 3  # crossings refined per criterion (the best ones on the grid)
# grid points searched per criterion for two crossings between them and their neighbours (the
# ones where the crossing equation comes closest to zero)
_N_HIDDEN = 2
# Safeguarded Newton (or bisection) steps from the grid estimate, in one compiled loop (more steps
# cost run time, not compilation); then one step with gradients.  Near a sharp resonance the
# grid estimate can sit several bisections away: 3 steps left crossings at 1e-8 whose value
# depended on round-off (a gain crossover of a lead loop, a modulus margin next to a lightly
# damped mode); 12 reached python-control's value in both.
_NEWTON_STEPS = 16
# The modulus margin's grid estimate: the best local minima of |1 + L| on the grid, each
# searched on the log-frequency interpolant at this many points per grid interval.
_N_SPIRAL_MINIMA = 8
_SPIRAL_SAMPLES = 32


def _c(x) -> Array:
    return jnp.asarray(x).astype(jnp.complex128)


class Margins(eqx.Module):
    """Stability margins of one open loop L (python-control's conventions; see module docs).

    Only crossings inside the frequency grid are found: make the grid span them.

    Attributes (shape ``*batch``):
        gain_margin: 1/|L| at the phase crossover whose margin is closest to 1 (log sense);
            inf when L never crosses the negative real axis on the grid.
        phase_margin_deg: (arg L mod 360°) − 180° at the gain crossover with the smallest
            |margin| (°); inf without gain crossover.
        modulus_margin: min |1 + L| (the inverse of the peak sensitivity).
        phase_crossover_hz, gain_crossover_hz, modulus_hz: where (Hz); NaN where none.
    """

    gain_margin: Float[Array, "*batch"]
    phase_margin_deg: Float[Array, "*batch"]
    modulus_margin: Float[Array, "*batch"]
    phase_crossover_hz: Float[Array, "*batch"]
    gain_crossover_hz: Float[Array, "*batch"]
    modulus_hz: Float[Array, "*batch"]

    @property
    def gain_margin_db(self) -> Float[Array, "*batch"]:
        """20 log10(gain_margin) (dB)."""
        return 20.0 * jnp.log10(self.gain_margin)



def _grid_candidates(u, L):
    """Crossing candidates per grid interval from log-frequency interpolation of log L.

    Within [u_k, u_{k+1}] (u = log ω) ``L(t) = L_k (L_{k+1}/L_k)^t``: exact for power laws
    (integrators, the rigid body) and second order in the spacing otherwise.  Returns, per
    criterion, (valid, u estimate, bracket lo, bracket hi, score, value, sign of the crossing
    equation at lo).
    """
    L0, L1 = L[:-1], L[1:]
    u0, u1 = u[:-1], u[1:]
    lm = jnp.log(jnp.abs(L))
    lm0, lm1 = lm[:-1], lm[1:]
    dphi = jnp.angle(L1 / L0)
    # Phase crossover: arg(−L) = a0 + t dphi crosses 0 (the negative real axis).
    a0 = jnp.angle(-L0)
    a1 = a0 + dphi
    # a zero of L on either side has no phase: no crossing there (L ≡ 0 has no gain margin
    # to lose, GM = ∞)
    pc = ((a0 <= 0) != (a1 <= 0)) & (jnp.abs(L0) > 0) & (jnp.abs(L1) > 0)
    t = jnp.where(pc, a0 / jnp.where(pc, a0 - a1, 1.0), 0.5)
    lm_pc = lm0 + t * (lm1 - lm0)
    sign = jnp.where(a0 <= 0, -1.0, 1.0)
    gm = (pc, u0 + t * (u1 - u0), u0, u1, jnp.abs(lm_pc), jnp.exp(-lm_pc), sign)
    # Gain crossover: log|L| = lm0 + t (lm1 − lm0) crosses 0.
    gc = (lm0 > 0) != (lm1 > 0)
    t = jnp.where(gc, lm0 / jnp.where(gc, lm0 - lm1, 1.0), 0.5)
    pm_deg = jnp.degrees(jnp.remainder(jnp.angle(L0) + t * dphi, _TWO_PI) - math.pi)
    sign = jnp.where(lm0 > 0, 1.0, -1.0)
    pm = (gc, u0 + t * (u1 - u0), u0, u1, jnp.abs(pm_deg), pm_deg, sign)
    # Modulus margin: local minima of |1 + L|² on the grid, vertex of the parabola through the
    # three points in u; the two ends of the grid are candidates too (not refined).
    d2 = jnp.abs(1.0 + L) ** 2
    xm, x0, xp = u[:-2], u[1:-1], u[2:]
    ym, y0, yp = d2[:-2], d2[1:-1], d2[2:]
    interior = (y0 <= ym) & (y0 < yp)
    num = (x0 - xm) ** 2 * (y0 - yp) - (x0 - xp) ** 2 * (y0 - ym)
    den = (x0 - xm) * (y0 - yp) - (x0 - xp) * (y0 - ym)
    safe = interior & (den != 0)
    xv = jnp.clip(x0 - 0.5 * num / jnp.where(safe, den, 1.0), xm, xp)
    xv = jnp.where(safe, xv, x0)
    # value of the interpolating parabola at xv (Lagrange form)
    yv = (
        ym * (xv - x0) * (xv - xp) / ((xm - x0) * (xm - xp))
        + y0 * (xv - xm) * (xv - xp) / ((x0 - xm) * (x0 - xp))
        + yp * (xv - xm) * (xv - x0) / ((xp - xm) * (xp - x0))
    )
    # A parabola whose vertex dives below zero fits a resonance the grid does not resolve (it
    # gave margins of 0 for loops whose grid never came closer than 0.07 to −1).  There the
    # estimate is the least |1 + L(t)|² on the crossings' interpolant, L(t) = L_k (L_{k+1}/L_k)^t,
    # over the two intervals around the grid point (_SPIRAL_SAMPLES points in each), for the
    # best _N_SPIRAL_MINIMA such points by grid value; the others keep their grid value.  On a
    # model the estimate only starts the refinement.
    dived = yv < 0
    xv, yv = jnp.where(dived, x0, xv), jnp.clip(yv, 0.0, y0)
    yv = jnp.where(dived, y0, yv)
    n_best = min(_N_SPIRAL_MINIMA, y0.shape[0])
    _, best = jax.lax.top_k(-jnp.where(interior & dived, y0, jnp.inf), n_best)
    t = jnp.linspace(0.0, 1.0, _SPIRAL_SAMPLES + 1)
    log_ratio = jax.lax.complex(lm1 - lm0, dphi)  # per interval: L(t) = L_k e^{t·log_ratio}
    halves = []
    for k in (best, best + 1):  # the interval left of the grid point, then the one right of it
        Lt = L0[k][:, None] * jnp.exp(_c(t)[None, :] * log_ratio[k][:, None])
        halves.append((jnp.abs(1.0 + Lt) ** 2, u0[k][:, None] + t * (u1[k] - u0[k])[:, None]))
    dd = jnp.concatenate([halves[0][0], halves[1][0][:, 1:]], axis=1)
    uu = jnp.concatenate([halves[0][1], halves[1][1][:, 1:]], axis=1)
    j = jnp.argmin(dd, axis=1)
    pick, use = jnp.arange(n_best), dived[best]
    xv = xv.at[best].set(jnp.where(use, uu[pick, j], xv[best]))
    yv = yv.at[best].set(jnp.where(use, jnp.minimum(dd[pick, j], y0[best]), yv[best]))
    ends = jnp.array([True, True])
    sm_valid = jnp.concatenate([ends[:1], interior, ends[1:]])
    sm_u = jnp.concatenate([u[:1], xv, u[-1:]])
    sm_lo = jnp.concatenate([u[:1], xm, u[-1:]])
    sm_hi = jnp.concatenate([u[:1], xp, u[-1:]])
    sm_val = jnp.sqrt(jnp.concatenate([d2[:1], yv, d2[-1:]]))
    sm = (sm_valid, sm_u, sm_lo, sm_hi, sm_val, sm_val, -jnp.ones_like(sm_u))
    return gm, pm, sm


def _hidden_pairs(u, L):
    """Grid points where a crossing equation comes closest to zero without crossing it in
    either interval beside them: a resonance can carry |L| above 1 (or arg L past −180°) and
    back between two grid points.  Per crossing criterion (phase crossover, gain crossover):
    (valid, bracket lo, bracket hi, sign of the equation there, score |f| at the grid point).
    The model's extremum of the equation in the bracket decides whether a pair is hidden
    there (:func:`model_margins`)."""
    lm = jnp.log(jnp.abs(L))
    out = []
    for f in (jnp.angle(-L), lm):
        fm, f0, fp = f[:-2], f[1:-1], f[2:]
        a = jnp.abs(f)
        am, a0, ap = a[:-2], a[1:-1], a[2:]
        same = (jnp.sign(fm) == jnp.sign(f0)) & (jnp.sign(fp) == jnp.sign(f0)) & (f0 != 0)
        # the phase equation wraps at ±π, far from the negative real axis
        near = jnp.isfinite(lm[1:-1]) & ((f is lm) | (a0 < 0.5 * math.pi))
        valid = same & near & (a0 <= am) & (a0 < ap)
        out.append((valid, u[:-2], u[2:], jnp.sign(f0), a0))
    return out


def _pick(valid, score):
    s = jnp.where(valid, score, jnp.inf)
    k = jnp.argmin(s)
    return k, jnp.any(valid)


def _finish(gm, pm, sm) -> Margins:
    """Margins from the chosen (found, u, value) of each criterion."""

    def freq(found, u):
        return jnp.where(found, jnp.exp(jnp.where(found, u, 0.0)) / _TWO_PI, jnp.nan)

    (gf, gu, gv), (pf, pu, pv), (sf, su, sv) = gm, pm, sm
    return Margins(
        gain_margin=jnp.where(gf, gv, jnp.inf),
        phase_margin_deg=jnp.where(pf, pv, jnp.inf),
        modulus_margin=sv,
        phase_crossover_hz=freq(gf, gu),
        gain_crossover_hz=freq(pf, pu),
        modulus_hz=freq(sf, su),
    )


def grid_margins(u, L) -> Margins:
    """Margins from a sampled open loop (no model): interpolated crossings."""
    out = []
    for valid, u_est, _, _, score, value, _ in _grid_candidates(u, L):
        k, found = _pick(valid, score)
        out.append((found, u_est[k], value[k]))
    return _finish(*out)


def _jet(L_fn, params, v):
    """L(e^v) of every loop and its first two derivatives in v = log ω (each shape (n_loops,))."""
    (L, L1), (_, L2) = jax.jvp(lambda w: _jet1(L_fn, params, w), (v,), (jnp.ones_like(v),))
    return L, L1, L2


def _jet1(L_fn, params, v):
    """L(e^v) of every loop and its derivative in v = log ω (each shape (n_loops,))."""
    return jax.jvp(lambda w: jnp.stack(L_fn(params, jnp.exp(w))), (v,), (jnp.ones_like(v),))


def _equations(L, L1):
    """The three crossing equations, stacked (3,): arg(−L) = 0 (phase crossover), log|L| = 0
    (gain crossover), d|1 + L|²/dv / 2 = 0 (modulus margin)."""
    return jnp.stack([jnp.angle(-L), jnp.log(jnp.abs(L)), jnp.real((1.0 + L) * jnp.conj(L1))])


def _criteria(L, L1, L2):
    """(f, df/dv) of the crossing equations (:func:`_equations`), then of the equations of
    their extrema in v: d arg(−L)/dv = 0 and d log|L|/dv = 0 (stacked (5,))."""
    r = L1 / L
    dr = L2 / L - r * r
    f = jnp.concatenate([_equations(L, L1), jnp.stack([jnp.imag(r), jnp.real(r)])])
    df = jnp.stack([
        jnp.imag(r), jnp.real(r), jnp.abs(L1) ** 2 + jnp.real((1.0 + L) * jnp.conj(L2)),
        jnp.imag(dr), jnp.real(dr),
    ])
    return f, df


def _values(L):
    """(score, value) of each criterion at a crossing, stacked (3,)."""
    pm = jnp.degrees(jnp.remainder(jnp.angle(L), _TWO_PI) - math.pi)
    sm = jnp.abs(1.0 + L)
    score = jnp.stack([jnp.abs(jnp.log(jnp.abs(L))), jnp.abs(pm), sm])
    value = jnp.stack([1.0 / jnp.abs(L), pm, sm])
    return score, value


def model_margins(u, Ls, L_fn, params) -> list[Margins]:
    """Margins of the loops ``L_fn(params, ω)`` (tuple, sampled as ``Ls`` on ω = e^u), every
    crossing refined on the model.

    Per loop and criterion the best ``_N_CANDIDATES`` grid crossings are bracketed and refined
    together (one vectorised, safeguarded Newton iteration over all of them: bisection when a
    step leaves its bracket) with the parameters' gradients stopped.  Crossings the grid does
    not see, two inside one pair of grid intervals (a resonance that lifts |L| above 1 or turns
    arg L past −180° and back between grid points), are looked for first: at the best
    ``_N_HIDDEN`` grid points where the equation comes closest to zero without crossing,
    its extremum is refined on the model the same way; where the extremum lies across zero, the
    two crossings on either side of it join the candidates.  One last Newton step with live
    parameters, ``v* = v − f(v; θ)/f'(v)``, carries the derivative of the crossing (implicit
    function theorem: dv*/dθ = −f_θ/f_v), and L at v* is its first-order expansion from v
    (exact to round-off, with the right derivative).  Then the best is chosen again.
    """
    frozen = jax.tree_util.tree_map(jax.lax.stop_gradient, params)
    k = min(_N_CANDIDATES, u.shape[0] - 1)
    k_pairs = min(_N_HIDDEN, u.shape[0] - 2)
    lanes = []  # (loop, criterion, valid, u0, lo, hi, sign at lo) per candidate
    extrema = []  # (loop, criterion, valid, lo, hi, sign of the crossing equation there)
    for i, L in enumerate(Ls):
        for c, (valid, u_est, lo, hi, score, _, sign) in enumerate(_grid_candidates(u, L)):
            _, idx = jax.lax.top_k(-jnp.where(valid, score, jnp.inf), k)
            lanes.append((
                jnp.full(k, i), jnp.full(k, c), valid[idx], u_est[idx], lo[idx], hi[idx],
                sign[idx],
            ))
        if k_pairs > 0:
            for c, (valid, lo, hi, sign, score) in enumerate(_hidden_pairs(u, L)):
                _, idx = jax.lax.top_k(-jnp.where(valid, score, jnp.inf), k_pairs)
                extrema.append((jnp.full(k_pairs, i), jnp.full(k_pairs, c), valid[idx],
                                lo[idx], hi[idx], sign[idx]))

    def f_at(p, v, i, c):
        f, df = _criteria(*(x[i] for x in _jet(L_fn, p, v)))
        return f[c], df[c], f[jnp.where(c >= 3, c - 3, c)]

    loop_i, crit, valid, u0, lo, hi, sign_lo = (jnp.concatenate(x) for x in zip(*lanes))
    ok = ok_cross = lo < hi  # the ends of the grid (modulus margin) are not refined
    n_cross = loop_i.shape[0]
    cat = lambda *x: jnp.concatenate(x)
    if extrema:
        # The extrema of the equations f (criterion + 3: their derivatives change sign from
        # −sign(f) to sign(f)) are refined beside the crossings, in a first round of steps;
        # then, in the same slots, the pairs of crossings on either side of those that lie
        # across zero, in [lo, v_e] and [v_e, hi].
        e_loop, e_crit, e_valid, e_lo, e_hi, e_sign = (cat(*x) for x in zip(*extrema))
        n_ext = e_loop.shape[0]
        pad = max(0, 3 * n_ext - n_cross)  # the second round takes 4 n_ext slots
        z = jnp.zeros(pad)
        slots = (cat(loop_i, e_loop, z.astype(loop_i.dtype)), cat(crit, e_crit + 3,
                 z.astype(crit.dtype)), cat(sign_lo, -e_sign, z))
        u0, lo, hi = cat(u0, 0.5 * (e_lo + e_hi), z), cat(lo, e_lo, z), cat(hi, e_hi, z)
        ok = cat(ok, e_valid, z > 0)
    else:
        n_ext = 0
        slots = (loop_i, crit, sign_lo)
    n_slots = slots[0].shape[0]

    # A fixed number of steps (the grid start is O(Δu²) close, so a few quadratic steps reach
    # round-off), in a loop so that the jets of L are compiled once.
    def newton(k, state):
        (v, a, b, df, ok, fc, (loop_s, crit_s, sign_s)), first = state
        if n_ext:
            # at the start of the second round: the first round's crossings are kept, and the
            # slots take the pairs, from the refined extrema v_e with the crossing equation f
            # and f'' there (the first round's last pass); each crossing of a pair starts where
            # the parabola of f through v_e crosses zero.  With them, from the same starts,
            # the least |1 + L| on either side of each extremum (a resonance between grid
            # points can pass −1 closer than any grid point).
            ext = slice(n_cross, n_cross + n_ext)
            v_e, sign, f_e, f2 = v[ext], e_sign, fc[ext], df[ext]
            hidden = ok[ext] & (jnp.sign(f_e) == -sign) & (v_e > e_lo) & (v_e < e_hi)
            d = jnp.sqrt(jnp.abs(2.0 * f_e / jnp.where(f2 != 0, f2, 1.0)))
            zp = jnp.zeros(n_slots - 4 * n_ext)
            two = lambda x, y: cat(x, y, x, y)  # noqa: E731
            pa, pb = cat(two(e_lo, v_e), zp), cat(two(v_e, e_hi), zp)
            guess = jnp.clip(two(v_e - d, v_e + d), pa[:4 * n_ext], pb[:4 * n_ext])
            minus = -jnp.ones_like(sign)
            pairs = (cat(guess, zp), pa, pb, df, cat(hidden, hidden, ok[ext], ok[ext], zp > 0),
                     fc, (cat(e_loop, e_loop, e_loop, e_loop, zp.astype(e_loop.dtype)),
                          cat(e_crit, e_crit, jnp.full_like(e_crit, 2), jnp.full_like(e_crit, 2),
                              zp.astype(e_crit.dtype)),
                          cat(sign, -sign, minus, minus, zp)))
            now = (v, a, b, df, ok, fc, (loop_s, crit_s, sign_s))
            switch = k == _NEWTON_STEPS + 1
            first = jax.tree_util.tree_map(lambda x, y: jnp.where(switch, y, x), first,
                                           (v[:n_cross], df[:n_cross]))
            v, a, b, df, ok, fc, (loop_s, crit_s, sign_s) = jax.tree_util.tree_map(
                lambda x, y: jnp.where(switch, y, x), now, pairs)
        fv, dfv, fc = jax.vmap(lambda v, i, c: f_at(frozen, v, i, c))(v, loop_s, crit_s)
        left = jnp.sign(fv) == sign_s  # the root lies in [v, b]
        a, b = jnp.where(left, v, a), jnp.where(left, b, v)
        step = v - fv / dfv
        # (a converged v is an end of its bracket, and its step rounds to v: kept)
        inside = (step >= a) & (step <= b) & jnp.isfinite(step)
        new = jnp.where((fv == 0) | ~ok, v, jnp.where(inside, step, 0.5 * (a + b)))
        # the last pass of a round only evaluates: f'(v) at the refined root, for the final step
        last = (k == _NEWTON_STEPS) | (k == 2 * _NEWTON_STEPS + 1)
        v = jnp.where(last, v, new)
        return (v, a, b, dfv, ok, fc, (loop_s, crit_s, sign_s)), first

    v0 = jnp.clip(u0, lo, hi)
    one = jnp.ones_like(v0)
    state = ((v0, lo, hi, one, ok, one, slots), (v0[:n_cross], one[:n_cross]))
    (v, _, _, df, ok_s, _, _), (v1, df1) = jax.lax.fori_loop(
        0, (2 if n_ext else 1) * (_NEWTON_STEPS + 1), newton, state)
    if n_ext:  # the first round's crossings, then the pairs and the minima beside them
        v, df = cat(v1, v[:4 * n_ext]), cat(df1, df[:4 * n_ext])
        loop_i = cat(loop_i, e_loop, e_loop, e_loop, e_loop)
        crit = cat(crit, e_crit, e_crit, jnp.full_like(e_crit, 2), jnp.full_like(e_crit, 2))
        valid, ok = cat(valid, ok_s[:4 * n_ext]), cat(ok_cross, ok_s[:4 * n_ext])
        # a minimum searched beside an extremum, in a bracket that need not hold one, counts
        # where it converged (else a first-order step from a slope could undershoot)
        settled = cat(jnp.zeros(n_cross + 2 * n_ext, bool), jnp.ones(2 * n_ext, bool))
    else:
        ok = ok_cross
        settled = jnp.zeros(n_cross, bool)
    v, df = jax.lax.stop_gradient(v), jax.lax.stop_gradient(df)

    def final(v, i, c, ok, df, settled):
        L, L1 = (x[i] for x in _jet1(L_fn, params, v))
        f = _equations(L, L1)
        dv = jnp.where(ok & (df != 0), -f[c] / jnp.where(df != 0, df, 1.0), 0.0)
        score, value = _values(L + L1 * _c(dv))
        # a phase crossover bisected onto the phase's wrap (L on the positive real axis, where
        # arg(−L) jumps from −π to π) is none
        real = jnp.where(c == 0, jnp.abs(f[0]) < 0.5, True)
        real &= ~settled | (jnp.abs(dv) <= 1e-9)
        return v + dv, jnp.where(real, score[c], jnp.inf), value[c]

    v, score, value = jax.vmap(final)(v, loop_i, crit, ok, df, settled)
    valid &= score < jnp.inf
    out = []
    for i in range(len(Ls)):
        per = []
        for c in range(3):
            j, found = _pick(valid & (loop_i == i) & (crit == c), score)
            per.append((found, v[j], value[j]))
        out.append(_finish(*per))
    return out
