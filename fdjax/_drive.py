r"""The ball-screw feed drive: substructures coupled at the nut into H_M(Y_table, ω) (paper Eq. 2).

Degrees of freedom of the uncoupled substructures that the coupling needs:

    u = (θ1, θ_l, u_l, x_n, x_2, x_3)

(motor angle; screw rotation, screw axial displacement and carriage displacement at the nut;
linear scale; tool point).  The nut joint deforms by ``Δ = x_n − u_l − i_sc θ_l = B u`` with
``B = [0, −i_sc, −1, 1, 0, 0]`` and carries ``k_ja + iωc_ja``.  LM-FBS (:func:`fdjax.couple`):

    Y_c = Y − Y Bᵀ (i_sc² h_R,ll + h_A,ll + h_S,nn + 1/(k_ja + iωc_ja))⁻¹ B Y,

whose bracket is the one in the paper's Eq. (1); the typeset Eq. (2) is garbled and is replaced by
this derivation.  ``H_M`` is the block of ``Y_c`` with outputs (θ1, x2, x3) and inputs (T1 at θ1,
F3 at x3), i.e. a 3×2 matrix per (position, frequency).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from . import _checks
from ._coupling import block_diagonal, couple_entries
from ._linalg import from_entries, recip, stack_entries
from ._substructures import Axial, Carriage, NutJoint, Rotary, Screw, tridiagonal_dense

__all__ = ["BallScrewDrive", "reference_drive", "OUTPUTS", "INPUTS"]

OUTPUTS = ("theta1", "x2", "x3")
"""Output coordinates of H_M: motor angle (rad), linear scale (m), tool point (m)."""
INPUTS = ("T1", "F3")
"""Input coordinates of H_M: motor torque (N·m), disturbance force at the tool point (N)."""


def _scalar(x) -> Array:
    return jnp.asarray(x, dtype=jnp.float64)


class BallScrewDrive(eqx.Module):
    """A ball-screw feed drive with position-dependent dynamics (paper Figs. 6–9).

    Attributes:
        screw: the ball screw (length, diameter, lead, material).
        rotary: subsystem R (motor rotor, coupling, rotational supports).
        axial: subsystem A (thrust bearings).
        carriage: subsystem S (carriage axial + pitch; nut, scale and tool heights).
        nut: the screw–nut joint (k_ja, c_ja).
        nut_offset: l0 (m): the nut sits at l = Y_table + l0 from the drive-end bearing.
        travel_m: (min, max) table position Y_table (m), static.
    """

    screw: Screw
    rotary: Rotary
    axial: Axial
    carriage: Carriage
    nut: NutJoint
    nut_offset: Float[Array, ""] = eqx.field(converter=_scalar)
    travel_m: tuple[float, float] = eqx.field(static=True, default=(0.1, 0.7))

    def __check_init__(self):
        lo, hi = self.travel_m
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(
                f"`BallScrewDrive(travel_m=...)` must be an increasing (min, max) pair, "
                f"got {self.travel_m}"
            )
        _checks.finite(self.nut_offset, "BallScrewDrive(nut_offset=...)")
        if _checks.is_concrete(self.nut_offset) and _checks.is_concrete(self.screw.length):
            l0, L = float(self.nut_offset), float(self.screw.length)
            if not (lo + l0 > 0 and hi + l0 < L):
                raise ValueError(
                    f"`BallScrewDrive(travel_m=..., nut_offset=...)` must keep the nut strictly "
                    f"inside the screw (0, {L:.6g}) m, got nut positions "
                    f"[{lo + l0:.6g}, {hi + l0:.6g}] m"
                )

    # ------------------------------------------------------------------ core (unchecked)
    def substructure_receptances(self, position_m, omega):
        """Uncoupled receptances: R (h11, h1l, hll), A h_ll and S (3×3 over x_n, x2, x3)."""
        l = jnp.asarray(position_m) + self.nut_offset
        r = self.rotary.receptance(self.screw.torsion(), l, omega)
        a = self.axial.receptance(self.screw.axial(), l, omega)
        s = self.carriage.receptance(omega)
        return r, a, s

    def coupled_receptance(self, position_m, omega) -> list[list[Complex[Array, ...]]]:
        """Coupled receptance over (θ1, θ_l, u_l, x_n, x2, x3) by LM-FBS (paper Eq. 1).

        Returned as a 6×6 nested list of broadcast arrays (see ``fdjax._linalg``).
        """
        (h11, h1l, hll), ha, hs = self.substructure_receptances(position_m, omega)
        Y = block_diagonal([[h11, h1l], [h1l, hll]], [[ha]], hs)
        B = [[0, -jnp.asarray(self.screw.ratio).astype(jnp.complex128), -1.0, 1.0, 0, 0]]
        joint = [[recip(self.nut.dynamic_stiffness(omega))]]
        return couple_entries(Y, B, joint)

    def receptance(self, position_m, omega) -> Complex[Array, "... 3 2"]:
        """H_M at broadcastable table positions (m) and angular frequencies (rad/s), unchecked."""
        return from_entries(self.receptance_entries(position_m, omega))

    def receptance_entries(self, position_m, omega) -> list[list[Complex[Array, ...]]]:
        """H_M as a 3×2 nested list of arrays (no interleaving; the fastest form in a jit)."""
        Yc = self.coupled_receptance(position_m, omega)
        return [[Yc[i][j] for j in (0, 5)] for i in (0, 4, 5)]

    def receptance_direct(self, position_m, omega) -> Complex[Array, "... 3 2"]:
        """H_M by assembling the whole drive as one dynamic stiffness (no coupling step).

        DOFs (θ1, θ(0), θ(l), θ(L), u(0), u(l), u(L), x_c, ψ); the nut joint adds
        ``(k_ja + iωc_ja) bᵀb`` with ``b = [0, 0, −i_sc, 0, 0, −1, 0, 1, h_n]``.  Independent of
        the LM-FBS algebra, it proves the coupling's signs.
        """
        l = jnp.asarray(position_m) + self.nut_offset
        dr, er = self.rotary.line(self.screw.torsion(), l, omega)
        da, ea = self.axial.line(self.screw.axial(), l, omega)
        axial, pitch = self.carriage.modal_stiffness(omega)
        shape = jnp.broadcast_shapes(*[jnp.shape(x) for x in (*dr, *er, *da, *ea, axial, pitch)])
        Ds = jnp.zeros((*shape, 2, 2), jnp.complex128)
        Ds = Ds.at[..., 0, 0].set(jnp.broadcast_to(axial, shape))
        Ds = Ds.at[..., 1, 1].set(jnp.broadcast_to(pitch, shape))
        D = jnp.zeros((*shape, 9, 9), jnp.complex128)
        D = D.at[..., :4, :4].set(jnp.broadcast_to(tridiagonal_dense(dr, er), (*shape, 4, 4)))
        D = D.at[..., 4:7, 4:7].set(jnp.broadcast_to(tridiagonal_dense(da, ea), (*shape, 3, 3)))
        D = D.at[..., 7:, 7:].set(Ds)
        c = self.carriage
        zero, one = jnp.zeros(()), jnp.ones(())
        b = jnp.stack(
            [zero, zero, -self.screw.ratio, zero, zero, -one, zero, one, c.nut_height]
        ).astype(jnp.complex128)
        kj = jnp.broadcast_to(self.nut.dynamic_stiffness(omega), shape)
        D = D + kj[..., None, None] * (b[:, None] * b[None, :])
        e = jnp.eye(9, dtype=jnp.float64)
        outputs = jnp.stack([e[0], e[7] + c.scale_height * e[8], e[7] + c.tool_height * e[8]])
        inputs = jnp.stack([e[0], e[7] + c.tool_height * e[8]], -1).astype(jnp.complex128)
        X = jnp.linalg.solve(D, jnp.broadcast_to(inputs, (*shape, 9, 2)))
        return jnp.einsum("oi,...ij->...oj", outputs.astype(jnp.complex128), X)

    # ------------------------------------------------------------------ public, checked
    def frf(
        self, position_m: Float[ArrayLike, " pos"], freq_hz: Float[ArrayLike, " freq"]
    ) -> Complex[Array, "pos freq 3 2"]:
        r"""H_M(Y_table, f): the drive's 3×2 receptance on a position × frequency grid.

        Outputs (θ1 rad, x2 m, x3 m) per inputs (T1 N·m, F3 N), paper Eq. (2) (derived form,
        see the module docstring).  jit-compiled and vectorised; differentiable with respect to
        every physical parameter of the drive.

        Args:
            position_m: table positions Y_table (m) inside ``travel_m``; scalar or 1-D.
            freq_hz: a positive, strictly increasing frequency grid (Hz).

        Returns:
            Complex array of shape (n_pos, n_freq, 3, 2).
        """
        pos = self._check_positions(position_m)
        freq_hz = _checks.frequency_grid(freq_hz, "BallScrewDrive.frf(freq_hz=...)")
        out = _drive_frf(self, pos, freq_hz)
        return _checks.finite_output(out, "BallScrewDrive.frf(...)")

    def frf_direct(
        self, position_m: Float[ArrayLike, " pos"], freq_hz: Float[ArrayLike, " freq"]
    ) -> Complex[Array, "pos freq 3 2"]:
        """Same as :meth:`frf` by direct assembly (one model, no coupling step); a reference."""
        pos = self._check_positions(position_m)
        freq_hz = _checks.frequency_grid(freq_hz, "BallScrewDrive.frf_direct(freq_hz=...)")
        return _drive_frf_direct(self, pos, freq_hz)

    def _check_positions(self, position_m) -> Array:
        pos = jnp.atleast_1d(jnp.asarray(position_m, dtype=jnp.float64))
        if pos.ndim != 1:
            raise ValueError(
                "`BallScrewDrive.frf(position_m=...)` must be a scalar or 1-D, "
                f"got shape {pos.shape}"
            )
        lo, hi = self.travel_m
        return _checks.check(
            pos,
            lambda p: (p >= lo) & (p <= hi),
            "BallScrewDrive.frf(position_m=...)",
            f"inside the travel [{lo:.6g}, {hi:.6g}] m",
        )


def _drive_frf(drive: BallScrewDrive, pos, freq_hz):
    # Two compiled stages on purpose: fused into one program, XLA's concatenate fusion would
    # recompute the shared substructure algebra once per output entry (≈6× slower).
    return stack_entries(_drive_entries(drive, pos, freq_hz))


@eqx.filter_jit
def _drive_entries(drive: BallScrewDrive, pos, freq_hz):
    omega = 2 * jnp.pi * freq_hz
    shape = (pos.shape[0], freq_hz.shape[0])
    H = drive.receptance_entries(pos[:, None], omega[None, :])
    return [[jnp.broadcast_to(x, shape) for x in row] for row in H]



@eqx.filter_jit
def _drive_frf_direct(drive: BallScrewDrive, pos, freq_hz):
    omega = 2 * jnp.pi * freq_hz
    return jax.vmap(lambda p: drive.receptance_direct(p, omega))(pos)


def reference_drive() -> BallScrewDrive:
    """The built-in reference drive: a medium machine-tool axis, 600 mm travel.

    Every value is a plausible catalogue or handbook figure for a 32 mm ball-screw axis
    carrying a 250 kg table; see the inline notes.  The nut runs from l = 0.25 m to 0.85 m on
    a 1.0 m screw, so the free screw span and the axial stiffness at the nut change with
    Y_table and the modes move with position.
    """
    screw = Screw(
        length=1.0,  # m, bearing-to-bearing length of a 1 m-class axis with 600 mm travel
        diameter=0.0275,  # m, root diameter of a 32 mm nominal screw (d_nom − ball diameter)
        lead=0.010,  # m/rev, common 32×10 screw: i_sc = 1.59 mm/rad
        youngs_modulus=2.06e11,  # Pa, bearing steel
        shear_modulus=7.93e10,  # Pa, steel
        density=7850.0,  # kg/m³, steel
        retardation=1.0e-6,  # s, ζ ≈ βω/2 ≈ 0.3 % at 1 kHz: lightly damped screw modes
    )
    rotary = Rotary(
        motor_inertia=3.4e-3,  # kg·m², rotor of an ~10 N·m servo motor plus motor-side hub
        coupling_stiffness=1.5e4,  # N·m/rad, metal bellows coupling for a 32 mm screw
        coupling_damping=0.5,  # N·m·s/rad, a few % damping of the coupling mode
        motor_damping=0.01,  # N·m·s/rad, viscous friction of motor bearings
        drive_end_inertia=4.0e-4,  # kg·m², screw-side hub, bearing rings and lock nut
        drive_end_damping=0.02,  # N·m·s/rad, preloaded angular-contact bearing friction
        free_end_inertia=5.0e-5,  # kg·m², floating bearing inner ring and nut
        free_end_damping=0.005,  # N·m·s/rad, floating-end bearing friction
    )
    axial = Axial(
        drive_end_stiffness=7.5e8,  # N/m, preloaded pair of 60° thrust angular-contact bearings
        drive_end_damping=1.5e4,  # N·s/m, bearing-housing damping
        free_end_stiffness=0.0,  # floating end: fixed–free axial arrangement
        free_end_damping=0.0,
        drive_end_mass=1.5,  # kg, bearing inner rings, spacer and lock nut
    )
    carriage = Carriage(
        mass=250.0,  # kg, table with fixture and workpiece
        pitch_inertia=9.0,  # kg·m², ≈ m (a² + h²)/12 for a 0.6 m × 0.25 m table
        pitch_stiffness=2.0e8,  # N·m/rad, 4 blocks of ~1.3 GN/m at ±0.2 m spacing
        axial_damping=3.0e3,  # N·s/m, viscous equivalent of guideway and seal friction
        pitch_damping=1.5e4,  # N·m·s/rad, ζ ≈ 0.18 % ... guideway joint damping
        nut_height=-0.06,  # m, screw axis below the pitch centre
        scale_height=-0.10,  # m, linear scale at the carriage base
        tool_height=0.25,  # m, tool point above the table (cutting height)
    )
    nut = NutJoint(
        stiffness=5.0e8,  # N/m, preloaded double nut, 32 mm screw (catalogue ~500 N/µm)
        damping=4.0e3,  # N·s/m, nut joint damping
    )
    return BallScrewDrive(screw, rotary, axial, carriage, nut, nut_offset=0.15, travel_m=(0.1, 0.7))
