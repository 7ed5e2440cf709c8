r"""One container for every linear time-invariant system of the toolkit.

A filter's realisation, a controller's law, the continuous closed loop and the sampled closed
loop are all

    continuous (``dt is None``):   ẋ = A x + B u,        y = C x + D u,
    discrete   (``dt = T``):       x_{k+1} = A x_k + B u_k,   y_k = C x_k + D u_k,

with python-control's shapes (``control.ss(A, B, C, D[, dt])`` accepts the arrays as they
are).  The helpers here build systems from parts (series, parallel sums, Tustin and zero-order
hold discretisation) and evaluate them; everything is a pure JAX function, so ``jit``, ``vmap``
and ``grad`` pass through.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, ArrayLike, Complex, Float, Inexact

from . import _checks

__all__ = ["LTI"]

_TWO_PI = 2.0 * math.pi


def _c(x) -> Array:
    return jnp.asarray(x).astype(jnp.complex128)


class LTI(eqx.Module):
    r"""A linear time-invariant system in state space, continuous or discrete.

    Attributes:
        A: (n, n).  B: (n, m).  C: (p, n).  D: (p, m).
        dt: the sample period T (s) of a discrete system; None for a continuous one.
        position_m: the table position (m) the system belongs to, where it has one (a closed
            loop around the drive); None otherwise.
    """

    A: Float[Array, "n n"]
    B: Float[Array, "n m"]
    C: Float[Array, "p n"]
    D: Float[Array, "p m"]
    dt: Float[Array, ""] | None = None
    position_m: Float[Array, ""] | None = None

    def __check_init__(self):
        # trailing dimensions (a batch of systems may lead); shapes are static under jit
        shapes = [getattr(getattr(self, k), "shape", None) for k in "ABCD"]
        ok = all(sh is not None and len(sh) >= 2 for sh in shapes)
        if ok:
            (a0, a1), (b0, b1), (c0, c1), (d0, d1) = (sh[-2:] for sh in shapes)
            ok = a0 == a1 == b0 == c1 and c0 == d0 and b1 == d1
        if not ok:
            raise ValueError("`LTI(A=..., B=..., C=..., D=...)` must have shapes (n, n), "
                             f"(n, m), (p, n), (p, m), got {', '.join(map(str, shapes))}")

    @property
    def n_states(self) -> int:
        """The number of states n (A is n × n)."""
        return self.A.shape[-1]

    @property
    def is_discrete(self) -> bool:
        """Whether the system is discrete (it has a sample period ``dt``)."""
        return self.dt is not None

    def _one(self, fn: str) -> None:
        if self.A.ndim != 2:
            raise ValueError(f"`LTI.{fn}` needs one system (A of shape (n, n)), got a batch (A "
                             f"of shape {self.A.shape}): jax.vmap it over the systems")

    def transfer(self, x: Inexact[ArrayLike, "*shape"]) -> Complex[Array, "*shape p m"]:
        """C (xI − A)⁻¹ B + D at complex ``x`` of any shape (x = s, or z for a discrete system);
        one system (``jax.vmap`` over a batch)."""
        self._one("transfer")
        return transfer(self.A, self.B, self.C, self.D, x)

    def frf(self, freq_hz: Float[ArrayLike, " freq"]) -> Complex[Array, "freq p m"]:
        """Frequency response at ``freq_hz`` (Hz): s = i2πf, or z = e^{i2πfT} when discrete,
        then up to the Nyquist frequency 1/(2T) (above it the response aliases)."""
        where = "LTI.frf(freq_hz=...)"
        self._one("frf")
        f = _checks.frequency_grid(freq_hz, where)
        if self.dt is not None:
            f = _checks.below_nyquist(f, self.dt, where)
        return self.transfer(self.unit_circle_or_axis(_TWO_PI * f))

    def unit_circle_or_axis(self, omega) -> Complex[Array, "*shape"]:
        """The point of the complex plane at angular frequency ω: iω, or e^{iωT}."""
        s = _c(omega) * 1j
        return s if self.dt is None else jnp.exp(s * _c(self.dt))

    def poles(self) -> Complex[Array, " n"]:
        """Eigenvalues of A, sorted by real part (continuous) or modulus (discrete), largest first.

        Under ``vmap`` on a CPU prefer :func:`fdjax.check_stability`, which takes one
        eigenvalue problem per position."""
        lam = jnp.linalg.eigvals(self.A)
        key = jnp.real(lam) if self.dt is None else jnp.abs(lam)
        return lam[jnp.argsort(-key)]


def transfer(A, B, C, D, x) -> Array:
    """C (xI − A)⁻¹ B + D at complex x (any shape) by a direct solve (:func:`solve`), against
    B or, with fewer outputs than inputs, against Cᵀ (the transposed system)."""
    x = _c(x)
    n = A.shape[-1]
    if n == 0:
        return jnp.broadcast_to(_c(D), (*x.shape, *D.shape))
    M = x[..., None, None] * jnp.eye(n, dtype=jnp.complex128) - _c(A)
    if C.shape[-2] < B.shape[-1]:  # fewer outputs than inputs: (C M⁻¹) B, C M⁻¹ = (M⁻ᵀ Cᵀ)ᵀ
        Ct = jnp.broadcast_to(_c(C).T, (*x.shape, n, C.shape[-2]))
        return jnp.swapaxes(solve(jnp.swapaxes(M, -1, -2), Ct), -1, -2) @ _c(B) + _c(D)
    X = solve(M, jnp.broadcast_to(_c(B), (*x.shape, *B.shape)))
    return _c(C) @ X + _c(D)


@jax.custom_jvp
def solve(M, R) -> Array:
    """M⁻¹R for a batch of small dense systems M (…, n, n), R (…, n, k) (:func:`_eliminate`).

    Differentiated in closed form, d(M⁻¹R) = M⁻¹(dR − dM M⁻¹R), with M⁻¹ from one more
    elimination (:func:`_inverse`): every derivative, of any order and in either mode, is then
    matrix products, never a derivative of the elimination loop and never one more elimination
    per tangent (a Hessian's columns share the two eliminations)."""
    return _eliminate(M, R)


@solve.defjvp
def _solve_jvp(primals, tangents):
    M, R = primals
    dM, dR = tangents
    X = solve(M, R)
    return X, _inverse(M) @ (dR - dM @ X)


@jax.custom_jvp
def _inverse(M) -> Array:
    """M⁻¹ (…, n, n) by elimination against the identity; d(M⁻¹) = −M⁻¹ dM M⁻¹."""
    eye = jnp.broadcast_to(jnp.eye(M.shape[-1], dtype=M.dtype), M.shape)
    return _eliminate(M, eye)


@_inverse.defjvp
def _inverse_jvp(primals, tangents):
    (M,), (dM,) = primals, tangents
    Mi = _inverse(M)
    return Mi, -Mi @ dM @ Mi


def _eliminate(M, R) -> Array:
    """M⁻¹R for a batch of small dense systems M (…, n, n), R (…, n, k): Gaussian elimination
    with partial pivoting (backward stable) in plain array operations, one ``fori_loop`` step
    per column.  XLA:CPU has dead-locked (every thread asleep) running batched LAPACK solves
    inside the vectorised, differentiated margin refinement on 2-core machines; this form has
    no custom call.  (Unrolled, the nested jets of that refinement compile for minutes.)"""
    n = M.shape[-1]
    rows = jnp.arange(n)
    A = jnp.concatenate([M, R], -1)

    def eliminate(j, A):
        # partial pivoting: the largest entry of column j at or below the diagonal
        colj = jnp.take(A, j, axis=-1)
        p = jnp.argmax(jnp.where(rows >= j, jnp.abs(colj), -1.0), axis=-1)
        row_j = jnp.take(A, j, axis=-2)
        row_p = jnp.take_along_axis(A, p[..., None, None], -2)[..., 0, :]
        is_p = rows == p[..., None]
        A = jnp.where((rows == j)[:, None], row_p[..., None, :],
                      jnp.where(is_p[..., :, None], row_j[..., None, :], A))
        colj, row_j = jnp.take(A, j, axis=-1), jnp.take(A, j, axis=-2)
        pivot = jnp.take(row_j, j, axis=-1)
        factor = jnp.where(rows > j, colj / pivot[..., None], 0.0)
        return A - factor[..., :, None] * row_j[..., None, :]

    def substitute(jj, X):  # rows of X below j are known, the rest still zero
        j = n - 1 - jj
        u = jnp.take(U, j, axis=-2)
        xj = (jnp.take(Y, j, axis=-2) - jnp.einsum("...i,...ik->...k", u, X)) / jnp.take(
            u, j, axis=-1)[..., None]
        return jnp.where((rows == j)[:, None], xj[..., None, :], X)

    A = jax.lax.fori_loop(0, n, eliminate, A)
    U, Y = A[..., :n], A[..., n:]
    X = jnp.zeros_like(Y)
    X = jax.lax.fori_loop(0, n, substitute, X)
    return X




def series(first: LTI, second: LTI) -> LTI:
    """u → first → second → y (first's outputs feed second's inputs)."""
    n1, n2 = first.A.shape[0], second.A.shape[0]
    A = jnp.block([
        [first.A, jnp.zeros((n1, n2))],
        [second.B @ first.C, second.A],
    ])
    B = jnp.concatenate([first.B, second.B @ first.D], 0)
    C = jnp.concatenate([second.D @ first.C, second.C], 1)
    return LTI(A, B, C, second.D @ first.D, first.dt)


def parallel(systems: list[LTI], dt=None) -> LTI:
    """Σ_i G_i with separate inputs: block-diagonal A and B, concatenated C, D side by side.

    Inputs are the concatenation of each system's inputs; the outputs are summed."""
    A = jsl.block_diag(*[s.A for s in systems])
    B = jsl.block_diag(*[s.B for s in systems])
    C = jnp.concatenate([s.C for s in systems], 1)
    D = jnp.concatenate([s.D for s in systems], 1)
    return LTI(A, B, C, D, dt)


def tustin(sys: LTI, period) -> LTI:
    """Bilinear (Tustin) discretisation, unprewarped: s = (2/T)(z − 1)/(z + 1)."""
    h = jnp.asarray(period, jnp.float64)
    n = sys.A.shape[0]
    if n == 0:
        return LTI(sys.A, sys.B, sys.C, sys.D, h)
    Q = jnp.linalg.inv(jnp.eye(n) - 0.5 * h * sys.A)
    Ad = Q @ (jnp.eye(n) + 0.5 * h * sys.A)
    Bd = Q @ sys.B * h
    Cd = sys.C @ Q
    Dd = sys.D + Cd @ sys.B * (0.5 * h)
    return LTI(Ad, Bd, Cd, Dd, h)


def expm(M) -> Array:
    r"""exp(M) after a diagonal balancing M → D⁻¹MD (Osborne's iteration, powers of two, so
    exact): the realisations here can be badly scaled (the Padé delay: ‖M‖₁ ~ 1e7 for a loop
    step), which costs exp and its derivative accuracy; balancing brings the norm down by orders
    of magnitude.  exp(D⁻¹MD) = D⁻¹ exp(M) D; D is held constant under differentiation."""
    d = _balance(M)
    E = _expm_pade13(M * d[None, :] / d[:, None])
    return E * d[:, None] / d[None, :]


def _balance(M) -> Array:
    """The diagonal d (powers of two) of Osborne's balancing D⁻¹MD, D = diag(d): 12 sweeps
    toward equal off-diagonal row and column sums; held constant under differentiation."""
    Ma = jnp.abs(jax.lax.stop_gradient(M))
    off = Ma * (1.0 - jnp.eye(M.shape[0]))
    log_d = jnp.zeros(M.shape[0])
    for _ in range(12):
        d = jnp.exp2(log_d)
        Bm = off * d[None, :] / d[:, None]
        r, c = jnp.sum(Bm, 1), jnp.sum(Bm, 0)
        ok = (r > 0) & (c > 0)
        step = jnp.where(ok, 0.5 * jnp.log2(jnp.where(ok, r / jnp.where(ok, c, 1.0), 1.0)), 0.0)
        log_d = log_d + jnp.round(step)
    return jnp.exp2(log_d)


def hessenberg(A) -> tuple[Array, Array]:
    """(H, Q) with A = Q H Qᵀ, H upper Hessenberg and Q orthogonal, by Householder reflections
    (plain array operations: ``vmap`` and derivatives of any order pass)."""
    n = A.shape[-1]
    idx = jnp.arange(n)

    def reflect(k, HQ):
        H, Q = HQ
        x = jnp.where(idx > k, jnp.take(H, k, axis=1), 0.0)
        xx = x @ x
        big = xx > 0
        alpha = jnp.where(big, jnp.sqrt(jnp.where(big, xx, 1.0)), 0.0)
        sign = jnp.where(jnp.take(x, k + 1) >= 0, 1.0, -1.0)
        v = x + jnp.where(idx == k + 1, sign * alpha, 0.0)
        vv = v @ v
        ok = vv > 0
        beta = jnp.where(ok, 2.0 / jnp.where(ok, vv, 1.0), 0.0)
        H = H - beta * jnp.outer(v, v @ H)
        H = H - beta * jnp.outer(H @ v, v)
        return H, Q - beta * jnp.outer(Q @ v, v)

    H, Q = jax.lax.fori_loop(0, max(n - 2, 0), reflect, (A, jnp.eye(n, dtype=A.dtype)))
    return jnp.where(idx[:, None] > idx[None, :] + 1, 0.0, H), Q


def transfer_hessenberg(A, B, C, D, x) -> Array:
    r"""C (xI − A)⁻¹ B + D at many complex x (any shape), as :func:`transfer`, for a fixed A:
    A is balanced (:func:`_balance`) and reduced once to Hessenberg form H = Qᵀ D⁻¹AD Q
    (:func:`hessenberg`), after which each point costs O(n²) instead of O(n³): elimination of
    the single subdiagonal with pivoting between neighbouring rows, then back substitution
    (the method of SLICOT's TB05AD).  Backward stable: the error is round-off relative to
    ‖D⁻¹AD‖."""
    n = A.shape[-1]
    x = _c(x)
    if n == 0:
        return jnp.broadcast_to(_c(D), (*x.shape, *D.shape))
    d = _balance(A)
    H, Q = hessenberg(A * d[None, :] / d[:, None])
    b = _c(Q.T @ (B / d[:, None]))
    c = _c((C * d[None, :]) @ Q)
    z = x.reshape(-1)
    F, k = z.shape[0], b.shape[1]
    Hc = _c(H)
    eye = jnp.eye(n, dtype=jnp.complex128)

    def row(i):  # row i of [zI − H | b] at every z, (F, n + k)
        return jnp.concatenate([z[:, None] * jnp.take(eye, i, 0) - jnp.take(Hc, i, 0),
                                jnp.broadcast_to(jnp.take(b, i, 0), (F, k))], axis=1)

    def eliminate(j, carry):  # the pivot row of column j and the remainder of the other
        r, U = carry
        s = row(j + 1)
        swap = jnp.abs(jnp.take(s, j, 1)) > jnp.abs(jnp.take(r, j, 1))
        top = jnp.where(swap[:, None], s, r)
        low = jnp.where(swap[:, None], r, s)
        factor = jnp.take(low, j, 1) / jnp.take(top, j, 1)
        U = jax.lax.dynamic_update_index_in_dim(U, top, j, 1)
        return low - factor[:, None] * top, U

    r, U = jax.lax.fori_loop(0, n - 1, eliminate,
                             (row(0), jnp.zeros((F, n, n + k), jnp.complex128)))
    U = jax.lax.dynamic_update_index_in_dim(U, r, n - 1, 1)

    def substitute(jj, X):  # rows of X below j are known, the rest still zero
        j = n - 1 - jj
        u = jnp.take(U, j, 1)
        xj = (u[:, n:] - jnp.einsum("fi,fik->fk", u[:, :n], X)) / jnp.take(u, j, 1)[:, None]
        return jax.lax.dynamic_update_index_in_dim(X, xj, j, 1)

    X = jax.lax.fori_loop(0, n, substitute, jnp.zeros((F, n, k), jnp.complex128))
    G = c @ X + _c(D)
    return G.reshape(*x.shape, *G.shape[-2:])


# Higham (2005), "The scaling and squaring method for the matrix exponential revisited": the
# [13/13] Padé approximant is accurate to double precision for ‖A‖₁ ≤ θ₁₃.
_PADE13 = (64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
           129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0,
           40840800.0, 960960.0, 16380.0, 182.0, 1.0)
_THETA13 = 5.371920351148152
_MAX_SQUARINGS = 48  # ‖A‖₁ up to θ₁₃·2⁴⁸ ≈ 1.5e15


def _expm_pade13(A) -> Array:
    """exp(A) by scaling and squaring with the [13/13] Padé approximant: one solve and a
    fixed-length loop of conditional squarings (a small program that differentiates in both
    modes; the number of squarings s = ⌈log₂(‖A‖₁/θ₁₃)⌉ is held constant under
    differentiation)."""
    b = _PADE13
    n = A.shape[-1]
    norm = jnp.max(jnp.sum(jnp.abs(jax.lax.stop_gradient(A)), axis=-2))
    s = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / _THETA13)), 0, _MAX_SQUARINGS)
    A = A * jnp.exp2(-s)
    eye = jnp.eye(n, dtype=A.dtype)
    A2 = A @ A
    A4 = A2 @ A2
    A6 = A4 @ A2
    U = A @ (A6 @ (b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4 + b[3] * A2
             + b[1] * eye)
    V = A6 @ (b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * eye
    R = solve(V - U, V + U)
    return jax.lax.fori_loop(0, _MAX_SQUARINGS, lambda i, R: jnp.where(i < s, R @ R, R), R)


def zoh(A, B, period) -> tuple[Array, Array]:
    """(Φ, Γ) of the exact zero-order hold: [[Φ, Γ], [0, I]] = exp([[A, B], [0, 0]] T)."""
    n, m = A.shape[0], B.shape[1]
    M = jnp.zeros((n + m, n + m)).at[:n, :n].set(A).at[:n, n:].set(B)
    E = expm(M * jnp.asarray(period, jnp.float64))
    return E[:n, :n], E[:n, n:]
