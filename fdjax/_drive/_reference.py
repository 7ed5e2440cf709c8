"""The built-in reference drive: a heavy machine-tool axis whose sampled speed and position
loops are limited by its modes, as the paper's drive is (``examples/servo_drive_study.py``)."""

from __future__ import annotations

from ._model import BallScrewDrive
from ._substructures import Axial, Carriage, NutJoint, Rotary, Screw

__all__ = ["reference_drive", "table1_drive", "REFERENCE_PARAMETERS"]

REFERENCE_PARAMETERS: tuple[tuple[str, float, str, tuple[float, float], str], ...] = (
    ("screw.length", 0.85, "m", (0.75, 1.0),
     "bearing span: 600 mm travel, a 150 mm nut and the ends"),
    ("screw.diameter", 0.0575, "m", (0.050, 0.060),
     "effective diameter of a 63 mm screw (root ≈ 57 mm)"),
    ("screw.bore_diameter", 0.032, "m", (0.0, 0.040), "bored (coolant) screw, 12 mm wall"),
    ("screw.lead", 0.010, "m", (0.005, 0.020), "catalogue 63×10 screw: i_sc = 1.59 mm/rad"),
    ("screw.youngs_modulus", 2.06e11, "Pa", (2.0e11, 2.12e11), "bearing steel (handbook)"),
    ("screw.shear_modulus", 7.93e10, "Pa", (7.7e10, 8.1e10), "bearing steel (handbook)"),
    ("screw.density", 7850.0, "kg/m³", (7800.0, 7900.0), "steel (handbook value)"),
    ("screw.retardation", 1.0e-6, "s", (1e-8, 1e-5), "steel: ζ = βω/2 ≈ 0.3 % at 1 kHz"),
    ("screw.loss_factor", 0.0, "–", (0.0, 0.0),
     "hysteretic damping has no time-domain model; the retardation holds the material's"),
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
    ("axial.free_end_damping", 0.0, "N·s/m", (0.0, 0.0), "no axial support at the free end"),
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


def table1_drive() -> BallScrewDrive:
    """A drive calibrated to the modal data of the paper's Table 1 (h21 at Y_table = 115 mm).

    The model-updating example of ``examples/calibrate_table1.py`` (README, "Calibration to
    Table 1"): its modes match Table 1 in 11 of 15 targets, but its loops are limited by the
    delay rather than by its modes, so it poses no scheduling problem;
    :func:`reference_drive` is the drive for control design.

    A heavy machine-tool axis, 600 mm travel: a 700 kg saddle (Y axis carrying the X table and
    workpiece) on a 50×5 ball screw, fixed–fixed, driven through an elastomer jaw coupling.  Every
    value is a plausible catalogue or handbook figure; the uncertain ones (joint stiffnesses and
    dampings, pitch properties, bearing stiffnesses, hub inertias, heights) were fitted by
    :func:`fdjax.update_model` inside physically plausible bounds (``examples/calibrate_table1.py``
    reproduces the fit; the bounds and their reasons are there) and rounded to two digits.  The
    nut runs from l = 0.25 m to 0.85 m on a 1.0 m screw, so the modes move with Y_table.

    Modes of h21 = x2/T1 at Y_table = 115 mm (:func:`fdjax.drive_modes`) against Table 1
    (targets: frequency within 3 %, damping within 25 %, resonant phase within 15°):

    ====  ====================  ======================  ===========================  =====
    mode  Table 1 f, ζ, phase   model f, ζ, phase       Δf, Δζ, Δphase               met
    ====  ====================  ======================  ===========================  =====
    1     49 Hz, 0.120, −135°   49.5 Hz, 0.141, −131°   +1.0 %, +17 %, +4°           3/3
    2     95 Hz, 0.170, −155°   95.1 Hz, 0.076, −277°   +0.1 %, −55 %, −122°         1/3
    3     130 Hz, 0.090, −260°  131.4 Hz, 0.101, −100°  +1.1 %, +12 %, +160°         2/3
    4     1030 Hz, 0.003, −198° 1034 Hz, 0.0058, −196°  +0.4 %, +92 %, +2°           2/3
    5     1529 Hz, 0.010, −31°  1508 Hz, 0.0100, −26°   −1.4 %, +0.3 %, +5°          3/3
    ====  ====================  ======================  ===========================  =====

    11 of 15 targets are met.  The shortfall is structural (README, "Calibration to Table 1"):
    mode 1 is the saddle's pitch–axial mode, mode 2 its axial–pitch mode and mode 3 the coupling
    (motor against screw) mode.  Mode 3 lies above the saddle's axial resonance, where the saddle
    moves in anti-phase with the screw, so in h21 it is in phase (≈ −90°), not out of phase as in
    Table 1; mode 2's phase and damping are set by the same axial–pitch pair and no joint damping
    within bounds turns its phase by more than ~15°.  The screw-torsion mode 4 takes its damping
    from the coupling and hub dampers, not the screw material, and stays ~2× too damped.
    """
    screw = Screw(
        length=1.0,  # m, bearing-to-bearing length of a 1 m-class axis with 600 mm travel
        # m, effective diameter of a 50×5 screw (root ≈ 46.8 mm, less the thread): calibrated to
        # Table 1 within [25, 45] mm (32–50 mm screws)
        diameter=0.045,
        lead=0.005,  # m/rev, catalogue 50×5 screw: i_sc = 0.796 mm/rad; calibrated in [5, 20] mm
        youngs_modulus=2.06e11,  # Pa, bearing steel
        shear_modulus=7.93e10,  # Pa, steel
        density=7850.0,  # kg/m³, steel
        # s, negligible material damping (lower bound of the fit, 1e-8–1e-5 s): the screw modes
        # take their damping from the joints
        retardation=1.0e-8,
    )
    rotary = Rotary(
        # kg·m², rotor of a ~20 N·m servo motor plus motor-side hub; calibrated in [1.5e-3, 1.5e-2]
        motor_inertia=6.2e-3,
        # N·m/rad, elastomer jaw (spider) coupling, dynamic torsional stiffness; calibrated to
        # Table 1 at the lower bound of [2e3, 5e4] (elastomer … metal bellows couplings)
        coupling_stiffness=2.0e3,
        # N·m·s/rad, elastomer hysteresis: ζ ≈ 10 % of the coupling mode; calibrated in [1e-3, 5]
        coupling_damping=0.50,
        # N·m·s/rad, linearised small-amplitude friction of motor bearings and seal (upper bound
        # of the calibration range [1e-3, 0.05])
        motor_damping=0.05,
        # kg·m², steel screw-side coupling hub for a 50 mm shaft, bearing rings and lock nut;
        # calibrated at the upper bound of [1e-4, 2.5e-3]
        drive_end_inertia=2.5e-3,
        drive_end_damping=1.0e-3,  # N·m·s/rad, bearing friction (lower bound [1e-3, 1])
        free_end_inertia=1.4e-4,  # kg·m², free-end bearing rings and lock nut, calibrated
        free_end_damping=0.005,  # N·m·s/rad, free-end bearing friction
    )
    axial = Axial(
        # N/m, thrust-bearing pair with its support block and bolted housing; calibrated at the
        # lower bound of [1e8, 2e9]
        drive_end_stiffness=1.0e8,
        drive_end_damping=6.6e3,  # N·s/m, bearing-housing damping, calibrated in [1e2, 5e4]
        # N/m, fixed–fixed screw: the free-end support also takes axial load; calibrated in
        # [1e7, 5e8]
        free_end_stiffness=1.4e8,
        free_end_damping=0.0,
        drive_end_mass=0.5,  # kg, bearing inner rings, spacer and lock nut (lower bound)
    )
    carriage = Carriage(
        mass=700.0,  # kg, Y-axis saddle carrying the X table and workpiece (bound [250, 700])
        # kg·m², ≈ m (a² + h²)/12 = 0.052 m² · m for a 0.75 m × 0.25 m saddle; calibrated in
        # [4, 60] (J/m between 0.015 and 0.09 m²)
        pitch_inertia=36.0,
        # N·m/rad, guideway blocks plus the bending of saddle and bed (e.g. 4 blocks of
        # 1.3e8 N/m at ±0.1 m); calibrated at the lower bound of [5e6, 7e8]
        pitch_stiffness=5.0e6,
        # N·s/m, equivalent viscous damping of the guideway joints at vibration amplitudes
        # (pre-sliding), not gross-sliding friction; calibrated at the upper bound of [1e2, 5e4]
        axial_damping=5.0e4,
        pitch_damping=3.6e3,  # N·m·s/rad, ζ ≈ 14 % guideway joint damping, calibrated [1e2, 1e5]
        nut_height=-0.12,  # m, screw axis below the pitch centre, calibrated in [−0.15, −0.02]
        scale_height=-0.20,  # m, linear scale at the saddle base (bound of [−0.20, −0.02])
        tool_height=0.25,  # m, tool point above the table (cutting height); h21 does not see it
    )
    nut = NutJoint(
        # N/m, preloaded double nut of a 50 mm screw (catalogue ~1.5 kN/µm); upper bound of the
        # calibration range [1e8, 1.5e9]
        stiffness=1.5e9,
        damping=100.0,  # N·s/m, nut joint damping (lower bound of [1e2, 3e4])
    )
    return BallScrewDrive(screw, rotary, axial, carriage, nut, nut_offset=0.15, travel_m=(0.1, 0.7))
