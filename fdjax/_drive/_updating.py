r"""Model updating: fit the drive's physical parameters to measured modal data.

Given target modal data (e.g. the paper's Table 1 at Y_table = 115 mm),
bounded physical parameters are adjusted by Levenberg–Marquardt (optimistix) on residuals
normalised by the tolerances,

    r = [ln(f/f*) / tol_f,  ln(ζ/ζ*) / tol_ζ,  wrap(φ − φ*) / tol_φ],

so ``|r| ≤ 1`` means "within tolerance".  Each target is paired with the nearest-frequency
visible model mode (greedy, in target order; a mode is visible when its own term is at least
``visibility`` of the whole FRF at its natural frequency).  Bounds are kept by the parameterisation
``θ = lo (hi/lo)^σ(u)`` (or ``lo + (hi − lo) σ(u)`` for signed quantities), not by clipping.
"""

from __future__ import annotations

import dataclasses
import operator
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from .. import _checks
from ._model import INPUTS, OUTPUTS, BallScrewDrive
from ._modes import DriveModes, _channel, _modes_at, _wrap_deg
from ._twin import TwinOptions, _check_inputs, _twin_options

__all__ = ["ModalData", "ModelUpdate", "update_model", "TABLE_1", "TABLE_1_POSITION_M"]


def _vector_field(where: str, test):
    """A float64 1-D field checked in its converter (the guarded value is the stored leaf)."""

    def convert(x):
        v = jnp.atleast_1d(_checks.real_array(x, where))
        if v.ndim != 1:
            raise ValueError(f"`{where}` must be a scalar or 1-D, got shape {v.shape}")
        return test(v, where)

    return eqx.field(converter=convert)


class ModalData(eqx.Module):
    """Target modal data of one FRF: frequency (Hz), damping ratio, resonant phase (°).

    Frequencies and damping ratios must be finite and positive (the residuals take their
    logarithms), phases finite.
    """

    frequency_hz: Float[Array, " n"] = _vector_field("ModalData(frequency_hz=...)",
                                                     _checks.positive)
    damping_ratio: Float[Array, " n"] = _vector_field("ModalData(damping_ratio=...)",
                                                      _checks.positive)
    phase_deg: Float[Array, " n"] = _vector_field("ModalData(phase_deg=...)", _checks.finite)

    def __check_init__(self):
        n = self.frequency_hz.shape
        if self.damping_ratio.shape != n or self.phase_deg.shape != n:
            raise ValueError(
                "`ModalData(frequency_hz=..., damping_ratio=..., phase_deg=...)` must have equal "
                f"lengths, got {n[0]}, {self.damping_ratio.shape[0]}, {self.phase_deg.shape[0]}"
            )


TABLE_1 = ModalData(
    frequency_hz=[49.0, 95.0, 130.0, 1030.0, 1529.0],
    damping_ratio=[0.120, 0.170, 0.090, 0.003, 0.010],
    phase_deg=[-135.0, -155.0, -260.0, -198.0, -31.0],
)
"""The paper's Table 1: modes of h21 (x2/T1) identified at Y_table = 115 mm."""

TABLE_1_POSITION_M = 0.115
"""Where the paper identified Table 1's modes: Y_table = 115 mm (m)."""


TOLERANCES = (0.03, 0.25, 15.0)
"""Default calibration tolerances: frequency 3 % (relative), damping 25 % (relative), resonant
phase 15° (modulo 360°)."""


class ModelUpdate(eqx.Module):
    """Result of :func:`update_model`.

    Attributes:
        drive: the updated drive.
        modes: the model modes paired with the targets (same order as the targets).
        target: the target modal data.
        residual: normalised residuals (3, n_targets): frequency, damping, phase rows;
            ``|r| ≤ 1`` is within tolerance.
        frequency_error: relative frequency errors f/f* − 1.
        damping_error: relative damping errors ζ/ζ* − 1.
        phase_error_deg: phase errors wrapped to (−180°, 180°].
        parameters: the fitted parameter values by path.
        steps: Levenberg–Marquardt steps taken.
        success: whether the solver converged.
        at_bound: by path, whether the fitted value lies at one of its bounds (within 0.1 % of
            the search range, in log space for positive bounds): the bound, not the data,
            decides such a parameter; the solver may still report success.
    """

    drive: BallScrewDrive
    modes: DriveModes
    target: ModalData
    residual: Float[Array, "3 n"]
    frequency_error: Float[Array, " n"]
    damping_error: Float[Array, " n"]
    phase_error_deg: Float[Array, " n"]
    parameters: dict
    steps: Array
    success: Array
    at_bound: dict

    def within(self, tolerances=TOLERANCES) -> np.ndarray:
        """Boolean (3, n): which targets meet the given (frequency, damping, phase) tolerances."""
        return meets((self.frequency_error, self.damping_error, self.phase_error_deg), tolerances)


def modal_errors(modes: DriveModes, target: ModalData) -> tuple[Array, Array, Array]:
    """Errors of modes paired with their targets, index by index: f/f* − 1, ζ/ζ* − 1 and the
    resonant phase's difference wrapped to (−180°, 180°]."""
    return (
        modes.frequency_hz / target.frequency_hz - 1,
        modes.damping_ratio / target.damping_ratio - 1,
        _wrap_deg(modes.phase_deg - target.phase_deg, 180.0),
    )


def meets(errors, tolerances=TOLERANCES) -> np.ndarray:
    """Boolean (3, n): which of the (frequency, damping, phase) ``errors`` of
    :func:`modal_errors` lie within ``tolerances``."""
    return np.stack([np.abs(np.asarray(e)) <= t for e, t in zip(errors, tolerances)])


def _pair(modes: DriveModes, target: ModalData, visibility: float) -> Array:
    """Greedy pairing: each target (in order) takes the nearest visible, unused model mode."""
    n_m = modes.frequency_hz.shape[-1]
    visible = modes.prominence >= visibility
    used = jnp.logical_not(visible)
    picks = []
    for t in range(target.frequency_hz.shape[0]):
        cost = jnp.abs(jnp.log(modes.frequency_hz / target.frequency_hz[t]))
        k = jnp.argmin(jnp.where(used, 1e6 + cost, cost))  # falls back to used modes
        picks.append(k)
        used = used | (jnp.arange(n_m) == k)
    return jax.lax.stop_gradient(jnp.stack(picks))


def _getter(path: str):
    return operator.attrgetter(path)


def _fraction(value, lo, hi, log):
    """Where ``value`` lies in its search range: 0 at ``lo``, 1 at ``hi`` (in log space for
    positive bounds)."""
    if log:
        return (np.log(value) - np.log(lo)) / (np.log(hi) - np.log(lo))
    return (value - lo) / (hi - lo)


def _to_unit(value, lo, hi, log):
    x = np.clip(_fraction(value, lo, hi, log), 1e-6, 1 - 1e-6)
    return np.log(x / (1 - x))


def _at_bound(value: float, lo: float, hi: float, log: bool, room: float = 1e-3) -> bool:
    """Whether ``value`` lies within ``room`` of the search range from a bound."""
    x = _fraction(value, lo, hi, log)
    return bool(x <= room or x >= 1 - room)


def _from_unit(u, lo, hi, log: bool):
    s = jax.nn.sigmoid(u)
    return jnp.exp(jnp.log(lo) + s * (jnp.log(hi) - jnp.log(lo))) if log else lo + s * (hi - lo)


class _Fit(eqx.Module):
    """The static structure of a model update (the data travel as arrays in ``_FitData``)."""

    paths: tuple[str, ...] = eqx.field(static=True)
    log: tuple[bool, ...] = eqx.field(static=True)
    out: int = eqx.field(static=True)
    inp: int = eqx.field(static=True)
    n_modes: int = eqx.field(static=True)
    n_elements: int = eqx.field(static=True)
    nut_correction: bool = eqx.field(static=True)


class _FitData(eqx.Module):
    """Everything the residual reads, as arrays: passed through optimistix's ``args``, so a
    new data set of the same shapes runs the compiled program again (a closure would not)."""

    drive: BallScrewDrive
    target: ModalData
    position_m: Array
    lo: Array
    hi: Array
    tolerances: Array
    visibility: Array
    fit: _Fit


def _build(u, data: _FitData) -> BallScrewDrive:
    fit = data.fit
    values = [_from_unit(u[k], data.lo[k], data.hi[k], fit.log[k]) for k in range(len(fit.paths))]
    getters = [_getter(p) for p in fit.paths]
    return eqx.tree_at(lambda d: [g(d) for g in getters], data.drive, values)


def _model_modes(drive, data: _FitData) -> DriveModes:
    f = data.fit
    return _modes_at(drive, data.position_m, f.out, f.inp, f.n_modes, f.n_elements,
                     f.nut_correction, "update_model")


def _residuals(modes: DriveModes, target: ModalData, tolerances) -> Array:
    """Normalised residuals (3, n): ln(f/f*)/tol_f, ln(ζ/ζ*)/tol_ζ, wrap(φ − φ*)/tol_φ."""
    tf, tz, tp = tolerances[0], tolerances[1], tolerances[2]
    return jnp.stack([
        jnp.log(modes.frequency_hz / target.frequency_hz) / tf,
        jnp.log(modes.damping_ratio / target.damping_ratio) / tz,
        _wrap_deg(modes.phase_deg - target.phase_deg, 180.0) / tp,
    ])


def _update_residual(u, data: _FitData):
    m = _model_modes(_build(u, data), data)
    k = _pair(m, data.target, data.visibility)
    paired = jax.tree_util.tree_map(lambda x: x[k], m)
    return _residuals(paired, data.target, data.tolerances).reshape(-1)


def _update(u0, data: _FitData, solver, max_steps: int):
    sol = optx.least_squares(
        _update_residual, solver, u0, args=data, max_steps=max_steps, throw=False
    )
    fitted = _build(sol.value, data)
    m = _model_modes(fitted, data)
    paired = jax.tree_util.tree_map(lambda x: x[_pair(m, data.target, data.visibility)], m)
    r = _residuals(paired, data.target, data.tolerances)
    return fitted, paired, r, sol.stats["num_steps"], sol.result == optx.RESULTS.successful


_update_jit = eqx.filter_jit(_update)
_DEFAULT_SOLVER = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6)


def update_model(
    drive: BallScrewDrive,
    target: ModalData,
    parameters: Mapping[str, tuple[float, float]],
    position_m: float,
    *,
    output: str = "x2",
    input: str = "T1",
    tolerances: tuple[float, float, float] = (0.03, 0.25, 15.0),
    visibility: float = 0.05,
    n_modes: int = 12,
    twin: TwinOptions | None = None,
    max_steps: int = 200,
    solver: optx.AbstractLeastSquaresSolver | None = None,
) -> ModelUpdate:
    r"""Fit bounded physical parameters so the model's modes match measured modal data.

    Minimises ``Σ r²`` with the normalised residuals of the module docstring by
    Levenberg–Marquardt, differentiating through the eigen-analysis of the twin.  The data
    (drive, target, position, bounds, tolerances) reach the compiled solve as arrays through
    optimistix's ``args``: a second call with new values of the same shapes compiles nothing.

    Args:
        drive: the starting model.
        target: measured modal data of the FRF entry ``output``/``input``.
        parameters: ``{"carriage.pitch_stiffness": (lo, hi), ...}`` — attribute paths of the
            drive's parameters with their physically plausible bounds.  Positive bounds are
            searched in log space; a bound ≤ 0 makes the search linear.
        position_m: the table position at which the data were measured (m).
        output, input: the FRF entry the data are of: the output ``"theta1"``, ``"x2"`` or
            ``"x3"`` over the input ``"T1"`` or ``"F3"`` (default h21 = x2/T1, Table 1's).
        tolerances: (relative frequency, relative damping, phase in degrees) used to normalise
            the residuals; all positive.
        visibility: a model mode can be paired only if its prominence (its share of the FRF at
            its own natural frequency) is at least this (in [0, 1)): modes a measurement could
            not see are not matched.
        n_modes: model modes to pair from (static), at least the number of targets.
        twin: the twin's mesh and nut correction (:class:`fdjax.TwinOptions`).
        max_steps: Levenberg–Marquardt steps (static, ≥ 0; 0 only evaluates the residuals).
        solver: an optimistix least-squares solver (default Levenberg–Marquardt, rtol 1e-6).

    Returns:
        A :class:`ModelUpdate` with the fitted drive and the residuals mode by mode.
    """
    fn = "update_model"
    if not isinstance(target, ModalData):
        raise ValueError(f"`{fn}(target=...)` must be a ModalData, got {type(target).__name__}")
    drive, pos = _check_inputs(drive, position_m, fn)
    if not isinstance(parameters, Mapping) or not parameters:
        raise ValueError(f"`{fn}(parameters=...)` must name at least one parameter")
    paths = tuple(parameters)
    bounds = []
    for p in paths:
        try:
            value = _getter(p)(drive)
        except (AttributeError, TypeError):
            raise ValueError(f"`{fn}(parameters=...)` has no drive parameter {p!r}") from None
        if not isinstance(value, jax.Array) or value.ndim != 0:
            raise ValueError(
                f"`{fn}(parameters=...)`: {p!r} must be a scalar physical parameter of the "
                f"drive, got {type(value).__name__}"
            )
        if p == "screw.loss_factor":
            raise ValueError(
                f"`{fn}(parameters=...)`: 'screw.loss_factor' enters no time-domain model "
                "(fit 'screw.retardation')"
            )
        try:
            lo, hi = (_checks.concrete_float(v, f"{fn}(parameters=...)") for v in parameters[p])
        except (TypeError, ValueError):
            raise ValueError(
                f"`{fn}(parameters=...)` bounds for {p!r} must be a (lo, hi) pair of numbers, "
                f"got {parameters[p]!r}"
            ) from None
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(
                f"`{fn}(parameters=...)` bounds for {p!r} must be finite with lo < hi, "
                f"got ({lo}, {hi})"
            )
        # each bound through the parameter's own constructor, so that the fit cannot leave
        # what a drive may be (a negative stiffness, a bore wider than the screw)
        parent_path, _, leaf = p.rpartition(".")
        parent = _getter(parent_path)(drive) if parent_path else drive
        for v in (lo, hi):
            try:
                dataclasses.replace(parent, **{leaf: v})
            except (TypeError, ValueError) as err:
                raise ValueError(f"`{fn}(parameters=...)` bound {v:g} for {p!r} is not a value "
                                 f"the drive may take: {err}") from None
        bounds.append((lo, hi))
    tol = np.asarray(tolerances, dtype=np.float64) if np.ndim(tolerances) == 1 else None
    if tol is None or tol.shape != (3,):
        raise ValueError(
            f"`{fn}(tolerances=...)` must be (frequency, damping, phase_deg), got {tolerances!r}"
        )
    tol = _checks.positive(jnp.asarray(tol), f"{fn}(tolerances=...)")
    vis = _checks.check(
        _checks.real_scalar(visibility, f"{fn}(visibility=...)"),
        lambda v: (v >= 0) & (v < 1), f"{fn}(visibility=...)", "in [0, 1)",
    )
    twin = _twin_options(twin, fn)
    n_el = int(twin.n_elements)
    n_targets = target.frequency_hz.shape[0]
    n_keep = _checks.static_int(n_modes, f"{fn}(n_modes=...)", n_targets, 2 * n_el + 4)
    max_steps = _checks.static_int(max_steps, f"{fn}(max_steps=...)", 0)
    if solver is None:
        solver = _DEFAULT_SOLVER
    elif not isinstance(solver, optx.AbstractLeastSquaresSolver | optx.AbstractMinimiser):
        raise ValueError(
            f"`{fn}(solver=...)` must be an optimistix least-squares solver, got "
            f"{type(solver).__name__}"
        )
    log = tuple(lo > 0 for lo, _ in bounds)
    u0 = jnp.asarray([
        _to_unit(float(np.clip(float(_getter(p)(drive)), lo, hi)), lo, hi, lg)
        for p, (lo, hi), lg in zip(paths, bounds, log)
    ])
    fit = _Fit(
        paths=paths,
        log=log,
        out=_channel(output, OUTPUTS, fn, "output"),
        inp=_channel(input, INPUTS, fn, "input"),
        n_modes=n_keep,
        n_elements=n_el,
        nut_correction=bool(twin.nut_correction),
    )
    data = _FitData(
        drive=drive,
        target=target,
        position_m=pos,
        lo=jnp.asarray([b[0] for b in bounds]),
        hi=jnp.asarray([b[1] for b in bounds]),
        tolerances=tol,
        visibility=vis,
        fit=fit,
    )
    fitted, paired, r, steps, success = _update_jit(u0, data, solver, max_steps)
    values = {p: float(_getter(p)(fitted)) for p in paths}
    return ModelUpdate(
        drive=fitted,
        modes=paired,
        target=target,
        residual=r,
        **dict(zip(("frequency_error", "damping_error", "phase_error_deg"),
                   modal_errors(paired, target))),
        parameters=values,
        steps=steps,
        success=success,
        at_bound={p: _at_bound(values[p], lo, hi, lg)
                  for p, (lo, hi), lg in zip(paths, bounds, log)},
    )
