"""fdjax: differentiable design of ball-screw feed-drive controllers in JAX.

Importing fdjax switches JAX to float64 (``jax_enable_x64``): receptances of a machine-tool
axis are ~1e-9 m/N and float32 loses them.  If JAX is not imported yet, fdjax sets
``JAX_ENABLE_X64`` (unless you set it) so that JAX starts in float64; if it is, fdjax switches
the flag.  Set it yourself before creating arrays if you import JAX first and create arrays
before importing fdjax.

The public names below are loaded on first use (the command line answers ``--help`` without
importing JAX); each is defined in the private module named next to it.
"""

from __future__ import annotations

import importlib
import os
import sys
from typing import TYPE_CHECKING

__version__ = "0.1.0"

if "jax" in sys.modules:
    sys.modules["jax"].config.update("jax_enable_x64", True)
else:
    os.environ.setdefault("JAX_ENABLE_X64", "1")
# XLA:CPU's concurrency-optimised scheduler has been seen to dead-lock (every thread asleep, on
# the first or a later call of a compiled program) on the loop programs here on small
# machines, and to compile them slowly.  XLA reads the flag when JAX starts its CPU backend
# (at the first array), so this holds also where JAX was imported first.
_flag = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
if "xla_cpu_enable_concurrency_optimized_scheduler" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

_EXPORTS = {
    "._analysis": (
        "check_stability",
        "closed_loop",
        "gain_headroom",
        "loop_margins",
        "LoopMargins",
        "open_loop",
        "OpenLoop",
        "Stability",
        "stability_margins",
    ),
    "._control": (
        "CLOSED_LOOP_INPUTS",
        "CLOSED_LOOP_OUTPUTS",
        "DEFAULT_PADE_ORDER",
        "LAW_SIGNALS",
        "PI",
        "PID",
        "AbstractBlock",
        "AbstractController",
        "DiscreteBlock",
        "DoubleLoop",
        "FilterBlock",
        "Law",
        "Margins",
        "pade",
        "Path",
        "PIDLoop",
        "SampledLaw",
        "Servo",
        "to_python_control",
    ),
    "._control._reference": (
        "reference_controller",
        "reference_mcm",
        "reference_pid",
        "reference_servo",
        "rigid_feedforward",
    ),
    "._coupling": (
        "couple",
        "joint_receptance",
    ),
    "._drive": (
        "DEFAULT_BAND_HZ",
        "DEFAULT_ELEMENTS",
        "INPUTS",
        "OUTPUTS",
        "TABLE_1",
        "TABLE_1_POSITION_M",
        "VELOCITY_OUTPUTS",
        "Axial",
        "BallScrewDrive",
        "Carriage",
        "count_modes",
        "drive_modes",
        "DriveModes",
        "fe_matrices",
        "FEMatrices",
        "ModalData",
        "ModelUpdate",
        "NutJoint",
        "reference_drive",
        "REFERENCE_PARAMETERS",
        "table1_drive",
        "Rod",
        "rod_receptance",
        "Rotary",
        "Screw",
        "state_space",
        "StateSpace",
        "Support",
        "Table",
        "track_drive_modes",
        "TwinOptions",
        "update_model",
    ),
    "._filters": (
        "MCM",
        "AbstractFilter",
        "DiscreteFilter",
        "NotchFilter",
        "PeakFilter",
    ),
    "._lti": (
        "LTI",
    ),
    "._lumped": (
        "chain_model",
        "LumpedModel",
        "three_mass",
    ),
    "._modal": (
        "identify_modes",
        "identify_modes_batched",
        "ModalFit",
        "stabilisation_diagram",
        "StabilisationDiagram",
        "track_modes",
    ),
    "._results": (
        "RESULTS",
    ),
    "._simulation": (
        "SIMULATION_OUTPUTS",
        "AbstractLoopModel",
        "Continuous",
        "ExponentialFOH",
        "PadeODE",
        "SampledData",
        "simulate",
        "Simulation",
    ),
    "._tune": (
        "ATANetwork",
        "DoubleLoopParameterisation",
        "fit_network",
        "load_schedule",
        "save_schedule",
        "ScheduledLoop",
        "Objective",
        "ObjectiveTerms",
        "margin_penalty",
        "GAIN_PARAMETERS",
        "MCM_PARAMETERS",
        "MCMBounds",
        "LocalTuning",
        "tune_local",
        "tune_simplex",
        "tune_newton",
        "trust_region_step",
        "shape_loops",
        "LoopShaping",
        "AbstractParameterisation",
        "PIDParameterisation",
        "PID_PARAMETERS",
        "InterpolatedLoop",
        "RobustTuning",
        "tune_robust",
        "tune_shared_gains",
        "smooth_max",
        "descend",
        "Descent",
        "train_schedule",
        "certify",
        "Certificate",
        "save_designs",
        "load_designs",
        "synthesise",
        "Synthesis",
        "evaluate",
        "CONTROLLERS",
        "tuning_motion",
        "tuning_objective",
    ),
    "._trajectory": (
        "concatenate",
        "jerk_limited",
        "reciprocating",
        "Trajectory",
    ),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    module = _WHERE.get(name)
    if name == "plots":  # the figures' submodule: `fdjax.plots` after a bare `import fdjax`
        return importlib.import_module(".plots", __name__)
    if module is None and name.startswith("_") and not name.startswith("__"):
        try:  # a private submodule, for introspection and tests
            import jax

            with jax.ensure_compile_time_eval():
                return importlib.import_module("." + name, __name__)
        except ModuleNotFoundError:
            pass
    if module is None:
        raise AttributeError(f"module 'fdjax' has no attribute {name!r}")
    import jax

    jax.config.update("jax_enable_x64", True)  # also when JAX was imported in between
    # the first use may come inside a user's jit trace: the module-level constants that the
    # import builds (default arguments such as Servo()) must be concrete arrays, not tracers
    # of that trace (which leak into the next one)
    with jax.ensure_compile_time_eval():
        value = getattr(importlib.import_module(module, __name__), name)
    _with_notes(value)
    globals()[name] = value
    return value


def _with_notes(value) -> None:
    """A public name whose docstring leans on its private module's docstring (the equations
    and conventions a module's names share) gets that text appended, so that ``help()`` on
    the public name shows it."""
    import re

    doc = getattr(value, "__doc__", None)
    mod = sys.modules.get(getattr(value, "__module__", None) or "")
    phrase = re.compile(r"(the\s+)?module\s+(docstring|docs)")  # across a line break too
    if not (callable(value) and doc and phrase.search(doc) and mod and mod.__doc__):
        return
    import inspect
    import textwrap

    notes = textwrap.indent(inspect.cleandoc(mod.__doc__), "    ")
    try:
        value.__doc__ = (phrase.sub(lambda m: "the notes below" if m.group(1) else
                                    "notes below", doc)
                         + f"\n\n    Notes (``{value.__module__}``):\n\n{notes}\n")
    except (AttributeError, TypeError):  # a docstring that cannot be set: leave it
        pass


def __dir__():
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:
    from ._analysis import (
        LoopMargins as LoopMargins,
        OpenLoop as OpenLoop,
        Stability as Stability,
        check_stability as check_stability,
        closed_loop as closed_loop,
        gain_headroom as gain_headroom,
        loop_margins as loop_margins,
        open_loop as open_loop,
        stability_margins as stability_margins,
    )
    from ._control import (
        CLOSED_LOOP_INPUTS as CLOSED_LOOP_INPUTS,
        CLOSED_LOOP_OUTPUTS as CLOSED_LOOP_OUTPUTS,
        DEFAULT_PADE_ORDER as DEFAULT_PADE_ORDER,
        LAW_SIGNALS as LAW_SIGNALS,
        PI as PI,
        PID as PID,
        AbstractBlock as AbstractBlock,
        AbstractController as AbstractController,
        DiscreteBlock as DiscreteBlock,
        DoubleLoop as DoubleLoop,
        FilterBlock as FilterBlock,
        Law as Law,
        Margins as Margins,
        Path as Path,
        PIDLoop as PIDLoop,
        SampledLaw as SampledLaw,
        Servo as Servo,
        pade as pade,
        to_python_control as to_python_control,
    )
    from ._control._reference import (
        reference_controller as reference_controller,
        reference_mcm as reference_mcm,
        reference_pid as reference_pid,
        reference_servo as reference_servo,
        rigid_feedforward as rigid_feedforward,
    )
    from ._coupling import (
        couple as couple,
        joint_receptance as joint_receptance,
    )
    from ._drive import (
        DEFAULT_BAND_HZ as DEFAULT_BAND_HZ,
        DEFAULT_ELEMENTS as DEFAULT_ELEMENTS,
        INPUTS as INPUTS,
        OUTPUTS as OUTPUTS,
        REFERENCE_PARAMETERS as REFERENCE_PARAMETERS,
        TABLE_1 as TABLE_1,
        TABLE_1_POSITION_M as TABLE_1_POSITION_M,
        VELOCITY_OUTPUTS as VELOCITY_OUTPUTS,
        Axial as Axial,
        BallScrewDrive as BallScrewDrive,
        Carriage as Carriage,
        DriveModes as DriveModes,
        FEMatrices as FEMatrices,
        ModalData as ModalData,
        ModelUpdate as ModelUpdate,
        NutJoint as NutJoint,
        Rod as Rod,
        Rotary as Rotary,
        Screw as Screw,
        StateSpace as StateSpace,
        Support as Support,
        Table as Table,
        TwinOptions as TwinOptions,
        count_modes as count_modes,
        drive_modes as drive_modes,
        fe_matrices as fe_matrices,
        reference_drive as reference_drive,
        rod_receptance as rod_receptance,
        state_space as state_space,
        table1_drive as table1_drive,
        track_drive_modes as track_drive_modes,
        update_model as update_model,
    )
    from ._filters import (
        MCM as MCM,
        AbstractFilter as AbstractFilter,
        DiscreteFilter as DiscreteFilter,
        NotchFilter as NotchFilter,
        PeakFilter as PeakFilter,
    )
    from ._lti import (
        LTI as LTI,
    )
    from ._lumped import (
        LumpedModel as LumpedModel,
        chain_model as chain_model,
        three_mass as three_mass,
    )
    from ._modal import (
        ModalFit as ModalFit,
        StabilisationDiagram as StabilisationDiagram,
        identify_modes as identify_modes,
        identify_modes_batched as identify_modes_batched,
        stabilisation_diagram as stabilisation_diagram,
        track_modes as track_modes,
    )
    from ._results import (
        RESULTS as RESULTS,
    )
    from ._simulation import (
        SIMULATION_OUTPUTS as SIMULATION_OUTPUTS,
        AbstractLoopModel as AbstractLoopModel,
        Continuous as Continuous,
        ExponentialFOH as ExponentialFOH,
        PadeODE as PadeODE,
        SampledData as SampledData,
        Simulation as Simulation,
        simulate as simulate,
    )
    from ._trajectory import (
        Trajectory as Trajectory,
        concatenate as concatenate,
        jerk_limited as jerk_limited,
        reciprocating as reciprocating,
    )
    from ._tune import (
        GAIN_PARAMETERS as GAIN_PARAMETERS,
        MCM_PARAMETERS as MCM_PARAMETERS,
        PID_PARAMETERS as PID_PARAMETERS,
        AbstractParameterisation as AbstractParameterisation,
        ATANetwork as ATANetwork,
        Certificate as Certificate,
        Descent as Descent,
        DoubleLoopParameterisation as DoubleLoopParameterisation,
        InterpolatedLoop as InterpolatedLoop,
        LocalTuning as LocalTuning,
        LoopShaping as LoopShaping,
        MCMBounds as MCMBounds,
        Objective as Objective,
        ObjectiveTerms as ObjectiveTerms,
        PIDParameterisation as PIDParameterisation,
        RobustTuning as RobustTuning,
        ScheduledLoop as ScheduledLoop,
        Synthesis as Synthesis,
        certify as certify,
        descend as descend,
        evaluate as evaluate,
        fit_network as fit_network,
        load_designs as load_designs,
        load_schedule as load_schedule,
        margin_penalty as margin_penalty,
        save_designs as save_designs,
        save_schedule as save_schedule,
        shape_loops as shape_loops,
        smooth_max as smooth_max,
        synthesise as synthesise,
        train_schedule as train_schedule,
        trust_region_step as trust_region_step,
        tune_local as tune_local,
        tune_newton as tune_newton,
        tune_robust as tune_robust,
        tune_shared_gains as tune_shared_gains,
        tune_simplex as tune_simplex,
    )
