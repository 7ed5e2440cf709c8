r"""The moving table: the plant's matrices follow the table, Y(t) = Y₀ + r(t).

The finite-element model is rebuilt at Y and projected on a fixed modal basis V (a Ritz basis:
the modes at Y₀, the rigid-body mode exact), so the nut's stiffness moves along the screw during
the motion (the paper froze the position).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, Float

from .._drive._model import BallScrewDrive
from .._drive._twin import (
    StateSpace,
    TwinOptions,
    _assemble,
    _generalised_eigh,
    _rigid_mode,
    _second_order,
)


class MovingPlant(eqx.Module):
    """Galerkin projection of the FE model at Y on the fixed modal basis V (N × m)."""

    drive: BallScrewDrive
    V: Float[Array, "N m"]
    twin: TwinOptions = eqx.field(static=True)

    @classmethod
    def at_rest(cls, drive, position_m, twin: TwinOptions, kept_modes: int) -> MovingPlant:
        """The basis of the modes at Y₀ (the rigid-body mode set exactly)."""
        n = int(twin.n_elements)
        fe = _assemble(drive, position_m, n, bool(twin.nut_correction))
        lam, Psi, L, _ = _generalised_eigh(fe)
        psi0 = L.T @ _rigid_mode(drive, n)
        Psi_m = Psi[:, :kept_modes].at[:, 0].set(psi0 / jnp.linalg.norm(psi0))
        return cls(drive, jsl.solve_triangular(L.T, Psi_m, lower=False), twin)

    def at(self, position_m) -> StateSpace:
        """The plant at Y, on the basis V (no residual flexibility: D = 0)."""
        fe = _assemble(self.drive, position_m, int(self.twin.n_elements),
                       bool(self.twin.nut_correction))
        V = self.V
        Mr, Kr, Cr = V.T @ fe.mass @ V, V.T @ fe.stiffness @ V, V.T @ fe.damping @ V
        m = V.shape[1]
        MK = jnp.linalg.solve(Mr, jnp.concatenate([Kr, Cr, V.T @ fe.inputs], 1))
        return _second_order(MK[:, :m], MK[:, m : 2 * m], MK[:, 2 * m :], fe.outputs @ V,
                             jnp.zeros((3, 2)), jnp.zeros(m), position_m, self.drive.screw.ratio)
