"""The simulated plant's description: structural differences from the controller's arm in
plant.yaml, and a complete arm description (--plant-file) simulated whatever the controller believes."""
import math
import os
import shutil

import numpy as np
import pytest

from soft_arm_experiments.harness import load_setup, run_experiment
from soft_arm_experiments.harness_cli import main as harness_main
from soft_arm_drivers.sim.plant_config import load_plant_config
from soft_arm_model import build_model, load_arm_config
from soft_arm_model.parameters import ConfigError, default_config_dir

# the plant of plant.yaml with every difference from arm.yaml taken out
NEUTRAL = ["plant.youngs_modulus_scale=1.0", "plant.viscosity_scale=1.0", "plant.density_scale=1.0",
           "plant.friction=[0.1, 0.1, 0.1, 0.1]"]
# a short coiling protocol: two clik windows and one replay
SHORT = ["tasks.coiling.phases=[upward, downward]", "tasks.coiling.phase.upward.window=3.0",
         "tasks.coiling.phase.upward.sequence=[1, 2]", "tasks.coiling.phase.downward.window=1.0",
         "tasks.coiling.phase.downward.sequence=[1]", "control.clik.switch_delay=1.0"]


def test_structural_differences_reach_the_plants_arm():
    arm = load_arm_config()
    plant = load_plant_config(arm, overrides={
        "tendon.start_angle_error": "[0.05, 0, 0, -0.02]", "tendon.end_angle_error": "[0, 0.03, 0, 0]",
        "tendon.offset_fraction": "[0.57, 0.6, 0.64, 0.6]", "density_scale": 1.05,
        "friction": "[0.09, 0.16, 0.1, 0.12]", "discretisation.legendre_order": "[4, 1]",
        "discretisation.shear": True, "youngs_modulus_scale": 0.88})
    p = plant.plant_arm(arm)
    assert p.tendons[0].start_angle == pytest.approx(arm.tendons[0].start_angle + 0.05)
    assert p.tendons[3].start_angle == pytest.approx(arm.tendons[3].start_angle - 0.02)
    assert p.tendons[1].end_angle == pytest.approx(arm.tendons[1].end_angle + 0.03)
    assert [t.offset_fraction for t in p.tendons] == [0.57, 0.6, 0.64, 0.6]
    assert [t.friction for t in p.tendons] == [0.09, 0.16, 0.1, 0.12]
    assert p.material.density == pytest.approx(1.05 * arm.material.density)
    assert p.material.youngs_modulus == pytest.approx(0.88 * arm.material.youngs_modulus)
    assert p.enabled_modes == arm.enabled_modes + ("shear_y", "shear_z")
    # six modes, orders 4 and 1: 6 * 5 + 6 * 2 coordinates against the controller's 4 * (4 + 1)
    assert build_model(p).n == 42 and build_model(arm).n == 20


@pytest.mark.parametrize("key, value, message", [
    ("tendon.offset_fraction", "[0.6, 0.6, 0.6]", "plant.tendon.offset_fraction"),
    ("discretisation.legendre_order", "[3]", "one per division"),
    ("tendon.start_angle_error", "[0, 0, 0, 0.9]", "plant.tendon.start_angle_error"),
    ("tip_payload", "-0.001", "plant.tip_payload"),
])
def test_bad_plant_values_name_the_key(key, value, message):
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        load_plant_config(load_arm_config(), overrides={key: value})


def _arm_file(tmp_path, edit=None):
    path = tmp_path / "plant_arm.yaml"
    text = open(os.path.join(default_config_dir(), "arm.yaml"), encoding="utf-8").read()
    path.write_text(edit(text) if edit else text)
    return str(path)


def test_a_plant_file_with_a_wrong_length_list_or_an_unknown_key_is_refused(tmp_path):
    short = _arm_file(tmp_path, lambda t: t.replace("offset_fraction: [0.6, 0.6, 0.6, 0.6]",
                                                    "offset_fraction: [0.6, 0.6, 0.6]"))
    with pytest.raises(ConfigError, match=r"arm\.tendons\.offset_fraction"):
        load_setup("coiling", overrides=[f"plant.plant_file={short}"])
    (tmp_path / "unknown").mkdir()
    unknown = _arm_file(tmp_path / "unknown", lambda t: t.replace("poisson_ratio:", "poison_ratio:"))
    with pytest.raises(ConfigError, match=r"unknown key arm\.material\.poison_ratio.*poisson_ratio"):
        load_setup("coiling", overrides=[f"plant.plant_file={unknown}"])
    assert harness_main(["coiling", "--plant-file", str(tmp_path / "missing.yaml"), "--quiet"]) == 2


def test_a_plant_file_equal_to_arm_yaml_reproduces_the_run_exactly(tmp_path):
    """The file replaces the differences of plant.yaml: with the controller's own arm as the file,
    the run is the one of plant.yaml with every difference taken out, sample for sample."""
    neutral = run_experiment(load_setup("coiling", overrides=NEUTRAL + SHORT))
    shutil.copy(os.path.join(default_config_dir(), "arm.yaml"), tmp_path / "arm.yaml")
    from_file = run_experiment(load_setup("coiling", overrides=SHORT + [
        f"plant.plant_file={tmp_path / 'arm.yaml'}"]))
    a, b = neutral.record.arrays(), from_file.record.arrays()
    assert a["x"].shape == b["x"].shape and a["x"].size > 0
    assert np.array_equal(a["x"], b["x"], equal_nan=True) and np.array_equal(a["tension"], b["tension"])
    default = run_experiment(load_setup("coiling", overrides=SHORT)).record.arrays()
    assert not np.array_equal(default["x"], a["x"])       # plant.yaml's differences do matter
    assert math.isfinite(neutral.summary.rms_error)


FRAME_ERROR = ["plant.mocap.frame_error.rotation_deg=[0.0, 1.2, 1.6]",
               "plant.mocap.frame_error.translation=[0.003, -0.004, 0.0]"]


def _identified_arm_file(path, arm, registration=None):
    """An arm file as soft-arm-identify writes it: the arm, and the mocap calibration composed of
    ``registration`` after mocap.yaml's (none: no calibration in the file)."""
    from soft_arm_experiments.identify_cli import composed_calibration, write_identified_arm
    from soft_arm_drivers.mocap.bridge_config import load_mocap_config
    from soft_arm_model.config import write_arm_file
    if registration is None:
        write_arm_file(str(path), arm)
    else:
        calibration = composed_calibration(registration, load_mocap_config().calibration)
        write_identified_arm(str(path), arm, calibration)
    return str(path)


def test_the_mocap_calibration_of_an_arm_file_is_the_one_the_markers_come_through(tmp_path):
    """The simulated rig has no bridge: an arm file whose calibration undoes plant.mocap.frame_error
    gives markers in arm_base; one without a calibration leaves the frame error; the default setup
    has no correction."""
    from scipy.spatial.transform import Rotation
    from soft_arm_model.identification import Registration
    points = np.array([[0.01, -0.02, -0.3], [0.05, 0.1, -0.2]])
    plain = load_setup("coiling", overrides=FRAME_ERROR)
    R = Rotation.from_rotvec(np.radians([0.0, 1.2, 1.6])).as_matrix()
    assert np.allclose(plain.plant.as_mocap_reports(points), points @ R.T + [0.003, -0.004, 0.0])
    undo = Registration(R.T, -R.T @ np.array([0.003, -0.004, 0.0]))
    arm = load_arm_config()
    fixed = load_setup("coiling", overrides=FRAME_ERROR,
                       arm_file=_identified_arm_file(tmp_path / "a.yaml", arm, undo))
    assert np.allclose(fixed.plant.as_mocap_reports(points), points, atol=1e-12)
    bare = load_setup("coiling", overrides=FRAME_ERROR,
                      arm_file=_identified_arm_file(tmp_path / "b.yaml", arm))
    assert np.allclose(bare.plant.as_mocap_reports(points), plain.plant.as_mocap_reports(points))


def test_the_frame_error_then_the_bridge_correction_make_the_reports(tmp_path):
    """as_mocap_reports (one affine map, composed once) is the frame error applied first and the
    bridge's correction after it, for a correction that does not undo the error (the order shows)."""
    from scipy.spatial.transform import Rotation
    from soft_arm_model.identification import Registration
    points = np.array([[0.01, -0.02, -0.3], [0.05, 0.1, -0.2], [0.0, 0.0, 0.0]])
    correction = Registration(Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix(),
                              np.array([0.01, 0.02, -0.03]))
    arm_file = _identified_arm_file(tmp_path / "a.yaml", load_arm_config(), correction)
    plant = load_setup("coiling", overrides=FRAME_ERROR, arm_file=arm_file).plant
    rotvec, translation = plant.mocap_frame_error
    rotation, shift = (np.asarray(a, dtype=float) for a in plant.bridge_correction)
    assert not np.allclose(rotation, np.eye(3))
    reported = points @ Rotation.from_rotvec(rotvec).as_matrix().T + np.asarray(translation)
    assert np.allclose(plant.as_mocap_reports(points), reported @ rotation.T + shift, atol=1e-12)
    assert np.allclose(plant.as_mocap_reports(points[0]), plant.as_mocap_reports(points)[0])


def test_the_plant_stays_the_same_arm_whatever_arm_file_the_controller_is_given(tmp_path):
    """plant.yaml's differences apply to arm.yaml, not to the controller's arm file: an identified
    arm changes what the controller believes, not the arm it controls."""
    from dataclasses import replace
    differences = ["plant.youngs_modulus_scale=0.88", "plant.tendon.start_angle_error=[0.04, 0, 0, 0]"]
    plain = load_setup("coiling", overrides=differences)
    truth = plain.plant.plant_arm(plain.arm)
    stiffer = replace(truth.material, youngs_modulus=2 * truth.material.youngs_modulus)
    believed = replace(truth, material=stiffer)
    other = load_setup("coiling", overrides=differences,
                       arm_file=_identified_arm_file(tmp_path / "arm.yaml", believed))
    assert other.arm.material.youngs_modulus == pytest.approx(2 * truth.material.youngs_modulus)
    assert other.plant.plant_arm(other.arm) == truth
