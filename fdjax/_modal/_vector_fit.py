r"""Stage 1 of the identification: vector fitting, a start without peak picking.

Vector fitting (Gustavsen & Semlyen 1999, IEEE Trans. Power Delivery 14(3); relaxed form,
Gustavsen 2006, ibid. 21(3)) starts from lightly damped pole pairs spread logarithmically
over the band. Each iteration solves one *linear* least-squares problem
:math:`\sigma(s)H_k(s) \approx N_k(s)` for all channels with a shared

.. math::

    \sigma(s) = \tilde d + \sum_j \frac{\tilde c_j}{s-a_j},
    \qquad \mathrm{Re}\sum_i\sigma(s_i) = N \ \text{(non-triviality)},

and moves the poles to the zeros of :math:`\sigma`, the eigenvalues of
:math:`\mathrm{diag}(a) - \mathbf 1\tilde c^T/\tilde d`. The poles at :math:`s = 0` enter only
the numerator, so they stay there. Spare pairs absorb noise and out-of-band dynamics; backward
elimination (``_select_modes``) then keeps the ``n_modes`` pairs whose removal would raise the
residual most. Fixed iteration counts, so it jits and vmaps.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array

from .._checks import to_complex
from ._linear import _RIDGE, _basis, _cplx, _gram, _spd_solve

# Poles whose imaginary part is below this fraction of their modulus are treated as real.
_REAL_POLE_TOL = 1e-6
# Smallest damping ratio a relocated pole may have (keeps the log-parametrisation finite).
_MIN_ZETA = 1e-7


def _starting_poles(omega: Array, n_modes: int) -> Array:
    """Lightly damped pairs spread logarithmically over the band (Gustavsen's start)."""
    lo = jnp.log(jnp.maximum(omega[0], omega[-1] * 1e-4))
    hi = jnp.log(omega[-1])
    frac = (jnp.arange(n_modes, dtype=jnp.float64) + 0.5) / n_modes
    beta = jnp.exp(lo + (hi - lo) * frac)
    return _cplx(-0.01 * beta, beta)


def _upper_poles(z: Array, n_modes: int) -> Array:
    """From the 2n relocated poles keep n stable ones in the upper half plane.

    Unstable poles are reflected into the left half plane. A real pole that would leave a
    pair incomplete is replaced by a lightly damped pair of the same modulus, which the
    next iterations relocate; this keeps array sizes fixed under ``jit``.
    """
    z = _cplx(-jnp.abs(jnp.real(z)), jnp.imag(z))
    z = z[jnp.argsort(-jnp.imag(z))][:n_modes]
    mod = jnp.abs(z)
    is_real = jnp.imag(z) <= _REAL_POLE_TOL * mod
    z = jnp.where(is_real, _cplx(-0.05 * mod, 0.99875 * mod), z)
    # Keep a minimum damping so the refinement's log-parametrisation stays finite.
    re = jnp.minimum(jnp.real(z), -_MIN_ZETA * jnp.abs(z))
    return _cplx(re, jnp.imag(z))


def _real_start(omega: Array, n_real: int) -> Array:
    """Real start poles at −ω_min·10^(−k/2): below the band, where a damped rigid body's
    pole −c_eq/J_eq lies (a ball screw on damped guideways, a few rad/s)."""
    k = jnp.arange(n_real, dtype=jnp.float64)
    return -omega[0] * 10.0 ** (-0.5 * k)


def _split_poles(z: Array, n_modes: int, n_real: int):
    """From the 2n + n_r relocated poles, n_r real ones (those nearest the real axis, made
    stable and real) and n pairs in the upper half plane (``_upper_poles``)."""
    if n_real == 0:
        return _upper_poles(z, n_modes), jnp.zeros((0,), jnp.float64)
    rel = jnp.abs(jnp.imag(z)) / jnp.maximum(jnp.abs(z), 1e-300)
    order = jnp.argsort(rel)
    zr = z[order[:n_real]]
    rp = -jnp.maximum(jnp.abs(jnp.real(zr)), 1e-8 * jnp.abs(z).max())
    return _upper_poles(z[order[n_real:]], n_modes), jnp.sort(rp)


def _vf_iteration(poles, s, h, w, rigid_body, upper_residual):
    poles, rpoles = poles
    n2 = 2 * poles.shape[0]
    n_r = rpoles.shape[0]
    n_freq = s.shape[0]
    modal, fixed = _basis(s, poles, rigid_body, upper_residual, rpoles)
    m0 = modal.shape[1] + fixed.shape[1]
    # Relaxed σ(s) = Σ c̃ⱼ φⱼ(s) + d̃ (Gustavsen 2006, IEEE Trans. Power Delivery 21(3)); the
    # real poles' columns 1/(s−a) belong to σ too.
    plain = 1.0 / (s[:, None] - to_complex(rpoles)[None, :])
    sig_basis = jnp.concatenate([modal, plain, jnp.ones((n_freq, 1), jnp.complex128)], axis=1)
    # σ's columns are identical up to a unimodular factor across channels (|w h| ≈ 1), so
    # one column scaling shared by all channels keeps the stacked σ system balanced.
    sig_scale = jnp.sqrt(jnp.sum(jnp.abs(sig_basis) ** 2, axis=0))

    def one(hk, wk):
        wk = to_complex(wk)
        num = jnp.concatenate([wk[:, None] * modal, wk[:, None] * fixed], axis=1)
        num = num / to_complex(jnp.sqrt(jnp.sum(jnp.abs(num) ** 2, axis=0)))
        sig = -(wk * hk)[:, None] * sig_basis / to_complex(sig_scale)
        # σ's block of the per-channel normal equations after eliminating the numerator
        # coefficients (the Schur complement; equal to R₂₂ᵀR₂₂ of the fast-VF QR).
        g_nn, g_ns = _gram(num, sig)
        g_ss, _ = _gram(sig, sig[:, 0])
        chol = jsl.cho_factor(g_nn + _RIDGE * jnp.eye(m0), lower=True)
        return g_ss - g_ns.T @ jsl.cho_solve(chol, g_ns)

    schur = jnp.sum(jax.vmap(one, in_axes=(1, 1))(h, w), axis=0)
    # Non-triviality: Re Σᵢ σ(sᵢ) = n_freq, weighted like one channel's equations.
    n_ch = h.shape[1]
    row_w = jnp.sqrt(jnp.sum((w * jnp.abs(h)) ** 2) / n_ch) / n_freq
    con = row_w * jnp.sum(jnp.real(sig_basis), axis=0) / sig_scale
    lhs = schur + con[:, None] * con[None, :]
    c = _spd_solve(lhs, con * (row_w * n_freq))
    c = c / sig_scale
    d = c[-1]
    d = jnp.where(jnp.abs(d) < 1e-8, jnp.where(d < 0, -1e-8, 1e-8), d)
    rc = _cplx(c[0:n2:2], c[1:n2:2]) / to_complex(d)
    # Zeros of σ = d̃(1 + Σ rⱼ/(s−aⱼ)): eigenvalues of diag(a) − 1rᵀ over all poles.
    a_all = jnp.concatenate([poles, jnp.conj(poles), to_complex(rpoles)])
    r_all = jnp.concatenate([rc, jnp.conj(rc), to_complex(c[n2 : n2 + n_r] / d)])
    ones = jnp.ones((n2 + n_r, 1), jnp.complex128)
    zeros = jnp.linalg.eigvals(jnp.diag(a_all) - ones * r_all[None, :])
    return _split_poles(zeros, poles.shape[0], n_r)


def _vector_fit(poles, s, h, w, iterations, rigid_body, upper_residual):
    """``iterations`` relocations of ``poles = (pairs, real_poles)``."""
    def body(_, p):
        return _vf_iteration(p, s, h, w, rigid_body, upper_residual)

    return jax.lax.fori_loop(0, iterations, body, poles)


def _select_modes(poles, s, h, w, n_modes, rigid_body, upper_residual):
    """Keep ``n_modes`` of the over-sized vector fit's pole pairs, by backward elimination.

    ``poles = (pairs, real_poles)``; the real poles are always kept. Each round removes the
    pair whose removal increases the weighted least-squares residual
    least (pairs outside the band go first), refitting the residues of the others. Poles
    that fit noise, and one pole of a doublet that splits a mode between two poles, cost
    nothing to remove; a mode of the data does. Uses the Gram matrices of the linear
    problem, so each trial is an m×m solve with the removed columns masked out.
    """
    poles, rpoles = poles
    n_tot = poles.shape[0]
    modal, fixed = _basis(s, poles, rigid_body, upper_residual, rpoles)
    phi = jnp.concatenate([modal, fixed], axis=1)
    m = phi.shape[1]

    def gram(hk, wk):
        wk = to_complex(wk)
        a = wk[:, None] * phi
        b = wk * hk
        scale = jnp.sqrt(jnp.sum(jnp.abs(a) ** 2, axis=0))
        a = a / to_complex(scale)
        g, ab = _gram(a, b)
        return g, ab, jnp.sum(jnp.abs(b) ** 2)

    g, ab, bb = jax.vmap(gram, in_axes=(1, 1))(h, w)
    wn = jnp.abs(poles)
    in_band = (wn >= jnp.imag(s[0])) & (wn <= jnp.imag(s[-1]))

    def residual(keep):
        col = jnp.concatenate([jnp.repeat(keep, 2), jnp.ones(m - 2 * n_tot, bool)])
        colf = col.astype(jnp.float64)
        gm = g * (colf[:, None] * colf[None, :]) + jnp.diag(1.0 - colf) + _RIDGE * jnp.eye(m)
        abm = ab * colf
        x = _spd_solve(gm, abm)
        return jnp.sum(bb - jnp.sum(abm * x, axis=-1))

    def remove_one(_, keep):
        trial = keep[None, :] & ~jnp.eye(n_tot, dtype=bool)
        cost = jax.vmap(residual)(trial)
        cost = jnp.where(in_band, cost, -jnp.inf)
        cost = jnp.where(keep, cost, jnp.inf)
        return keep.at[jnp.argmin(cost)].set(False)

    keep = jax.lax.fori_loop(0, n_tot - n_modes, remove_one, jnp.ones(n_tot, bool))
    return poles[jnp.argsort(~keep, stable=True)[:n_modes]], rpoles
