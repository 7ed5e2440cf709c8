r"""The adaptive tuning algorithm (ATA, paper Sec. 4.2, Fig. 15): a small network maps the table
position to the MCM's seven filter parameters, and the scheduled controller is the double loop
with the network's filters at the position it is asked at.

    θ(Y) = W₃ σ(W₂ σ(W₁ ŷ + b₁) + b₂) + b₃,    ŷ = 2 (Y − Y_min)/(Y_max − Y_min) − 1,
    MCM(Y) = ``bounds.to_mcm(θ(Y))``,

σ the logistic function (two sigmoid hidden layers, as the paper's network), θ the normalised
parameters of :class:`MCMBounds` (every output an admissible filter).  A network built with
``gains=True`` (or widened by :meth:`ATANetwork.with_gains`) schedules the feedback gains too:
three more outputs δ(Y) = (δ_p, δ_v, δ_i) scale the loop's gains,

    k_p(Y) = k_p e^{δ_p(Y)},   k_v(Y) = k_v e^{δ_v(Y)},   k_i(Y) = k_i e^{δ_i(Y)},

δ held within ±30 (``LOG_GAIN_LIMIT``), so every output is a positive, finite gain.
:class:`ScheduledLoop` is an :class:`fdjax.AbstractController` whose law at Y is that of its
double loop with MCM(Y), so it runs through every path of the control architecture: margins,
stability, both simulations.

:func:`save_schedule` / :func:`load_schedule` store a schedule as its leaves
(``eqx.tree_serialise_leaves``; a path without a suffix takes ``.eqx``) beside a JSON file of
its hyperparameters and units (the path with suffix ``.json``).
"""

from __future__ import annotations

import abc
import hashlib
import io
import json
import math
import os
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .. import _checks
from .._control._controllers import AbstractController, DoubleLoop, Law
from .._drive._model import BallScrewDrive, travel_pair
from .._filters import MCM
from ._optimisers import optimiser_or
from ._parameterisation import LOG_GAIN_LIMIT, MCM_PARAMETERS, MCMBounds

__all__ = ["ATANetwork", "ScheduledLoop", "InterpolatedLoop", "fit_network", "save_schedule",
           "load_schedule"]

_FORMAT = "fdjax-schedule/1"


GAIN_OUTPUTS = ("log_kp", "log_kv", "log_ki")
"""The gain outputs of an :class:`ATANetwork` with ``gains=True``: δ_p, δ_v, δ_i."""


class ATANetwork(eqx.Module):
    r"""The scheduling network: normalised table position in, two sigmoid hidden layers of
    ``width`` neurons, the seven normalised MCM parameters out, and with ``gains=True`` the
    three logarithmic gain factors δ(Y) after them (module docstring).

    Attributes:
        mlp: the ``eqx.nn.MLP`` (1 → width → width → 7, or 10 with gains).
        travel_m: (Y_min, Y_max) that map to ŷ = ∓1 (static).
        gains: whether the network schedules the gains too (static).
    """

    mlp: eqx.nn.MLP
    travel_m: tuple[float, float] = eqx.field(static=True)
    gains: bool = eqx.field(static=True)

    def __init__(self, travel_m: tuple[float, float], *, width: int = 8, gains: bool = False,
                 key: PRNGKeyArray | None = None):
        lo, hi = travel_pair(travel_m, "ATANetwork(travel_m=...)")
        width = _checks.static_int(width, "ATANetwork(width=...)", 1, 256)
        gains = _checks.static_bool(gains, "ATANetwork(gains=...)")
        key = jax.random.PRNGKey(0) if key is None else key
        n_out = len(MCM_PARAMETERS) + (len(GAIN_OUTPUTS) if gains else 0)
        self.mlp = eqx.nn.MLP(1, n_out, width, 2, activation=jax.nn.sigmoid,
                              key=key, dtype=jnp.float64)
        self.travel_m = (lo, hi)
        self.gains = gains

    @property
    def width(self) -> int:
        """Neurons per hidden layer."""
        return self.mlp.width_size

    @property
    def outputs(self) -> tuple[str, ...]:
        """The names of the outputs: :data:`fdjax.MCM_PARAMETERS`, then with gains
        ``log_kp``, ``log_kv``, ``log_ki`` (the factors δ of the module docstring)."""
        return MCM_PARAMETERS + (GAIN_OUTPUTS if self.gains else ())

    def __call__(self, position_m: Float[ArrayLike, ""]) -> Float[Array, " outputs"]:
        """The outputs at table position Y (m), a real scalar inside ``travel_m`` (a network
        does not extrapolate; checked eagerly, and under ``jit``/``vmap``/``grad`` by an
        ``eqx.error_if``): θ(Y), the normalised MCM parameters, and with gains δ(Y) after
        them."""
        where = "ATANetwork(position_m=...)"
        lo, hi = self.travel_m
        y = _checks.inside(_checks.real_scalar(position_m, where), lo, hi, where,
                           "the network's travel")
        return self._outputs(y)

    def _outputs(self, position_m) -> Float[Array, " outputs"]:
        """:meth:`__call__` without its checks, for positions checked already (the scheduled
        loop's, the fitted designs')."""
        lo, hi = self.travel_m
        y = 2.0 * (jnp.asarray(position_m, jnp.float64) - lo) / (hi - lo) - 1.0
        return self.mlp(jnp.reshape(y, (1,)))

    def with_gains(self) -> ATANetwork:
        """This network with three gain outputs added, their weights and biases zero: the same
        filters at every position and δ(Y) = 0, the loop's own gains, until it is trained (the
        start of an end-to-end gain schedule from a filter schedule)."""
        if self.gains:
            return self
        last = self.mlp.layers[-1]
        pad = len(GAIN_OUTPUTS)
        wider = ATANetwork(self.travel_m, width=self.width, gains=True)
        layers = self.mlp.layers[:-1] + (eqx.tree_at(
            lambda lin: (lin.weight, lin.bias), wider.mlp.layers[-1],
            (jnp.concatenate([last.weight, jnp.zeros((pad, last.weight.shape[1]))]),
             jnp.concatenate([last.bias, jnp.zeros(pad)]))),)
        return eqx.tree_at(lambda n: n.mlp.layers, wider, layers)


def _scheduled(loop: DoubleLoop, network: ATANetwork, bounds: MCMBounds,
               position_m) -> DoubleLoop:
    """The double loop ``loop`` with the network's MCM (and gain factors) at Y (checked by the
    caller)."""
    out = network._outputs(position_m)
    n = len(MCM_PARAMETERS)
    loop = eqx.tree_at(lambda c: c.mcm, loop, bounds.to_mcm(out[:n]))
    if network.gains:
        d = jnp.clip(out[n:], -LOG_GAIN_LIMIT, LOG_GAIN_LIMIT)
        loop = eqx.tree_at(lambda c: (c.log_kp, c.log_kv, c.log_ki), loop,
                           (loop.log_kp + d[0], loop.log_kv + d[1], loop.log_ki + d[2]))
    return loop


class _ScheduledDoubleLoop(AbstractController):
    """A double loop whose MCM moves with the table position inside :class:`MCMBounds`: at Y
    it runs the fixed double loop :meth:`controller` (Y)."""

    bounds: eqx.AbstractVar[MCMBounds]

    @abc.abstractmethod
    def controller(self, position_m: Float[ArrayLike, ""]) -> DoubleLoop:
        """The fixed double loop run at table position Y (m)."""

    @property
    def highest_frequency_hz(self) -> float:
        """The bounds' highest filter frequency (Hz), ``bounds.freq_hz[1]``
        (:attr:`AbstractController.highest_frequency_hz`)."""
        return float(self.bounds.freq_hz[1])

    def fixed_at(self, positions_m: Float[ArrayLike, " n"]) -> DoubleLoop:
        """The double loops run at ``positions_m`` (m), stacked
        (:meth:`AbstractController.fixed_at`)."""
        where = f"{type(self).__name__}.fixed_at(positions_m=...)"
        y = _checks.real_array(positions_m, where)
        if y.ndim != 1 or y.size == 0:
            raise ValueError(f"`{where}` must be a 1-D array of at least one position, got "
                             f"shape {y.shape}")
        return jax.vmap(self.controller)(y)


class ScheduledLoop(_ScheduledDoubleLoop):
    r"""A double loop whose MCM is scheduled over the table position by an :class:`ATANetwork`
    (paper Fig. 15): at Y, the law of ``loop`` with ``bounds.to_mcm(network(Y))``.

    The gains (k_p, k_v, k_i, feed-forward) are those of ``loop`` (its own MCM is not used),
    the feedback gains scaled by e^{δ(Y)} when the network schedules them
    (``ATANetwork(gains=True)``); the network's weights and the gains are the tunable leaves.

    Attributes:
        loop: the double loop that carries the gains.
        network: the scheduling network.
        bounds: the admissible filters (static numbers).
    """

    loop: DoubleLoop
    network: ATANetwork
    bounds: MCMBounds

    def __init__(self, loop: DoubleLoop, network: ATANetwork, bounds: MCMBounds):
        for name, value, cls in (("loop", loop, DoubleLoop), ("network", network, ATANetwork),
                                 ("bounds", bounds, MCMBounds)):
            _checks.instance(value, cls, f"ScheduledLoop({name}=...)")
        # the loop carries the gains only: its own MCM is replaced by the network's
        self.loop = eqx.tree_at(lambda c: c.mcm, loop, MCM())
        self.network = network
        self.bounds = bounds

    def _in_travel(self, position_m, where: str):
        """``position_m`` checked inside the network's travel (guarded when traced)."""
        lo, hi = self.network.travel_m
        return _checks.inside(position_m, lo, hi, where, "the network's travel")

    def check_position(self, position_m: Float[ArrayLike, ""] | None, where: str):
        """Positions (m) inside the network's travel (:meth:`AbstractController.check_position`)."""
        if position_m is None:
            raise ValueError(f"`{where}` is required: the schedule's law depends on the table "
                             "position")
        return self._in_travel(position_m, where)

    def controller(self, position_m: Float[ArrayLike, ""]) -> DoubleLoop:
        """The fixed double loop the schedule runs at table position Y (m), inside the travel
        the network was built for (a network does not extrapolate)."""
        where = "ScheduledLoop.controller(position_m=...)"
        position_m = _checks.real_array(position_m, where)
        if position_m.ndim != 0:
            raise ValueError(f"`{where}` must be one table position (a scalar; fixed_at or "
                             f"jax.vmap over positions), got shape {position_m.shape}")
        return _scheduled(self.loop, self.network, self.bounds,
                          self._in_travel(position_m, where))

    def filter_table(self, positions_m: Float[ArrayLike, " n"]) -> dict[str, list[float]]:
        """The scheduled filters at ``positions_m`` (m), one row per position, in the units a
        drive's parameter list uses: ``position_mm``; the peak filter's ``peak_K``,
        ``peak_freq_hz``, ``peak_xi``, ``peak_phi_deg``; the notch's ``notch_freq_hz``,
        ``notch_zeta_n``, ``notch_zeta_d``; the feedback gains ``kp`` (1/s), ``kv`` (A·s/m),
        ``ki`` (rad/s), the same in every row unless the network schedules them.  Columns of a
        CSV or a JSON table."""
        y = jnp.atleast_1d(_checks.real_array(positions_m,
                                              "ScheduledLoop.filter_table(positions_m=...)"))
        if y.ndim != 1 or y.size == 0:
            raise ValueError(f"`ScheduledLoop.filter_table(positions_m=...)` must be 1-D with "
                             f"at least one position, got shape {y.shape}")
        y = self._in_travel(y, "ScheduledLoop.filter_table(positions_m=...)")
        loops = jax.vmap(self.controller)(y)
        pk, nt = loops.mcm.peak, loops.mcm.notch
        cols = {
            "position_mm": y * 1e3,
            "peak_K": pk.K[:, 0],
            "peak_freq_hz": pk.omega[:, 0] / (2 * math.pi),
            "peak_xi": pk.xi[:, 0],
            "peak_phi_deg": jnp.degrees(pk.phi[:, 0]),
            "notch_freq_hz": nt.omega[:, 0] / (2 * math.pi),
            "notch_zeta_n": nt.zeta_n[:, 0],
            "notch_zeta_d": nt.zeta_d[:, 0],
            "kp": loops.kp, "kv": loops.kv, "ki": loops.ki,
        }
        return {k: [float(v) for v in jnp.asarray(c)] for k, c in cols.items()}

    def law(self, position_m: Float[ArrayLike, ""]) -> Law:
        """The law of :meth:`controller` at the table position."""
        if position_m is None:
            raise ValueError("`ScheduledLoop.law(position_m=...)` needs the table position (m)")
        return self.controller(position_m).law(position_m)


class InterpolatedLoop(_ScheduledDoubleLoop):
    r"""A double loop whose MCM is interpolated linearly, parameter by parameter, between local
    designs in the normalised form of :class:`MCMBounds` (the baseline a scheduling network
    must beat):

        θ(Y) = θ_i + (θ_{i+1} − θ_i)(Y − Y_i)/(Y_{i+1} − Y_i),  Y_i ≤ Y ≤ Y_{i+1},

    held at the end designs outside [Y_1, Y_n]; MCM(Y) = ``bounds.to_mcm(θ(Y))``.

    Attributes:
        loop: the double loop that carries the gains (its own MCM is not used).
        positions_m: the design positions Y_i (m), increasing, (n,).
        theta: the normalised MCM parameters θ_i, (n, 7).
        bounds: the admissible filters (static numbers).
    """

    loop: DoubleLoop
    positions_m: Float[Array, " n"]
    theta: Float[Array, "n 7"]
    bounds: MCMBounds

    def __init__(self, loop: DoubleLoop, positions_m: Float[ArrayLike, " n"],
                 theta: Float[ArrayLike, "n 7"], bounds: MCMBounds):
        _checks.instance(loop, DoubleLoop, "InterpolatedLoop(loop=...)")
        _checks.instance(bounds, MCMBounds, "InterpolatedLoop(bounds=...)")
        y = _checks.real_array(positions_m, "InterpolatedLoop(positions_m=...)")
        t = _checks.real_array(theta, "InterpolatedLoop(theta=...)")
        if y.ndim != 1 or y.shape[0] < 2 or t.shape != (y.shape[0], len(MCM_PARAMETERS)):
            raise ValueError(f"`InterpolatedLoop(positions_m=..., theta=...)` must have shapes "
                             f"(n,) and (n, 7) with n ≥ 2, got {y.shape} and {t.shape}")
        y = _checks.inside(y, -_checks.LONGEST_TRAVEL_M, _checks.LONGEST_TRAVEL_M,
                           "InterpolatedLoop(positions_m=...)",
                           "the longest travel of a ball-screw axis")
        t = _checks.finite(t, "InterpolatedLoop(theta=...)")
        if not bool(jnp.all(jnp.diff(y) > 0)):
            raise ValueError("`InterpolatedLoop(positions_m=...)` must be increasing, got "
                             f"{[float(v) for v in y]}")
        self.loop = eqx.tree_at(lambda c: c.mcm, loop, MCM())
        self.positions_m = y
        self.theta = t
        self.bounds = bounds

    def _position(self, position_m, where: str):
        """A finite real position (m).  Outside the design positions the end designs hold, so
        any finite value is one; but a value whose thousandth lies between the design
        positions (and which itself does not) was given in millimetres, and is refused."""
        y = _checks.finite(_checks.real_array(position_m, where), where)
        lo, hi = self.positions_m[0], self.positions_m[-1]
        mm = ((y < lo) | (y > hi)) & (y / 1000 >= lo) & (y / 1000 <= hi)
        if _checks.is_concrete(mm):  # eagerly, with the value
            if np.any(np.asarray(mm)):
                bad = float(np.asarray(y)[np.asarray(mm)][0]) if np.ndim(y) else float(y)
                raise ValueError(f"`{where}` must be a table position in metres (the designs "
                                 f"lie at {float(lo):.6g} … {float(hi):.6g} m), got {bad:.6g}; "
                                 f"{bad:.6g} mm is {bad / 1000:.6g} m")
        else:  # traced: the same sentence, without the value
            y = eqx.error_if(y, jnp.any(mm), f"`{where}` must be a table position in metres "
                             "(the value lies between the designs once divided by 1000: it "
                             "was given in mm)")
        return y

    def check_position(self, position_m: Float[ArrayLike, ""] | None, where: str):
        """Finite positions (m), not in mm (:meth:`AbstractController.check_position`)."""
        if position_m is None:
            raise ValueError(f"`{where}` is required: the interpolated designs depend on the "
                             "table position")
        return self._position(position_m, where)

    def _scalar(self, position_m, where: str):
        y = self._position(position_m, where)
        if y.ndim != 0:
            raise ValueError(f"`{where}` must be one table position (a scalar; jax.vmap over "
                             f"positions), got shape {y.shape}")
        return y

    def normalised(self, position_m: Float[ArrayLike, ""]) -> Float[Array, " 7"]:
        """θ(Y) (class docstring)."""
        return self._interpolated(
            self._scalar(position_m, "InterpolatedLoop.normalised(position_m=...)"))

    def _interpolated(self, y):
        return jax.vmap(lambda col: jnp.interp(y, self.positions_m, col))(self.theta.T)

    def controller(self, position_m: Float[ArrayLike, ""]) -> DoubleLoop:
        """The fixed double loop at table position Y (m); outside the design positions the
        end designs hold."""
        y = self._scalar(position_m, "InterpolatedLoop.controller(position_m=...)")
        mcm = self.bounds.to_mcm(self._interpolated(y))
        return eqx.tree_at(lambda c: c.mcm, self.loop, mcm)

    def law(self, position_m: Float[ArrayLike, ""]) -> Law:
        """The law of :meth:`controller` at the table position."""
        if position_m is None:
            raise ValueError("`InterpolatedLoop.law(position_m=...)` needs the table position (m)")
        return self.controller(position_m).law(position_m)


def fit_network(
    network: ATANetwork,
    positions_m: Float[ArrayLike, " n"],
    targets: Float[ArrayLike, "n 7"],
    *,
    steps: int = 3000,
    optimiser: optax.GradientTransformation | None = None,
) -> tuple[ATANetwork, Float[Array, " steps"]]:
    r"""Train the network by backpropagation on local designs, as the paper does (Sec. 4.2):
    minimise the mean squared error (1/n) Σ_i ‖θ(Y_i) − θ_i‖² over the design positions Y_i
    and their normalised parameters θ_i (:meth:`MCMBounds.from_mcm` of the local MCMs; for a
    network with gains, each row followed by the designs' log gain factors δ_i).

    ``steps`` optimiser steps (a ``lax.scan``: one compilation) of ``optimiser`` (default
    ``optax.adam(1e-2)``) on the network's weights.  Returns the trained network and the loss
    at each step, evaluated before its update (the first is the start's; the returned network
    is one update past the last).  At least one design; its positions inside the network's
    travel (m: a position in mm is named with its value in metres) and its targets finite.
    """
    fn = "fit_network"
    _checks.instance(network, ATANetwork, f"{fn}(network=...)")
    y = _checks.real_array(positions_m, f"{fn}(positions_m=...)")
    t = _checks.real_array(targets, f"{fn}(targets=...)")
    m = len(network.outputs)
    if y.ndim != 1 or y.shape[0] == 0 or t.shape != (y.shape[0], m):
        raise ValueError(
            f"`{fn}(positions_m=..., targets=...)` must have shapes (n,) and (n, {m}) "
            f"(n ≥ 1 designs; {m} the network's outputs), got {y.shape} and {t.shape}"
        )
    lo, hi = network.travel_m
    y = _checks.inside(y, lo, hi, f"{fn}(positions_m=...)", "the network's travel")
    t = _checks.finite(t, f"{fn}(targets=...)")
    steps = _checks.static_int(steps, f"{fn}(steps=...)", 1)
    opt = optimiser_or(optimiser, f"{fn}(optimiser=...)", "adam", 1e-2)
    return _fit(network, y, t, steps, opt)


@eqx.filter_jit
def _fit(network, y, t, steps, opt):
    params, static = eqx.partition(network, eqx.is_inexact_array)

    def loss(p):
        net = eqx.combine(p, static)
        return jnp.mean(jnp.sum((jax.vmap(net._outputs)(y) - t) ** 2, axis=-1))

    def step(carry, _):
        p, state = carry
        value, g = jax.value_and_grad(loss)(p)
        # optax's bias correction raises a float to an int32 power: standard promotion
        with jax.numpy_dtype_promotion("standard"):
            upd, state = opt.update(g, state, p)
            p = optax.apply_updates(p, upd)
        return (p, state), value

    with jax.numpy_dtype_promotion("standard"):
        state = opt.init(params)
    (params, _), history = jax.lax.scan(step, (params, state), None, length=steps)
    return eqx.combine(params, static), history


def bounds_json(b: MCMBounds) -> dict:
    """The bounds as a JSON object (:func:`bounds_from_json` reads it back)."""
    return {"period_s": b.period, "freq_hz": list(b.freq_hz),
            "peak_gain": list(b.peak_gain), "peak_damping": list(b.peak_damping),
            "peak_phase_max_rad": b.peak_phase_max,
            "notch_damping": list(b.notch_damping), "notch_depth_min": b.notch_depth_min}


def bounds_from_json(b: dict) -> MCMBounds:
    """The :class:`MCMBounds` of :func:`bounds_json`."""
    return MCMBounds(period=b["period_s"], freq_hz=tuple(b["freq_hz"]),
                     peak_gain=tuple(b["peak_gain"]), peak_damping=tuple(b["peak_damping"]),
                     peak_phase_max=b["peak_phase_max_rad"],
                     notch_damping=tuple(b["notch_damping"]),
                     notch_depth_min=b["notch_depth_min"])


def drive_fingerprint(drive) -> dict:
    """What identifies the drive a design was tuned for: its type, travel (m) and the SHA-256 of
    its parameters (its leaves, as ``eqx.tree_serialise_leaves`` writes them) and structure."""
    buf = io.BytesIO()
    eqx.tree_serialise_leaves(buf, drive)
    digest = hashlib.sha256(buf.getvalue())
    digest.update(str(jax.tree_util.tree_structure(drive)).encode())
    return {"type": type(drive).__name__, "travel_m": [float(v) for v in drive.travel_m],
            "sha256": digest.hexdigest()}


def check_drive(meta: dict, drive, where: str, path: str) -> None:
    """``drive`` against the fingerprint in ``meta`` (a ``ValueError`` naming ``where`` when
    they differ; nothing to check when the file records no drive)."""
    if drive is None:
        return
    _checks.instance(drive, BallScrewDrive, where.replace("path", "drive"))
    saved = meta.get("drive")
    if not isinstance(saved, dict) or "sha256" not in saved:
        raise ValueError(f"`{where.replace('path', 'drive')}`: {path!r} records no drive to "
                         "compare with (saved without drive=...); load it without drive=")
    if drive_fingerprint(drive)["sha256"] != saved["sha256"]:
        raise ValueError(f"`{where.replace('path', 'drive')}`: {path!r} was tuned for another "
                         f"drive ({saved.get('type')}, travel {saved.get('travel_m')} m, "
                         "other parameters)")


def _hyperparameters(schedule: ScheduledLoop, extra: dict | None, drive=None) -> dict:
    b = schedule.bounds
    return {
        "format": _FORMAT,
        "network": {"width": schedule.network.width, "depth": 2, "activation": "sigmoid",
                    "inputs": ["position (normalised over travel_m)"],
                    "gains": schedule.network.gains, "outputs": list(schedule.network.outputs),
                    "travel_m": list(schedule.network.travel_m)},
        "bounds": bounds_json(b),
        "units": {"kp": "1/s", "kv": "A·s/m", "ki": "rad/s", "k_ffv": "-", "k_ffa": "A·s²/m",
                  "position": "m", "omega": "rad/s"},
        "gains": {k: float(getattr(schedule.loop, k))
                  for k in ("kp", "kv", "ki", "k_ffv", "k_ffa")},
        "metadata": dict(extra or {}),
        **({} if drive is None else {"drive": drive_fingerprint(drive)}),
    }


def _schedule_path(fn, path):
    """The leaves' path, ``.eqx`` added when it has no suffix (as equinox's serialisation adds
    it to a path without one: the file written and the file read are the same); the JSON beside
    it takes the suffix .json, so the path cannot."""
    path = os.fspath(path)
    if os.path.splitext(path)[1].lower() == ".json":
        raise ValueError(f"`{fn}(path=...)` must be the schedule's leaves (e.g. "
                         f"'schedule.eqx'), not the JSON beside them, got {path!r}")
    if pathlib.Path(path).suffix == "":  # equinox's own rule (`tree_serialise_leaves`)
        path = str(pathlib.Path(path).with_suffix(".eqx"))
    return path


def save_schedule(path: str | os.PathLike, schedule: ScheduledLoop, *,
                  drive: BallScrewDrive | None = None, metadata: dict | None = None) -> None:
    """Write ``schedule`` to ``path`` (its leaves, ``eqx.tree_serialise_leaves``) and its
    hyperparameters, gains, units, ``metadata`` and, with ``drive``, the drive it was tuned for
    (type, travel and a SHA-256 of its parameters) to the JSON file beside it (``path`` with
    suffix ``.json``, plain JSON: read it for the metadata).  A path without a suffix takes
    ``.eqx``, as in equinox: ``save_schedule("s1", ...)`` writes ``s1.eqx`` and ``s1.json``.
    :func:`load_schedule` reads both back (from ``"s1"`` or ``"s1.eqx"``), bit for bit."""
    _checks.instance(schedule, ScheduledLoop, "save_schedule(schedule=...)")
    if drive is not None:
        _checks.instance(drive, BallScrewDrive, "save_schedule(drive=...)")
    path = _schedule_path("save_schedule", path)
    folder = os.path.dirname(path)
    if folder and not os.path.isdir(folder):
        raise FileNotFoundError(f"`save_schedule(path=...)`: no folder {folder!r}")
    write_pair(path, schedule, os.path.splitext(path)[0] + ".json",
               _hyperparameters(schedule, metadata, drive), "save_schedule")


def write_pair(leaves_path: str, tree, json_path: str, meta: dict, fn: str) -> None:
    """``tree``'s leaves to ``leaves_path`` and ``meta`` to ``json_path``, each written whole
    or not at all (a temporary file beside it, then renamed): a failure leaves the files
    that were there before.  Metadata that JSON cannot hold is a ``ValueError`` naming
    ``fn(metadata=...)``, and a tree with a non-finite leaf one naming ``fn`` and the leaf, both
    raised before anything is written."""
    _check_finite_leaves(tree, f"{fn}(...)", "cannot be saved")
    try:
        text = json.dumps(meta, indent=2, ensure_ascii=False)
    except (TypeError, ValueError) as err:
        raise ValueError(f"`{fn}(metadata=...)` must hold only what JSON can (strings, "
                         f"numbers, lists, dicts; a JAX or NumPy array as .tolist()): "
                         f"{err}") from None
    tmp = []
    try:
        for target, write in ((leaves_path, lambda t: eqx.tree_serialise_leaves(t, tree)),
                              (json_path, lambda t: pathlib.Path(t).write_text(
                                  text, encoding="utf-8"))):
            tmp.append((target + ".tmp", target))
            write(tmp[-1][0])
        for t, target in tmp:
            os.replace(t, target)
    finally:
        for t, _ in tmp:
            if os.path.exists(t):
                os.remove(t)


def read_json(path: str, where: str, kind: str) -> dict:
    """The JSON object in ``path``; a file that is not one (malformed, truncated, of another
    kind) is a ``ValueError`` naming ``where`` and the file."""
    try:
        with open(path, encoding="utf-8") as f:
            meta = json.load(f)
    except (ValueError, UnicodeDecodeError) as err:
        raise ValueError(f"`{where}`: {path!r} is not the JSON file of {kind} ({err})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"`{where}`: {path!r} is not the JSON file of {kind} (it holds a "
                         f"{type(meta).__name__}, not an object)")
    return meta


def _check_finite_leaves(tree, where: str, consequence: str) -> None:
    """A ``ValueError`` naming the first leaf of ``tree`` (by its path) that holds NaN or ∞."""
    for key, leaf in jax.tree_util.tree_leaves_with_path(eqx.filter(tree, eqx.is_array)):
        if not np.all(np.isfinite(np.asarray(leaf))):
            raise ValueError(f"`{where}`: the leaf {jax.tree_util.keystr(key)} holds NaN or ∞, "
                             f"{consequence}")


def read_leaves(path: str, like, where: str, kind: str):
    """``like``'s leaves read from ``path`` (``eqx.tree_deserialise_leaves``); a file that does
    not hold them (truncated, corrupt, or the leaves of something else) is a ``ValueError``
    naming ``where`` and the file."""
    try:
        with open(path, "rb") as f:  # a file object: equinox adds no suffix to it
            tree = eqx.tree_deserialise_leaves(f, like)
            left = len(f.read())
    except Exception as err:  # numpy's and equinox's errors of a file that is not the tree
        raise ValueError(f"`{where}`: {path!r} does not hold the leaves of {kind} that its JSON "
                         f"describes (truncated, corrupt, or written for something else): "
                         f"{type(err).__name__}: {err}") from err
    if left:  # the leaves of a larger tree (another file) read as far as this one goes
        raise ValueError(f"`{where}`: {path!r} does not hold the leaves of {kind} that its JSON "
                         f"describes (written for something else: {left} bytes left over)")
    _check_finite_leaves(tree, where, f"in {path!r} (not {kind} a loop can run)")
    return tree


def load_schedule(path: str | os.PathLike, *,
                  drive: BallScrewDrive | None = None) -> ScheduledLoop:
    """Read a schedule written by :func:`save_schedule` (the leaves at ``path``, the
    hyperparameters from the JSON file beside it, ``path`` with suffix ``.json``).  A path
    without a suffix takes ``.eqx``, as :func:`save_schedule` does: ``load_schedule("s1")``
    reads ``s1.eqx`` and ``s1.json``.  With ``drive``, the drive the schedule was saved for
    must be this one (same parameters).  Leaves that are not those the JSON describes
    (another file, its gains, its network) are an error."""
    given = os.fspath(path)
    path = _schedule_path("load_schedule", given)
    if os.path.isdir(given):
        hint = os.path.join(given, "schedule.eqx")
        hint = f"; did you mean {hint!r}?" if os.path.exists(hint) else ""
        raise IsADirectoryError(f"`load_schedule(path=...)` must be a schedule's file (e.g. "
                                f"'schedule.eqx'), got the folder {given!r}{hint}")
    # leaves at the path without a suffix: written by an fdjax before save_schedule added .eqx
    leaves = given if not os.path.exists(path) and os.path.isfile(given) else path
    meta_path = os.path.splitext(path)[0] + ".json"
    if not os.path.exists(leaves):
        raise FileNotFoundError(f"`load_schedule(path=...)`: no file {path!r}")
    if not os.path.exists(meta_path):
        raise FileNotFoundError(f"`load_schedule(path=...)`: no file {meta_path!r} (the "
                                f"hyperparameters that save_schedule writes beside {leaves!r})")
    where = "load_schedule(path=...)"
    meta = read_json(meta_path, where, "an fdjax schedule")
    if meta.get("format") != _FORMAT:
        raise ValueError(f"`{where}`: {meta_path!r} is not an fdjax schedule "
                         f"(format {meta.get('format')!r}, expected {_FORMAT!r})")
    try:
        bounds = bounds_from_json(meta["bounds"])
        network = meta["network"]
        if (network.get("depth", 2), network.get("activation", "sigmoid")) != (2, "sigmoid"):
            raise ValueError(f"a network of depth {network.get('depth')!r} and activation "
                             f"{network.get('activation')!r}, where fdjax's has 2 and "
                             "'sigmoid'")
        net = ATANetwork(tuple(network["travel_m"]), width=network["width"],
                         gains=bool(network.get("gains", False)))
        if "outputs" in network and list(network["outputs"]) != list(net.outputs):
            raise ValueError(f"outputs {network['outputs']}, where the network has "
                             f"{list(net.outputs)}")
        like = ScheduledLoop(DoubleLoop(**meta["gains"]), net, bounds)
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise ValueError(f"`{where}`: {meta_path!r} does not describe an fdjax schedule "
                         f"({type(err).__name__}: {err})") from err
    check_drive(meta, drive, where, meta_path)
    schedule = read_leaves(leaves, like, where, "a schedule")
    # the JSON's gains are e^θ as the saving backend rounded it (XLA's exp and libm's differ
    # by up to 2 ulp): compared to 1e-12 relative
    gains = {k: float(getattr(schedule.loop, k)) for k in meta["gains"]}
    if not np.allclose(list(gains.values()), [float(v) for v in meta["gains"].values()],
                       rtol=1e-12, atol=0.0):
        raise ValueError(f"`{where}`: {leaves!r} does not hold the leaves its JSON describes: "
                         f"gains {gains}, where {meta_path!r} has {meta['gains']} (the leaves "
                         "of another schedule, or an edited JSON)")
    return schedule
