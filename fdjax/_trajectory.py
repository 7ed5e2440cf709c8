r"""Reference motions r(t) for closed-loop simulation: jerk-limited moves (paper Figs. 16–17).

A ``Trajectory`` is a piecewise-constant *jerk* j(t) on knots 0 = t_0 ≤ t_1 ≤ … ≤ t_k = T,
integrated exactly three times from rest at the initial position r0. On segment i, with
τ = t − t_i ∈ [0, h_i], h_i = t_{i+1} − t_i,

    a(t) = a_i + j_i τ,
    v(t) = v_i + a_i τ + j_i τ²/2,
    r(t) = r_i + v_i τ + a_i τ²/2 + j_i τ³/6,

and the states at the knots follow by evaluating these at τ = h_i (exact cubic integration):

    a_{i+1} = a_i + j_i h_i,
    v_{i+1} = v_i + a_i h_i + j_i h_i²/2,
    r_{i+1} = r_i + v_i h_i + a_i h_i²/2 + j_i h_i³/6,      a_0 = v_0 = 0, r_0 = r0.

So r is C² (position, velocity and acceleration continuous) and j is piecewise constant.
Before t = 0 the trajectory rests at r0; after T it rests at r(T) (v = a = j = 0).

``jerk_limited`` builds the classic seven-segment ("double S") point-to-point move of
Biagiotti & Melchiorri, *Trajectory Planning for Automatic Machines and Robots* (Springer 2008),
Sec. 3.4, for a move from rest to rest; ``reciprocating`` chains such moves into the short-stroke
back-and-forth reference of the paper's Figs. 16–17; ``concatenate`` plays trajectories one after
another. Units are SI: m, m/s, m/s², m/s³, s.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._checks import (
    LONGEST_TRAVEL_M,
    check,
    concrete_float,
    finite,
    inside,
    is_concrete,
    nonnegative,
    numeric,
    positive,
    real_scalar,
    static_int,
)

__all__ = ["Trajectory", "concatenate", "jerk_limited", "reciprocating"]

_COMPARE_ALL_MAX = 64  # segments up to which `evaluate` locates t by comparing with every knot


def _real(value, where: str, ndim: int) -> Array:
    """``value`` as a float64 array of rank ``ndim`` (shape and dtype facts only)."""
    arr = numeric(value, where)
    if jnp.issubdtype(arr.dtype, jnp.complexfloating):
        raise ValueError(f"`{where}` must be real, got dtype {arr.dtype}")
    if arr.ndim != ndim:
        kind = "a scalar" if ndim == 0 else f"a {ndim}-D array"
        raise ValueError(f"`{where}` must be {kind}, got shape {arr.shape}")
    return arr.astype(jnp.float64)


def _knots_ok(v):
    """Elementwise: finite, first knot 0, each knot ≥ the previous one."""
    xp = np if isinstance(v, np.ndarray) else jnp
    prev = xp.concatenate([xp.zeros(1, v.dtype), v[:-1]])
    first = xp.arange(v.shape[0]) == 0
    return xp.isfinite(v) & (v >= prev) & (~first | (v == 0))


class Trajectory(eqx.Module):
    r"""A reference motion r(t) with piecewise-constant jerk, starting from rest at ``r0``.

    On segment i (t_i ≤ t < t_{i+1}, τ = t − t_i) the motion is the exact cubic

        r(t) = r_i + v_i τ + a_i τ²/2 + j_i τ³/6,   v = ṙ,  a = r̈,  j = j_i,

    with the knot states (r_i, v_i, a_i) integrated from (r0, 0, 0) (see the module docstring).
    For t < 0 it rests at r0 and for t > T = ``t_knots[-1]`` at r(T), with v = a = j = 0 (the
    constructors below end every move at rest, so this keeps r, v, a continuous).

    **Arguments:**

    - ``t_knots``: knot times t_0 = 0 ≤ t_1 ≤ … ≤ t_k in s, shape (k+1,), k ≥ 1. Zero-length
      segments are allowed (they are skipped).
    - ``jerk``: the constant jerk of each segment in m/s³, shape (k,).
    - ``r0``: initial position in m (the initial velocity and acceleration are 0).

    The motion is stored as its segments' ``durations`` h_i = t_{i+1} − t_i (the leaf), not as
    knot times: the states are integrated over the segments' own lengths, so that a move played
    late in a long sequence (:func:`concatenate`, many cycles of :func:`reciprocating`) is the
    same move, ending at rest where it should (lengths recovered as differences of large knot
    times are off by their rounding, ~εt, and the error grows with the time: 1.4 µm after
    1000 cycles of 0.3 m strokes).  ``t_knots`` is their running sum, which may differ from
    knot times given to the constructor by their rounding (a few ulps).

    The knot states are not stored either: ``evaluate`` integrates them (O(k), one sequential
    scan), then locates each time with ``searchsorted`` (O(log k); O(k) compares for k ≤ 64,
    which compile faster) and evaluates one cubic. Stored as leaves they would go stale under
    ``eqx.tree_at`` and cut the gradient w.r.t. ``jerk`` and the durations; computed on the
    fly, r(t) is differentiable w.r.t. every leaf and w.r.t. t. ``evaluate`` is compiled once
    per structure (k) and shape of t.
    """

    durations: Float[Array, " k"]
    jerk: Float[Array, " k"]
    r0: Float[Array, ""]

    def __init__(self, t_knots: Float[ArrayLike, " knots"], jerk: Float[ArrayLike, " segments"],
                 r0: Float[ArrayLike, ""] = 0.0):
        t_knots = _real(t_knots, "Trajectory(t_knots=...)", 1)
        jerk = _real(jerk, "Trajectory(jerk=...)", 1)
        r0 = _real(r0, "Trajectory(r0=...)", 0)
        if t_knots.shape[0] < 2:
            raise ValueError(
                "`Trajectory(t_knots=...)` must hold at least two knots (one segment), "
                f"got shape {t_knots.shape}"
            )
        if jerk.shape[0] != t_knots.shape[0] - 1:
            raise ValueError(
                "`Trajectory(jerk=...)` must have one entry per segment "
                f"(len(t_knots) - 1 = {t_knots.shape[0] - 1}), got shape {jerk.shape}"
            )
        t_knots = check(
            t_knots, _knots_ok, "Trajectory(t_knots=...)", "finite, non-decreasing and start at 0"
        )
        self.durations = jnp.diff(t_knots)
        self.jerk = finite(jerk, "Trajectory(jerk=...)")
        self.r0 = finite(r0, "Trajectory(r0=...)")

    @property
    def t_knots(self) -> Float[Array, " k1"]:
        """The knot times t_0 = 0, t_{i+1} = t_i + h_i (s), shape (k+1,): the running sum of
        ``durations``."""
        return _knot_times(self)

    @property
    def duration(self) -> Float[Array, ""]:
        """T = t_k, the time at which the motion ends (s)."""
        return self.t_knots[-1]

    @property
    def num_segments(self) -> int:
        """k, the number of constant-jerk segments (static)."""
        return self.jerk.shape[0]

    def knot_states(self) -> tuple[Float[Array, " k1"], Float[Array, " k1"], Float[Array, " k1"]]:
        r"""(r_i, v_i, a_i) at every knot, by exact cubic integration from (r0, 0, 0).

        a_{i+1} = a_i + j_i h_i,
        v_{i+1} = v_i + a_i h_i + j_i h_i²/2,
        r_{i+1} = r_i + v_i h_i + a_i h_i²/2 + j_i h_i³/6,    (r_0, v_0, a_0) = (r0, 0, 0).
        """
        return _knot_states(self)

    def evaluate(
        self, t: Float[ArrayLike, "*t"]
    ) -> tuple[Float[Array, "*t"], Float[Array, "*t"], Float[Array, "*t"], Float[Array, "*t"]]:
        r"""Position, velocity, acceleration and jerk (r, ṙ, r̈, j) at times ``t`` (s), any shape.

        With i the segment holding t (the last one among equal knots) and τ = t − t_i:
        r = r_i + v_i τ + a_i τ²/2 + j_i τ³/6, v = v_i + a_i τ + j_i τ²/2, a = a_i + j_i τ.
        Outside [0, T] the motion rests (v = a = j = 0) at r0 before and at r(T) after.
        """
        t = numeric(t, "Trajectory.evaluate(t=...)")
        if jnp.issubdtype(t.dtype, jnp.complexfloating):
            raise ValueError(f"`Trajectory.evaluate(t=...)` must be real, got dtype {t.dtype}")
        t = finite(t.astype(jnp.float64), "Trajectory.evaluate(t=...)")
        return _evaluate(self, t)

    def sample(self, t: Float[ArrayLike, "*t"]) -> Float[Array, "*t 3"]:
        """(r, ṙ, r̈) at times ``t`` stacked on a last axis of size 3, e.g. a simulation input.

        For n samples at a step dt use ``t = dt * jnp.arange(n)``.
        """
        t = numeric(t, "Trajectory.sample(t=...)")
        if jnp.issubdtype(t.dtype, jnp.complexfloating):
            raise ValueError(f"`Trajectory.sample(t=...)` must be real, got dtype {t.dtype}")
        t = finite(t.astype(jnp.float64), "Trajectory.sample(t=...)")
        r, v, a, _ = _evaluate(self, t)
        return jnp.stack([r, v, a], axis=-1)

    def position_range(self) -> tuple[Float[Array, ""], Float[Array, ""]]:
        r"""(min r, max r): the exact extremes of the position over the whole motion (m).

        On segment i, r is the cubic r_i + v_i τ + a_i τ²/2 + j_i τ³/6 on τ ∈ [0, h_i], so its
        extremes lie at the knots or where the velocity v_i + a_i τ + j_i τ²/2 vanishes inside
        the segment.  Those roots are taken in the cancellation-free form τ = q/A, C/q with
        A = j_i/2, B = a_i, C = v_i, q = −(B + sign(B)√(B² − 4AC))/2 (one root when j_i = 0).
        Before t = 0 and after T the motion rests at r0 and r(T), both knots.  O(k), fixed
        shapes: jit-, vmap- and grad-safe, e.g. to check Y₀ + r(t) against a drive's travel.
        """
        return _position_range(self)


def _step(state, seg):
    """One segment of exact cubic integration: (r, v, a) at t_i → at t_{i+1}."""
    r, v, a = state
    h, j = seg
    new = (r + h * (v + h * (a / 2 + h * j / 6)), v + h * (a + h * j / 2), a + h * j)
    return new, new


def _from_durations(durations, jerk, r0) -> Trajectory:
    """A :class:`Trajectory` with these segment durations (concrete or traced, finite and ≥ 0
    by construction: from validated moves), jerks and start."""
    template = Trajectory(t_knots=np.zeros(2), jerk=np.zeros(1))
    return eqx.tree_at(lambda t: (t.durations, t.jerk, t.r0), template,
                       (jnp.asarray(durations, jnp.float64), jnp.asarray(jerk, jnp.float64),
                        jnp.asarray(r0, jnp.float64)))


def _running_sum(total, h):
    total = total + h
    return total, total


@eqx.filter_jit
def _knot_times(traj: Trajectory):
    # A sequential scan (compiles far faster than cumsum on CPU; the same sums as np.cumsum)
    zero = jnp.zeros((), jnp.float64)
    _, t = jax.lax.scan(_running_sum, zero, traj.durations)
    return jnp.concatenate([zero[None], t])


@eqx.filter_jit
def _knot_states(traj: Trajectory):
    # A sequential scan is the recurrence itself (and compiles far faster than cumsum on CPU).
    zero = jnp.zeros((), jnp.float64)
    start = (traj.r0, zero, zero)
    _, states = jax.lax.scan(_step, start, (traj.durations, traj.jerk))
    return tuple(jnp.concatenate([s0[None], x]) for s0, x in zip(start, states))


@eqx.filter_jit
def _evaluate(traj: Trajectory, t: Float[Array, "*t"]):
    """The body of ``Trajectory.evaluate``, compiled once per structure and shape of ``t``."""
    rk, vk, ak = _knot_states(traj)
    tk = traj.t_knots
    T = tk[-1]
    k = traj.num_segments
    # One row per segment, gathered once: (t_i, r_i, v_i, a_i, j_i).
    rows = jnp.stack([tk[:-1], rk[:-1], vk[:-1], ak[:-1], traj.jerk], axis=-1)
    # t clamped to [0, T] by selection, not by jnp.clip: at t = T (or 0) exactly, clip's
    # derivative splits in half between t and T, whereas r(t) at a fixed t moves with t only
    tc = jnp.where(t > T, T, jnp.where(t < 0.0, 0.0, t))
    # The last segment starting at or before tc (zero-length segments are skipped). For the
    # few knots of a move, comparing with all of them (O(k) per time) compiles fastest; long
    # sequences use the binary search (O(log k)).
    method = "compare_all" if k <= _COMPARE_ALL_MAX else "scan_unrolled"
    i = jnp.searchsorted(tk, tc, side="right", method=method) - 1
    row = rows[jnp.clip(i, 0, k - 1)]
    tau = tc - row[..., 0]
    ri, vi, ai, ji = row[..., 1], row[..., 2], row[..., 3], row[..., 4]
    r = ri + tau * (vi + tau * (ai / 2 + tau * ji / 6))
    v = vi + tau * (ai + tau * ji / 2)
    a = ai + tau * ji
    # At rest outside [0, T]: r is already held by the clamp; v, a, j are switched off.
    moving = ((t >= 0.0) & (t <= T)).astype(t.dtype)
    return r, v * moving, a * moving, ji * moving


@eqx.filter_jit
def _position_range(traj: Trajectory):
    rk, vk, ak = _knot_states(traj)
    h = traj.durations
    r, v, a, j = rk[:-1], vk[:-1], ak[:-1], traj.jerk
    # Roots of (j/2) τ² + a τ + v = 0, without cancellation; a non-real or out-of-segment
    # root is replaced by τ = 0 (the knot, already a candidate).
    A, B, C = j / 2, a, v
    disc = B * B - 4 * A * C
    real = disc >= 0
    # √disc with a finite derivative at disc = 0 (a double root: the velocity touches zero)
    sqrt_disc = jnp.where(disc > 0, jnp.sqrt(jnp.where(disc > 0, disc, 1.0)), 0.0)
    q = -0.5 * (B + jnp.where(B >= 0, 1.0, -1.0) * sqrt_disc)
    safe_q = jnp.where(q != 0, q, 1.0)
    safe_A = jnp.where(A != 0, A, 1.0)
    roots = jnp.stack([
        jnp.where(real & (A != 0), q / safe_A, 0.0),
        jnp.where(real & (q != 0), C / safe_q, 0.0),
    ])
    tau = jnp.where((roots > 0) & (roots < h), roots, 0.0)
    r_roots = r + tau * (v + tau * (a / 2 + tau * j / 6))
    candidates = jnp.concatenate([rk, r_roots.reshape(-1)])
    return jnp.min(candidates), jnp.max(candidates)


def _number(value, where: str, test) -> float:
    """A concrete real scalar (the profile's structure is computed in Python) passing ``test``
    (``finite``, ``positive`` or ``nonnegative``), as a Python float."""
    return test(concrete_float(value, where), where)


def _move(value, where: str) -> float:
    """A signed move length (m), finite and no longer than :data:`LONGEST_TRAVEL_M` (no
    ball-screw axis is longer): a longer one was given in millimetres, and the message says
    so with its value in metres (:func:`fdjax._checks.inside`)."""
    d = _number(value, where, finite)
    return inside(d, -LONGEST_TRAVEL_M, LONGEST_TRAVEL_M, where,
                  "the longest travel of a ball-screw axis", "move lengths")


def _double_s_durations(h: float, v: float, a: float, j: float) -> tuple[float, float, float]:
    r"""(T_j, T_c, T_v): jerk, constant-acceleration and cruise durations for a rest-to-rest move.

    Accelerating from rest to a peak velocity v_p under the limits a, j takes
    T_j = a/j, T_a = T_j + v_p/a when v_p j ≥ a² (a is reached) and T_j = √(v_p/j), T_a = 2T_j
    otherwise; the acceleration phase covers v_p T_a/2, so both ramps together cover
    D(v_p) = v_p T_a. If h ≥ D(v) the move cruises at v for T_v = (h − D(v))/v; otherwise v_p < v
    solves D(v_p) = h, which reaches a iff h ≥ D(a²/j) = 2a³/j².
    """
    if v * j >= a * a:
        tj = a / j
        ta = tj + v / a
    else:
        tj = math.sqrt(v / j)
        ta = 2.0 * tj
    reach = v * ta
    # T_c ≥ 0 in exact arithmetic; on a limit's boundary (v j = a², or h = 2a³/j²) its
    # rounding can fall a few ulps below zero, so it is clamped at 0
    if h >= reach:
        return tj, max(ta - 2.0 * tj, 0.0), (h - reach) / v
    c = a * (a / j)  # a²/j, written (as 2a³/j² below) so that nothing overflows needlessly
    if h >= 2.0 * c * (a / j):
        # v_p²/a + v_p a/j − h = 0; the root is well conditioned (√(a⁴/j² + 4ha) ≥ 3a²/j).
        vp = (math.sqrt(c * c + 4.0 * h * a) - c) / 2.0
        tj = a / j
        return tj, max(vp / a - tj, 0.0), 0.0
    return (h / (2.0 * j)) ** (1.0 / 3.0), 0.0, 0.0


def jerk_limited(
    distance: float,
    v_max: float,
    a_max: float,
    j_max: float,
    *,
    start: float = 0.0,
    dwell: float = 0.0,
) -> Trajectory:
    r"""The seven-segment jerk-limited ("double S") move by ``distance`` m, from rest to rest.

    Jerk sequence s·(+J, 0, −J, 0, −J, 0, +J) with s = sign(distance), J = ``j_max``, and
    durations (T_j, T_c, T_j, T_v, T_j, T_c, T_j) (Biagiotti & Melchiorri 2008, Sec. 3.4, with
    zero initial and final velocity). With h = |distance|, v = ``v_max``, a = ``a_max``:

    * acceleration phase to v: T_j = a/j, T_a = a/j + v/a if v j ≥ a² (a is reached), else
      T_j = √(v/j), T_a = 2T_j (triangular acceleration); it covers v T_a/2;
    * v is reached if h ≥ v T_a: cruise T_v = h/v − T_a, total T = h/v + T_a, i.e.
      T = h/v + v/a + a/j (full seven segments) or T = h/v + 2√(v/j) (a not reached);
    * otherwise no cruise (T_v = 0) and the peak velocity v_p < v:
      if h ≥ 2a³/j², a is reached, T_j = a/j, v_p = (√(a⁴/j² + 4ha) − a²/j)/2,
      T_a = a/j + v_p/a, T = 2T_a = a/j + √(a²/j² + 4h/a);
      else neither limit is reached, T_j = (h/(2j))^{1/3}, T_a = 2T_j, T = 4T_j.

    T_c = T_a − 2T_j. Peaks: |v| ≤ v, |a| = j T_j ≤ a, |j| = J.

    **Arguments:**

    - ``distance``: signed move length in m (negative moves backwards; 0 gives a pure dwell;
      300 mm is ``0.3``), at most 20 m (``LONGEST_TRAVEL_M``) either way: a longer one was
      given in mm and is refused, with its value in metres. The travel is checked where the
      move meets a drive (see :meth:`Trajectory.position_range`).
    - ``v_max``, ``a_max``, ``j_max``: positive limits in m/s, m/s², m/s³.
    - ``start``: initial position in m.
    - ``dwell``: rest time appended after the move in s (a zero-jerk segment).

    ``distance`` and the limits must be concrete numbers (the segments' durations are computed
    from them in Python); ``start`` and ``dwell`` are leaves of the result and may be traced
    (``jit``, ``vmap``, ``grad``).

    **Returns:** a ``Trajectory`` with 8 segments (zero-length ones where a phase is absent), of
    duration T + ``dwell``, ending at ``start + distance``.
    """
    fn = "jerk_limited({}=...)"
    d = _move(distance, fn.format("distance"))
    limits = _limits(v_max, a_max, j_max, fn)
    return _double_s(d, limits, _start(start, fn), _dwell(dwell, fn), fn)


def _limits(v_max, a_max, j_max, fn: str) -> tuple[float, float, float]:
    """The concrete, positive limits (v, a, j) of a move; ``fn`` formats the argument names."""
    names = {"v_max": v_max, "a_max": a_max, "j_max": j_max}
    return tuple(_number(x, fn.format(k), positive) for k, x in names.items())


def _start(value, fn: str) -> Array:
    """The initial position (m): a finite real scalar, concrete or traced (it is the leaf r0)."""
    where = fn.format("start")
    return finite(real_scalar(value, where), where)


def _dwell(value, fn: str) -> Array:
    """A rest time (s): a finite, non-negative real scalar, concrete or traced (a leaf)."""
    where = fn.format("dwell")
    return nonnegative(real_scalar(value, where), where)


def _double_s(d: float, limits, r0, rest, fn: str) -> Trajectory:
    """``jerk_limited``'s body: the move by ``d`` m under ``limits``, then ``rest`` s at rest;
    ``fn`` is the public function called, for the message of a move too long to time."""
    v, a, j = limits
    tj, tc, tv = _double_s_durations(abs(d), v, a, j)
    durations = np.array([tj, tc, tj, tv, tj, tc, tj], dtype=np.float64)
    if not np.all(np.isfinite(durations)):
        names = fn.format("v_max=..., a_max=..., j_max")
        raise ValueError(
            f"`{names}` are too small for a move of {abs(d):.6g} m: its durations overflow"
            f" (got v_max={v:.6g} m/s, a_max={a:.6g} m/s², j_max={j:.6g} m/s³)"
        )
    s = float(np.sign(d))
    jerks = s * j * np.array([1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0, 0.0])
    return _from_durations(jnp.concatenate([jnp.asarray(durations), rest[None]]), jerks, r0)


@eqx.filter_jit
def _end_state(traj: Trajectory):
    """The final velocity and acceleration, and whether they are zero to 1e-9 of their scales.

    The scales are the sums of the absolute increments, Σ|a_m h_m + j_m h_m²/2| and Σ|j_m h_m|,
    which bound the rounding of the recurrence by a few eps per term.
    """
    _, vk, ak = _knot_states(traj)
    h, jm = traj.durations, traj.jerk
    a_scale = jnp.sum(jnp.abs(jm * h))
    v_scale = jnp.sum(jnp.abs(h * (ak[:-1] + h * jm / 2)))
    at_rest = (jnp.abs(vk[-1]) <= 1e-9 * v_scale) & (jnp.abs(ak[-1]) <= 1e-9 * a_scale)
    return vk[-1], ak[-1], at_rest


def concatenate(*trajectories: Trajectory) -> Trajectory:
    r"""Play ``trajectories`` one after another, each starting where the previous one ends.

    The pieces' segment durations and jerks are joined (each segment keeps its exact length,
    however late it plays) and the motion is re-integrated, so each later piece moves
    *relative* to where the previous one stops (its own ``r0`` is ignored) and the result
    starts at the first piece's ``r0``. Every piece but the last must end at rest (v = a = 0),
    otherwise it would not play as it does on its own; this is checked, also under ``jit``.
    """
    if not trajectories:
        raise ValueError("`concatenate(*trajectories)` needs at least one Trajectory, got none")
    for n, traj in enumerate(trajectories):
        if not isinstance(traj, Trajectory):
            raise ValueError(
                f"`concatenate(*trajectories)` takes Trajectory objects, got "
                f"{type(traj).__name__} at position {n}"
            )
    moving = []  # traced pieces' flags: whether each ends in motion
    for n, traj in enumerate(trajectories[:-1]):
        v_end, a_end, at_rest = _end_state(traj)
        if is_concrete(at_rest):
            if not bool(at_rest):
                raise ValueError(
                    f"`concatenate(*trajectories)`: trajectory {n} must end at rest to be "
                    f"followed by another, got final velocity {float(v_end):.6g} m/s and "
                    f"acceleration {float(a_end):.6g} m/s²"
                )
        else:
            moving.append(jnp.logical_not(at_rest))
    durations = check(jnp.concatenate([traj.durations for traj in trajectories]),
                      lambda h: (h >= 0) & jnp.isfinite(jnp.cumsum(h)),
                      "concatenate(*trajectories)",
                      "made of segments of finite, non-negative durations, with finite knot "
                      "times (their running sum)")
    if moving:
        durations = eqx.error_if(durations, jnp.any(jnp.stack(moving)),
                                 "`concatenate(*trajectories)`: every trajectory but the last "
                                 "must end at rest (v = a = 0) to be followed by another")
    return _from_durations(durations,
                           jnp.concatenate([traj.jerk for traj in trajectories]),
                           trajectories[0].r0)


def reciprocating(
    stroke: float = 5e-3,
    v_max: float = 0.1,
    a_max: float = 2.0,
    j_max: float = 200.0,
    *,
    cycles: int = 1,
    dwell: float = 0.0,
    start: float = 0.0,
) -> Trajectory:
    r"""Short-stroke reciprocating reference (paper Figs. 16–17): ``cycles`` × (out, dwell, back,
    dwell).

    Each cycle is ``jerk_limited(stroke, ...)`` followed by ``jerk_limited(-stroke, ...)``, each
    with ``dwell`` s of rest after it, so the axis is back at ``start`` at the end of every cycle,
    t = n (2T + 2·dwell), with T the duration of one stroke (see ``jerk_limited``).

    The defaults are a short stroke of a machine-tool feed axis: 5 mm at 0.1 m/s, 2 m/s² and
    200 m/s³. With them v_max is not reached (the stroke is shorter than v T_a = 6 mm): T_j =
    10 ms, peak 0.0905 m/s, T = a/j + √(a²/j² + 4h/a) ≈ 0.1105 s, so one cycle takes ≈ 0.221 s
    plus the dwells, about two cycles in a 0.5 s simulation window.

    **Arguments:**

    - ``stroke``: signed stroke length in m (negative goes backwards first; 5 mm is ``5e-3``),
      at most 20 m (``LONGEST_TRAVEL_M``) either way: a longer one was given in mm and is
      refused, with its value in metres. A trajectory does not know the drive: whoever places
      it on one checks start + stroke against the travel, e.g. with
      :meth:`Trajectory.position_range` (``simulate`` does).
    - ``v_max``, ``a_max``, ``j_max``: positive limits in m/s, m/s², m/s³.
    - ``cycles``: number of out-and-back cycles, an integer ≥ 1.
    - ``dwell``: rest after each stroke in s.
    - ``start``: initial (and final) position in m.

    ``stroke``, the limits and ``cycles`` must be concrete (they fix the segments); ``start``
    and ``dwell`` may be traced (``jit``, ``vmap``, ``grad``).
    """
    cycles = static_int(cycles, "reciprocating(cycles=...)", 1)
    fn = "reciprocating({}=...)"
    h = _move(stroke, fn.format("stroke"))
    limits = _limits(v_max, a_max, j_max, fn)
    rest = _dwell(dwell, fn)
    r0 = _start(start, fn)

    out = _double_s(h, limits, r0, rest, fn)
    back = _double_s(-h, limits, r0 + h, rest, fn)
    return concatenate(*([out, back] * int(cycles)))
