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
from .._drive._twin import StateSpace, _assemble, _generalised_eigh, _rigid_mode


class MovingPlant(eqx.Module):
    """Galerkin projection of the FE model at Y on the fixed modal basis V (N × m)."""

    drive: BallScrewDrive
    V: Float[Array, "N m"]
    n_elements: int = eqx.field(static=True)

    @classmethod
    def at_rest(cls, drive, position_m, n_elements: int, n_modes: int) -> MovingPlant:
        """The basis of the modes at Y₀ (the rigid-body mode set exactly)."""
        fe = _assemble(drive, position_m, n_elements, True)
        lam, Psi, L, _ = _generalised_eigh(fe)
        psi0 = L.T @ _rigid_mode(drive, n_elements)
        Psi_m = Psi[:, :n_modes].at[:, 0].set(psi0 / jnp.linalg.norm(psi0))
        return cls(drive, jsl.solve_triangular(L.T, Psi_m, lower=False), n_elements)

    def at(self, position_m) -> StateSpace:
        fe = _assemble(self.drive, position_m, self.n_elements, True)
        V = self.V
        Mr, Kr, Cr = V.T @ fe.mass @ V, V.T @ fe.stiffness @ V, V.T @ fe.damping @ V
        m = V.shape[1]
        MK = jnp.linalg.solve(Mr, jnp.concatenate([Kr, Cr, V.T @ fe.inputs], 1))
        zero, eye = jnp.zeros((m, m)), jnp.eye(m)
        A = jnp.block([[zero, eye], [-MK[:, :m], -MK[:, m : 2 * m]]])
        B = jnp.concatenate([jnp.zeros((m, 2)), MK[:, 2 * m :]], 0)
        Cq = fe.outputs @ V
        return StateSpace(
            A=A,
            B=B,
            C=jnp.concatenate([Cq, jnp.zeros_like(Cq)], 1),
            D=jnp.zeros((3, 2)),
            C_velocity=jnp.concatenate([jnp.zeros_like(Cq), Cq], 1),
            natural_freq_hz=jnp.zeros(m),
            position_m=jnp.asarray(position_m, jnp.float64),
            screw_ratio=jnp.asarray(self.drive.screw.ratio, jnp.float64),
        )
