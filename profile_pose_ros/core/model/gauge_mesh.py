"""The gauge as a closed triangle mesh (trimesh) for 3D printing or CAM.

The solid is the prism under the faceted top: each top face is a planar quadrilateral between two
ridges (or a ridge and a side), walls drop to base_z, and the bottom is closed with the same vertices,
so the mesh is watertight by construction (checked with trimesh, also by a test). Exported in
millimetres, the unit slicers and CAM tools assume for STL.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .gauge import Gauge


def gauge_mesh(gauge: Gauge):
    """A trimesh.Trimesh of the gauge solid in metres, gauge frame G, outward normals."""
    import trimesh

    ends = np.array([-gauge.length / 2, gauge.length / 2])
    half = gauge.width / 2
    chains = []  # per end: x of the top outline's vertices (sides and ridges), left to right
    for y in ends:
        chains.append(np.concatenate([[-half], gauge.ridge_x(y), [half]]))
    m = len(chains[0])
    vertices, faces = [], []

    def vertex(x: float, y: float, z: float) -> int:
        vertices.append((x, y, z))
        return len(vertices) - 1

    top = [[vertex(x, y, float(gauge.surface_z(np.clip(x, -half + 1e-12, half - 1e-12), y)))
            for x in chain] for chain, y in zip(chains, ends)]
    # a ridge vertex sits on two faces; surface_z picks one, and both agree there to rounding
    base = [[vertex(x, y, gauge.base_z) for x in chain] for chain, y in zip(chains, ends)]
    front, back = 0, 1
    for k in range(m - 1):
        faces += [(top[front][k], top[front][k + 1], top[back][k + 1]), (top[front][k], top[back][k + 1], top[back][k])]
        faces += [(base[front][k], base[back][k + 1], base[front][k + 1]), (base[front][k], base[back][k], base[back][k + 1])]
        faces += [(top[front][k], base[front][k + 1], top[front][k + 1]), (top[front][k], base[front][k], base[front][k + 1])]
        faces += [(top[back][k], top[back][k + 1], base[back][k + 1]), (top[back][k], base[back][k + 1], base[back][k])]
    left, right = 0, m - 1
    faces += [(top[front][left], top[back][left], base[back][left]),
              (top[front][left], base[back][left], base[front][left])]
    faces += [(top[front][right], base[back][right], top[back][right]),
              (top[front][right], base[front][right], base[back][right])]
    mesh = trimesh.Trimesh(np.array(vertices), np.array(faces), process=True)
    if mesh.volume < 0:  # wound inwards: turn every triangle over
        mesh.invert()
    return mesh


def export_stl(gauge: Gauge, path: str | Path) -> dict:
    """Write the gauge as binary STL in mm; returns what trimesh says of the solid."""
    mesh = gauge_mesh(gauge)
    if not mesh.is_watertight or not mesh.is_volume:
        raise RuntimeError(f"gauge '{gauge.name}': the mesh is not a closed solid (a bug; please report)")
    scaled = mesh.copy()
    scaled.apply_scale(1000.0)
    scaled.export(str(path), file_type="stl")
    return {"path": str(path), "triangles": int(len(mesh.faces)), "watertight": bool(mesh.is_watertight),
            "volume_cm3": float(mesh.volume * 1e6), "bounds_mm": (mesh.bounds * 1e3).round(3).tolist()}
