"""The profiler driver without ROS: a connection state machine over a profile source, trigger sync with
the MCU, drop accounting, and stamping. Frames go out through `emit(frame, stamp_s, synced)`.

States: connecting -> synchronising -> streaming; any error -> backoff -> connecting. It never gives up
and never raises into the caller: a device fault is a state, a counter and `last_error`.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

from ..core.timing.clock_sync import TriggerMatcher
from ..core.wire.profiler_protocol import ProfileFrame, ProfilerProtocolError
from .profile_source import ProfileSource
from .trigger_link import CONNECTING as CONNECTING_MCU
from .trigger_link import TriggerLink

CONNECTING, SYNCHRONISING, STREAMING, BACKOFF, STOPPED = (
    "connecting", "synchronising", "streaming", "backoff", "stopped")
CLOCK_STEP_S = 1.0  # a stamp this far behind the last one: the host clock was set back; carry on from it


@dataclass
class LinkSettings:
    stamp_source: str = "trigger"  # trigger | receive
    max_input_age: float = 1.0  # s without any data from the device -> reconnect (0: never)
    backoff_min: float = 0.1
    backoff_max: float = 0.5
    sync_timeout: float = 0.02  # how long a profile waits for its trigger line
    max_stamp_error: float = 2e-4  # s: a trigger stamp the MCU clock map cannot bound this closely is not used
    sync_quiet: float = 0.05  # quiet time after disarming before the counters are paired
    resync_after_misses: int = 20  # consecutive unmatched profiles (with the MCU alive) -> pair again


@dataclass
class LinkCounters:
    frames: int = 0
    published: int = 0
    dropped: int = 0  # gaps in the profiler's trigger count: profiles the device took but we never got
    #                   (in the stream, or while reconnecting)
    bad_frames: int = 0
    unsynced: int = 0  # published with the receive time: no MCU configured, or stamp_source 'receive'
    untimed: int = 0  # not published: an MCU is configured but is silent, disconnected or not paired
    late_lines: int = 0  # not published: the MCU is alive but this trigger's line missed sync_timeout
    discarded: int = 0  # received while the MCU link starts or counters are paired (trigger time unknown)
    unconfirmed: int = 0  # not published: the trigger's line came, but the clock map could not bound its
    #                       host time within max_stamp_error (the map still settling, or every PING slow)
    out_of_order: int = 0  # not published: its stamp was not after the last published one (never expected)
    connections: int = 0
    resyncs: int = 0
    unacknowledged_pairings: int = 0  # pairings abandoned: the MCU did not acknowledge DISARM or RESET in time


class ProfilerLink:
    def __init__(self, source: ProfileSource, trigger: TriggerLink | None, settings: LinkSettings,
                 emit: Callable[[ProfileFrame, float, bool], None], log: Callable[[str], None] = print,
                 batch_end: Callable[[], None] | None = None) -> None:
        """emit: each profile, with its stamp; batch_end (optional): after the profiles of one read, i.e.
        those that were waiting together (the composed driver hands only the newest of them on)."""
        if settings.stamp_source not in ("trigger", "receive"):
            raise ValueError(f"stamp_source must be 'trigger' or 'receive', not {settings.stamp_source!r}")
        self.source, self.trigger, self.settings = source, trigger, settings
        self.emit, self.log, self.batch_end = emit, log, batch_end
        self.counters = LinkCounters()
        self.state = CONNECTING
        self.last_error = ""
        self.matcher = TriggerMatcher()
        self._cond = threading.Condition()
        self._last_count: int | None = None
        self._last_stamp = -math.inf  # the newest published stamp: stamps only ever go forward
        self._count_seen_on_this_connection = False
        self._misses = 0
        self._resync = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="profiler-link", daemon=True)

    # ---------------------------------------------------------------- wiring
    def on_trigger(self, seq: int, host_time: float, error_bound: float) -> None:
        """TriggerLink's callback (its thread). A time the clock map cannot vouch for is kept as NaN: the
        profile of that trigger is then known to be untimed rather than waiting for a line that came."""
        with self._cond:
            self.matcher.add_trigger(seq, host_time if self._vouched(error_bound) else math.nan)
            self._cond.notify_all()

    def request_resync(self, reason: str) -> None:
        """Forget the pairing now (stamps from it would be wrong) and pair again once the MCU is up."""
        self.log(f"re-pairing trigger counters: {reason}")
        with self._cond:
            self.matcher.forget()
        self._resync.set()

    def start(self) -> "ProfilerLink":
        if self.trigger is not None:
            self.trigger.on_trigger = self.on_trigger
            self.trigger.on_resync_needed = self.request_resync
            self.trigger.start()
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=3.0)
        if self.trigger is not None:
            self.trigger.stop()
        self.state = STOPPED

    # ---------------------------------------------------------------- state machine
    def _run(self) -> None:
        backoff = self.settings.backoff_min
        while not self._stop.is_set():
            self.state = CONNECTING
            try:
                self.source.open()
                self.counters.connections += 1
                self._count_seen_on_this_connection = False  # the device may have restarted its count
                backoff = self.settings.backoff_min
                if self.matcher.offset is None and not self.matcher.pairing:
                    self._resync.set()  # a reconnect to the same device keeps its count: no need to re-pair
                self._stream()
            except (OSError, ProfilerProtocolError, TimeoutError) as exc:
                self.last_error = f"{self.source.name}: {exc}"
                self.log(f"profiler link: {self.last_error}; reconnecting in {backoff:.2f} s")
            except Exception as exc:  # noqa: BLE001 - a device fault must never end the driver
                self.last_error = f"{self.source.name}: unexpected {exc!r}"
                self.log(f"profiler link: {self.last_error}")
            finally:
                self.source.close()
            if self._stop.is_set():
                break
            self.state = BACKOFF
            self._stop.wait(backoff)
            backoff = min(2 * backoff, self.settings.backoff_max)

    def _stream(self) -> None:
        while not self._stop.is_set():
            if self._resync.is_set():
                self._resync.clear()
                self._synchronise()
            self.state = STREAMING
            self._handle(self.source.read(0.05))
            age = self.source.seconds_since_data()
            if self.settings.max_input_age > 0 and age > self.settings.max_input_age:
                raise TimeoutError(f"no data for {age:.2f} s (max_input_age)")
            if self.trigger is not None and self.trigger.ok and self.matcher.offset is None \
                    and not self.matcher.pairing and self.settings.stamp_source == "trigger":
                self._resync.set()  # the MCU came (back) after a failed pairing

    def _synchronise(self) -> None:
        """Disarm, let the stream go quiet, reset and re-arm the MCU: then the first trigger line and the
        first profile are the same pulse. Without a live MCU there is nothing to pair (and no profile goes out)."""
        if self.trigger is None or not self.trigger.ok:
            return
        self.state = SYNCHRONISING
        self.counters.resyncs += 1
        try:
            if not self.trigger.command("DISARM"):
                self.last_error = "trigger MCU did not acknowledge DISARM"
                self.counters.unacknowledged_pairings += 1
                return
            quiet_since = time.monotonic()
            deadline = quiet_since + 1.0
            while time.monotonic() - quiet_since < self.settings.sync_quiet and time.monotonic() < deadline:
                frames = [i for i in self.source.read(0.01) if isinstance(i, ProfileFrame)]
                if frames:
                    self.counters.discarded += len(frames)
                    self._last_count = frames[-1].trigger_count
                    self._count_seen_on_this_connection = True
                    quiet_since = time.monotonic()
            if not self.trigger.command("RESET"):
                self.last_error = "trigger MCU did not acknowledge RESET"
                self.counters.unacknowledged_pairings += 1
                return
            with self._cond:  # the last profile before disarming says which count the next trigger gets
                self.matcher.arm(self._last_count if self._count_seen_on_this_connection else None)
            self._misses = 0
        finally:
            if not self.trigger.command("ARM"):  # always: a disarmed MCU would stop the whole cell
                self.last_error = "trigger MCU did not acknowledge ARM"

    # ---------------------------------------------------------------- frames
    def _handle(self, items: list) -> None:
        arrival = time.time()
        for item in items:
            if isinstance(item, ProfilerProtocolError):
                self.counters.bad_frames += 1
                self.last_error = f"bad frame: {item}"
                continue
            self._frame(item, arrival)
        if self.batch_end is not None and items:
            self.batch_end()

    def _frame(self, frame: ProfileFrame, arrival: float) -> None:
        c = self.counters
        c.frames += 1
        if self._last_count is not None:  # across reconnects too: frames missed while away are lost
            gap = (frame.trigger_count - self._last_count - 1) & 0xFFFFFFFF
            if gap < 0x80000000:
                c.dropped += gap
            elif self.trigger is not None and not self.matcher.pairing:  # the count went back: the device
                #                                                           restarted; pair again
                self.request_resync("the profiler's trigger count restarted")
        self._last_count = frame.trigger_count
        self._count_seen_on_this_connection = True
        stamp = self._trigger_time(frame.trigger_count)
        if stamp is None or math.isnan(stamp):
            if self._stamped_by_trigger():
                self._count_untimed(stamp)  # never a receive-time stamp: it would look fresh and exact
                return
            c.unsynced += 1
            stamp, synced = arrival, False
        else:
            synced = True
        if stamp <= self._last_stamp and self._last_stamp - stamp < CLOCK_STEP_S:
            c.out_of_order += 1
            return
        self._last_stamp = stamp
        self.emit(frame, stamp, synced)
        c.published += 1

    def _stamped_by_trigger(self) -> bool:
        """An MCU is configured and stamps come from it: a profile without its trigger's time is dropped."""
        return self.trigger is not None and self.settings.stamp_source == "trigger"

    def _count_untimed(self, stamp: float | None) -> None:
        """Why a profile had no trigger time (stamp None: no line; NaN: a line the clock map cannot vouch for)."""
        c = self.counters
        if stamp is not None:
            c.unconfirmed += 1  # the clock map still settling (after a start, reconnect or MCU restart)
        elif self.trigger.state == CONNECTING_MCU or self.matcher.pairing:
            c.discarded += 1  # the MCU link opening, training its clock or pairing counters
        elif self.trigger.ok and self.matcher.offset is not None:
            c.late_lines += 1  # the MCU is alive and paired but this trigger's line is late or lost
        else:
            c.untimed += 1  # the MCU silent, disconnected, or not paired

    @property
    def stamps_trusted(self) -> bool:
        """The next trigger would be stamped: the MCU is up and its clock map bounds the stamp closely."""
        return self.trigger is not None and self.trigger.ok and self._vouched(self.trigger.clock.error_bound)

    def _vouched(self, error_bound: float) -> bool:
        """A trigger time the clock map bounds closely enough to stamp a profile with."""
        return error_bound <= self.settings.max_stamp_error

    def _trigger_time(self, trigger_count: int) -> float | None:
        with self._cond:
            self.matcher.note_profile(trigger_count)
            if self.settings.stamp_source != "trigger" or not (self.matcher.offset is not None
                                                                  or self.matcher.pairing):
                return None
            alive = self.trigger is not None and self.trigger.ok
            self._cond.wait_for(lambda: self.matcher.trigger_time(trigger_count) is not None,
                                timeout=self.settings.sync_timeout if alive else 0.0)
            stamp = self.matcher.trigger_time(trigger_count)
        if stamp is None and alive:
            self._misses += 1
            if self._misses >= self.settings.resync_after_misses:
                self._misses = 0
                self.request_resync(f"{self.settings.resync_after_misses} profiles in a row without their trigger")
        elif stamp is not None:
            self._misses = 0
        return stamp
