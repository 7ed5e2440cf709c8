r"""Gradient synthesis of the controllers (paper Sec. 4.2): the parameterisation that gradient
steps cannot break.

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
