r"""Modes of the drive model: exact eigen-analysis of the time-domain twin.

The time-domain twin's finite-element matrices give the first-order system ``ż = A z + B u``
with ``A = [[0, I], [−M⁻¹K, −M⁻¹C]]``.  Its eigenvalues ``λ_r = −ζ_r ω_r ± iω_r √(1−ζ_r²)``
give natural frequency ``ω_r = |λ_r|`` and damping ratio ``ζ_r = −Re λ_r / |λ_r|``; with
right/left eigenvectors the residue of output ``o`` per input ``i`` is
``R_r = (S v_r)_o (w_rᵀ B)_i`` and the mode's own term is the conjugate pair

    h_r(ω) = R_r / (iω − λ_r) + R̄_r / (iω − λ̄_r).

Its **resonant phase** is ``arg h_r(ω_r)`` (paper Table 1, Fig. 12): for a term
``A e^{iα} / (ω_r² − ω² + 2iζω_rω)`` this is ``α − 90°``.  Phases are wrapped to (−360°, 0].
These are exact properties of the model (no curve fit), differentiable in every parameter.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from .. import _checks
from .._sweep import map_positions
from ._model import INPUTS, OUTPUTS, BallScrewDrive
from ._twin import TwinOptions, _assemble, _check_inputs, _check_time_domain, _twin_options

__all__ = ["DriveModes", "drive_modes", "track_drive_modes"]


class DriveModes(eqx.Module):
    """Modes of one FRF entry of the drive model, ascending in frequency.

    Attributes:
        frequency_hz: natural frequencies |λ_r|/2π (Hz).
        damping_ratio: damping ratios −Re λ_r/|λ_r|.
        phase_deg: resonant phase of the entry, arg h_r(ω_r) in (−360°, 0].
        amplitude: |h_r(ω_r)|, the mode's peak contribution (units of the FRF entry).
        prominence: |h_r(ω_r)| / |h(ω_r)|, the mode's share of the whole entry at its own
            natural frequency: how visible (identifiable) it is in a measured FRF.
        poles: λ_r (rad/s), upper half-plane.
        shapes: residues of all three outputs (θ1, x2, x3) for the chosen input, (n, 3):
            the mode shapes seen from that input, used to track modes over position.
    """

    frequency_hz: Float[Array, "*b n"]
    damping_ratio: Float[Array, "*b n"]
    phase_deg: Float[Array, "*b n"]
    amplitude: Float[Array, "*b n"]
    prominence: Float[Array, "*b n"]
    poles: Complex[Array, "*b n"]
    shapes: Complex[Array, "*b n 3"]


def _wrap_deg(phi, upper: float = 0.0):
    """Wrap degrees to (upper − 360°, upper]: (−360°, 0] for resonant phases, ``upper=180``
    for phase errors in (−180°, 180]."""
    return phi - 360.0 * jnp.ceil((phi - upper) / 360.0)


def _channel(name, names, fn, arg):
    if not isinstance(name, str) or name not in names:
        raise ValueError(f"`{fn}({arg}=...)` must be one of {names}, got {name!r}")
    return names.index(name)


def _modes_from_fe(fe, out: int, inp: int, n_keep: int, fn: str = "drive_modes") -> DriveModes:
    N = fe.mass.shape[0]
    Minv = jnp.linalg.inv(fe.mass)
    A = jnp.block([[jnp.zeros((N, N)), jnp.eye(N)], [-Minv @ fe.stiffness, -Minv @ fe.damping]])
    # a NaN parameter (traced, so not refused at the entry) is not "too many modes" below
    A = eqx.error_if(A, jnp.logical_not(jnp.all(jnp.isfinite(A))),
                     f"`{fn}(drive=...)` gives a non-finite model at this position; check the "
                     f"drive's parameters for NaN/inf")
    B = jnp.concatenate([jnp.zeros((N,)), Minv @ fe.inputs[:, inp]])
    C = jnp.concatenate([fe.outputs[out], jnp.zeros((N,))])
    # Residues need left eigenvectors: rows of V⁻¹.  They are invariant to the scaling of
    # each eigenvector, so the eigenvector-derivative gauge JAX asks us to accept is harmless.
    lam, V = jax.lax.linalg.eig(A, compute_left_eigenvectors=False, enable_eigvec_derivs=True)
    W = jnp.linalg.inv(V)
    # the lowest oscillatory poles in the upper half-plane (rigid-body and overdamped poles
    # are real and excluded)
    oscillatory = jnp.imag(lam) > 1e-6 * jnp.max(jnp.abs(lam))
    # fewer oscillatory poles than asked for (overdamped modes): the sort below would pick
    # real or lower-half-plane poles as modes
    lam = eqx.error_if(lam, jnp.sum(oscillatory) < n_keep,
                       f"`{fn}(n_modes=...)` asks for more modes than the drive has "
                       f"oscillatory poles at this position (some modes are overdamped): ask for "
                       f"fewer")
    keep = jnp.argsort(jnp.where(oscillatory, jnp.abs(lam), jnp.inf))[:n_keep]
    lam, V, W = lam[keep], V[:, keep], W[keep, :]
    Cc, Bc = C.astype(jnp.complex128), B.astype(jnp.complex128)
    wb = W @ Bc
    R = (V.T @ Cc) * wb
    # residues of every output (θ1, x2, x3) for this input: the mode's shape for tracking
    shapes = (V[:N].T @ fe.outputs.T.astype(jnp.complex128)) * wb[:, None]
    wr = jnp.abs(lam)
    s = 1j * wr.astype(jnp.complex128)
    term = R / (s - lam) + jnp.conj(R) / (s - jnp.conj(lam))
    # the whole FRF entry at each natural frequency, to judge how prominent the mode is
    D = (fe.stiffness.astype(jnp.complex128)[None]
         - (wr**2)[:, None, None].astype(jnp.complex128) * fe.mass.astype(jnp.complex128)[None]
         + s[:, None, None] * fe.damping.astype(jnp.complex128)[None])
    q = jnp.linalg.solve(D, jnp.broadcast_to(fe.inputs[:, inp].astype(jnp.complex128),
                                            (n_keep, N))[..., None])[..., 0]
    total = q @ fe.outputs[out].astype(jnp.complex128)
    idx = jnp.argsort(wr)
    return DriveModes(
        frequency_hz=(wr / (2 * jnp.pi))[idx],
        damping_ratio=(-jnp.real(lam) / wr)[idx],
        phase_deg=_wrap_deg(jnp.degrees(jnp.angle(term)))[idx],
        amplitude=jnp.abs(term)[idx],
        prominence=(jnp.abs(term) / jnp.abs(total))[idx],
        poles=lam[idx],
        shapes=shapes[idx],
    )


def drive_modes(
    drive: BallScrewDrive,
    position_m: Float[ArrayLike, ""] | Float[ArrayLike, " n"],
    *,
    output: str = "x2",
    input: str = "T1",
    n_modes: int = 12,
    twin: TwinOptions | None = None,
) -> DriveModes:
    """The lowest ``n_modes`` flexible modes of one FRF entry of the drive at a position.

    Exact eigen-analysis of the finite-element twin (see the module docstring; its mesh and
    nut correction from ``twin``, a :class:`fdjax.TwinOptions`, whose ``kept_modes`` and
    ``residual`` do not enter: every mode of the mesh is analysed); the default entry is
    h21 = x2/T1, the paper's Table 1 and Fig. 12.  Differentiable; a 1-D ``position_m`` runs
    one compiled loop over the positions (returned with a leading axis).

    Args:
        drive: the drive.
        position_m: the table position (m), or a 1-D array of them.
        output, input: the FRF entry whose modal constants (phase, residue) are reported: the
            output ``"theta1"``, ``"x2"`` or ``"x3"`` over the input ``"T1"`` or ``"F3"``.
        n_modes: how many of the lowest flexible modes (static).
        twin: the twin's mesh and nut correction (:class:`fdjax.TwinOptions`).
    """
    fn = "drive_modes"
    out = _channel(output, OUTPUTS, fn, "output")
    inp = _channel(input, INPUTS, fn, "input")
    twin = _twin_options(twin, fn)
    n_el = int(twin.n_elements)
    # at most N − 1 oscillatory pole pairs for N = 2·n_elements + 3 + the carriage's DOFs (2,
    # or 3 with a table; the rigid body gives two real poles)
    car = drive.carriage.n_dofs if isinstance(drive, BallScrewDrive) else 2  # (named below)
    n_keep = _checks.static_int(n_modes, f"{fn}(n_modes=...)", 1, 2 * n_el + 2 + int(car))
    pos = _checks.real_array(position_m, f"{fn}(position_m=...)")
    if pos.ndim == 0:
        drive, pos = _check_inputs(drive, pos, fn)
        return _modes_jit(drive, pos, out, inp, n_keep, n_el, twin.nut_correction)
    if pos.ndim != 1:
        raise ValueError(f"`{fn}(position_m=...)` must be a scalar or 1-D, got {pos.shape}")
    drive = _check_time_domain(drive, fn)
    pos = drive._check_positions(pos, fn)
    return _modes_batch_jit(drive, pos, out, inp, n_keep, n_el, twin.nut_correction)


def _modes_at(drive, pos, out, inp, n_modes, n_elements, nut_correction=True,
              fn="drive_modes"):
    return _modes_from_fe(_assemble(drive, pos, n_elements, bool(nut_correction)), out, inp,
                          n_modes, fn)


def _modes_batch(drive, pos, out, inp, n_modes, n_elements, nut_correction=True):
    return map_positions(
        lambda p: _modes_at(drive, p, out, inp, n_modes, n_elements, nut_correction), pos)


# Positions reach these as arrays (a Python float would be static: one compile per value).
_modes_jit = eqx.filter_jit(_modes_at)
_modes_batch_jit = eqx.filter_jit(_modes_batch)


def track_drive_modes(
    modes: DriveModes, *, freq_tol: float = 0.05, mac_tol: float = 0.2
) -> DriveModes:
    """Re-order a position batch of :func:`drive_modes` so each index follows one mode.

    Neighbouring positions are paired by minimising the frequency change (extrapolated) and
    ``1 − MAC`` of the three-output mode shapes (see :func:`fdjax.track_modes`).
    """
    from .._modal import _track

    _checks.instance(modes, DriveModes, "track_drive_modes(modes=...)",
                     "an fdjax.DriveModes (from fdjax.drive_modes)")
    freq_tol = _checks.positive(
        _checks.real_scalar(freq_tol, "track_drive_modes(freq_tol=...)"),
        "track_drive_modes(freq_tol=...)",
    )
    mac_tol = _checks.positive(
        _checks.real_scalar(mac_tol, "track_drive_modes(mac_tol=...)"),
        "track_drive_modes(mac_tol=...)",
    )
    if modes.frequency_hz.ndim != 2:
        raise ValueError(
            "`track_drive_modes(modes=...)` must be a batch over positions, got frequency_hz "
            f"of shape {modes.frequency_hz.shape}"
        )
    perm = _track(modes.frequency_hz, modes.shapes, freq_tol, mac_tol, True)

    def take(x):
        idx = perm.reshape(perm.shape + (1,) * (x.ndim - 2))
        return jnp.take_along_axis(x, idx, axis=1)

    return jax.tree_util.tree_map(take, modes)
