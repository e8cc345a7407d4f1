"""Windshield-like glass panes for the back-imaging simulator: a doubly curved top skin, a known sag, and the
bottom skin one thickness below along the normals.

A pane is a height field z = f(x, y) over a rectangle centred on the origin of {W} (apex at z=0, curving down
to the edges), tessellated on a regular grid. The top skin is what the cell measures (the CAD); the bottom
skin is the top skin offset by -thickness along its vertex normals (the glass's other face). mm throughout.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh
from numpy.typing import NDArray

HeightFn = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]


def heightfield_mesh(height: HeightFn, size_mm: tuple[float, float], spacing_mm: float) -> trimesh.Trimesh:
    """Triangulate z = height(x, y) on a regular grid over [-w/2, w/2] x [-d/2, d/2], faces facing +z."""
    w, d = size_mm
    nx, ny = int(round(w / spacing_mm)) + 1, int(round(d / spacing_mm)) + 1
    x, y = np.meshgrid(np.linspace(-w / 2, w / 2, nx), np.linspace(-d / 2, d / 2, ny))
    verts = np.column_stack([x.ravel(), y.ravel(), height(x, y).ravel()])
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, e = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.vstack([np.column_stack([a, b, e]), np.column_stack([a, e, c])])
    return trimesh.Trimesh(verts, faces, process=False)


def windshield_height(radius_x_mm: float, radius_y_mm: float) -> HeightFn:
    """Height of a doubly curved pane: z = -(x^2 / 2 Rx + y^2 / 2 Ry), convex towards +z."""
    return lambda x, y: -(x * x / (2 * radius_x_mm) + y * y / (2 * radius_y_mm))


def sag_height(base: HeightFn, depth_mm: float, centre_mm: tuple[float, float], sigma_mm: float) -> HeightFn:
    """``base`` with a smooth Gaussian sag of ``depth_mm`` (positive = down) centred at ``centre_mm``."""
    cx, cy = centre_mm
    return lambda x, y: base(x, y) - depth_mm * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma_mm**2))


def bottom_skin(top: trimesh.Trimesh, thickness_mm: float) -> trimesh.Trimesh:
    """The glass's other face: every top vertex moved ``thickness_mm`` against its vertex normal."""
    verts = np.asarray(top.vertices) - thickness_mm * np.asarray(top.vertex_normals)
    return trimesh.Trimesh(verts, np.asarray(top.faces), process=False)
