r"""End-to-end training of the scheduling network (paper Sec. 4.2 trains it on six local designs;
here it is trained against the tuning objective itself, over the whole travel).

At every step a batch of B positions covers the travel (or a fixed set of positions, for an
optimiser with a line search): its two ends, where the drive's
modes are furthest from the middle's and a schedule's margins are least, and B − 2 positions
drawn between them, stratified,

    Y_0 = Y_min,  Y_b = Y_min + (Y_max − Y_min)(b − 1 + u_b)/(B − 2),  Y_{B−1} = Y_max,
    u_b ~ U(0, 1),   b = 1 … B−2,

and the network's weights (optionally the loop's gains) descend

    ½ (mean_b J(schedule, Y_b) + smax_β J(schedule, Y_b))

(:class:`fdjax.Objective`, :func:`fdjax.smooth_max`), all positions in one ``vmap``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .. import _checks
from .._drive._model import BallScrewDrive
from ._local import Descent, descend, smooth_max
from ._objective import Objective
from ._optimisers import optimiser_or
from ._parameterisation import LOG_GAIN_LIMIT, check_sampled_by
from ._schedule import ScheduledLoop

__all__ = ["train_schedule", "batch_positions", "held_gains"]


def batch_positions(key: PRNGKeyArray, travel: tuple[float, float],
                    batch: int) -> Float[Array, " batch"]:
    """The positions of one step (module docstring): the travel's ends and ``batch`` − 2
    positions drawn between them, one in each of ``batch`` − 2 equal strata (ascending)."""
    lo, hi = travel
    n = batch - 2
    u = jax.random.uniform(key, (n,), jnp.float64)
    inner = lo + (hi - lo) * (jnp.arange(n, dtype=jnp.float64) + u) / max(n, 1)
    return jnp.concatenate([jnp.array([lo]), jnp.clip(inner, lo, hi), jnp.array([hi])])


_GAINS = lambda s: (s.loop.log_kp, s.loop.log_kv, s.loop.log_ki)  # noqa: E731


def held_gains(schedule: ScheduledLoop, reference: Float[Array, " 3"]) -> ScheduledLoop:
    """The schedule with its loop's log gains held within ±``LOG_GAIN_LIMIT`` of
    ``reference`` (ln k_p, ln k_v, ln k_i at the start of training): a trained gain is
    k_ref e^{clip(ln k − ln k_ref, ±30)}, finite and positive after a step of any finite
    length, and bit for bit the trained value inside the limit."""
    raw = jnp.stack(_GAINS(schedule))
    held = jnp.where(jnp.abs(raw - reference) <= LOG_GAIN_LIMIT, raw,
                     reference + jnp.clip(raw - reference, -LOG_GAIN_LIMIT, LOG_GAIN_LIMIT))
    return eqx.tree_at(_GAINS, schedule, tuple(held))


class _EndToEndLoss(eqx.Module):
    static: ScheduledLoop
    objective: Objective
    drive: BallScrewDrive
    positions: Array | None
    reference_gains: Array | None
    travel: tuple[float, float] = eqx.field(static=True)
    batch: int = eqx.field(static=True)
    sharpness: float = eqx.field(static=True)

    def __call__(self, params, key=None):
        schedule = eqx.combine(params, self.static)
        if self.reference_gains is not None:
            schedule = held_gains(schedule, self.reference_gains)
        y = self.positions if key is None else batch_positions(key, self.travel, self.batch)
        j = jax.vmap(lambda p: self.objective(schedule, self.drive, p).total)(y)
        return 0.5 * (jnp.mean(j) + smooth_max(j, self.sharpness)), jnp.max(j)


def train_schedule(
    schedule: ScheduledLoop,
    objective: Objective,
    drive: BallScrewDrive,
    *,
    steps: int = 200,
    batch: int = 8,
    positions_m: Float[ArrayLike, " n"] | None = None,
    key: PRNGKeyArray | None = None,
    optimiser: optax.GradientTransformation | None = None,
    train_gains: bool = False,
    train_feedforward: bool = False,
    sharpness: float = 2.0,
    chunk: int = 25,
    progress: bool = False,
) -> tuple[ScheduledLoop, Descent]:
    r"""Train a schedule end to end against the objective over the travel (module docstring),
    from ``schedule`` (e.g. the network fitted to local designs by :func:`fdjax.fit_network`).

    Args:
        schedule: the scheduled loop to start from.
        objective: J(controller, Y).
        drive: the drive (positions are drawn over its travel).
        steps: optimiser steps; batch: positions per step (≥ 2): the travel's two ends and
            ``batch`` − 2 drawn between them.
        positions_m: instead of drawn batches, these positions (m) at every step: the
            objective is then deterministic, as an optimiser with a line search needs
            (``optax.lbfgs()``), and the best step is the best schedule on them.
        key: PRNG key of the position draws (default ``PRNGKey(0)``).
        optimiser: an optax transformation (default ``optax.adam(3e-3)``); a later call
            with the same object and shapes reuses the compiled steps.
        train_gains: also train the loop's feedback gains (k_p, k_v, k_i), common to every
            position, each held within e^±30 of its start, so that no step of any length
            overflows it.  A network with gains (``ATANetwork(gains=True)``)
            schedules them over the position through its own outputs, which are trained with
            its weights.
        train_feedforward: also train its feed-forward gains (k_ffv, k_ffa); off, they keep
            their values (zero in a feedback-only loop), so that a feedback schedule is compared
            with feedback designs.
        sharpness: β of the smooth maximum over the batch.
        chunk, progress: as :func:`fdjax.tune_local`.

    Returns:
        The schedule of the lowest batch objective seen (with drawn batches, each step's is on
        its own batch), and the :class:`Descent` record (``history``: the batch objective per
        step, ``aux``: the batch's worst J).
    """
    fn = "train_schedule"
    _checks.instance(schedule, ScheduledLoop, f"{fn}(schedule=...)")
    _checks.instance(objective, Objective, f"{fn}(objective=...)")
    _checks.instance(drive, BallScrewDrive, f"{fn}(drive=...)")
    check_sampled_by(schedule.bounds.freq_hz[1], objective.servo, f"{fn}(schedule=...)")
    objective = objective.resolved(drive, fn)
    steps, batch, chunk = (_checks.static_int(value, f"{fn}({name}=...)", least)
                           for name, value, least in (("steps", steps, 1), ("batch", batch, 2),
                                                      ("chunk", chunk, 1)))
    sharpness = _checks.static_positive(sharpness, f"{fn}(sharpness=...)")
    spec = jax.tree_util.tree_map(lambda _: False, schedule)
    spec = eqx.tree_at(lambda s: s.network, spec,
                       jax.tree_util.tree_map(eqx.is_inexact_array, schedule.network))
    if train_gains:
        spec = eqx.tree_at(_GAINS, spec, (True,) * 3)
    if train_feedforward:
        ff = lambda s: (s.loop.k_ffv, s.loop.k_ffa)  # noqa: E731
        spec = eqx.tree_at(ff, spec, (True,) * 2)
    lo, hi = drive.travel_m
    n_lo, n_hi = schedule.network.travel_m
    if positions_m is not None:
        where = f"{fn}(positions_m=...)"
        fixed = np.asarray(_checks.real_array(positions_m, where))
        if fixed.ndim != 1 or fixed.size == 0:
            raise ValueError(f"`{where}` must be a non-empty 1-D array, got shape {fixed.shape}")
        _checks.inside(fixed, lo, hi, where)
        _checks.inside(fixed, n_lo, n_hi, where, "the network's travel")
        fixed = jnp.asarray(fixed)
    else:
        fixed = None
        if not (n_lo <= lo and hi <= n_hi):  # the batches are drawn over the drive's travel
            raise ValueError(f"`{fn}(schedule=...)`: the network's travel [{n_lo:.6g}, "
                             f"{n_hi:.6g}] m must cover the drive's [{lo:.6g}, {hi:.6g}] m, "
                             "over which the batches are drawn (or give positions_m)")
    params, static = eqx.partition(schedule, spec)
    reference = jnp.stack(_GAINS(schedule)) if train_gains else None
    loss = _EndToEndLoss(static, objective, drive, fixed, reference,
                         tuple(float(v) for v in drive.travel_m), batch, float(sharpness))
    opt = optimiser_or(optimiser, f"{fn}(optimiser=...)", "adam", 3e-3)
    if fixed is not None:
        key = None
    elif key is None:
        key = jax.random.PRNGKey(0)
    res = descend(loss, params, opt, steps, chunk=chunk, key=key,
                  progress=fn if progress else None)
    best = eqx.combine(res.best, static)
    return (best if reference is None else held_gains(best, reference)), res


