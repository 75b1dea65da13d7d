"""sim_cell: the simulated cell as a ROS node: the profiler on TCP, the trigger MCU as a pyserial
socket:// URL, sim/ground_truth (relative, like every topic: a namespace separates cells), /diagnostics, and
faults switched by parameters at run time."""
from __future__ import annotations

import math
import sys

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.time import Time

from ..core.control.controller_limits import ControllerLimits
from ..core.model.gauge import Gauge, GaugeError
from ..core.model.render import DEFAULT_PROFILER
from ..core.wire.motoplus_protocol import units_to_metres
from ..resources import DEFAULT_GAUGE, config_path
from ..sim.arm import Arm, ArmModel
from ..sim.cell import SensorNoise, SimCell, Truth
from ..sim.motion import ArmMotion, ScriptedMotion, pose_from_vector, steps_from_lists
from ..sim.profiler_device import CORRUPT_MODES, ProfilerDevice, ProfilerFaults
from ..sim.robot_controller import DEFAULT_LIMITS_SI, TICK_S, ControllerFaults, RobotController
from ..sim.trigger_mcu import McuFaults, TriggerMcu
from .diagnostics import OK, WARN, diagnostic_array
from .messages import pose_stamped, twist_stamped
from .parameters import Param, declare_all, updated
from .process_tuning import SIM_SWITCH_INTERVAL_S
from .run import run_node

NODE_NAME = "sim_cell"
DEFAULT_POSE = [0.0, 0.0, 0.45, math.pi, 0.0, 0.0]  # looking straight down from 0.45 m (F z = -G z)


PARAMETERS = [
    Param("gauge_file", "", "Gauge YAML; empty: the shipped config/gauge_paper_n5.yaml.", read_only=True),
    Param("gauge_frame", "gauge", "frame_id of sim/ground_truth.", read_only=True),
    Param("host", "127.0.0.1", "Address the simulated devices listen on.", read_only=True),
    Param("profiler_port", 24692, "Profiler data port (0: any free port, see the log).", 0, 65535, read_only=True),
    Param("mcu_port", 24693, "Trigger MCU port, for serial_url socket://host:port (0: any free port).", 0, 65535,
          read_only=True),
    Param("trigger_rate", 83.333, "Robot signal rate, Hz (0: no internal clock); setting it (re)starts the clock.",
          0.0, 2000.0),
    Param("max_triggers", 0, "Stop triggering after this many from the clock's start (0: never).", 0, 2 ** 31 - 1),
    Param("profiler_pose", DEFAULT_POSE, "Nominal pose of F in G: x y z (m) and rotation vector (rad).",
          read_only=True),
    Param("sine_amplitude", [0.0] * 6, "Sine motion amplitude per axis x y z rx ry rz (m, rad).", read_only=True),
    Param("sine_frequency", [0.0] * 6, "Sine motion frequency per axis (Hz).", read_only=True),
    Param("step_times", [0.0], "Scripted steps: times (s after start); with step_axes and step_sizes.",
          read_only=True),
    Param("step_axes", [""], "Scripted steps: axis of each (x y z rx ry rz); '' for none.", read_only=True),
    Param("step_sizes", [0.0], "Scripted steps: size of each (m or rad).", read_only=True),
    Param("noise_std", 5e-6, "Profiler depth noise (m).", 0.0, 1e-3),
    Param("spike_fraction", 0.0, "Fraction of points replaced by glints.", 0.0, 0.5),
    Param("seed", 0, "Random seed of noise and faults.", 0, 2 ** 31 - 1, read_only=True),
    Param("drop_fraction", 0.0, "Fault: fraction of frames never sent.", 0.0, 1.0),
    Param("delay_ms", 0.0, "Fault: extra delay of every frame (ms).", 0.0, 10000.0),
    Param("corrupt_fraction", 0.0, "Fault: fraction of frames damaged.", 0.0, 1.0),
    Param("corrupt_mode", "mixed", f"Fault: how frames are damaged: {', '.join(CORRUPT_MODES)} or mixed."),
    Param("close_after_frames", 0, "Fault: close the profiler connection after every N frames (0: never).",
          0, 2 ** 31 - 1),
    Param("mcu_silent", False, "Fault: the MCU fires but writes and answers nothing."),
    Param("mcu_garbage_fraction", 0.0, "Fault: fraction of triggers preceded by a line of noise.", 0.0, 1.0),
    Param("mcu_close_after_triggers", 0, "Fault: drop the MCU's serial connection after every N triggers (0: never).",
          0, 2 ** 31 - 1),
    Param("mcu_reboot_after_triggers", 0, "Fault: the MCU restarts by itself (its clock and count from zero, READY) "
          "after every N triggers (0: never).", 0, 2 ** 31 - 1),
    Param("mcu_baudrate", 1000000, "MCU serial baud rate (line transmission time).", 9600, 4000000, read_only=True),
    Param("mcu_drift_ppm", 300.0, "MCU clock error (ppm).", -10000.0, 10000.0, read_only=True),
    Param("mcu_micros_start", 0, "MCU micros() at each boot (to exercise the 32-bit wrap).", 0, 2 ** 32 - 1,
          read_only=True),
    Param("robot_enabled", True, "Simulate the robot controller (MotoPlus protocol on robot_port).", read_only=True),
    Param("profiler_trigger", "robot", "What triggers the profiler when the robot is simulated: 'robot' (its "
          "per-period output, the paper's cell) or 'clock' (trigger_rate, e.g. a 1 kHz profiler beside a 250 Hz "
          "controller).", read_only=True),
    Param("robot_port", 11000, "Robot controller port (0: any free port).", 0, 65535, read_only=True),
    Param("control_period", 0.012, "Controller period (s): 0.012 (83.3 Hz) or 0.004 (250 Hz).", 0.004, 0.1,
          read_only=True),
    Param("arm_delay", 0.01061, "Command-to-motion delay (s): one 4 ms clock plus the paper's mean profile transfer "
          "time.", 0.0, 0.1, read_only=True),
    Param("gauge_in_base", [0.0] * 6, "The truth: pose of the gauge in the robot base frame (x y z m, rotation "
          "vector rad). The loop's nodes never see it (profile_pose_calibrate measures it).", read_only=True),
    Param("profiler_in_flange", [0.0] * 6, "The truth: pose of the profiler frame F on the robot's flange (x y z m, "
          "rotation vector rad).", read_only=True),
    Param("tool_in_flange", [0.0] * 6, "The tool the controller was told (its tool file): increments move this "
          "frame, and robot_state reports its pose.", read_only=True),
    Param("program_offset", [0.0] * 6, "The robot program's target offset from the start pose (m, rad); "
          "setting it is a step command."),
    Param("controller_max_step", DEFAULT_LIMITS_SI["max_step"], "The controller's own per-period clamp (m, rad): a "
          "HELLO may ask for less, never more.", read_only=True),
    Param("controller_max_offset", DEFAULT_LIMITS_SI["max_offset"], "The controller's own bound on the total offset "
          "(m, rad).", read_only=True),
    Param("controller_max_speed", DEFAULT_LIMITS_SI["max_speed"], "The controller's own speed limit (m/s, rad/s): also "
          "bounds each period's step.", read_only=True),
    Param("controller_max_watchdog", DEFAULT_LIMITS_SI["max_watchdog_s"], "The longest watchdog a HELLO may ask "
          "for (s).", 0.01, 10.0,
          read_only=True),
    Param("state_delay_ms", 0.0, "Fault: every STATE this much late (ms).", 0.0, 10000.0),
    Param("state_drop_fraction", 0.0, "Fault: fraction of STATE frames not sent.", 0.0, 1.0),
    Param("disconnect_after_periods", 0, "Fault: end the controller session after N armed periods (0: never).",
          0, 2 ** 31 - 1),
    Param("diagnostics_period", 1.0, "Period of /diagnostics (s).", 0.02, 60.0, read_only=True),
]

_FAULTS = {"drop_fraction", "delay_ms", "corrupt_fraction", "corrupt_mode", "close_after_frames",
           "mcu_silent", "mcu_garbage_fraction", "mcu_close_after_triggers", "mcu_reboot_after_triggers",
           "noise_std", "spike_fraction"}
_CLOCK = {"trigger_rate", "max_triggers"}
_ROBOT = {"program_offset", "state_delay_ms", "state_drop_fraction", "disconnect_after_periods"}


def check_values(values: dict) -> None:
    """The rules the descriptors cannot state; raises ValueError naming the parameter."""
    if values["profiler_trigger"] not in ("robot", "clock"):
        raise ValueError(f"profiler_trigger must be 'robot' or 'clock', not {values['profiler_trigger']!r}")
    if values["corrupt_mode"] not in CORRUPT_MODES + ("mixed",):
        raise ValueError(f"corrupt_mode {values['corrupt_mode']!r} is not one of {CORRUPT_MODES + ('mixed',)}")
    if len(values["program_offset"]) != 6:
        raise ValueError("program_offset needs six values")


def motion_from(values: dict) -> ScriptedMotion:
    rotation, translation = pose_from_vector(np.array(values["profiler_pose"], float))
    axes = [a for a in values["step_axes"]]
    times, sizes = list(values["step_times"]), list(values["step_sizes"])
    if axes == [""]:
        times, axes, sizes = [], [], []
    return ScriptedMotion(rotation, translation, steps_from_lists(times, axes, sizes),
                          np.array(values["sine_amplitude"], float), np.array(values["sine_frequency"], float))


class SimCellNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        v = self.values = declare_all(self, PARAMETERS)
        gauge_file = v["gauge_file"] or str(config_path(DEFAULT_GAUGE))
        self.gauge = Gauge.from_yaml(gauge_file)
        motion = motion_from(v)  # ValueError: main() reports it
        check_values(v)
        profiler = ProfilerDevice(v["host"], v["profiler_port"], faults=ProfilerFaults(), seed=v["seed"])
        mcu = TriggerMcu(v["host"], v["mcu_port"], baudrate=v["mcu_baudrate"], drift_ppm=v["mcu_drift_ppm"],
                         micros_start=v["mcu_micros_start"], faults=McuFaults(), seed=v["seed"] + 1)
        self.robot = None
        if v["robot_enabled"]:
            arm = Arm(ArmModel(delay_s=v["arm_delay"]))
            motion = ArmMotion(motion.rotation, motion.translation, arm, v["gauge_in_base"],
                               v["profiler_in_flange"], v["tool_in_flange"])
        self.cell = SimCell(self.gauge, motion, profiler, mcu, SensorNoise(), DEFAULT_PROFILER,
                            on_truth=self._publish_truth, seed=v["seed"] + 2)
        if v["robot_enabled"]:
            ticks = int(round(v["control_period"] / TICK_S))
            if abs(ticks * TICK_S - v["control_period"]) > 1e-9:
                raise ValueError(f"control_period {v['control_period']} is not a multiple of the 4 ms clock")
            on_period = self.cell.robot_signal if v["profiler_trigger"] == "robot" else None
            limits = ControllerLimits.from_si(v["controller_max_step"], v["controller_max_offset"],
                                              v["controller_max_speed"], v["controller_max_watchdog"])
            self.robot = RobotController(arm, on_period, v["host"], v["robot_port"], ticks,
                                         ControllerFaults(), seed=v["seed"] + 3, on_applied=self._publish_applied,
                                         limits=limits, pose_of=motion.controller_pose)
        self._apply_faults(v)
        self.truth_pub = self.create_publisher(PoseStamped, "sim/ground_truth", 100)
        self.applied_pub = self.create_publisher(TwistStamped, "sim/robot_increment", 100)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.cell.start()
        if self.robot is not None:
            self.robot.start()
        if self._clock_triggers(v) and v["trigger_rate"] > 0:
            self.cell.run_clock(v["trigger_rate"], v["max_triggers"])
        self.create_timer(v["diagnostics_period"], self._publish_diagnostics)
        clock = (f"robot controller on tcp://{v['host']}:{self.robot.port}, {1 / v['control_period']:.1f} Hz; "
                 if self.robot is not None else "")
        clock += (f"internal trigger clock {v['trigger_rate']:.3f} Hz" if self._clock_triggers(v)
                  else "the controller triggers the profiler")
        self.get_logger().info(f"profiler on tcp://{profiler.server.host}:{profiler.port}, trigger MCU on {mcu.url}, "
                               f"{clock}, gauge '{self.gauge.name}'")

    def _clock_triggers(self, v: dict) -> bool:
        return self.robot is None or v["profiler_trigger"] == "clock"

    def _apply_faults(self, v: dict, changed: set[str] | None = None) -> None:
        """Faults and noise from parameter values; `changed` (None: all) limits one-shot faults to the
        parameters actually set, so changing another parameter does not fire them again."""
        f = self.cell.profiler.faults
        f.drop_fraction, f.delay_s = v["drop_fraction"], v["delay_ms"] * 1e-3
        f.corrupt_fraction, f.corrupt_mode = v["corrupt_fraction"], v["corrupt_mode"]
        f.close_after_frames = v["close_after_frames"]
        m = self.cell.mcu.faults
        m.silent, m.garbage_fraction = v["mcu_silent"], v["mcu_garbage_fraction"]
        m.close_after_triggers, m.reboot_after_triggers = v["mcu_close_after_triggers"], v["mcu_reboot_after_triggers"]
        self.cell.noise.noise_std, self.cell.noise.spike_fraction = v["noise_std"], v["spike_fraction"]
        if self.robot is not None:
            r = self.robot.faults
            r.state_delay_s, r.state_drop_fraction = v["state_delay_ms"] * 1e-3, v["state_drop_fraction"]
            if changed is None or "disconnect_after_periods" in changed:
                r.disconnect_after_periods = v["disconnect_after_periods"]
            self.robot.program = np.array(v["program_offset"], dtype=float)

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        names = {p.name for p in parameters}
        if names - _FAULTS - _CLOCK - _ROBOT:
            return SetParametersResult(successful=False,
                                       reason="only faults, noise, the clock and the program change at run time")
        try:
            values, _ = updated(self.values, parameters, check_values)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.values = values
        self._apply_faults(values, names)
        if names & _CLOCK and self._clock_triggers(values):
            self.cell.run_clock(values["trigger_rate"], values["max_triggers"])
        return SetParametersResult(successful=True)

    def _publish_truth(self, truth: Truth) -> None:
        if not self.truth_pub.get_subscription_count():  # a third of the clock thread's time at 1 kHz
            return
        stamp = Time(nanoseconds=truth.time_ns).to_msg()
        self.truth_pub.publish(pose_stamped(truth.rotation, truth.translation, stamp, self.values["gauge_frame"]))

    def _publish_applied(self, wall_time: float, units: tuple[int, ...]) -> None:
        """The increment the controller applied this armed period (m, rad): what the robot was really told."""
        if not self.applied_pub.get_subscription_count():
            return
        stamp = Time(nanoseconds=int(wall_time * 1e9)).to_msg()
        self.applied_pub.publish(twist_stamped(units_to_metres(units), stamp, "base"))

    def _publish_diagnostics(self) -> None:
        p, m, c = self.cell.profiler, self.cell.mcu, self.cell
        faults = {k: self.values[k] for k in sorted(_FAULTS)}
        active = {k: val for k, val in faults.items() if val and k not in ("noise_std", "corrupt_mode")}
        level, message = (WARN, f"faults injected: {active}") if active else (OK, "simulating")
        values = {"triggers": p.trigger_count, "mcu_seq": m.seq, "mcu_armed": m.armed, "signals": c.signals,
                  "late_signals": c.late_signals, "frames_sent": p.frames_sent, "frames_dropped": p.frames_dropped,
                  "frames_corrupted": p.frames_corrupted, "frames_unsent": p.frames_unsent,
                  "profiler_connections": p.server.connections, "profiler_closes": p.closes,
                  "mcu_connections": m.server.connections, "mcu_lines": m.lines_sent,
                  "mcu_closes": m.closes, "mcu_reboots": m.reboots,
                  "profiler_port": p.port, "mcu_url": m.url, **faults, **c.frame_latency.report()}
        if self.robot is not None:
            values.update(self.robot.report())
        self.diagnostics_pub.publish(diagnostic_array(self, "cell",
                                                      "sim_cell", level, message, values))

    def destroy_node(self) -> None:
        if self.robot is not None:
            self.robot.close()
        self.cell.close()
        super().destroy_node()


def main(args=None) -> int:
    return run_node(SimCellNode, NODE_NAME, args, startup_errors=(GaugeError, ValueError, OSError),
                    switch_interval=SIM_SWITCH_INTERVAL_S)


if __name__ == "__main__":
    sys.exit(main())
