"""One DiagnosticStatus per node on /diagnostics, in the form diagnostic_aggregator expects."""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

OK, WARN, ERROR, STALE = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR, DiagnosticStatus.STALE
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}


def diagnostic_array(node, what: str, hardware_id: str, level: int, message: str, values: dict) -> DiagnosticArray:
    """Named `<namespace>/<node>: <what>` (no leading slash; just `<node>: <what>` outside a namespace), so
    several cells on one /diagnostics stay apart."""
    name = f"{node.get_fully_qualified_name().lstrip('/')}: {what}"
    stamp = node.get_clock().now().to_msg()
    status = DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id)
    scheduling = getattr(node, "scheduling", None)  # run.py: a loop node's realtime_priority outcome
    if scheduling is not None:
        values = {**values, "scheduling": scheduling}
    status.values = [KeyValue(key=str(k), value=_text(v)) for k, v in values.items()]
    array = DiagnosticArray()
    array.header.stamp = stamp
    array.status = [status]
    return array


def _text(value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


class RefusalCounter:
    """For a Node that refuses inputs: `self.refused` counts them by reason (its /diagnostics show the
    counts), and each is logged, at most once a second per call site."""

    refused: dict[str, int]

    def _refuse(self, why: str, text: str) -> None:
        self.refused[why] += 1
        self.get_logger().error(text, throttle_duration_sec=1.0)
