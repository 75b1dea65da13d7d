"""The calibration's stations: offsets of the tool from its start pose (x y z m, then a rotation vector rad,
base axes), each inside the envelope the bridge enforces.

Turns about all three axes, both ways, determine the profiler's orientation on the tool and its place
(a turn moves the profiler by its lever arm); translations along all three axes pin the gauge's
orientation in the base frame; the pairs mix both so that no unknown rests on one station.
"""
from __future__ import annotations

import numpy as np


def stations(translation: float = 4e-3, turn: float = np.radians(2.0)) -> np.ndarray:
    """13 offsets, the start pose first and last-but-none: (13, 6)."""
    d, a = translation, turn
    h = a / np.sqrt(2.0)
    rows = [
        [0, 0, 0, 0, 0, 0],
        [d, 0, 0, 0, 0, 0], [0, d, 0, 0, 0, 0], [0, 0, d, 0, 0, 0],
        [0, 0, 0, a, 0, 0], [0, 0, 0, 0, a, 0], [0, 0, 0, 0, 0, a],
        [-d, 0, 0, -a, 0, 0], [0, -d, 0, 0, -a, 0], [0, 0, -d, 0, 0, -a],
        [d, d, 0, h, h, 0], [0, -d, d, 0, h, -h], [-d, 0, -d, -h, 0, h],
    ]
    return np.array(rows, dtype=float)
