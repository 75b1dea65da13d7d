"""Shipped parameter files and generated docs stay in step with the declared parameters."""
import pytest
import yaml

from conftest import ROOT
from profile_pose_ros.nodes import pose_estimator
from profile_pose_ros.tools.param_docs import generated, node_modules


def test_parameter_reference_is_generated_from_descriptors():
    assert (ROOT / "docs" / "parameters.md").read_text() == generated(), (
        "regenerate: python -m profile_pose_ros.tools.param_docs > docs/parameters.md")


def assert_declared_and_in_range(module, values: dict) -> None:
    """Each value names a parameter the node declares, of its type, within its range."""
    declared = {p.name: p for p in module.PARAMETERS}
    for key, value in values.items():
        assert key in declared, (module.NODE_NAME, key)
        p = declared[key]
        assert type(value) is type(p.default) or (isinstance(p.default, list) and isinstance(value, list)), key
        if p.low is not None:
            assert p.low <= value <= p.high, (module.NODE_NAME, key)


@pytest.mark.parametrize("module", node_modules(), ids=lambda m: m.NODE_NAME)
def test_params_file_names_exactly_the_declared_parameters_within_range(module):
    document = yaml.safe_load((ROOT / "config" / f"{module.NODE_NAME}.yaml").read_text())
    values = document[module.NODE_NAME]["ros__parameters"]
    assert set(values) == {p.name for p in module.PARAMETERS}
    assert_declared_and_in_range(module, values)


def test_pose_estimator_params_file_is_a_valid_combination():
    values = yaml.safe_load((ROOT / "config" / "pose_estimator.yaml").read_text())["pose_estimator"]["ros__parameters"]
    pose_estimator.options_from(values)


@pytest.mark.parametrize("name", ["cell.yaml", "hardware.yaml"])
def test_cell_parameter_files_are_generated_and_every_block_is_valid(name):
    from profile_pose_ros.tools import config_files

    text = (ROOT / "config" / name).read_text()
    assert text == {"cell.yaml": config_files.cell_file, "hardware.yaml": config_files.hardware_file}[name](), (
        "regenerate: python -m profile_pose_ros.tools.config_files")
    document = yaml.safe_load(text)
    assert set(document["/**"]["ros__parameters"]) == set(config_files.FRAMES)
    modules = {m.NODE_NAME: m for m in node_modules()}
    blocks = {key.removeprefix("/**/"): block["ros__parameters"] for key, block in document.items() if key != "/**"}
    assert {"profiler_driver", "pose_estimator", "pd_compensator", "motoplus_bridge"} <= set(blocks)
    assert ("sim_cell" in blocks) == (name == "cell.yaml")
    for node, values in blocks.items():
        assert set(values) == {p.name for p in modules[node].PARAMETERS} - set(config_files.FRAMES), node
        assert_declared_and_in_range(modules[node], values)
    pose_estimator.options_from({**blocks["pose_estimator"], **document["/**"]["ros__parameters"]})


def test_the_simulated_cells_loop_timing_and_clamps_are_the_experiments() -> None:
    """cell.yaml (the bringup) runs the modal law as profile_pose experiment does at 12 ms: the same loop
    delay for the bridge's answer_wait, and per-period steps that are the speed limits over a period."""
    from profile_pose_ros.nodes.motoplus_bridge import PARAMETERS as BRIDGE
    from profile_pose_ros.nodes.parameters import defaults
    from profile_pose_ros.nodes.sim_cell import PARAMETERS as SIM
    from profile_pose_ros.tools.experiment import bridge_for, loop_delay, period_steps

    blocks = {key.split("/")[-1]: value["ros__parameters"]
              for key, value in yaml.safe_load((ROOT / "config" / "cell.yaml").read_text()).items()}
    compensator, bridge, sim = blocks["pd_compensator"], blocks["motoplus_bridge"], blocks["sim_cell"]
    period = bridge["period"]
    assert compensator["control_period"] == period == sim["control_period"]
    answer_wait = bridge.get("answer_wait", defaults(BRIDGE)["answer_wait"])
    assert answer_wait == bridge_for(compensator).get("answer_wait", answer_wait)
    assert compensator["loop_delay"] == pytest.approx(loop_delay(period, answer_wait), abs=1e-6)
    assert bridge["max_step"] == pytest.approx(period_steps(compensator["max_speed"], period).tolist())
    speed = defaults(SIM)["controller_max_speed"]
    assert sim["controller_max_step"] == pytest.approx(period_steps(speed, period).tolist())
    assert set(defaults(BRIDGE)) >= set(bridge)


@pytest.mark.parametrize("layer, nodes", [("fast_steps.yaml", {"pd_compensator", "motoplus_bridge"}),
                                          ("fast_steps_250hz.yaml", {"pd_compensator"})])
def test_the_fast_steps_layers_set_only_declared_parameters_within_range(layer: str, nodes: set[str]):
    """config/fast_steps.yaml (and at 250 Hz fast_steps_250hz.yaml) is layered over cell.yaml with
    --params-file: a misspelt key there would be ignored by the node, and the cell would run the slow law
    without a word."""
    modules = {m.NODE_NAME: m for m in node_modules()}
    document = yaml.safe_load((ROOT / "config" / layer).read_text())
    assert nodes <= set(document)
    for node, block in document.items():
        assert_declared_and_in_range(modules[node], block["ros__parameters"])
