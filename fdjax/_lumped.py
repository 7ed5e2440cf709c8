"""Lumped mass–damping–stiffness models and the paper's three-mass two-spring example (Sec. 2)."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from . import _checks
from ._linalg import entries, inv_entries, small_inv

__all__ = ["LumpedModel", "chain_model", "three_mass"]

_SYMMETRY_RTOL = 1e-12
"""Largest max|A − Aᵀ| accepted, relative to max|A|: assembled or transformed matrices (TᵀMT)
are symmetric to round-off, a few ulps of their largest entry (not of each entry: a small
off-diagonal entry of a transformed matrix can differ from its mirror by 3e-12 of itself)."""

_PSD_RTOL = 1e-9
"""Most negative eigenvalue of K or C accepted, relative to the largest |eigenvalue|: a free
structure's rigid-body eigenvalue of 0 comes out within a few ulps of the largest."""


def _matrix_field(name: str):
    """A float64 matrix field whose converter checks it is finite, so that the guarded value is
    the stored leaf (the check survives jit, unlike one in __check_init__)."""
    where = f"LumpedModel({name}=...)"

    def convert(x):
        return _checks.finite(_checks.real_array(x, where), where)

    return eqx.field(converter=convert)


def _omega(omega, where: str) -> Array:
    """Angular frequencies (rad/s, real or complex, any shape) that must be finite."""
    return _checks.finite(_checks.numeric(omega, where), where)


class LumpedModel(eqx.Module):
    r"""A linear mass–damping–stiffness model ``M q̈ + C q̇ + K q = f``.

    Its receptance (displacement over force) is

    .. math:: H(ω) = (K - ω^2 M + iωC)^{-1},

    the FRF of the paper's Fig. 2 (entry ``H[i, j]`` is ``x_i / F_j``).

    Attributes:
        mass: mass matrix ``M`` (n, n), kg, symmetric positive definite.
        stiffness: stiffness matrix ``K`` (n, n), N/m, symmetric positive semi-definite.
        damping: viscous damping matrix ``C`` (n, n), N·s/m, symmetric positive semi-definite.
    """

    mass: Float[Array, "n n"] = _matrix_field("mass")
    stiffness: Float[Array, "n n"] = _matrix_field("stiffness")
    damping: Float[Array, "n n"] = _matrix_field("damping")

    def __check_init__(self):
        if self.mass.ndim != 2 or self.mass.shape[0] == 0:
            raise ValueError(f"`LumpedModel(mass=...)` must be a square matrix (n, n) with n ≥ "
                             f"1, got shape {self.mass.shape}")
        n = self.mass.shape[-1]
        for name in ("mass", "stiffness", "damping"):
            a = getattr(self, name)
            if a.shape != (n, n):
                raise ValueError(
                    f"`LumpedModel({name}=...)` must have shape ({n}, {n}), got {a.shape}"
                )
        for name in ("mass", "stiffness", "damping"):
            a = getattr(self, name)
            if not _checks.is_concrete(a):
                continue  # checked where it is used (frf, modes) under jit
            a = np.asarray(a)
            if np.max(np.abs(a - a.T)) > _SYMMETRY_RTOL * np.max(np.abs(a)):
                raise ValueError(
                    f"`LumpedModel({name}=...)` must be symmetric (a reciprocal structure), "
                    f"got max |A − Aᵀ| = {np.max(np.abs(a - a.T)):.3g}"
                )
            eig = np.linalg.eigvalsh(a)
            if name == "mass" and np.any(eig <= 0):
                raise ValueError("`LumpedModel(mass=...)` must be positive definite, got "
                                 f"eigenvalues {_checks.fmt(eig)}")
            if name != "mass" and np.any(eig < -_PSD_RTOL * np.max(np.abs(eig))):
                raise ValueError(
                    f"`LumpedModel({name}=...)` must be positive semi-definite (a passive "
                    f"structure), got eigenvalues {_checks.fmt(eig)}"
                )

    @property
    def size(self) -> int:
        """The number of degrees of freedom (the mass matrix is size × size)."""
        return self.mass.shape[-1]

    def dynamic_stiffness(self, omega: Float[ArrayLike, "*b"]) -> Complex[Array, "*b n n"]:
        """``D(ω) = K − ω² M + iωC`` at finite angular frequencies ``omega`` (rad/s)."""
        return self._dynamic_stiffness(
            _omega(omega, "LumpedModel.dynamic_stiffness(omega=...)")
        )

    def _dynamic_stiffness(self, omega):
        w = _checks.to_complex(omega)[..., None, None]
        K = self.stiffness.astype(jnp.complex128)
        M = self.mass.astype(jnp.complex128)
        C = self.damping.astype(jnp.complex128)
        return K - w * w * M + 1j * w * C

    def receptance(self, omega: Float[ArrayLike, "*b"]) -> Complex[Array, "*b n n"]:
        """``H(ω) = D(ω)⁻¹`` at finite angular frequencies ``omega`` (rad/s); a non-finite
        result (a free model at ω = 0, an undamped resonance) is an error."""
        omega = _omega(omega, "LumpedModel.receptance(omega=...)")
        H = small_inv(self._dynamic_stiffness(omega))
        return _checks.finite_output(H, "LumpedModel.receptance(...)")

    def frf(self, freq_hz: Float[ArrayLike, " freq"]) -> Complex[Array, "freq n n"]:
        """Receptance matrix ``H[f, i, j] = x_i / F_j`` (m/N) on a frequency grid in Hz."""
        freq_hz = _checks.frequency_grid(freq_hz, "LumpedModel.frf(freq_hz=...)")
        model = self
        # traced matrices (checked where concrete, in __check_init__): the mirrored upper
        # triangle below is the receptance of a symmetric model only, and of a passive one
        # only where M is positive definite and K, C positive semi-definite
        model = _checked(self, ("mass", "stiffness", "damping"))
        upper, finite = _frf_upper(model, freq_hz)
        H = _mirror(upper, self.size)
        if _checks.is_concrete(finite):
            if not bool(finite):
                raise ValueError(
                    "`LumpedModel.frf(...)` produced a non-finite result; check the parameters "
                    "for NaN/inf"
                )
            return H
        return _checks.finite_output(H, "LumpedModel.frf(...)")

    def modes(self) -> tuple[Float[Array, " n"], Float[Array, "n n"]]:
        """Undamped normal modes: natural frequencies (Hz, ascending) and mass-normalised shapes.

        Solves ``K φ = ω² M φ`` through the symmetric form ``L⁻¹ K L⁻ᵀ`` with ``M = L Lᵀ``;
        rigid-body modes come out at (numerically) zero frequency, with a zero derivative (the
        square root is not differentiated at ω² ≤ 0).  A mass matrix that is not positive
        definite (checked at construction where concrete) is an error here under ``jit``.
        """
        # cholesky reads M's lower triangle and eigh symmetrises: traced matrices that are not
        # symmetric (checked where concrete, in __check_init__) would give wrong modes
        model = _checked(self, ("mass", "stiffness"), definite=False)
        L = jnp.linalg.cholesky(model.mass)
        # NaN where M is not positive definite: refused at construction where M is concrete,
        # here where it is traced
        L = _checks.check(L, jnp.isfinite, "LumpedModel.modes()",
                          "computed from a symmetric positive definite mass matrix")
        Linv = jnp.linalg.inv(L)
        lam, V = jnp.linalg.eigh(Linv @ model.stiffness @ Linv.T)
        # a negative ω² is a divergent mode, not a rigid-body one: K is not positive
        # semi-definite (refused at construction where K is concrete, here where it is traced)
        lam = _checks.check(lam, lambda x: x >= -_PSD_RTOL * abs(x).max(), "LumpedModel.modes()",
                            "computed from a positive semi-definite stiffness matrix")
        shapes = Linv.T @ V
        flexible = lam > 0.0
        omega = jnp.where(flexible, jnp.sqrt(jnp.where(flexible, lam, 1.0)), 0.0)
        return omega / (2 * jnp.pi), shapes


def _checked(model: LumpedModel, names, definite: bool = True) -> LumpedModel:
    """``model`` with the traced matrices among ``names`` guarded as the constructor checks
    concrete ones: symmetric (to :data:`_SYMMETRY_RTOL`) and, with ``definite``, M positive
    definite and K, C positive semi-definite (to :data:`_PSD_RTOL`; ``modes`` checks these
    from its own factorisations)."""
    for name in names:
        a = getattr(model, name)
        if _checks.is_concrete(a):
            continue
        a = eqx.error_if(a, jnp.max(jnp.abs(a - a.T)) > _SYMMETRY_RTOL * jnp.max(jnp.abs(a)),
                         f"`LumpedModel({name}=...)` must be symmetric (a reciprocal structure)")
        if definite:
            eig = jnp.linalg.eigvalsh(0.5 * (a + a.T))
            if name == "mass":
                a = eqx.error_if(a, jnp.any(eig <= 0),
                                 "`LumpedModel(mass=...)` must be positive definite")
            else:
                a = eqx.error_if(a, jnp.any(eig < -_PSD_RTOL * jnp.max(jnp.abs(eig))),
                                 f"`LumpedModel({name}=...)` must be positive semi-definite (a "
                                 "passive structure)")
        model = eqx.tree_at(lambda m, name=name: getattr(m, name), model, a)
    return model


@eqx.filter_jit
def _frf_upper(model: LumpedModel, freq_hz):
    # The receptance of a symmetric model is symmetric (reciprocity): compute the upper
    # triangle only, and the finiteness flag in the same program.
    inv = inv_entries(entries(model._dynamic_stiffness(2 * jnp.pi * freq_hz)))
    n = model.size
    upper = [inv[i][j] for i in range(n) for j in range(i, n)]
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in upper]))
    return upper, finite


@functools.partial(jax.jit, static_argnums=1)
def _mirror(upper, n: int):
    # A second compiled program interleaves the planes into (freq, n, n), mirroring the
    # upper triangle; fused with the algebra above, XLA would recompute it per entry.
    index = {}
    k = 0
    for i in range(n):
        for j in range(i, n):
            index[i, j] = index[j, i] = k
            k += 1
    flat = [upper[index[i, j]] for i in range(n) for j in range(n)]
    return jnp.stack(flat, -1).reshape(*upper[0].shape, n, n)


def chain_model(
    masses: Float[ArrayLike, " n"],
    stiffnesses: Float[ArrayLike, " n-1"],
    dampings: Float[ArrayLike, " n-1"],
    mass_dampings: Float[ArrayLike, " n"] | None = None,
) -> LumpedModel:
    """A free–free chain of masses joined by spring–damper pairs (paper Fig. 1).

    Args:
        masses: masses m_i (kg), all positive.
        stiffnesses: k_i between m_i and m_{i+1} (N/m), all positive.
        dampings: c_i in parallel with k_i (N·s/m), non-negative.
        mass_dampings: optional dampers from each mass to ground (N·s/m), e.g. the paper's c_m2.
    """
    def vector(x, name, test):
        where = f"chain_model({name}=...)"
        v = _checks.real_array(x, where)
        if v.ndim != 1:
            raise ValueError(f"`{where}` must be 1-D, got shape {v.shape}")
        return test(v, where)

    m = vector(masses, "masses", _checks.positive)
    k = vector(stiffnesses, "stiffnesses", _checks.positive)
    c = vector(dampings, "dampings", _checks.nonnegative)
    n = m.shape[0]
    if n == 0:
        raise ValueError("`chain_model(masses=...)` must hold at least one mass, got none")
    if k.shape != (n - 1,) or c.shape != (n - 1,):
        raise ValueError(
            f"`chain_model(stiffnesses=..., dampings=...)` must have {n - 1} entries for "
            f"{n} masses, got {k.shape[0]} and {c.shape[0]}"
        )

    def assemble(e):
        # Σ_i e_i (δ_i − δ_{i+1})(δ_i − δ_{i+1})ᵀ
        D = jnp.eye(n, n - 1) - jnp.eye(n, n - 1, k=-1)
        return (D * e) @ D.T

    cg = jnp.zeros(n) if mass_dampings is None else mass_dampings
    cg = vector(cg, "mass_dampings", _checks.nonnegative)
    if cg.shape != (n,):
        raise ValueError(
            f"`chain_model(mass_dampings=...)` must have {n} entries for {n} masses, "
            f"got {cg.shape[0]}"
        )
    return LumpedModel(jnp.diag(m), assemble(k), assemble(c) + jnp.diag(cg))


def three_mass() -> LumpedModel:
    """The paper's three-mass two-spring (3M2S) system (Sec. 2, Fig. 1).

    m1 = 100 kg, m2 = 150 kg, m3 = 50 kg, k1 = 5e7 N/m, k2 = 2e7 N/m, c1 = 1e3 N·s/m,
    c2 = 400 N·s/m, c_m2 = 0; the force F1 acts on m1. Resonances near 104 Hz and 155 Hz.
    """
    return chain_model([100.0, 150.0, 50.0], [5e7, 2e7], [1e3, 4e2], [0.0, 0.0, 0.0])
