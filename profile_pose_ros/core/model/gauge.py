"""Gauge model: the faceted gauge of DESIGN.md, validated, with its ridges (paper eq. 2).

A gauge is n+1 planar top faces ordered along +x; consecutive faces meet in the n ridges
q_i + lambda [u_i, 1, w_i] whose intersections with the laser plane are the profile's corners.
Validation rejects any gauge that the estimator cannot work with and names the face and the rule,
because a gauge that is machined before it is checked is an expensive mistake.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import yaml

MIN_RIDGES = 4
UNIT_TOLERANCE = 1e-6
MIN_FACE_ANGLE_DEG = 1.0  # consecutive faces closer than this are "parallel"
MIN_RIDGE_ELEVATION_DEG = 10.0  # a ridge this close to the gauge's x-z plane is "parallel" to it
MIN_RIDGE_SPREAD_DEG = 0.5  # all ridge directions within this cone: y is unobservable


class GaugeError(ValueError):
    """A gauge file or description that cannot be used; the message names the source and the rule."""


@dataclass(frozen=True)
class Gauge:
    """A validated gauge. Arrays are read-only float64; lengths in metres."""

    name: str
    width: float
    length: float
    normals: np.ndarray  # (n+1, 3) unit face normals, nz > 0
    offsets: np.ndarray  # (n+1,) face k is {p : normals[k] . p = offsets[k]}
    base_z: float
    q: np.ndarray = field(init=False)  # (n, 3) ridge points in the y = 0 plane
    u: np.ndarray = field(init=False)  # (n,) ridge direction x per unit y
    w: np.ndarray = field(init=False)  # (n,) ridge direction z per unit y
    source: str = "<dict>"

    def __post_init__(self) -> None:
        q, u, w = _ridges(self.normals, self.offsets, self.source)
        for name, value in (("q", q), ("u", u), ("w", w)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        self.normals.setflags(write=False)
        self.offsets.setflags(write=False)

    @cached_property
    def kernel_faces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(normals, offsets, ridge x at y = 0, u) as the compiled dense refinement takes them: contiguous
        writable copies (its prebuilt signature; and numba's code for its loops is slower on read-only
        arrays), made once per gauge, not per profile."""
        return tuple(np.array(a, dtype=np.float64) for a in (self.normals, self.offsets, self.q[:, 0], self.u))

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_yaml(cls, path: str | Path) -> "Gauge":
        """Load and validate a gauge YAML file (safe loader only)."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise GaugeError(f"gauge file {path}: not found") from None
        except OSError as exc:
            raise GaugeError(f"gauge file {path}: cannot be read ({exc.strerror or exc})") from None
        except UnicodeDecodeError as exc:
            raise GaugeError(f"gauge file {path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
        try:
            document = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise GaugeError(f"gauge file {path}: not valid YAML ({exc})") from None
        return cls.from_dict(document, source=str(path))

    @classmethod
    def from_dict(cls, document: Any, source: str = "<dict>") -> "Gauge":
        """Validate a parsed gauge document (the top-level mapping with key 'gauge')."""
        if not isinstance(document, Mapping) or not isinstance(document.get("gauge"), Mapping):
            raise GaugeError(f"gauge {source}: top-level key 'gauge' (a mapping) is missing")
        g = document["gauge"]
        name = str(g.get("name", Path(source).stem))
        width = _positive_number(g, "width", source)
        length = _positive_number(g, "length", source)
        faces = g.get("faces")
        if not isinstance(faces, list):
            raise GaugeError(f"gauge {source}: 'faces' must be a list of {{normal, offset}}")
        if len(faces) < MIN_RIDGES + 1:
            raise GaugeError(
                f"gauge {source}: {len(faces)} faces give {max(len(faces) - 1, 0)} ridges; "
                f"rule: at least {MIN_RIDGES} ridges ({MIN_RIDGES + 1} faces) are needed"
            )
        normals = np.empty((len(faces), 3))
        offsets = np.empty(len(faces))
        for k, face in enumerate(faces):
            normals[k], offsets[k] = _face(face, k, source)
        _check_faces(normals, source)
        gauge_base = g.get("base_z")
        if gauge_base is None:
            base_z = float("nan")
        else:
            base_z = _finite_number(gauge_base, f"gauge {source}: 'base_z'")
        gauge = cls(name=name, width=width, length=length, normals=normals, offsets=offsets,
                    base_z=base_z, source=source)
        _check_ridges_in_footprint(gauge)
        lowest = float(np.min(gauge.corner_heights()))
        if gauge_base is None:
            object.__setattr__(gauge, "base_z", min(0.0, lowest - 0.01))
        elif base_z >= lowest:
            raise GaugeError(
                f"gauge {source}: base_z {base_z:.4f} m is not below the lowest top-surface point "
                f"{lowest:.4f} m; rule: the base must be under the top faces"
            )
        return gauge

    def to_dict(self) -> dict:
        """The YAML document of this gauge (round-trips through from_dict)."""
        return {"gauge": {
            "name": self.name, "width": float(self.width), "length": float(self.length),
            "base_z": float(self.base_z),
            "faces": [{"normal": [float(v) for v in n], "offset": float(d)}
                      for n, d in zip(self.normals, self.offsets)],
        }}

    # ---------------------------------------------------------------- geometry
    @property
    def n_ridges(self) -> int:
        return len(self.u)

    @property
    def directions(self) -> np.ndarray:
        """(n, 3) ridge directions [u, 1, w]."""
        return np.column_stack([self.u, np.ones_like(self.u), self.w])

    def without_face(self, face: int, count: int = 1) -> "Gauge":
        """The gauge as a profile that misses `count` adjacent faces from `face` sees it: the faces either side
        meet at a virtual ridge, where their planes cross. Same frame and footprint, so a pose of this gauge is
        a pose of the real one."""
        label = f"without face {face}" if count == 1 else f"without faces {face}..{face + count - 1}"
        return self._with_faces(label, lambda index: (index < face) | (index >= face + count))

    def faces_in_view(self, first: int, last: int) -> "Gauge":
        """The gauge as a profile that shows only faces first..last sees it (the others beyond the ends of its
        view): those faces and the ridges between them. Same frame and footprint."""
        return self._with_faces(f"faces {first}..{last}", lambda index: (index >= first) & (index <= last))

    def _with_faces(self, label: str, keep: Callable[[np.ndarray], np.ndarray]) -> "Gauge":
        """The gauge of the faces keep(face indices) selects, made once per gauge and label: a gap profile's
        description asks for its reduced gauge every time, so a made one costs a lookup and no array work. So
        is a refusal: faces whose planes never meet raise the same GaugeError each time without being validated
        again."""
        cache = self.__dict__.setdefault("_with_faces_cache", {})
        made = cache.get(label)
        if made is None:
            chosen = keep(np.arange(len(self.normals)))
            try:
                made = Gauge(f"{self.name} {label}", self.width, self.length, np.array(self.normals[chosen]),
                             np.array(self.offsets[chosen]), self.base_z, source=self.source)
            except GaugeError as exc:
                made = str(exc)
            cache[label] = made
        if isinstance(made, str):
            raise GaugeError(made)  # a new one each time: a kept exception would grow its traceback per raise
        return made

    def ridge_x(self, y: np.ndarray | float) -> np.ndarray:
        """x of every ridge at gauge y; shape (..., n)."""
        y = np.asarray(y, dtype=float)[..., None]
        return self.q[:, 0] + self.u * y

    def face_index(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Index of the top face above gauge (x, y): the number of ridges left of x."""
        return np.sum(self.ridge_x(y) < np.asarray(x, dtype=float)[..., None], axis=-1)

    def surface_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the top surface at gauge (x, y) (the footprint is not checked)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        k = self.face_index(x, y)
        n = self.normals[k]
        return (self.offsets[k] - n[..., 0] * x - n[..., 1] * y) / n[..., 2]

    def corner_heights(self) -> np.ndarray:
        """Top-surface heights at the footprint's corners and at the ridge ends."""
        ys = np.array([-self.length / 2, self.length / 2])
        xs = np.concatenate([np.full(2, -self.width / 2), np.full(2, self.width / 2),
                             self.ridge_x(ys).ravel()])
        yy = np.concatenate([ys, ys, np.repeat(ys, self.n_ridges)])
        return self.surface_z(xs, yy)

    def face_slope_deg(self) -> np.ndarray:
        """Angle of each face from the horizontal (90 deg minus the paper's beta)."""
        return np.degrees(np.arccos(np.clip(self.normals[:, 2], -1.0, 1.0)))


# -------------------------------------------------------------------- validation helpers
def _finite_number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise GaugeError(f"{what} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise GaugeError(f"{what} must be finite, got {value}")
    return value


def _positive_number(mapping: Mapping, key: str, source: str) -> float:
    if key not in mapping:
        raise GaugeError(f"gauge {source}: '{key}' is missing")
    value = _finite_number(mapping[key], f"gauge {source}: '{key}'")
    if value <= 0:
        raise GaugeError(f"gauge {source}: '{key}' must be > 0 m, got {value}")
    return value


def _face(face: Any, k: int, source: str) -> tuple[np.ndarray, float]:
    where = f"gauge {source}: face {k}"
    if not isinstance(face, Mapping) or "normal" not in face or "offset" not in face:
        raise GaugeError(f"{where} must be a mapping with 'normal' and 'offset'")
    raw = face["normal"]
    if not isinstance(raw, (list, tuple)) or len(raw) != 3:
        raise GaugeError(f"{where}: normal must be a list of 3 numbers, got {raw!r}")
    normal = np.array([_finite_number(v, f"{where}: normal component") for v in raw])
    offset = _finite_number(face["offset"], f"{where}: offset")
    norm = float(np.linalg.norm(normal))
    if abs(norm - 1.0) > UNIT_TOLERANCE:
        raise GaugeError(f"{where}: normal {list(raw)} has length {norm:.9f}; rule: it must be a "
                         f"unit vector (within {UNIT_TOLERANCE:g})")
    if normal[2] <= 0:
        raise GaugeError(f"{where}: normal z component is {normal[2]:g}; rule: nz > 0 (the face "
                         f"must face the sensor)")
    return normal, offset


def _check_faces(normals: np.ndarray, source: str) -> None:
    for k in range(len(normals) - 1):
        angle = math.degrees(math.asin(min(1.0, float(np.linalg.norm(np.cross(normals[k], normals[k + 1]))))))
        if angle < MIN_FACE_ANGLE_DEG:
            raise GaugeError(f"gauge {source}: faces {k} and {k + 1} are parallel ({angle:.3f} deg "
                             f"apart); rule: consecutive faces must differ by >= {MIN_FACE_ANGLE_DEG} deg")
        direction = np.cross(normals[k], normals[k + 1])
        elevation = math.degrees(math.asin(abs(direction[1]) / np.linalg.norm(direction)))
        if elevation < MIN_RIDGE_ELEVATION_DEG:
            raise GaugeError(f"gauge {source}: ridge {k} (faces {k}/{k + 1}) is {elevation:.2f} deg from the "
                             f"gauge's x-z plane; rule: a ridge must cross that plane at >= "
                             f"{MIN_RIDGE_ELEVATION_DEG} deg or the laser plane cannot cut it")
    directions = np.cross(normals[:-1], normals[1:])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    directions *= np.sign(directions[:, 1:2])
    cosines = np.clip(directions @ directions.T, -1.0, 1.0)
    spread = math.degrees(float(np.max(np.arccos(cosines))))
    if spread < MIN_RIDGE_SPREAD_DEG:
        raise GaugeError(f"gauge {source}: all ridges are parallel (spread {spread:.3f} deg); rule: ridge "
                         f"directions must differ by >= {MIN_RIDGE_SPREAD_DEG} deg or the shift along "
                         f"them (y) is unobservable")


def _ridges(normals: np.ndarray, offsets: np.ndarray, source: str) -> tuple[np.ndarray, ...]:
    """Paper eq. (2): ridge i = faces i and i+1, point q_i in y = 0, direction [u_i, 1, w_i]."""
    faces = np.arange(len(normals))
    q, u, w, crossing = ridge_lines(normals, offsets, faces[:-1], faces[1:])
    for i in np.flatnonzero(~crossing)[:1]:
        raise GaugeError(f"gauge {source}: ridge {i} (faces {i}/{i + 1}) does not cross y = 0")
    return q, u, w


def ridge_lines(normals: np.ndarray, offsets: np.ndarray, first: np.ndarray,
                second: np.ndarray) -> tuple[np.ndarray, ...]:
    """The lines where faces first[k] and second[k] meet, as eq. (2) writes a ridge: (q, u, w, crossing), NaN
    and crossing False where the two do not cross y = 0 (parallel in x-z). Every pair in one solve: the virtual
    ridges of a partial view's gauges (estimation/hidden_face.py) are made on a gauge's first profile."""
    a, b = normals[first], normals[second]
    systems = np.empty((len(a), 2, 2))  # rows: the two faces' x, z
    systems[:, 0, 0], systems[:, 0, 1], systems[:, 1, 0], systems[:, 1, 1] = a[:, 0], a[:, 2], b[:, 0], b[:, 2]
    crossing = np.abs(np.linalg.det(systems)) >= 1e-12
    rhs = np.stack([offsets[first], offsets[second]], axis=1)[..., None]
    q = np.zeros((len(a), 3))
    q[crossing, ::2] = np.linalg.solve(systems[crossing], rhs[crossing])[..., 0]
    # the cross product a x b as np.cross forms it, without its axis handling (most of its time on a few rows)
    dx, dy, dz = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2], \
        a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, w = dx / dy, dz / dy
    q[~crossing], u[~crossing], w[~crossing] = np.nan, np.nan, np.nan
    return q, u, w, crossing


def _check_ridges_in_footprint(gauge: Gauge) -> None:
    half_w = gauge.width / 2
    for y in (-gauge.length / 2, gauge.length / 2):
        xs = gauge.ridge_x(y)
        for i, x in enumerate(xs):
            if not -half_w < x < half_w:
                raise GaugeError(f"gauge {gauge.source}: ridge {i} leaves the footprint (x = {x:.4f} m at "
                                 f"y = {y:+.4f} m, width {gauge.width} m); rule: every ridge must span "
                                 f"the gauge's length inside its width")
        for i in range(len(xs) - 1):
            if xs[i + 1] <= xs[i]:
                raise GaugeError(f"gauge {gauge.source}: ridges {i} and {i + 1} cross inside the footprint "
                                 f"(near y = {y:+.4f} m); rule: faces are ordered along +x and each face "
                                 f"must have a positive width everywhere")
