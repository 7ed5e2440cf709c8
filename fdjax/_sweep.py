"""One way to sweep a function over table positions.

Every position sweep of the toolkit (modes over the travel, modal fits per position,
closed-loop poles over the travel) runs through :func:`map_positions`, so the one decision it
encodes lives in one place: on XLA:CPU a batched non-symmetric eigenvalue problem (``vmap`` of
``jnp.linalg.eig``) has been seen to dead-lock (jax 0.10), so a sweep whose body takes one is a
``lax.map`` — a compiled loop, one position at a time — there, and a ``vmap`` elsewhere.
"""

from __future__ import annotations

from collections.abc import Callable

import jax


def map_positions(fn: Callable, xs, *, has_eig: bool = True, batch_size: int | None = None):
    """``fn`` mapped over the leading axis of ``xs`` (a pytree of arrays).

    Args:
        fn: a function of one position's slice of ``xs``.
        xs: a pytree whose leaves share the leading (position) axis.
        has_eig: the body takes a non-symmetric eigenvalue problem (then a ``lax.map`` on the
            CPU; a ``vmap`` on other backends).
        batch_size: ``lax.map``'s batch size (chunks of positions ``vmap``-ed together) for
            bodies without a non-symmetric eig that still benefit from a bounded memory; 1 is a
            plain ``lax.map``, one position at a time with no ``vmap`` at all.
    """
    if batch_size == 1 or (has_eig and jax.default_backend() == "cpu"):
        return jax.lax.map(fn, xs)
    if batch_size is not None:
        return jax.lax.map(fn, xs, batch_size=batch_size)
    return jax.vmap(fn)(xs)
