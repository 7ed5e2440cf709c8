"""The ball-screw feed drive, in pipeline order (each file imports only the ones above it):

* ``_rods`` — exact dynamic stiffness of uniform rods and shafts (wave solution).
* ``_substructures`` — the screw, the subsystems R, A, S (with an optional table) and the nut
  joint (paper Figs. 8–9).
* ``_model`` — :class:`BallScrewDrive`: the substructures coupled at the nut, H_M (Eq. 2).
* ``_reference`` — :func:`reference_drive`: the built-in drive's data, each value with its
  unit, plausible range and reason.
* ``_twin`` — the finite-element time-domain twin and its truncated modal state space.
* ``_modes`` — exact modes of the model: frequency, damping, resonant phase, tracking.
* ``_updating`` — model updating: fitting bounded parameters to measured modal data.
"""

from ._model import (
    INPUTS as INPUTS,
    OUTPUTS as OUTPUTS,
    BallScrewDrive as BallScrewDrive,
)
from ._modes import (
    DriveModes as DriveModes,
    drive_modes as drive_modes,
    track_drive_modes as track_drive_modes,
)
from ._reference import (
    REFERENCE_PARAMETERS as REFERENCE_PARAMETERS,
    reference_drive as reference_drive,
    table1_drive as table1_drive,
)
from ._rods import Rod as Rod, Support as Support, rod_receptance as rod_receptance
from ._substructures import (
    Axial as Axial,
    Carriage as Carriage,
    NutJoint as NutJoint,
    Rotary as Rotary,
    Screw as Screw,
    Table as Table,
)
from ._twin import (
    DEFAULT_BAND_HZ as DEFAULT_BAND_HZ,
    DEFAULT_ELEMENTS as DEFAULT_ELEMENTS,
    VELOCITY_OUTPUTS as VELOCITY_OUTPUTS,
    FEMatrices as FEMatrices,
    StateSpace as StateSpace,
    TwinOptions as TwinOptions,
    count_modes as count_modes,
    fe_matrices as fe_matrices,
    state_space as state_space,
)
from ._updating import (
    TABLE_1 as TABLE_1,
    TABLE_1_POSITION_M as TABLE_1_POSITION_M,
    ModalData as ModalData,
    ModelUpdate as ModelUpdate,
    update_model as update_model,
)
