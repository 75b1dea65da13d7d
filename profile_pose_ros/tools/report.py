"""Statistics and plain-text tables shared by the command-line tools."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np


def summary(values: Iterable[float]) -> dict:
    a = np.asarray(list(values), dtype=float)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "mean": float(a.mean()), "std": float(a.std()), "median": float(np.median(a)),
            "p99": float(np.percentile(a, 99)), "max": float(a.max()), "min": float(a.min())}


def nearest_stamp(sorted_stamps: np.ndarray, stamp: int, tolerance: int) -> int | None:
    """The element of sorted_stamps nearest to stamp, or None if none is within tolerance."""
    k = int(np.searchsorted(sorted_stamps, stamp))
    candidates = [int(sorted_stamps[j]) for j in (k - 1, k) if 0 <= j < len(sorted_stamps)]
    best = min(candidates, key=lambda s: abs(s - stamp), default=None)
    return best if best is not None and abs(best - stamp) <= tolerance else None


def table(headers: Sequence[str], rows: Sequence[Sequence], title: str = "") -> str:
    cells = [[str(h) for h in headers]] + [[c if isinstance(c, str) else f"{c:.3f}" for c in row] for row in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(headers))]
    lines = [title] if title else []
    for k, row in enumerate(cells):
        lines.append("  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(row, widths))))
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def run_dir(base: str | Path = "runs", name: str = "") -> Path:
    path = Path(base) / (time.strftime("%Y%m%d-%H%M%S") + (f"-{name}" if name else ""))
    path.mkdir(parents=True, exist_ok=True)
    return path


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, default=float))
