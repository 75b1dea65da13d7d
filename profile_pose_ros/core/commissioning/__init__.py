"""Commissioning a cell: where the gauge and the profiler sit (hand_eye), the moves that measure it
(sequence), and the check of the loop's signs before it closes (first_motion)."""
