"""The command line and the figures it writes."""

import os

import numpy as np

from fdjax import cli


def test_demo_writes_figures(tmp_path, capsys):
    out = tmp_path / "demo"
    assert cli.main(["demo", "--out", str(out)]) == 0
    for name in ("fig2_three_mass_frf.png", "fig3_deflection_shapes.png",
                 "fig5_velocity_nyquist.png", "fig10_frf_family.png", "fig11_h21_cloud.png",
                 "fig12_resonant_phase.png", "fig14_peak_filter.png",
                 "fig16_pid_tracking.png", "fig17_mcm_tracking.png"):
        path = out / name
        assert path.exists() and os.path.getsize(path) > 10_000, name
    text = capsys.readouterr().out
    assert "103.7 Hz, 154.5 Hz" in text
    assert "Y_table =   100 mm" in text
    assert "RMS scale error" in text
    # summary.json: the numbers the chain produced, consistent with what the tests establish
    import json

    s = json.loads((out / "summary.json").read_text())
    assert s["quick"] is True
    np.testing.assert_allclose(s["three_mass"]["natural_frequencies_hz"], [103.7, 154.5],
                               atol=0.05)
    assert s["table_1"]["targets_met"] == 11  # the documented shortfall (test_calibrate)
    assert len(s["table_1"]["modes"]) == 5
    loop = s["double_loop"]
    assert len(loop["positions_m"]) == 13
    assert min(loop["inner"]["gain_margin"]) > 1 and min(loop["outer"]["gain_margin"]) > 1
    assert set(s["tracking"]["rms_scale_error_m"]) == {
        "PID w/o FFC", "PID w/ FFC", "P/PI + MCM w/o FFC", "P/PI + MCM w/ FFC"}
    err = s["mcm_discretisation"]["max_relative_error"]
    assert err["fitted"] < 0.01 < 0.05 < err["tustin"]
    assert sorted(s["figures"]) == sorted(p.name for p in out.glob("*.png"))


def test_modes_writes_table(tmp_path, capsys):
    import json

    assert cli.main(["modes", "--out", str(tmp_path), "--positions", "3", "--n-modes", "4",
                     "--source", "model"]) == 0
    data = json.loads((tmp_path / "modes.json").read_text())
    assert len(data["modes"]) == 12
    first = data["modes"][0]
    assert first["position_mm"] == 100.0 and 45.0 < first["frequency_hz"] < 55.0  # 49.5 Hz
    assert (tmp_path / "modes.csv").read_text().startswith("position_mm,mode,frequency_hz")
    assert "Modes of h21" in capsys.readouterr().out
