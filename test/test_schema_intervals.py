"""The interval a schema's text states ("a rate in (0, 1e6] N/s") is the interval its check accepts:
the text is what an error and a parameter's descriptor (description and range) tell the user, so
it must not drift from the check. For every float and int entry of every configuration schema."""
import math

import pytest

from soft_arm_control.config import CONTROL_SCHEMA, TASK_SCHEMA
from soft_arm_drivers.can.driver_config import SCHEMA as DRIVER_SCHEMA
from soft_arm_experiments.excitation import SCHEMA as EXCITATION_SCHEMA
from soft_arm_drivers.mocap.bridge_config import MOCAP_SCHEMA
from soft_arm_drivers.sim.emulated_rig import SCHEMA as EMULATOR_SCHEMA
from soft_arm_drivers.sim.plant_config import PLANT_SCHEMA
from soft_arm_model.config import ARM_SCHEMA
from soft_arm_model.parameters import allowed_interval
from soft_arm_ros.parameters import GRAPH_SCHEMA

SCHEMAS = {"arm": ARM_SCHEMA, "control": CONTROL_SCHEMA, "tasks": TASK_SCHEMA, "rig.motors": DRIVER_SCHEMA,
           "excitation": EXCITATION_SCHEMA, "mocap": MOCAP_SCHEMA, "emulator": EMULATOR_SCHEMA,
           "plant": PLANT_SCHEMA, "graph": GRAPH_SCHEMA}
ENTRIES = [(f"{ns}.{key}", entry) for ns, schema in SCHEMAS.items() for key, entry in schema.items()
           if entry[0] in ("float", "int") and entry[1] is not None and allowed_interval(entry[2])]


def test_the_interval_is_read_from_the_text():
    assert allowed_interval("a rate in (0, 1e6] N/s") == (0.0, 1e6, False, True)
    assert allowed_interval("a count in [1, 10000]") == (1.0, 10000.0, True, True)
    assert allowed_interval("a factor in [-0.5, 2)") == (-0.5, 2.0, True, False)
    assert allowed_interval("one of ['a', 'b']") is None
    assert len(ENTRIES) >= 60


@pytest.mark.parametrize("name,entry", ENTRIES, ids=[n for n, _ in ENTRIES])
def test_the_check_accepts_the_interval_its_text_states(name, entry):
    kind, check, allowed = entry
    low, high, low_in, high_in = allowed_interval(allowed)
    step = 1 if kind == "int" else max(abs(high - low) * 1e-9, 1e-12)
    value = int if kind == "int" else float
    assert check(value(low)) == low_in, f"{name}: {allowed} but the check says otherwise at {low}"
    assert check(value(high)) == high_in, f"{name}: {allowed} but the check says otherwise at {high}"
    assert not check(value(low) - step) and not check(value(high) + step), \
        f"{name}: accepts values outside {allowed}"
    middle = value((low + high) / 2) if math.isfinite(high) else value(low + 1)
    assert check(middle), f"{name}: refuses {middle}, inside {allowed}"
