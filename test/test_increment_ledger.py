"""IncrementLedger: what the controller never applied, from its STATEs (pure code)."""
import numpy as np

from profile_pose_ros.core.control.increment_ledger import IncrementLedger


def units(x: int) -> tuple[int, ...]:
    return (x, 0, 0, 0, 0, 0)


def test_an_answer_replaced_before_its_tick_is_lost_and_only_that():
    ledger = IncrementLedger()
    ledger.reset(units(0))
    ledger.sent(1, units(10), answered=1000)  # answer to STATE 1, applied at tick 2
    assert ledger.state(1, units(10))[0] == 0 and ledger.lost_answered is None
    ledger.sent(2, units(20), answered=2000)  # answer to STATE 2 misses tick 3 ...
    assert ledger.state(1, units(10))[0] == 0  # STATE 3: nothing applied, 2 is still pending
    ledger.sent(3, units(30), answered=3000)  # ... and answer 3 replaces it before tick 4
    assert ledger.state(3, units(40))[0] == 20  # STATE 4: 3 applied, 2 never was
    assert ledger.lost_answered == 2000  # the compensator's model is told which period's answer it was


def test_states_that_never_arrive_hide_no_motion():
    ledger = IncrementLedger()
    ledger.reset(units(5))
    ledger.sent(1, units(10))
    ledger.sent(2, units(-4))  # both applied; the STATE between them was dropped
    assert ledger.state(2, units(11))[0] == 0


def test_a_pending_answer_is_not_lost_and_a_new_session_forgets():
    ledger = IncrementLedger()
    ledger.sent(1, units(7))  # before any session: ignored
    ledger.reset(units(0))
    ledger.sent(2, units(7))
    assert np.all(ledger.state(1, units(0)) == 0)  # not yet applied, not yet replaced
    ledger.reset(units(100))
    assert np.all(ledger.state(2, units(100)) == 0)
