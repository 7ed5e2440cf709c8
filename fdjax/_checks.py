"""Input validation shared by every module (the three error tiers of the house style).

* Shapes and static facts raise ``ValueError`` at construction.
* Value ranges are checked eagerly with NumPy when the value is concrete and raise a
  ``ValueError`` naming the argument in call syntax, its value and what was expected.
* When the value is a tracer (inside ``jit``/``vmap``/``grad``) the same condition becomes an
  ``eqx.error_if`` on the value that flows on, so nothing fails silently with NaN.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(x) -> bool:
    """True when ``x`` holds a value now (not a tracer inside a transformation)."""
    return not isinstance(x, jax.core.Tracer)


def fmt(value) -> str:
    """Short printable form of a concrete value for error messages."""
    arr = np.asarray(value)
    if arr.ndim == 0:
        return f"{arr.item():.6g}" if np.isrealobj(arr) else f"{arr.item()}"
    if arr.size <= 6:
        return np.array2string(arr, precision=6, separator=", ")
    return f"array(shape={arr.shape}, min={np.nanmin(arr):.6g}, max={np.nanmax(arr):.6g})"


def _describe_bad(arr: np.ndarray, good: np.ndarray) -> str:
    """The offending value (and its index when ``arr`` is not a scalar)."""
    if arr.ndim == 0 or good.ndim == 0:
        return fmt(arr)
    bad = np.argwhere(~np.broadcast_to(good, arr.shape))
    idx = tuple(int(i) for i in bad[0])
    where = idx[0] if len(idx) == 1 else idx
    more = f" and {len(bad) - 1} more" if len(bad) > 1 else ""
    return f"{fmt(arr[idx])} at index {where}{more}"


def check(
    value,
    ok: Callable,
    where: str,
    expected: str,
):
    """Check ``ok(value)`` holds elementwise; return ``value`` (guarded if traced).

    ``where`` is the argument in call syntax, e.g. ``"BallScrewDrive(lead=...)"``;
    ``expected`` completes the sentence "must be ...".
    """
    if is_concrete(value):
        arr = np.asarray(value)
        with np.errstate(invalid="ignore"):
            good = np.asarray(ok(arr))
        if not np.all(good):
            raise ValueError(f"`{where}` must be {expected}, got {_describe_bad(arr, good)}")
        return value
    good = jnp.all(ok(value))
    return eqx.error_if(value, jnp.logical_not(good), f"`{where}` must be {expected}")


def positive(value, where: str):
    """Finite and strictly positive."""
    return check(value, lambda v: _isfinite(v) & (v > 0), where, "finite and positive")


def nonnegative(value, where: str):
    """Finite and non-negative."""
    return check(value, lambda v: _isfinite(v) & (v >= 0), where, "finite and non-negative")


def finite(value, where: str):
    """Finite (no NaN, no inf)."""
    return check(value, _isfinite, where, "finite (no NaN or inf)")


def _isfinite(v):
    return np.isfinite(v) if isinstance(v, np.ndarray | np.generic) else jnp.isfinite(v)


def frequency_grid(freq_hz, where: str = "frf(freq_hz=...)"):
    """Validate a frequency grid in Hz: 1-D, finite, positive and strictly increasing."""
    freq_hz = jnp.asarray(freq_hz)
    if freq_hz.ndim == 0:
        freq_hz = freq_hz[None]
    if freq_hz.ndim != 1:
        raise ValueError(f"`{where}` must be a 1-D grid, got shape {freq_hz.shape}")
    if jnp.issubdtype(freq_hz.dtype, jnp.complexfloating):
        raise ValueError(f"`{where}` must be real, got dtype {freq_hz.dtype}")
    freq_hz = freq_hz.astype(jnp.float64)
    freq_hz = positive(freq_hz, where)

    def increasing(v):
        xp = np if isinstance(v, np.ndarray) else jnp
        return xp.all(xp.diff(v) > 0) if v.shape[0] > 1 else xp.asarray(True)

    return check(freq_hz, increasing, where, "strictly increasing")


def finite_output(value, where: str):
    """Guard a computed result: a non-finite entry becomes an error, never a silent NaN."""
    if is_concrete(value):
        if not np.all(np.isfinite(np.asarray(value))):
            raise ValueError(
                f"`{where}` produced a non-finite result; check the parameters for NaN/inf"
            )
        return value
    return eqx.error_if(
        value,
        jnp.logical_not(jnp.all(jnp.isfinite(value))),
        f"`{where}` produced a non-finite result; check the parameters for NaN/inf",
    )


def _field(test, where: str, **kwargs):
    def convert(x):
        return test(jnp.asarray(x, dtype=jnp.float64), where)

    return eqx.field(converter=convert, **kwargs)


def positive_field(where: str, **kwargs):
    """A float64 Module field that must be finite and positive.

    The check runs in the field's converter, so it also guards values traced inside
    ``jit``/``vmap`` (the stored leaf carries the ``eqx.error_if``).
    """
    return _field(positive, where, **kwargs)


def nonnegative_field(where: str, **kwargs):
    """A float64 Module field that must be finite and non-negative (see ``positive_field``)."""
    return _field(nonnegative, where, **kwargs)


def finite_field(where: str, **kwargs):
    """A float64 Module field that must be finite (see ``positive_field``)."""
    return _field(finite, where, **kwargs)
