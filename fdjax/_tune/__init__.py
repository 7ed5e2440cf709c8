r"""Gradient synthesis of the controllers (paper Sec. 4.2): the parameterisation that gradient
steps cannot break.

* ``_penalties``: smooth robustness penalties of an open loop (modulus, gain and phase
  margins as distances from forbidden sets of the Nyquist plane).
* ``_parameterisation``: :class:`MCMBounds` (the seven normalised MCM parameters the scheduling
  network outputs) and :class:`DoubleLoopParameterisation` (gains and filters of a
  :class:`fdjax.DoubleLoop` as one vector of order-one reals).
"""

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
