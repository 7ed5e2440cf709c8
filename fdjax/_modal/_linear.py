r"""The rational basis of the modal model and its linear least-squares sub-problem.

For fixed poles :math:`\lambda_r` the model

.. math::

    H_k(s) = \sum_r \Big(\frac{R_{rk}}{s-\lambda_r} + \frac{R_{rk}^*}{s-\lambda_r^*}\Big)
             + \frac{c_{0k}}{s^2} + \frac{c_{1k}}{s} + d_k

is linear in the residues and in the rigid-body and residual terms: with the real basis
columns :math:`1/(s-a) + 1/(s-a^*)` and :math:`i/(s-a) - i/(s-a^*)` of each pole pair (the
pair's residue is :math:`R = x_1 + i x_2`) and :math:`s^{-2}, s^{-1}, 1`, every channel is
:math:`\min_x \lVert w_k(\Phi x - h_k)\rVert` over real :math:`x`, real and imaginary parts
stacked. Both stages of the identification solve it: vector fitting inside each relocation,
the variable-projection refinement as its inner problem (Golub & Pereyra 1973).

This file holds the basis, the Gram and SPD helpers, the semi-normal-equations solver with
its cheap derivative, and the per-channel fit for given poles.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array

from .._checks import to_complex


def _cplx(re: Array, im: Array) -> Array:
    return jax.lax.complex(jnp.asarray(re, jnp.float64), jnp.asarray(im, jnp.float64))


def _basis(s: Array, poles: Array, rigid_body: int, upper_residual: bool,
           real_poles: Array | None = None):
    """Modal basis (N, 2n) and fixed basis (N, n_fixed), complex.

    For the pole pair (a, a*) the two real-coefficient columns are
    1/(s-a) + 1/(s-a*) and i/(s-a) - i/(s-a*): c1 φ1 + c2 φ2 = R/(s-a) + R*/(s-a*) with
    R = c1 + i c2. The fixed basis is, in this order, ψ_a = 1/(s^b (s-a)) for each real
    pole a (``real_poles``; b = ``rigid_body``), s⁻², s⁻¹ (the last b of them) and 1.

    ψ_a spans with s⁻¹ … s⁻ᵇ the same space as 1/(s-a), since
    Q/(s-a) = Q Σ_{j<b} aʲ/s^{j+1} + Q aᵇ ψ_a, but is not nearly parallel to them: for a
    real pole far below the band (a damped rigid body, |a| ≪ ω), 1/(s-a) ≈ 1/s + a/s² and the
    normal equations would lose all the digits of the difference. :func:`_real_residues`
    maps the coefficients back.
    """
    inv = 1.0 / (s[:, None] - poles[None, :])
    invc = 1.0 / (s[:, None] - jnp.conj(poles)[None, :])
    modal = jnp.stack([inv + invc, 1j * (inv - invc)], axis=-1).reshape(s.shape[0], -1)
    fixed = []
    if real_poles is not None:
        psi = 1.0 / (s[:, None] - to_complex(real_poles)[None, :]) / s[:, None] ** rigid_body
        fixed += list(psi.T)
    fixed += [s**-2, s**-1][2 - rigid_body :]
    if upper_residual:
        fixed.append(jnp.ones_like(s))
    if fixed:
        fixed = jnp.stack(fixed, axis=1)
    else:
        fixed = jnp.zeros((s.shape[0], 0), jnp.complex128)
    return modal, fixed


def _ri(x: Array) -> Array:
    """Stack real and imaginary parts along the first axis."""
    return jnp.concatenate([jnp.real(x), jnp.imag(x)], axis=0)


# Ridge on the unit-diagonal Gram matrices (keeps a Cholesky defined if two basis columns
# nearly coincide); its bias is removed again by the refinement step of _lstsq_solve.
_RIDGE = 1e-13


def _gram(a: Array, b: Array) -> tuple[Array, Array]:
    """Re(aᴴa), Re(aᴴb): normal equations of the real unknowns of min ||a x − b||."""
    ar, br = _ri(a), _ri(b)
    return ar.T @ ar, ar.T @ br


def _spd_solve(g: Array, b: Array) -> Array:
    """g⁻¹ b for a symmetric positive definite g (batched over leading axes)."""
    chol = jnp.linalg.cholesky(g)
    y = jax.lax.linalg.triangular_solve(chol, b[..., None], left_side=True, lower=True)
    x = jax.lax.linalg.triangular_solve(
        chol, y, left_side=True, lower=True, transpose_a=True
    )
    return x[..., 0]


def _lstsq_solve_qr2(a: Array, b: Array):
    """:func:`_lstsq_solve` by Cholesky-QR2 (Yamamoto et al. 2015): the Cholesky factor of
    the Gram matrix of Q₁ = a R₁⁻¹ corrects R₁, so R = R₂R₁ is the R of a QR of ``a`` to
    ~κ(a)·eps for κ(a) up to ~1e8, where the semi-normal equations lose every digit beyond
    1/κ². Used for models with real poles: with a pole pair above the band (nearly a
    constant over it) beside the rigid-body and real-pole columns the weighted basis reaches
    κ ~ 1e7. Twice the work of :func:`_lstsq_solve`."""
    scale = jnp.sqrt(jnp.sum(a**2, axis=0))
    a_s = a / scale
    m = a.shape[1]
    l1 = jnp.linalg.cholesky(a_s.T @ a_s + _RIDGE * jnp.eye(m))
    q1t = jsl.solve_triangular(l1, a_s.T, lower=True)  # (a_s R₁⁻¹)ᵀ with R₁ = l1ᵀ
    l2 = jnp.linalg.cholesky(q1t @ q1t.T + 1e-15 * jnp.eye(m))

    def ginv_s(v):  # (a_sᵀa_s)⁻¹ v = R₁⁻¹ R₂⁻¹ R₂⁻ᵀ R₁⁻ᵀ v, R₂ = l2ᵀ
        y = jsl.solve_triangular(l1, v, lower=True)
        y = jsl.solve_triangular(l2, y, lower=True)
        y = jsl.solve_triangular(l2, y, lower=True, trans=1)
        return jsl.solve_triangular(l1, y, lower=True, trans=1)

    x = ginv_s(a_s.T @ b)
    r = b - a_s @ x
    x = x + ginv_s(a_s.T @ r)
    r = b - a_s @ x

    def ginv(v):
        v = v / (scale if v.ndim == 1 else scale[:, None])
        out = ginv_s(v)
        return out / (scale if v.ndim == 1 else scale[:, None])

    return x / scale, r, ginv


def _lstsq_solve(a: Array, b: Array, accurate: bool = False):
    """x minimising ||a x − b|| for real a (M, m) and b (M,); returns x, r = b − a x and
    ``ginv``, a function applying (aᵀa)⁻¹.

    Semi-normal equations with one step of iterative refinement on the column-scaled
    Gram matrix (a Cholesky of an m×m matrix): on these tall-skinny problems one BLAS-3
    product instead of a Householder QR, much faster on CPU, and accurate to ~κ(a)·eps
    after the refinement; the weighted modal bases here have κ of order 10–10³.
    ``accurate``: by :func:`_lstsq_solve_qr2` instead.
    """
    if accurate:
        return _lstsq_solve_qr2(a, b)
    scale = jnp.sqrt(jnp.sum(a**2, axis=0))
    a_s = a / scale
    chol = jsl.cho_factor(a_s.T @ a_s + _RIDGE * jnp.eye(a.shape[1]), lower=True)
    x = jsl.cho_solve(chol, a_s.T @ b)
    r = b - a_s @ x
    x = x + jsl.cho_solve(chol, a_s.T @ r)
    r = b - a_s @ x

    def ginv(v):
        v = v / (scale if v.ndim == 1 else scale[:, None])
        out = jsl.cho_solve(chol, v)
        return out / (scale if v.ndim == 1 else scale[:, None])

    return x / scale, r, ginv


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _lstsq(a: Array, b: Array, accurate: bool = False) -> tuple[Array, Array]:
    """:func:`_lstsq_solve` without the factor, with a cheap explicit derivative."""
    x, r, _ = _lstsq_solve(a, b, accurate)
    return x, r


@_lstsq.defjvp
def _lstsq_jvp(accurate, primals, tangents):
    # Differentiating the normal equations aᵀa x = aᵀb:
    #   aᵀa dx = daᵀ r + aᵀ(db − da x),   dr = db − da x − a dx.
    # Written out so that the tangents of a batch of directions (jacfwd) share one factor.
    a, b = primals
    da, db = tangents
    x, r, ginv = _lstsq_solve(a, b, accurate)
    e = db - da @ x
    dx = ginv(da.T @ r + a.T @ e)
    return (x, r), (dx, e - a @ dx)


def _real_residues(q, real_poles, rigid, rigid_body):
    """From the coefficients q of ψ_a (see :func:`_basis`) to the residues Q of 1/(s-a), and
    the s⁻¹ … s⁻ᵇ coefficients ``rigid`` (rows: the last ``rigid_body`` of s⁻², s⁻¹) of the
    same fit written with 1/(s-a): Q = q/aᵇ, and Q aʲ/s^{j+1} moves out of the s^{-(j+1)}
    coefficient."""
    a = real_poles[:, None]
    big_q = q / a**rigid_body
    rigid = list(rigid)
    for j in range(rigid_body):
        # rigid's rows are s^-rb … s^-1; s^-(j+1) is row rb − 1 − j
        rigid[rigid_body - 1 - j] = rigid[rigid_body - 1 - j] - jnp.sum(big_q * a**j, axis=0)
    return big_q, rigid


def _linear_fit(poles, s, h, w, rigid_body, upper_residual, real_poles=None):
    """For fixed poles, the weighted linear least-squares coefficients and residuals.

    Per channel k: min_x ||w_k (Φ x − h_k)|| over real x, Φ = [modal, fixed], real and
    imaginary parts stacked. Returns x of shape (m, C) and the weighted residuals (C, 2N).
    """
    modal, fixed = _basis(s, poles, rigid_body, upper_residual, real_poles)
    phi = jnp.concatenate([modal, fixed], axis=1)
    accurate = real_poles is not None and real_poles.shape[0] > 0

    def one(hk, wk):
        wk = to_complex(wk)
        return _lstsq(_ri(wk[:, None] * phi), _ri(wk * hk), accurate)

    return jax.vmap(one, in_axes=(1, 1), out_axes=(1, 0))(h, w)
