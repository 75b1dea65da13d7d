"""The bridge's client tells which answer the controller never applied (MotoPlusClient on_lost), against
sim_cell's robot controller in this process: its own count of replaced answers is the witness."""
from __future__ import annotations

import threading

import numpy as np

from profile_pose_ros.core.wire import motoplus_protocol as mp
from profile_pose_ros.devices.motoplus_client import MotoPlusClient, SessionLimits
from profile_pose_ros.sim.arm import Arm
from profile_pose_ros.sim.robot_controller import RobotController

from conftest import wait_for

STEP_UM = 20  # each answer's increment on x


class OneAnswerLate(MotoPlusClient):
    """Holds one moving answer (the tenth) for 1.5 periods before sending it: it reaches the controller after
    its next tick, and the answer to the next STATE replaces it there before it is applied."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.held: tuple[tuple[int, ...], int] | None = None  # (increment, time_us of the STATE it answered)

    def _send(self, body: mp.Body) -> bool:
        if isinstance(body, mp.Correction) and any(body.increment) and self.held is None \
                and self.counters.corrections >= 10:
            self.held = (body.increment, self.last_state.time_us)
            threading.Event().wait(1.5 * self.limits.period_s)
        return super()._send(body)


def test_an_answer_replaced_before_its_tick_is_told_with_the_state_it_answered() -> None:
    controller = RobotController(Arm(), port=0)
    controller.start()
    told: list[tuple[np.ndarray, int]] = []
    limits = SessionLimits(max_step=mp.units_to_metres((200,) * 3 + (100,) * 3),
                           max_offset=mp.units_to_metres((5000,) * 3 + (2000,) * 3), watchdog_s=2.0)
    step = np.array(mp.units_to_metres((STEP_UM, 0, 0, 0, 0, 0)))
    client = OneAnswerLate("127.0.0.1", controller.port, limits, lambda now: (step, now), lambda *_: None,
                           max_age_s=lambda: 0.05, log=lambda _text: None,
                           on_lost=lambda units, answered: told.append((np.asarray(units), answered))).start()
    client.arm()
    try:
        assert wait_for(lambda: client.held is not None and client.counters.corrections > 30), vars(client.counters)
        # the witness, the controller's own count (on a loaded machine the thread may lose another one itself)
        assert wait_for(lambda: len(told) == controller.replaced >= 1), (told, controller.replaced)
        assert client.counters.lost_increments == len(told)
        # the compensator places the loss in its model by the STATE its answer was for
        held = [units.tolist() for units, answered in told if answered == client.held[1]]
        assert held == [[STEP_UM, 0, 0, 0, 0, 0]], (told, client.held)
    finally:
        client.stop()
        controller.close()
