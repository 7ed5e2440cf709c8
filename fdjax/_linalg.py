"""Small dense linear algebra on matrices stored as nested lists of arrays ("entry planes").

On a position × frequency grid every matrix entry is a whole array.  Keeping the entries as
separate arrays (rather than a trailing ``(n, n)`` axis) lets XLA fuse the closed-form algebra
below into one vectorised loop over the grid; batched LAPACK calls on millions of 2×2 or 3×3
systems would spend their time in call overhead.  An entry may be the Python integer ``0`` for a
structural zero; products with it are skipped at trace time.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Inexact

__all__ = [
    "recip", "small_inv", "small_solve", "entries", "from_entries", "inv_entries", "mul", "add",
]

Entries = list[list]


def recip(z):
    """``1/z``.

    Kept as XLA's native division: writing ``conj(z)/|z|²`` with real operations is faster in a
    single fused chain, but splitting every complex value into parts makes XLA:CPU duplicate the
    shared upstream work across fusions, which cost 2× on the drive grid (measured).
    """
    return 1.0 / z


def mul(a, b):
    """Product that keeps structural zeros (the Python int 0) out of the traced graph."""
    if _is_zero(a) or _is_zero(b):
        return 0
    return a * b


def add(*terms):
    """Sum that drops structural zeros."""
    terms = [t for t in terms if not _is_zero(t)]
    if not terms:
        return 0
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def _is_zero(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and x == 0


def entries(A: Inexact[Array, "*batch n m"]) -> Entries:
    """Split the trailing matrix axes into a nested list of entry arrays."""
    return [[A[..., i, j] for j in range(A.shape[-1])] for i in range(A.shape[-2])]


def from_entries(E: Entries, *, shape=None, dtype=None) -> Array:
    """Stack a nested list of entry arrays back to ``(*batch, n, m)`` (zeros broadcast)."""
    arrays = [x for row in E for x in row if not _is_zero(x)]
    if shape is None:
        shape = jnp.broadcast_shapes(*[jnp.shape(x) for x in arrays])
    if dtype is None:
        dtype = arrays[0].dtype if arrays else jnp.float64
    rows = [
        jnp.stack([jnp.broadcast_to(jnp.asarray(x, dtype), shape) for x in row], -1) for row in E
    ]
    return jnp.stack(rows, -2)


def inv_entries(A: Entries) -> Entries:
    """Inverse of a small matrix given as entries: adjugate formula for n ≤ 3, LU otherwise."""
    n = len(A)
    if n == 1:
        return [[recip(A[0][0])]]
    if n == 2:
        (a, b), (c, d) = A
        r = recip(add(mul(a, d), _neg(mul(b, c))))
        return [[mul(d, r), _neg(mul(b, r))], [_neg(mul(c, r)), mul(a, r)]]
    if n == 3:
        cof = [
            [
                add(
                    mul(A[(i + 1) % 3][(j + 1) % 3], A[(i + 2) % 3][(j + 2) % 3]),
                    _neg(mul(A[(i + 1) % 3][(j + 2) % 3], A[(i + 2) % 3][(j + 1) % 3])),
                )
                for j in range(3)
            ]
            for i in range(3)
        ]
        r = recip(add(*[mul(A[0][j], cof[0][j]) for j in range(3)]))
        return [[mul(cof[j][i], r) for j in range(3)] for i in range(3)]
    M = from_entries(A)
    return entries(jnp.linalg.inv(M))


def _neg(x):
    return 0 if _is_zero(x) else -x


def small_inv(A: Inexact[Array, "*batch n n"]) -> Inexact[Array, "*batch n n"]:
    """Inverse of a batch of small square matrices (closed form for n ≤ 3)."""
    if A.shape[-1] > 3:
        return jnp.linalg.inv(A)
    return from_entries(inv_entries(entries(A)), shape=A.shape[:-2], dtype=A.dtype)


def small_solve(A: Inexact[Array, "*batch n n"], B: Inexact[Array, "*batch n k"]):
    """Solve ``A X = B`` for a batch of small systems (closed form for n ≤ 3)."""
    n = A.shape[-1]
    batch = jnp.broadcast_shapes(A.shape[:-2], B.shape[:-2])
    if n > 3:
        return jnp.linalg.solve(
            jnp.broadcast_to(A, (*batch, *A.shape[-2:])),
            jnp.broadcast_to(B, (*batch, *B.shape[-2:])),
        )
    X = matmul_entries(inv_entries(entries(A)), entries(B))
    return from_entries(X, shape=batch, dtype=jnp.result_type(A.dtype, B.dtype))


def matmul_entries(A: Entries, B: Entries) -> Entries:
    """``A @ B`` on entries, skipping structural zeros."""
    return [
        [add(*[mul(A[i][k], B[k][j]) for k in range(len(B))]) for j in range(len(B[0]))]
        for i in range(len(A))
    ]


@jax.jit
def stack_entries(E: Entries) -> Array:
    """``from_entries`` as its own compiled program.

    Called on entries returned by another jitted function, it keeps XLA from fusing the
    interleaving with the producers (a concatenate fusion recomputes shared work per entry).
    """
    return from_entries(E)
