"""profiler_driver: the profiler (sim_cell over TCP, or a Keyence LJ-X8000 through libljxacom.so) ->
`profile` (PointCloud2 as DESIGN.md fixes it, sensor-data QoS), stamped with the trigger's host time.

Thin glue around devices.profiler_link.ProfilerLink, which owns the connection thread; this node only
declares parameters, publishes what the link emits, and reports /diagnostics.
"""
from __future__ import annotations

import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2

from ..core.timing.latency_window import LatencyWindow
from ..core.wire.profile_cdr import encode_xyz_table_cdr
from ..core.wire.profiler_protocol import ProfileFrame
from ..devices.ljx import LjxProfileSource
from ..devices.profile_source import SimProfileSource
from ..devices.profiler_link import STREAMING, LinkSettings, ProfilerLink
from ..devices.trigger_link import TriggerLink
from .diagnostics import ERROR, OK, WARN, diagnostic_array
from .local_topics import LocalTopics, LoopOutput
from .parameters import Param, declare_all
from .process_tuning import LOOP_SWITCH_INTERVAL_S, REALTIME_PARAMETERS
from .run import run_node

NODE_NAME = "profiler_driver"
BACKENDS = ("sim", "ljx")


PARAMETERS = [
    Param("backend", "sim", "Profiler backend: 'sim' (sim_cell's TCP protocol) or 'ljx' (Keyence LJ-X8000 "
          "through libljxacom.so).", read_only=True),
    Param("host", "127.0.0.1", "Profiler controller address.", read_only=True),
    Param("port", 24692, "Profiler data port (LJ-X8000: high-speed data port, default 24692).", 1, 65535,
          read_only=True),
    Param("command_port", 24691, "ljx: the controller's command port.", 1, 65535, read_only=True),
    Param("library_path", "libljxacom.so", "ljx: path of Keyence's Linux communication library.", read_only=True),
    Param("device_id", 0, "ljx: the library's device slot (0-5).", 0, 5, read_only=True),
    Param("serial_url", "", "Trigger MCU: a serial device or pyserial URL (socket://127.0.0.1:24693 for "
          "sim_cell); empty: no MCU, profiles are stamped with their receive time.", read_only=True),
    Param("baudrate", 1000000, "Trigger MCU baud rate (also used to subtract each line's transmission time).",
          9600, 4000000, read_only=True),
    Param("stamp_source", "trigger", "'trigger': the trigger's host time via the MCU clock (a profile without "
          "one is dropped and counted, never stamped otherwise); 'receive': arrival time, for a cell without an "
          "MCU (a stamp that is late by the device's transfer time).", read_only=True),
    Param("trigger_latency", 0.0, "Delay from a trigger's line leaving the MCU to its arrival here, beyond "
          "transmission (s): a USB adapter's latency; measure it once per cell. -1: half the fastest PING round "
          "trip (assumes a symmetric link).", -1.0, 0.05, read_only=True),
    Param("sync_timeout", 0.02, "How long a profile may wait for its trigger line (s).", 0.0, 0.1,
          read_only=True),
    Param("max_stamp_error", 2e-4, "A profile is published with its trigger's time only while the MCU clock map "
          "bounds that time this closely, either way (s): about the fastest recent PING round trip, plus the drift "
          "estimate's error carried over the seconds since. Others are dropped and counted (a map still settling "
          "moves between triggers). A USB serial adapter needs its round trip here.",
          1e-5, 0.05, read_only=True),
    Param("frame_id", "profiler", "frame_id of the published profiles (the profiler frame F).", read_only=True),
    Param("max_input_age", 1.0, "Reconnect when the device sends nothing for this long (s); 0 disables "
          "(ljx in external-trigger mode sends nothing between triggers).", 0.0, 60.0, read_only=True),
    Param("reconnect_min", 0.1, "First reconnect delay (s); doubles up to reconnect_max.", 0.01, 10.0,
          read_only=True),
    Param("reconnect_max", 0.5, "Longest reconnect delay (s).", 0.01, 60.0, read_only=True),
    Param("profile_decimation", 1, "Publish every this many profiles on `profile` (1: all). For profiler_estimator, "
          "where the estimate is made in this process and `profile` serves only a recorder or a viewer; a separate "
          "pose_estimator takes only the profiles published.", 1, 1000, read_only=True),
    Param("diagnostics_period", 1.0, "Period of /diagnostics (s).", 0.02, 60.0, read_only=True),
    *REALTIME_PARAMETERS,
]


def trigger_stamps(v: dict) -> bool:
    """Whether profiles carry their trigger's time (an MCU configured, stamp_source 'trigger')."""
    return bool(v["serial_url"]) and v["stamp_source"] == "trigger"


def make_source(v: dict):
    if v["backend"] == "sim":
        return SimProfileSource(v["host"], v["port"])
    if v["backend"] == "ljx":
        return LjxProfileSource(v["library_path"], v["host"], v["command_port"], v["port"], v["device_id"])
    raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, not {v['backend']!r}")


class ProfilerDriverNode(Node):
    def __init__(self, local: LocalTopics | None = None, **kwargs) -> None:
        """local: the composed nodes' topics (cell_container), else None."""
        super().__init__(NODE_NAME, **kwargs)
        v = self.values = declare_all(self, PARAMETERS)
        source = make_source(v)
        trigger = None
        if v["serial_url"]:
            trigger = TriggerLink(v["serial_url"], v["baudrate"], on_trigger=lambda *_: None,
                                  on_resync_needed=lambda _: None, trigger_latency=v["trigger_latency"])
        settings = LinkSettings(stamp_source=v["stamp_source"], max_input_age=v["max_input_age"],
                                backoff_min=v["reconnect_min"], backoff_max=max(v["reconnect_min"],
                                                                                v["reconnect_max"]),
                                sync_timeout=v["sync_timeout"], max_stamp_error=v["max_stamp_error"])
        self.profile_pub = self.create_publisher(PointCloud2, "profile", qos_profile_sensor_data)
        self.profile_out = LoopOutput(self.profile_pub, local, self.get_logger())
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        logger = self.get_logger()
        self._read = 0  # profiles emitted: every profile_decimation-th is published
        self._newest: bytes | None = None  # composed: the newest profile of the current read, to hand over
        self.superseded = 0  # composed: profiles a newer one replaced before the estimator took it
        self.link = ProfilerLink(source, trigger, settings, self._emit,
                                 log=lambda text: logger.warn(text, throttle_duration_sec=1.0),
                                 batch_end=self._hand_over_newest if local is not None else None)
        self._window = (time.monotonic(), 0, 0, 0, 0)
        self.latency = LatencyWindow("trigger_to_profile_ms")  # the stamp (trigger or receive time) -> published
        self.create_timer(v["diagnostics_period"], self._publish_diagnostics)
        self.link.start()
        logger.info(f"profiler {source.name}, trigger MCU {v['serial_url'] or 'none'}, "
                    f"stamps from {v['stamp_source']}")

    def _emit(self, frame: ProfileFrame, stamp: float, synced: bool) -> None:
        """Runs on the link's thread. Published serialized (core/wire/profile_cdr.py): building the PointCloud2
        for rclpy to convert back was a third of this node's time per profile; the point table comes
        straight from the device's counts (ProfileFrame.xyz_table)."""
        sec, nanosec = divmod(int(round(stamp * 1e9)), 1_000_000_000)
        serialized = encode_xyz_table_cdr(frame.xyz_table(), sec, nanosec, self.values["frame_id"])
        self._read += 1
        if self._read % self.values["profile_decimation"] == 0:
            self.profile_out.publish(serialized)
        self.latency.add(time.time() - stamp)
        if self.profile_out.local is not None:
            self.superseded += self._newest is not None
            self._newest = serialized

    def _hand_over_newest(self) -> None:
        """Composed, the link thread after each read: the estimate, the correction and the bridge's store
        follow here, for the newest profile only (local_topics.py)."""
        newest, self._newest = self._newest, None
        if newest is not None:
            self.profile_out.hand_over(newest)

    def _publish_diagnostics(self) -> None:
        link, c, trigger = self.link, self.link.counters, self.link.trigger
        now = time.monotonic()
        start, published0, dropped0, bad0, unconfirmed0 = self._window
        self._window = (now, c.published, c.dropped, c.bad_frames, c.unconfirmed)
        elapsed = max(now - start, 1e-9)
        rate = (c.published - published0) / elapsed
        new_drops, new_bad = c.dropped - dropped0, c.bad_frames - bad0
        if link.state != STREAMING:
            level, message = ERROR, f"{link.state}: {link.last_error or 'no connection yet'}"
        elif trigger is not None and not trigger.ok and trigger_stamps(self.values):
            level, message = ERROR, (f"trigger MCU {trigger.state} ({trigger.last_error or 'no line yet'}): profiles "
                                     "have no trigger time and are not published")
        elif trigger is None or not trigger_stamps(self.values):
            level, message = WARN, f"profiles stamped with their receive time ({rate:.1f} Hz): no trigger MCU in use"
        elif c.unconfirmed > unconfirmed0:
            level, message = WARN, (f"{c.unconfirmed - unconfirmed0} profiles dropped: their trigger time is bounded "
                                    f"to {trigger.clock.error_bound * 1e3:.2f} ms, not max_stamp_error "
                                    f"{self.values['max_stamp_error'] * 1e3:.2f} ms")
        elif new_drops or new_bad:
            level, message = WARN, f"{new_drops} profiles dropped, {new_bad} bad frames in {elapsed:.1f} s"
        elif rate == 0:
            level, message = WARN, "connected, no profiles (no triggers?)"
        else:
            level, message = OK, f"streaming at {rate:.1f} Hz"
        values = {"state": link.state, "rate_hz": rate, "profiles_published": c.published,
                  "profiles_dropped": c.dropped, "bad_frames": c.bad_frames, "unsynced_profiles": c.unsynced,
                  "dropped_late_trigger_line": c.late_lines,
                  "discarded_while_pairing": c.discarded, "dropped_unconfirmed_stamp": c.unconfirmed,
                  "dropped_out_of_order": c.out_of_order, "dropped_untimed": c.untimed, "connections": c.connections, "pairings": c.resyncs,
                  "pairings_unacknowledged": c.unacknowledged_pairings,
                  "pairings_disagreeing": link.matcher.disagreements,
                  "last_error": link.last_error or "none", "source": link.source.name,
                  **({"superseded_before_estimation": self.superseded} if self.profile_out.local is not None else {}),
                  **self.latency.report()}
        if trigger is not None:
            jitter_median, jitter_max = trigger.clock.residual_stats()
            values.update({"trigger_state": trigger.state, "trigger_lines": trigger.lines,
                           "trigger_bad_lines": trigger.bad_lines, "triggers_lost": trigger.triggers_lost,
                           "trigger_port_reopens": trigger.reopens, "trigger_error": trigger.last_error or "none",
                           "trigger_count_offset": link.matcher.offset if link.matcher.offset is not None else "none",
                           "mcu_clock_drift_ppm": trigger.clock.drift_ppm,
                           "mcu_clock": "converged" if trigger.clock.converged else "converging",
                           "mcu_clock_resets": trigger.clock.resets, "mcu_clock_last_reset": trigger.clock.last_reset,
                           "stamp_error_bound_us": trigger.clock.error_bound * 1e6,
                           "serial_latency_us": trigger.latency * 1e6,
                           "fastest_ping_round_trip_us": trigger.fastest_round_trip * 1e6,
                           "kernel_timestamps": trigger.kernel_timestamps,
                           "sync_jitter_median_us": jitter_median * 1e6, "sync_jitter_max_us": jitter_max * 1e6})
        self.diagnostics_pub.publish(diagnostic_array(self, "profiler", link.source.name,
                                                      level, message, values))

    def destroy_node(self) -> None:
        self.link.stop()
        super().destroy_node()


def main(args=None) -> int:
    return run_node(ProfilerDriverNode, NODE_NAME, args, startup_errors=(ValueError, OSError),
                    switch_interval=LOOP_SWITCH_INTERVAL_S)


if __name__ == "__main__":
    sys.exit(main())
