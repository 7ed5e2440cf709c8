"""The three substructures of a ball-screw feed drive (paper Sec. 3.1, Figs. 8–9).

* :class:`Screw` — the ball screw: geometry, material and lead (transmission ratio i_sc).
* :class:`Rotary` (R) — motor rotor, coupling, screw torsion, rotational supports.
* :class:`Axial` (A) — screw axial vibration with its thrust bearing(s).
* :class:`Carriage` (S) — carriage axial motion and pitch on the guideway joints, with the nut,
  the linear scale (coordinate 2) and the tool point (coordinate 3) at their heights.
* :class:`Table` — an optional second sliding body on the carriage (e.g. the X table on a Y
  saddle), compliant in the drive's direction, which carries the tool point / workpiece.
* :class:`NutJoint` — the screw–nut joint, axial stiffness k_ja and damping c_ja.

Each substructure gives its exact receptances at the coordinates the coupling needs, and its
dynamic stiffness as a dense matrix for direct assembly (used to prove the coupling's signs).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float

from .. import _checks
from .._linalg import add, inv_entries, mul, recip
from ._rods import Rod, Support, line_stiffness, spring_stiffness, tridiagonal_receptance

__all__ = ["Screw", "Rotary", "Axial", "Table", "Carriage", "NutJoint"]


_cplx = _checks.to_complex


def _omega(omega, where: str) -> Array:
    """Angular frequencies (rad/s, real or complex, any shape) that must be finite."""
    return _checks.finite(jnp.asarray(omega), where)


def _nut_point(shaft: Rod, l, where: str) -> Array:
    """The nut point l (m) strictly inside the screw (0, L): an end would be a zero-length
    segment."""
    l = _checks.real_array(l, where)
    L = shaft.length
    if _checks.is_concrete(l) and _checks.is_concrete(L):
        Ln = float(L)  # a NumPy scalar: a jax array would be staged into an enclosing trace
        return _checks.check(l, lambda x: (x > 0) & (x < Ln), where,
                             f"strictly inside (0, {Ln:.6g}) m")
    ok = jnp.all((l > 0) & (l < L))
    return eqx.error_if(l, ~ok, f"`{where}` must be strictly inside (0, L) m")


HIGHEST_POINT_M = 5.0
"""No point of a feed drive's carriage or table lies farther from the pitch centre (a tall
gantry's tool is about 2 m from its guideways): a height beyond it (m) was given in mm."""

LARGEST_LEAD_M = 0.5
"""No ball screw has a longer lead (the longest catalogue leads are about 0.1–0.2 m per
revolution): a lead beyond it (m) was given in mm."""


_SCREW_SIZES = (
    ("length", _checks.LONGEST_TRAVEL_M, "no ball screw is longer"),
    ("diameter", _checks.LARGEST_SCREW_DIAMETER_M, "no ball screw is thicker"),
    ("bore_diameter", _checks.LARGEST_SCREW_DIAMETER_M, "no ball screw is thicker"),
    ("lead", LARGEST_LEAD_M, "per revolution; no ball screw has a longer lead"),
)
"""The plausibility limits of :class:`Screw` (field, most in m, why)."""


def tridiagonal_dense(diag, off) -> Complex[Array, "... n n"]:
    """Dense symmetric tridiagonal matrix from diagonal/off-diagonal lists (broadcast)."""
    n = len(diag)
    shape = jnp.broadcast_shapes(*[jnp.shape(d) for d in diag], *[jnp.shape(e) for e in off])
    D = jnp.zeros((*shape, n, n), jnp.complex128)
    for i in range(n):
        D = D.at[..., i, i].set(jnp.broadcast_to(diag[i], shape))
    for i in range(n - 1):
        e = jnp.broadcast_to(off[i], shape)
        D = D.at[..., i, i + 1].set(e).at[..., i + 1, i].set(e)
    return D


class Screw(eqx.Module):
    """The ball screw: a uniform steel shaft in torsion and axial motion.

    Attributes:
        length: distance between the drive-end and free-end bearings L (m).
        diameter: effective (root) diameter d (m) for both EA and GJ.
        bore_diameter: diameter d_i of a hollow screw's bore (m), 0 ≤ d_i < d (default 0:
            solid).  Large screws are often bored, for coolant or for weight.
        lead: lead p (m/rev); the transmission ratio is i_sc = p / 2π (m/rad).
        youngs_modulus: E (Pa).  shear_modulus: G (Pa).  density: ρ (kg/m³).
        retardation: Kelvin–Voigt retardation time β (s) of the screw material.
        loss_factor: hysteretic loss factor η (frequency domain only).

    Lengths are in metres.  A concrete length, diameter or bore, or lead beyond what any
    ball screw has (L > ``LONGEST_TRAVEL_M`` = 20 m, d or d_i > ``LARGEST_SCREW_DIAMETER_M``
    = 1 m, p > ``LARGEST_LEAD_M`` = 0.5 m) is refused, with the value in metres when it was
    given in millimetres (850 mm is 0.85 m); traced values (inside ``jit``/``vmap``) are
    checked finite and positive only.
    """

    length: Float[Array, ""] = _checks.positive_field("Screw(length=...)")
    diameter: Float[Array, ""] = _checks.positive_field("Screw(diameter=...)")
    lead: Float[Array, ""] = _checks.positive_field("Screw(lead=...)")
    youngs_modulus: Float[Array, ""] = _checks.positive_field(
        "Screw(youngs_modulus=...)", default=2.06e11
    )
    shear_modulus: Float[Array, ""] = _checks.positive_field(
        "Screw(shear_modulus=...)", default=7.93e10
    )
    density: Float[Array, ""] = _checks.positive_field("Screw(density=...)", default=7850.0)
    bore_diameter: Float[Array, ""] = _checks.nonnegative_field(
        "Screw(bore_diameter=...)", default=0.0
    )
    retardation: Float[Array, ""] = _checks.nonnegative_field("Screw(retardation=...)", default=0.0)
    loss_factor: Float[Array, ""] = _checks.nonnegative_field("Screw(loss_factor=...)", default=0.0)

    def __check_init__(self):
        # lengths in metres: a concrete value beyond what any ball screw has was given in mm
        for name, limit, reason in _SCREW_SIZES:
            _checks.at_most(getattr(self, name), limit, f"Screw({name}=...)", reason)
        for name, kind in (("youngs_modulus", "modulus"), ("shear_modulus", "modulus"),
                           ("density", "density")):
            _checks.material(getattr(self, name), kind, f"Screw({name}=...)")
        self._checked()

    def _checked(self) -> Screw:
        """This screw, its bore checked narrower than the screw: eagerly where both are
        concrete (as the constructor does), else by an ``eqx.error_if`` on the bore that flows
        on (a screw traced under ``vmap``/``jit``, or changed by ``eqx.tree_at``, whose
        section would be negative, then NaN)."""
        d, di = self.diameter, self.bore_diameter
        where = "`Screw(bore_diameter=...)` must be smaller than the diameter"
        if _checks.is_concrete(d) and _checks.is_concrete(di):
            if not np.all(np.asarray(di) < np.asarray(d)):
                raise ValueError(f"{where} {_checks.fmt(d)} m, got {_checks.fmt(di)}")
            return self
        return eqx.tree_at(lambda s: s.bore_diameter, self,
                           eqx.error_if(di, jnp.any(jnp.logical_not(di < d)), where))

    @property
    def ratio(self) -> Float[Array, ""]:
        """Transmission ratio i_sc = lead / 2π (m/rad)."""
        return self.lead / (2 * jnp.pi)

    def section(self) -> tuple[Array, Array, Array, Array]:
        """``(GJ, ρJ, EA, ρA)`` of the (hollow) circular section:
        J = π(d⁴ − d_i⁴)/32, A = π(d² − d_i²)/4."""
        d, di = self.diameter, self.bore_diameter
        area = jnp.pi * (d**2 - di**2) / 4
        polar = jnp.pi * (d**4 - di**4) / 32
        return (self.shear_modulus * polar, self.density * polar,
                self.youngs_modulus * area, self.density * area)

    def torsion(self) -> Rod:
        """The screw in torsion: a :class:`fdjax.Rod` with Z = GJ, μ = ρJ."""
        gj, rho_j, _, _ = self._checked().section()
        return Rod(self.length, gj, rho_j, self.loss_factor, self.retardation)

    def axial(self) -> Rod:
        """The screw in axial motion: a :class:`fdjax.Rod` with Z = EA, μ = ρA."""
        _, _, ea, rho_a = self._checked().section()
        return Rod(self.length, ea, rho_a, self.loss_factor, self.retardation)


class _LineSubsystem(eqx.Module):
    """A subsystem along the screw: a line of nodes with the nut point at 0 < l < L.

    ``line(rod, l, ω)`` gives its tridiagonal dynamic stiffness (diagonal, off-diagonal) over
    the nodes of the class docstring; ``receptance(rod, l, ω)`` the entries the coupling reads.
    Both check l and ω and name the method called."""

    def line(self, rod: Rod, l, omega):
        """Tridiagonal dynamic stiffness over the subsystem's nodes, 0 < l < L (m)."""
        name = type(self).__name__
        l = _nut_point(rod, l, f"{name}.line(l=...)")
        return self._line(rod, l, _omega(omega, f"{name}.line(omega=...)"))

    def receptance(self, rod: Rod, l, omega):
        """The receptances the coupling reads (see the class docstring)."""
        name = type(self).__name__
        l = _nut_point(rod, l, f"{name}.receptance(l=...)")
        out = self._receptance(rod, l, _omega(omega, f"{name}.receptance(omega=...)"))
        return _checks.finite_tree(out, f"{name}.receptance(...)")

    def _line(self, rod: Rod, l, omega):
        raise NotImplementedError

    def _receptance(self, rod: Rod, l, omega):
        raise NotImplementedError


class Rotary(_LineSubsystem):
    """Subsystem R: motor rotor — coupling — screw in torsion, on rotational supports.

    Line of nodes: motor rotor θ1 | coupling | screw drive end θ(0) | screw | nut θ(l) | screw |
    free end θ(L).  ``receptance(shaft, l, ω)`` gives (h_11, h_1l, h_ll): motor and nut-point
    rotation per torque (rad/(N·m)).

    Attributes:
        motor_inertia: rotor inertia J_m incl. motor-side coupling hub (kg·m²).
        motor_damping: motor viscous friction (N·m·s/rad).
        coupling_stiffness, coupling_damping: torsional coupling (N·m/rad, N·m·s/rad).
        drive_end_inertia: screw-side coupling hub, bearing rings, nuts (kg·m²).
        drive_end_damping: rotational friction of the drive-end bearings (N·m·s/rad).
        free_end_inertia, free_end_damping: the same at the free (floating) end.
    """

    motor_inertia: Float[Array, ""] = _checks.positive_field("Rotary(motor_inertia=...)")
    coupling_stiffness: Float[Array, ""] = _checks.positive_field("Rotary(coupling_stiffness=...)")
    coupling_damping: Float[Array, ""] = _checks.nonnegative_field(
        "Rotary(coupling_damping=...)", default=0.0
    )
    motor_damping: Float[Array, ""] = _checks.nonnegative_field(
        "Rotary(motor_damping=...)", default=0.0
    )
    drive_end_inertia: Float[Array, ""] = _checks.nonnegative_field(
        "Rotary(drive_end_inertia=...)", default=0.0
    )
    drive_end_damping: Float[Array, ""] = _checks.nonnegative_field(
        "Rotary(drive_end_damping=...)", default=0.0
    )
    free_end_inertia: Float[Array, ""] = _checks.nonnegative_field(
        "Rotary(free_end_inertia=...)", default=0.0
    )
    free_end_damping: Float[Array, ""] = _checks.nonnegative_field(
        "Rotary(free_end_damping=...)", default=0.0
    )

    def _line(self, shaft: Rod, l, omega):
        diag, off = line_stiffness(
            shaft,
            omega,
            [jnp.zeros(()), l, shaft.length],
            [
                Support(0.0, self.drive_end_damping, self.drive_end_inertia),
                None,
                Support(0.0, self.free_end_damping, self.free_end_inertia),
            ],
        )
        kc = spring_stiffness(self.coupling_stiffness, self.coupling_damping, omega)
        w = _cplx(omega)
        motor = kc - w * w * _cplx(self.motor_inertia) + 1j * w * _cplx(self.motor_damping)
        return [motor, diag[0] + kc, *diag[1:]], [-kc, *off]

    def _receptance(self, shaft: Rod, l, omega):
        diag, off = self._line(shaft, l, omega)
        return tuple(tridiagonal_receptance(diag, off, [(0, 0), (0, 2), (2, 2)]))


class Axial(_LineSubsystem):
    """Subsystem A: the screw in axial motion on its thrust bearing(s).

    Line of nodes: drive end u(0) (thrust bearing) | screw | nut u(l) | screw | free end u(L).
    ``receptance(rod, l, ω)`` gives h_ll: the screw's axial displacement at the nut per axial
    force (m/N).

    Attributes:
        drive_end_stiffness, drive_end_damping: thrust bearing pair (N/m, N·s/m).
        free_end_stiffness, free_end_damping: free-end bearing; 0 for a floating (fixed–free)
            screw, positive for a fixed–fixed (pre-tensioned) arrangement.
        drive_end_mass: bearing inner rings, lock nut (kg).
    """

    drive_end_stiffness: Float[Array, ""] = _checks.positive_field("Axial(drive_end_stiffness=...)")
    drive_end_damping: Float[Array, ""] = _checks.nonnegative_field(
        "Axial(drive_end_damping=...)", default=0.0
    )
    free_end_stiffness: Float[Array, ""] = _checks.nonnegative_field(
        "Axial(free_end_stiffness=...)", default=0.0
    )
    free_end_damping: Float[Array, ""] = _checks.nonnegative_field(
        "Axial(free_end_damping=...)", default=0.0
    )
    drive_end_mass: Float[Array, ""] = _checks.nonnegative_field(
        "Axial(drive_end_mass=...)", default=0.0
    )

    def _line(self, rod: Rod, l, omega):
        return line_stiffness(
            rod,
            omega,
            [jnp.zeros(()), l, rod.length],
            [
                Support(self.drive_end_stiffness, self.drive_end_damping, self.drive_end_mass),
                None,
                Support(self.free_end_stiffness, self.free_end_damping, 0.0),
            ],
        )

    def _receptance(self, rod: Rod, l, omega):
        diag, off = self._line(rod, l, omega)
        return tridiagonal_receptance(diag, off, [(1, 1)])[0]


def _check_height(value, where: str) -> None:
    """A height (m) given in mm is refused with its value in metres (:data:`HIGHEST_POINT_M`)."""
    _checks.at_most(value, HIGHEST_POINT_M, where, "no point of a carriage lies farther from "
                    "its pitch centre", magnitude=True)


class Table(eqx.Module):
    r"""A second sliding body on the carriage, compliant in the drive's direction.

    On a Y axis the X table (with the workpiece) rides on the saddle on its own guideways; in Y
    it is held by the lateral stiffness of the X guideways and of the X screw's bearing.  It
    moves x_t along the drive and pitches with the saddle (its pitch inertia is part of
    :attr:`Carriage.pitch_inertia`); the connection acts at height h_t above the saddle's pitch
    centre, where the saddle moves x_c + h_t ψ, and deforms by

        δ = x_t − (x_c + h_t ψ),     force (k_t + iωc_t) δ,

    i.e. it adds ``(k_t + iωc_t) b bᵀ`` to the carriage's dynamic stiffness over (x_c, ψ, x_t)
    with ``b = (−1, −h_t, 1)``.  A table point at height h moves x = x_t + (h − h_t) ψ.

    Attributes:
        mass: m_t, the table with the workpiece (kg).
        stiffness: k_t of the connection to the saddle in the drive's direction (N/m).
        damping: c_t of the connection (N·s/m); internal: it adds nothing to the drive's
            rigid-body damping.
        height: h_t, height of the connection above the saddle's pitch centre (m).
    """

    mass: Float[Array, ""] = _checks.positive_field("Table(mass=...)")
    stiffness: Float[Array, ""] = _checks.positive_field("Table(stiffness=...)")
    damping: Float[Array, ""] = _checks.nonnegative_field("Table(damping=...)", default=0.0)
    height: Float[Array, ""] = _checks.finite_field("Table(height=...)", default=0.0)

    def __check_init__(self):
        _check_height(self.height, "Table(height=...)")


class Carriage(eqx.Module):
    r"""Subsystem S: the carriage (table) as a rigid body in axial motion x_c and pitch ψ.

    A point at height h above the pitch centre moves x = x_c + h ψ, so the receptance between
    points a and b is ``h_ab = 1/(−ω²m + iωc_x) + h_a h_b /(k_ψ − ω²J + iωc_ψ)``.

    **With a** :class:`Table` (``table=Table(...)``) the carriage is the saddle and a second
    body x_t rides on it; the nut and the linear scale stay on the saddle,
    ``x_n = x_c + h_n ψ``, ``x_2 = x_c + h_s ψ``, while the tool point and its force F3 move to
    the table, ``x_3 = x_t + (h_3 − h_t) ψ``.  Over (x_c, ψ, x_t) the dynamic stiffness is

        D = diag(−ω²m + iωc_x, k_ψ − ω²J + iωc_ψ, −ω²m_t) + (k_t + iωc_t) b bᵀ,
        b = (−1, −h_t, 1),

    and ``h_ab = a_aᵀ D⁻¹ a_b`` with ``a_n = (1, h_n, 0)``, ``a_2 = (1, h_s, 0)``,
    ``a_3 = (0, h_3 − h_t, 1)``.  :meth:`receptance` solves it in the coordinates
    (x_c, ψ, δ), δ = x_t − x_c − h_t ψ, where the connection is diagonal,

        D_δ = diag(−ω²m + iωc_x, k_ψ − ω²J + iωc_ψ, k_t + iωc_t) − ω²m_t c cᵀ,  c = (1, h_t, 1),

    (the table's inertia sees x_t = cᵀ(x_c, ψ, δ)), with the points ``a_n = (1, h_n, 0)``,
    ``a_2 = (1, h_s, 0)``, ``a_3 = (1, h_3, 1)``: a stiff table (k_t → ∞) then forms no
    difference of large numbers and tends to a carriage of mass m + m_t, mass coupling
    m_t h_t and pitch inertia J + m_t h_t².  Without a table (``table=None``) the model is the
    rigid body above, unchanged.

    Attributes:
        mass: carriage with table and workpiece (kg); the saddle alone when ``table`` is given.
        pitch_inertia: about the pitch centre (kg·m²), the table's included.
        axial_damping: equivalent viscous friction of the guideways (N·s/m).
        pitch_stiffness: k_ψ of the guideway blocks (N·m/rad) ≈ k_block · Σ (block offset)².
        pitch_damping: c_ψ (N·m·s/rad).
        nut_height, scale_height, tool_height: heights of the nut axis, the linear scale
            (coordinate 2) and the tool point (coordinate 3) above the pitch centre (m).
        table: an optional :class:`Table` on the carriage, carrying the tool point; ``None``
            (default) for a single rigid body.  Its presence is structural (static shapes).
    """

    mass: Float[Array, ""] = _checks.positive_field("Carriage(mass=...)")
    pitch_inertia: Float[Array, ""] = _checks.positive_field("Carriage(pitch_inertia=...)")
    pitch_stiffness: Float[Array, ""] = _checks.positive_field("Carriage(pitch_stiffness=...)")
    axial_damping: Float[Array, ""] = _checks.nonnegative_field(
        "Carriage(axial_damping=...)", default=0.0
    )
    pitch_damping: Float[Array, ""] = _checks.nonnegative_field(
        "Carriage(pitch_damping=...)", default=0.0
    )
    nut_height: Float[Array, ""] = _checks.finite_field("Carriage(nut_height=...)", default=0.0)
    scale_height: Float[Array, ""] = _checks.finite_field("Carriage(scale_height=...)", default=0.0)
    tool_height: Float[Array, ""] = _checks.finite_field("Carriage(tool_height=...)", default=0.0)
    table: Table | None = None

    def __check_init__(self):
        for name in ("nut_height", "scale_height", "tool_height"):
            _check_height(getattr(self, name), f"Carriage({name}=...)")
        if self.table is not None and not isinstance(self.table, Table):
            raise ValueError(
                f"`Carriage(table=...)` must be a fdjax.Table or None, got "
                f"{type(self.table).__name__}"
            )

    @property
    def heights(self) -> Float[Array, " 3"]:
        """Heights of (nut, scale, tool)."""
        return jnp.stack([self.nut_height, self.scale_height, self.tool_height])

    @property
    def n_dofs(self) -> int:
        """Rigid-body coordinates: 2 (x_c, ψ), or 3 (x_c, ψ, x_t) with a table (static)."""
        return 2 if self.table is None else 3

    def modal_stiffness(self, omega):
        """Dynamic stiffness of the axial and pitch coordinates (diagonal) of the carriage
        (the saddle alone when it carries a table)."""
        return self._modal_stiffness(_omega(omega, "Carriage.modal_stiffness(omega=...)"))

    def receptance(self, omega) -> list[list[Complex[Array, "*shape"]]]:
        """Receptance over (x_n, x_2, x_3) per axial force at those points (m/N), as entries."""
        out = self._receptance(_omega(omega, "Carriage.receptance(omega=...)"))
        return _checks.finite_tree(out, "Carriage.receptance(...)")

    def _modal_stiffness(self, omega):
        w = _cplx(omega)
        axial = -w * w * _cplx(self.mass) + 1j * w * _cplx(self.axial_damping)
        pitch = (
            _cplx(self.pitch_stiffness)
            - w * w * _cplx(self.pitch_inertia)
            + 1j * w * _cplx(self.pitch_damping)
        )
        return axial, pitch

    def _dynamic_stiffness(self, omega) -> Complex[Array, "... d d"]:
        """Dense dynamic stiffness over (x_c, ψ) or, with a table, (x_c, ψ, x_t)."""
        axial, pitch = self._modal_stiffness(omega)
        diag = [axial, pitch]
        if self.table is not None:
            diag.append(-_cplx(omega) ** 2 * _cplx(self.table.mass))
        shape = jnp.broadcast_shapes(*[jnp.shape(x) for x in diag])
        d = len(diag)
        D = jnp.zeros((*shape, d, d), jnp.complex128)
        for i, x in enumerate(diag):
            D = D.at[..., i, i].set(jnp.broadcast_to(x, shape))
        if self.table is not None:
            t = self.table
            b = _cplx(jnp.stack([-jnp.ones(()), -t.height, jnp.ones(())]))
            kt = spring_stiffness(t.stiffness, t.damping, omega)
            D = D + kt[..., None, None] * (b[:, None] * b[None, :])
        return D

    def _points(self) -> Float[Array, "3 d"]:
        """Rows ``a_n, a_2, a_3``: the displacements of the nut, the scale and the tool point
        over the carriage's coordinates (x_c, ψ) or (x_c, ψ, x_t), and the forces there."""
        one, zero = jnp.ones(()), jnp.zeros(())
        if self.table is None:
            return jnp.stack([jnp.stack([one, h]) for h in
                              (self.nut_height, self.scale_height, self.tool_height)])
        r = self.tool_height - self.table.height
        return jnp.stack([jnp.stack([one, self.nut_height, zero]),
                          jnp.stack([one, self.scale_height, zero]),
                          jnp.stack([zero, r, one])])

    def _receptance(self, omega):
        axial, pitch = self._modal_stiffness(omega)
        h = [_cplx(x) for x in (self.nut_height, self.scale_height, self.tool_height)]
        if self.table is None:
            ya, yp = recip(axial), recip(pitch)
            return [[ya + yp * (h[i] * h[j]) for j in range(3)] for i in range(3)]
        # (x_c, ψ, δ) coordinates (class docstring): the connection is diagonal, the table's
        # inertia a rank-one term; a 3×3 adjugate inverse with one division, by det D_δ.
        t = self.table
        kt = spring_stiffness(t.stiffness, t.damping, omega)
        mt = -_cplx(omega) ** 2 * _cplx(t.mass)
        ht = _cplx(t.height)
        c = [1.0, ht, 1.0]
        k = [axial, pitch, kt]
        D = [[add(k[i] if i == j else 0, mt * (c[i] * c[j])) for j in range(3)]
             for i in range(3)]
        Y = inv_entries(D)
        # points (1, h_n, 0), (1, h_s, 0), (1, h_3, 1)
        pts = [[1.0, h[0], 0], [1.0, h[1], 0], [1.0, h[2], 1.0]]

        def form(u, v):
            return add(*[mul(mul(u[p], Y[p][q]), v[q]) for p in range(3) for q in range(3)])

        return [[form(pts[i], pts[j]) for j in range(3)] for i in range(3)]


class NutJoint(eqx.Module):
    """The screw–nut joint: axial stiffness k_ja (N/m) and damping c_ja (N·s/m) (paper Eq. 1)."""

    stiffness: Float[Array, ""] = _checks.positive_field("NutJoint(stiffness=...)")
    damping: Float[Array, ""] = _checks.nonnegative_field("NutJoint(damping=...)", default=0.0)

    def dynamic_stiffness(self, omega):
        """``k_ja + iωc_ja`` at finite angular frequencies ``omega`` (rad/s)."""
        return self._dynamic_stiffness(_omega(omega, "NutJoint.dynamic_stiffness(omega=...)"))

    def _dynamic_stiffness(self, omega):
        return spring_stiffness(self.stiffness, self.damping, omega)
