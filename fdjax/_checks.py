"""Input validation shared by every module (the three error tiers of the house style).

* Shapes and static facts raise ``ValueError`` at construction.
* Value ranges are checked eagerly with NumPy when the value is concrete and raise a
  ``ValueError`` naming the argument in call syntax, its value and what was expected.
* When the value is a tracer (inside ``jit``/``vmap``/``grad``) the same condition becomes an
  ``eqx.error_if`` on the value that flows on, so nothing fails silently with NaN.
"""

from __future__ import annotations

import dataclasses
import math
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


LONGEST_TRAVEL_M = 20.0
"""No ball-screw axis is longer: a table position or travel beyond it (m) was given in mm."""

LARGEST_SCREW_DIAMETER_M = 1.0
"""No ball screw is thicker (the largest catalogue screws are about 0.2 m): a screw's or a
rod's diameter or bore beyond it (m) was given in mm."""

MATERIALS = {
    # (lowest, highest, unit, (the unit mistaken for it, its size in SI units))
    "modulus": (1e8, 1e13, "Pa", ("N/mm² (MPa)", 1e6)),
    "density": (100.0, 3e4, "kg/m³", ("g/cm³", 1e3)),
}
"""Plausible elastic moduli (polymers ~1e9 Pa to carbides ~7e11 Pa) and densities of what a
feed drive's shafts are made of, and the unit a value outside them was most likely given in."""


def material(value, kind: str, where: str):
    """A concrete modulus (``kind="modulus"``, Pa) or density (``"density"``, kg/m³) inside the
    plausible range of :data:`MATERIALS`, else a ValueError that names the likely unit
    (2.06e5 N/mm² is 2.06e11 Pa).  Traced values are returned as they are."""
    if not is_concrete(value):
        return value
    lo, hi, unit, (other, scale) = MATERIALS[kind]
    try:
        return check(value, lambda v: (v >= lo) & (v <= hi), where,
                     f"between {lo:g} and {hi:g} {unit}")
    except ValueError as err:
        v = float(np.ravel(np.asarray(value, np.float64))[0])
        if lo <= v * scale <= hi:
            raise ValueError(f"{err}; in {unit}: {v:.6g} {other} is {v * scale:.6g} "
                             f"{unit}") from None
        raise


def inside(value, lo: float, hi: float, where: str, what: str = "the travel",
           noun: str = "table positions"):
    """Table positions (m; or other lengths, ``noun``) inside ``what`` = [lo, hi], checked by
    :func:`check`.  A concrete value that misses the range but lies inside it once divided by
    1000 was given in millimetres: the message says so, with the value in metres."""
    _numbers(value, where)  # a string or another object that is not numbers: a TypeError
    # the ends with a round-off's slack: np.arange(0.1, 0.7 + 1e-3, 1e-3) ends at
    # 0.7000000000000005, which is the end of the travel
    tol = 1e-12 * max(1.0, abs(lo), abs(hi))
    ok = lambda p: (p >= lo - tol) & (p <= hi + tol)  # noqa: E731  (NaN fails both)
    expected = f"inside {what} [{lo:.6g}, {hi:.6g}] m"
    if not is_concrete(value):  # traced: the same sentences, without the value
        value = jnp.asarray(value)
        bad = jnp.logical_not(jnp.all(ok(value)))
        # the hint only where the check fails (under vmap each position picks its sentence)
        in_mm = bad & jnp.all(ok(value) | ok(value / 1000))
        return eqx.branched_error_if(
            value, bad, in_mm.astype(jnp.int32),
            [f"`{where}` must be {expected}",
             f"`{where}` must be {expected}; {noun} are in metres (the value lies "
             f"inside once divided by 1000: it was given in mm)"])
    try:
        return check(value, ok, where, expected)
    except ValueError as err:  # raised eagerly: the value is concrete and real here
        mm = _in_mm(value, ok)
        if mm is not None:
            raise ValueError(f"{err}; {noun} are in metres: {mm:.6g} mm is "
                             f"{mm / 1000:.6g} m") from None
        raise


def below_nyquist(freq_hz, dt, where: str):
    """A frequency grid (Hz) at most the Nyquist frequency 1/(2 dt) of a sample period ``dt``
    (s), above which a sampled response aliases: a ValueError with the values where ``dt`` is
    concrete, an ``eqx.error_if`` where it is traced."""
    if is_concrete(dt):
        top = 0.5 / float(dt)
        return check(freq_hz, lambda v: v <= top * (1 + 1e-12), where,
                     f"at most the Nyquist frequency {top:.6g} Hz of the sample period "
                     f"{float(dt):.6g} s ({top * 2 * math.pi:.6g} rad/s: the grid is in Hz)")
    return eqx.error_if(freq_hz, jnp.any(freq_hz * dt > 0.5 * (1 + 1e-12)),
                        f"`{where}` must be at most the Nyquist frequency 1/(2 dt) (the grid "
                        f"is in Hz)")


def _in_mm(value, ok: Callable) -> float | None:
    """The first entry of a concrete ``value`` that fails ``ok`` when every failing entry
    passes it once divided by 1000 (lengths given in millimetres), else None."""
    arr = np.asarray(value, np.float64)
    with np.errstate(invalid="ignore"):
        bad = arr[~np.broadcast_to(ok(arr), arr.shape)]
        # divided, not multiplied by 1e-3: 700 * 1e-3 is 0.7000000000000001
        return float(bad[0]) if bad.size and np.all(ok(bad / 1000)) else None


def mm_hint(value: float) -> str:
    """The end of a message about a length (m) that was given in millimetres."""
    return f"; lengths are in metres: {value:.6g} mm is {value / 1000:.6g} m"


def at_most(value, limit: float, where: str, reason: str, *, magnitude: bool = False):
    """A concrete length (m) checked at most ``limit`` (its magnitude, with ``magnitude``) by
    :func:`check`, the message giving ``reason``; a value beyond it whose thousandth is within
    it was given in millimetres, and the message says so (:func:`mm_hint`).  A traced value is
    returned as it is: a plausibility check of what is given, not a guard of what is
    computed."""
    if not is_concrete(value):
        return value
    ok = (lambda v: abs(v) <= limit) if magnitude else (lambda v: v <= limit)  # noqa: E731
    size = " in magnitude" if magnitude else ""
    try:
        return check(value, ok, where, f"at most {limit:g} m{size} ({reason})")
    except ValueError as err:  # concrete and real here
        mm = _in_mm(value, ok)
        if mm is not None:
            raise ValueError(f"{err}{mm_hint(mm)}") from None
        raise


def instance(value, cls, where: str, expected: str | None = None):
    """``value`` when it is a ``cls``, else a ``TypeError`` naming ``where`` (the argument in
    call syntax) and ``expected`` (default "an fdjax.<cls>"), which completes "must be ..."."""
    if not isinstance(value, cls):
        expected = expected or f"an fdjax.{cls.__name__}"
        raise TypeError(f"`{where}` must be {expected}, got {type(value).__name__}")
    return value


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
    """Validate a frequency grid in Hz: 1-D, not empty, finite, positive and strictly
    increasing."""
    freq_hz = numeric(freq_hz, where)
    if freq_hz.ndim == 0:
        freq_hz = freq_hz[None]
    if freq_hz.ndim != 1 or freq_hz.shape[0] == 0:
        raise ValueError(f"`{where}` must be a 1-D grid of at least one frequency, got shape "
                         f"{freq_hz.shape}")
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
        return test(real_array(x, where), where)

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


def finite_scalar(value, where: str) -> jax.Array:
    """A real scalar as float64, finite when it is concrete.  A traced value passes unguarded:
    for the parts a controller builds inside ``jit`` from its own fields (the gains of its
    blocks), which were checked where the controller was made."""
    arr = real_scalar(value, where)
    return finite(arr, where) if is_concrete(arr) else arr


def finite_scalar_field(where: str, **kwargs):
    """A Module field converted by :func:`finite_scalar`."""
    return eqx.field(converter=lambda x: finite_scalar(x, where), **kwargs)


# ------------------------------------------------------------------ casts and static facts
def to_float(x) -> jax.Array:
    """``x`` as a float64 array (no checks): the one real cast of the package."""
    return jnp.asarray(x, dtype=jnp.float64)


def to_complex(x) -> jax.Array:
    """``x`` as a complex128 array (no checks): the one complex cast of the package."""
    return jnp.asarray(x).astype(jnp.complex128)


def _numbers(value, where: str):
    """``value`` as an array of numbers, a NumPy one unless it is a JAX array already: a
    string, a list of strings or another object that is not numbers is a ``TypeError`` naming
    ``where`` (not JAX's or NumPy's own message)."""
    if isinstance(value, jax.Array):
        return value
    try:
        arr = np.asarray(value)
    except Exception:  # e.g. a list of traced values: JAX converts it, or says why not
        try:
            return jnp.asarray(value)
        except Exception:
            arr = np.asarray(None)
    if arr.dtype.kind not in "biufc":
        text = repr(value)
        text = text if len(text) <= 60 else text[:57] + "..."
        raise TypeError(f"`{where}` must be a number or an array of numbers, got {text}")
    return arr


def numeric(value, where: str) -> jax.Array:
    """``value`` as a JAX array of numbers (:func:`_numbers` checks what it is)."""
    return jnp.asarray(_numbers(value, where))


def real_array(value, where: str) -> jax.Array:
    """A real array of any shape as float64; a complex dtype is a ``ValueError`` (shape fact)."""
    arr = numeric(value, where)
    if jnp.issubdtype(arr.dtype, jnp.complexfloating):
        raise ValueError(f"`{where}` must be real, got dtype {arr.dtype}")
    if arr.dtype == bool:  # True is not a length of 1 m
        raise ValueError(f"`{where}` must be a number, got booleans")
    return arr.astype(jnp.float64)


def real_scalar(value, where: str) -> jax.Array:
    """A real scalar as a float64 0-d array (shape and dtype facts; the range is the caller's).

    Jit-safe: a traced scalar stays traced, and a Python float becomes an array, so it is a
    traced argument of a jitted function (not a static one, which would compile per value).
    """
    arr = numeric(value, where)
    if arr.ndim != 0 or jnp.issubdtype(arr.dtype, jnp.complexfloating) or arr.dtype == bool:
        raise ValueError(f"`{where}` must be a real scalar, got {arr.dtype} of shape {arr.shape}")
    return arr.astype(jnp.float64)


def concrete_float(value, where: str) -> float:
    """A concrete real scalar as a Python float, for quantities that fix a static structure
    (e.g. segment durations computed in Python); a traced value is a ``ValueError``."""
    if not is_concrete(value):
        raise ValueError(
            f"`{where}` must be a concrete number (it fixes the structure of what is built), "
            "got a traced value; call it outside jit/vmap/grad"
        )
    arr = np.asarray(_numbers(value, where))
    if not np.isrealobj(arr):
        raise ValueError(f"`{where}` must be real, got dtype {arr.dtype}")
    if arr.dtype == bool:  # True is not a duration of 1 s
        raise ValueError(f"`{where}` must be a number, got the boolean {value!r}")
    if arr.shape != ():
        raise ValueError(f"`{where}` must be a scalar, got shape {arr.shape}")
    return float(arr)


def static_int(value, where: str, lo: int, hi: int | None = None) -> int:
    """A static count: a Python/NumPy integer (not a bool) in ``[lo, hi]``, as a Python int."""
    ok = isinstance(value, int | np.integer) and not isinstance(value, bool)
    if ok:
        value = int(value)
        ok = value >= lo and (hi is None or value <= hi)
    if not ok:
        rng = f"between {lo} and {hi}" if hi is not None else f"at least {lo}"
        raise ValueError(f"`{where}` must be an integer {rng}, got {value!r}")
    return value


def static_number(value, where: str, ok: Callable = lambda v: True,
                  expected: str = "a finite number") -> float:
    """A static setting (a concrete real scalar, not a bool, finite and with ``ok(value)``) as
    a Python float, for settings that fix what is compiled; otherwise a ``ValueError`` naming
    ``where`` and ``expected`` (which completes "must be ...")."""
    try:
        v = math.nan if isinstance(value, bool | np.bool_) else concrete_float(value, where)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and ok(v)):
        raise ValueError(f"`{where}` must be {expected}, got {value!r}")
    return v


def static_positive(value, where: str) -> float:
    """A static positive number (:func:`static_number`), e.g. a smooth maximum's sharpness."""
    return static_number(value, where, lambda v: v > 0, "a finite positive number")


def static_bool(value, where: str) -> bool:
    """A static flag: a Python or NumPy bool (not a traced value, not an int)."""
    if not isinstance(value, bool | np.bool_):
        raise TypeError(f"`{where}` must be a bool, got {value!r}")
    return bool(value)


def finite_parameters(tree, where: str, traced: bool = False):
    """Every floating-point array leaf of a parameter pytree (a controller, a drive) finite.
    Concrete leaves are checked here, the first non-finite one named by its path; traced ones
    only with ``traced=True``, by an ``eqx.error_if`` on the returned tree.  Returns the tree."""
    # array-like: a leaf set to a Python or NumPy float (eqx.tree_at(..., float("nan"))) too
    leaves = [(path, x) for path, x in jax.tree_util.tree_leaves_with_path(tree)
              if eqx.is_inexact_array(x) or isinstance(x, float | complex | np.inexact)]
    for path, x in leaves:
        a = np.asarray(x) if is_concrete(x) else None
        if a is not None and not np.all(np.isfinite(a)):
            raise ValueError(f"`{where}` must have finite parameters, got "
                             f"{a[~np.isfinite(a)].ravel()[0]} in {jax.tree_util.keystr(path)}")
    live = [x for _, x in leaves if not is_concrete(x)]
    if not (traced and live):
        return tree
    bad = jnp.logical_not(jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in live])))
    return eqx.error_if(tree, bad, f"`{where}` must have finite parameters")


def finite_tree(tree, where: str):
    """:func:`finite_output` for a pytree of results (e.g. a nested list of entry arrays of
    broadcast-compatible shapes): every leaf must be finite; returns the tree (guarded)."""
    leaves = jax.tree_util.tree_leaves(tree)
    message = f"`{where}` produced a non-finite result; check the parameters for NaN/inf"
    if all(is_concrete(x) for x in leaves):
        if not all(np.all(np.isfinite(np.asarray(x))) for x in leaves):
            raise ValueError(message)
        return tree
    ok = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))
    return eqx.error_if(tree, jnp.logical_not(ok), message)


def constructor_checks(tree, fn: str):
    """Run again, on every Module in ``tree`` whose leaves are concrete, the checks its
    constructor ran (each field's converter and ``__check_init__``): ``eqx.tree_at`` replaces
    leaves without them, so a stiffness set negative after construction would otherwise reach
    the model.  Their ValueError names the field (``NutJoint(stiffness=...)``) and ``fn``, the
    function the value was given to.  Modules with traced leaves are left to the checks that
    flow with the values.  Returns ``tree``."""

    def visit(node):
        if isinstance(node, list | tuple):
            for item in node:
                visit(item)
            return
        if not isinstance(node, eqx.Module):
            return
        fields = [(f, getattr(node, f.name)) for f in dataclasses.fields(node)]
        concrete = all(is_concrete(x) for x in jax.tree_util.tree_leaves(node))
        try:
            if concrete:
                for f, value in fields:
                    convert = f.metadata.get("converter")
                    if convert is not None and value is not None:
                        convert(value)
                check = getattr(type(node), "__check_init__", None)
                if check is not None:
                    check(node)
        except ValueError as e:
            raise ValueError(f"{e} (in the model given to `{fn}`)") from None
        for _, value in fields:
            visit(value)

    visit(tree)
    return tree
