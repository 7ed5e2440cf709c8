r"""The time-domain twin: a finite-element model of the drive and its truncated modal realisation.

The frequency-domain model (:mod:`fdjax._drive._model`) is exact but lives in ω.  A controller
is simulated in time, so here the same drive at one table position becomes

    M q̈ + C q̇ + K q = F u,        y = S q,        u = (T1, F3),  y = (θ1, x2, x3),

over the degrees of freedom (DOFs)

    q = (θ1, θ_0 … θ_n, u_0 … u_n, x_c, ψ)        (N = 2n + 5),

with ``x_t`` appended after ψ (N = 2n + 6) when the carriage carries a :class:`fdjax.Table`;
then a state-space realisation ``ẋ = A x + B u``, ``y = C x + D u`` of its modes below a band.

**Screw.** A uniform mesh of ``n`` linear two-node elements of length ``h = L/n`` over the whole
screw, the same for torsion (Z = GJ, μ = ρJ) and axial motion (Z = EA, μ = ρA):

    K_e = Z/h [[1, −1], [−1, 1]],   M_e = μh/6 [[2, 1], [1, 2]],   C_e = β K_e,

the last the Kelvin–Voigt part of ``Z*(ω) = Z(1 + iωβ)`` (:class:`fdjax.Rod`).  The hysteretic
loss factor η has no time-domain realisation and must be 0.

**Lumped parts**, exactly as in the frequency model (:mod:`fdjax._drive._substructures`): motor
inertia and friction on θ1, the coupling (k_c, c_c) between θ1 and θ_0, drive-end and free-end
inertias and dampers on θ_0 and θ_n, the thrust bearing (k, c, m) on u_0 and the free-end bearing
on u_n, and the carriage: mass m and guideway damping c_x on x_c, pitch inertia J, stiffness k_ψ
and damping c_ψ on ψ; a table adds its mass m_t on x_t and its connection to the saddle,
``k_t b_t b_tᵀ`` to K and ``c_t b_t b_tᵀ`` to C with ``b_t = (−1 on x_c, −h_t on ψ, +1 on x_t)``.
The tool point and F3 are ``x_c + h_3 ψ``, or ``x_t + (h_3 − h_t) ψ`` on a table.

**Nut.** The nut sits at ``l = Y_table + l0`` inside element ``k = ⌊l/h⌋`` at local coordinate
``ξ = l/h − k``.  The screw point under it moves with the element's shape functions,
``θ(l) = N₁θ_k + N₂θ_{k+1}``, ``u(l) = N₁u_k + N₂u_{k+1}`` (``N₁ = 1 − ξ``, ``N₂ = ξ``), so
the joint deformation ``Δ = x_n − u(l) − i_sc θ(l) = bᵀq`` with

    b = (−i_sc N on θ, −N on u, +1 on x_c, +h_n on ψ)

adds ``k_j bbᵀ`` to K and ``c_j bbᵀ`` to C.  ``k`` comes from integer arithmetic and N enters as
a one-hot-weighted vector, so the shapes are static and the model is differentiable in the
position and jit/vmap-able over it.

*Kink correction.*  Under the point force of the nut the exact screw displacement has a kink at
``l``, which the linear field inside the element cannot follow: interpolation alone makes the
nut point too stiff by the compliance of the element's two parts (nut point to either node,
nodes held) in parallel, ``ξ(1 − ξ) h / Z``.  That error is O(h) and dominates the O(h²) of
linear elements with consistent mass (0.6 % on the first mode at n = 16 for the reference
drive).  Splitting the element at ``l`` and condensing the new node statically gives exactly
interpolation plus this compliance in series with the joint:

    1/k_eff = 1/k_j + c_loc,     c_loc = ξ(1 − ξ) h (1/EA + i_sc²/GJ),

with the damping of the series connection expanded to first order in s,
``c_eff = k_eff² (c_j/k_j² + β c_loc)``.  It vanishes when the nut is on a node and restores
O(h²) convergence at every position (tested).  ``nut_correction=False`` gives the plain
interpolation.

**Modal truncation.**  M = LLᵀ (Cholesky), ``Ã = L⁻¹KL⁻ᵀ = ΨΛΨᵀ`` (``jnp.linalg.eigh``), mass-
normalised modes ``Φ = L⁻ᵀΨ``.  The first ``m`` modes are kept, ascending.  The first is the
rigid-body mode (motor, screw and carriage turning together, ``x_c = x_t = i_sc θ``): it is set
from its closed form, ``ψ₀ ∝ Lᵀr`` with λ₀ = 0 exactly, since eigh gives it only to ±eps·λ_max.

    q = Φ_m η,    η̈ + Ξ η̇ + Λ_m η = Φ_mᵀF u,    Ξ = Φ_mᵀ C Φ_m  (full: the damping stays
                                                                 non-proportional),

    A = [[0, I], [−Λ_m, −Ξ]],   B = [[0], [Φ_mᵀF]],   C = [S Φ_m, 0],
    D = S Φ_r Λ_r⁻¹ Φ_rᵀ F     (the static residual flexibility of the truncated modes r).

D keeps the quasi-static compliance of the truncated modes (screw axial and torsional modes
above the band), which the kept modes cannot represent: without damping it removes the
truncation error below the band to O((ω/ω_r)²).  It is computed without the truncated
eigenvectors, in the mass-normalised coordinates, as

    Ψ_r Λ_r⁻¹ Ψ_rᵀ F̃ = P (Ã + σψ₀ψ₀ᵀ)⁻¹ P F̃,    P = I − Ψ_mΨ_mᵀ,   F̃ = L⁻¹F,

(any σ > 0; the shift only makes the solve regular), which forms no difference of large
flexibilities and differentiates without the eigenvector sensitivities of nearly coincident
high modes.  Velocity outputs ``ẏ = S Φ_m η̇`` have no residual term (its derivative ``D u̇``
is not proper).  The truncated modes' damping coupling and inertia are not represented: the
error they leave grows towards the band edge, so keep modes to about twice the highest
frequency of interest (the default band).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from .. import _checks
from .._lti import transfer
from ._model import INPUTS, OUTPUTS, BallScrewDrive

__all__ = [
    "TwinOptions",
    "FEMatrices",
    "StateSpace",
    "fe_matrices",
    "state_space",
    "count_modes",
    "DEFAULT_ELEMENTS",
    "DEFAULT_BAND_HZ",
    "VELOCITY_OUTPUTS",
]

DEFAULT_ELEMENTS = 12
"""Default number of screw elements: every natural frequency of the reference drive below
2 kHz within 0.5 % of the exact one at every table position (tested; worst 0.16 % over the
travel, against 0.23 % at 10 elements and 0.35 % at 8)."""

DEFAULT_BAND_HZ = 4000.0
"""Default band of kept modes: twice the 2 kHz range of interest, so that the truncated modes
shift no resonance peak below 2 kHz by more than 0.5 % (tested)."""

VELOCITY_OUTPUTS = ("theta1_dot", "x2_dot", "x3_dot")
"""Velocity outputs of a :class:`StateSpace`: motor speed (rad/s), scale and tool velocity (m/s)."""

_TWO_PI = 2.0 * math.pi


class TwinOptions(eqx.Module):
    """How a drive becomes its time-domain twin: the mesh, the modes kept, the corrections.

    Built once and passed as ``twin=`` to every function that realises the drive in time
    (:func:`state_space`, :func:`fe_matrices`, :func:`count_modes`, :func:`fdjax.drive_modes`,
    :func:`fdjax.update_model`, :func:`fdjax.simulate` and the loop analyses).  Every field is
    static: it fixes array shapes, so a new value compiles anew, while positions and drive
    parameters stay traced.

    Attributes:
        n_elements: screw elements n, uniform over the screw length (N = 2n + 5 DOFs, 2n + 6
            with a table).  The default meets 0.5 % on every natural frequency below 2 kHz of
            the reference drive.
        kept_modes: modes kept in the state space (rigid-body mode included; the state has
            2·kept_modes entries), 1 ≤ kept_modes ≤ N.  ``None`` keeps the modes up to
            ``band_hz`` (counted over the travel with :func:`count_modes`, which needs concrete
            drive parameters: give it when the drive itself is traced).
        band_hz: the band of kept modes when ``kept_modes`` is None.
        residual: add the truncated modes' static flexibility as the feed-through D.
        nut_correction: add the screw element's local compliance ξ(1−ξ)h/Z in series with the
            nut joint, which makes the mesh convergence O(h²) at every position.
    """

    n_elements: int = eqx.field(static=True, default=DEFAULT_ELEMENTS)
    kept_modes: int | None = eqx.field(static=True, default=None)
    band_hz: float = eqx.field(static=True, default=DEFAULT_BAND_HZ)
    residual: bool = eqx.field(static=True, default=True)
    nut_correction: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        _checks.static_int(self.n_elements, "TwinOptions(n_elements=...)", 1)
        if self.kept_modes is not None:
            # N = 2·n_elements + 5 DOFs, one more with a table (checked against the drive in
            # modes_for)
            _checks.static_int(self.kept_modes, "TwinOptions(kept_modes=...)", 1,
                               2 * int(self.n_elements) + 6)
        band = _checks.concrete_float(self.band_hz, "TwinOptions(band_hz=...)")
        _checks.positive(band, "TwinOptions(band_hz=...)")
        _checks.static_bool(self.residual, "TwinOptions(residual=...)")
        _checks.static_bool(self.nut_correction, "TwinOptions(nut_correction=...)")

    def modes_for(self, drive: BallScrewDrive, fn: str = "state_space") -> int:
        """The number of kept modes for ``drive``: ``kept_modes``, or the band's count."""
        if self.kept_modes is not None:
            n_dofs = 2 * int(self.n_elements) + 3 + int(drive.carriage.n_dofs)
            if int(self.kept_modes) > n_dofs:
                raise ValueError(f"`{fn}(twin=...)` keeps {int(self.kept_modes)} modes, more than "
                                 f"the {n_dofs} DOFs of this drive's mesh "
                                 f"(n_elements={int(self.n_elements)})")
            return int(self.kept_modes)
        return _count_modes(drive, self.band_hz, int(self.n_elements), 11,
                            bool(self.nut_correction), fn)

    def resolve(self, drive: BallScrewDrive, fn: str = "state_space") -> TwinOptions:
        """The same options with ``kept_modes`` counted for ``drive`` (when it is None)."""
        if self.kept_modes is not None:
            return self
        return dataclasses.replace(self, kept_modes=self.modes_for(drive, fn))


def _twin_options(twin, fn: str) -> TwinOptions:
    if twin is None:
        return TwinOptions()
    _checks.instance(twin, TwinOptions, f"{fn}(twin=...)")
    return twin


_cplx = _checks.to_complex


# ------------------------------------------------------------------------------------ modules
class FEMatrices(eqx.Module):
    r"""The finite-element model ``M q̈ + C q̇ + K q = F u``, ``y = S q`` at one table position.

    DOFs ``q = (θ1, θ_0 … θ_n, u_0 … u_n, x_c, ψ)`` (rad, rad, m, m, rad), N = 2n + 5, and
    x_t (m) last, N = 2n + 6, when the carriage carries a :class:`fdjax.Table`.

    Attributes:
        mass: M, (N, N), symmetric positive definite.
        damping: C, (N, N), symmetric positive semi-definite.
        stiffness: K, (N, N), symmetric positive semi-definite, one rigid-body null vector.
        inputs: F, (N, 2): generalised forces per (T1, F3).
        outputs: S, (3, N): (θ1, x2, x3) from the DOFs.
    """

    mass: Float[Array, "n n"]
    damping: Float[Array, "n n"]
    stiffness: Float[Array, "n n"]
    inputs: Float[Array, "n 2"]
    outputs: Float[Array, "3 n"]

    def frf(self, freq_hz: Float[ArrayLike, " freq"]) -> Complex[Array, "freq 3 2"]:
        """Full (untruncated) receptance ``S (K + iωC − ω²M)⁻¹ F``, shape (n_freq, 3, 2)."""
        freq_hz = _checks.frequency_grid(freq_hz, "FEMatrices.frf(freq_hz=...)")
        return _checks.finite_output(_fe_frf(self, freq_hz), "FEMatrices.frf(...)")


class StateSpace(eqx.Module):
    r"""A state-space realisation ``ẋ = A x + B u``, ``y = C x + D u`` of the drive at one position.

    ``u = (T1, F3)`` (N·m, N), ``y = (θ1, x2, x3)`` (rad, m, m); the state is
    ``x = (η, η̇)`` with η the mass-normalised modal coordinates of the kept modes.
    ``C_velocity`` gives ``(θ̇1, ẋ2, ẋ3) = C_velocity x`` (no feed-through).  Shapes follow
    python-control: ``control.ss(A, B, C, D)`` accepts them as they are.

    Attributes:
        A: (2m, 2m).  B: (2m, 2).  C: (3, 2m).  D: (3, 2), the residual flexibility.
        C_velocity: (3, 2m).
        natural_freq_hz: undamped natural frequencies of the kept modes (m,), ascending; the
            first is the rigid-body mode at 0 Hz.
        position_m: the table position Y_table (m).
        screw_ratio: the drive's i_sc = lead/2π (m/rad), which turns the encoder's motor speed
            into the table's linear units (the speed loop of a controller needs it).
        outputs, inputs, velocity_outputs: names of the channels (static).
    """

    A: Float[Array, "s s"]
    B: Float[Array, "s 2"]
    C: Float[Array, "3 s"]
    D: Float[Array, "3 2"]
    C_velocity: Float[Array, "3 s"]
    natural_freq_hz: Float[Array, " m"]
    position_m: Float[Array, ""]
    screw_ratio: Float[Array, ""]
    outputs: tuple[str, ...] = eqx.field(static=True, default=OUTPUTS)
    inputs: tuple[str, ...] = eqx.field(static=True, default=INPUTS)
    velocity_outputs: tuple[str, ...] = eqx.field(static=True, default=VELOCITY_OUTPUTS)

    @property
    def kept_modes(self) -> int:
        """Number of kept modes m (the state has 2m entries)."""
        return self.natural_freq_hz.shape[-1]

    def frf(
        self, freq_hz: Float[ArrayLike, " freq"], *, velocity: bool = False
    ) -> Complex[Array, "freq 3 2"]:
        r"""Frequency response ``C (iωI − A)⁻¹ B + D`` (or ``C_velocity (iωI − A)⁻¹ B``).

        Same convention as :meth:`fdjax.BallScrewDrive.frf` at one position: outputs
        (θ1, x2, x3) per inputs (T1, F3), shape (n_freq, 3, 2).
        """
        freq_hz = _checks.frequency_grid(freq_hz, "StateSpace.frf(freq_hz=...)")
        velocity = _checks.static_bool(velocity, "StateSpace.frf(velocity=...)")
        s = 1j * _cplx(_TWO_PI * freq_hz)
        if velocity:
            out = _transfer_jit(self.A, self.B, self.C_velocity, jnp.zeros_like(self.D), s)
        else:
            out = _transfer_jit(self.A, self.B, self.C, self.D, s)
        return _checks.finite_output(out, "StateSpace.frf(...)")


# ------------------------------------------------------------------------------------ assembly
def _tridiag(n: int, diag: float, off: float) -> np.ndarray:
    """The (n + 1)×(n + 1) assembled pattern of identical two-node elements [[d, o], [o, d]]."""
    t = np.diag(np.full(n + 1, 2.0 * diag)) + off * (np.eye(n + 1, k=1) + np.eye(n + 1, k=-1))
    t[0, 0] = t[n, n] = diag
    return t


def _shape_vector(l, h, n: int):
    """Shape-function vector N (n + 1,) of the point l and its local coordinate ξ ∈ [0, 1]."""
    r = l / h
    k = jnp.clip(jnp.floor(r).astype(jnp.int32), 0, n - 1)
    xi = r - k.astype(jnp.float64)
    e = jax.nn.one_hot(k, n + 1, dtype=jnp.float64)
    e_next = jax.nn.one_hot(k + 1, n + 1, dtype=jnp.float64)
    return (1.0 - xi) * e + xi * e_next, xi


def _assemble(drive: BallScrewDrive, position_m, n: int, nut_correction: bool) -> FEMatrices:
    screw, rot, ax, car, nut = drive.screw, drive.rotary, drive.axial, drive.carriage, drive.nut
    table = car.table
    N = 2 * n + 3 + car.n_dofs
    it, ia, ic, ip = 1, n + 2, 2 * n + 3, 2 * n + 4  # first θ node, first u node, x_c, ψ
    itab = 2 * n + 5  # x_t, when there is a table
    h = screw.length / n
    # Z and μ of Screw.torsion()/Screw.axial(), without building the Rods, whose value checks
    # would be compiled again into every program.
    Z_t, mu_t, Z_a, mu_a = screw.section()
    beta = screw.retardation

    # Screw: K_e = Z/h [[1, −1], [−1, 1]], M_e = μh/6 [[2, 1], [1, 2]], as constant patterns
    # (NumPy, static) scaled by the traced coefficients: few operations, fast to compile.
    def screw_block(tors_coef, axial_coef, pattern):
        out = np.zeros((2, N, N))
        out[0, it : it + n + 1, it : it + n + 1] = pattern
        out[1, ia : ia + n + 1, ia : ia + n + 1] = pattern
        return tors_coef * out[0] + axial_coef * out[1]

    K = screw_block(Z_t / h, Z_a / h, _tridiag(n, 1.0, -1.0))
    M = screw_block(mu_t * h / 6, mu_a * h / 6, _tridiag(n, 2.0, 1.0))
    C = beta * K

    def lumped(entries):
        """Σ value · pattern over (value, [(i, j, sign), ...]) entries."""
        values = jnp.stack([jnp.asarray(v, jnp.float64) for v, _ in entries])
        pattern = np.zeros((len(entries), N, N))
        for k, (_, where) in enumerate(entries):
            for i, j, sign in where:
                pattern[k, i, j] += sign
        return jnp.tensordot(values, pattern, axes=1)

    def spring(i, j):
        return [(i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)]

    def at(i):
        return [(i, i, 1.0)]

    # Rotary: motor, coupling, drive-end (θ_0) and free-end (θ_n) hubs; axial: thrust bearing on
    # u_0, free-end bearing on u_n; carriage: rigid body (x_c, ψ) on the guideways (and the
    # table's mass on x_t).
    masses = [
        (rot.motor_inertia, at(0)), (rot.drive_end_inertia, at(it)),
        (rot.free_end_inertia, at(it + n)), (ax.drive_end_mass, at(ia)),
        (car.mass, at(ic)), (car.pitch_inertia, at(ip)),
    ]
    if table is not None:
        masses.append((table.mass, at(itab)))
    M = M + lumped(masses)
    C = C + lumped([
        (rot.motor_damping, at(0)), (rot.coupling_damping, spring(0, it)),
        (rot.drive_end_damping, at(it)), (rot.free_end_damping, at(it + n)),
        (ax.drive_end_damping, at(ia)), (ax.free_end_damping, at(ia + n)),
        (car.axial_damping, at(ic)), (car.pitch_damping, at(ip)),
    ])
    K = K + lumped([
        (rot.coupling_stiffness, spring(0, it)), (ax.drive_end_stiffness, at(ia)),
        (ax.free_end_stiffness, at(ia + n)), (car.pitch_stiffness, at(ip)),
    ])

    # Nut joint at l, by the element's shape functions.
    l = jnp.asarray(position_m, jnp.float64) + drive.nut_offset
    shape, xi = _shape_vector(l, h, n)
    b = jnp.concatenate([
        jnp.zeros(1, jnp.float64), -screw.ratio * shape, -shape,
        jnp.stack([jnp.ones((), jnp.float64), car.nut_height]),
    ])
    kj, cj = nut.stiffness, nut.damping
    if nut_correction:
        c_loc = xi * (1.0 - xi) * h * (1.0 / Z_a + screw.ratio**2 / Z_t)
        k_eff = 1.0 / (1.0 / kj + c_loc)
        cj = k_eff**2 * (cj / kj**2 + beta * c_loc)
        kj = k_eff
    if table is not None:
        b = jnp.concatenate([b, jnp.zeros(1, jnp.float64)])
    bb = b[:, None] * b[None, :]
    K = K + kj * bb
    C = C + cj * bb

    e = np.eye(N)
    if table is None:
        tool = e[ic] + car.tool_height * e[ip]
    else:
        # The table's connection to the saddle, δ = x_t − x_c − h_t ψ = b_tᵀq; the tool point
        # (and F3) on the table, x_3 = x_t + (h_3 − h_t) ψ.
        bt = (e[itab] - e[ic]) - table.height * e[ip]
        btbt = bt[:, None] * bt[None, :]
        K = K + table.stiffness * btbt
        C = C + table.damping * btbt
        tool = e[itab] + (car.tool_height - table.height) * e[ip]
    F = jnp.stack([e[0], tool], -1)
    S = jnp.stack([e[0], e[ic] + car.scale_height * e[ip], tool])
    return FEMatrices(mass=M, damping=C, stiffness=K, inputs=F, outputs=S)


def _rigid_mode(drive: BallScrewDrive, n: int):
    """The null vector of K: everything turns together, the carriage (and its table, x_t last)
    follows at i_sc, u = ψ = 0."""
    N = 2 * n + 3 + drive.carriage.n_dofs
    r = jnp.zeros(N, jnp.float64).at[: n + 2].set(1.0)
    r = r.at[2 * n + 3].set(drive.screw.ratio)
    if drive.carriage.table is not None:
        r = r.at[2 * n + 5].set(drive.screw.ratio)
    return r


def _safe_sqrt(x):
    """√x for x ≥ 0 with a finite derivative (0) at the rigid-body mode's x = 0."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _generalised_eigh(fe: FEMatrices):
    """Mass-normalised ``(λ, Ψ, L)`` with ``L⁻¹KL⁻ᵀ = ΨΛΨᵀ``, ``M = LLᵀ``."""
    L = jnp.linalg.cholesky(fe.mass)
    X = jsl.solve_triangular(L, fe.stiffness, lower=True)
    At = jsl.solve_triangular(L, X.T, lower=True)
    At = 0.5 * (At + At.T)
    lam, Psi = jnp.linalg.eigh(At)
    return lam, Psi, L, At


def _realise(drive, position_m, n: int, n_modes: int, residual: bool, nut_correction: bool):
    fe = _assemble(drive, position_m, n, nut_correction)
    lam, Psi, L, At = _generalised_eigh(fe)
    m = n_modes
    # The lowest mode is the rigid-body rotation, known exactly: eigh returns it only to
    # round-off (λ₀ ≈ ±eps·λ_max, which would leave A a spurious slow pole), so set it exactly.
    psi0 = L.T @ _rigid_mode(drive, n)
    psi0 = psi0 / jnp.linalg.norm(psi0)
    lam_m = jnp.concatenate([jnp.zeros(1, jnp.float64), lam[1:m]])
    Psi_m = Psi[:, :m].at[:, 0].set(psi0)
    Phi = jsl.solve_triangular(L.T, Psi_m, lower=False)
    Xi = Phi.T @ fe.damping @ Phi
    Xi = 0.5 * (Xi + Xi.T)
    N = fe.mass.shape[0]
    if residual and m < N:
        # Residual flexibility Ψ_rΛ_r⁻¹Ψ_rᵀ of the truncated modes in mass-normalised
        # coordinates: project the kept modes out of the load, solve with the rigid-body mode
        # shifted to σ (any σ > 0: it is projected out), project again.  No difference of large
        # flexibilities is formed, so D is accurate to round-off relative to itself.
        sigma = jax.lax.stop_gradient(lam[m])
        Ft = jsl.solve_triangular(L, fe.inputs, lower=True)
        St = jsl.solve_triangular(L, fe.outputs.T, lower=True)  # (L⁻¹Sᵀ): S L⁻ᵀ = St.T
        Ft = Ft - Psi_m @ (Psi_m.T @ Ft)
        G = jnp.linalg.solve(At + sigma * psi0[:, None] * psi0[None, :], Ft)
        G = G - Psi_m @ (Psi_m.T @ G)
        D = St.T @ G
    else:
        D = jnp.zeros((3, 2), jnp.float64)
    return _second_order(jnp.diag(lam_m), Xi, Phi.T @ fe.inputs, fe.outputs @ Phi, D,
                         _safe_sqrt(lam_m) / _TWO_PI, position_m, drive.screw.ratio)


def _second_order(K, C, F, S, D, natural_freq_hz, position_m, screw_ratio) -> StateSpace:
    """The state space of ``η̈ + C η̇ + K η = F u``, ``y = S η + D u`` (unit mass), x = (η, η̇)."""
    m = K.shape[0]
    zero, eye = jnp.zeros((m, m), jnp.float64), jnp.eye(m, dtype=jnp.float64)
    return StateSpace(
        A=jnp.block([[zero, eye], [-K, -C]]),
        B=jnp.concatenate([jnp.zeros_like(F), F], axis=0),
        C=jnp.concatenate([S, jnp.zeros_like(S)], axis=1),
        D=D,
        C_velocity=jnp.concatenate([jnp.zeros_like(S), S], axis=1),
        natural_freq_hz=natural_freq_hz,
        position_m=jnp.asarray(position_m, jnp.float64),
        screw_ratio=jnp.asarray(screw_ratio, jnp.float64),
    )


_realise_jit = eqx.filter_jit(_realise)
_assemble_jit = eqx.filter_jit(_assemble)


@eqx.filter_jit
def _natural_freqs(drive, positions, n: int, nut_correction: bool):
    def one(p):
        lam = _generalised_eigh(_assemble(drive, p, n, nut_correction))[0]
        return jnp.sqrt(jnp.maximum(lam, 0.0)) / _TWO_PI

    return jax.vmap(one)(positions)


@eqx.filter_jit
def _fe_frf(fe: FEMatrices, freq_hz):
    w = _cplx(_TWO_PI * freq_hz)[:, None, None]
    Dyn = _cplx(fe.stiffness) + 1j * w * _cplx(fe.damping) - w * w * _cplx(fe.mass)
    X = jnp.linalg.solve(Dyn, jnp.broadcast_to(_cplx(fe.inputs), Dyn.shape[:1] + fe.inputs.shape))
    return _cplx(fe.outputs) @ X


_transfer_jit = eqx.filter_jit(transfer)


# ------------------------------------------------------------------------------------ checks
def _check_inputs(drive: BallScrewDrive, position_m, fn: str) -> tuple[BallScrewDrive, Array]:
    """Validate the position (real scalar, inside the travel) and η = 0; return both, guarded.

    The position comes back as a float64 array, so a Python float reaches the jitted
    assembly as a traced argument (a static one would compile once per value)."""
    drive = _check_time_domain(drive, fn)
    pos = _checks.real_array(position_m, f"{fn}(position_m=...)")
    if pos.ndim != 0:
        raise ValueError(
            f"`{fn}(position_m=...)` must be a scalar (use jax.vmap over positions), "
            f"got shape {pos.shape}"
        )
    return drive, drive._check_travel(pos, fn)


def _check_time_domain(drive: BallScrewDrive, fn: str) -> BallScrewDrive:
    """A drive with a time-domain realisation: the screw's loss factor η must be 0 (and its
    bore narrower than the screw, ``Screw._checked``, checked where the FE model is built
    from the section directly)."""
    if not isinstance(drive, BallScrewDrive):
        raise ValueError(f"`{fn}(drive=...)` must be a BallScrewDrive, got {type(drive).__name__}")
    drive = eqx.tree_at(lambda d: d.screw, drive, drive.screw._checked())
    eta = drive.screw.loss_factor
    expected = (
        "0 for a time-domain model (hysteretic damping has no state-space realisation; use "
        "`Screw(retardation=...)` for material damping)"
    )
    if _checks.is_concrete(eta):
        _checks.check(eta, lambda v: v == 0, "Screw(loss_factor=...)", expected)
        return drive
    # η itself enters no FE matrix: guard the screw length, which enters all of them, so the
    # check survives jit's dead-code elimination.
    length = eqx.error_if(
        drive.screw.length, eta != 0, f"`Screw(loss_factor=...)` must be {expected}"
    )
    return eqx.tree_at(lambda d: d.screw.length, drive, length)


def _is_concrete_tree(tree) -> bool:
    return all(_checks.is_concrete(x) for x in jax.tree_util.tree_leaves(tree))


# ------------------------------------------------------------------------------------ public
def fe_matrices(
    drive: BallScrewDrive,
    position_m: Float[ArrayLike, ""],
    *,
    twin: TwinOptions | None = None,
) -> FEMatrices:
    r"""The drive's finite-element matrices (M, C, K, F, S) at one table position.

    ``M q̈ + C q̇ + K q = F (T1, F3)``, ``(θ1, x2, x3) = S q``; see the module docstring for the
    DOFs, the elements, the nut interpolation and its kink correction.

    Args:
        drive: the drive (its screw must have ``loss_factor = 0``).
        position_m: table position Y_table (m) inside ``drive.travel_m``, a scalar.
        twin: the mesh (``n_elements``) and ``nut_correction`` (:class:`TwinOptions`).
    """
    twin = _twin_options(twin, "fe_matrices")
    drive, pos = _check_inputs(drive, position_m, "fe_matrices")
    fe = _assemble_jit(drive, pos, int(twin.n_elements), bool(twin.nut_correction))
    return _checks.finite_tree(fe, "fe_matrices")


def count_modes(
    drive: BallScrewDrive,
    band_hz: float | None = None,
    *,
    twin: TwinOptions | None = None,
    n_positions: int = 11,
) -> int:
    """Number of FE modes (rigid-body mode included) with natural frequency ≤ ``band_hz``.

    The largest count over ``n_positions`` table positions evenly spread over the travel, so
    that one static ``kept_modes`` serves every position (and ``jax.vmap`` over positions).
    ``band_hz`` defaults to ``twin.band_hz``.  Needs concrete drive parameters (not inside
    ``grad``/``vmap`` over the drive).
    """
    if not isinstance(drive, BallScrewDrive):
        raise ValueError(
            f"`count_modes(drive=...)` must be a BallScrewDrive, got {type(drive).__name__}"
        )
    twin = _twin_options(twin, "count_modes")
    n_positions = _checks.static_int(n_positions, "count_modes(n_positions=...)", 1)
    band = twin.band_hz if band_hz is None else band_hz
    return _count_modes(drive, band, int(twin.n_elements), n_positions,
                        bool(twin.nut_correction), "count_modes")


def _count_modes(drive, band_hz, n: int, n_positions: int, nut_correction: bool, fn: str) -> int:
    band = _checks.concrete_float(band_hz, f"{fn}(band_hz=...)")
    _checks.positive(band, f"{fn}(band_hz=...)")
    hint = (
        "give the number of kept modes, `twin=fdjax.TwinOptions(kept_modes=...)` (the state "
        "size is static), counted once outside with `fdjax.count_modes(drive)`"
    )
    if not _is_concrete_tree(drive):
        raise ValueError(
            f"`{fn}(drive=...)` needs concrete drive parameters to count modes; "
            f"inside jit/grad/vmap over the drive {hint}"
        )
    lo, hi = drive.travel_m
    # a concrete drive inside a `jax.jit` trace (the drive closed over, the position traced):
    # the count is computed now, as outside, not staged into the trace
    with jax.ensure_compile_time_eval():
        positions = drive._check_travel(jnp.linspace(lo, hi, n_positions), fn)
        f = _natural_freqs(drive, positions, n, nut_correction)
    if not _checks.is_concrete(f):
        raise ValueError(f"`{fn}(...)` cannot count modes inside `jax.jit`: {hint}")
    counts = np.sum(np.asarray(f) <= band, axis=-1)
    return int(max(1, counts.max()))


def state_space(
    drive: BallScrewDrive,
    position_m: Float[ArrayLike, ""],
    *,
    twin: TwinOptions | None = None,
) -> StateSpace:
    r"""State-space realisation of the drive at one table position (the time-domain twin).

    The finite-element model of :func:`fe_matrices`, reduced to its lowest ``kept_modes``
    undamped modes (rigid-body mode included) with the full modal damping matrix and, with
    ``residual=True``, the static residual flexibility of the truncated modes as D:

        A = [[0, I], [−Λ, −ΦᵀCΦ]],  B = [[0], [ΦᵀF]],  C = [SΦ, 0],  D = S Φ_r Λ_r⁻¹ Φ_rᵀ F,

    so ``C (iωI − A)⁻¹ B + D`` approximates ``drive.frf(position_m, f)[0]`` (paper Eq. 2)
    over the band.  Differentiable in the position and every drive parameter; ``jax.jit``
    and ``jax.vmap`` over positions compile once.

    Args:
        drive: the drive; its screw must have ``loss_factor = 0`` (use ``retardation``).
        position_m: table position Y_table (m) inside ``drive.travel_m``, a scalar.
        twin: the mesh, the kept modes (by default those below 4 kHz over the travel) and the
            corrections (:class:`TwinOptions`).  Give ``kept_modes`` when the drive itself is
            traced (grad over its parameters).

    Returns:
        A :class:`StateSpace` with 2·kept_modes states.
    """
    twin = _twin_options(twin, "state_space")
    drive, pos = _check_inputs(drive, position_m, "state_space")
    m = twin.modes_for(drive, "state_space")
    ss = _realise_jit(drive, pos, int(twin.n_elements), m, bool(twin.residual),
                      bool(twin.nut_correction))
    # a drive with non-physical values says so here: eagerly, or under jit by an error_if
    A, B, C, D = _checks.finite_tree([ss.A, ss.B, ss.C, ss.D], "state_space")
    return eqx.tree_at(lambda s: (s.A, s.B, s.C, s.D), ss, (A, B, C, D))
