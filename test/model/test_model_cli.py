"""The soft-arm-model command: every subcommand, JSON output, overrides and clear errors."""
import json

import numpy as np
import pytest

from soft_arm_model.cli import main


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_summary_json(capsys):
    code, out, _ = _run(capsys, "summary", "--json", "--set", "discretisation.legendre_order=[2, 0]")
    assert code == 0
    res = json.loads(out)
    assert res["dof"] == 16 and res["modes"] == ["torsion", "bending_y", "bending_z", "axial"]
    f = res["natural_frequencies_hz"]
    assert len(f) == 16 and 0.1 < f[0] < 5 and f[-1] > 10 * f[0]


def test_equilibrium_json_and_plot(capsys, tmp_path):
    png = tmp_path / "shape.png"
    code, out, _ = _run(capsys, "equilibrium", "--tensions", "0", "0", "3", "3", "--json",
                        "--plot", str(png))
    assert code == 0 and png.stat().st_size > 1000
    res = json.loads(out)
    assert res["frame"] == "arm_base"
    tip = np.array(res["tip_position_m"])
    assert abs(tip[0]) < 1e-9 and tip[1] > 0.01  # symmetric crossed pair bends towards +y
    np.testing.assert_allclose(res["marker_positions_m"][-1], tip, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(res["tip_quaternion_xyzw"]), 1.0, atol=1e-12)


def test_equilibrium_text_and_override_changes_result(capsys):
    code, out, _ = _run(capsys, "equilibrium", "--tensions", "2", "0", "0", "0")
    assert code == 0 and "tip position" in out
    soft = json.loads(_run(capsys, "equilibrium", "--tensions", "2", "0", "0", "0", "--json")[1])
    stiff = json.loads(_run(capsys, "equilibrium", "--tensions", "2", "0", "0", "0", "--json",
                            "--set", "material.youngs_modulus=6e5")[1])
    assert stiff["tip_position_m"][2] < soft["tip_position_m"][2]  # stiffer arm bends less


def test_workspace(capsys, tmp_path):
    png = tmp_path / "ws.png"
    code, out, _ = _run(capsys, "workspace", "--levels", "0", "5", "--tendons", "3", "4", "--json",
                        "--plot", str(png))
    res = json.loads(out)
    assert code == 0 and res["samples"] == 4 and res["converged"] == 4 and png.exists()


@pytest.mark.parametrize("argv,fragment", [
    (["equilibrium", "--tensions", "1", "2"], "needs 4 values"),
    (["equilibrium", "--tensions", "-1", "0", "0", "0"], ">= 0 N"),
    (["summary", "--set", "material.youngs_modulus=abc"], "arm.material.youngs_modulus"),
    (["summary", "--set", "geometry.lenght=1"], "did you mean arm.geometry.length"),
    (["summary", "--set", "novalue"], "key=value"),
    (["summary", "--config", "/nonexistent.yaml"], "cannot read"),
])
def test_bad_arguments_give_clear_errors(capsys, argv, fragment):
    code, _, err = _run(capsys, *argv)
    assert code == 2 and fragment in err
