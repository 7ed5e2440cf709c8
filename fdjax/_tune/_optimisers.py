"""The optimisers the tuners use by default, one object each."""

from __future__ import annotations

import functools

import optax

__all__ = ["default_optimiser", "optimiser_or", "checked_optimiser"]


@functools.cache
def default_optimiser(name: str, *args) -> optax.GradientTransformation:
    """One optax transformation per name and arguments (``default_optimiser("adam", 0.02)`` is
    ``optax.adam(0.02)``), the same object at every call.  A compiled step is keyed on the
    optimiser's functions, which compare by identity: a default made afresh at every call
    would compile afresh; pass the same object to reuse the compiled steps."""
    return getattr(optax, name)(*args)


def checked_optimiser(optimiser, where: str, example: str = "optax.adam(0.01)"):
    """``optimiser`` when it is an optax transformation (``init`` and ``update``), else a
    ``TypeError`` naming ``where`` with ``example``."""
    if not (callable(getattr(optimiser, "init", None))
            and callable(getattr(optimiser, "update", None))):
        raise TypeError(f"`{where}` must be an optax GradientTransformation (e.g. {example}), "
                        f"got {optimiser!r}")
    return optimiser


def optimiser_or(optimiser, where: str, name: str, *args) -> optax.GradientTransformation:
    """``optimiser``, checked (:func:`checked_optimiser`), or the default
    :func:`default_optimiser` ``(name, *args)`` when it is None."""
    if optimiser is None:
        return default_optimiser(name, *args)
    return checked_optimiser(optimiser, where,
                             f"optax.{name}({', '.join(map(repr, args))})")
