"""High-rate subscriptions served directly, not through the executor's generic wait: the package's only
use of rclpy's private API (its C extension's WaitSet and take_message), kept here with its reason, and
held to rclpy by test_rclpy_private_api.py, which fails by name when an upgrade changes any of it.

rclpy's executor rebuilds a wait set over every timer, service, guard condition and event handler of the
node on each wake-up; at 1 kHz that costs about as much as estimating the pose (the node's CPU share fell by
a fifth without it: docs/performance.md). A DirectInput waits on its subscriptions (a node's one high-rate
input; every topic the recorder records) and drains each that is ready, so a profile costs one wait and
one take; `spin` runs the executor for everything else (timers, parameter services, QoS events) at a
housekeeping period (50 ms: an executor pass costs a fraction of a millisecond of CPU, too much to pay a
hundred times a second for work that can wait). A deadline that must be kept (the
compensator's watchdog) is a `tick` of the DirectInput instead. The subscriptions are in
a callback group the executor never schedules, so the two never compete for a message. Single-threaded:
two threads waiting in rcl at once would contend for the GIL.
"""
from __future__ import annotations

import math
import time
from contextlib import ExitStack
from typing import Callable

from rclpy._rclpy_pybind11 import RCLError
from rclpy.callback_groups import CallbackGroup, MutuallyExclusiveCallbackGroup
from rclpy.executors import ConditionReachedException, ShutdownException, TimeoutException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.subscription import Subscription

from .run import StopRequest


class ServedDirectly(CallbackGroup):
    """A callback group whose entities the executor leaves alone: a DirectInput serves them."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


class DirectInput:
    def __init__(self, subscription: Subscription | None, context, callback: Callable | None = None, guard=None,
                 tick: Callable[[], float] | None = None) -> None:
        """subscription and callback: the input (more with add(); None to start with none). guard: an
        optional GuardCondition (in a ServedDirectly group) whose callback runs here when another thread
        triggers it, as promptly as a message. tick: an optional deadline check (the compensator's
        watchdog), run here when its time comes; it returns the time.monotonic() at which it wants to run
        next, so a node that stays healthy is not woken for it at a fixed rate. Monotonic: a wall clock
        set forward or back must not hold a deadline off."""
        self.context = context
        self.inputs: list[tuple[Subscription, Callable, bool]] = []
        self.guard = guard
        self.tick = tick
        self.tick_due = time.monotonic() if tick is not None else math.inf
        self.wait_set = None
        if subscription is not None:
            self.add(subscription, callback)
        else:
            self._new_wait_set()  # a guard alone is worth waiting on (the bridge composed: its sent increments)

    def add(self, subscription: Subscription, callback: Callable, with_info: bool = False) -> None:
        """One more subscription (in a ServedDirectly group) to serve; each ready one is drained in turn.
        with_info: callback(message, info), info being rmw's dict (source_timestamp, received_timestamp
        in ns: when the writer published it and when DDS delivered it here, before this thread woke)."""
        self.inputs.append((subscription, callback, with_info))
        self._new_wait_set()

    def remove(self, subscription: Subscription) -> None:
        """Stop serving `subscription` (the caller destroys it)."""
        self.inputs = [item for item in self.inputs if item[0] is not subscription]
        self._new_wait_set()

    def _new_wait_set(self) -> None:
        if not self.inputs and self.guard is None:
            self.wait_set = None
            return
        self.wait_set = _rclpy.WaitSet(len(self.inputs), 0 if self.guard is None else 1, 0, 0, 0, 0,
                                       self.context.handle)

    def pump(self, timeout_sec: float) -> int:
        """Wait up to timeout_sec (or the tick's deadline) for messages, then handle every one queued and
        the tick if due; returns how many messages."""
        timeout_sec = max(0.0, min(timeout_sec, self.tick_due - time.monotonic()))
        if self.wait_set is None:  # nothing to wait on yet (rcl refuses an empty wait set)
            time.sleep(timeout_sec)
            ready = []
        else:
            ready = self._wait(timeout_sec)
        handled = 0
        for subscription, callback, with_info in ready:
            for message, info in take_all(subscription):
                if with_info:
                    callback(message, info)
                else:
                    callback(message)
                handled += 1
        if time.monotonic() >= self.tick_due:
            self.tick_due = self.tick()
        return handled

    def _wait(self, timeout_sec: float) -> list[tuple[Subscription, Callable, bool]]:
        """The inputs with messages; runs the guard's callback when it was triggered."""
        with ExitStack() as held:
            self.wait_set.clear_entities()
            for subscription, *_ in self.inputs:
                held.enter_context(subscription.handle)
                self.wait_set.add_subscription(subscription.handle)
            if self.guard is not None:
                held.enter_context(self.guard.handle)
                self.wait_set.add_guard_condition(self.guard.handle)
            self.wait_set.wait(int(timeout_sec * 1e9))
            ready = [item for k, item in enumerate(self.inputs) if self.wait_set.is_ready("subscription", k)]
            guard_ready = self.guard is not None and self.wait_set.is_ready("guard_condition", 0)
        if guard_ready:
            self.guard.callback()
        return ready


def take_all(subscription: Subscription):
    """Every message queued on `subscription` now, as (message, rmw's info dict), without waiting."""
    while True:
        with subscription.handle:
            taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
        if taken is None:
            return
        yield taken


def on_message_lost(node, subscription: Subscription, callback: Callable) -> None:
    """callback(info) when the middleware reports samples that never reached `subscription`: its event
    handler, which rclpy builds only for a subscription created with one, added to the node's executor."""
    for handler in SubscriptionEventCallbacks(message_lost=callback).create_event_handlers(
            MutuallyExclusiveCallbackGroup(), subscription.handle, subscription.topic_name):
        node.add_waitable(handler)


def serve_ready(executor) -> int:
    """Run the executor's callbacks until none is ready, without waiting; returns how many ran. One
    spin_once() runs one, and one wait hands over one message per subscription: at one pass per
    housekeeping period a topic the executor serves would fall behind for good."""
    served = round_served = 0
    while True:
        try:
            handler, _, _ = executor.wait_for_ready_callbacks(timeout_sec=0.0)
        except ShutdownException:
            return served
        except (TimeoutException, ConditionReachedException):
            if round_served == 0:  # a wait with nothing ready: drained
                return served
            round_served = 0
            continue
        handler()
        if handler.exception() is not None:
            raise handler.exception()
        served += 1
        round_served += 1


def spin(executor, direct_input: DirectInput, stop: StopRequest, housekeeping_period: float = 0.05) -> None:
    """Serve direct_input continuously and the executor's other work every housekeeping_period, until
    `stop` (Ctrl-C) or shutdown."""
    context = executor.context
    due = time.monotonic()
    while context.ok() and not stop.is_set():
        try:
            direct_input.pump(max(0.0, due - time.monotonic()))
            if time.monotonic() >= due:
                serve_ready(executor)
                due = time.monotonic() + housekeeping_period
        except RCLError:
            if context.ok():
                raise
            return  # Ctrl-C shut the context down between the check and the wait: a normal exit
