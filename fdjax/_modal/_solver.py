r"""Stage 2 of the identification: variable-projection Levenberg–Marquardt refinement.

The residues, rigid-body and residual terms enter linearly, so for given poles they are the
exact linear least-squares solution (``_linear``); only the :math:`2n` pole parameters are
iterated (variable projection, Golub & Pereyra 1973), on the weighted complex residual
:math:`w\,(H_\text{fit}-H)`, real and imaginary parts, with the Jacobian in closed form

.. math:: \partial_j r = -P^\perp (\partial_j A)\,x - A (A^T A)^{-1} (\partial_j A)^T r .

Each pole is parametrised about its start as
:math:`\lambda = -\sigma_0 e^{v} + i\omega_{d0} e^{\zeta_0 u}` (a unit of u is one relative
half-power bandwidth), and the parameters are scaled by the start Jacobian's column norms
(Marquardt scaling, as in MINPACK), so lightly and heavily damped modes are equally well
conditioned.

This file holds the parametrisation, the residual with its custom derivative, and the
default solver: ``optimistix``'s Gauss–Newton family with a damped Newton step solved by
Cholesky and a trust region that also accepts a step at the round-off of the loss.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array

from .._checks import to_complex
from ._linear import _basis, _cplx, _linear_fit, _lstsq_solve, _ri

# Gain on the Marquardt-scaled residual: JᵀJ has diagonal _RESIDUAL_GAIN² against the initial
# damping μ = 1.
_RESIDUAL_GAIN = 100.0


def _pole_scales(p0: Array):
    """Reference decay rate, damped frequency and relative bandwidth of each start pole."""
    sigma0 = -jnp.real(p0)
    wd0 = jnp.imag(p0)
    zeta0 = jnp.clip(sigma0 / jnp.abs(p0), 1e-3, 0.5)
    return sigma0, wd0, zeta0


def _poles_from_params(u: Array, p0: Array) -> Array:
    sigma0, wd0, zeta0 = _pole_scales(p0)
    return _cplx(-sigma0 * jnp.exp(u[:, 1]), wd0 * jnp.exp(zeta0 * u[:, 0]))


def _real_from_params(v: Array, r0: Array) -> Array:
    """Real poles a = a₀ e^v (negative like a₀): a unit of v is a relative change."""
    return r0 * jnp.exp(v)


def _varpro_plain(u, p0, s, h, w, rigid_body, upper_residual):
    (u, v), (p0, r0) = u, p0
    poles = _poles_from_params(u, p0)
    _, res = _linear_fit(poles, s, h, w, rigid_body, upper_residual,
                         _real_from_params(v, r0))
    return res


def _varpro_jacobian(u, p0, s, h, w, rigid_body, upper_residual):
    r"""Residual r (C, 2N) and its Jacobians ∂r/∂u (C, 2N, n, 2), ∂r/∂v (C, 2N, n_r), in
    closed form.

    ``u, p0 = (u_pairs, v_real), (pairs₀, real₀)``. Variable projection (Golub & Pereyra
    1973): with r = b − A x, x = A⁺b,

    .. math:: \partial_j r = -P^\perp (\partial_j A)\,x - A (A^T A)^{-1} (\partial_j A)^T r,

    and ∂ⱼA has only the two columns of the pole pair that θⱼ moves: for
    g = 1/(s−λ), gᶜ = 1/(s−λ*), (∂ⱼA)x = w(g² c R + gᶜ² c* R*) with c = ∂λ/∂θⱼ and
    R = x₁ + i x₂ the pair's residue; (∂ⱼA)ᵀr has the entries Re(c* α + c β) and
    Im(c* α − c β) with α = Σ w ḡ² r_c, β = Σ w ḡᶜ² r_c (r_c the complex residual).
    A real pole a (coefficient x_a of the column w ψ_a, ψ_a = 1/(s^b(s−a)), see
    ``_linear._basis``) has (∂A)x = w γ x_a and the single entry Re Σ w̄ γ̄ r_c of (∂A)ᵀr, with
    γ = a/(s^b (s−a)²) (∂a/∂v = a).
    O(N·m·n) per channel instead of 2n passes of forward-mode differentiation.
    """
    (u, v), (p0, r0) = u, p0
    n = u.shape[0]
    n_r = v.shape[0]
    n_freq = s.shape[0]
    poles = _poles_from_params(u, p0)
    rpoles = _real_from_params(v, r0)
    _, _, zeta0 = _pole_scales(p0)
    # ∂λ/∂u: u₀ scales Im λ by exp(ζ₀u₀), u₁ scales Re λ by exp(u₁).
    dlam = jnp.stack(
        [_cplx(jnp.zeros(n), zeta0 * jnp.imag(poles)), _cplx(jnp.real(poles), jnp.zeros(n))],
        axis=-1,
    )
    modal, fixed = _basis(s, poles, rigid_body, upper_residual, rpoles)
    phi = jnp.concatenate([modal, fixed], axis=1)
    m = phi.shape[1]
    g2 = (1.0 / (s[:, None] - poles[None, :])) ** 2
    gc2 = (1.0 / (s[:, None] - jnp.conj(poles)[None, :])) ** 2
    # ψ_a = 1/(s^b (s−a)): ∂ψ/∂v = a/(s^b (s−a)²)
    gr2 = ((1.0 / (s[:, None] - to_complex(rpoles)[None, :])) ** 2 * to_complex(rpoles)[None]
           / s[:, None] ** rigid_body)
    eye = jnp.eye(n)

    def one(hk, wk):
        wc = to_complex(wk)
        a = _ri(wc[:, None] * phi)
        x, r, ginv = _lstsq_solve(a, _ri(wc * hk), n_r > 0)
        res = _cplx(x[0 : 2 * n : 2], x[1 : 2 * n : 2])
        cr = dlam * res[:, None]
        du = wc[:, None, None] * (g2[:, :, None] * cr[None] + gc2[:, :, None] * jnp.conj(cr)[None])
        du = _ri(du.reshape(n_freq, 2 * n))
        rc = _cplx(r[:n_freq], r[n_freq:])
        alpha = jnp.sum((wc * rc)[:, None] * jnp.conj(g2), axis=0)
        beta = jnp.sum((wc * rc)[:, None] * jnp.conj(gc2), axis=0)
        q1 = jnp.real(jnp.conj(dlam) * alpha[:, None] + dlam * beta[:, None])
        q2 = jnp.imag(jnp.conj(dlam) * alpha[:, None] - dlam * beta[:, None])
        q = jnp.stack([eye[:, :, None] * q1[None], eye[:, :, None] * q2[None]], axis=1)
        q = q.reshape(2 * n, 2 * n)
        # real poles: columns 2n … 2n + n_r − 1 of A
        dur = _ri(wc[:, None] * gr2 * to_complex(x[2 * n : 2 * n + n_r])[None])
        qr = jnp.real(jnp.sum(jnp.conj(wc[:, None] * gr2) * rc[:, None], axis=0))
        du = jnp.concatenate([du, dur], axis=1)
        q = jnp.block([[q, jnp.zeros((2 * n, n_r))], [jnp.zeros((n_r, 2 * n)), jnp.diag(qr)],
                       [jnp.zeros((m - 2 * n - n_r, 2 * n + n_r))]])
        jac = -du + a @ ginv(a.T @ du - q)
        return r, jac[:, : 2 * n].reshape(2 * n_freq, n, 2), jac[:, 2 * n :]

    r, ju, jv = jax.vmap(one, in_axes=(1, 1))(h, w)
    return r, (ju, jv)


@functools.partial(jax.custom_jvp, nondiff_argnums=(5, 6))
def _varpro(u, p0, s, h, w, rigid_body, upper_residual):
    """Variable-projection residual r(u) (C, 2N): the weighted misfit left after the
    residues, rigid-body and residual terms are fitted by linear least squares."""
    return _varpro_plain(u, p0, s, h, w, rigid_body, upper_residual)


def _varpro_jvp(rigid_body, upper_residual, primals, tangents):
    # The pole-parameter direction by the closed-form Jacobian (so that linearising the
    # residual, as the solver does every step, costs one m×m factorisation and a matmul);
    # data directions (used by the implicit adjoint) by forward-mode differentiation.
    u, *data = primals
    du, *ddata = tangents
    res, (ju, jv) = _varpro_jacobian(u, *data, rigid_body, upper_residual)
    dres = jnp.zeros_like(res)
    du_c, dv = du
    if not isinstance(du_c, SymbolicZero):
        dres = dres + jnp.einsum("cinj,nj->ci", ju, du_c)
    if not isinstance(dv, SymbolicZero):
        dres = dres + jnp.einsum("cin,n->ci", jv, dv)
    ddata_leaves = jax.tree_util.tree_leaves(ddata, is_leaf=lambda t: isinstance(t, SymbolicZero))
    if not all(isinstance(t, SymbolicZero) for t in ddata_leaves):
        ddata = jax.tree_util.tree_map(
            lambda t: jnp.zeros(t.shape, t.dtype) if isinstance(t, SymbolicZero) else t, ddata,
            is_leaf=lambda t: isinstance(t, SymbolicZero),
        )
        _, dd = jax.jvp(
            lambda *d: _varpro_plain(u, *d, rigid_body, upper_residual), tuple(data),
            tuple(ddata),
        )
        dres = dres + dd
    return res, dres


_varpro.defjvp(_varpro_jvp, symbolic_zeros=True)


def _varpro_residual(u, args):
    p0, s, h, w, rigid_body, upper_residual = args
    return _varpro(u, p0, s, h, w, rigid_body, upper_residual)


def _scaled_residual(v, args):
    """The residual in Marquardt-scaled parameters v = u·d, times _RESIDUAL_GAIN."""
    d, rest = args
    u = jax.tree_util.tree_map(lambda a, b: a / b, v, d)
    return _RESIDUAL_GAIN * _varpro_residual(u, rest)


class _RoundOffTrustRegion(optx.AbstractSearch):
    """optimistix's classical trust region, plus: a step that changes the loss by no more
    than its round-off is accepted.

    On noisy data the loss near the optimum is dominated by the noise, and the decrease
    predicted for a converging Gauss–Newton step falls below the round-off of the loss
    (~1e-16 relative): the plain trust region then rejects every step, shrinking the step
    size, and never reaches its convergence test (which runs on accepted steps only).
    """

    inner: optx.ClassicalTrustRegion
    rtol: float = eqx.field(static=True, default=1e-12)

    def init(self, y, f_info_struct):
        return self.inner.init(y, f_info_struct)

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, state = self.inner.step(
            first_step, y, y_eval, f_info, f_eval_info, state
        )
        f0, f1 = f_info.as_min(), f_eval_info.as_min()
        flat = jnp.abs(f1 - f0) <= self.rtol * jnp.abs(f0)
        return step_size, accept | flat, result, state


def _quiet(**kwargs) -> None:
    del kwargs


class _LevenbergMarquardt(optx.AbstractGaussNewton):
    """``optx.LevenbergMarquardt`` with a Cholesky normal-equations step and the
    round-off-tolerant trust region above."""

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    descent: optx.DampedNewtonDescent = optx.DampedNewtonDescent(
        linear_solver=lx.Normal(lx.Cholesky())
    )
    search: _RoundOffTrustRegion = _RoundOffTrustRegion(optx.ClassicalTrustRegion())
    verbose: Callable = _quiet


# One instance, so that repeated calls hit the jit cache (the solver is a static argument).
# The damped step solves the normal equations (JᵀJ + μI) δ = −Jᵀr by Cholesky: J has only
# 2·n_modes columns and a condition number of order 10–100 in the scaled parameters, and this
# is about twice as fast as a QR of the (2·n_freq·n_channel)-row augmented Jacobian.
# Tolerances are on the scaled parameters v (unit ≈ one column norm of J, i.e. a change that
# moves the weighted residual by its own size).
_DEFAULT_SOLVER = _LevenbergMarquardt(rtol=1e-8, atol=1e-8)
