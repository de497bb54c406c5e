"""Mesh primitives for the procedural scenes: quads, boxes, cylinders, spheres.

Every builder returns `(vertices_world (V,3) float64 m, triangles (T,3) int64)`.
Triangle winding is irrelevant: the ray caster is two-sided and shading uses
|n . l|.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.types import F64
from ingest.runtime.o3d import o3d

Tri = np.ndarray[Any, np.dtype[np.int64]]
Mesh = tuple[F64, Tri]


def quad(corner: F64 | list[float], edge_u: F64 | list[float], edge_v: F64 | list[float]) -> Mesh:
    """Parallelogram spanned by `edge_u` and `edge_v` from `corner` (two triangles)."""
    c, u, v = (np.asarray(a, np.float64) for a in (corner, edge_u, edge_v))
    verts = np.stack([c, c + u, c + u + v, c + v])
    return verts, np.array([[0, 1, 2], [0, 2, 3]], np.int64)


def grid(corner: F64 | list[float], edge_u: F64 | list[float], edge_v: F64 | list[float], n: int) -> Mesh:
    """`quad` split into n x n cells, so no triangle is huge (keeps float32 queries precise)."""
    c, u, v = (np.asarray(a, np.float64) for a in (corner, edge_u, edge_v))
    return merge([quad(c + u * i / n + v * j / n, u / n, v / n) for i in range(n) for j in range(n)])


def box(lo: F64 | list[float], hi: F64 | list[float]) -> Mesh:
    """Axis-aligned box between corners `lo` and `hi` (12 triangles)."""
    mesh = o3d.geometry.TriangleMesh.create_box(*(np.asarray(hi) - np.asarray(lo)).tolist())
    verts = np.asarray(mesh.vertices, np.float64) + np.asarray(lo, np.float64)
    return verts, np.asarray(mesh.triangles, np.int64)


def cylinder(p0: F64 | list[float], p1: F64 | list[float], radius_m: float, resolution: int = 16) -> Mesh:
    """Closed cylinder of `radius_m` with its axis from `p0` to `p1`."""
    a, b = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    axis = b - a
    length = float(np.linalg.norm(axis))
    # <= 0.5 m segments: Open3D's float32 closest-point query degrades on long sliver triangles
    split = max(1, int(np.ceil(length / 0.5)))
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius_m, length, resolution=resolution, split=split)
    verts = np.asarray(mesh.vertices, np.float64)  # axis along +z, centred at the origin
    z = axis / length
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z], axis=1)
    return verts @ R.T + (a + b) / 2, np.asarray(mesh.triangles, np.int64)


def sphere(center: F64 | list[float], radius_m: float, resolution: int = 12) -> Mesh:
    """UV sphere around `center`."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius_m, resolution=resolution)
    return np.asarray(mesh.vertices, np.float64) + np.asarray(center, np.float64), np.asarray(
        mesh.triangles, np.int64
    )


def merge(parts: list[Mesh]) -> Mesh:
    """Concatenate meshes into one vertex/triangle list."""
    verts: list[F64] = []
    tris: list[Tri] = []
    offset = 0
    for v, t in parts:
        verts.append(v)
        tris.append(t + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(tris)
