r"""Gradient synthesis of the controllers (paper Sec. 4.2): the parameterisation that gradient
steps cannot break.

* ``_penalties``: smooth robustness penalties of an open loop (modulus, gain and phase
  margins as distances from forbidden sets of the Nyquist plane).
* ``_objective``: :class:`Objective`, RMS tracking error of the sampled loop plus the
  penalties, one function of the controller and the position.
* ``_schedule``: :class:`ATANetwork` (position → the seven normalised filter parameters, and
  optionally three log gain factors), :class:`ScheduledLoop` (the double loop with the
  network's MCM and gains), save and load.
* ``_local``: :func:`tune_local`, one design per table position in one ``vmap``-ed optax run;
  :func:`tune_robust` (one design for all positions), :func:`tune_shared_gains` (one gain set,
  one MCM per position); :func:`descend`, the optax loop they share.
* ``_newton``: :func:`tune_newton`, trust-region Newton steps with the exact Hessian per
  position in one ``vmap`` (:func:`trust_region_step`, the exact subproblem), and
  :func:`shape_loops`, the same steps on the part of the objective that needs no run (the
  margin term and the poles' barrier): a start found without simulation.
* ``_simplex``: :func:`tune_simplex`, the adaptive Nelder–Mead simplex per position in one
  ``vmap`` (a derivative-free search for the basin that the gradient then refines).
* ``_end_to_end``: :func:`train_schedule`, the network trained against the objective itself.
* ``_designs``: :func:`save_designs` / :func:`load_designs`, named controllers bit for bit.
* ``_synthesis``: :func:`synthesise`, the whole chain of Fig. 18, and :func:`evaluate`.
* ``_certify``: :func:`certify`, stability and exact sampled margins every 1 mm.
* ``_parameterisation``: :class:`MCMBounds` (the seven normalised MCM parameters the scheduling
  network outputs) and :class:`DoubleLoopParameterisation` (gains and filters of a
  :class:`fdjax.DoubleLoop` as one vector of order-one reals).
"""

from ._certify import (
    Certificate as Certificate,
    certify as certify,
)
from ._designs import load_designs as load_designs, save_designs as save_designs
from ._end_to_end import train_schedule as train_schedule
from ._local import (
    Descent as Descent,
    LocalTuning as LocalTuning,
    RobustTuning as RobustTuning,
    descend as descend,
    smooth_max as smooth_max,
    tune_local as tune_local,
    tune_robust as tune_robust,
    tune_shared_gains as tune_shared_gains,
)
from ._newton import (
    LoopShaping as LoopShaping,
    shape_loops as shape_loops,
    trust_region_step as trust_region_step,
    tune_newton as tune_newton,
)
from ._objective import (
    Objective as Objective,
    ObjectiveTerms as ObjectiveTerms,
)
from ._parameterisation import (
    GAIN_PARAMETERS as GAIN_PARAMETERS,
    MCM_PARAMETERS as MCM_PARAMETERS,
    PID_PARAMETERS as PID_PARAMETERS,
    AbstractParameterisation as AbstractParameterisation,
    DoubleLoopParameterisation as DoubleLoopParameterisation,
    MCMBounds as MCMBounds,
    PIDParameterisation as PIDParameterisation,
)
from ._penalties import (
    gain_distance as gain_distance,
    margin_penalty as margin_penalty,
    modulus_distance as modulus_distance,
    phase_distance as phase_distance,
    soft_min as soft_min,
)
from ._schedule import (
    ATANetwork as ATANetwork,
    InterpolatedLoop as InterpolatedLoop,
    ScheduledLoop as ScheduledLoop,
    fit_network as fit_network,
    load_schedule as load_schedule,
    save_schedule as save_schedule,
)
from ._simplex import tune_simplex as tune_simplex
from ._synthesis import (
    CONTROLLERS as CONTROLLERS,
    Synthesis as Synthesis,
    evaluate as evaluate,
    synthesise as synthesise,
    tuning_motion as tuning_motion,
    tuning_objective as tuning_objective,
)
