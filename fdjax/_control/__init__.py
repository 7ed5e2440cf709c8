"""Controllers and their realisations: the servo's hardware, the blocks a law is built from,
the controllers of paper Fig. 13, the interconnection with the plant, margin algorithms."""

from ._blocks import (
    DEFAULT_PADE_ORDER as DEFAULT_PADE_ORDER,
    PI as PI,
    PID as PID,
    AbstractBlock as AbstractBlock,
    DiscreteBlock as DiscreteBlock,
    FilterBlock as FilterBlock,
    pade as pade,
)
from ._controllers import (
    LAW_SIGNALS as LAW_SIGNALS,
    AbstractController as AbstractController,
    DoubleLoop as DoubleLoop,
    Law as Law,
    Path as Path,
    PIDLoop as PIDLoop,
    SampledLaw as SampledLaw,
)
from ._export import to_python_control as to_python_control
from ._interconnect import (
    CLOSED_LOOP_INPUTS as CLOSED_LOOP_INPUTS,
    CLOSED_LOOP_OUTPUTS as CLOSED_LOOP_OUTPUTS,
)
from ._margins import Margins as Margins
from ._servo import Servo as Servo
