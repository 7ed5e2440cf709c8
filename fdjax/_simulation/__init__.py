"""Loop models and runs: the sampled loop, the continuous loop, the diffrax solution, the
moving table, and :func:`simulate`."""

from ._methods import (
    AbstractLoopModel as AbstractLoopModel,
    Continuous as Continuous,
    ExponentialFOH as ExponentialFOH,
    PadeODE as PadeODE,
    SampledData as SampledData,
)
from ._simulate import (
    SIMULATION_OUTPUTS as SIMULATION_OUTPUTS,
    Simulation as Simulation,
    simulate as simulate,
)
