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

A :class:`fdjax.Table` on the carriage changes only the carriage's receptance h_S over
(x_n, x2, x3): the tool point x3 and F3 move to the table, and the table's own coordinate stays
inside h_S (:class:`fdjax.Carriage`); the coupling at the nut is the same.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from .. import _checks
from .._coupling import block_diagonal, couple_entries
from .._linalg import from_entries, recip, stack_entries
from ._substructures import Axial, Carriage, NutJoint, Rotary, Screw, tridiagonal_dense

__all__ = ["BallScrewDrive", "OUTPUTS", "INPUTS"]

OUTPUTS = ("theta1", "x2", "x3")
"""Output coordinates of H_M: motor angle (rad), linear scale (m), tool point (m)."""
INPUTS = ("T1", "F3")
"""Input coordinates of H_M: motor torque (N·m), disturbance force at the tool point (N)."""


def travel_pair(value, where: str) -> tuple[float, float]:
    """A travel ``value`` as a (min, max) pair of Python floats in m (a static field: hashable,
    compared by value), checked: two concrete numbers (else a ``TypeError`` when they are not
    numbers, a ``ValueError`` when it is not a pair), finite and increasing, and neither beyond
    :data:`fdjax._checks.LONGEST_TRAVEL_M` (a travel given in millimetres: the message says
    so, with the value in metres).  ``where`` is the argument in call syntax, e.g.
    ``"BallScrewDrive(travel_m=...)"``."""
    pair = "a (min, max) pair of numbers in m"
    try:
        lo, hi = value
    except (TypeError, ValueError):  # a number, three numbers, ...
        raise ValueError(f"`{where}` must be {pair}, got {value!r}") from None
    try:
        lo, hi = (_checks.concrete_float(v, where) for v in (lo, hi))
    except TypeError:  # a string or another object that is not a number
        raise TypeError(f"`{where}` must be {pair}, got {value!r}") from None
    except ValueError:  # an array, a complex or a traced value
        raise ValueError(f"`{where}` must be {pair}, got {value!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise ValueError(f"`{where}` must be an increasing (min, max) pair in m, got {value!r}")
    far = hi if abs(hi) >= abs(lo) else lo
    if abs(far) > _checks.LONGEST_TRAVEL_M:  # no ball-screw axis is that long: given in mm
        raise ValueError(f"`{where}` must be a (min, max) pair in m, got {value!r}; table "
                         f"positions are in metres: {far:.6g} mm is {far * 1e-3:.6g} m")
    return (lo, hi)


def _travel(value) -> tuple[float, float]:
    """``BallScrewDrive``'s ``travel_m`` converter (:func:`travel_pair`)."""
    return travel_pair(value, "BallScrewDrive(travel_m=...)")


class BallScrewDrive(eqx.Module):
    """A ball-screw feed drive with position-dependent dynamics (paper Figs. 6–9).

    Attributes:
        screw: the ball screw (length, diameter, lead, material).
        rotary: subsystem R (motor rotor, coupling, rotational supports).
        axial: subsystem A (thrust bearings).
        carriage: subsystem S (carriage axial + pitch; nut, scale and tool heights; an
            optional :class:`fdjax.Table` carrying the tool point).
        nut: the screw–nut joint (k_ja, c_ja).
        nut_offset: l0 (m): the nut sits at l = Y_table + l0 from the drive-end bearing
            (refused when the nut would leave the screw on the travel; an offset of 1
            or more, longer than the screw, that fits once read in mm is refused with
            its value in metres).
        travel_m: (min, max) table position Y_table (m), static; neither beyond
            ``LONGEST_TRAVEL_M`` = 20 m (:func:`travel_pair`).

    Every public method checks its inputs (positions inside the travel, finite frequencies)
    and its result (finite): eagerly as a ``ValueError``, under ``jit``/``vmap``/``grad`` as an
    ``eqx.error_if`` on the value that flows on.
    """

    screw: Screw
    rotary: Rotary
    axial: Axial
    carriage: Carriage
    nut: NutJoint
    nut_offset: Float[Array, ""] = _checks.finite_field("BallScrewDrive(nut_offset=...)")
    travel_m: tuple[float, float] = eqx.field(static=True, default=(0.1, 0.7),
                                              converter=_travel)

    def __check_init__(self):
        for name, cls in (("screw", Screw), ("rotary", Rotary), ("axial", Axial),
                          ("carriage", Carriage), ("nut", NutJoint)):
            _checks.instance(getattr(self, name), cls, f"BallScrewDrive({name}=...)")
        lo, hi = self.travel_m  # a checked pair (`travel_pair`, the field's converter)
        if _checks.is_concrete(self.nut_offset) and _checks.is_concrete(self.screw.length):
            l0, L = float(self.nut_offset), float(self.screw.length)
            if not (lo + l0 > 0 and hi + l0 < L):
                # an offset longer than the screw that fits once read in mm (and is a
                # millimetre or more, not a metre value slightly off): given in mm
                mm = abs(l0) > L and abs(l0) >= 1.0
                if mm and lo + l0 / 1000 > 0 and hi + l0 / 1000 < L:
                    raise ValueError(
                        f"`BallScrewDrive(nut_offset=...)` must keep the nut strictly inside "
                        f"the screw (0, {L:.6g}) m over the travel [{lo:.6g}, {hi:.6g}] m, got "
                        f"{l0:.6g} (nut positions [{lo + l0:.6g}, {hi + l0:.6g}] m)"
                        f"{_checks.mm_hint(l0)}"
                    )
                raise ValueError(
                    f"`BallScrewDrive(travel_m=..., nut_offset=...)` must keep the nut strictly "
                    f"inside the screw (0, {L:.6g}) m, got nut positions "
                    f"[{lo + l0:.6g}, {hi + l0:.6g}] m"
                )
        # Traced (e.g. vmapped) nut_offset or screw length: the nut is checked, per position,
        # by every public method (`_check_travel`).

    # ------------------------------------------------------------------ rigid-body summaries
    def reflected_inertia(self) -> Float[Array, ""]:
        r"""Inertia of the rigid drive reflected to the motor (kg·m²).

            J_eq = J_m + J_de + J_fe + ρJ·L + (m + m_t)·i_sc²

        (rotor with motor-side hub, screw-side and free-end hubs, the screw in torsion, and the
        carriage with its table, m_t = 0 without one, through the screw ratio): the rigid-body
        asymptote x2/T1 → i_sc/(−ω²J_eq + iωc_eq) far below the first mode, and the
        acceleration feed-forward of a rigid drive, k_ffa = J_eq/(k_motor·i_sc).
        """
        r = self.rotary
        rho_j = self.screw.section()[1]
        J = (r.motor_inertia + r.drive_end_inertia + r.free_end_inertia
             + rho_j * self.screw.length + self.carriage.mass * self.screw.ratio**2)
        if self.carriage.table is not None:
            J = J + self.carriage.table.mass * self.screw.ratio**2
        return J

    def reflected_damping(self) -> Float[Array, ""]:
        r"""Viscous damping of the rigid drive reflected to the motor (N·m·s/rad).

            c_eq = c_m + c_de + c_fe + c_x·i_sc²

        (motor and bearing friction, guideway damping through the screw ratio; a
        :class:`fdjax.Table`'s damper is internal and adds nothing); the velocity feed-forward
        of a rigid drive is k_ffv = c_eq/(k_motor·i_sc).
        """
        r = self.rotary
        return (r.motor_damping + r.drive_end_damping + r.free_end_damping
                + self.carriage.axial_damping * self.screw.ratio**2)

    # ------------------------------------------------------------------ input checks
    def _check_travel(self, position_m, fn: str, param: str = "position_m") -> Array:
        """Table positions of any shape: real, finite, inside ``travel_m`` and with the nut
        inside the screw; returned as float64 (guarded when traced).  ``fn`` is the function
        the user called, e.g. ``"BallScrewDrive.receptance"`` or ``"simulate"``, ``param`` the
        name of its argument."""
        where = f"{fn}({param}=...)"
        # a drive edited after construction (eqx.tree_at) has skipped its constructor's checks
        _checks.constructor_checks(self, fn)
        pos = _checks.real_array(position_m, where)
        if pos.size == 0:
            raise ValueError(f"`{where}` must hold at least one table position, got shape "
                             f"{pos.shape}")
        lo, hi = self.travel_m
        pos = _checks.inside(pos, lo, hi, where)
        # The nut stays inside the screw for every position of the travel when the drive was
        # built with concrete values (__check_init__); a traced or tree_at-edited nut_offset
        # or screw length is only known here.
        l0, L = self.nut_offset, self.screw.length
        expected = "such that the nut lies inside the screw, 0 < position_m + nut_offset < L"
        if all(_checks.is_concrete(x) for x in (pos, l0, L)):
            # NumPy scalars: a concrete jax array here would be staged into an enclosing trace
            l0n, Ln = float(l0), float(L)
            return _checks.check(pos, lambda p: (p + l0n > 0) & (p + l0n < Ln), where,
                                 f"{expected} = {Ln:.6g} m")
        ok = jnp.all((pos + l0 > 0) & (pos + l0 < L))
        return eqx.error_if(pos, ~ok, f"`{where}` must be {expected}")

    def _check_positions(self, position_m, fn: str = "BallScrewDrive.frf") -> Array:
        """Table positions as a 1-D float64 array (a scalar becomes shape (1,)), checked as
        :meth:`_check_travel` does, with messages naming ``fn``."""
        pos = jnp.atleast_1d(_checks.real_array(position_m, f"{fn}(position_m=...)"))
        if pos.ndim != 1:
            raise ValueError(
                f"`{fn}(position_m=...)` must be a scalar or 1-D, got shape {pos.shape}"
            )
        return self._check_travel(pos, fn)

    def _check_point(self, position_m, omega, fn: str) -> tuple[Array, Array]:
        """Broadcastable positions (m) and finite angular frequencies (rad/s, real or
        complex) of the pointwise methods."""
        pos = self._check_travel(position_m, fn)
        omega = _checks.finite(jnp.asarray(omega), f"{fn}(omega=...)")
        return pos, omega

    # ------------------------------------------------------------------ core (unchecked)
    def _substructure_receptances(self, position_m, omega):
        l = jnp.asarray(position_m) + self.nut_offset
        r = self.rotary._receptance(self.screw.torsion(), l, omega)
        a = self.axial._receptance(self.screw.axial(), l, omega)
        s = self.carriage._receptance(omega)
        return r, a, s

    def _coupled_receptance(self, position_m, omega):
        (h11, h1l, hll), ha, hs = self._substructure_receptances(position_m, omega)
        Y = block_diagonal([[h11, h1l], [h1l, hll]], [[ha]], hs)
        B = [[0, -jnp.asarray(self.screw.ratio).astype(jnp.complex128), -1.0, 1.0, 0, 0]]
        joint = [[recip(self.nut._dynamic_stiffness(omega))]]
        return couple_entries(Y, B, joint)

    def _receptance_entries(self, position_m, omega):
        Yc = self._coupled_receptance(position_m, omega)
        return [[Yc[i][j] for j in (0, 5)] for i in (0, 4, 5)]

    def _receptance_direct(self, position_m, omega):
        l = jnp.asarray(position_m) + self.nut_offset
        dr, er = self.rotary._line(self.screw.torsion(), l, omega)
        da, ea = self.axial._line(self.screw.axial(), l, omega)
        c = self.carriage
        d = c.n_dofs
        n = 7 + d  # θ1, θ(0), θ(l), θ(L), u(0), u(l), u(L), then the carriage's (x_c, ψ[, x_t])
        Ds = c._dynamic_stiffness(omega)
        shape = jnp.broadcast_shapes(*[jnp.shape(x) for x in (*dr, *er, *da, *ea)],
                                     Ds.shape[:-2])
        D = jnp.zeros((*shape, n, n), jnp.complex128)
        D = D.at[..., :4, :4].set(jnp.broadcast_to(tridiagonal_dense(dr, er), (*shape, 4, 4)))
        D = D.at[..., 4:7, 4:7].set(jnp.broadcast_to(tridiagonal_dense(da, ea), (*shape, 3, 3)))
        D = D.at[..., 7:, 7:].set(jnp.broadcast_to(Ds, (*shape, d, d)))
        zero, one = jnp.zeros(()), jnp.ones(())
        points = c._points()  # rows nut, scale, tool over the carriage's coordinates
        b = jnp.concatenate(
            [jnp.stack([zero, zero, -self.screw.ratio, zero, zero, -one, zero]), points[0]]
        ).astype(jnp.complex128)
        kj = jnp.broadcast_to(self.nut._dynamic_stiffness(omega), shape)
        D = D + kj[..., None, None] * (b[:, None] * b[None, :])
        e = jnp.eye(n, dtype=jnp.float64)[0]
        rows = jnp.concatenate([jnp.zeros((3, 7)), points], axis=1)
        outputs = jnp.stack([e, rows[1], rows[2]])
        inputs = jnp.stack([e, rows[2]], -1).astype(jnp.complex128)
        X = jnp.linalg.solve(D, jnp.broadcast_to(inputs, (*shape, n, 2)))
        return jnp.einsum("oi,...ij->...oj", outputs.astype(jnp.complex128), X)

    # ------------------------------------------------------------------ public, checked
    def substructure_receptances(self, position_m: Float[ArrayLike, "*shape"],
                                 omega: Complex[ArrayLike, "*shape"]):
        """Uncoupled receptances: R (h11, h1l, hll), A h_ll and S (3×3 over x_n, x2, x3)."""
        fn = "BallScrewDrive.substructure_receptances"
        out = self._substructure_receptances(*self._check_point(position_m, omega, fn))
        return _checks.finite_tree(out, f"{fn}(...)")

    def coupled_receptance(
        self, position_m: Float[ArrayLike, "*shape"], omega: Complex[ArrayLike, "*shape"]
    ) -> list[list[Complex[Array, "*shape"]]]:
        """Coupled receptance over (θ1, θ_l, u_l, x_n, x2, x3) by LM-FBS (paper Eq. 1),
        Y_c = Y − Y Bᵀ (B Y Bᵀ + Y_j)⁻¹ B Y (:func:`fdjax.couple`): Y the substructures'
        receptances side by side, B the nut's compatibility, Y_j the nut joint's receptance.

        Returned as a 6×6 nested list of broadcast arrays (see ``fdjax._linalg``).
        """
        fn = "BallScrewDrive.coupled_receptance"
        out = self._coupled_receptance(*self._check_point(position_m, omega, fn))
        return _checks.finite_tree(out, f"{fn}(...)")

    def receptance(self, position_m: Float[ArrayLike, "*shape"],
                   omega: Complex[ArrayLike, "*shape"]) -> Complex[Array, "... 3 2"]:
        """H_M (paper Eq. 2: the coupled receptance at the drive's outputs θ1, x2, x3 over its
        inputs T1, F3) at broadcastable table positions (m) and angular frequencies (rad/s).

        Positions must lie inside ``travel_m`` and ω must be finite (real, or complex for a
        pole search); a non-finite result (ω = 0 is the rigid-body pole) is an error.
        """
        fn = "BallScrewDrive.receptance"
        out = from_entries(self._receptance_entries(*self._check_point(position_m, omega, fn)))
        return _checks.finite_output(out, f"{fn}(...)")

    def receptance_entries(
        self, position_m: Float[ArrayLike, "*shape"], omega: Complex[ArrayLike, "*shape"]
    ) -> list[list[Complex[Array, "*shape"]]]:
        """H_M (paper Eq. 2) as a 3×2 nested list of arrays (no interleaving; the fastest form
        in a jit)."""
        fn = "BallScrewDrive.receptance_entries"
        out = self._receptance_entries(*self._check_point(position_m, omega, fn))
        return _checks.finite_tree(out, f"{fn}(...)")

    def receptance_direct(self, position_m: Float[ArrayLike, "*shape"],
                          omega: Complex[ArrayLike, "*shape"]) -> Complex[Array, "... 3 2"]:
        """H_M by assembling the whole drive as one dynamic stiffness (no coupling step).

        DOFs (θ1, θ(0), θ(l), θ(L), u(0), u(l), u(L), x_c, ψ), and x_t last with a
        :class:`fdjax.Table` on the carriage (its connection ``(k_t + iωc_t) b_t b_tᵀ``,
        ``b_t = (−1, −h_t, 1)`` on (x_c, ψ, x_t)); the nut joint adds ``(k_ja + iωc_ja) bᵀb``
        with ``b = [0, 0, −i_sc, 0, 0, −1, 0, 1, h_n(, 0)]``.  The tool point is
        ``x_c + h_3 ψ``, or ``x_t + (h_3 − h_t) ψ`` on the table.  Independent of the LM-FBS
        algebra (and of the carriage's closed-form receptance), it proves the coupling's
        signs.
        """
        fn = "BallScrewDrive.receptance_direct"
        out = self._receptance_direct(*self._check_point(position_m, omega, fn))
        return _checks.finite_output(out, f"{fn}(...)")

    def frf(
        self, position_m: Float[ArrayLike, " pos"], freq_hz: Float[ArrayLike, " freq"]
    ) -> Complex[Array, "pos freq 3 2"]:
        r"""H_M(Y_table, f): the drive's 3×2 receptance on a position × frequency grid.

        Outputs (θ1 rad, x2 m, x3 m) per inputs (T1 N·m, F3 N), paper Eq. (2) in its derived
        form: LM-FBS at the nut over u = (θ1, θ_l, u_l, x_n, x2, x3),
        Y_c = Y − Y Bᵀ (i_sc² h_R,ll + h_A,ll + h_S,nn + 1/(k_ja + iωc_ja))⁻¹ B Y with
        B = [0, −i_sc, −1, 1, 0, 0] (the bracket of paper Eq. 1; i_sc = lead/2π in m/rad, the
        reciprocal of the paper's ratio), H_M the rows (θ1, x2, x3) and columns (T1, F3) of
        Y_c.  jit-compiled and vectorised; differentiable with respect to
        every physical parameter of the drive.

        Args:
            position_m: table positions Y_table (m) inside ``travel_m``; scalar or 1-D.
            freq_hz: a positive, strictly increasing frequency grid (Hz).

        Returns:
            Complex array of shape (n_pos, n_freq, 3, 2).
        """
        pos = self._check_positions(position_m, "BallScrewDrive.frf")
        freq_hz = _checks.frequency_grid(freq_hz, "BallScrewDrive.frf(freq_hz=...)")
        out = _drive_frf(self, pos, freq_hz)
        return _checks.finite_output(out, "BallScrewDrive.frf(...)")

    def frf_direct(
        self, position_m: Float[ArrayLike, " pos"], freq_hz: Float[ArrayLike, " freq"]
    ) -> Complex[Array, "pos freq 3 2"]:
        """Same as :meth:`frf` by direct assembly (one model, no coupling step); a reference."""
        pos = self._check_positions(position_m, "BallScrewDrive.frf_direct")
        freq_hz = _checks.frequency_grid(freq_hz, "BallScrewDrive.frf_direct(freq_hz=...)")
        out = _drive_frf_direct_jit(self, pos, freq_hz)
        return _checks.finite_output(out, "BallScrewDrive.frf_direct(...)")


def _drive_frf(drive: BallScrewDrive, pos, freq_hz):
    # Two compiled stages on purpose: fused into one program, XLA's concatenate fusion would
    # recompute the shared substructure algebra once per output entry (≈6× slower).
    return stack_entries(_drive_entries_jit(drive, pos, freq_hz))


def _drive_entries(drive: BallScrewDrive, pos, freq_hz):
    omega = 2 * jnp.pi * freq_hz
    shape = (pos.shape[0], freq_hz.shape[0])
    H = drive._receptance_entries(pos[:, None], omega[None, :])
    return [[jnp.broadcast_to(x, shape) for x in row] for row in H]


def _drive_frf_direct(drive: BallScrewDrive, pos, freq_hz):
    omega = 2 * jnp.pi * freq_hz
    return jax.vmap(lambda p: drive._receptance_direct(p, omega))(pos)


# The positions and frequencies reach these as arrays (never Python floats, which
# eqx.filter_jit would treat as static and compile once per value).
_drive_entries_jit = eqx.filter_jit(_drive_entries)
_drive_frf_direct_jit = eqx.filter_jit(_drive_frf_direct)
