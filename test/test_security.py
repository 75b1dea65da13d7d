"""What an attacker on the cell network could reach: listeners on loopback unless configured, one robot
peer, DDS discovery kept on the machine by the bringup, and no input ever evaluated."""
from __future__ import annotations

import re

import pytest

from profile_pose_ros.nodes import sim_cell
from profile_pose_ros.sim.arm import Arm
from profile_pose_ros.sim.profiler_device import ProfilerDevice
from profile_pose_ros.sim.robot_controller import RobotController
from profile_pose_ros.sim.trigger_mcu import TriggerMcu
from profile_pose_ros.tools.bringup import discovery_range

from conftest import ROOT


def test_every_simulated_device_listens_on_loopback_by_default() -> None:
    devices = [ProfilerDevice(), TriggerMcu(), RobotController(Arm()).start()]
    try:
        for device in devices:
            host = device.host if isinstance(device, RobotController) else device.server.host
            assert host == "127.0.0.1", type(device).__name__
    finally:
        for device in devices:
            device.close()
    assert next(p for p in sim_cell.PARAMETERS if p.name == "host").default == "127.0.0.1"


def test_the_bringup_keeps_discovery_on_this_machine_unless_told() -> None:
    assert discovery_range(None, {}) == "LOCALHOST"
    assert discovery_range(None, {"ROS_AUTOMATIC_DISCOVERY_RANGE": "subnet"}) == "SUBNET"
    assert discovery_range("OFF", {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}) == "OFF"
    with pytest.raises(ValueError, match="discovery range"):
        discovery_range("everywhere", {})


def test_no_input_is_ever_evaluated() -> None:
    """YAML only through safe_load, no pickle, no eval/exec anywhere in the package."""
    forbidden = re.compile(r"yaml\.load\(|yaml\.unsafe_load|yaml\.Loader|\bpickle\b|\beval\(|\bexec\(|marshal\.loads")
    offenders = [f"{path.relative_to(ROOT)}:{n}" for path in sorted((ROOT / "profile_pose_ros").rglob("*.py"))
                 for n, line in enumerate(path.read_text().splitlines(), 1) if forbidden.search(line)]
    assert not offenders, offenders
