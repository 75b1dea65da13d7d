"""Every writable parameter takes effect at run time: set through the parameter service (as `ros2 param
set` does), it is accepted and the node works with the new value from then on (each node reads its
working values afresh where it uses them). Whatever a node reads only at start is declared read-only, so
`ros2 param set` says so instead of reporting a success that changes nothing."""
from __future__ import annotations

import pytest
from rclpy.parameter import Parameter

from profile_pose_ros.nodes import motoplus_bridge, pd_compensator, pose_estimator, profiler_driver
from profile_pose_ros.nodes import sim_cell
from profile_pose_ros.tools.graph import parameter_client

NODES = {
    "profiler_driver": (profiler_driver, lambda ctx: profiler_driver.ProfilerDriverNode(
        context=ctx, parameter_overrides=[Parameter("port", value=9)])),
    "pose_estimator": (pose_estimator, lambda ctx: pose_estimator.PoseEstimatorNode(context=ctx)),
    "pd_compensator": (pd_compensator, lambda ctx: pd_compensator.PdCompensatorNode(context=ctx)),
    "motoplus_bridge": (motoplus_bridge, lambda ctx: motoplus_bridge.MotoPlusBridgeNode(
        context=ctx, parameter_overrides=[Parameter("port", value=9)])),
    "sim_cell": (sim_cell, lambda ctx: sim_cell.SimCellNode(context=ctx, parameter_overrides=[
        Parameter(name, value=0) for name in ("profiler_port", "mcu_port", "robot_port")])),
}
# values that are valid and differ from the defaults, where the type alone does not give one
CHANGED = {"refine_weighting": "uniform", "refine_model": "dense", "corrupt_mode": "flip", "profiler_frame": "",
           "program_offset": [1e-4, 0.0, 0.0, 0.0, 0.0, 0.0]}


def changed(param, current):
    if param.name in CHANGED:
        return CHANGED[param.name]
    if isinstance(current, bool):
        return not current
    if isinstance(current, str):
        return current + "_b"
    if not isinstance(current, (int, float)):  # a list, or rclpy's array('d')
        return [0.5 * v if v else 0.01 for v in current]
    if param.low is not None:
        value = param.low + 0.37 * (param.high - param.low)
        return int(value) if isinstance(current, int) else float(value)
    return current + 1 if isinstance(current, int) else 0.5 * current


def node_and_setter(ros, name: str):
    """The node, its PARAMETERS, and a function that sets one of them through the parameter service."""
    module, factory = NODES[name]
    node = ros.add(factory(ros.context))
    # its services available and its replies matched (RuntimeError otherwise): a reply DDS drops while its path
    # is still being matched would fail the first set
    client = parameter_client(ros.node(f"{name}_setter"), node.get_name(), ros.spin_until, 10.0)

    def set_one(param_name: str, value):
        future = client.set_parameters([Parameter(param_name, value=value)])
        assert ros.spin_until(future.done, 10.0), param_name
        return future.result().results[0]
    return node, module.PARAMETERS, set_one


@pytest.mark.parametrize("name", sorted(NODES))
def test_every_writable_parameter_takes_effect_at_run_time(ros, name) -> None:
    node, parameters, set_one = node_and_setter(ros, name)
    for param in [p for p in parameters if not p.read_only]:
        value = changed(param, node.values[param.name])
        current = node.values[param.name]
        assert value != (list(current) if isinstance(value, list) else current), param.name
        result = set_one(param.name, value)
        assert result.successful, (param.name, value, result.reason)
        applied = node.values[param.name]
        assert (list(applied) if isinstance(value, list) else applied) == value, (param.name, "accepted, not applied")


@pytest.mark.parametrize("name", sorted(NODES))
def test_a_read_only_parameter_is_refused_at_run_time(ros, name) -> None:
    node, parameters, set_one = node_and_setter(ros, name)
    param = next(p for p in parameters if p.read_only)
    assert not set_one(param.name, changed(param, node.values[param.name])).successful  # ros2 param set says so
