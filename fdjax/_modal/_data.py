"""The FRF data an identification fits: the checks of :func:`fdjax.identify_modes`,
:func:`fdjax.identify_modes_batched` and :func:`fdjax.stabilisation_diagram` on their inputs,
and the scaling both the order selection and the fit start from."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._checks import (
    finite,
    frequency_grid,
    is_concrete,
    numeric,
    positive,
    static_int,
    to_complex,
)
from ._fit import _TWO_PI, ModalFit


@eqx.filter_jit
def _prepare(freq_hz, frf, weights):
    """Scaled data: s̃ = iω/ω_ref, channels at unit RMS, weights at unit weighted RMS."""
    n_freq = freq_hz.shape[0]
    omega = _TWO_PI * freq_hz
    omega_ref = omega[-1]
    s = to_complex(omega / omega_ref) * 1j
    h = frf.reshape(n_freq, -1).astype(jnp.complex128)
    if weights is None:
        w = 1.0 / jnp.maximum(jnp.abs(h), 1e-300)
    else:
        w = jnp.broadcast_to(weights.reshape(n_freq, -1), h.shape)
    # Neither normalisation changes the minimiser: coefficients become of order one and
    # the solver's tolerances relative.
    h_scale = jnp.sqrt(jnp.mean(jnp.abs(h) ** 2, axis=0))
    h = h / to_complex(h_scale)
    w = w * h_scale
    w = w / jnp.sqrt(jnp.mean((w * jnp.abs(h)) ** 2))
    return s, h, w, h_scale, omega_ref

def _check_inputs(where, n_batch, freq_hz, frf, n_modes, rigid_body, upper_residual, weights,
                  initial, vf_iterations, vf_extra_modes, max_steps, real_poles=0):
    """Shared validation of identify_modes(_batched); ``n_batch`` leading position axes."""
    freq_hz = frequency_grid(freq_hz, f"{where}(freq_hz=...)")
    n_freq = freq_hz.shape[0]
    frf = numeric(frf, f"{where}(frf=...)")
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
    frf = finite(frf, f"{where}(frf=...)")
    # a channel that is zero at every frequency has nothing to fit (and no scale)
    if is_concrete(frf):
        flat = np.abs(np.asarray(frf)).reshape(frf.shape[:n_batch + 1] + (-1,))
        dead = np.all(flat == 0, axis=n_batch)
        if np.any(dead):
            idx = tuple(int(i) for i in np.argwhere(dead)[0])
            at = f"(position, channel) {idx}" if n_batch else f"channel {idx[0]}"
            raise ValueError(f"`{where}(frf=...)` must not have a channel that is zero at every "
                             f"frequency, got one at {at} (flattened output × input index)")
    else:  # traced (jit, vmap): the same check, in the program
        flat = jnp.abs(frf).reshape(frf.shape[:n_batch + 1] + (-1,))
        frf = eqx.error_if(frf, jnp.any(jnp.all(flat == 0, axis=n_batch)),
                           f"`{where}(frf=...)` must not have a channel that is zero at every "
                           "frequency")
    if frf.size == 0:
        raise ValueError(f"`{where}(frf=...)` must have at least one channel, got shape "
                         f"{frf.shape}")
    if weights is None:  # the default weights 1/|H| need every sample away from zero
        message = (f"`{where}(frf=...)` must not be exactly zero at any frequency when "
                   f"`{where}(weights=...)` is None (the default weights are 1/|H|); give "
                   f"weights")
        if is_concrete(frf):
            zero = np.argwhere(np.asarray(frf) == 0)
            if zero.size:
                raise ValueError(f"{message}, got 0 at index {tuple(int(i) for i in zero[0])}")
        else:
            frf = eqx.error_if(frf, jnp.any(frf == 0), message)
    rigid_body = static_int(rigid_body, f"{where}(rigid_body=...)", 0, 2)
    if not isinstance(upper_residual, bool):
        raise TypeError(f"`{where}(upper_residual=...)` must be a bool, got {upper_residual!r}")
    real_poles = static_int(real_poles, f"{where}(real_poles=...)", 0)
    n_fixed = rigid_body + int(upper_residual) + real_poles
    vf_iterations = static_int(vf_iterations, f"{where}(vf_iterations=...)", 0)
    vf_extra_modes = static_int(vf_extra_modes, f"{where}(vf_extra_modes=...)", 0)
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
    n_modes = static_int(n_modes, f"{where}(n_modes=...)", 1, max_modes)
    max_steps = static_int(max_steps, f"{where}(max_steps=...)", 1)
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
        weights = positive(weights, f"{where}(weights=...)")
    if initial is not None:
        expected = (*frf.shape[:n_batch], n_modes)
        if not isinstance(initial, ModalFit):
            raise ValueError(f"`{where}(initial=...)` must be a ModalFit, got {type(initial)}")
        if initial.poles.shape != expected:
            raise ValueError(
                f"`{where}(initial=...)` must hold poles of shape {expected} (n_modes = "
                f"{n_modes}), got poles of shape {initial.poles.shape}"
            )
        expected = (*frf.shape[:n_batch], real_poles)
        got = (*frf.shape[:n_batch], 0) if initial.real_poles is None else initial.real_poles.shape
        if got != expected:
            raise ValueError(
                f"`{where}(initial=...)` must hold real poles of shape {expected} (real_poles "
                f"= {real_poles}), got real poles of shape {got}"
            )
    static = (rigid_body, upper_residual, vf_iterations, vf_extra_modes, max_steps, real_poles)
    return freq_hz, frf, weights, n_modes, static
