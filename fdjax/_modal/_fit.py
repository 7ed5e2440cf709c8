r"""The identified modal model, :class:`ModalFit` (paper Sec. 3.2, Table 1).

For every channel :math:`k` and :math:`s = i\omega`,

.. math::

    H_k(s) = \sum_{r} \Big(\frac{R_{rk}}{s-\lambda_r} + \frac{R_{rk}^*}{s-\lambda_r^*}\Big)
             + \frac{c_{0k}}{s^2} + \frac{c_{1k}}{s} + d_k ,

with natural frequency :math:`|\lambda_r|/2\pi`, damping ratio
:math:`-\mathrm{Re}\lambda_r/|\lambda_r|` and the resonant phase :math:`\arg T_r(\omega_r)`
of each mode's own term :math:`T_r(i\omega) = R_r/(i\omega-\lambda_r) +
\bar R_r/(i\omega-\bar\lambda_r)`, wrapped to :math:`(-360°, 0°]` (paper Table 1, Fig. 12).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike, Complex, Float, Int

from .._checks import frequency_grid, to_complex

_TWO_PI = 2.0 * math.pi


def _wrap_phase_deg(z: Array) -> Array:
    """Phase of ``z`` in degrees, wrapped to (-360, 0]."""
    phase = jnp.degrees(jnp.angle(z))
    return jnp.where(phase > 0, phase - 360.0, phase)


class ModalFit(eqx.Module):
    r"""Modes identified from an FRF by :func:`identify_modes` (paper Sec. 3.2, Table 1).

    The fitted model, for every channel :math:`k` (output/input pair) and :math:`s=i\omega`,

    .. math::

        H_k(s) = \sum_{r} \Big(\frac{R_{rk}}{s-\lambda_r} + \frac{R_{rk}^*}{s-\lambda_r^*}\Big)
                 + \sum_j \frac{Q_{jk}}{s-a_j} + \frac{c_{0k}}{s^2} + \frac{c_{1k}}{s} + d_k .

    Modes are sorted by natural frequency. Arrays carry extra leading axes when the fit was
    ``jax.vmap``-ed over positions; use ``jax.vmap(lambda m: m.frf(f))(fits)`` then.

    **Fields:**

    - ``frequency_hz``: natural frequencies :math:`|\lambda_r|/2\pi`, shape ``(n_modes,)``.
    - ``damping_ratio``: damping ratios :math:`\zeta_r = -\mathrm{Re}\lambda_r/|\lambda_r|`.
    - ``phase_deg``: resonant phase :math:`\arg T_r(\omega_r)` in degrees, in (-360, 0],
      per channel: shape ``(n_modes, *channel_shape)`` (``(n_modes,)`` for a SISO FRF).
    - ``residues``: complex residues :math:`R_{rk}` (units of H times rad/s), shape
      ``(n_modes, *channel_shape)``.
    - ``poles``: :math:`\lambda_r` in rad/s, upper half plane, shape ``(n_modes,)``.
    - ``real_poles``: real poles :math:`a_j < 0` in rad/s (the damped rigid body
      :math:`-c_\text{eq}/J_\text{eq}` of a drive on damped guideways; not modes), shape
      ``(n_real,)``, ``(0,)`` (or ``None``) when none were fitted.
    - ``real_residues``: their real residues :math:`Q_{jk}`, shape ``(n_real, *channel_shape)``.
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
    damping_ratio: Float[Array, "*batch mode"]
    phase_deg: Float[Array, "*batch mode *channel"]
    residues: Complex[Array, "*batch mode *channel"]
    poles: Complex[Array, "*batch mode"]
    rigid_body: Float[Array, "*batch 2 *channel"]
    upper_residual: Float[Array, "*batch *channel"]
    fit_error: Float[Array, "*batch *channel"]
    fit_error_total: Float[Array, "*batch"]
    num_steps: Int[Array, "*batch"]
    result: optx.RESULTS
    real_poles: Float[Array, "*batch real"] | None = None
    real_residues: Float[Array, "*batch real *channel"] | None = None

    @property
    def n_modes(self) -> int:
        """Number of modes (the last axis of ``frequency_hz``)."""
        return self.frequency_hz.shape[-1]

    def mode_frf(self, freq_hz: Float[ArrayLike, " freq"]) -> Complex[Array, "freq mode *channel"]:
        r"""Each mode's own term :math:`R_r/(i\omega-\lambda_r) + R_r^*/(i\omega-\lambda_r^*)`
        at ``freq_hz`` (unbatched fits only)."""
        self._unbatched("mode_frf")
        freq_hz = frequency_grid(freq_hz, "ModalFit.mode_frf(freq_hz=...)")
        s = to_complex(_TWO_PI * freq_hz) * 1j
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
        s = to_complex(_TWO_PI * freq_hz) * 1j
        s_ = s[(slice(None), *((None,) * (self.residues.ndim - 1)))]
        modal = jnp.sum(self.mode_frf(freq_hz), axis=1)
        c0 = to_complex(self.rigid_body[0])[None]
        c1 = to_complex(self.rigid_body[1])[None]
        d = to_complex(self.upper_residual)[None]
        out = modal + c0 / s_**2 + c1 / s_ + d
        if self.real_poles is None:
            return out
        for a, q in zip(self.real_poles, self.real_residues):
            out = out + to_complex(q)[None] / (s_ - to_complex(a))
        return out

    def _unbatched(self, name: str) -> None:
        if self.frequency_hz.ndim != 1:
            raise ValueError(
                f"`ModalFit.{name}(...)` needs an unbatched fit (frequency_hz of shape "
                f"(n_modes,)), got frequency_hz of shape {self.frequency_hz.shape}; use "
                f"`jax.vmap(lambda m: m.{name}(freq_hz))(fits)` for a batch"
            )
