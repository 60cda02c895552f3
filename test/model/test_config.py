"""Config loading: the shipped file is valid; every bad value is named with what is allowed."""
import pytest
import yaml

from soft_arm_model import ConfigError, load_arm_config
from soft_arm_model.parameters import default_config_dir, read_parameters


def test_default_config_describes_the_paper_arm():
    cfg = load_arm_config()
    assert cfg.geometry.length == 0.38
    assert (cfg.geometry.base_radius, cfg.geometry.tip_radius) == (0.016, 0.0048)
    angles = [(round(t.start_angle * 180 / 3.141592653589793), round(t.end_angle * 180 / 3.141592653589793))
              for t in cfg.tendons]
    assert angles == [(30, 30), (150, 150), (60, 120), (120, 60)]
    assert all(t.end == 0.325 for t in cfg.tendons)
    assert 0.325 in cfg.discretisation.division_ends


@pytest.mark.parametrize("key,value,fragment", [
    ("material.youngs_modulus", -1.0, "arm.material.youngs_modulus = -1.0"),
    ("material.poisson_ratio", 0.7, "[0, 0.5]"),
    ("material.axial_law", "hooke", "one of ['linear', 'neo_hookean']"),
    ("tendons.friction", [0.1, 0.1, 0.1], "4 values, one per tendon"),
    ("tendons.offset_fraction", [0.6, 0.6, 1.2, 0.6], "[0, 1)"),
    ("geometry.tip_radius", 0.02, "no larger than geometry.base_radius"),
    ("discretisation.division_ends", [0.3, 0.38], "division boundary at the end of tendon_1"),
    ("discretisation.gauss_points", [3, 4], "at least legendre_order + 1"),
    ("discretisation.legendre_order", [2.5, 0], "orders in [0, 12]"),
    ("gravity", [0, 0], "three components"),
    ("markers.positions", [0.2, 0.1], "strictly increasing"),
])
def test_bad_values_name_key_value_and_range(key, value, fragment):
    with pytest.raises(ConfigError) as err:
        load_arm_config(overrides={key: value})
    message = str(err.value)
    assert f"arm.{key}" in message and fragment in message


def test_unknown_and_missing_keys(tmp_path):
    with pytest.raises(ConfigError, match="did you mean arm.material.youngs_modulus"):
        load_arm_config(overrides={"material.youngs_modulos": 1e5})
    params = read_parameters(f"{default_config_dir()}/arm.yaml")
    del params["arm"]["material"]["viscosity"]
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": params}}))
    with pytest.raises(ConfigError, match="missing key arm.material.viscosity"):
        load_arm_config(str(path))


def test_overrides_parse_like_ros_parameters():
    cfg = load_arm_config(overrides={"material.youngs_modulus": "2.5e5",
                                     "tendons.friction": "[0, 0, 0.2, 0.2]"})
    assert cfg.material.youngs_modulus == 2.5e5
    assert [t.friction for t in cfg.tendons] == [0, 0, 0.2, 0.2]


@pytest.mark.parametrize("value", ["[0, 0", "\udcff"])     # bad YAML; bytes not UTF-8 (a --set)
def test_an_override_that_does_not_parse_is_a_config_error(value):
    with pytest.raises(ConfigError, match="material.youngs_modulus: cannot parse"):
        load_arm_config(overrides={"material.youngs_modulus": value})


def test_not_a_parameter_file(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("arm: {}\n")
    with pytest.raises(ConfigError, match="ROS 2 parameter layout"):
        load_arm_config(str(path))
    with pytest.raises(ConfigError, match="cannot read"):
        load_arm_config(str(tmp_path / "missing.yaml"))
