"""An identified arm's file tells the shape estimator what it should be told of that arm:
soft-arm-identify writes the payload's uncertainty there as ``estimator.prior.payload``, and a run
given the file (the harness's ``arm_file``, soft-arm-experiment's ``--arm-file``, a node's
``--params-file``) takes every ``estimator.prior`` the file carries over estimator.yaml's."""
import numpy as np
import pytest

from soft_arm_control.shape_estimation import load_estimator_config, prior_overrides
from soft_arm_experiments.experiment import _ros_arguments
from soft_arm_experiments.harness import load_setup
from soft_arm_experiments.identify_cli import identified_priors, write_identified_arm
from soft_arm_model import load_arm_config
from soft_arm_model.identification import Estimate
from soft_arm_model.parameters import ConfigError

NAMES = ("tendon_1", "tendon_2", "tendon_3", "tendon_4")


def _estimates(tip_mass_uncertainty=3e-4):
    """A fit's estimates: the tip mass's uncertainty split 0.6 standard error, 0.8 basis shift; the
    stiffness and a routing with uncertainties of their own."""
    def e(value, uncertainty, unit="-"):
        return Estimate(value, 0.6 * uncertainty, unit, 0.8 * uncertainty)

    out = {"youngs_modulus": e(1.7e5, 850.0, "Pa"), "tip_mass": e(0.002, tip_mass_uncertainty, "kg")}
    out.update({f"offset_fraction[{n}]": e(0.6, 0.01) for n in NAMES})
    return out


def test_the_estimator_is_told_the_payloads_uncertainty_alone():
    """Both shares of the tip mass's uncertainty (the noise's and the basis shift's); the stiffness,
    friction and routing stay estimator.yaml's (identified_priors' docstring says why)."""
    assert identified_priors(_estimates()) == pytest.approx({"prior.payload": 3e-4})


def test_a_payload_uncertainty_beyond_what_the_estimator_takes_is_its_interval_end():
    """An unidentifiable tip mass (0.5 kg of uncertainty) is written as 0.1 kg, the schema's end."""
    priors = identified_priors(_estimates(0.5))
    assert priors == {"prior.payload": 0.1}
    assert load_estimator_config(overrides=priors).prior_payload == 0.1


def _arm_file(directory, priors=None):
    directory.mkdir(exist_ok=True)
    path = str(directory / "arm_identified.yaml")
    write_identified_arm(path, load_arm_config(), (np.eye(3), np.zeros(3)), "a test arm", priors)
    return path


def test_an_identified_arm_file_tells_the_harness_its_priors_beneath_the_runs_own_overrides(tmp_path):
    """The harness given a file with priors (any ``estimator.prior``: a lab may state its own arm's):
    they replace estimator.yaml's; ``--set`` still wins; the file read as an arm is unchanged by
    them; a file without priors leaves estimator.yaml's."""
    priors = {"prior.stiffness": 0.02, "prior.friction": 0.01, "prior.tendon_offset": 0.02,
              "prior.tendon_angle": 0.02, "prior.payload": 3e-4}
    path = _arm_file(tmp_path, priors)
    assert prior_overrides(path) == pytest.approx(priors)
    assert load_arm_config(path) == load_arm_config()
    est = load_setup("coiling", arm_file=path).estimator
    assert (est.prior_stiffness, est.prior_friction, est.prior_tendon_offset, est.prior_tendon_angle,
            est.prior_payload) == pytest.approx(tuple(priors.values()))
    est = load_setup("coiling", overrides=["estimator.prior.payload=0.001"], arm_file=path).estimator
    assert est.prior_payload == 0.001 and est.prior_tendon_offset == pytest.approx(0.02)
    default = load_estimator_config()
    assert load_setup("coiling", arm_file=_arm_file(tmp_path / "plain")).estimator == default


def test_a_prior_the_estimator_cannot_take_is_refused_naming_the_arm_file(tmp_path):
    path = _arm_file(tmp_path, {"prior.tendon_angle": 0.5})
    with pytest.raises(ConfigError, match=r"arm_identified\.yaml.*estimator\.prior\.tendon_angle = 0\.5"):
        load_setup("coiling", arm_file=path)
    path = _arm_file(tmp_path, {"prior.routing": 0.01})
    with pytest.raises(ConfigError, match=r"arm_identified\.yaml.*prior\.routing"):
        prior_overrides(path)


def test_the_graphs_nodes_read_the_arm_file_after_estimator_yaml_and_before_the_overrides(tmp_path):
    """ROS takes the last value a parameter is given: the arm file's priors over estimator.yaml's,
    the command line's ``-p`` over both."""
    path = _arm_file(tmp_path, identified_priors(_estimates()))
    args = _ros_arguments("coiling", ["estimator.prior.payload=0.001"], None, path)
    files = [args[i + 1] for i, a in enumerate(args) if a == "--params-file"]
    assert files[-1] == path and files[-2].endswith("estimator.yaml")
    assert not any(f.endswith("/arm.yaml") for f in files)
    assert args.index("estimator.prior.payload:=0.001") > args.index(path)
