r"""Time simulation of the closed feed-drive loop (paper Sec. 5, Figs. 16–17).

:func:`simulate` runs any controller around the drive's twin on a reference motion with the
method it is given (:class:`fdjax.SampledData`, the loop as the servo runs it, or
:class:`fdjax.PadeODE`, the continuous loop by diffrax); the method carries the behaviour.
With ``moving=True`` the plant's matrices follow the table, Y(t) = Y₀ + r(t)
(:mod:`fdjax._simulation._moving`).

**Outputs** (:class:`Simulation`): θ1, x2, x3, the motor torque T1 and current T1/k_m, the
tracking errors e2 = r − x2 (scale) and e3 = r − x3 (tool point).  A run that diverges — a
state turns non-finite, or the scale error exceeds ``error_bound`` — stops there: the outputs
are frozen at their last finite values (no NaN reaches the user) and the result code says so.
``throw=True`` (default) raises; eagerly with the values (position, pole, time), under
``jit``/``vmap`` with the result code's own message.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .. import _checks, _memory
from .._control._controllers import AbstractController
from .._control._servo import Servo
from .._drive._model import BallScrewDrive
from .._drive._twin import StateSpace, TwinOptions, _twin_options, state_space
from .._results import RESULTS
from ._methods import AbstractLoopModel, SampledData, _check_filters_sampled, growing
from ._moving import MovingPlant

__all__ = ["Simulation", "simulate", "SIMULATION_OUTPUTS"]

SIMULATION_OUTPUTS = ("theta1", "x2", "x3", "T1")
"""Outputs of a closed loop and of a run: motor angle (rad), scale and tool positions (m),
torque (N·m)."""


class Simulation(eqx.Module):
    r"""A simulated run of the closed loop.

    Attributes:
        t: output times (s), (n,).
        reference: r, ṙ, r̈ (m, m/s, m/s²), (n, 3).
        theta1: motor angle (rad).  x2: scale position (m).  x3: tool-point position (m).
        torque: motor torque T1 (N·m).  current: T1/k_motor (A).
        error_scale: e2 = r − x2 (m).  error_tool: e3 = r − x3 (m).
        position_m: table position Y (m) at each output time: Y₀ + r(t) (the plant is frozen at
            Y₀ unless the run was ``moving``).
        result: :class:`fdjax.RESULTS` code.
        failed_at: index of the first output sample after which the run was stopped (n when
            it ran to the end).
        growth_rate: max Re s over the closed loop's poles (1/s) for a frozen plant, from the
            spectral radius of the one-step transition matrix (works under jit and vmap);
            ≥ 0 makes ``result`` ``unstable`` even before the run has grown past
            ``error_bound``.  For the moving table, that of the loop at rest where the motion
            starts or where it ends, whichever is less stable (a run through an unstable
            stretch between is judged by its error).
        travel_m: the drive's travel (m, static; ±∞ for a StateSpace plant), for the
            out-of-travel message.
        unstable_at_m: for the moving table, the position of that loop at rest (m); None
            otherwise (the loop is the one at Y₀).
    """

    t: Float[Array, "*batch n"]
    reference: Float[Array, "*batch n 3"]
    theta1: Float[Array, "*batch n"]
    x2: Float[Array, "*batch n"]
    x3: Float[Array, "*batch n"]
    torque: Float[Array, "*batch n"]
    current: Float[Array, "*batch n"]
    error_scale: Float[Array, "*batch n"]
    error_tool: Float[Array, "*batch n"]
    position_m: Float[Array, "*batch n"]
    result: RESULTS
    failed_at: Int[Array, "*batch"]
    growth_rate: Float[Array, "*batch"] | None
    travel_m: tuple[float, float] = eqx.field(static=True, default=(-math.inf, math.inf))
    unstable_at_m: Float[Array, "*batch"] | None = None

    def rms_error(self, which: str = "scale") -> Float[Array, "*batch"]:
        """RMS tracking error (m) over the run: ``"scale"`` (r − x2) or ``"tool"`` (r − x3)."""
        errors = {"scale": self.error_scale, "tool": self.error_tool}
        e = errors.get(which) if isinstance(which, str) else None
        if e is None:
            raise ValueError(
                f"`Simulation.rms_error(which=...)` must be 'scale' or 'tool', got {which!r}"
            )
        return jnp.sqrt(jnp.mean(e * e, axis=-1))

    @property
    def message(self) -> str:
        """One line per run, e.g. "closed loop unstable at table position 0.7 m: growing at
        12.3 1/s" or "… diverged …: stopped at t = 0.123 s, table position 0.7 m"."""
        codes = np.atleast_1d(np.asarray(self.result._value))
        k = np.atleast_1d(np.asarray(self.failed_at))
        t = np.asarray(self.t).reshape(codes.shape[0], -1)
        pos = np.asarray(self.position_m).reshape(codes.shape[0], -1)
        # Y₀, where the loop is built (position_m is Y₀ + r(t), and r(0) may be off zero)
        r0 = np.asarray(self.reference)[..., 0, 0].reshape(-1)
        names = {int(getattr(RESULTS, a)._value): a for a in RESULTS._name_to_item}
        lo, hi = self.travel_m
        lines = []
        for i, code in enumerate(codes):
            name = names[int(code)]
            j = min(int(k[i]), t.shape[1] - 1)
            y0 = pos[i, 0] - r0[i]
            if name == "successful":
                lines.append(f"simulation ok at table position {y0:.4g} m")
            elif name == "unstable":
                g = np.atleast_1d(np.asarray(self.growth_rate))[i]
                at = y0 if self.unstable_at_m is None else np.atleast_1d(
                    np.asarray(self.unstable_at_m))[i]
                rest = "" if self.unstable_at_m is None else " (the loop at rest there)"
                lines.append(f"closed loop unstable at table position {at:.4g} m{rest}: "
                             f"growing at {g:.4g} 1/s")
            elif name == "out_of_travel":
                far = pos[i, np.argmax(np.maximum(pos[i] - hi, lo - pos[i]))]
                lines.append(
                    f"the reference motion from table position {y0:.4g} m reaches {far:.4g} m, "
                    f"outside the travel [{lo:.4g}, {hi:.4g}] m"
                )
            else:
                lines.append(
                    f"{RESULTS[getattr(RESULTS, name)]}: stopped at t = {t[i, j]:.6g} s, "
                    f"table position {pos[i, j]:.4g} m"
                )
        return "\n".join(lines)


def simulate(
    controller: AbstractController,
    plant: StateSpace | BallScrewDrive,
    reference,
    method: AbstractLoopModel = SampledData(),
    *,
    servo: Servo = Servo(),
    position_m: Float[ArrayLike, ""] | None = None,
    duration: float | None = None,
    disturbance: Float[ArrayLike, " n"] | None = None,
    moving: bool = False,
    twin: TwinOptions | None = None,
    error_bound: float = 0.01,
    throw: bool = True,
) -> Simulation:
    r"""Simulate the closed loop on a reference motion (paper Figs. 16–17).

    The controller's law around the drive's twin, from rest at t = 0, over ``duration``
    seconds, with feed-forward from the same reference:

    * ``method=SampledData()`` — the exact sampled-data loop at the servo's period (ZOH plant,
      discrete law, whole-sample delay), run by the lifted recursion; outputs every period;
    * ``method=PadeODE(dt, pade_order, solver, …)`` — the continuous loop with a Padé delay,
      solved by ``diffrax.diffeqsolve``; outputs every ``dt``.

    With ``moving=True`` (a drive plant) the plant's matrices follow the table, Y(t) = Y₀ + r(t):
    the FE model is rebuilt along the motion and projected on the modes at Y₀ (exponential
    midpoint rule over each step; no growth rate, divergence is still caught).

    Differentiable (``jax.grad``) in every leaf of ``controller`` and of a drive plant;
    ``jax.vmap`` over positions compiles once (pass ``throw=False`` and read ``result``).

    Args:
        controller: the controller (e.g. :class:`fdjax.DoubleLoop`, :class:`fdjax.PIDLoop`).
        plant: a :class:`fdjax.StateSpace` at one position, or a :class:`fdjax.BallScrewDrive`
            with ``position_m`` (its twin is built with :func:`fdjax.state_space`).
        reference: the motion, any object with ``evaluate(t) -> (r, ṙ, r̈, …)`` such as a
            :class:`fdjax.Trajectory`; r is the table's displacement from Y₀ (m).
        method: :class:`fdjax.SampledData` (default) or :class:`fdjax.PadeODE`.
        servo: the servo's hardware (period, delay, motor constant).
        position_m: table position Y₀ (m) for a drive plant; Y₀ + r(t) must stay inside the
            drive's travel.
        duration: simulated time (s), static; default the reference's ``duration``.  At
            least one output period; the run covers it in whole output periods (rounded to
            the nearest).  A run holds about 320 bytes per output sample (520 with
            :class:`fdjax.PadeODE`); one that would not fit in the memory available is
            refused before it starts.
        disturbance: force F3 at the tool point (N) on the output grid, (n,); default 0.
        moving: moving-table mode (a drive plant; slower: the loop is rebuilt every step).
        twin: how a drive plant becomes its twin (:class:`fdjax.TwinOptions`: mesh, kept
            modes, corrections); the moving table uses its mesh and kept modes.
        error_bound: a scale error |r − x2| beyond this (m) counts as divergence.
        throw: raise when the result is not ``successful`` (unstable, diverged, solver failed,
            out of travel) — eagerly naming the table position (and the growth rate, or the
            time it stopped); under jit with the result code's message.

    Returns:
        A :class:`Simulation`; ``result`` says how it ended and ``message`` says it in words.
    """
    fn = "simulate"
    _checks.instance(controller, AbstractController, f"{fn}(controller=...)",
                     "an fdjax controller (DoubleLoop, PIDLoop or a subclass of "
                     "fdjax.AbstractController)")
    throw = _checks.static_bool(throw, f"{fn}(throw=...)")
    controller = _checks.finite_parameters(controller, f"{fn}(controller=...)", traced=throw)
    _checks.instance(servo, Servo, f"{fn}(servo=...)")
    if not callable(getattr(method, "run", None)):
        raise TypeError(
            f"`{fn}(method=...)` must be fdjax.SampledData() or fdjax.PadeODE(), "
            f"got {type(method).__name__}"
        )
    if not callable(getattr(reference, "evaluate", None)):
        raise TypeError(
            f"`{fn}(reference=...)` must have an evaluate(t) method (e.g. an "
            f"fdjax.Trajectory), got {type(reference).__name__}"
        )
    given = duration is not None
    if duration is None:
        duration = getattr(reference, "duration", None)
        if duration is None:
            raise ValueError(f"`{fn}(duration=...)` is required for this reference")
        h = getattr(reference, "durations", None)
        if not _checks.is_concrete(duration) and h is not None and _checks.is_concrete(h):
            # inside jit, a closed-over trajectory's sums are staged: add its segments' durations
            # on the host, in order (as Trajectory.t_knots does)
            duration = float(np.cumsum(np.asarray(h))[-1])
    if not _checks.is_concrete(duration):
        if given:
            raise ValueError(f"`{fn}(duration=...)` must be a concrete number (it sets the "
                             "number of output samples), not a value traced by jit")
        raise ValueError(
            f"`{fn}(reference=...)` was built inside, or passed into, a traced function (jit, "
            "vmap, grad), so its duration, which sets the number of output samples, is not "
            f"known there: build the motion outside and close over it, or give "
            f"`{fn}(duration=...)` as a number")
    duration = _checks.concrete_float(duration, f"{fn}(duration=...)")
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"`{fn}(duration=...)` must be positive, got {duration:.6g}")
    eb = _checks.positive(_checks.real_scalar(error_bound, f"{fn}(error_bound=...)"),
                          f"{fn}(error_bound=...)")
    moving = _checks.static_bool(moving, f"{fn}(moving=...)")
    if not moving:  # a moving table rebuilds the loop and says so itself
        method.check_use(controller, plant if isinstance(plant, StateSpace) else None, servo,
                         f"{fn}(method=...)")
    elif isinstance(method, SampledData):  # the filters it discretises at every step
        _check_filters_sampled(controller, servo, fn)
    dt = method.output_period(servo)
    n = int(round(duration / dt)) + 1
    if duration < dt * (1 - 1e-9):  # a run of one sample (or PadeODE's of one output time)
        raise ValueError(f"`{fn}(duration=...)` must span at least one output period of "
                         f"{method.name} ({dt:.6g} s), got {duration:.6g} s")
    need, avail = n * method.bytes_per_sample, _memory.available_bytes()
    if avail is not None and need > avail:
        raise ValueError(
            f"`{fn}(duration=...)`: {duration:.6g} s is {n} output samples (every "
            f"{dt:.3g} s), about {need / 2**30:.1f} GiB, more than the "
            f"{avail / 2**30:.1f} GiB of memory available; simulate a shorter run"
        )
    twin = _twin_options(twin, fn)
    if isinstance(plant, BallScrewDrive):
        if position_m is None:
            raise ValueError(f"`{fn}(position_m=...)` is required when the plant is a drive")
        pos0 = _checks.real_scalar(position_m, f"{fn}(position_m=...)")
        pos0 = plant._check_travel(pos0, fn)
        pos0 = controller.check_position(pos0, f"{fn}(position_m=...)")
        lo, hi = plant.travel_m
        if throw:  # else the run's result says out_of_travel
            _check_reach(reference, pos0, lo, hi, fn, duration)
        twin = twin.resolve(plant, fn)
        travel = (float(lo), float(hi))
    elif isinstance(plant, StateSpace):
        if position_m is not None or moving:
            raise ValueError(
                f"`{fn}(position_m=..., moving=True)` need a BallScrewDrive plant (the model is "
                f"rebuilt along the motion), got a {type(plant).__name__}"
            )
        if plant.A.ndim != 2:
            raise ValueError(
                f"`{fn}(plant=...)` must be the twin at one position (A of shape (n, n)), got a "
                f"batch of twins (A of shape {plant.A.shape}): jax.vmap the simulation over "
                "them, or give the drive with one position_m")
        pos0, travel = None, (-math.inf, math.inf)
    else:
        raise TypeError(
            f"`{fn}(plant=...)` must be an fdjax.StateSpace or BallScrewDrive, "
            f"got {type(plant).__name__}"
        )
    if disturbance is None:
        force = jnp.zeros(n)
    else:
        force = _checks.real_array(disturbance, f"{fn}(disturbance=...)")
        if force.shape != (n,):
            raise ValueError(
                f"`{fn}(disturbance=...)` must have shape ({n},) (one value per "
                f"output sample), got {force.shape}"
            )
        force = _checks.finite(force, f"{fn}(disturbance=...)")
    sim = _simulate_jit(
        controller, plant, reference, method, servo, pos0, force, n, bool(moving),
        twin, eb, travel,
    )
    if throw:
        failed = sim.result != RESULTS.successful
        if _checks.is_concrete(sim.failed_at):
            if bool(np.any(np.asarray(failed))):
                if bool(np.any(np.asarray(sim.result == RESULTS.out_of_travel))):
                    raise ValueError(f"`{fn}(reference=..., position_m=...)`: {sim.message}")
                msg = _with_pole(sim, controller, plant, method, servo, pos0, twin)
                r0 = float(np.asarray(sim.reference).reshape(-1, 3)[0, 0])  # r at t = 0
                if int(np.atleast_1d(np.asarray(sim.failed_at))[0]) == 0 and r0 != 0.0:
                    msg += (f"; the reference starts at r(0) = {r0:.6g} m, a step (r is the "
                            f"displacement from {fn}(position_m=...), where the loop starts at "
                            "rest)")
                raise RuntimeError(msg)
        else:
            sim = sim.result.error_if(sim, failed)
    return sim


def _check_reach(reference, pos0, lo, hi, fn, duration):
    """Before a run of the whole motion: a reference with exact extremes (a
    :class:`fdjax.Trajectory`) keeps the table inside the travel from ``pos0``, or the error
    says where it goes (and, for a move of a metre or more that fits once divided by 1000,
    that it was given in mm).  A run of part of the motion (``duration`` shorter) is judged by
    the positions it runs through, as under ``jit``."""
    reach = getattr(reference, "position_range", None)
    if reach is None or not _checks.is_concrete(pos0):
        return
    whole = getattr(reference, "duration", None)
    if whole is None or not _checks.is_concrete(whole) or duration < float(whole):
        return
    r_lo, r_hi = reach()
    if not (_checks.is_concrete(r_lo) and _checks.is_concrete(r_hi)):
        return
    y0, r_lo, r_hi = float(pos0), float(r_lo), float(r_hi)
    if lo <= y0 + r_lo and y0 + r_hi <= hi:
        return
    far = y0 + (r_hi if y0 + r_hi > hi else r_lo)
    msg = (f"`{fn}(reference=..., position_m=...)`: the reference motion from table position "
           f"{y0:.4g} m reaches {far:.4g} m, outside the travel [{lo:.4g}, {hi:.4g}] m")
    if abs(far - y0) >= 1.0 and lo <= y0 + r_lo / 1000 and y0 + r_hi / 1000 <= hi:
        msg += (f"; motions are in metres: a move of {far - y0:.6g} mm is "
                f"{(far - y0) / 1000:.6g} m")
    raise ValueError(msg)


def _with_pole(sim, controller, plant, method, servo, pos0, twin) -> str:
    """The message, with the least stable pole's frequency for an unstable frozen loop (found
    on the host: a batched non-symmetric eig has dead-locked XLA:CPU)."""
    msg = sim.message
    if not bool(np.any(np.asarray(sim.result == RESULTS.unstable))) or np.ndim(sim.failed_at):
        return msg
    at = pos0 if sim.unstable_at_m is None else float(sim.unstable_at_m)  # moving: rest's
    model = plant if pos0 is None else state_space(plant, at, twin=twin)
    A = np.asarray(method.closed_loop(controller, model, servo).A)
    lam = np.asarray(method.poles_to_s(jnp.asarray(np.linalg.eigvals(A)), servo))
    pole = lam[np.argmax(lam.real)]
    return msg.replace(": growing", f": pole at {abs(pole.imag) / (2 * np.pi):.4g} Hz growing")


def _simulate_impl(
    controller, plant, reference, method, servo, pos0, force, n, moving, twin, bound, travel,
):
    dt = method.output_period(servo)
    t = jnp.arange(n, dtype=jnp.float64) * dt
    r, v, a = (jnp.asarray(x, jnp.float64) for x in reference.evaluate(t)[:3])
    W = jnp.stack([r, v, a, force], 1)
    unstable_at = None
    if pos0 is None:  # a StateSpace plant
        Y, failed_at, result, growth = method.run(controller, plant, W, servo, bound)
        pos = plant.position_m + r
        outside = jnp.zeros((), bool)
    else:
        pos = pos0 + r
        lo, hi = travel
        if moving:
            mid = pos0 + jnp.asarray(reference.evaluate(t + 0.5 * dt)[0], jnp.float64)
            inside = lambda y: (y >= lo) & (y <= hi)
            outside = ~jnp.all(inside(pos) & inside(mid))
            # Clipped so that a run that is reported out of travel still builds valid models.
            clip = lambda y: jnp.clip(y, lo, hi)
            moving_plant = MovingPlant.at_rest(plant, pos0, twin, twin.kept_modes)
            Y, failed_at, result = method.run_moving(
                controller, moving_plant, W, clip(pos), clip(mid), servo, bound
            )
            # the loop at rest where the motion starts and where it ends: unstable there, the
            # run is (a run passing through an unstable stretch is judged by its error)
            ends = jnp.stack([pos0, clip(pos[-1])])
            # on the run's own basis (the plant the steps are built from, without the FE
            # model's eigen-decomposition at each end)
            g_ends = jax.vmap(lambda y: method.frozen_growth(
                controller, moving_plant.at(y), servo))(ends)
            worst = jnp.argmax(g_ends)
            growth, unstable_at = g_ends[worst], ends[worst]
            # as the frozen run: growing makes it unstable, diverged or not
            result = RESULTS.where(growing(growth, servo.period), RESULTS.unstable, result)
        else:
            outside = ~jnp.all((pos >= lo) & (pos <= hi))
            model = state_space(plant, pos0, twin=twin)
            Y, failed_at, result, growth = method.run(controller, model, W, servo, bound)
    result = RESULTS.where(outside, RESULTS.out_of_travel, result)
    return Simulation(
        t=t,
        reference=W[:, :3],
        theta1=Y[:, 0],
        x2=Y[:, 1],
        x3=Y[:, 2],
        torque=Y[:, 3],
        current=Y[:, 3] / servo.k_motor,
        error_scale=r - Y[:, 1],
        error_tool=r - Y[:, 2],
        position_m=pos,
        result=result,
        failed_at=failed_at,
        growth_rate=growth,
        travel_m=travel,
        unstable_at_m=unstable_at,
    )


_simulate_traced = eqx.debug.assert_max_traces(_simulate_impl, max_traces=None)
_simulate_jit = eqx.filter_jit(_simulate_traced)
