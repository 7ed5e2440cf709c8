"""The command line, the figures it writes, and the reference settings it reproduces them with
(:mod:`fdjax._control._reference`)."""

import ast
import csv
import importlib.metadata
import json
import os
import pathlib
import re
import subprocess
import sys

import equinox as eqx
import jax
import numpy as np
import pytest

import fdjax
from fdjax import cli
from fdjax._control._reference import (
    reference_mcm,
    reference_pid,
    reference_servo,
    rigid_feedforward,
)

EPS = np.finfo(np.float64).eps
CLI_PATH = pathlib.Path(cli.__file__)
REFERENCE_PATH = pathlib.Path(fdjax.__file__).parent / "_control" / "_reference.py"
HEAVY = ("numpy", "jax", "jaxlib", "equinox", "diffrax", "optimistix", "matplotlib", "scipy")


# ---------------------------------------------------------------------- commands
def test_demo_writes_figures(tmp_path):
    # The demo runs in its own process, with the tests' XLA flags (conftest.py; its workers'
    # environment) but LLVM's optimisation level 1 where they set 0: the demo runs, not only
    # compiles, its margins' refinement at 6 × 61 positions, which level 0 slows.  Measured
    # alone: 98 s / 126 CPU-s against 127 s / 137 CPU-s at level 0 and 98 s / 134 CPU-s with
    # XLA's defaults, the printed text the same under all three and summary.json's numbers
    # within 2.8e-9 relative.  `make demo` runs it with XLA's defaults.
    out = tmp_path / "demo"
    env = dict(os.environ, XLA_FLAGS=os.environ.get("XLA_FLAGS", "").replace(
        "--xla_backend_optimization_level=0", "--xla_backend_optimization_level=1"))
    proc = subprocess.run([sys.executable, "-m", "fdjax.cli", "demo", "--out", str(out)],
                          capture_output=True, text=True, timeout=1200, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in ("fig2_three_mass_frf.png", "fig3_deflection_shapes.png",
                 "fig5_velocity_nyquist.png", "fig10_frf_family.png", "fig11_h21_cloud.png",
                 "fig12_resonant_phase.png", "fig14_peak_filter.png",
                 "fig16_pid_tracking.png", "fig17_mcm_tracking.png"):
        path = out / name
        assert path.exists() and os.path.getsize(path) > 10_000, name
    text = proc.stdout
    assert "103.7 Hz, 154.5 Hz" in text
    assert "Y_table =   100 mm" in text
    assert "RMS scale error" in text
    assert "least margins at 13 positions (gain margins in dB)" in text
    # the reference controller's margins in dB (sampled speed loop: GM 4.25 = 12.6 dB), and
    # where it is unstable: from 470–475 mm sampled, 515–520 mm continuous with a Padé delay
    # of order 8 (eigenvalues, fdjax.check_stability), so from the 13-position grid's 500 and
    # 550 mm
    assert "  sampled, as the servo runs it: speed loop GM ≥ 12.6 dB, PM ≥ 53.5°" in text
    assert "; unstable from 500 mm (eigenvalues)\n" in text
    assert "  continuous, exact delay: speed loop GM ≥ " in text
    assert "; gain margin below 0 dB from 550 mm\n" in text
    # summary.json: the numbers the chain produced, consistent with what the tests establish
    s = json.loads((out / "summary.json").read_text())
    assert s["quick"] is True
    np.testing.assert_allclose(s["three_mass"]["natural_frequencies_hz"], [103.7, 154.5],
                               atol=0.05)
    # the reference drive's documented shortfall against Table 1 (test_reference, README)
    assert s["table_1"]["targets_met"] == 2
    assert len(s["table_1"]["modes"]) == 5
    loop = s["double_loop"]
    assert len(loop["positions_m"]) == 13
    assert loop["servo"] == {"period_s": 1.25e-4, "delay_samples": 2, "tau_s": 2.5e-4,
                             "k_motor": 1.2, "current_limit_a": 40.0}
    for model in ("sampled", "continuous"):
        for name in ("speed", "position"):
            assert len(loop[model][name]["gain_margin"]) == 13, (model, name)
    sp, pos_ = loop["sampled"]["speed"], loop["sampled"]["position"]
    # the reference controller, tuned at 115 mm and held fixed: its speed loop keeps its margins
    # over the travel (GM 4.25, PM ≥ 53°); its position loop loses them toward the screw end,
    # where the saddle's axial mode has moved from 177 to 118 Hz (GM 1.86 → 0.80)
    assert min(sp["gain_margin"]) > 4 and min(sp["phase_margin_deg"]) > 50
    assert pos_["gain_margin"][0] > 1.8 and pos_["gain_margin"][-1] < 0.85
    assert np.all(np.diff(pos_["gain_margin"]) < 0)
    # the sampled loop adds the ZOH's and the backward difference's half-sample lags to τ:
    # its position loop has less gain margin than the continuous one at every position
    assert np.all(np.asarray(pos_["gain_margin"])
                  < np.asarray(loop["continuous"]["position"]["gain_margin"]))
    assert loop["sampled"]["freq_hz"][1] < 0.5 / 1.25e-4  # below Nyquist
    rms = s["tracking"]["rms_scale_error_m"]
    assert set(rms) == {"PID w/o FFC", "PID w/ FFC", "P/PI + MCM w/o FFC", "P/PI + MCM w/ FFC"}
    assert rms["PID w/ FFC"] < rms["PID w/o FFC"] / 10
    assert rms["P/PI + MCM w/ FFC"] < rms["P/PI + MCM w/o FFC"] / 10
    err = s["mcm_discretisation"]["max_relative_error"]
    assert err["fitted"] < 0.01 < 0.05 < err["tustin"]
    assert sorted(s["figures"]) == sorted(p.name for p in out.glob("*.png"))
    # Fig. 18 of the shipped designs: every controller at every 10 mm, and the schedule files
    c = s["control"]
    np.testing.assert_allclose(c["positions_mm"], np.arange(100.0, 701.0, 10.0))
    for name in fdjax.CONTROLLERS:
        for key in ("rms_error_um", "stable", "gain_margin_db", "phase_margin_deg",
                    "modulus_margin"):
            assert len(c[name][key]) == 61, (name, key)
        # its table per controller: the same numbers, as written (17 significant digits)
        with open(out / f"fig18_{name}.csv") as fh:
            rows = list(csv.DictReader(fh))
        assert list(rows[0])[:3] == ["position_mm", "rms_error_um", "stable"], name
        np.testing.assert_allclose([float(r["rms_error_um"]) for r in rows],
                                   c[name]["rms_error_um"], rtol=1e-15)
        np.testing.assert_allclose([float(r["modulus_margin"]) for r in rows],
                                   c[name]["modulus_margin"], rtol=1e-15)
    assert "fig18_rms_over_travel.png" in s["figures"]
    # the shipped designs (README's Fig. 18): the schedules, the robust MCM and the robust PID
    # keep the required margins at every 10 mm (measured least: GM 6.51 dB, PM 32.1°, modulus
    # margin 0.505 for the schedules, 0.523 for the robust MCM, 0.526 for the robust PID), and
    # the robust MCM's error (83.59–83.69 µm) is below the end-to-end schedule's
    # (84.34–84.60 µm) at every position; the MCM tuned at 115 mm and held
    # fixed does not (modulus margin 0.526 → 0.390, below 0.5 from 220 mm; GM 5.73 dB at
    # 700 mm) but stays stable with its error flat at 68.5–68.7 µm, below the schedules'; the
    # PID tuned at 115 mm likewise (modulus margin 0.241, GM 3.89 dB at 700 mm); end to end is
    # 0.965–0.967× the backpropagation schedule's error at every position and 0.694× the
    # robust PID's in the worst case
    for name in ("mcm_robust", "mcm_interp", "mcm_ata", "mcm_ata_e2e", "pid_robust"):
        assert all(c[name]["stable"]), name
        assert min(c[name]["gain_margin_db"]) > 6.0 and min(c[name]["phase_margin_deg"]) > 30.0
        assert min(c[name]["modulus_margin"]) > 0.5, name
    fixed = c["mcm_fixed"]
    assert all(fixed["stable"])
    assert fixed["modulus_margin"][-1] < 0.4 < 0.5 < fixed["modulus_margin"][0]
    assert fixed["gain_margin_db"][-1] < 6.0 < fixed["gain_margin_db"][0]
    pid = c["pid_115"]
    assert all(pid["stable"]) and pid["modulus_margin"][-1] < 0.25 < 0.5 < pid["modulus_margin"][0]
    assert np.ptp(pid["rms_error_um"]) < 0.003 * np.max(pid["rms_error_um"])
    rms = {k: np.asarray(c[k]["rms_error_um"], float) for k in fdjax.CONTROLLERS}
    assert np.ptp(rms["mcm_fixed"]) < 0.003 * np.max(rms["mcm_fixed"])
    assert np.all(rms["mcm_fixed"] < rms["mcm_ata_e2e"])
    assert np.all(rms["mcm_ata_e2e"] <= 0.97 * rms["mcm_ata"])   # end to end: better everywhere
    assert rms["mcm_ata_e2e"].max() < 0.70 * rms["pid_robust"].max()
    assert np.all(rms["mcm_robust"] < rms["mcm_ata_e2e"])
    sched = fdjax.load_schedule(out / "schedule.eqx")
    shipped, _ = fdjax.load_designs(cli.SHIPPED_DESIGNS)
    np.testing.assert_array_equal(sched.network(0.37), shipped["mcm_ata_e2e"].network(0.37))
    assert (out / "filters.csv").exists() and (out / "filters.json").exists()
    filters = json.loads((out / "filters.json").read_text())
    # the schedule's common gains in every row, beside its filters
    np.testing.assert_allclose(filters["kv"], float(shipped["mcm_ata_e2e"].loop.kv), rtol=1e-14)
    assert all(c[name]["modulus_margin_required"] == 0.5 for name in fdjax.CONTROLLERS)


def test_modes_writes_table(tmp_path, capsys):
    assert cli.main(["modes", "--out", str(tmp_path), "--positions", "3", "--n-modes", "4",
                     "--source", "model"]) == 0
    data = json.loads((tmp_path / "modes.json").read_text())
    assert len(data["modes"]) == 12
    first = data["modes"][0]
    assert first["position_mm"] == 100.0 and 45.0 < first["frequency_hz"] < 55.0  # 49.5 Hz
    assert (tmp_path / "modes.csv").read_text().startswith("position_mm,mode,frequency_hz")
    assert "Modes of h21" in capsys.readouterr().out


# ---------------------------------------------------------------------- argument errors
@pytest.mark.parametrize(
    "argv, message",
    [
        (["reprodce"], "unknown command 'reprodce'; did you mean 'reproduce'?"),
        (["figure", "--out", "x"], "unknown command 'figure'; did you mean 'figures'?"),
        (["plot"], "unknown command 'plot' (commands: reproduce, demo, figures, modes, tune)"),
        (["reproduce", "--quik"], "unrecognized arguments: --quik; did you mean '--quick'? "
                                  "(options of 'reproduce': --out, --quick)"),
        (["reproduce", "--qui"], "unrecognized arguments: --qui; did you mean '--quick'?"),
        # no silent abbreviations
        (["modes", "--source", "data"], "argument --source: invalid choice: 'data'"),
        # --positions is a count: a position typed in mm (or m) says so
        (["modes", "--positions", "115mm"],
         "argument --positions: expected the number of table positions spread over the travel "
         "(a count, not a position in m or mm), an integer ≥ 2 and ≤ 601; got '115mm'"),
        (["modes", "--positions", "0.115"], "a count, not a position in m or mm"),
        (["modes", "--positions", "1"], "an integer ≥ 2 and ≤ 601; got '1'"),
        (["modes", "--positions", "1000000"], "an integer ≥ 2 and ≤ 601; got '1000000'"),
        (["modes", "--n-modes", "0"],
         "argument --n-modes: expected the number of modes, an integer ≥ 1 and ≤ 100; got '0'"),
        (["modes", "--n-modes", "99999", "--source", "model"],
         "argument --n-modes: expected the number of modes, an integer ≥ 1 and ≤ 100; "
         "got '99999'"),
        ([], "the following arguments are required: {reproduce,demo,figures,modes,tune}"),
        (["tnue"], "unknown command 'tnue'; did you mean 'tune'?"),
        (["tune", "--steps", "10"], "unrecognized arguments: --steps 10 (options of 'tune': "
                                    "--out, --quick)"),
        (["demo", "--quick"], "unrecognized arguments: --quick; demo is already 'fdjax "
                              "reproduce --quick' (options of 'demo': --out)"),
        # before the command: a typo of --version, a command's option, anything else
        (["--versoin"], "unknown option '--versoin' before the command; did you mean "
                        "'--version'?"),
        (["--out", "x", "demo"], "unknown option '--out' before the command; it is an option "
                                 "of reproduce, demo, figures, modes, tune: give it after the "
                                 "command, e.g. 'fdjax reproduce --out ...'"),
        (["-v"], "unknown option '-v' before the command; before a command fdjax takes --help "
                 "and --version only"),
    ],
    ids=["typo", "typo-figures", "unknown-command", "bad-option", "abbreviation", "bad-choice",
         "positions-in-mm", "positions-in-m", "positions-too-few", "positions-too-many",
         "n-modes-zero", "n-modes-too-many", "no-command",
         "typo-tune", "tune-bad-option", "demo-is-quick", "version-typo", "option-first",
         "unknown-short"],
)
def test_argument_errors(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err, err
    if "unrecognized arguments" in message:  # the command's usage, not fdjax's
        assert err.startswith(f"usage: fdjax {argv[0]} "), err


# ---------------------------------------------------------------------- --out before any work
def _no_work(monkeypatch):
    """Every command's work raises: a test that reaches it has started computing."""
    def work(*args, **kwargs):
        raise AssertionError("the command started its work")

    for name in ("reproduce", "tune", "modes", "three_mass_figures", "drive_figures",
                 "loop_figures", "simulation_figures"):
        monkeypatch.setattr(cli, name, work)


@pytest.mark.parametrize("command", ["reproduce", "demo", "figures", "modes", "tune"])
@pytest.mark.parametrize("where, reason", [
    ("file", "exists and is not a directory"),
    ("file/sub", "cannot create it: {tmp}/file is not a directory"),
    ("file/a/b", "cannot create it: {tmp}/file is not a directory"),
], ids=["existing-file", "under-a-file", "deep-under-a-file"])
def test_out_is_checked_before_any_work(command, where, reason, tmp_path, monkeypatch, capsys):
    _no_work(monkeypatch)
    (tmp_path / "file").write_text("not a folder")
    out = f"{tmp_path}/{where}"
    extra = ["--quick"] if command in ("reproduce", "tune") else []
    with pytest.raises(SystemExit) as exc:
        cli.main([command, *extra, "--out", out])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == (f"fdjax {command}: error: --out {out}: "
                                    + reason.format(tmp=tmp_path)), err
    assert "Traceback" not in err
    assert (tmp_path / "file").read_text() == "not a folder"


@pytest.mark.parametrize("command, name", [("modes", "modes.json"), ("demo", "summary.json"),
                                           ("tune", "schedule.eqx")])
def test_a_folder_where_a_file_goes_is_refused_before_any_work(command, name, tmp_path,
                                                                monkeypatch, capsys):
    """A folder in the way of a file the command writes: refused before minutes of work."""
    _no_work(monkeypatch)
    (tmp_path / name).mkdir()
    with pytest.raises(SystemExit) as exc:
        cli.main([command, "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"fdjax {command}: error: --out {tmp_path}: {tmp_path}/{name} is a directory, where "
        "the command writes a file")


def test_out_empty_is_refused(monkeypatch, capsys):
    _no_work(monkeypatch)
    with pytest.raises(SystemExit) as exc:
        cli.main(["modes", "--out="])
    assert exc.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        "fdjax modes: error: --out : an empty path; give a directory")


@pytest.mark.parametrize("command", ["reproduce", "demo", "figures", "modes", "tune"])
def test_out_is_created_before_any_work(command, tmp_path, monkeypatch):
    out = tmp_path / "a" / "b"
    seen = []
    monkeypatch.setattr(cli, "reproduce", lambda o, quick: seen.append(os.path.isdir(o)))
    monkeypatch.setattr(cli, "tune", lambda o, quick: seen.append(os.path.isdir(o)))
    monkeypatch.setattr(cli, "modes", lambda o, *a: seen.append(os.path.isdir(o)))
    monkeypatch.setattr(cli, "three_mass_figures", lambda o: seen.append(os.path.isdir(o)))
    monkeypatch.setattr(cli, "drive_figures", lambda o: (None, None, None))
    monkeypatch.setattr(cli, "loop_figures", lambda *a: None)
    monkeypatch.setattr(cli, "simulation_figures", lambda o: None)
    assert cli.main([command, "--out", str(out)]) == 0
    assert seen == [True]


# ---------------------------------------------------------------------- --version, --help
def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out == f"fdjax {importlib.metadata.version('fdjax')}\n"


def test_version_from_a_source_tree(monkeypatch, capsys):
    """Without the package's metadata (not pip-installed), the version fdjax itself carries."""
    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", missing)
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out == f"fdjax {fdjax.__version__}\n"


def test_reproduce_help_says_what_quick_does(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["reproduce", "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert ("--quick evaluate the designs shipped with fdjax (fdjax/data/reference_designs) "
            "for Fig. 18 instead of tuning them afresh") in text
    assert "13 table positions instead of 61" in text


def test_help_lists_the_commands(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "{" + ",".join(cli.COMMANDS) + "}" in out.splitlines()[0]   # the parser's commands
    for command in cli.COMMANDS:
        assert f"fdjax {command}" in out
        # each command's own line under "positional arguments", with its help
        assert re.search(rf"^    {command} +\S", out, re.M), command
    assert "``" not in out     # the module docstring's markup is not printed


# ---------------------------------------------------------------------- printed margins
_GRID_M = [round(0.1 + 0.05 * k, 10) for k in range(13)]


def _margins(gm_speed, gm_position):
    return {"speed": {"gain_margin": gm_speed, "phase_margin_deg": [60.0] * len(gm_speed)},
            "position": {"gain_margin": gm_position,
                         "phase_margin_deg": [80.0] * (len(gm_position) - 1) + [-10.25]}}


def test_loop_line_in_db_and_where_unstable():
    """Gain margins print in dB (20 log10: 4.25 → 12.57 dB, 0.8 → −1.94 dB); the positions
    where a gain margin is below 0 dB are named as runs of the grid."""
    # the sampled position loop of the reference controller (demo): below 1 from 500 mm
    position = [1.862, 1.685, 1.531, 1.397, 1.282, 1.184, 1.101, 1.03, 0.97, 0.918, 0.873,
                0.834, 0.8]
    line = cli._loop_line("continuous", _margins([4.25] * 13, position), _GRID_M)
    assert line == ("continuous: speed loop GM ≥ 12.6 dB, PM ≥ 60.0°; position loop GM ≥ "
                    "-1.9 dB, PM ≥ -10.2°; gain margin below 0 dB from 500 mm")
    # with the eigenvalues' verdict (the sampled loop), that is what names the positions
    sampled = {**_margins([4.25] * 13, position), "stable": [True] * 7 + [False] * 6}
    assert cli._loop_line("sampled", sampled, _GRID_M).endswith(
        "PM ≥ -10.2°; unstable from 450 mm (eigenvalues)")
    assert cli._loop_line("x", _margins([4.25] * 13, [2.0] * 13), _GRID_M) == (
        "x: speed loop GM ≥ 12.6 dB, PM ≥ 60.0°; position loop GM ≥ 6.0 dB, PM ≥ -10.2°")
    speed = [0.5, 0.9] + [2.0] * 4 + [0.99] + [2.0] * 2 + [0.9] * 3 + [2.0]
    assert cli._loop_line("x", _margins(speed, [2.0] * 13), _GRID_M).endswith(
        "; gain margin below 0 dB up to 150 mm, at 400 mm, at 550–650 mm")
    assert cli._where([True] * 3, [0.1, 0.2, 0.3]) == "at every position"
    assert cli._where([False, True, False], [0.1, 0.2, 0.3]) == "at 200 mm"


# ---------------------------------------------------------------------- --help is light
_PROBE = """
import json, sys
{load}
try:
    cli.main(["--help"])
except SystemExit as exc:
    code = exc.code
print(json.dumps({{"code": code, "heavy": [m for m in {heavy!r} if m in sys.modules]}}))
"""


def _probe(load: str) -> dict:
    src = _PROBE.format(load=load, heavy=HEAVY)
    run = subprocess.run([sys.executable, "-c", src], capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_cli_module_imports_only_the_standard_library():
    """cli.py on its own (loaded from its file, without the package init): ``--help`` answers
    with none of numpy, JAX, equinox, diffrax or matplotlib imported."""
    load = ("import importlib.util\n"
            f"spec = importlib.util.spec_from_file_location('fdjax_cli_alone', {str(CLI_PATH)!r})\n"
            "cli = importlib.util.module_from_spec(spec)\n"
            "spec.loader.exec_module(cli)")
    got = _probe(load)
    assert got == {"code": 0, "heavy": []}


def test_cli_module_level_imports_are_standard_library():
    tree = ast.parse(CLI_PATH.read_text())
    names = []
    for node in tree.body:  # module level only; the commands import inside their functions
        if isinstance(node, ast.Import):
            names += [a.name.split(".")[0] for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names.append((node.module or "").split(".")[0] if node.level == 0 else ".")
    assert set(names) <= {"__future__", "argparse", "csv", "json", "os", "sys", "time",
                          "typing"}, names


def test_fdjax_help_does_not_import_jax():
    """``fdjax --help`` through the installed package: nothing heavy once the package init is
    lazy.  Skipped while ``fdjax/__init__.py`` itself imports JAX (then the time is the
    package's, not the command line's)."""
    eager = _probe("import fdjax\nfrom fdjax import cli")
    heavy = [m for m in eager["heavy"] if m in ("jax", "equinox", "diffrax", "matplotlib")]
    if heavy:
        bare = subprocess.run([sys.executable, "-c", "import sys, fdjax; print('jax' in "
                               "sys.modules)"], capture_output=True, text=True, timeout=120)
        if bare.stdout.strip() == "True":
            pytest.skip("fdjax/__init__.py imports JAX eagerly; cli.py itself is checked by "
                        "test_cli_module_imports_only_the_standard_library")
    assert eager["code"] == 0 and heavy == [], eager


def test_import_sets_the_scheduler_flag_also_after_jax():
    """Imported after JAX (before its first array), fdjax still selects the sequential CPU
    scheduler and float64; a flag the user set is kept."""
    code = ("import os, jax\nimport fdjax\nimport jax.numpy as jnp\n"
            "print(os.environ['XLA_FLAGS'], jnp.zeros(1).dtype)")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64")}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, env=dict(env, JAX_PLATFORMS="cpu"))
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["--xla_cpu_enable_concurrency_optimized_scheduler=false",
                                  "float64"], run.stdout
    mine = "--xla_cpu_enable_concurrency_optimized_scheduler=true"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, env=dict(env, JAX_PLATFORMS="cpu", XLA_FLAGS=mine))
    assert run.returncode == 0 and run.stdout.split() == [mine, "float64"], run


# ---------------------------------------------------------------------- reference settings
def test_reference_module_imports_only_from_below():
    """_reference is domain code: it builds on the controllers, filters and the drive, never
    on the edges (plots, cli) or the analyses; ``_checks`` (argument validation) is below all."""
    tree = ast.parse(REFERENCE_PATH.read_text())
    allowed = {"_controllers", "_servo", "_blocks", "_drive", "_filters", "_statespace",
               "_checks"}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            assert (node.module or "").split(".")[0] in allowed, node.module
        elif isinstance(node, ast.ImportFrom | ast.Import):
            mods = [node.module] if isinstance(node, ast.ImportFrom) else [
                a.name for a in node.names]
            assert not any(m.startswith("fdjax") for m in mods), mods


def test_reference_servo_is_the_default_servo():
    servo = reference_servo()
    assert servo.period == fdjax.Servo().period == 1.25e-4
    assert servo.delay_samples == fdjax.Servo().delay_samples == 2
    assert float(servo.k_motor) == float(fdjax.Servo().k_motor) == 1.2
    assert servo.tau == 2.5e-4


def test_reference_mcm_targets_the_axial_and_torsional_modes():
    """At its centre the peak term is (K/2ξ) e^{i(π/2 − φ)} (Eq. (3)), the notch factor at its
    centre is ζ_n/ζ_d (Eq. (4)): closed forms, to the round-off of one second-order section."""
    mcm = reference_mcm()
    K, xi, phi = 0.34, 0.20, np.radians(-50.0)
    np.testing.assert_allclose(np.asarray(mcm.peak.omega) / (2 * np.pi), [174.0], rtol=4 * EPS)
    np.testing.assert_allclose(np.asarray(mcm.notch.omega) / (2 * np.pi), [1260.0],
                               rtol=4 * EPS)
    peak = complex(np.asarray(mcm.peak.frf([174.0]))[0])
    np.testing.assert_allclose(peak, 1 + K / (2 * xi) * np.exp(1j * (np.pi / 2 - phi)),
                               rtol=1e-13)
    notch = complex(np.asarray(mcm.notch.frf([1260.0]))[0])
    np.testing.assert_allclose(notch, 0.005 / 0.34, rtol=1e-12)
    c = fdjax.reference_controller()
    assert (float(c.kp), float(c.kv), float(c.ki), float(c.k_ffv)) == pytest.approx(
        (200.0, 5400.0, 60.0, 1.0), rel=1e-14)
    np.testing.assert_allclose(float(c.k_ffa), float(rigid_feedforward(fdjax.reference_drive())[1]),
                               rtol=1e-15)


def test_reference_pid_is_the_default_scaled_to_6_db():
    base, pid = fdjax.PIDLoop(), reference_pid(k_ffv=2.0, k_ffa=0.5)
    for name in ("kp", "ki", "kd"):
        np.testing.assert_allclose(float(getattr(pid, name)), 6.2 * float(getattr(base, name)),
                                   rtol=4 * EPS)
    np.testing.assert_allclose(float(pid.wd), float(base.wd), rtol=4 * EPS)
    assert float(pid.k_ffv) == 2.0 and float(pid.k_ffa) == 0.5
    assert float(reference_pid().k_ffv) == 0.0 == float(reference_pid().k_ffa)


@pytest.mark.parametrize("position_m", [0.1, 0.4, 0.7])
def test_rigid_feedforward_is_the_rigid_body_mode_of_the_fe_model(position_m):
    """k_ffa = rᵀMr/(k_m i_sc), k_ffv = rᵀCr/(k_m i_sc) for the rigid-body mode r of the FE
    model (every rotation 1, the carriage at i_sc, the axial DOFs still).  Both sides are sums of
    the same N² products: they agree to N²·ε of the sum of the products' magnitudes."""
    drive = fdjax.reference_drive()
    servo = fdjax.Servo(k_motor=1.5)
    k_ffv, k_ffa = (float(x) for x in rigid_feedforward(drive, servo))
    fe = fdjax.fe_matrices(drive, position_m)
    n = fdjax.DEFAULT_ELEMENTS
    M, C = np.asarray(fe.mass), np.asarray(fe.damping)
    N = M.shape[0]
    r = np.zeros(N)
    r[: n + 2] = 1.0  # motor and every screw rotation node
    r[2 * n + 3] = isc = float(drive.screw.ratio)  # the carriage follows at i_sc
    scale = 1.5 * isc
    for got, X in ((k_ffa, M), (k_ffv, C)):
        bound = N**2 * EPS * (np.abs(r) @ np.abs(X) @ np.abs(r)) / scale
        assert abs(got - r @ X @ r / scale) <= bound


def test_rigid_feedforward_gradient_and_default_servo():
    """∂k_ffa/∂m = i_sc/k_m (J_eq = … + m i_sc²) and ∂k_ffa/∂k_m = −k_ffa/k_m, by jax.grad;
    without a servo, the reference servo's k_m; the DoubleLoop default k_ffa is the same
    rigid-body feed-forward (its J_eq quoted to 6 significant digits: ≤ 3.8e-6 relative)."""
    drive = fdjax.reference_drive()
    servo = reference_servo()
    isc, km = float(drive.screw.ratio), float(servo.k_motor)
    g_mass = jax.grad(lambda m: rigid_feedforward(
        eqx.tree_at(lambda d: d.carriage.mass, drive, m), servo)[1])(drive.carriage.mass)
    np.testing.assert_allclose(float(g_mass), isc / km, rtol=16 * EPS)
    k_ffa = float(rigid_feedforward(drive)[1])
    g_km = jax.grad(lambda k: rigid_feedforward(drive, fdjax.Servo(k_motor=k))[1])(servo.k_motor)
    np.testing.assert_allclose(float(g_km), -k_ffa / km, rtol=16 * EPS)
    # the default's inertia is quoted to 6 digits (1.30769e-2): half a unit in the last, 3.8e-6
    np.testing.assert_allclose(float(fdjax.DoubleLoop().k_ffa), k_ffa, rtol=4e-6)


def test_rigid_feedforward_errors():
    with pytest.raises(TypeError, match=r"`rigid_feedforward\(drive=\.\.\.\)` must be an "
                                        r"fdjax.BallScrewDrive, got Servo"):
        rigid_feedforward(fdjax.Servo())
    with pytest.raises(TypeError, match=r"`rigid_feedforward\(servo=\.\.\.\)` must be an "
                                        r"fdjax.Servo, got float"):
        rigid_feedforward(fdjax.reference_drive(), 1.2)


def test_progress_bar_in_a_log_and_on_a_terminal(monkeypatch, capsys):
    """The tuners' progress: a line per report in a log; on a terminal one line rewritten in
    place, ended by the last report or by the next message."""
    from fdjax import _progress

    monkeypatch.setattr(_progress, "_terminal", lambda: False)
    _progress.bar("tune_local", 5, 20, "J mean 1.5, max 2")
    _progress.bar("tune_local", 20, 20, "J mean 1.2, max 1.4")
    assert capsys.readouterr().err == (
        "tune_local [█████░░░░░░░░░░░░░░░] step 5/20, J mean 1.5, max 2\n"
        "tune_local [████████████████████] step 20/20, J mean 1.2, max 1.4\n")
    monkeypatch.setattr(_progress, "_terminal", lambda: True)
    _progress.bar("tune_simplex", 1, 3, "best J 2", "evaluation")
    _progress.say("next stage")
    _progress.bar("tune_simplex", 3, 3, "best J 1", "evaluation")
    _progress.say("done")
    assert capsys.readouterr().err == (
        "\r\x1b[2Ktune_simplex [███████░░░░░░░░░░░░░] evaluation 1/3, best J 2\nnext stage\n"
        "\r\x1b[2Ktune_simplex [████████████████████] evaluation 3/3, best J 1\ndone\n")
