r"""Mode tracking over table positions (paper Sec. 3.2, Figs. 11–12).

:func:`track_modes` walks along a position batch of :class:`ModalFit`\ s and pairs the modes at
position :math:`p+1` with the tracked modes at :math:`p` by minimising, over all pairings, the
summed cost

.. math::

    C_{ij} = \Big(\frac{f_j^{(p+1)} - \hat f_i}{\mathrm{freq\_tol}\,\hat f_i}\Big)^2
           + \Big(\frac{1 - \mathrm{MAC}(R_i^{(p)}, R_j^{(p+1)})}{\mathrm{mac\_tol}}\Big)^2,
    \qquad \mathrm{MAC}(a, b) = \frac{|a^H b|^2}{|a|^2 |b|^2},

frequency proximity (to a linear extrapolation) and mode-shape correlation of the residue
vectors.
"""

from __future__ import annotations

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._checks import instance, positive, real_scalar
from ._fit import ModalFit


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


# A pairing with a missing mode (a NaN entry) costs as much as one five tolerances off: where
# another track can take the mode, a track takes the gap rather than a mode farther than that
# (a track with no frequency yet, NaN from the first position, takes the mode that appears).
_MISSING = 25.0


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
        cost = df**2 + dmac**2
        # A mode missing at a position (NaN, from an order-free sweep) pairs with what is left
        # at the cost _MISSING (a cost of 1e30 had absorbed the real ones in round-off,
        # 1e30 + 100 == 1e30, and the pairing was the first permutation's).
        perm = _assign(jnp.where(jnp.isnan(cost), _MISSING, cost))
        f_t, psi_t = f_new[perm], psi_new[perm]
        # a track whose mode is missing here keeps its last frequencies and shape
        gap = jnp.isnan(f_t)
        carry = (jnp.where(gap, f_prev, f_t), jnp.where(gap, f_prev2, f_prev),
                 jnp.where(gap[:, None], psi_prev, psi_t), k + 1)
        return carry, perm

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

    Returns the same ``ModalFit`` with ``frequency_hz``, ``damping_ratio``, ``phase_deg``,
    ``residues`` and ``poles`` permuted per position; other fields are unchanged.
    """
    instance(fits, ModalFit, "track_modes(fits=...)",
             "an fdjax.ModalFit (from fdjax.identify_modes_batched)")
    if fits.frequency_hz.ndim != 2:
        raise ValueError(
            "`track_modes(fits=...)` must be a batch over positions with frequency_hz of "
            f"shape (n_positions, n_modes), got shape {fits.frequency_hz.shape}"
        )
    # arrays, not Python floats: a new tolerance runs the program compiled for the first
    freq_tol, mac_tol = (positive(real_scalar(v, f"track_modes({name}=...)"),
                                  f"track_modes({name}=...)")
                         for name, v in (("freq_tol", freq_tol), ("mac_tol", mac_tol)))
    n_pos, n = fits.frequency_hz.shape
    shapes = fits.residues.reshape(n_pos, n, -1)
    perm = _track(fits.frequency_hz, shapes, freq_tol, mac_tol, bool(extrapolate))

    def take(x):
        idx = perm.reshape(perm.shape + (1,) * (x.ndim - 2))
        return jnp.take_along_axis(x, idx, axis=1)

    return eqx.tree_at(
        lambda m: (m.frequency_hz, m.damping_ratio, m.phase_deg, m.residues, m.poles),
        fits,
        tuple(take(x) for x in (fits.frequency_hz, fits.damping_ratio, fits.phase_deg,
                                 fits.residues, fits.poles)),
    )
