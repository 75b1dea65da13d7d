"""Messages a reader never took, counted from the writer's publication sequence numbers.

DDS numbers each writer's samples 1, 2, 3, ...; a KEEP_LAST reader that falls behind has its oldest
samples overwritten in its history without any middleware event (the message-lost event covers only
samples that never arrived), so a slow node would drop profiles and say nothing. A gap in the numbers it
takes counts both kinds. One writer per topic is assumed (DESIGN.md's graph); a number that goes back
is a new writer (a restarted driver, a bag replay) and starts the count afresh. What a writer sent before
this reader's first message from it is not counted: it may have been sent before the two had matched,
which is discovery, not loss.
"""
from __future__ import annotations


class SequenceGaps:
    def __init__(self) -> None:
        self.last: int | None = None
        self.missed = 0  # in total
        self.writers = 0  # how many times the numbering started again

    def update(self, sequence: int | None) -> int:
        """The sequence number of the message just taken (None: the middleware gives none); returns how
        many were missed just before it."""
        if sequence is None:
            return 0
        if self.last is None or sequence <= self.last:
            gap = 0
            self.writers += 1
        else:
            gap = sequence - self.last - 1
        self.last = sequence
        self.missed += gap
        return gap
