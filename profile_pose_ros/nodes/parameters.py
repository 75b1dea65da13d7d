"""Declaring parameters with descriptors (description, range), so `ros2 param describe` and the
generated parameter reference say the same thing as the code."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, TypeVar

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

T = TypeVar("T")


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    description: str
    low: float | int | None = None
    high: float | int | None = None
    read_only: bool = False

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(description=self.description, read_only=self.read_only)
        if self.low is not None and not isinstance(self.default, bool):
            if isinstance(self.default, int):
                d.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high), step=1)]
            else:
                d.floating_point_range = [FloatingPointRange(from_value=float(self.low), to_value=float(self.high),
                                                             step=0.0)]
        return d


def defaults(params: list[Param]) -> dict[str, Any]:
    """Every parameter's default by name: what a node runs with when nothing overrides it."""
    return {p.name: p.default for p in params}


def declare_all(node: Node, params: list[Param]) -> dict[str, Any]:
    """Declare every parameter and return their (possibly overridden) values by name. An empty list
    default declares a string array (rclpy would guess a byte array) that is unset until given."""
    values = {}
    for p in params:
        default = Parameter.Type.STRING_ARRAY if isinstance(p.default, list) and not p.default else p.default
        node.declare_parameter(p.name, default, p.descriptor())
        try:
            values[p.name] = node.get_parameter(p.name).value
        except ParameterUninitializedException:
            values[p.name] = []
    return values


def updated(current: dict, parameters, build: Callable[[dict], T]) -> tuple[dict, T]:
    """`current` with the changed parameters applied, and what `build` makes of them; build raises
    ValueError or TypeError for an invalid combination, and then nothing changes."""
    values = dict(current)
    values.update({p.name: p.value for p in parameters})
    return values, build(values)
