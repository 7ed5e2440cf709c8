r"""Gradient synthesis of the controllers (paper Sec. 4.2): the parameterisation that gradient
steps cannot break.

* ``_penalties``: smooth robustness penalties of an open loop (modulus, gain and phase
  margins as distances from forbidden sets of the Nyquist plane).
* ``_objective``: :class:`Objective`, RMS tracking error of the sampled loop plus the
  penalties, one function of the controller and the position.
* ``_schedule``: :class:`ATANetwork` (position → the seven normalised filter parameters),
  :class:`ScheduledLoop` (the double loop with the network's MCM), save and load.
* ``_local``: :func:`tune_local`, one design per table position in one ``vmap``-ed optax run.
* ``_parameterisation``: :class:`MCMBounds` (the seven normalised MCM parameters the scheduling
  network outputs) and :class:`DoubleLoopParameterisation` (gains and filters of a
  :class:`fdjax.DoubleLoop` as one vector of order-one reals).
"""

from ._local import (
    LocalTuning as LocalTuning,
    tune_local as tune_local,
)
from ._objective import (
    Objective as Objective,
    ObjectiveTerms as ObjectiveTerms,
)
from ._parameterisation import (
    GAIN_PARAMETERS as GAIN_PARAMETERS,
    MCM_PARAMETERS as MCM_PARAMETERS,
    DoubleLoopParameterisation as DoubleLoopParameterisation,
    MCMBounds as MCMBounds,
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
    ScheduledLoop as ScheduledLoop,
    fit_network as fit_network,
    load_schedule as load_schedule,
    save_schedule as save_schedule,
)
