"""A request whose reply DDS may drop (tools/graph.py: first_answered): sent again until one is answered, and
never after that. The futures here stand for rclpy's: only their done() is read."""
from __future__ import annotations

import time

from profile_pose_ros.tools.graph import first_answered


class Reply:
    def __init__(self) -> None:
        self.answered = False

    def done(self) -> bool:
        return self.answered


def sender(sent: list[Reply]):
    """send() for first_answered: a new request's reply, kept in `sent`."""
    def send() -> Reply:
        sent.append(Reply())
        return sent[-1]
    return send


def test_a_lost_reply_is_asked_for_again_and_the_first_answer_ends_it() -> None:
    sent: list[Reply] = []
    lost = 2  # the first two requests' replies never come

    def spin_until(condition, timeout: float) -> bool:
        if len(sent) > lost:
            sent[-1].answered = True
        return condition()

    answered = first_answered(sender(sent), spin_until, time.monotonic() + 10.0, wait=0.0)
    assert answered is sent[2] and len(sent) == 3


def test_a_late_reply_to_an_earlier_request_counts() -> None:
    sent: list[Reply] = []

    def spin_until(condition, timeout: float) -> bool:
        if len(sent) == 2:
            sent[0].answered = True  # the first request's reply, delayed past the first wait
        return condition()

    assert first_answered(sender(sent), spin_until, time.monotonic() + 10.0, wait=0.0) is sent[0] and len(sent) == 2


def test_nothing_answered_by_the_deadline_is_none_after_one_request() -> None:
    sent: list[Reply] = []
    assert first_answered(sender(sent), lambda condition, timeout: condition(), time.monotonic()) is None
    assert len(sent) == 1
