r"""The whole gradient synthesis of paper Sec. 4.2 and Fig. 18 on one drive, as one function.

1. **Local designs**: the full double loop (gains and MCM) at 115 mm (the fixed MCM of
   Fig. 18): a simplex search (:func:`tune_simplex`) from the reference controller with k_v
   halved (stable at every position) finds the basin and the gradient (:func:`tune_local`)
   descends it (Adam), both on the objective with wide margin penalties (w = 0.05: smooth
   far from the requirements); L-BFGS (``optax.lbfgs``, a line search on every step) then
   continues on the objective with sharp penalties (``margin_width``, default 0.01), which
   takes the design up to its requirements.  Then the six positions over the travel by
   L-BFGS from the design at 115 mm.  Every stage from here on uses the sharp objective.
2. **Common gains**: one gain set and one MCM per design position (:func:`tune_shared_gains`,
   L-BFGS), what a schedule of the filters needs, from the design at 115 mm at every
   position.
3. **Baselines**: a PID tuned at 115 mm by the same three stages, the robust PID
   (:func:`tune_robust` over 13 positions, from the reference PID and from the PID tuned at
   115 mm with wide penalties, the better of the two continued by L-BFGS with sharp ones),
   the MCM
   tuned at 115 mm held fixed, the six MCMs interpolated linearly in their normalised
   parameters (:class:`InterpolatedLoop`), and the robust MCM: one double loop with its MCM
   for every position (:func:`tune_robust` over 13 positions, L-BFGS), the fixed design a
   schedule must beat, from the end-to-end schedule at the screw end.
4. **The ATA network** fitted to the six MCMs by backpropagation (:func:`fit_network`), then
   **trained end to end** against the objective over the travel, with the loop's common gains
   (:func:`train_schedule`, L-BFGS on a grid of positions over the travel).
5. **Evaluation**: RMS error, stability and the exact sampled margins of every controller on a
   grid of positions (:func:`evaluate`, :func:`certify`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import ArrayLike, Float

from .. import _checks, _progress
from .._checks import instance
from .._control._controllers import AbstractController
from .._control._reference import (
    reference_controller,
    reference_pid,
    reference_servo,
    rigid_feedforward,
)
from .._control._servo import Servo
from .._drive._model import BallScrewDrive
from .._drive._reference import reference_drive
from .._drive._twin import TwinOptions
from .._memory import release
from .._trajectory import Trajectory, reciprocating
from ._certify import certificate, check_grid_resolves, default_grid, point_checks
from ._end_to_end import train_schedule
from ._local import Descent, LocalTuning, RobustTuning, tune_local, tune_robust, tune_shared_gains
from ._objective import Objective
from ._optimisers import default_optimiser
from ._parameterisation import (
    DoubleLoopParameterisation,
    MCMBounds,
    PIDParameterisation,
    check_sampled_by,
)
from ._schedule import ATANetwork, InterpolatedLoop, ScheduledLoop, fit_network
from ._simplex import tune_simplex

__all__ = ["CONTROLLERS", "Synthesis", "synthesise", "evaluate", "tuning_motion",
           "tuning_objective"]

CONTROLLERS = ("pid_115", "pid_robust", "mcm_fixed", "mcm_robust", "mcm_interp", "mcm_ata",
               "mcm_ata_e2e")
"""The controllers of fdjax's Fig. 18 (the paper's Fig. 18, PID against MCM + ATA, with the
baselines of a fair comparison added), in the order of the figure's legend."""

LABELS = {
    "pid_115": "PID tuned at 115 mm",
    "pid_robust": "robust PID",
    "mcm_fixed": "MCM tuned at 115 mm, fixed",
    "mcm_robust": "robust MCM (one design)",
    "mcm_interp": "local MCMs interpolated",
    "mcm_ata": "MCM + ATA (backpropagation)",
    "mcm_ata_e2e": "MCM + ATA (end to end)",
}

DESIGN_POSITIONS_M = tuple(float(v) for v in np.linspace(0.1, 0.7, 6))
FIXED_POSITION_M = 0.115
WIDE_MARGIN_WIDTH = 0.05


def tuning_motion() -> Trajectory:
    """The motion the controllers are tuned on: a 1 mm reciprocating stroke, one 0.1 s cycle,
    limits 50 mm/s, 2 m/s², 400 m/s³ (the speed peaks at 40 mm/s: the stroke is too short to
    reach the limit), the short-stroke motion of paper Figs. 16–17 shortened."""
    return reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)


def tuning_objective(servo: Servo | None = None, *, feedforward: bool = False,
                     kept_modes: int | None = 6, margin_width: float = 0.05) -> Objective:
    """The objective of the synthesis: :class:`Objective` on :func:`tuning_motion`, margins on
    400 frequencies from 5 Hz to 0.975 of the servo's Nyquist frequency (3.9 kHz at the
    reference servo's 8 kHz), the twin with ``kept_modes`` modes.  The error scale
    e_ref is 100 µm for feedback-only loops (their RMS error on this motion is 85–200 µm) and
    1 µm with feed-forward (1–5 µm), so that J is of order one and the margin penalties
    weigh the same in both.  ``margin_width`` is the margin penalties' width w, and their
    smooth minimum's β is 10/w (within (log 400)/β of the grid's minimum).  A design settles
    where the penalties' slope meets the error's, a few w above each requirement: 0.1–0.15
    above the modulus margin at the default w = 0.05, which is smooth for a search from afar;
    0.01–0.04 above at w = 0.01, where :func:`synthesise` finishes every design
    (``examples/margin_requirements.py`` compares them).

    ``servo`` is an :class:`fdjax.Servo` (default :func:`reference_servo`), ``feedforward`` a
    bool, ``kept_modes`` an integer from 1 to the twin's number of modes (``None``: the modes
    of the twin's band) and ``margin_width`` a finite positive real scalar."""
    fn = "tuning_objective"
    if servo is not None:
        instance(servo, Servo, f"{fn}(servo=...)")
    feedforward = _checks.static_bool(feedforward, f"{fn}(feedforward=...)")
    if kept_modes is not None:  # the twin's own limit, named here (TwinOptions)
        kept_modes = _checks.static_int(kept_modes, f"{fn}(kept_modes=...)", 1,
                                        2 * TwinOptions().n_elements + 5)
    where = f"{fn}(margin_width=...)"
    margin_width = _checks.positive(_checks.real_scalar(margin_width, where), where)
    servo = reference_servo() if servo is None else servo
    return Objective(tuning_motion(), np.geomspace(5.0, 0.975 * 0.5 / float(servo.period), 400),
                     servo=servo,
                     twin=TwinOptions(kept_modes=kept_modes),
                     error_scale_m=1e-6 if feedforward else 1e-4,
                     margin_width=margin_width, margin_sharpness=10.0 / margin_width)


def _adam(steps: int, peak: float = 0.05) -> optax.GradientTransformation:
    """Adam with a cosine decay of the step from ``peak`` to ``peak``/10 over ``steps``."""
    return optax.adam(optax.cosine_decay_schedule(peak, max(steps, 1), alpha=0.1))


@dataclass
class Synthesis:
    """Result of :func:`synthesise`.

    Attributes:
        controllers: the controllers of Fig. 18 by name (:data:`CONTROLLERS`).
        schedule_bp, schedule_e2e: the scheduled loops (backpropagation, end to end).
        local: the full local designs at 115 mm and the six design positions.
        simplex: the simplex searches at 115 mm (``"mcm"``, ``"pid"``) the gradient starts from.
        coarse: the gradient stages with wide margin penalties that the sharp ones continue
            (``"mcm"``, ``"pid"`` at 115 mm; ``"pid_robust"``).
        shared: the six MCMs with common gains.
        pid_115, pid_robust: the PID tunings.
        mcm_robust: the robust MCM's tuning (one design for every position).
        network_loss: the backpropagation loss per step.
        e2e: the end-to-end training record.
        bounds, design_positions_m: the filter bounds and the six design positions (m).
        parameterisation: θ ↔ double loop of the local designs.
        seconds: wall time of each stage (s), compilation included.
    """

    controllers: dict[str, AbstractController]
    schedule_bp: ScheduledLoop
    schedule_e2e: ScheduledLoop
    local: LocalTuning
    shared: LocalTuning
    pid_115: LocalTuning
    pid_robust: RobustTuning
    network_loss: np.ndarray
    e2e: Descent
    mcm_robust: RobustTuning
    bounds: MCMBounds
    design_positions_m: np.ndarray
    parameterisation: DoubleLoopParameterisation
    seconds: dict[str, float] = field(default_factory=dict)
    simplex: dict[str, LocalTuning] = field(default_factory=dict)
    coarse: dict = field(default_factory=dict)

    def local_table(self) -> dict[str, list]:
        """The local designs (common gains) per design position, physical units."""
        par = self.parameterisation
        rows = {k: [] for k in ("position_mm", "kp", "kv", "ki", "k_ffv", "k_ffa", "peak_K",
                                "peak_freq_hz", "peak_xi", "peak_phi_deg", "notch_freq_hz",
                                "notch_zeta_n", "notch_zeta_d", "objective")}
        for y, th, j in zip(self.shared.positions_m, self.shared.best_theta,
                            self.shared.terms.total):
            c = par.to_controller(th)
            pk, nt = c.mcm.peak, c.mcm.notch
            vals = [float(y) * 1e3, c.kp, c.kv, c.ki, c.k_ffv, c.k_ffa, pk.K[0],
                    pk.omega[0] / (2 * math.pi), pk.xi[0], math.degrees(float(pk.phi[0])),
                    nt.omega[0] / (2 * math.pi), nt.zeta_n[0], nt.zeta_d[0], j]
            for k, v in zip(rows, vals):
                rows[k].append(float(v))
        return rows


def _join(a: LocalTuning, b: LocalTuning) -> LocalTuning:
    """Two local tunings of the same parameterisation and steps as one, a's positions first."""
    cat = lambda x, y: jnp.concatenate([x, y])  # noqa: E731
    return LocalTuning(cat(a.positions_m, b.positions_m), cat(a.theta, b.theta),
                       cat(a.best_theta, b.best_theta),
                       jnp.concatenate([a.history, b.history], axis=1),
                       jax.tree_util.tree_map(cat, a.terms, b.terms), a.seconds + b.seconds,
                       None if a.evaluations is None or b.evaluations is None
                       else jnp.concatenate([a.evaluations, b.evaluations], axis=1))


def _say(progress, text):
    if progress:
        _progress.say(text)


def _count(name, value, least):
    _checks.static_int(value, f"synthesise({name}=...)", least)


def synthesise(
    drive: BallScrewDrive | None = None,
    *,
    servo: Servo | None = None,
    local_steps: int = 300,
    refine_steps: int = 100,
    shared_steps: int = 100,
    pid_steps: int = 300,
    network_steps: int = 4000,
    e2e_steps: int = 60,
    e2e_positions: int = 13,
    robust_steps: int = 120,
    simplex_evaluations: int = 3000,
    train_gains: bool = True,
    feedforward: bool = False,
    margin_width: float = 0.01,
    progress: bool = True,
) -> Synthesis:
    """Run the synthesis of the module docstring on ``drive`` (default
    :func:`fdjax.reference_drive`) and return every design and training record.

    ``feedforward=False`` (default) compares feedback designs, as Fig. 18 does: no controller
    has feed-forward, so the tracking error is that of the loop, which the MCM improves by
    raising the loop gains.  With feed-forward (``True``) the error on this drive is set by the
    axial compliance the rigid feed-forward leaves uncompensated, about the same for every
    loop.  At 115 mm, for the MCM and for the PID, ``simplex_evaluations`` evaluations of the
    simplex search (:func:`tune_simplex`) and ``local_steps`` (``pid_steps``) Adam steps with a
    cosine decay (:func:`tune_local`) run on the objective with wide margin penalties
    (:func:`tuning_objective` with w = 0.05), then ``refine_steps`` L-BFGS steps on the
    objective with ``margin_width``, the one every later stage uses: ``refine_steps`` L-BFGS
    steps for the six local designs, the robust PID's sharp stage (after ``pid_steps`` Adam
    steps with wide penalties), ``shared_steps`` for the common gains; ``e2e_steps`` L-BFGS
    steps end to end, on ``e2e_positions`` positions evenly over the travel (every 50 mm by
    default, most of them between the six design positions); ``robust_steps`` L-BFGS steps for
    the robust MCM; ``network_steps`` Adam steps fit the network to the six designs
    (:func:`fit_network`, backpropagation), and ``train_gains`` (default True) lets the
    end-to-end stage train the common feedback gains with the network.  ``servo`` defaults to
    :func:`reference_servo`; ``progress`` prints each stage's progress to stderr.  Between
    stages the compiled programs are released when the process holds many memory maps (each
    program maps its machine code; a process may hold 65530)."""
    drive = reference_drive() if drive is None else drive
    instance(drive, BallScrewDrive, "synthesise(drive=...)")
    servo = reference_servo() if servo is None else servo
    instance(servo, Servo, "synthesise(servo=...)")
    lo, hi = drive.travel_m
    if not (lo <= DESIGN_POSITIONS_M[0] and DESIGN_POSITIONS_M[-1] <= hi):
        raise ValueError(
            f"`synthesise(drive=...)` must have a travel that holds the paper's design positions "
            f"{DESIGN_POSITIONS_M[0]:g}–{DESIGN_POSITIONS_M[-1]:g} m and {FIXED_POSITION_M:g} m "
            f"(Fig. 18), got [{lo:.6g}, {hi:.6g}] m; for other positions run the tuners "
            f"(tune_local, tune_shared_gains, fit_network, train_schedule) directly")
    seconds = {}
    _checks.static_positive(margin_width, "synthesise(margin_width=...)")
    # every count before the first stage, not when its stage comes minutes later
    for name, value, least in (
            ("local_steps", local_steps, 1), ("refine_steps", refine_steps, 1),
            ("shared_steps", shared_steps, 1), ("pid_steps", pid_steps, 1),
            ("network_steps", network_steps, 1), ("e2e_steps", e2e_steps, 1),
            ("e2e_positions", e2e_positions, 2), ("robust_steps", robust_steps, 1)):
        _count(name, value, least)
    obj = tuning_objective(servo, feedforward=feedforward, margin_width=margin_width)
    # a continuation in the penalties' width: the wide ones find and descend a basin from
    # afar, the sharp ones take the design up to its requirements
    wide = tuning_objective(servo, feedforward=feedforward, margin_width=WIDE_MARGIN_WIDTH)
    bounds = MCMBounds.for_servo(servo)
    ref = reference_controller(drive, servo)
    par = DoubleLoopParameterisation(bounds, ref, feedforward=feedforward)
    # more evaluations than the MCM's simplex has vertices
    _count("simplex_evaluations", simplex_evaluations, len(par.names) + 2)
    start = eqx.tree_at(lambda c: c.log_kv, ref, ref.log_kv + math.log(0.5))
    design = np.asarray(DESIGN_POSITIONS_M)

    t0 = time.perf_counter()
    _say(progress, f"MCM at {FIXED_POSITION_M * 1e3:.0f} mm: simplex search, then gradient")
    search, coarse, at_115 = _at_115(par, wide, obj, drive, start, simplex_evaluations,
                                     local_steps, refine_steps, progress)
    release()
    # the six local designs start from the design at 115 mm, as a servo engineer would
    _say(progress, f"local designs at {', '.join(f'{y * 1e3:.0f}' for y in design)} mm")
    six = tune_local(par, obj, drive, design, at_115.best_theta[0], steps=refine_steps,
                     optimiser=default_optimiser("lbfgs"), chunk=10, progress=progress)
    local = _join(at_115, six)
    seconds["local"] = time.perf_counter() - t0

    release()  # compiled programs of the stage before: memory maps
    t0 = time.perf_counter()
    _say(progress, "six MCMs with common gains")
    # common gains and one MCM per position, from the design at 115 mm everywhere (stable
    # with the margins over the travel on the reference drive), so that the schedule starts
    # where the fixed MCM is and descends from there
    shared = tune_shared_gains(par, obj, drive, design, at_115.best_theta[0],
                               steps=shared_steps, optimiser=default_optimiser("lbfgs"), chunk=10,
                               progress=progress)
    seconds["shared"] = time.perf_counter() - t0

    release()  # compiled programs of the stage before: memory maps
    t0 = time.perf_counter()
    k_ffv, k_ffa = rigid_feedforward(drive, servo) if feedforward else (1.0, 1.0)
    pid0 = reference_pid(k_ffv=k_ffv, k_ffa=k_ffa)
    ppar = PIDParameterisation(pid0, servo=servo, feedforward=feedforward)
    _say(progress, "PID at 115 mm: simplex search, then gradient")
    pid_search, pid_coarse, pid_115 = _at_115(ppar, wide, obj, drive, pid0,
                                              simplex_evaluations, pid_steps, refine_steps,
                                              progress)
    release()
    _say(progress, "robust PID over 13 positions, from the reference PID and from the PID "
                   "tuned at 115 mm")
    robust_y = robust_positions(drive)
    robust = [tune_robust(ppar, wide, drive, robust_y, s0, steps=pid_steps,
                          optimiser=_adam(pid_steps), progress=progress)
              for s0 in (ppar.from_controller(pid0), pid_coarse.best_theta[0])]
    robust_coarse = min(robust, key=lambda r: float(jnp.min(r.history)))
    _say(progress, "robust PID: sharp margin penalties")
    pid_robust = tune_robust(ppar, obj, drive, robust_y, robust_coarse.best_theta,
                             steps=refine_steps, optimiser=default_optimiser("lbfgs"), chunk=10,
                             progress=progress)
    seconds["pid"] = time.perf_counter() - t0

    release()  # compiled programs of the stage before: memory maps
    t0 = time.perf_counter()
    loop = par.to_controller(shared.best_theta[0])
    targets = shared.best_theta[:, 5:]
    net0 = ATANetwork(drive.travel_m, width=8, key=jax.random.PRNGKey(0))
    net, loss = fit_network(net0, design, targets, steps=network_steps)
    schedule_bp = ScheduledLoop(loop, net, bounds)
    seconds["network"] = time.perf_counter() - t0
    _say(progress, f"ATA network fitted by backpropagation: loss {float(loss[-1]):.3g}")

    release()  # compiled programs of the stage before: memory maps
    t0 = time.perf_counter()
    _say(progress, "ATA network trained end to end")
    # a fixed grid over the travel (every 50 mm by default: most between the design points)
    # makes the objective deterministic, for L-BFGS
    e2e_y = np.linspace(*drive.travel_m, e2e_positions)
    schedule_e2e, e2e = train_schedule(schedule_bp, obj, drive, steps=e2e_steps,
                                       positions_m=e2e_y, train_gains=train_gains,
                                       train_feedforward=feedforward,
                                       optimiser=default_optimiser("lbfgs"), chunk=10,
                                       progress=progress)
    seconds["end_to_end"] = time.perf_counter() - t0

    release()  # compiled programs of the stage before: memory maps
    t0 = time.perf_counter()
    _say(progress, "robust MCM over 13 positions, from the end-to-end schedule at the screw end")
    mcm_robust = robust_mcm(par, obj, drive, schedule_e2e, steps=robust_steps,
                            progress=progress)
    seconds["mcm_robust"] = time.perf_counter() - t0

    controllers = {
        "pid_115": ppar.to_controller(pid_115.best_theta[0]),
        "pid_robust": ppar.to_controller(pid_robust.best_theta),
        "mcm_fixed": par.to_controller(local.best_theta[0]),
        "mcm_robust": par.to_controller(mcm_robust.best_theta),
        "mcm_interp": InterpolatedLoop(loop, design, targets, bounds),
        "mcm_ata": schedule_bp,
        "mcm_ata_e2e": schedule_e2e,
    }
    return Synthesis(controllers, schedule_bp, schedule_e2e, local, shared, pid_115,
                     pid_robust, np.asarray(loss), e2e, mcm_robust, bounds, design, par,
                     seconds,
                     {"mcm": search, "pid": pid_search},
                     {"mcm": coarse, "pid": pid_coarse, "pid_robust": robust_coarse})


def _at_115(par, wide, sharp, drive, start, evaluations, steps, refine, progress):
    """The design at 115 mm: simplex and Adam on the wide-penalty objective, then L-BFGS on
    the sharp one."""
    y = [FIXED_POSITION_M]
    search = tune_simplex(par, wide, drive, y, start, evaluations=evaluations,
                          progress=progress)
    coarse = tune_local(par, wide, drive, y, search.best_theta[0], steps=steps,
                        optimiser=_adam(steps, 0.02), progress=progress)
    _say(progress, "sharp margin penalties")
    fine = tune_local(par, sharp, drive, y, coarse.best_theta[0], steps=refine,
                      optimiser=default_optimiser("lbfgs"), chunk=10, progress=progress)
    return search, coarse, fine


def robust_positions(drive: BallScrewDrive) -> np.ndarray:
    """The 13 positions, evenly over the drive's travel, at which the robust designs (the PID
    and the MCM) are tuned."""
    return np.linspace(*drive.travel_m, 13)


def robust_mcm(par: DoubleLoopParameterisation, objective: Objective, drive: BallScrewDrive,
               schedule: ScheduledLoop, *, steps: int = 120,
               progress: bool = False) -> RobustTuning:
    """The robust MCM of Fig. 18: one double loop with its MCM (gains and filters) for every
    position, by ``steps`` L-BFGS steps of :func:`tune_robust` over 13 positions on the
    travel, from ``schedule``'s controller at the screw end (where the margins bind)."""
    y = robust_positions(drive)
    start = par.from_controller(schedule.controller(drive.travel_m[1]))
    return tune_robust(par, objective, drive, y, start, steps=steps,
                       optimiser=default_optimiser("lbfgs"), chunk=10, progress=progress)


def _program_key(controllers: AbstractController):
    """What decides the compiled program of stacked controllers: their kind (the tree) and their
    arrays' shapes and types (a second peak filter is another program), not their values."""
    leaves, tree = jax.tree_util.tree_flatten(eqx.filter(controllers, eqx.is_array))
    return tree, tuple((x.shape, x.dtype) for x in leaves)


def evaluate(
    controllers: dict[str, AbstractController],
    drive: BallScrewDrive,
    positions_m: Float[ArrayLike, " n"],
    *,
    servo: Servo | None = None,
    motion: Trajectory | None = None,
    progress: bool = True,
) -> dict[str, dict]:
    """RMS tracking error of ``motion`` (default :func:`tuning_motion`) at the scale on the full
    twin, stability and the exact sampled margins of each controller at ``positions_m``
    (:func:`certify`'s checks).  Per controller: ``rms_error_um`` (None where unstable),
    ``stable``, ``gain_margin_db``, ``phase_margin_deg``, ``modulus_margin`` (lists over the
    positions) and ``certificate``.  Controllers of the same kind share one compiled program.
    ``servo`` defaults to :func:`reference_servo`; ``progress`` prints a line per controller to
    stderr."""
    if not isinstance(controllers, dict) or not controllers:
        raise TypeError("`evaluate(controllers=...)` must be a non-empty dict of name → "
                        f"controller, got {type(controllers).__name__}")
    for name, c in controllers.items():
        instance(c, AbstractController, f"evaluate(controllers[{name!r}]=...)",
                 "an fdjax controller")
    instance(drive, BallScrewDrive, "evaluate(drive=...)")
    servo = reference_servo() if servo is None else servo
    instance(servo, Servo, "evaluate(servo=...)")
    motion = tuning_motion() if motion is None else motion
    instance(motion, Trajectory, "evaluate(motion=...)")
    y = np.atleast_1d(np.asarray(drive._check_travel(positions_m, "evaluate", "positions_m")))
    if y.ndim != 1:
        raise ValueError(f"`evaluate(positions_m=...)` must be a position or a 1-D array of "
                         f"positions, got shape {y.shape}")
    for name, c in controllers.items():
        where = f"evaluate(controllers[{name!r}]=...)"
        check_sampled_by(c.highest_frequency_hz, servo, where)
        c.check_position(y, f"evaluate(positions_m=...) for {where}")
    release()
    twin = TwinOptions().resolve(drive, "evaluate")
    f = default_grid(servo)
    groups: dict = {}
    for name, c in controllers.items():
        fixed = c.fixed_at(y)
        check_grid_resolves(fixed, f, f"evaluate(controllers[{name!r}]=...)",
                            "a filter this sharp needs fdjax.certify with a grid of points "
                            "closer than {} Hz around it")
        groups.setdefault(_program_key(fixed), []).append((name, fixed))
    out = {}
    for members in groups.values():
        stacked = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs),
                                         *[m[1] for m in members])
        ys = np.tile(y, len(members))
        checks = point_checks(stacked, drive, ys, servo=servo, freq_hz=f, twin=twin,
                              motion=motion)
        for k, (name, _) in enumerate(members):
            part = {key: np.asarray(v)[k * y.size:(k + 1) * y.size]
                    for key, v in checks.items()}
            cert = certificate(y, part)
            rms = [float(r) * 1e6 if ok else None for r, ok in zip(part["rms"], cert.stable)]
            out[name] = {"rms_error_um": rms, "stable": cert.stable.tolist(),
                         "gain_margin_db": cert.gain_margin_db.tolist(),
                         "phase_margin_deg": cert.phase_margin_deg.tolist(),
                         "modulus_margin": cert.modulus_margin.tolist(), "certificate": cert}
    for name in controllers:
        _say(progress, f"{name}: {out[name]['certificate'].message}")
    return {name: out[name] for name in controllers}
