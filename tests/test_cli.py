"""The command line and the figures it writes."""

import os

from fdjax import cli


def test_demo_writes_figures(tmp_path, capsys):
    out = tmp_path / "demo"
    assert cli.main(["demo", "--out", str(out)]) == 0
    for name in ("fig2_three_mass_frf.png", "fig3_deflection_shapes.png",
                 "fig5_velocity_nyquist.png", "fig10_frf_family.png", "fig11_h21_cloud.png"):
        path = out / name
        assert path.exists() and os.path.getsize(path) > 10_000, name
    text = capsys.readouterr().out
    assert "103.7 Hz, 154.5 Hz" in text
    assert "Y_table =   100 mm" in text
