"""The profile's PointCloud2 layout (DESIGN.md), decoded and encoded without ROS.

The node hands over the message's fields; everything that can be wrong with them is checked here and
raised as ProfileFormatError with a message a person can act on. Nothing else is raised for any input.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..compiled.codes import ALL_INVALID, DECODED, OFF_PLANE
from ..compiled.loader import decode_xz

FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
POINT_STEP = 16  # x, y, z, intensity as float32
_DATATYPE_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32", 7: "FLOAT32", 8: "FLOAT64"}


class ProfileFormatError(ValueError):
    """The cloud is not a profile as DESIGN.md fixes it."""


@dataclass(frozen=True)
class Field:
    name: str
    offset: int
    datatype: int
    count: int = 1


def decode_profile(*, width: int, height: int, fields: Sequence[Field], is_bigendian: bool, point_step: int,
                   row_step: int, data: bytes | bytearray | memoryview | Sequence[int], compiled: bool = True
                   ) -> np.ndarray:
    """(N, 2) float64 [x, z]; NaN rows are invalid points. Raises ProfileFormatError. compiled=False takes the
    numpy reference path (identical results)."""
    if height != 1:
        raise ProfileFormatError(f"height is {height}; a profile is one row (height = 1)")
    if width <= 0:
        raise ProfileFormatError("empty cloud (width = 0)")
    if point_step <= 0:
        raise ProfileFormatError(f"point_step is {point_step}; it must be positive")
    if is_bigendian:
        raise ProfileFormatError("big-endian cloud; profiles are little-endian")
    by_name = {}
    for f in fields:
        by_name.setdefault(f.name, f)
    for name in ("x", "z"):
        if name not in by_name:
            raise ProfileFormatError(f"field '{name}' is missing (fields: {sorted(by_name) or 'none'})")
    for name in ("x", "y", "z"):
        f = by_name.get(name)
        if f is None:
            continue
        if f.datatype != FLOAT32 or f.count != 1:
            kind = _DATATYPE_NAMES.get(f.datatype, f"datatype {f.datatype}")
            raise ProfileFormatError(f"field '{name}' is {kind} x {f.count}; profiles use one FLOAT32")
        if f.offset < 0 or f.offset + 4 > point_step:
            raise ProfileFormatError(f"field '{name}' at offset {f.offset} does not fit point_step {point_step}")
    if row_step != width * point_step:
        raise ProfileFormatError(f"row_step {row_step} != width {width} x point_step {point_step}")
    size = len(data)
    if size != row_step * height:
        raise ProfileFormatError(f"data has {size} bytes; width {width} x point_step {point_step} needs "
                                 f"{row_step * height}")
    try:
        raw = np.frombuffer(data, dtype=np.uint8)
    except TypeError:  # a plain sequence of ints
        try:
            raw = np.frombuffer(bytes(data), dtype=np.uint8)
        except (TypeError, ValueError) as exc:
            raise ProfileFormatError(f"data is not a byte buffer ({exc})") from None

    aligned = point_step % 4 == 0 and all(by_name[k].offset % 4 == 0 for k in ("x", "y", "z") if k in by_name)
    if aligned and compiled:  # every profile publisher we know: one compiled pass over the float32 table
        table = raw.view("<f4").reshape(width, point_step // 4)
        points = np.empty((width, 2))
        status, count = decode_xz(table, *(by_name[k].offset // 4 if k in by_name else -1 for k in "xyz"), points)
        if status != DECODED:
            raise ProfileFormatError(_REASONS[status](count))
        return points
    return _decode_numpy(raw, by_name, width, point_step, aligned)


_REASONS = {
    OFF_PLANE: lambda count: f"{count} points have y != 0; a profile lies in the laser plane (y = 0)",
    ALL_INVALID: lambda count: f"all {count} points are invalid (NaN or +-inf)",
}


def _decode_numpy(raw: np.ndarray, by_name: dict, width: int, point_step: int, aligned: bool) -> np.ndarray:
    """The reference for the compiled pass, and the path for layouts it does not take (unaligned fields)."""
    table = raw.view("<f4").reshape(width, point_step // 4) if aligned else None

    def column(name: str) -> np.ndarray:
        if table is not None:  # a strided view, no copy
            return table[:, by_name[name].offset // 4]
        dtype = np.dtype({"names": [name], "formats": ["<f4"], "offsets": [by_name[name].offset],
                          "itemsize": point_step})
        return raw.view(dtype)[name]

    x, z = column("x"), column("z")
    if "y" in by_name:
        y = column("y")
        off_plane = np.isfinite(y) & (y != 0.0)
        if off_plane.any():
            raise ProfileFormatError(_REASONS[OFF_PLANE](int(off_plane.sum())))
    # REP-117's +-inf ("no return", "too close"), as some profiler drivers publish them: invalid points
    x = np.where(np.isinf(x) | np.isinf(z), np.float32(np.nan), x)
    points = np.empty((width, 2))
    with np.errstate(invalid="ignore"):  # signalling NaNs (any bit pattern can arrive) are still NaN
        np.add(x, 0.0 * z, out=points[:, 0])  # a point is invalid if either coordinate is NaN (0 * NaN = NaN;
        np.add(z, 0.0 * x, out=points[:, 1])  # an inf z has made its x NaN, and 0 * inf is NaN too)
    if np.isnan(points[:, 0]).all():
        raise ProfileFormatError(_REASONS[ALL_INVALID](width))
    return points


XYZ_FIELDS = (Field("x", 0, FLOAT32), Field("y", 4, FLOAT32), Field("z", 8, FLOAT32))  # 12 bytes a point


def encode_profile(points: np.ndarray, intensity: np.ndarray | None = None) -> tuple[list[Field], int, bytes]:
    """(fields, point_step, data) for an (N, 2) [x, z] profile: x, y=0, z float32, optional intensity."""
    points = np.asarray(points, dtype=float)
    n = len(points)
    step = POINT_STEP if intensity is not None else 12
    buffer = np.empty((n, step // 4), dtype="<f4")
    x, z = points[:, 0], points[:, 1]
    valid = np.isfinite(x) & np.isfinite(z)  # .all(axis=1) is 10x slower here
    # an invalid point is NaN in x, y and z; np.where beat zeros + a masked assignment by a third (half of
    # a rendered profile is invalid: off the gauge or out of range)
    buffer[:, 0] = np.where(valid, x, np.nan)
    buffer[:, 1] = np.where(valid, 0.0, np.nan)
    buffer[:, 2] = np.where(valid, z, np.nan)
    fields = list(XYZ_FIELDS)
    if intensity is not None:
        buffer[:, 3] = intensity
        fields.append(Field("intensity", 12, FLOAT32))
    return fields, step, buffer.tobytes()
