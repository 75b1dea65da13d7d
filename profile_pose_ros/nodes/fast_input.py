"""A high-rate subscription served directly, not through the executor's generic wait.

rclpy's executor rebuilds a wait set over every timer, service, guard condition and event handler of the
node on each wake-up; at 1 kHz that costs about as much as estimating the pose. A FastInput waits on the
one subscription and drains it, so a profile costs one wait and one take; `spin` runs the executor for
everything else (timers, parameter services, QoS events) at a housekeeping period (50 ms: each executor
pass cost ~0.3 ms of CPU, 3 % of a core at the former 10 ms). A deadline that must be kept (the
compensator's watchdog) is a `tick` of the FastInput instead. The subscription is in
a callback group the executor never schedules, so the two never compete for a message. Single-threaded:
two threads waiting in rcl at once would contend for the GIL.
"""
from __future__ import annotations

import math
import time
from typing import Callable

from rclpy._rclpy_pybind11 import RCLError
from rclpy.callback_groups import CallbackGroup
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.subscription import Subscription

from .run import StopRequest


class ServedDirectly(CallbackGroup):
    """A callback group whose entities the executor leaves alone: a FastInput serves them."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


class FastInput:
    def __init__(self, subscription: Subscription, context, callback: Callable, guard=None,
                 tick: Callable[[], float] | None = None) -> None:
        """guard: an optional GuardCondition (in a ServedDirectly group) whose callback runs here when
        another thread triggers it, as promptly as a message. tick: an optional deadline check (the
        compensator's watchdog), run here when its time comes; it returns the wall-clock time at which it
        wants to run next, so a node that stays healthy is not woken for it at a fixed rate."""
        self.subscription = subscription
        self.callback = callback
        self.guard = guard
        self.tick = tick
        self.tick_due = time.time() if tick is not None else math.inf
        self.wait_set = _rclpy.WaitSet(1, 0 if guard is None else 1, 0, 0, 0, 0, context.handle)

    def pump(self, timeout_sec: float) -> int:
        """Wait up to timeout_sec (or the tick's deadline) for messages, then handle every one queued and
        the tick if due; returns how many messages."""
        timeout_sec = min(timeout_sec, self.tick_due - time.time())
        handle = self.subscription.handle
        with handle:
            self.wait_set.clear_entities()
            self.wait_set.add_subscription(handle)
            if self.guard is not None:
                with self.guard.handle:
                    self.wait_set.add_guard_condition(self.guard.handle)
            self.wait_set.wait(int(max(timeout_sec, 0.0) * 1e9))
            message_ready = self.wait_set.is_ready("subscription", 0)
            guard_ready = self.guard is not None and self.wait_set.is_ready("guard_condition", 0)
        if guard_ready:
            self.guard.callback()
        handled = 0
        while message_ready:
            with handle:
                taken = handle.take_message(self.subscription.msg_type, self.subscription.raw)
            if taken is None:
                break
            self.callback(taken[0])
            handled += 1
        if time.time() >= self.tick_due:
            self.tick_due = self.tick()
        return handled


def spin(executor, fast_input: FastInput, stop: StopRequest, housekeeping_period: float = 0.05) -> None:
    """Serve fast_input continuously and the executor's other work every housekeeping_period, until
    `stop` (Ctrl-C) or shutdown."""
    context = executor.context
    due = time.monotonic()
    while context.ok() and not stop.is_set():
        try:
            fast_input.pump(max(0.0, due - time.monotonic()))
            if time.monotonic() >= due:
                executor.spin_once(timeout_sec=0.0)
                due = time.monotonic() + housekeeping_period
        except RCLError:
            if context.ok():
                raise
            return  # Ctrl-C shut the context down between the check and the wait: a normal exit
