r"""Loop analysis of any controller around the drive (paper Sec. 4, Figs. 5, 7, 13–14): open
loops, stability margins of the loop as it runs, closed loops and their stability.

Every function takes the controller (a :class:`fdjax.AbstractController`), the plant, the servo's
hardware (:class:`fdjax.Servo`) and the loop model ``method``: :class:`fdjax.SampledData`
(default: the sampled loop as the servo runs it — zero-order-hold plant, backward-difference
speed, discrete filters, whole-sample delay), :class:`fdjax.Continuous` (exact delay
e^{−iωτ}, Padé where a realisation is needed) or :class:`fdjax.PadeODE`.

The plant is one of

* a :class:`fdjax.BallScrewDrive` with ``position_m`` (scalar or 1-D): its time-domain twin is
  built at each position (:func:`fdjax.state_space`), all positions in one compiled program;
* a :class:`fdjax.StateSpace` (the twin at one position, or a batch of them from ``jax.vmap``);
* an FRF array (…, n_freq, 3, 2) on ``freq_hz`` (outputs θ1, x2, x3; inputs T1, F3), e.g.
  ``drive.frf(positions, freq_hz)`` or a measurement, with ``screw_ratio`` (continuous models
  only: the sampled loop needs the plant in state space).

The open loops are broken at the plant input (``plant_input``), at the speed feedback
(``speed``, the position loop open) and at the scale (``position``, the speed loop closed);
see :mod:`fdjax._control._interconnect` for the equations.  Margins follow python-control's
conventions (:mod:`fdjax._control._margins`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Complex, Float

from . import _checks
from ._control._controllers import AbstractController
from ._control._margins import Margins, grid_margins, model_margins
from ._control._servo import Servo
from ._drive._model import BallScrewDrive
from ._drive._twin import StateSpace, TwinOptions, _twin_options, state_space
from ._lti import LTI
from ._results import RESULTS
from ._simulation._lifted import MARGINAL
from ._simulation._methods import AbstractLoopModel, SampledData
from ._sweep import map_positions

__all__ = [
    "OpenLoop",
    "LoopMargins",
    "Stability",
    "open_loop",
    "loop_margins",
    "stability_margins",
    "closed_loop",
    "check_stability",
    "gain_headroom",
]

_TWO_PI = 2.0 * math.pi
_LOOPS = ("plant_input", "speed", "position")


class OpenLoop(eqx.Module):
    """Open-loop frequency responses of a controller around a plant.

    Attributes:
        freq_hz: the frequency grid (Hz), (n_freq,).
        plant_input: L_u, broken at the plant input (every loop open there), (*batch, n_freq).
        speed: L_v, broken at the speed feedback with the position loop open; None when the
            controller closes no speed loop (a PID on the scale).
        position: L_p, broken at the scale with the speed loop closed; None without a position
            loop.
    """

    freq_hz: Float[Array, " freq"]
    plant_input: Complex[Array, "*batch freq"]
    speed: Complex[Array, "*batch freq"] | None
    position: Complex[Array, "*batch freq"] | None


class LoopMargins(eqx.Module):
    """Margins (:class:`fdjax.Margins`) of the loop broken at each of its break points (None
    where the controller closes no such loop).

    Attributes:
        plant_input: the loop broken at the current command (the plant input, paper Fig. 7).
        speed: broken at the speed feedback v_m (the inner loop of Fig. 13).
        position: broken at the scale feedback x2 (the outer loop of Fig. 13).
    """

    plant_input: Margins
    speed: Margins | None
    position: Margins | None


class Stability(eqx.Module):
    """Result of :func:`check_stability`.

    Attributes:
        stable: every closed-loop pole decays (Re s < 0; |z| < 1 for the sampled loop).
        growth_rate: max Re s over the poles (1/s), s = ln z / T for the sampled loop;
            negative when stable.  A pole on the stability boundary to round-off,
            |Re s| T ≤ 1e-9 with T the servo's period (ln|z| for the sampled loop; a time
            constant above 1.4 days at 8 kHz), counts as Re s = 0 exactly (growth 0: marginally
            stable, not stable), by both loop models and by :func:`fdjax.simulate` alike: a
            state no feedback acts on, such as the table position of a controller without a
            position loop (s = 0), or an undamped mode it does not see.
        min_damping: min over the poles of −Re s/|s| (the least damped pole's ratio; 0 for a
            pole on the boundary).
        position_m: the table position (m).
        poles: the closed loop's eigenvalues (s, or z for the sampled loop), least stable first.
        result: ``RESULTS.successful`` or ``RESULTS.unstable``.
        discrete: whether ``poles`` are z (static).
    """

    stable: Bool[Array, "*batch"]
    growth_rate: Float[Array, "*batch"]
    min_damping: Float[Array, "*batch"]
    position_m: Float[Array, "*batch"]
    poles: Complex[Array, "*batch n"]
    result: RESULTS
    discrete: bool = eqx.field(static=True)

    @property
    def message(self) -> str:
        """One line per position, e.g. "closed loop unstable at table position 0.7 m: least
        stable pole at 98.27 Hz growing at 26.79 1/s"."""
        stable = np.atleast_1d(np.asarray(self.stable))
        pos = np.atleast_1d(np.asarray(self.position_m))
        g = np.atleast_1d(np.asarray(self.growth_rate))
        poles = np.asarray(self.poles).reshape(stable.shape[0], -1)
        lines = []
        for ok, p, gr, lam in zip(stable, pos, g, poles):
            w = lam[0]
            hz = abs(np.angle(w)) / (2 * np.pi * self._period) if self.discrete else (
                abs(w.imag) / (2 * np.pi)
            )
            if gr == 0.0:
                lines.append(
                    f"closed loop marginally stable at table position {p:.4g} m: a pole at "
                    f"{hz:.4g} Hz neither decays nor grows, a state no feedback acts on (such "
                    "as the table position of a controller without a position loop)"
                )
                continue
            what = "decaying" if ok else "growing"
            lines.append(
                f"closed loop {'stable' if ok else 'unstable'} at table position {p:.4g} m: "
                f"least stable pole at {hz:.4g} Hz {what} at {abs(gr):.4g} 1/s"
            )
        return "\n".join(lines)

    _period: float = eqx.field(static=True, default=math.nan)


# ------------------------------------------------------------------------------------ checks
def _check_controller(controller, fn: str, traced: bool = False) -> AbstractController:
    _checks.instance(controller, AbstractController, f"{fn}(controller=...)",
                     "an fdjax controller (DoubleLoop, PIDLoop or a subclass of "
                     "fdjax.AbstractController)")
    return _checks.finite_parameters(controller, f"{fn}(controller=...)", traced=traced)


def _check_servo(servo, fn: str) -> Servo:
    _checks.instance(servo, Servo, f"{fn}(servo=...)")
    return servo


def _check_method(method, fn: str) -> AbstractLoopModel:
    _checks.instance(method, AbstractLoopModel, f"{fn}(method=...)",
                     "fdjax.SampledData(), fdjax.Continuous() or fdjax.PadeODE()")
    return method


def _plant(plant, position_m, fn: str, *, twin=None, freq_hz=None, screw_ratio=None):
    """Normalise the plant to ("model", StateSpace | (drive, positions)) or ("frf", H)."""
    twin = _twin_options(twin, fn)
    if isinstance(plant, BallScrewDrive):
        if position_m is None:
            raise ValueError(f"`{fn}(position_m=...)` is required when the plant is a drive")
        pos = plant._check_positions(position_m, fn)
        return "drive", (plant, pos, twin.resolve(plant, fn)), np.ndim(position_m) == 0
    if position_m is not None and isinstance(plant, StateSpace):
        raise ValueError(f"`{fn}(position_m=...)` is only for a BallScrewDrive or FRF plant")
    if isinstance(plant, StateSpace):
        if plant.A.ndim not in (2, 3):
            raise ValueError(
                f"`{fn}(plant=...)` must be a StateSpace with A of shape (n, n), or (batch, n, n) "
                f"from jax.vmap over positions, got A of shape {plant.A.shape}"
            )
        return "model", plant, plant.A.ndim == 2
    if not isinstance(plant, np.ndarray | jax.Array | list | tuple):
        raise TypeError(
            f"`{fn}(plant=...)` must be a BallScrewDrive (with position_m), a StateSpace, or an "
            f"FRF array of shape (..., n_freq, 3, 2), got {type(plant).__name__}"
        )
    H = jnp.asarray(plant)
    if freq_hz is None:  # closed_loop, check_stability: a model's poles, not a response's
        raise TypeError(f"`{fn}(plant=...)` must be a drive or a StateSpace, not an FRF array "
                        f"(shape {H.shape}): the closed loop's poles need a model")
    if H.ndim < 3 or H.shape[-2:] != (3, 2) or H.shape[-3] != freq_hz.shape[0]:
        n = f"n_freq = {freq_hz.shape[0]}"
        raise ValueError(
            f"`{fn}(plant=...)` must be a BallScrewDrive (with position_m), a StateSpace, or an "
            f"FRF array of shape (..., n_freq, 3, 2) with {n}, got "
            f"{type(plant).__name__} of shape {getattr(H, 'shape', None)}"
        )
    if not jnp.issubdtype(H.dtype, jnp.complexfloating):
        raise ValueError(f"`{fn}(plant=...)` must be a complex FRF array, got dtype {H.dtype}")
    if screw_ratio is None:
        raise ValueError(
            f"`{fn}(screw_ratio=...)` is required with an FRF plant: the drive's i_sc = lead/2π "
            "(m/rad), e.g. `drive.screw.ratio`"
        )
    sr = _checks.positive(jnp.asarray(screw_ratio, jnp.float64), f"{fn}(screw_ratio=...)")
    H = _checks.finite(H.astype(jnp.complex128), f"{fn}(plant=...)")
    if position_m is None:
        pos = jnp.full(H.shape[:-3], jnp.nan)
    else:
        pos = _checks.real_array(position_m, f"{fn}(position_m=...)")
        try:
            pos = jnp.broadcast_to(pos, H.shape[:-3])
        except ValueError:
            raise ValueError(
                f"`{fn}(position_m=...)` must be one position per FRF, shape {H.shape[:-3]} "
                f"(the FRF array's leading axes), got shape {pos.shape}"
            ) from None
    return "frf", (H, sr, pos), H.ndim == 3


def _entry(fn, controller, plant, servo, method, position_m, twin, *,
           freq_hz=None, min_points=1, screw_ratio=None, traced=True):
    """The checks every entry point makes: (controller, servo, method, kind, plant, scalar,
    frequency grid or None).  A traced controller's parameters are checked finite too (an
    ``eqx.error_if``: a NaN gain would read as infinite margins), except with ``traced=False``
    (the tuning objective's open loops, :func:`_open_loop`)."""
    controller = _check_controller(controller, fn, traced)
    servo, method = _check_servo(servo, fn), _check_method(method, fn)
    f = None if freq_hz is None else _grid(freq_hz, fn, min_points)
    kind, p, scalar = _plant(plant, position_m, fn, twin=twin,
                             freq_hz=f, screw_ratio=screw_ratio)
    where = f"{fn}(position_m=...)"
    if kind == "drive":
        p = (p[0], controller.check_position(p[1], where), p[2])
    elif kind == "frf":
        checked = controller.check_position(position_m, where)  # None: a fixed controller
        if checked is not None:
            p = (p[0], p[1], jnp.broadcast_to(jnp.asarray(checked, jnp.float64), p[2].shape))
    elif kind == "model":  # a twin built at its position: a schedule is checked there
        controller.check_position(p.position_m, f"{fn}(plant=...).position_m")
    if f is not None:
        f = _below_nyquist(f, kind, method, servo, fn)
    method.check_use(controller, p if kind == "model" else None, servo, f"{fn}(method=...)")
    return controller, servo, method, kind, p, scalar, f


def _map_twins(kind, p, body, has_eig=False):
    """``body(twin)`` for each twin: a drive's positions, a StateSpace batch, or one twin."""
    if kind == "drive":
        drive, pos, twin = p
        return map_positions(
            lambda y: body(state_space(drive, y, twin=twin)), pos,
            has_eig=has_eig,
        )
    if p.A.ndim == 3:
        return map_positions(body, p, has_eig=has_eig)
    return body(p)


def _squeeze(tree, scalar: bool, kind: str):
    if kind == "drive" and scalar:
        return jax.tree_util.tree_map(lambda x: x[0], tree)
    return tree


def _grid(freq_hz, fn: str, min_points: int = 1):
    f = _checks.frequency_grid(freq_hz, f"{fn}(freq_hz=...)")
    if f.shape[0] < min_points:
        raise ValueError(f"`{fn}(freq_hz=...)` must have at least {min_points} points, got "
                         f"{f.shape[0]}")
    return f


def _below_nyquist(f, kind, method, servo, fn: str):
    if kind == "frf" and not method.takes_frf:
        raise ValueError(
            f"`{fn}(method=...)`: the sampled loop needs the plant in state space (its "
            "zero-order-hold equivalent is not a function of the FRF): pass the drive with "
            "`position_m=...` or a `fdjax.state_space(...)` twin, or analyse the FRF with "
            "`method=fdjax.Continuous()`"
        )
    top = method.max_freq_hz(servo)
    if math.isfinite(top):
        f = _checks.check(
            f, lambda v: v < top, f"{fn}(freq_hz=...)",
            f"below the servo's Nyquist frequency {top:.6g} Hz for the sampled loop",
        )
    return f


# ------------------------------------------------------------------------------------ public
def open_loop(
    controller: AbstractController,
    plant: BallScrewDrive | StateSpace | Complex[ArrayLike, "*pos freq 3 2"],
    freq_hz: Float[ArrayLike, " freq"],
    *,
    servo: Servo = Servo(),
    method: AbstractLoopModel = SampledData(),
    position_m: Float[ArrayLike, "*pos"] | None = None,
    screw_ratio: Float[ArrayLike, ""] | None = None,
    twin: TwinOptions | None = None,
) -> OpenLoop:
    r"""Open-loop frequency responses of ``controller`` around ``plant`` (module docstring).

        L_u = −P (K_x g_x + K_v g_v),  L_v = −K_v P g_v,  L_p = −K_x P g_x / (1 + L_v),

    with P = k_m e^{−iωτ} (continuous) or k_m z^{−d} on z = e^{iωT} (sampled).  For the
    double loop of paper Fig. 13: L_v = C_v G_MCM k_m e^{−iωτ} i_sc iω h_θ1,T1 and
    L_p = k_p h_x2,T1 C_v G_MCM k_m e^{−iωτ}/(1 + L_v).  Differentiable in the controller and
    the plant; one compiled program for a batch of positions.

    Args:
        controller: the controller.
        plant: a drive (with ``position_m``), a StateSpace (or batch), or an FRF array (with
            ``screw_ratio``; continuous methods only).
        freq_hz: positive, increasing grid (Hz); below the Nyquist frequency for the sampled
            loop.
        servo: the servo's hardware (default: the reference servo).
        method: ``SampledData()`` (default), ``Continuous(pade_order=None)`` or a ``PadeODE``.
        position_m: table position(s) (m) for a drive plant (or an FRF's, for a scheduled
            controller).
        screw_ratio: i_sc (m/rad) for an FRF plant.
        twin: how a drive plant becomes its twin (:class:`fdjax.TwinOptions`; default the
            modes below 4 kHz).
    """
    return _open_loop(controller, plant, freq_hz, servo, method, position_m, screw_ratio, twin)


def _open_loop(controller, plant, freq_hz, servo=Servo(), method=SampledData(), position_m=None,
               screw_ratio=None, twin=None, *, traced=True) -> OpenLoop:
    """:func:`open_loop`; with ``traced=False`` a traced controller's parameters are not
    guarded finite: for the tuning objective, evaluated at an optimiser's trial points, whose
    non-finite values the tuners refuse themselves."""
    controller, servo, method, kind, p, scalar, f = _entry(
        "open_loop", controller, plant, servo, method, position_m, twin,
        freq_hz=freq_hz, screw_ratio=screw_ratio, traced=traced,
    )
    loops = _open_loop_jit(controller, kind, p, f, servo, method)
    return OpenLoop(freq_hz=f, **_squeeze(loops, scalar, kind))


def _frf_loops(method, controller, p, omega, servo):
    """The open loops of measured FRFs (…, n_freq, 3, 2), each with the controller's law at its
    own table position (a scheduled controller's law takes one position)."""
    H, sr, pos = p

    def one(h, y):
        return method.frf_open_loops(controller, h, omega, sr, servo, y)

    if pos.ndim == 0:
        return one(H, pos)
    out = jax.vmap(one)(H.reshape((-1,) + H.shape[-3:]), pos.reshape(-1))
    return jax.tree_util.tree_map(lambda L: L.reshape(pos.shape + L.shape[1:]), out)


def _open_loop_impl(controller, kind, p, f, servo, method):
    omega = _TWO_PI * f
    if kind == "frf":
        return _frf_loops(method, controller, p, omega, servo)

    def one(twin):
        L_fn, params = method.open_loop_model(controller, twin, servo)
        return L_fn(params, omega)

    return _map_twins(kind, p, one)


_open_loop_traced = eqx.debug.assert_max_traces(_open_loop_impl, max_traces=None)
_open_loop_jit = eqx.filter_jit(_open_loop_traced)


def stability_margins(
    freq_hz: Float[ArrayLike, " freq"], L: Complex[ArrayLike, "*batch freq"]
) -> Margins:
    r"""Gain, phase and modulus margins of a sampled SISO open loop L on ``freq_hz``.

    python-control's conventions (module docstring).  Crossings are located inside grid
    intervals by interpolating log L linearly in log ω (exact for power laws, second order in
    the spacing otherwise); the modulus margin by a parabola through the three grid points
    around each local minimum of |1 + L|.  For a model use :func:`loop_margins`, which refines
    the crossings to round-off.  Leading batch axes are mapped over.

    Args:
        freq_hz: positive, increasing grid (Hz), long enough to contain the crossovers.
        L: complex open loop on that grid, shape (*batch, n_freq).
    """
    f = _grid(freq_hz, "stability_margins", 3)
    L = jnp.asarray(L)
    if L.ndim < 1 or L.shape[-1] != f.shape[0]:
        raise ValueError(
            f"`stability_margins(L=...)` must have shape (*batch, n_freq) with n_freq = "
            f"{f.shape[0]}, got {L.shape}"
        )
    L = _checks.finite(L.astype(jnp.complex128), "stability_margins(L=...)")
    return _stability_margins_jit(f, L)


def _batched_grid_margins(u, L):
    fn = lambda x: grid_margins(u, x)
    for _ in range(L.ndim - 1):
        fn = jax.vmap(fn)
    return fn(L)


@eqx.filter_jit
def _stability_margins_jit(f, L):
    return _batched_grid_margins(jnp.log(_TWO_PI * f), L)


def loop_margins(
    controller: AbstractController,
    plant: BallScrewDrive | StateSpace | Complex[ArrayLike, "*pos freq 3 2"],
    freq_hz: Float[ArrayLike, " freq"],
    *,
    servo: Servo = Servo(),
    method: AbstractLoopModel = SampledData(),
    position_m: Float[ArrayLike, "*pos"] | None = None,
    screw_ratio: Float[ArrayLike, ""] | None = None,
    twin: TwinOptions | None = None,
) -> LoopMargins:
    r"""Gain, phase and modulus margins (with their frequencies) of the loop broken at the plant
    input, at the speed feedback and at the scale.

    By default those of the loop as it runs: the sampled loop on the unit circle (module
    docstring), the margins python-control's ``stability_margins`` gives for the same frequency
    response (its polynomial method on the discrete system's transfer function can be far off at
    this order).  The open loops are sampled on ``freq_hz``, every crossing is bracketed there and,
    for a twin (a drive or a StateSpace), refined by safeguarded Newton steps on the model's own
    L to round-off; the margins are differentiable through the refined crossings.  On a twin,
    two crossings that no grid point separates (a resonance lifting |L| above 1, or turning the
    phase past −180°, and back between grid points) are found from the extremum of |L| or of
    the phase between them.  For an FRF array they are interpolated
    (:func:`stability_margins`), and the grid must bracket every crossing (a few hundred points
    per decade around lightly damped modes).

    Margins are read from the open loops alone; they do not say whether the closed loop is
    stable (a loop whose Nyquist curve encircles −1 has margins too).  Ask
    :func:`check_stability` (the eigenvalues), as :func:`fdjax.certify` does.

    Args: as :func:`open_loop` (at least 3 frequencies).
    """
    controller, servo, method, kind, p, scalar, f = _entry(
        "loop_margins", controller, plant, servo, method, position_m, twin,
        freq_hz=freq_hz, min_points=3, screw_ratio=screw_ratio,
    )
    return _squeeze(_loop_margins_jit(controller, kind, p, f, servo, method), scalar, kind)


def _loop_margins_impl(controller, kind, p, f, servo, method):
    u = jnp.log(_TWO_PI * f)
    omega = _TWO_PI * f
    if kind == "frf":
        loops = _frf_loops(method, controller, p, omega, servo)
        return LoopMargins(**{
            k: None if L is None else _batched_grid_margins(u, L) for k, L in loops.items()
        })

    def one(twin):
        L_fn, params = method.open_loop_model(controller, twin, servo)
        present = [k for k, L in L_fn(params, omega[:1]).items() if L is not None]

        def Ls_fn(prm, w):
            out = L_fn(prm, w)
            return tuple(out[k] for k in present)

        ms = model_margins(u, Ls_fn(params, omega), Ls_fn, params)
        got = dict(zip(present, ms))
        return LoopMargins(**{k: got.get(k) for k in _LOOPS})

    return _map_twins(kind, p, one)


_loop_margins_traced = eqx.debug.assert_max_traces(_loop_margins_impl, max_traces=None)
_loop_margins_jit = eqx.filter_jit(_loop_margins_traced)


def closed_loop(
    controller: AbstractController,
    plant: BallScrewDrive | StateSpace,
    *,
    servo: Servo = Servo(),
    method: AbstractLoopModel = SampledData(),
    position_m: Float[ArrayLike, "*pos"] | None = None,
    twin: TwinOptions | None = None,
) -> LTI:
    r"""The loop closed around the twin, as one :class:`fdjax.LTI` with inputs (r, ṙ, r̈, F3)
    (:data:`fdjax.CLOSED_LOOP_INPUTS`) and outputs (θ1, x2, x3, T1)
    (:data:`fdjax.CLOSED_LOOP_OUTPUTS`).

    ``SampledData()`` (default): the discrete loop the servo runs — states: the plant's, the
    previous encoder angle, the discrete law's, the d delayed commands; ``dt`` is the servo
    period and ``control.ss(A, B, C, D, dt)`` accepts it as it is.  ``Continuous()`` or
    ``PadeODE()``: the continuous loop — the plant's, the law's and the Padé delay's states, the
    algebraic loop through the twin's residual feed-through solved exactly.

    Args: as :func:`open_loop` (no frequency grid; the plant is a drive or a StateSpace).
    """
    controller, servo, method, kind, p, scalar, _ = _entry(
        "closed_loop", controller, plant, servo, method, position_m, twin
    )
    return _squeeze(_closed_loop_jit(controller, kind, p, servo, method), scalar, kind)


def _closed_loop_impl(controller, kind, p, servo, method):
    return _map_twins(kind, p, lambda twin: method.closed_loop(controller, twin, servo))


_closed_loop_traced = eqx.debug.assert_max_traces(_closed_loop_impl, max_traces=None)
_closed_loop_jit = eqx.filter_jit(_closed_loop_traced)


def check_stability(
    controller: AbstractController,
    plant: BallScrewDrive | StateSpace,
    *,
    servo: Servo = Servo(),
    method: AbstractLoopModel = SampledData(),
    position_m: Float[ArrayLike, "*pos"] | None = None,
    twin: TwinOptions | None = None,
    throw: bool = False,
) -> Stability:
    r"""Closed-loop stability from the eigenvalues of :func:`closed_loop`.

    Stable when every pole decays: Re s < 0 for the continuous loop, |z| < 1 for the sampled
    one (then growth rates are ln|z|/T).  ``.message`` names the position and the least stable
    pole, e.g. "closed loop unstable at table position 0.7 m: least stable pole at 93.7 Hz
    growing at 16.5 1/s".  One compiled program for all positions; the eigenvalue problems run
    one position at a time (:func:`fdjax._sweep.map_positions`).

    Args: as :func:`closed_loop`, and
        throw: raise when unstable — eagerly a RuntimeError with ``.message``; under ``jit`` the
            result code's own message.  Off by default: an unstable loop is an answer.
    """
    throw = _checks.static_bool(throw, "check_stability(throw=...)")
    controller, servo, method, kind, p, scalar, _ = _entry(
        "check_stability", controller, plant, servo, method, position_m, twin
    )
    result = _squeeze(_stability_jit(controller, kind, p, servo, method), scalar, kind)
    if throw:
        failed = result.result != RESULTS.successful
        if _checks.is_concrete(result.stable):
            if bool(np.any(np.asarray(failed))):
                raise RuntimeError(result.message)
        else:
            result = result.result.error_if(result, failed)
    return result


def _stability_impl(controller, kind, p, servo, method):
    def one(twin):
        cl = method.closed_loop(controller, twin, servo)
        lam = jnp.linalg.eigvals(cl.A)
        s = method.poles_to_s(lam, servo)
        # a pole on the boundary to round-off (z = 1 - 1e-14, or s = 0 exactly; an undamped
        # mode): one verdict for both loop models and simulate, not one set by the last bit
        # (Stability.growth_rate)
        at_zero = jnp.abs(jnp.real(s)) * servo.period <= MARGINAL
        re = jnp.where(at_zero, 0.0, jnp.real(s))
        order = jnp.argsort(-re)
        lam, s, re, at_zero = lam[order], s[order], re[order], at_zero[order]
        growth = re[0]
        stable = growth < 0
        ratio = jnp.where(at_zero, 0.0,
                          -re / jnp.where(at_zero | ~jnp.isfinite(s), 1.0, jnp.abs(s)))
        damping = jnp.min(jnp.where(jnp.isfinite(s), ratio, jnp.inf))
        return Stability(
            stable=stable,
            growth_rate=growth,
            min_damping=damping,
            position_m=twin.position_m,
            poles=lam,
            result=RESULTS.where(stable, RESULTS.successful, RESULTS.unstable),
            discrete=method.max_freq_hz(servo) < math.inf,
            _period=float(servo.period),
        )

    return _map_twins(kind, p, one, has_eig=True)


_stability_traced = eqx.debug.assert_max_traces(_stability_impl, max_traces=None)
_stability_jit = eqx.filter_jit(_stability_traced)


def gain_headroom(
    controller: AbstractController,
    plant: BallScrewDrive | StateSpace,
    *,
    position_m: Float[ArrayLike, "*pos"] | None = None,
    servo: Servo = Servo(),
    method: AbstractLoopModel = SampledData(),
    twin: TwinOptions | None = None,
    max_gain: float = 1.0e3,
    rtol: float = 1.0e-3,
) -> np.ndarray:
    r"""How far the loop gain can grow before the closed loop goes unstable, by its eigenvalues.

    The largest g such that the loop with its whole controller output scaled by every factor in
    [1, g] (the servo's k_m → g·k_m: for a :class:`fdjax.DoubleLoop` the same as scaling k_v
    alone, for a :class:`fdjax.PIDLoop` all its gains together) is stable
    (:func:`check_stability`).  Unlike the gain margin read off the Nyquist plot, this is not
    fooled by conditionally stable loops or by several phase crossovers: g is found by a
    geometric scan (factor 1.25) and bisection in log g to ``rtol``, each step the eigenvalues of
    the closed loop.  g = 0 when the loop is unstable as it is, ``max_gain`` when it stays stable
    up to there.  ``20·log10(g)`` is the gain headroom in dB.  A loop with a pole at s = 0 (a
    controller without a position loop: marginally stable at every gain) is an error.

    Args: as :func:`check_stability`, and
        max_gain: the largest factor tried (> 1).
        rtol: relative accuracy of g (in (0, 0.1]).

    Returns:
        g per position (NumPy array of the positions' shape).
    """
    fn = "gain_headroom"
    max_gain = _checks.static_number(max_gain, f"{fn}(max_gain=...)", lambda v: v > 1,
                                     "a number > 1")
    rtol = _checks.static_number(rtol, f"{fn}(rtol=...)", lambda v: 0 < v <= 0.1,
                                 "a number in (0, 0.1]")
    # every argument checked here, named for the caller (the search calls check_stability)
    _, _, _, kind, p, scalar, _ = _entry(fn, controller, plant, servo, method, position_m, twin)
    if kind == "drive":
        position_m = np.asarray(plant._check_travel(position_m, fn))  # its own shape
        twin = p[2]  # the twin's modes counted once, not at every step of the search
    pos = None if position_m is None else np.asarray(position_m, np.float64)
    k_m = servo.k_motor
    if kind == "model" and not scalar:  # a batch of twins: g for each, as for positions
        n = plant.A.shape[0]
        return np.array([gain_headroom(controller, jax.tree_util.tree_map(
            lambda x, i=i: x[i] if getattr(x, "ndim", 0) and x.shape[0] == n else x, plant),
            servo=servo, method=method, max_gain=max_gain, rtol=rtol) for i in range(n)])

    def stable(g, p):
        s = eqx.tree_at(lambda s: s.k_motor, servo, k_m * g)
        st = check_stability(controller, plant, servo=s, method=method, position_m=p, twin=twin)
        return bool(np.all(np.asarray(st.stable)))

    def one(p):
        if not stable(1.0, p):
            st = check_stability(controller, plant, servo=servo, method=method, position_m=p,
                                 twin=twin)
            if bool(np.any(np.asarray(st.growth_rate) == 0.0)):
                raise ValueError(
                    f"`{fn}(controller=...)`: {st.message}; that pole stays at 0 at every gain, "
                    "so the loop has no gain headroom (the speed loop's gain margin is "
                    "loop_margins(...).speed)")
            return 0.0
        lo = 1.0
        while lo < max_gain:
            hi = min(lo * 1.25, max_gain)
            if not stable(hi, p):
                break
            lo = hi
        else:
            return float(max_gain)
        a, b = math.log(lo), math.log(hi)
        while b - a > rtol:
            mid = 0.5 * (a + b)
            a, b = (mid, b) if stable(math.exp(mid), p) else (a, mid)
        return math.exp(a)

    if pos is None or pos.ndim == 0:
        return np.asarray(one(None if pos is None else float(pos)))
    return np.array([one(float(p)) for p in pos.reshape(-1)]).reshape(pos.shape)
