"""Load a part mesh (STL, PLY, OBJ; STEP when ``cascadio`` is installed) and refuse what cannot be inspected.

Every problem a user can cause becomes a :class:`cell.errors.ConfigError` that names the file and says what
was found: missing or unreadable file, no faces, NaN coordinates, non-manifold edges, a part 1000x too small
or too large (metres or micrometres instead of millimetres), a part larger than the working volume. Zero-area
triangles are removed with a :class:`MeshWarning` (CAD exporters often leave a few); an open surface is
allowed (sheet-metal CAD is often a surface model) and shows in :func:`mesh_summary`.

Units: millimetres. The mesh is returned in the file's own frame (the part frame {P}).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from cell.errors import ConfigError

if TYPE_CHECKING:
    from cell.config import CellConfig, Recipe

MESH_SUFFIXES = (".stl", ".ply", ".obj")
STEP_SUFFIXES = (".step", ".stp")
MIN_EXTENT_MM = 1.0
MAX_EXTENT_MM = 5000.0


class MeshWarning(UserWarning):
    """A mesh problem that was repaired on load (e.g. zero-area triangles removed)."""


def load_mesh(
    path: str | Path,
    *,
    what: str = "part CAD",
    min_extent_mm: float = MIN_EXTENT_MM,
    max_extent_mm: float = MAX_EXTENT_MM,
) -> trimesh.Trimesh:
    """Read a triangle mesh in mm and validate it; ``what`` names its role in error messages.

    Duplicate vertices are merged (STL stores none shared) so that edges and manifoldness are meaningful.
    """
    p = Path(path)
    where = f"{what} {p}"
    suffix = p.suffix.lower()
    if suffix not in MESH_SUFFIXES + STEP_SUFFIXES:
        raise ConfigError(
            f"unsupported mesh format '{p.suffix}'; use one of {', '.join(MESH_SUFFIXES + STEP_SUFFIXES)}",
            path=where,
        )
    if not p.is_file():
        raise ConfigError("file not found; check the path", path=where)
    if p.stat().st_size == 0:
        raise ConfigError("file is empty (0 bytes)", path=where)
    if suffix in STEP_SUFFIXES:
        _require_step_support(where)
    try:
        loaded = trimesh.load(p, file_type=suffix[1:], force="mesh", process=False)
    except Exception as exc:  # third-party parsers raise anything from ValueError to struct.error
        fmt = suffix[1:].upper()
        if isinstance(exc, ImportError):  # trimesh falls back to text decoding with an optional package
            detail = (
                f"not a valid {fmt} file, or a text file in an encoding that needs the package '{exc.name}'"
            )
        else:
            detail = f"not a valid {fmt} file ({type(exc).__name__}: {exc})"
        raise ConfigError(f"unreadable: {detail}", path=where) from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ConfigError("no triangles found (empty mesh or not a triangle mesh)", path=where)
    mesh = loaded
    if suffix in STEP_SUFFIXES:
        # cascadio converts through glTF, whose unit is the metre: back to millimetres.
        mesh.apply_scale(1000.0)

    bad = ~np.isfinite(mesh.vertices).all(axis=1)
    if bad.any():
        raise ConfigError(
            f"{int(bad.sum())} of {len(mesh.vertices)} vertices have NaN or infinite coordinates", path=where
        )
    mesh.merge_vertices()
    _check_manifold(mesh, where)
    _remove_degenerate(mesh, where)
    check_units(mesh, where, min_extent_mm, max_extent_mm)
    return mesh


def _require_step_support(where: str) -> None:
    """Import cascadio (trimesh tessellates STEP through it) and register trimesh's STEP loader, which
    ``cell/__init__.py`` kept from loading at start-up."""
    try:
        import cascadio
    except ImportError as exc:
        raise ConfigError(
            "STEP needs the 'cascadio' package (pip install cascadio), or export the CAD as STL/PLY/OBJ",
            path=where,
        ) from exc
    from trimesh.exchange import cascade
    from trimesh.exchange.load import mesh_loaders

    cascade.cascadio = cascadio
    # trimesh types its loader table narrower than the loaders it registers itself (load_step takes file_type)
    mesh_loaders.update({"stp": cascade.load_step, "step": cascade.load_step})  # type: ignore[dict-item]


def _check_manifold(mesh: trimesh.Trimesh, where: str) -> None:
    """Refuse edges shared by more than two faces: inside/outside and normals are undefined there."""
    uses = np.bincount(mesh.edges_unique_inverse, minlength=len(mesh.edges_unique))
    over = int((uses > 2).sum())
    if over:
        raise ConfigError(
            f"non-manifold: {over} edge(s) are shared by more than two triangles "
            f"(at most {int(uses.max())}); "
            "repair the CAD export (no T-joints or fins)",
            path=where,
        )


def _remove_degenerate(mesh: trimesh.Trimesh, where: str) -> None:
    """Drop zero-area triangles with a warning; refuse a mesh made only of them."""
    # trimesh's test: the smallest side of the triangle's oriented 2D box is under tol.merge (1e-8 mm).
    degenerate = ~mesh.nondegenerate_faces()
    n = int(degenerate.sum())
    if n == 0:
        return
    if n == len(mesh.faces):
        raise ConfigError(f"all {n} triangles have zero area; nothing to inspect", path=where)
    mesh.update_faces(~degenerate)
    mesh.remove_unreferenced_vertices()
    mesh.metadata["degenerate_removed"] = n
    warnings.warn(
        f"{where}: removed {n} zero-area triangle(s) of {n + len(mesh.faces)}", MeshWarning, stacklevel=3
    )


def check_units(
    mesh: trimesh.Trimesh,
    path: str | Path,
    min_extent_mm: float = MIN_EXTENT_MM,
    max_extent_mm: float = MAX_EXTENT_MM,
) -> None:
    """Refuse a part whose largest extent (mm) is implausible, naming the scale factor that would fix it.

    A part under ``min_extent_mm`` is most likely written in metres (scale by 1000); one over
    ``max_extent_mm`` in micrometres (scale by 0.001).
    """
    largest = float(mesh.extents.max())
    if min_extent_mm <= largest <= max_extent_mm:
        return
    if largest < min_extent_mm:
        unit, factor = "metres", 1000.0
    else:
        unit, factor = "micrometres", 0.001
    fixed = largest * factor
    hint = (
        f"the file is probably in {unit}: scaling by {factor:g} gives {fixed:.6g} mm"
        if min_extent_mm <= fixed <= max_extent_mm
        else f"no factor of 1000 fixes it ({fixed:.6g} mm after scaling by {factor:g}); check the export"
    )
    raise ConfigError(
        f"largest extent is {largest:.6g} mm, outside the plausible {min_extent_mm:g}..{max_extent_mm:g} mm; "
        + hint,
        path=str(path),
    )


def check_in_volume(
    mesh: trimesh.Trimesh,
    path: str | Path,
    lower_mm: ArrayLike,
    upper_mm: ArrayLike,
    T_W_P: ArrayLike | None = None,
) -> None:
    """Refuse a part that is larger than, or placed outside, the working volume (axis box in world mm).

    ``T_W_P`` places the part in the world; the identity when omitted.
    """
    lo, hi = np.asarray(lower_mm, dtype=np.float64), np.asarray(upper_mm, dtype=np.float64)
    vertices = mesh.vertices if T_W_P is None else trimesh.transform_points(mesh.vertices, np.asarray(T_W_P))
    bmin, bmax = vertices.min(axis=0), vertices.max(axis=0)
    size, room = bmax - bmin, hi - lo
    if (size > room).any():
        raise ConfigError(
            f"part is {_fmt(size)} mm, larger than the working volume {_fmt(room)} mm", path=str(path)
        )
    if (bmin < lo).any() or (bmax > hi).any():
        raise ConfigError(
            f"part spans {_fmt(bmin)}..{_fmt(bmax)} mm in the world, outside the working volume "
            f"{_fmt(lo)}..{_fmt(hi)} mm; check part.T_W_P",
            path=str(path),
        )


def _fmt(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.1f}" for x in v) + ")"


def mesh_summary(mesh: trimesh.Trimesh) -> dict[str, Any]:
    """Key figures of a mesh for logs and reports: triangles, extents (mm), watertightness, area (mm^2)."""
    return {
        "triangles": int(len(mesh.faces)),
        "vertices": int(len(mesh.vertices)),
        "extents_mm": [float(x) for x in mesh.extents],
        "bounds_mm": mesh.bounds.tolist(),
        "watertight": bool(mesh.is_watertight),
        "area_mm2": float(mesh.area),
        "volume_mm3": float(mesh.volume) if mesh.is_watertight else None,
        "degenerate_removed": int(mesh.metadata.get("degenerate_removed", 0)),
    }


def working_volume_W(cfg: CellConfig) -> tuple[np.ndarray, np.ndarray]:
    """World box (mm) the part must fit in: the robot envelope mapped into {W}, from the table top up."""
    T_W_B = cfg.robot.T_W_B.matrix()
    lo, hi = np.asarray(cfg.robot.envelope_min_mm), np.asarray(cfg.robot.envelope_max_mm)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    cw = trimesh.transform_points(corners, T_W_B)
    return np.r_[cw.min(axis=0)[:2], -1.0], cw.max(axis=0)


def load_part_W(recipe: Recipe, recipe_path: str | Path, cfg: CellConfig) -> trimesh.Trimesh:
    """A recipe's validated nominal CAD placed in the world {W} (mm); ConfigError when it does not fit the
    cell's working volume or the recipe's face regions or coverage exclusions name faces it does not have."""
    from cell.analysis.regions import check_face_indices, check_region_faces

    mesh = load_mesh(recipe.part.cad)
    check_region_faces(recipe.regions, len(mesh.faces), recipe_path, prefix="regions.")
    check_face_indices(recipe.exclude_from_coverage, len(mesh.faces), recipe_path, "exclude_from_coverage")
    T_W_P = recipe.part.T_W_P.matrix()
    lo, hi = working_volume_W(cfg)
    check_in_volume(mesh, recipe.part.cad, lo, hi, T_W_P)
    return mesh.copy().apply_transform(T_W_P)
