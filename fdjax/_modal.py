r"""Modal identification from frequency response functions (paper Sec. 3.2, Table 1).

The paper reads natural frequency, damping ratio and *resonant phase* of each mode of the
drive's FRF h21 (Table 1) and follows them over the table position (Fig. 12). Here that is
a multi-mode rational fit of the whole band, never a peak pick: the first three modes of
Table 1 (49/95/130 Hz, ζ = 0.09–0.17) overlap so much that the phase at a magnitude peak
is not the phase of any one mode.

**Model.** With :math:`s = i\omega`, every channel :math:`k` of the FRF is fitted by

.. math::

    H_k(s) = \sum_{r=1}^{n} \Big(\frac{R_{rk}}{s-\lambda_r}
             + \frac{R_{rk}^*}{s-\lambda_r^*}\Big)
             + \frac{c_{0k}}{s^2} + \frac{c_{1k}}{s} + d_k ,

poles :math:`\lambda_r = -\zeta_r\omega_r + i\omega_r\sqrt{1-\zeta_r^2}` shared by all
channels, complex residues (complex modes allowed), a rigid-body double pole at
:math:`s = 0` (a ball-screw receptance falls as :math:`1/\omega^2`) and a real upper
residual :math:`d_k` for the modes above the band.

**Method, in two stages.**

1. *Vector fitting* (Gustavsen & Semlyen 1999, IEEE Trans. Power Delivery 14(3); relaxed
   form, Gustavsen 2006, ibid. 21(3)) gives the start without any peak picking. From
   ``n + vf_extra_modes`` lightly damped pole pairs spread logarithmically over the band,
   each iteration solves one *linear* least-squares problem
   :math:`\sigma(s)H_k(s) \approx N_k(s)` for all channels with a shared
   :math:`\sigma(s) = \tilde d + \sum_j \tilde c_j/(s-a_j)` (constrained by
   :math:`\mathrm{Re}\sum_i\sigma(s_i) = N`), and moves the poles to the zeros of
   :math:`\sigma`, the eigenvalues of :math:`\mathrm{diag}(a) - \mathbf 1\tilde c^T/\tilde d`.
   The poles at :math:`s = 0` enter only the numerator, so they stay there. The spare
   pairs then absorb noise and out-of-band dynamics (with exactly ``n`` pairs a pole can
   lock onto noise and leave a mode unfitted); backward elimination keeps the ``n`` pairs
   whose removal would raise the residual most, and a few relocations of those alone
   settle the rest. Robust over a wide band with overlapping, heavily damped modes beside
   lightly damped ones, where peak picking and circle fitting fail; fixed iteration
   counts, so it jits and vmaps.
2. *Variable-projection Levenberg–Marquardt refinement* (Golub & Pereyra 1973) of the
   weighted complex residual :math:`w\,(H_\text{fit}-H)`, real and imaginary parts, with
   ``optimistix.least_squares``. The residues, rigid-body and residual terms enter
   linearly, so for given poles they are the exact linear least-squares solution (one
   m×m Cholesky per channel); only the :math:`2n` pole parameters are iterated, with the
   Jacobian in closed form. The minimiser is that of the joint pole-and-residue problem
   (vector fitting's is not: it minimises a linearised, σ-weighted residual), but the
   iteration is small and needs no scaling of residues. Each pole is parametrised as
   :math:`\lambda = -\sigma_0 e^{v} + i\omega_{d0} e^{\zeta_0 u}` about its start (a unit
   of u is one relative half-power bandwidth), and the parameters are scaled by the
   start Jacobian's column norms (Marquardt scaling, as in MINPACK), so lightly
   (ζ = 0.003) and heavily (ζ = 0.17) damped modes are equally well conditioned. From the
   vector-fitting start it converges in about six Gauss–Newton-like steps.

The default weight :math:`w = 1/|H|` makes every point count by its *relative* error, the
maximum-likelihood weight for noise proportional to the response (as in measured and in
FBS-predicted FRFs); the magnitudes of ~1e-9 m/N and the 1/ω² fall of the rigid body then
do not matter, and each channel is normalised internally. Gradients of the identified
quantities with respect to the data pass through the refinement by the implicit function
theorem (``optimistix.ImplicitAdjoint``); the vector-fitting start carries no gradient,
which is exact because the minimiser does not depend on where the iteration starts.

**Resonant phase** (DESIGN.md §2, Table 1). For the term of mode :math:`r`,
:math:`T_r(\omega) = R_r/(i\omega-\lambda_r) + R_r^*/(i\omega-\lambda_r^*)
= (2\,\mathrm{Re}R_r\,i\omega - 2\,\mathrm{Re}(R_r\lambda_r^*)) /
(\omega_r^2-\omega^2+2i\zeta_r\omega_r\omega)`, the resonant phase is
:math:`\arg T_r(\omega_r)`, wrapped to :math:`(-360°, 0°]`. For a term written as
:math:`A_r e^{i\alpha_r}/(\omega_r^2-\omega^2+2i\zeta_r\omega_r\omega)` this is
:math:`\alpha_r - 90°`.

``identify_modes_batched`` runs the identification over a sweep of table positions in one
jitted program, and ``track_modes`` re-orders the modes of such a batch so that each index
follows one physical mode, by frequency proximity and mode-shape correlation (MAC).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import lineax as lx
import numpy as np
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Complex, Float, Int

from ._checks import check, frequency_grid, is_concrete

_TWO_PI = 2.0 * math.pi
# Poles whose imaginary part is below this fraction of their modulus are treated as real.
_REAL_POLE_TOL = 1e-6
# Smallest damping ratio a relocated pole may have (keeps the log-parametrisation finite).
_MIN_ZETA = 1e-7
# Vector-fitting relocations with the selected n_modes poles, after the over-sized stage.
_VF_FINAL_ITERATIONS = 5


def _complex(x: Array) -> Array:
    return jnp.asarray(x).astype(jnp.complex128)


def _cplx(re: Array, im: Array) -> Array:
    return jax.lax.complex(jnp.asarray(re, jnp.float64), jnp.asarray(im, jnp.float64))


def _wrap_phase_deg(z: Array) -> Array:
    """Phase of ``z`` in degrees, wrapped to (-360, 0]."""
    phase = jnp.degrees(jnp.angle(z))
    return jnp.where(phase > 0, phase - 360.0, phase)


class ModalFit(eqx.Module):
    r"""Modes identified from an FRF by :func:`identify_modes` (paper Sec. 3.2, Table 1).

    The fitted model, for every channel :math:`k` (output/input pair) and :math:`s=i\omega`,

    .. math::

        H_k(s) = \sum_{r} \Big(\frac{R_{rk}}{s-\lambda_r} + \frac{R_{rk}^*}{s-\lambda_r^*}\Big)
                 + \frac{c_{0k}}{s^2} + \frac{c_{1k}}{s} + d_k .

    Modes are sorted by natural frequency. Arrays carry extra leading axes when the fit was
    ``jax.vmap``-ed over positions; use ``jax.vmap(lambda m: m.frf(f))(fits)`` then.

    **Fields:**

    - ``frequency_hz``: natural frequencies :math:`|\lambda_r|/2\pi`, shape ``(n_modes,)``.
    - ``damping``: damping ratios :math:`\zeta_r = -\mathrm{Re}\lambda_r/|\lambda_r|`.
    - ``phase_deg``: resonant phase :math:`\arg T_r(\omega_r)` in degrees, in (-360, 0],
      per channel: shape ``(n_modes, *channel_shape)`` (``(n_modes,)`` for a SISO FRF).
    - ``residues``: complex residues :math:`R_{rk}` (units of H times rad/s), shape
      ``(n_modes, *channel_shape)``.
    - ``poles``: :math:`\lambda_r` in rad/s, upper half plane, shape ``(n_modes,)``.
    - ``rigid_body``: :math:`(c_{0k}, c_{1k})`, the coefficients of :math:`1/s^2` and
      :math:`1/s`, shape ``(2, *channel_shape)`` (zero where not fitted).
    - ``upper_residual``: :math:`d_k`, shape ``channel_shape`` (zero where not fitted).
    - ``fit_error``: normalised RMS complex residual per channel,
      :math:`\sqrt{\sum_f |w(H_\text{fit}-H)|^2 / \sum_f |wH|^2}` (with the default
      :math:`w = 1/|H|`, the RMS relative error), shape ``channel_shape``.
    - ``fit_error_total``: the same over all channels, a scalar.
    - ``num_steps``: Levenberg–Marquardt steps taken (0 without refinement).
    - ``result``: the ``optimistix.RESULTS`` code of the refinement.
    """

    frequency_hz: Float[Array, "*batch mode"]
    damping: Float[Array, "*batch mode"]
    phase_deg: Float[Array, "*batch mode *channel"]
    residues: Complex[Array, "*batch mode *channel"]
    poles: Complex[Array, "*batch mode"]
    rigid_body: Float[Array, "*batch 2 *channel"]
    upper_residual: Float[Array, "*batch *channel"]
    fit_error: Float[Array, "*batch *channel"]
    fit_error_total: Float[Array, "*batch"]
    num_steps: Int[Array, "*batch"]
    result: optx.RESULTS

    @property
    def n_modes(self) -> int:
        """Number of modes (the last axis of ``frequency_hz``)."""
        return self.frequency_hz.shape[-1]

    def mode_frf(self, freq_hz: Float[ArrayLike, " freq"]) -> Complex[Array, "freq mode *channel"]:
        r"""Each mode's own term :math:`R_r/(i\omega-\lambda_r) + R_r^*/(i\omega-\lambda_r^*)`
        at ``freq_hz`` (unbatched fits only)."""
        self._unbatched("mode_frf")
        freq_hz = frequency_grid(freq_hz, "ModalFit.mode_frf(freq_hz=...)")
        s = _complex(_TWO_PI * freq_hz) * 1j
        extra = (None,) * (self.residues.ndim - 1)
        s_ = s[(slice(None), None, *extra)]
        lam = self.poles[(None, slice(None), *extra)]
        res = self.residues[None]
        return res / (s_ - lam) + jnp.conj(res) / (s_ - jnp.conj(lam))

    def frf(self, freq_hz: Float[ArrayLike, " freq"]) -> Complex[Array, " freq *channel"]:
        r"""The fitted FRF :math:`H(i\,2\pi f)` at ``freq_hz``, shape ``(freq, *channel)``
        (unbatched fits only; ``jax.vmap`` over a batch)."""
        self._unbatched("frf")
        freq_hz = frequency_grid(freq_hz, "ModalFit.frf(freq_hz=...)")
        s = _complex(_TWO_PI * freq_hz) * 1j
        s_ = s[(slice(None), *((None,) * (self.residues.ndim - 1)))]
        modal = jnp.sum(self.mode_frf(freq_hz), axis=1)
        c0 = _complex(self.rigid_body[0])[None]
        c1 = _complex(self.rigid_body[1])[None]
        d = _complex(self.upper_residual)[None]
        return modal + c0 / s_**2 + c1 / s_ + d

    def _unbatched(self, name: str) -> None:
        if self.frequency_hz.ndim != 1:
            raise ValueError(
                f"`ModalFit.{name}(...)` needs an unbatched fit (frequency_hz of shape "
                f"(n_modes,)), got frequency_hz of shape {self.frequency_hz.shape}; use "
                f"`jax.vmap(lambda m: m.{name}(freq_hz))(fits)` for a batch"
            )


# --------------------------------------------------------------------------------------
# Rational basis and the linear (variable-projection) sub-problem.


def _basis(s: Array, poles: Array, rigid_body: int, upper_residual: bool):
    """Modal basis (N, 2n) and fixed basis (N, n_fixed), complex.

    For the pole pair (a, a*) the two real-coefficient columns are
    1/(s-a) + 1/(s-a*) and i/(s-a) - i/(s-a*): c1 φ1 + c2 φ2 = R/(s-a) + R*/(s-a*) with
    R = c1 + i c2.
    """
    inv = 1.0 / (s[:, None] - poles[None, :])
    invc = 1.0 / (s[:, None] - jnp.conj(poles)[None, :])
    modal = jnp.stack([inv + invc, 1j * (inv - invc)], axis=-1).reshape(s.shape[0], -1)
    fixed = [s**-2, s**-1][2 - rigid_body :]
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


def _lstsq_solve(a: Array, b: Array):
    """x minimising ||a x − b|| for real a (M, m) and b (M,); returns x, r = b − a x and
    ``ginv``, a function applying (aᵀa)⁻¹.

    Semi-normal equations with one step of iterative refinement on the column-scaled
    Gram matrix (a Cholesky of an m×m matrix): on these tall-skinny problems one BLAS-3
    product instead of a Householder QR, much faster on CPU, and accurate to ~κ(a)·eps
    after the refinement; the weighted modal bases here have κ of order 10–10³.
    """
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


@jax.custom_jvp
def _lstsq(a: Array, b: Array) -> tuple[Array, Array]:
    """:func:`_lstsq_solve` without the factor, with a cheap explicit derivative."""
    x, r, _ = _lstsq_solve(a, b)
    return x, r


@_lstsq.defjvp
def _lstsq_jvp(primals, tangents):
    # Differentiating the normal equations aᵀa x = aᵀb:
    #   aᵀa dx = daᵀ r + aᵀ(db − da x),   dr = db − da x − a dx.
    # Written out so that the tangents of a batch of directions (jacfwd) share one factor.
    a, b = primals
    da, db = tangents
    x, r, ginv = _lstsq_solve(a, b)
    e = db - da @ x
    dx = ginv(da.T @ r + a.T @ e)
    return (x, r), (dx, e - a @ dx)


def _linear_fit(poles, s, h, w, rigid_body, upper_residual):
    """For fixed poles, the weighted linear least-squares coefficients and residuals.

    Per channel k: min_x ||w_k (Φ x − h_k)|| over real x, Φ = [modal, fixed], real and
    imaginary parts stacked. Returns x of shape (m, C) and the weighted residuals (C, 2N).
    """
    modal, fixed = _basis(s, poles, rigid_body, upper_residual)
    phi = jnp.concatenate([modal, fixed], axis=1)

    def one(hk, wk):
        wk = _complex(wk)
        return _lstsq(_ri(wk[:, None] * phi), _ri(wk * hk))

    return jax.vmap(one, in_axes=(1, 1), out_axes=(1, 0))(h, w)


# --------------------------------------------------------------------------------------
# Stage 1: vector fitting.


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


def _vf_iteration(poles, s, h, w, rigid_body, upper_residual):
    n2 = 2 * poles.shape[0]
    n_freq = s.shape[0]
    modal, fixed = _basis(s, poles, rigid_body, upper_residual)
    m0 = modal.shape[1] + fixed.shape[1]
    # Relaxed σ(s) = Σ c̃ⱼ φⱼ(s) + d̃ (Gustavsen 2006, IEEE Trans. Power Delivery 21(3)).
    sig_basis = jnp.concatenate([modal, jnp.ones((n_freq, 1), jnp.complex128)], axis=1)
    # σ's columns are identical up to a unimodular factor across channels (|w h| ≈ 1), so
    # one column scaling shared by all channels keeps the stacked σ system balanced.
    sig_scale = jnp.sqrt(jnp.sum(jnp.abs(sig_basis) ** 2, axis=0))

    def one(hk, wk):
        wk = _complex(wk)
        num = jnp.concatenate([wk[:, None] * modal, wk[:, None] * fixed], axis=1)
        num = num / _complex(jnp.sqrt(jnp.sum(jnp.abs(num) ** 2, axis=0)))
        sig = -(wk * hk)[:, None] * sig_basis / _complex(sig_scale)
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
    rc = _cplx(c[0:n2:2], c[1:n2:2]) / _complex(d)
    a_all = jnp.concatenate([poles, jnp.conj(poles)])
    r_all = jnp.concatenate([rc, jnp.conj(rc)])
    ones = jnp.ones((n2, 1), jnp.complex128)
    zeros = jnp.linalg.eigvals(jnp.diag(a_all) - ones * r_all[None, :])
    return _upper_poles(zeros, poles.shape[0])


def _vector_fit(poles, s, h, w, iterations, rigid_body, upper_residual):
    def body(_, p):
        return _vf_iteration(p, s, h, w, rigid_body, upper_residual)

    return jax.lax.fori_loop(0, iterations, body, poles)


def _select_modes(poles, s, h, w, n_modes, rigid_body, upper_residual):
    """Keep ``n_modes`` of the over-sized vector fit's pole pairs, by backward elimination.

    Each round removes the pair whose removal increases the weighted least-squares residual
    least (pairs outside the band go first), refitting the residues of the others. Poles
    that fit noise, and one pole of a doublet that splits a mode between two poles, cost
    nothing to remove; a mode of the data does. Uses the Gram matrices of the linear
    problem, so each trial is an m×m solve with the removed columns masked out.
    """
    n_tot = poles.shape[0]
    modal, fixed = _basis(s, poles, rigid_body, upper_residual)
    phi = jnp.concatenate([modal, fixed], axis=1)
    m = phi.shape[1]

    def gram(hk, wk):
        wk = _complex(wk)
        a = wk[:, None] * phi
        b = wk * hk
        scale = jnp.sqrt(jnp.sum(jnp.abs(a) ** 2, axis=0))
        a = a / _complex(scale)
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
    return poles[jnp.argsort(~keep, stable=True)[:n_modes]]


# --------------------------------------------------------------------------------------
# Stage 2: variable-projection Levenberg–Marquardt.


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


def _varpro_plain(u, p0, s, h, w, rigid_body, upper_residual):
    poles = _poles_from_params(u, p0)
    _, res = _linear_fit(poles, s, h, w, rigid_body, upper_residual)
    return res


def _varpro_jacobian(u, p0, s, h, w, rigid_body, upper_residual):
    r"""Residual r (C, 2N) and its Jacobian ∂r/∂u (C, 2N, n, 2), in closed form.

    Variable projection (Golub & Pereyra 1973): with r = b − A x, x = A⁺b,

    .. math:: \partial_j r = -P^\perp (\partial_j A)\,x - A (A^T A)^{-1} (\partial_j A)^T r,

    and ∂ⱼA has only the two columns of the pole pair that θⱼ moves: for
    g = 1/(s−λ), gᶜ = 1/(s−λ*), (∂ⱼA)x = w(g² c R + gᶜ² c* R*) with c = ∂λ/∂θⱼ and
    R = x₁ + i x₂ the pair's residue; (∂ⱼA)ᵀr has the entries Re(c* α + c β) and
    Im(c* α − c β) with α = Σ w ḡ² r_c, β = Σ w ḡᶜ² r_c (r_c the complex residual).
    O(N·m·n) per channel instead of 2n passes of forward-mode differentiation.
    """
    n = u.shape[0]
    n_freq = s.shape[0]
    poles = _poles_from_params(u, p0)
    _, _, zeta0 = _pole_scales(p0)
    # ∂λ/∂u: u₀ scales Im λ by exp(ζ₀u₀), u₁ scales Re λ by exp(u₁).
    dlam = jnp.stack(
        [_cplx(jnp.zeros(n), zeta0 * jnp.imag(poles)), _cplx(jnp.real(poles), jnp.zeros(n))],
        axis=-1,
    )
    modal, fixed = _basis(s, poles, rigid_body, upper_residual)
    phi = jnp.concatenate([modal, fixed], axis=1)
    m = phi.shape[1]
    g2 = (1.0 / (s[:, None] - poles[None, :])) ** 2
    gc2 = (1.0 / (s[:, None] - jnp.conj(poles)[None, :])) ** 2
    eye = jnp.eye(n)

    def one(hk, wk):
        wc = _complex(wk)
        a = _ri(wc[:, None] * phi)
        x, r, ginv = _lstsq_solve(a, _ri(wc * hk))
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
        q = jnp.concatenate([q.reshape(2 * n, 2 * n), jnp.zeros((m - 2 * n, 2 * n))], axis=0)
        jac = -du + a @ ginv(a.T @ du - q)
        return r, jac.reshape(2 * n_freq, n, 2)

    return jax.vmap(one, in_axes=(1, 1))(h, w)


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
    res, jac = _varpro_jacobian(u, *data, rigid_body, upper_residual)
    dres = jnp.zeros_like(res)
    if not isinstance(du, SymbolicZero):
        dres = dres + jnp.einsum("cinj,nj->ci", jac, du)
    if not all(isinstance(t, SymbolicZero) for t in ddata):
        ddata = [
            jnp.zeros(t.shape, t.dtype) if isinstance(t, SymbolicZero) else t for t in ddata
        ]
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
    return _RESIDUAL_GAIN * _varpro_residual(v / d, rest)


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


# --------------------------------------------------------------------------------------
# The jitted core.


class _Model(eqx.Module):
    n_modes: int = eqx.field(static=True)
    rigid_body: int = eqx.field(static=True)
    upper_residual: bool = eqx.field(static=True)
    channel_shape: tuple[int, ...] = eqx.field(static=True)


# The work is split into three jitted stages so that calls that differ only in the start
# (vector fitting or ``initial=``) or in ``refine`` share compiled code; under a user's
# jit/vmap/grad they trace into one program as usual.


@eqx.filter_jit
def _prepare(freq_hz, frf, weights):
    """Scaled data: s̃ = iω/ω_ref, channels at unit RMS, weights at unit weighted RMS."""
    n_freq = freq_hz.shape[0]
    omega = _TWO_PI * freq_hz
    omega_ref = omega[-1]
    s = _complex(omega / omega_ref) * 1j
    h = frf.reshape(n_freq, -1).astype(jnp.complex128)
    if weights is None:
        w = 1.0 / jnp.maximum(jnp.abs(h), 1e-300)
    else:
        w = jnp.broadcast_to(weights.reshape(n_freq, -1), h.shape)
    # Neither normalisation changes the minimiser: coefficients become of order one and
    # the solver's tolerances relative.
    h_scale = jnp.sqrt(jnp.mean(jnp.abs(h) ** 2, axis=0))
    h = h / _complex(h_scale)
    w = w * h_scale
    w = w / jnp.sqrt(jnp.mean((w * jnp.abs(h)) ** 2))
    return s, h, w, h_scale, omega_ref


@eqx.filter_jit
def _start(s, h, w, model: _Model, iterations: int, extra: int):
    """Vector fitting with n_modes + extra pairs, backward elimination to n_modes, and a
    few relocations of the kept poles alone (which settle what the removed ones shared)."""
    rb, ur = model.rigid_body, model.upper_residual
    p0 = _starting_poles(jnp.imag(s), model.n_modes + extra)
    p0 = _vector_fit(p0, s, h, w, iterations, rb, ur)
    p0 = _select_modes(p0, s, h, w, model.n_modes, rb, ur)
    return _vector_fit(p0, s, h, w, _VF_FINAL_ITERATIONS, rb, ur)


@eqx.filter_jit
def _finish(s, h, w, h_scale, omega_ref, p0, solver, model: _Model, refine: bool,
            max_steps: int, throw: bool) -> ModalFit:
    """Refinement from the scaled start poles p0, then the modal quantities in SI units."""
    n = model.n_modes
    rb, ur = model.rigid_body, model.upper_residual
    p0 = jax.lax.stop_gradient(_upper_poles(p0, n))
    if refine:
        args = (p0, s, h, w, rb, ur)
        u0 = jnp.zeros((n, 2))
        # Marquardt scaling (as MINPACK's): parameters in units of the start Jacobian's column
        # norms, so that the damping μI of LM is isotropic; a fixed gain on the residual makes
        # μ = 1 (optimistix's first trust-region step) small against JᵀJ, so that the first
        # steps from the (already close) vector-fitting start are Gauss–Newton steps.
        _, jac0 = _varpro_jacobian(u0, p0, *jax.lax.stop_gradient((s, h, w)), rb, ur)
        d = jnp.sqrt(jnp.sum(jac0**2, axis=(0, 1)))
        d = jnp.maximum(d, 1e-12 * jnp.max(d))
        sol = optx.least_squares(
            _scaled_residual,
            solver,
            u0,
            (d, args),
            max_steps=max_steps,
            throw=throw,
        )
        poles = _poles_from_params(sol.value / d, p0)
        num_steps = sol.stats["num_steps"]
        result = sol.result
    else:
        poles = p0
        num_steps = jnp.array(0)
        result = optx.RESULTS.successful

    poles = poles[jnp.argsort(jnp.abs(poles))]
    x, res = _linear_fit(poles, s, h, w, rb, ur)
    nc = h.shape[1]
    # Undo the scalings: R̃/(s̃−λ̃) = ω_ref R̃/(s−λ), c̃₀/s̃² = ω_ref² c̃₀/s², c̃₁/s̃ = ω_ref c̃₁/s.
    residues = _cplx(x[0 : 2 * n : 2], x[1 : 2 * n : 2]) * _complex(h_scale * omega_ref)[None]
    fixed = x[2 * n :]
    rigid = jnp.zeros((2, nc))
    for k, j in enumerate(range(2 - rb, 2)):
        rigid = rigid.at[j].set(fixed[k] * h_scale * omega_ref ** (2 - j))
    upper = fixed[rb] * h_scale if ur else jnp.zeros(nc)
    poles = poles * _complex(omega_ref)

    wn = jnp.abs(poles)
    zeta = -jnp.real(poles) / wn
    s_n = _complex(wn) * 1j
    term = residues / (s_n - poles)[:, None] + jnp.conj(residues) / (s_n - jnp.conj(poles))[:, None]

    wh2 = jnp.sum((w * jnp.abs(h)) ** 2, axis=0)
    res2 = jnp.sum(res**2, axis=1)
    ch = model.channel_shape
    return ModalFit(
        frequency_hz=wn / _TWO_PI,
        damping=zeta,
        phase_deg=_wrap_phase_deg(term).reshape(n, *ch),
        residues=residues.reshape(n, *ch),
        poles=poles,
        rigid_body=rigid.reshape(2, *ch),
        upper_residual=upper.reshape(ch),
        fit_error=jnp.sqrt(res2 / wh2).reshape(ch),
        fit_error_total=jnp.sqrt(jnp.sum(res2) / jnp.sum(wh2)),
        num_steps=jnp.asarray(num_steps),
        result=result,
    )


def _static_int(value, where: str, lo: int, hi: int | None = None) -> int:
    ok = isinstance(value, int | np.integer) and not isinstance(value, bool)
    if ok:
        value = int(value)
        ok = value >= lo and (hi is None or value <= hi)
    if not ok:
        rng = f"between {lo} and {hi}" if hi is not None else f"at least {lo}"
        raise ValueError(f"`{where}` must be an integer {rng}, got {value!r}")
    return value


def identify_modes(
    freq_hz: Float[ArrayLike, " freq"],
    frf: Complex[ArrayLike, " freq *channel"],
    n_modes: int,
    *,
    rigid_body: int = 2,
    upper_residual: bool = True,
    weights: Float[ArrayLike, " freq *channel"] | None = None,
    initial: ModalFit | None = None,
    refine: bool = True,
    vf_iterations: int = 10,
    vf_extra_modes: int = 3,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
    throw: bool = True,
) -> ModalFit:
    r"""Identify natural frequencies, damping ratios and resonant phases from an FRF.

    Fits (paper Sec. 3.2; the modal data of Table 1)

    .. math::

        H_k(i\omega) \approx \sum_{r=1}^{n} \Big(\frac{R_{rk}}{i\omega-\lambda_r}
        + \frac{R_{rk}^*}{i\omega-\lambda_r^*}\Big) + \frac{c_{0k}}{(i\omega)^2}
        + \frac{c_{1k}}{i\omega} + d_k

    by minimising :math:`\sum_{f,k} |w_{fk}(H^\text{fit}_k - H_k)(f)|^2`: vector fitting for
    the start, then a variable-projection Levenberg–Marquardt refinement of the poles with
    the residues solved exactly (see the module docstring for the reasons). Returns the
    modes sorted by frequency with :math:`f_r = |\lambda_r|/2\pi`,
    :math:`\zeta_r = -\mathrm{Re}\lambda_r/|\lambda_r|` and the resonant phase
    :math:`\arg T_r(\omega_r)` of each mode's own term (DESIGN.md §2), in (-360°, 0°].

    Jit-able and vmap-able over positions (fixed sizes; ``n_modes`` and the options are
    static): ``jax.vmap(lambda h: identify_modes(freq_hz, h, 5))(frf_batch)``, or
    :func:`identify_modes_batched` (faster on CPU). Differentiable with respect to ``frf``
    (and ``weights``) through the refinement, by the implicit function theorem.
    Needs ``2·n_freq ≥ 4(n_modes + vf_extra_modes) + n_fixed + 2`` (n_fixed: rigid-body and
    residual terms).

    **Arguments:**

    - ``freq_hz``: frequency grid in Hz, positive and strictly increasing, shape ``(freq,)``.
    - ``frf``: complex FRF with frequency on the first axis, shape ``(freq,)``,
      ``(freq, n_out)`` or ``(freq, n_out, n_in)``; all channels share the poles.
    - ``n_modes``: number of complex-conjugate mode pairs in the band.
    - ``rigid_body``: number of poles at :math:`s=0`: 2 fits :math:`c_0/s^2 + c_1/s` (a
      free axis such as a ball-screw drive), 1 only :math:`c_1/s`, 0 none.
    - ``upper_residual``: fit the constant :math:`d_k` for modes above the band.
    - ``weights``: positive weights :math:`w`, broadcastable to ``frf``; default
      :math:`1/|H|` (relative error).
    - ``initial``: a previous ``ModalFit`` (e.g. the neighbouring position) whose poles start
      the refinement instead of vector fitting.
    - ``refine``: ``False`` returns the vector-fitting estimate (residues solved for its
      poles) without the nonlinear refinement.
    - ``vf_iterations``: number of vector-fitting pole relocations (with the spare pairs).
    - ``vf_extra_modes``: spare pole pairs of the vector-fitting stage (see the module
      docstring); 0 fits exactly ``n_modes`` pairs.
    - ``solver``: an ``optimistix`` least-squares solver, applied to the residual in
      Marquardt-scaled pole parameters (unit: one column norm of the start Jacobian). The
      default is Levenberg–Marquardt (``optx.AbstractGaussNewton`` with a damped Newton
      descent solved by Cholesky and a classical trust region that also accepts steps at the
      round-off of the loss), ``rtol = atol = 1e-8``: frequencies within ~1e-13 and damping
      ratios within ~1e-11 (relative) of the converged optimum, in ~6 steps from the
      vector-fitting start.
    - ``max_steps``, ``throw``: passed to ``optimistix.least_squares``; with
      ``throw=False`` a failed refinement is reported in ``ModalFit.result``.

    **Returns:** a :class:`ModalFit`.
    """
    freq_hz, frf, weights, n_modes, static = _check_inputs(
        "identify_modes", 0, freq_hz, frf, n_modes, rigid_body, upper_residual, weights,
        initial, vf_iterations, vf_extra_modes, max_steps,
    )
    rigid_body, upper_residual, vf_iterations, vf_extra_modes, max_steps = static
    if solver is None:
        solver = _DEFAULT_SOLVER
    model = _Model(
        n_modes=n_modes,
        rigid_body=rigid_body,
        upper_residual=upper_residual,
        channel_shape=tuple(frf.shape[1:]),
    )
    s, h, w, h_scale, omega_ref = _prepare(freq_hz, frf, weights)
    if initial is None:
        data = jax.lax.stop_gradient((s, h, w))
        p0 = _start(*data, model, vf_iterations, vf_extra_modes)
    else:
        p0 = jax.lax.stop_gradient(initial.poles.astype(jnp.complex128) / _complex(omega_ref))
    return _finish(s, h, w, h_scale, omega_ref, p0, solver, model, bool(refine), max_steps,
                   bool(throw))


def _check_inputs(where, n_batch, freq_hz, frf, n_modes, rigid_body, upper_residual, weights,
                  initial, vf_iterations, vf_extra_modes, max_steps):
    """Shared validation of identify_modes(_batched); ``n_batch`` leading position axes."""
    freq_hz = frequency_grid(freq_hz, f"{where}(freq_hz=...)")
    n_freq = freq_hz.shape[0]
    frf = jnp.asarray(frf)
    if not jnp.issubdtype(frf.dtype, jnp.complexfloating):
        raise ValueError(
            f"`{where}(frf=...)` must be a complex FRF (H, not |H|), got dtype {frf.dtype}"
        )
    lead = "(n_positions, " if n_batch else "("
    if frf.ndim - n_batch not in (1, 2, 3) or frf.shape[n_batch] != n_freq:
        raise ValueError(
            f"`{where}(frf=...)` must have shape {lead}n_freq), {lead}n_freq, n_out) or "
            f"{lead}n_freq, n_out, n_in) with n_freq = len(freq_hz) = {n_freq}, got shape "
            f"{frf.shape}"
        )
    frf = frf.astype(jnp.complex128)
    frf = check(frf, _isfinite, f"{where}(frf=...)", "finite (no NaN or inf)")
    rigid_body = _static_int(rigid_body, f"{where}(rigid_body=...)", 0, 2)
    if not isinstance(upper_residual, bool):
        raise ValueError(f"`{where}(upper_residual=...)` must be a bool, got {upper_residual!r}")
    n_fixed = rigid_body + int(upper_residual)
    vf_iterations = _static_int(vf_iterations, f"{where}(vf_iterations=...)", 0)
    vf_extra_modes = _static_int(vf_extra_modes, f"{where}(vf_extra_modes=...)", 0)
    # Vector fitting solves, per channel, 2·n_freq real equations for
    # 4(n_modes + vf_extra_modes) + n_fixed + 1 unknowns; it must be over-determined.
    max_modes = (2 * n_freq - n_fixed - 2) // 4 - vf_extra_modes
    if max_modes < 1:
        raise ValueError(
            f"`{where}(freq_hz=...)` has {n_freq} points, too few to fit one mode with "
            f"vf_extra_modes={vf_extra_modes}; expected at least "
            f"{(4 * (1 + vf_extra_modes) + n_fixed + 2 + 1) // 2} points"
        )
    if isinstance(n_modes, int | np.integer) and not isinstance(n_modes, bool):
        if n_modes > max_modes:
            raise ValueError(
                f"`{where}(n_modes=...)` must be at most {max_modes} for {n_freq} frequency "
                f"points (vf_extra_modes={vf_extra_modes}, {n_fixed} rigid/residual terms), "
                f"got {n_modes}"
            )
    n_modes = _static_int(n_modes, f"{where}(n_modes=...)", 1, max_modes)
    max_steps = _static_int(max_steps, f"{where}(max_steps=...)", 1)
    if weights is not None:
        weights = jnp.asarray(weights)
        if jnp.issubdtype(weights.dtype, jnp.complexfloating):
            raise ValueError(f"`{where}(weights=...)` must be real, got dtype {weights.dtype}")
        weights = weights.astype(jnp.float64)
        try:
            weights = jnp.broadcast_to(weights, frf.shape)
        except ValueError:
            raise ValueError(
                f"`{where}(weights=...)` must broadcast to frf's shape {frf.shape}, got "
                f"shape {weights.shape}"
            ) from None
        weights = check(
            weights, lambda v: _isfinite(v) & (v > 0), f"{where}(weights=...)",
            "finite and positive",
        )
    if initial is not None:
        expected = (*frf.shape[:n_batch], n_modes)
        if not isinstance(initial, ModalFit):
            raise ValueError(f"`{where}(initial=...)` must be a ModalFit, got {type(initial)}")
        if initial.poles.shape != expected:
            raise ValueError(
                f"`{where}(initial=...)` must hold poles of shape {expected} (n_modes = "
                f"{n_modes}), got poles of shape {initial.poles.shape}"
            )
    static = (rigid_body, upper_residual, vf_iterations, vf_extra_modes, max_steps)
    return freq_hz, frf, weights, n_modes, static


def identify_modes_batched(
    freq_hz: Float[ArrayLike, " freq"],
    frf: Complex[ArrayLike, "position freq *channel"],
    n_modes: int,
    *,
    batch_size: int = 1,
    rigid_body: int = 2,
    upper_residual: bool = True,
    weights: Float[ArrayLike, "position freq *channel"] | None = None,
    initial: ModalFit | None = None,
    refine: bool = True,
    vf_iterations: int = 10,
    vf_extra_modes: int = 3,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
    throw: bool = True,
) -> ModalFit:
    r""":func:`identify_modes` at every position of a sweep (paper Sec. 3.2, Figs. 10–12).

    ``frf`` carries a leading position axis, shape ``(n_positions, freq, *channel)``;
    ``weights`` broadcasts to it and ``initial`` is a batched :class:`ModalFit` (e.g. the
    previous sweep). Returns a :class:`ModalFit` whose arrays have a leading position axis,
    ready for :func:`track_modes`.

    One jitted program runs ``jax.lax.map`` over the positions, ``jax.vmap``-ing chunks of
    ``batch_size`` positions. On CPU ``batch_size=1`` (a loop inside the program) is the
    fastest: batched small linear algebra does not vectorise there, and a vmapped
    refinement iterates until its slowest position has converged. On a GPU use a large
    ``batch_size`` (``n_positions`` is the same as ``jax.vmap(identify_modes)``).
    The other arguments are those of :func:`identify_modes`.
    """
    freq_hz, frf, weights, n_modes, static = _check_inputs(
        "identify_modes_batched", 1, freq_hz, frf, n_modes, rigid_body, upper_residual,
        weights, initial, vf_iterations, vf_extra_modes, max_steps,
    )
    batch_size = _static_int(batch_size, "identify_modes_batched(batch_size=...)", 1)
    rigid_body, upper_residual, vf_iterations, vf_extra_modes, max_steps = static
    options = dict(
        rigid_body=rigid_body, upper_residual=upper_residual, refine=bool(refine),
        vf_iterations=vf_iterations, vf_extra_modes=vf_extra_modes,
        solver=_DEFAULT_SOLVER if solver is None else solver, max_steps=max_steps,
        throw=bool(throw),
    )
    return _map_positions(freq_hz, frf, weights, initial, n_modes, batch_size, options)


@eqx.filter_jit
def _map_positions(freq_hz, frf, weights, initial, n_modes, batch_size, options):
    def one(args):
        h, w, init = args
        return identify_modes(freq_hz, h, n_modes, weights=w, initial=init, **options)

    # batch_size=1 maps without vmap: a batched non-symmetric eig (the vector-fitting zeros)
    # has been seen to dead-lock on XLA:CPU (jax 0.10).
    if batch_size == 1:
        return jax.lax.map(one, (frf, weights, initial))
    return jax.lax.map(one, (frf, weights, initial), batch_size=batch_size)


def _isfinite(v):
    return np.isfinite(v) if isinstance(v, np.ndarray | np.generic) else jnp.isfinite(v)


# --------------------------------------------------------------------------------------
# Mode tracking over positions.


def _mac(a: Array, b: Array) -> Array:
    r"""Modal assurance criterion matrix :math:`|a_i^H b_j|^2/(|a_i|^2|b_j|^2)`, (n, n)."""
    num = jnp.abs(jnp.conj(a) @ b.T) ** 2
    den = jnp.sum(jnp.abs(a) ** 2, axis=1)[:, None] * jnp.sum(jnp.abs(b) ** 2, axis=1)[None, :]
    return num / jnp.maximum(den, jnp.finfo(jnp.float64).tiny)


def _assign(cost: Array) -> Array:
    """Assignment minimising the summed cost: ``perm[i]`` is the column for row ``i``.

    Exact (all permutations) for up to 7 modes, greedy on the smallest cost otherwise.
    """
    n = cost.shape[0]
    if n <= 7:
        perms = jnp.asarray(list(itertools.permutations(range(n))), dtype=jnp.int32)
        total = jnp.sum(cost[jnp.arange(n)[None, :], perms], axis=1)
        return perms[jnp.argmin(total)]

    def body(_, carry):
        c, perm = carry
        k = jnp.argmin(c)
        i, j = k // n, k % n
        c = c.at[i, :].set(jnp.inf).at[:, j].set(jnp.inf)
        return c, perm.at[i].set(j.astype(jnp.int32))

    _, perm = jax.lax.fori_loop(0, n, body, (cost, jnp.zeros(n, jnp.int32)))
    return perm


@eqx.filter_jit
def _track(freq, shapes, freq_tol, mac_tol, extrapolate: bool):
    def step(carry, x):
        f_prev, f_prev2, psi_prev, k = carry
        f_new, psi_new = x
        if extrapolate:
            f_pred = jnp.where(k >= 2, 2.0 * f_prev - f_prev2, f_prev)
            f_pred = jnp.where(f_pred > 0, f_pred, f_prev)
        else:
            f_pred = f_prev
        df = (f_new[None, :] - f_pred[:, None]) / (freq_tol * f_pred[:, None])
        dmac = (1.0 - _mac(psi_prev, psi_new)) / mac_tol
        perm = _assign(df**2 + dmac**2)
        f_t = f_new[perm]
        return (f_t, f_prev, psi_new[perm], k + 1), perm

    init = (freq[0], freq[0], shapes[0], jnp.array(1))
    _, perms = jax.lax.scan(step, init, (freq[1:], shapes[1:]))
    first = jnp.arange(freq.shape[1], dtype=jnp.int32)[None]
    return jnp.concatenate([first, perms.astype(jnp.int32)], axis=0)


def track_modes(
    fits: ModalFit,
    *,
    freq_tol: float = 0.05,
    mac_tol: float = 0.2,
    extrapolate: bool = True,
) -> ModalFit:
    r"""Re-order the modes of a position batch of fits so each index follows one mode.

    ``fits`` is a :class:`ModalFit` with a leading position axis (from
    :func:`identify_modes_batched` or ``jax.vmap`` of :func:`identify_modes`), positions in
    sweep order (paper Sec. 3.2, Figs. 11–12 follow
    modes over Y_table = 100–700 mm). Walking along the positions, the modes at position
    :math:`p+1` are paired with the tracked modes at :math:`p` by minimising, over all
    pairings, the summed cost

    .. math::

        C_{ij} = \Big(\frac{f_j^{(p+1)} - \hat f_i}{\mathrm{freq\_tol}\,\hat f_i}\Big)^2
               + \Big(\frac{1 - \mathrm{MAC}(R_i^{(p)}, R_j^{(p+1)})}{\mathrm{mac\_tol}}\Big)^2,
        \qquad \mathrm{MAC}(a, b) = \frac{|a^H b|^2}{|a|^2 |b|^2},

    where :math:`R` are the residue vectors over the channels (the mode shapes) and
    :math:`\hat f_i` is the frequency predicted by linear extrapolation from the two
    previous positions (``extrapolate=True``) or the previous frequency. So modes that cross
    in frequency keep their index when their shapes differ (several channels), and when
    their frequencies move smoothly (one channel, where MAC is always 1). The assignment is
    exact for up to 7 modes and greedy beyond.

    Returns the same ``ModalFit`` with ``frequency_hz``, ``damping``, ``phase_deg``,
    ``residues`` and ``poles`` permuted per position; other fields are unchanged.
    """
    if not isinstance(fits, ModalFit):
        raise ValueError(f"`track_modes(fits=...)` must be a ModalFit, got {type(fits)}")
    if fits.frequency_hz.ndim != 2:
        raise ValueError(
            "`track_modes(fits=...)` must be a batch over positions with frequency_hz of "
            f"shape (n_positions, n_modes), got shape {fits.frequency_hz.shape}"
        )
    for name, value in (("freq_tol", freq_tol), ("mac_tol", mac_tol)):
        if is_concrete(value) and not (np.isfinite(value) and value > 0):
            raise ValueError(f"`track_modes({name}=...)` must be finite and positive, got {value}")
    n_pos, n = fits.frequency_hz.shape
    shapes = fits.residues.reshape(n_pos, n, -1)
    perm = _track(fits.frequency_hz, shapes, freq_tol, mac_tol, bool(extrapolate))

    def take(x):
        idx = perm.reshape(perm.shape + (1,) * (x.ndim - 2))
        return jnp.take_along_axis(x, idx, axis=1)

    return eqx.tree_at(
        lambda m: (m.frequency_hz, m.damping, m.phase_deg, m.residues, m.poles),
        fits,
        tuple(take(x) for x in (fits.frequency_hz, fits.damping, fits.phase_deg,
                                 fits.residues, fits.poles)),
    )
