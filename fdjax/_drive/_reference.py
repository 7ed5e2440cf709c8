"""The built-in reference drive: a heavy machine-tool axis whose sampled speed and position
loops are limited by its modes, as the paper's drive is (``examples/servo_drive_study.py``)."""

from __future__ import annotations

from ._model import BallScrewDrive
from ._substructures import Axial, Carriage, NutJoint, Rotary, Screw

__all__ = ["reference_drive", "REFERENCE_PARAMETERS"]

REFERENCE_PARAMETERS: tuple[tuple[str, float, str, tuple[float, float], str], ...] = (
    ("screw.length", 0.85, "m", (0.75, 1.0),
     "bearing span: 600 mm travel, a 150 mm nut and the ends"),
    ("screw.diameter", 0.0575, "m", (0.050, 0.060),
     "effective diameter of a 63 mm screw (root ≈ 57 mm)"),
    ("screw.bore_diameter", 0.032, "m", (0.0, 0.040), "bored (coolant) screw, 12 mm wall"),
    ("screw.lead", 0.010, "m", (0.005, 0.020), "catalogue 63×10 screw: i_sc = 1.59 mm/rad"),
    ("screw.retardation", 1.0e-6, "s", (1e-8, 1e-5), "steel: ζ = βω/2 ≈ 0.3 % at 1 kHz"),
    ("rotary.motor_inertia", 3.0e-3, "kg·m²", (1.5e-3, 1.5e-2),
     "rotor of a ~20 N·m servo motor with its hub"),
    ("rotary.coupling_stiffness", 2.0e6, "N·m/rad", (2e5, 3e6),
     "lamina (disc) coupling for 60 mm shafts, stiff end of the range"),
    ("rotary.coupling_damping", 0.15, "N·m·s/rad", (0.01, 1.0), "steel discs: ζ below 1 %"),
    ("rotary.motor_damping", 0.05, "N·m·s/rad", (1e-3, 0.05),
     "motor bearings and seal, linearised (upper end: 5 N·m at 100 rad/s)"),
    ("rotary.drive_end_inertia", 7.7e-4, "kg·m²", (3e-4, 3e-3),
     "screw-side hub, bearing rings, lock nut"),
    ("rotary.drive_end_damping", 1.0e-3, "N·m·s/rad", (1e-3, 1.0),
     "preloaded bearing friction (lower end: the joints damp the modes)"),
    ("rotary.free_end_inertia", 3.0e-4, "kg·m²", (5e-5, 1e-3),
     "free-end bearing rings and lock nut"),
    ("rotary.free_end_damping", 5.0e-3, "N·m·s/rad", (1e-3, 1.0), "free-end bearing friction"),
    ("axial.drive_end_stiffness", 2.0e9, "N/m", (5e8, 3e9),
     "angular-contact thrust set of a 63 mm screw with its housing"),
    ("axial.drive_end_damping", 490.0, "N·s/m", (1e2, 5e4), "bearing-housing damping"),
    ("axial.free_end_stiffness", 0.0, "N/m", (0.0, 0.0),
     "fixed–supported: the free-end bearing takes no axial load"),
    ("axial.drive_end_mass", 5.0, "kg", (1.0, 10.0),
     "bearing inner rings, spacer, lock nut, hub"),
    ("carriage.mass", 1000.0, "kg", (250.0, 1500.0),
     "saddle carrying the X table and the workpiece"),
    ("carriage.pitch_inertia", 50.0, "kg·m²", (25.0, 80.0),
     "m(a² + h²)/12 of a 0.75 m × 0.25 m saddle ≈ 52"),
    ("carriage.pitch_stiffness", 5.5e6, "N·m/rad", (5e6, 7e8),
     "blocks with saddle and column bending in series; soft end: places the 47 Hz mode"),
    ("carriage.axial_damping", 9.1e4, "N·s/m", (1e2, 1e5),
     "guideways with damping carriages, pre-sliding; upper end: damps the low modes"),
    ("carriage.pitch_damping", 2800.0, "N·m·s/rad", (1e2, 1e5), "ζ ≈ 10 % guideway joints"),
    ("carriage.nut_height", -0.12, "m", (-0.20, -0.02), "screw axis below the pitch centre"),
    ("carriage.scale_height", -0.20, "m", (-0.25, -0.02), "linear scale at the saddle base"),
    ("carriage.tool_height", 0.30, "m", (0.0, 0.50), "tool point above the pitch centre"),
    ("nut.stiffness", 4.0e9, "N/m", (1e9, 4e9),
     "preloaded double nut of a 63 mm screw; catalogue top: the screw dominates the axial "
     "compliance, so it softens toward the screw end"),
    ("nut.damping", 5100.0, "N·s/m", (1e2, 3e4), "nut joint damping"),
    ("nut_offset", 0.08, "m", (0.05, 0.15), "nut 80 mm from the thrust bearing at Y_table = 0"),
)
"""Every parameter of :func:`reference_drive`: (attribute path, value in SI units, unit,
plausible (low, high), reason)."""


def reference_drive() -> BallScrewDrive:
    r"""The built-in reference drive: a heavy Y axis, 600 mm travel (Y_table 0.1–0.7 m).

    A 1000 kg saddle (carrying the X table and workpiece) on a hollow 63×10 ball screw held
    axially at the motor end only (fixed–supported: the axial stiffness at the nut falls by half
    toward the screw end), driven by a ~20 N·m servo motor through a stiff lamina coupling.
    Every value, its unit, plausible range and reason is in :data:`REFERENCE_PARAMETERS`.

    What the servo sees (sampled loop at 8 kHz, two periods of delay; ``examples/
    servo_drive_study.py``): the saddle's axial mode (174 Hz at 115 mm, out of phase in h21,
    177 → 118 Hz over the travel) limits the position loop and is the peak filter's target; the
    screw's torsional mode at 1260 Hz (ζ 0.004), which the motor encoder sees, limits the speed
    loop and is the notch's.  Modes of h21 at 115 mm (:func:`fdjax.drive_modes`): 47.0 Hz /
    ζ 0.101 / −107° (pitch), 174 Hz / 0.032 / −273° (axial), 1260 Hz / 0.004 / −87° (torsion),
    1750 Hz / 0.006 / −269° (screw axial).  The paper's Table 1 has three modes below 1 kHz; this
    drive has two (README, "The reference drive").
    """
    p = {path: value for path, value, *_ in REFERENCE_PARAMETERS}

    def part(prefix):
        return {k.split(".", 1)[1]: v for k, v in p.items() if k.startswith(prefix + ".")}

    return BallScrewDrive(
        Screw(**part("screw")), Rotary(**part("rotary")), Axial(**part("axial")),
        Carriage(**part("carriage")), NutJoint(**part("nut")),
        nut_offset=p["nut_offset"], travel_m=(0.1, 0.7),
    )
