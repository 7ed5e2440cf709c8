r"""Continuous rods and shafts: exact dynamic stiffness from the wave solution.

A uniform rod in axial motion (stiffness ``EA``, inertia ``ρA`` per length) and a uniform shaft in
torsion (``GJ``, ``ρJ``) obey the same wave equation ``Z* u'' = μ ü``.  With the complex modulus

    Z*(ω) = Z (1 + iη + iωβ)

(``η`` a hysteretic loss factor, ``β`` a Kelvin–Voigt retardation time, the material damping that
a time-domain model can realise) the wavenumber is ``κ = ω √(μ / Z*)`` and a segment of length ``a``
between nodes (0, a) has the exact dynamic stiffness

    D_seg = κ Z* / sin(κa) · [[cos κa, −1], [−1, cos κa]].

Segments, lumped springs and grounded supports strung along a line give a tridiagonal dynamic
stiffness, whose receptances at chosen nodes come from left/right Schur complements (a Thomas
elimination written elementwise, so large position × frequency grids fuse into one XLA loop).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from .. import _checks
from .._linalg import recip

__all__ = ["Rod", "Support", "rod_receptance"]


_scalar = _checks.to_float
_cplx = _checks.to_complex


def _omega(omega, where: str) -> Array:
    """Angular frequencies (rad/s, real or complex, any shape) that must be finite."""
    return _checks.finite(jnp.asarray(omega), where)


class Rod(eqx.Module):
    r"""A uniform rod (axial) or shaft (torsion), described by the 1-D wave equation.

    Attributes:
        length: length L (m).
        stiffness: axial stiffness EA (N) or torsional stiffness GJ (N·m²/rad).
        inertia: mass per length ρA (kg/m) or polar inertia per length ρJ (kg·m).
        loss_factor: hysteretic loss factor η (–), frequency-domain only.
        retardation: Kelvin–Voigt retardation time β (s): modal damping ratio ≈ βω/2.
    """

    length: Float[Array, ""] = _checks.positive_field("Rod(length=...)")
    stiffness: Float[Array, ""] = _checks.positive_field("Rod(stiffness=...)")
    inertia: Float[Array, ""] = _checks.positive_field("Rod(inertia=...)")
    loss_factor: Float[Array, ""] = _checks.nonnegative_field("Rod(loss_factor=...)", default=0.0)
    retardation: Float[Array, ""] = _checks.nonnegative_field("Rod(retardation=...)", default=0.0)

    def __check_init__(self):
        # a length in metres: a concrete value beyond any feed drive's was given in mm
        _checks.at_most(self.length, _checks.LONGEST_TRAVEL_M, "Rod(length=...)",
                        "no ball screw is longer")

    @classmethod
    def axial(
        cls,
        *,
        diameter: Float[ArrayLike, ""],
        length: Float[ArrayLike, ""],
        youngs_modulus: Float[ArrayLike, ""] = 2.06e11,
        density: Float[ArrayLike, ""] = 7850.0,
        loss_factor: Float[ArrayLike, ""] = 0.0,
        retardation: Float[ArrayLike, ""] = 0.0,
    ) -> Rod:
        """Solid circular rod in axial motion: ``EA = E πd²/4``, ``ρA = ρ πd²/4``.

        ``diameter`` d and ``length`` in m, ``youngs_modulus`` E in Pa, ``density`` ρ in
        kg/m³ (steel by default), ``loss_factor`` and ``retardation`` (s) as :class:`Rod`'s."""
        return cls._solid("axial", 2, diameter, length, ("youngs_modulus", youngs_modulus),
                          density, loss_factor, retardation)

    @classmethod
    def torsion(
        cls,
        *,
        diameter: Float[ArrayLike, ""],
        length: Float[ArrayLike, ""],
        shear_modulus: Float[ArrayLike, ""] = 7.93e10,
        density: Float[ArrayLike, ""] = 7850.0,
        loss_factor: Float[ArrayLike, ""] = 0.0,
        retardation: Float[ArrayLike, ""] = 0.0,
    ) -> Rod:
        """Solid circular shaft in torsion: ``GJ = G πd⁴/32``, ``ρJ = ρ πd⁴/32``.

        ``diameter`` d and ``length`` in m, ``shear_modulus`` G in Pa, ``density`` ρ in
        kg/m³ (steel by default), ``loss_factor`` and ``retardation`` (s) as :class:`Rod`'s."""
        return cls._solid("torsion", 4, diameter, length, ("shear_modulus", shear_modulus),
                          density, loss_factor, retardation)

    @classmethod
    def _solid(cls, kind, power, diameter, length, modulus, density, loss_factor, retardation):
        """The rod of a solid circular section: the area (power 2, πd²/4) or the polar moment
        (power 4, πd⁴/32) times the modulus and the density; each argument checked under the
        name the user passed it by."""
        where = f"Rod.{kind}({{}}=...)"
        name, value = modulus
        d = _checks.at_most(_checks.positive(_scalar(diameter), where.format("diameter")),
                            _checks.LARGEST_SCREW_DIAMETER_M, where.format("diameter"),
                            "no ball screw is thicker")
        section = jnp.pi * d**power / (4 if power == 2 else 32)
        length = _checks.at_most(_checks.positive(_scalar(length), where.format("length")),
                                 _checks.LONGEST_TRAVEL_M, where.format("length"),
                                 "no ball screw is longer")
        modulus = _checks.material(_checks.positive(_scalar(value), where.format(name)),
                                   "modulus", where.format(name))
        density = _checks.material(_checks.positive(_scalar(density), where.format("density")),
                                   "density", where.format("density"))
        return cls(length, modulus * section, density * section,
                   _checks.nonnegative(_scalar(loss_factor), where.format("loss_factor")),
                   _checks.nonnegative(_scalar(retardation), where.format("retardation")))

    @property
    def wave_speed(self) -> Float[Array, ""]:
        """Undamped wave speed ``c = √(Z/μ)`` (m/s)."""
        return jnp.sqrt(self.stiffness / self.inertia)

    def complex_stiffness(self, omega) -> Complex[Array, "*shape"]:
        """``Z*(ω) = Z (1 + iη + iωβ)`` at finite angular frequencies ``omega`` (rad/s)."""
        return self._complex_stiffness(_omega(omega, "Rod.complex_stiffness(omega=...)"))

    def impedance(self, omega) -> tuple[Complex[Array, "*shape"], Complex[Array, "*shape"]]:
        """``(κZ*, κ)``: wave impedance ``κZ* = ω√(μZ*)`` and wavenumber ``κ = ω√(μ/Z*)``."""
        return self._impedance(_omega(omega, "Rod.impedance(omega=...)"))

    def segment_stiffness(
        self, omega, length
    ) -> tuple[Complex[Array, "*shape"], Complex[Array, "*shape"]]:
        """Diagonal and off-diagonal entries of ``D_seg`` for a segment of the given length.

        ``d = κZ* cot(κa)``, ``e = −κZ*/sin(κa)``; ``length`` a > 0 (m).
        """
        kz, k = self._impedance(_omega(omega, "Rod.segment_stiffness(omega=...)"))
        a = _checks.positive(
            _checks.real_array(length, "Rod.segment_stiffness(length=...)"),
            "Rod.segment_stiffness(length=...)",
        )
        return _segment(kz, jnp.exp(1j * k * _cplx(a)))

    # Unchecked forms for the hot paths (line_stiffness and the drive), whose inputs are
    # validated once at the public entry point.
    def _complex_stiffness(self, omega):
        w = _cplx(omega)
        return _cplx(self.stiffness) * (
            1 + 1j * (_cplx(self.loss_factor) + w * _cplx(self.retardation))
        )

    def _impedance(self, omega):
        w = _cplx(omega)
        zs = self._complex_stiffness(omega)
        mu = _cplx(self.inertia)
        return w * jnp.sqrt(mu * zs), w * jnp.sqrt(mu / zs)

    def frf(
        self,
        freq_hz: Float[ArrayLike, " freq"],
        points_m: Float[ArrayLike, " p"],
        left: Support | None = None,
        right: Support | None = None,
    ) -> Complex[Array, "freq p p"]:
        """Receptance matrix between points along the rod (see :func:`rod_receptance`)."""
        freq_hz = _checks.frequency_grid(freq_hz, "Rod.frf(freq_hz=...)")
        _check_supports(left, right, "Rod.frf")
        points = _check_points(self, points_m, "Rod.frf")
        out = _rod_receptance(self, 2 * jnp.pi * freq_hz, points, left, right)
        return _checks.finite_output(out, "Rod.frf(...)")


class Support(eqx.Module):
    """A lumped attachment at a node: spring and damper to ground plus a lumped mass/inertia.

    Dynamic stiffness ``k + iωc − ω²m``. All zero (the default) is a free end.

    Attributes:
        stiffness: N/m (axial) or N·m/rad (torsion).
        damping: N·s/m or N·m·s/rad.
        mass: kg or kg·m².
    """

    stiffness: Float[Array, ""] = _checks.nonnegative_field("Support(stiffness=...)", default=0.0)
    damping: Float[Array, ""] = _checks.nonnegative_field("Support(damping=...)", default=0.0)
    mass: Float[Array, ""] = _checks.nonnegative_field("Support(mass=...)", default=0.0)

    def dynamic_stiffness(self, omega) -> Complex[Array, "*shape"]:
        """``k + iωc − ω²m`` at finite angular frequencies ``omega`` (rad/s)."""
        return self._dynamic_stiffness(_omega(omega, "Support.dynamic_stiffness(omega=...)"))

    def _dynamic_stiffness(self, omega):
        w = _cplx(omega)
        return _cplx(self.stiffness) + 1j * w * _cplx(self.damping) - w * w * _cplx(self.mass)


def _segment(kz, phase):
    """Segment entries from the phase factor ``E = e^{iκa}``.

    cot(κa) = i(E² + 1)/(E² − 1) and 1/sin(κa) = 2iE/(E² − 1): one complex exponential per
    segment instead of a complex sine and cosine.
    """
    e2 = phase * phase
    den = recip(e2 - 1.0)
    return 1j * kz * (e2 + 1.0) * den, -2j * kz * phase * den


def spring_stiffness(stiffness, damping, omega) -> Complex[Array, "*shape"]:
    """Dynamic stiffness ``k + iωc`` of a massless spring–damper element between two nodes."""
    return _cplx(stiffness) + 1j * _cplx(omega) * _cplx(damping)


def tridiagonal_receptance(
    diag: Sequence[Complex[Array, "*shape"]],
    off: Sequence[Complex[Array, "*shape"]],
    pairs: Sequence[tuple[int, int]],
) -> list[Complex[Array, "*shape"]]:
    r"""Entries ``(D⁻¹)_ij`` of a symmetric tridiagonal dynamic stiffness, elementwise.

    With left Schur complements ``a_0 = d_0``, ``a_i = d_i − e_{i−1}²/a_{i−1}`` and right ones
    ``b_{n−1} = d_{n−1}``, ``b_i = d_i − e_i²/b_{i+1}``:

        (D⁻¹)_ii = 1 / (a_i + b_i − d_i),   (D⁻¹)_ij = (D⁻¹)_jj Π_{k=i}^{j−1} (−e_k / a_k)  (i < j).

    ``diag`` has n arrays, ``off`` n−1 (all broadcast against each other).
    """
    n = len(diag)
    a = [diag[0]]
    for i in range(1, n):
        a.append(diag[i] - off[i - 1] ** 2 * recip(a[i - 1]))
    b = [None] * n
    b[n - 1] = diag[n - 1]
    for i in range(n - 2, -1, -1):
        b[i] = diag[i] - off[i] ** 2 * recip(b[i + 1])
    out = []
    for i, j in pairs:
        i, j = min(i, j), max(i, j)
        h = recip(a[j] + b[j] - diag[j])
        for k in range(i, j):
            h = h * (-off[k] * recip(a[k]))
        out.append(h)
    return out


def line_stiffness(
    rod: Rod,
    omega,
    nodes_m: Sequence,
    supports: Sequence[Support | None],
) -> tuple[list, list]:
    """Tridiagonal dynamic stiffness of a rod split at nodes ``0 = x_0 < x_1 < … < x_{n−1} = L``.

    ``nodes_m[0]`` is taken as 0 and ``nodes_m[-1]`` as ``rod.length``; ``supports[i]`` (or
    ``None``) is attached at node i.  Returns the diagonal and off-diagonal lists.  The segment
    phase factors are ratios ``e^{iκx_{i+1}}/e^{iκx_i}``, so each interior node costs one complex
    exponential and the end nodes depend on frequency only.
    """
    n = len(nodes_m)
    kz, k = rod._impedance(omega)
    phases = [jnp.ones((), jnp.complex128)]
    phases += [jnp.exp(1j * k * _cplx(x)) for x in nodes_m[1:-1]]
    phases.append(jnp.exp(1j * k * _cplx(rod.length)))
    diag = [jnp.zeros((), jnp.complex128) for _ in range(n)]
    off = []
    for i in range(n - 1):
        seg = phases[i + 1] if i == 0 else phases[i + 1] * recip(phases[i])
        d, e = _segment(kz, seg)
        diag[i] = diag[i] + d
        diag[i + 1] = diag[i + 1] + d
        off.append(e)
    for i, s in enumerate(supports):
        if s is not None:
            diag[i] = diag[i] + s._dynamic_stiffness(omega)
    return diag, off


def rod_receptance(
    rod: Rod,
    omega: Float[ArrayLike, " freq"],
    points_m: Float[ArrayLike, " p"],
    left: Support | None = None,
    right: Support | None = None,
) -> Complex[Array, "freq p p"]:
    r"""Exact receptance between points of a rod with end supports.

    The rod is split at the (strictly interior or end) points; the node set is
    ``{0, points, L}``. Free–free with no supports is singular at ω → 0 (rigid-body motion).

    Closed-form checks (tested): a fixed–free rod resonates at ``(2r−1)c/4L``, a free–free rod at
    ``rc/2L``, and a rod with a tip mass m_tip satisfies ``βL tan βL = m_rod/m_tip``.

    ``omega`` (rad/s) must be real and finite, shape ``(freq,)``; the points must lie in
    ``[0, L]`` and, when they are traced (inside ``jit``/``vmap``/``grad``, where they cannot be
    sorted and merged in Python), be strictly increasing and strictly inside ``(0, L)``.
    """
    _checks.instance(rod, Rod, "rod_receptance(rod=...)")
    _check_supports(left, right, "rod_receptance")
    where = "rod_receptance(omega=...)"
    omega = _checks.finite(_checks.real_array(omega, where), where)
    if omega.ndim != 1:
        raise ValueError(f"`{where}` must be 1-D, got shape {omega.shape}")
    points = _check_points(rod, points_m, "rod_receptance")
    out = _rod_receptance(rod, omega, points, left, right)
    return _checks.finite_output(out, "rod_receptance(...)")


def _check_supports(left, right, fn: str) -> None:
    """The end supports: each an :class:`Support` or None (free)."""
    for name, s in (("left", left), ("right", right)):
        if s is not None:
            _checks.instance(s, Support, f"{fn}({name}=...)", "an fdjax.Support or None (free)")


def _check_points(rod: Rod, points_m, fn: str) -> Array:
    """Points along the rod: real, scalar or 1-D, in [0, L]; traced, also strictly increasing
    and interior (the traced path of ``_rod_receptance`` makes one segment per gap)."""
    where = f"{fn}(points_m=...)"
    points = jnp.atleast_1d(_checks.real_array(points_m, where))
    if points.ndim != 1:
        raise ValueError(f"`{where}` must be a scalar or 1-D, got shape {points.shape}")
    L = rod.length
    expected = "within [0, L] m, L = Rod(length=...)"
    if _checks.is_concrete(points) and _checks.is_concrete(L):
        Ln = float(L)  # a NumPy scalar: a jax array would be staged into an enclosing trace
        return _checks.check(points, lambda p: (p >= 0) & (p <= Ln), where,
                             f"within [0, {Ln:.6g}] m")
    inside = (points >= 0) & (points <= L)
    points = eqx.error_if(points, ~jnp.all(inside), f"`{where}` must be {expected}")
    gaps = jnp.diff(jnp.concatenate([jnp.zeros(1), points, jnp.atleast_1d(L)]))
    return eqx.error_if(
        points,
        ~jnp.all(gaps > 0),
        f"`{where}` must be strictly increasing and strictly inside (0, L) when traced "
        "(under jit/vmap/grad; concrete points may repeat, be unsorted or sit on the ends)",
    )


def _rod_receptance(rod, omega, points_m, left=None, right=None):
    """The unchecked core of :func:`rod_receptance`."""
    omega = jnp.asarray(omega, jnp.float64)[:, None]
    pts = jnp.atleast_1d(jnp.asarray(points_m, jnp.float64))
    p = pts.shape[0]
    if _checks.is_concrete(pts) and _checks.is_concrete(rod.length):
        # Concrete points: sort, merge duplicates, and map points on the ends to the end nodes.
        L = float(rod.length)
        pn = np.asarray(pts)
        interior = sorted({float(x) for x in pn if 0.0 < x < L})
        xs = [jnp.zeros(()), *[pts[int(np.flatnonzero(pn == x)[0])] for x in interior], rod.length]
        last = len(xs) - 1
        idx = {
            i: 0 if pn[i] <= 0.0 else last if pn[i] >= L else 1 + interior.index(float(pn[i]))
            for i in range(p)
        }
    else:
        # Traced points: taken as strictly increasing interior points (no zero-length segment).
        xs = [jnp.zeros(()), *[pts[i] for i in range(p)], rod.length]
        last = len(xs) - 1
        idx = {i: i + 1 for i in range(p)}
    supports = [None] * len(xs)
    supports[0] = left
    supports[last] = right
    diag, off = line_stiffness(rod, omega, xs, supports)
    pairs = [(idx[i], idx[j]) for i in range(p) for j in range(p)]
    flat = tridiagonal_receptance(diag, off, pairs)
    return jnp.stack(flat, -1).reshape(omega.shape[0], p, p)
