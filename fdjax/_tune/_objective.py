r"""The tuning objective: RMS tracking error of the sampled loop plus smooth robustness
penalties (paper Sec. 5, Figs. 16–18).

At a table position Y the drive's twin is built once and shared by a sampled-data simulation
of the reference motion and the open loops on the unit circle:

    J(controller, Y) = e_rms / e_ref
                       + w_m Σ_breaks P_margin(L_b)                   (modulus, gain, phase)
                       + w_s softplus((g − g_max)/g_w)²                (closed-loop poles)
                       + w_c softplus((max|i| − i_max)/(0.05 i_max))²  (motor current),

(:meth:`Objective.margin_term` is the second line, from the open loops alone;
:meth:`Objective.simulated_term` the rest, from one run; :meth:`Objective.unsimulated_term`
the second and third lines, without a run), with e_rms the RMS error at the scale
(or the tool point), P_margin the smooth penalties of :func:`margin_penalty` on every break
point of the loop (plant input, speed feedback, scale), g the growth rate of the sampled
closed loop's least stable pole (s = ln z / T; negative when stable), max|i| the peak
current command and i_max the servo's current rating (``Servo.current_limit``).  An unstable
candidate gets a large, finite value and a finite gradient: the simulation stops at its error
bound and freezes its outputs, the growth-rate barrier grows quadratically; nothing is NaN.
Final designs are then checked with the exact margins and the eigenvalues
(:func:`fdjax.loop_margins`, :func:`fdjax.check_stability`).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import _checks
from .._analysis import _open_loop
from .._checks import is_concrete
from .._control._controllers import AbstractController
from .._control._servo import Servo
from .._drive._model import BallScrewDrive
from .._drive._twin import TwinOptions, state_space
from .._results import RESULTS
from .._simulation import SampledData, simulate
from .._trajectory import Trajectory
from ._penalties import MARGIN_REQUIREMENTS, grid_below_nyquist, penalty

__all__ = ["Objective", "ObjectiveTerms"]


def _scalar(x):
    # weights, widths and scales are traced leaves: a new value compiles nothing
    return jnp.asarray(x, jnp.float64)


def _array(x):
    # the grid is a leaf: a list or a float32 grid becomes the float64 array that jit sees
    return x if isinstance(x, jax.core.Tracer) else jnp.asarray(_checks.real_array(
        x, "Objective(freq_hz=...)"), jnp.float64)


class ObjectiveTerms(eqx.Module):
    """The terms of :class:`Objective` at one position (arrays, batched under ``vmap``).

    Attributes:
        total: J.
        rms_error_m: RMS tracking error (m).
        margin_penalty: Σ over the break points of the smooth margin penalties.
        growth_rate: growth rate of the least stable closed-loop pole (1/s).
        peak_current_a: max |current command| (A).
        stable: the sampled closed loop's poles all decay and the run succeeded.
    """

    total: Float[Array, "*batch"]
    rms_error_m: Float[Array, "*batch"]
    margin_penalty: Float[Array, "*batch"]
    growth_rate: Float[Array, "*batch"]
    peak_current_a: Float[Array, "*batch"]
    stable: Array


class Objective(eqx.Module):
    r"""J(controller, Y) of the module docstring, a pure function of the controller's leaves and
    the position (``vmap`` over positions, ``grad`` in the controller).

    Attributes:
        reference: the reference motion (e.g. :func:`fdjax.reciprocating`).
        freq_hz: the frequency grid of the margin penalties (Hz), below the Nyquist frequency;
            dense enough around the loop's resonances.
        servo: the servo hardware (not tuned).
        twin: how the drive becomes its twin (static); the tuners fix its number of kept
            modes for their drive first (:meth:`resolved`).
        output: ``"scale"`` (x2) or ``"tool"`` (x3), static.
        error_scale_m: e_ref (m).
        modulus_margin, gain_margin_db, phase_margin_deg: the requirements (static).
        margin_weight, stability_weight, current_weight: w_m, w_s, w_c.
        margin_width: the margin penalties' width w: a design settles where the
            penalty's slope meets that of the error, a few w above each requirement.
        margin_sharpness: the smooth minimum's β over the grid (error ≤ log(n)/β).
        max_growth_rate: g_max (1/s), static: the least stable pole must decay at least at −g_max.
        current_limit_a: i_max (A), static; None (default): the servo's rating,
            ``servo.current_limit``.
        duration: simulated time (s), static; default the reference's duration.
        error_bound_m: a run whose error passes this bound (m) stops; an unstable or diverged
            run's tracking term is this bound over e_ref.

    The weights, ``error_scale_m``, ``margin_width`` and ``margin_sharpness`` are array leaves:
    an objective with other values runs the programs compiled for the first.
    """

    reference: Trajectory
    freq_hz: Float[Array, " freq"] = eqx.field(converter=_array)
    servo: Servo = Servo()
    twin: TwinOptions | None = eqx.field(static=True, default=None)
    output: str = eqx.field(static=True, default="scale")
    error_scale_m: Float[Array, ""] = eqx.field(converter=_scalar, default=1e-6)
    modulus_margin: float = eqx.field(static=True, default=0.5)
    gain_margin_db: float = eqx.field(static=True, default=6.0)
    phase_margin_deg: float = eqx.field(static=True, default=30.0)
    margin_weight: Float[Array, ""] = eqx.field(converter=_scalar, default=10.0)
    margin_width: Float[Array, ""] = eqx.field(converter=_scalar, default=0.05)
    margin_sharpness: Float[Array, ""] = eqx.field(converter=_scalar, default=200.0)
    stability_weight: Float[Array, ""] = eqx.field(converter=_scalar, default=10.0)
    max_growth_rate: float = eqx.field(static=True, default=-5.0)
    current_weight: Float[Array, ""] = eqx.field(converter=_scalar, default=1.0)
    current_limit_a: float | None = eqx.field(static=True, default=None)
    duration: float | None = eqx.field(static=True, default=None)
    error_bound_m: float = eqx.field(static=True, default=0.01)

    def __post_init__(self):
        # the run's length sets the number of samples: static, read from the concrete reference
        if self.duration is None and isinstance(self.reference, Trajectory):
            self.duration = float(self.reference.duration)

    def __check_init__(self):
        _checks.instance(self.servo, Servo, "Objective(servo=...)")
        if self.output not in ("scale", "tool"):
            raise ValueError(f"`Objective(output=...)` must be 'scale' or 'tool', got "
                             f"{self.output!r}")
        _checks.instance(self.reference, Trajectory, "Objective(reference=...)")
        f = jnp.asarray(self.freq_hz)
        if f.ndim != 1 or f.shape[0] < 8:
            raise ValueError(f"`Objective(freq_hz=...)` must be a 1-D grid of at least 8 "
                             f"frequencies, got shape {f.shape}")
        if is_concrete(f):  # checked where the grid is given, not at the first evaluation
            grid_below_nyquist(f, self.servo, "Objective(freq_hz=...)")
        for name in ("error_scale_m", "margin_width", "margin_sharpness", "margin_weight",
                     "stability_weight", "current_weight"):
            v = getattr(self, name)
            if v.ndim != 0:
                raise ValueError(f"`Objective({name}=...)` must be a scalar, got shape {v.shape}")
            if is_concrete(v) and not (math.isfinite(float(v)) and float(v) >= (
                    0 if name.endswith("weight") else 1e-300)):
                kind = "non-negative" if name.endswith("weight") else "positive"
                raise ValueError(f"`Objective({name}=...)` must be finite and {kind}, got "
                                 f"{float(v)!r}")
        # the static settings: each fixes what is compiled, so each is checked here
        for name, ok, expected in MARGIN_REQUIREMENTS + (
            ("max_growth_rate", lambda v: True, "finite (1/s)"),
            ("duration", lambda v: v > 0, "finite and positive (s)"),
            ("error_bound_m", lambda v: v > 0, "finite and positive (m)"),
        ):
            _checks.static_number(getattr(self, name), f"Objective({name}=...)", ok, expected)
        if self.current_limit_a is not None:
            _checks.static_number(self.current_limit_a, "Objective(current_limit_a=...)",
                                  lambda v: v > 0, "finite and positive (A), or None (the "
                                  "servo's rating)")

    def resolved(self, drive: BallScrewDrive, fn: str = "Objective") -> Objective:
        """This objective with its twin's number of kept modes counted for ``drive`` (when the
        twin leaves it to the band): the state size is then fixed before ``jit``/``vmap``/
        ``grad`` see the drive, and the objective runs the same twin inside them as outside."""
        twin = (TwinOptions() if self.twin is None else self.twin).resolve(drive, fn)
        return self if twin == self.twin else dataclasses.replace(self, twin=twin)

    def _checked(self, fn, controller, drive, position_m):
        """The twin at the position and the discretisation that the run and the open loops
        share (one discrete law and one zero-order-hold plant)."""
        _checks.instance(controller, AbstractController, f"{fn}(controller=...)",
                         "an fdjax controller")
        _checks.instance(drive, BallScrewDrive, f"{fn}(drive=...)")
        position_m = drive._check_travel(position_m, fn)
        if position_m.ndim != 0:
            raise ValueError(f"`{fn}(position_m=...)` must be one table position (a scalar; "
                             f"jax.vmap the objective over positions), got shape "
                             f"{position_m.shape}")
        plant = state_space(drive, position_m, twin=self.twin)
        return plant, SampledData().sharing(controller, plant, self.servo)

    def _penalty(self, controller, plant, method):
        """Σ over the break points of the smooth margin penalties (unweighted)."""
        # unguarded: the tuners refuse non-finite trial points themselves
        loops = _open_loop(controller, plant, self.freq_hz, servo=self.servo, method=method,
                           traced=False)
        # the break points' loops as one batch: one penalty program for all of them
        Ls = jnp.stack([L for L in (loops.plant_input, loops.speed, loops.position)
                        if L is not None])
        return jnp.sum(penalty(Ls, self.modulus_margin, self.gain_margin_db,
                               self.phase_margin_deg, self.margin_sharpness, self.margin_width))

    def margin_term(self, controller: AbstractController, drive: BallScrewDrive,
                    position_m: Float[ArrayLike, ""]) -> Float[Array, ""]:
        r"""The weighted margin penalties w_m Σ_breaks P_margin(L_b), the part of J computed
        from the open loops on the frequency grid alone (no simulation): J minus this term is
        the part that needs the run.  Equal to ``margin_weight`` × the ``margin_penalty`` of
        :meth:`__call__`'s terms."""
        plant, method = self._checked("Objective.margin_term", controller, drive, position_m)
        return self.margin_weight * self._penalty(controller, plant, method)

    def _barrier(self, g):
        """The growth-rate barrier, unweighted: softplus((g − g_max)/g_w)²."""
        g_w = max(abs(self.max_growth_rate), 1.0)
        return jax.nn.softplus((g - self.max_growth_rate) / g_w) ** 2

    def unsimulated_term(self, controller: AbstractController, drive: BallScrewDrive,
                         position_m: Float[ArrayLike, ""]) -> Float[Array, ""]:
        r"""The margin term plus the growth-rate barrier, w_m Σ_breaks P_margin(L_b) +
        w_s softplus((g − g_max)/g_w)²: the part of J that needs no run of the loop (the open
        loops on the frequency grid and the sampled closed loop's least stable pole, as the
        run's own barrier takes it)."""
        plant, method = self._checked("Objective.unsimulated_term", controller, drive,
                                      position_m)
        g = method.frozen_growth(controller, plant, self.servo)
        return (self.margin_weight * self._penalty(controller, plant, method)
                + self.stability_weight * self._barrier(g))

    def __call__(self, controller: AbstractController, drive: BallScrewDrive,
                 position_m: Float[ArrayLike, ""]) -> ObjectiveTerms:
        """The terms of J at table position ``position_m`` (m)."""
        plant, method = self._checked("Objective", controller, drive, position_m)
        pen = self._penalty(controller, plant, method)
        return self._terms(controller, plant, method, pen)

    def simulated_term(self, controller: AbstractController, drive: BallScrewDrive,
                       position_m: Float[ArrayLike, ""]) -> Float[Array, ""]:
        r"""J less its margin term (:meth:`margin_term`): the tracking error and the barriers,
        from one run of the sampled loop and its poles, without the open loops."""
        plant, method = self._checked("Objective.simulated_term", controller, drive,
                                      position_m)
        return self._terms(controller, plant, method, jnp.zeros(())).total

    def _terms(self, controller, plant, method, pen) -> ObjectiveTerms:
        """The terms of J from one run, the margin penalties ``pen`` given."""
        sim = simulate(controller, plant, self.reference, method, servo=self.servo,
                       duration=self.duration, error_bound=self.error_bound_m, throw=False)
        rms = sim.rms_error(self.output)
        g = sim.growth_rate
        barrier = self._barrier(g)
        i_peak = jnp.max(jnp.abs(sim.current))
        i_max = self.servo.current_limit if self.current_limit_a is None else self.current_limit_a
        ok = (g < 0) & (sim.result == RESULTS.successful)
        # a growing run's last current is no measure of the design: capped, without gradient
        i_used = jnp.where(ok, i_peak, jnp.minimum(jax.lax.stop_gradient(i_peak), 2 * i_max))
        current = jax.nn.softplus((i_used - i_max) / (0.05 * i_max)) ** 2
        # An unstable or diverged run counts as the error bound it was stopped at, with no
        # gradient of its own (that of an exponentially growing run is huge): the penalties
        # and the growth-rate barrier lead back to stability.
        tracking = jnp.where(ok, rms, jax.lax.stop_gradient(rms))
        tracking = jnp.where(ok, tracking, self.error_bound_m) / self.error_scale_m
        total = (tracking + self.margin_weight * pen
                 + self.stability_weight * barrier + self.current_weight * current)
        return ObjectiveTerms(total, rms, pen, g, i_peak, ok)
