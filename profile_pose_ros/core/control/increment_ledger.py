"""Which increments the controller never applied, from what each STATE reports.

The controller applies the newest CORRECTION it holds at each period (docs/motoplus_protocol.md, rule 3).
An answer that reaches it after its period's tick is still pending when the next answer arrives and is
replaced: its motion is lost, and the loop would see it only as an error a few periods later. The bridge
counts the losses (`lost_increments`) and tells the compensator (`lost_increment`), whose model then counts
the commands the controller applied (ModalController.lost); it does not resend them. Every STATE says which
CORRECTION was applied last (`echoed_seq`) and the total offset applied since HELLO, so the bridge
can tell exactly what was lost: of the corrections up to the echoed one, what was sent minus what the
offset grew by. STATEs that never arrive do not matter: the offset covers every period since the last one
that did.
"""
from __future__ import annotations

import numpy as np


class IncrementLedger:
    def __init__(self) -> None:
        self._unresolved: list[tuple[int, np.ndarray, int]] = []  # (seq, units, answered) sent, not yet echoed
        self._offset: np.ndarray | None = None  # the total applied offset at the last STATE
        self.lost_answered: int | None = None  # what the oldest answer replaced at the last STATE answered

    def reset(self, offset) -> None:
        """A new session (the arming STATE): nothing outstanding; offsets count from this one."""
        self._unresolved.clear()
        self._offset = np.asarray(offset, dtype=np.int64)

    def sent(self, seq: int, units, answered: int = 0) -> None:
        """answered: which STATE this CORRECTION answers (its time_us), reported with a loss."""
        if self._offset is not None:
            self._unresolved.append((seq, np.asarray(units, dtype=np.int64), answered))

    def state(self, echoed_seq: int, offset) -> np.ndarray:
        """Units sent up to the echoed CORRECTION that the controller's offset does not show: lost. When some
        are, lost_answered says which STATE the oldest replaced answer was for (the one answer lost, as a rule)."""
        offset = np.asarray(offset, dtype=np.int64)
        self.lost_answered = None
        if self._offset is None:
            return np.zeros(6, dtype=np.int64)
        resolved = [(seq, units, answered) for seq, units, answered in self._unresolved if seq <= echoed_seq]
        self._unresolved = [entry for entry in self._unresolved if entry[0] > echoed_seq]
        sent = np.sum([units for _, units, _ in resolved], axis=0) if resolved else np.zeros(6, dtype=np.int64)
        lost = sent - (offset - self._offset)
        self._offset = offset
        if np.any(lost):
            replaced = [answered for seq, units, answered in resolved if seq < echoed_seq and np.any(units)]
            self.lost_answered = replaced[0] if replaced else None
        return lost
