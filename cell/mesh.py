"""Load a part mesh (STL, PLY, OBJ; STEP when ``cascadio`` is installed) and refuse what cannot be inspected.

Every problem a user can cause becomes a :class:`cell.errors.ConfigError` that names the file and says what
was found: missing or unreadable file, no faces, NaN coordinates, non-manifold edges, a part 1000x too small
or too large (metres or micrometres instead of millimetres), a part larger than the working volume. Zero-area
triangles are removed with a :class:`MeshWarning` (CAD exporters often leave a few); an open surface is
allowed (sheet-metal CAD is often a surface model) and shows in :func:`mesh_summary`.

Units: millimetres. The mesh is returned in the file's own frame (the part frame {P}).

:func:`load_mesh_arrays` gives the same mesh as arrays, with the same checks, errors and warnings, and reads a
plain binary STL or triangle PLY without importing trimesh (:mod:`cell.mesh_files`): ``cell compare`` starts
1 s of CPU sooner. The checks work on arrays, shared by both paths; merging duplicate vertices repeats
trimesh's rule (positions rounded to 1e-8 mm, first occurrence kept); tests/test_mesh.py compares the two.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cell.errors import ConfigError

if TYPE_CHECKING:
    import trimesh

    from cell.config import CellConfig, Recipe

MESH_SUFFIXES = (".stl", ".ply", ".obj")
STEP_SUFFIXES = (".step", ".stp")
MIN_EXTENT_MM = 1.0
MAX_EXTENT_MM = 5000.0
MERGE_DIGITS = 8  # trimesh's tol.merge (1e-8): vertices equal when their coordinates round alike at 1e-8 mm


class MeshWarning(UserWarning):
    """A mesh problem that was repaired on load (e.g. zero-area triangles removed)."""


@dataclass(frozen=True)
class MeshArrays:
    """A validated triangle mesh (mm) as :func:`load_mesh` would return it: vertices (V, 3) float64, faces
    (F, 3) int64, and how many zero-area triangles were removed."""

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    degenerate_removed: int = 0


def _check_file(p: Path, where: str) -> str:
    """The lower-case suffix of a mesh file that exists and is not empty; ConfigError otherwise."""
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
    return suffix


def load_mesh_arrays(
    path: str | Path,
    *,
    what: str = "part CAD",
    min_extent_mm: float = MIN_EXTENT_MM,
    max_extent_mm: float = MAX_EXTENT_MM,
) -> MeshArrays:
    """:func:`load_mesh` as arrays: the same checks, errors and warnings; a plain binary STL or triangle PLY
    is read without trimesh (others go through :func:`load_mesh`)."""
    from cell.mesh_files import read_plain_mesh

    p = Path(path)
    where = f"{what} {p}"
    suffix = _check_file(p, where)
    plain = read_plain_mesh(p) if suffix in (".stl", ".ply") else None
    if plain is None:
        mesh = load_mesh(p, what=what, min_extent_mm=min_extent_mm, max_extent_mm=max_extent_mm)
        return MeshArrays(
            np.asarray(mesh.vertices, np.float64),
            np.asarray(mesh.faces, np.int64),
            int(mesh.metadata.get("degenerate_removed", 0)),
        )
    v, f = plain
    _check_finite(v, where)
    v, f = merge_vertices(v, f)
    _check_edges(f, where)
    keep = nondegenerate(v, f)
    n = int((~keep).sum())
    if n:
        _degenerate_found(n, len(f), where, stacklevel=3)
        f = f[keep]
        used = np.zeros(len(v), bool)
        used[f] = True
        v, f = v[used], (np.cumsum(used) - 1)[f]
    check_extent(np.ptp(v, axis=0), where, min_extent_mm, max_extent_mm)
    return MeshArrays(v, f, n)


def merge_vertices(vertices: ArrayLike, faces: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Vertices equal to :data:`MERGE_DIGITS` digits merged, as ``trimesh.Trimesh.merge_vertices`` merges a
    mesh of positions only: the referenced vertices in the order of their first occurrence (the first of
    equal ones kept), unreferenced ones dropped, faces renumbered."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if len(v) == 0:
        return v, f
    referenced = np.zeros(len(v), bool)
    referenced[f] = True
    used = np.flatnonzero(referenced)
    rounded = (v[used] * (10**MERGE_DIGITS)).round().astype(np.int64)
    # equal rows next to each other, each run in index order (lexsort is stable): its first is the first
    # occurrence. 10x faster than np.unique(axis=0), which sorts the rows as opaque bytes.
    order = np.lexsort(rounded.T[::-1])
    sorted_rows = rounded[order]
    starts = np.r_[True, (sorted_rows[1:] != sorted_rows[:-1]).any(axis=1)]
    group = np.cumsum(starts) - 1  # run of each sorted row
    first = order[starts]  # first occurrence of each run (index into used)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))  # runs in order of first occurrence
    renumber = np.zeros(len(v), np.int64)
    renumber[used[order]] = rank[group]
    return v[used[np.sort(first)]], renumber[f]


def nondegenerate(vertices: NDArray[np.float64], faces: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Faces whose 2D oriented box has both sides longer than 1e-8 mm: ``trimesh``'s
    ``nondegenerate_faces`` (same expressions, same result bit for bit)."""
    tri = vertices[faces]
    vectors = tri[:, 1:, :] - tri[:, :2, :]
    areas = np.sqrt((np.cross(vectors[:, 0], vectors[:, 1]) ** 2).sum(axis=1)) / 2.0
    box = np.zeros((len(faces), 2), dtype=np.float64)
    for k, edge in enumerate((tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])):
        length = (edge**2).sum(axis=1) ** 0.5
        ok = length > 10.0**-MERGE_DIGITS
        box[:, k][ok] = (areas[ok] * 2) / length[ok]
    return np.asarray((box > 10.0**-MERGE_DIGITS).all(axis=1), dtype=bool)


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
    import trimesh

    p = Path(path)
    where = f"{what} {p}"
    suffix = _check_file(p, where)
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

    _check_finite(mesh.vertices, where)
    mesh.merge_vertices()
    _check_edges(mesh.faces, where)
    _remove_degenerate(mesh, where)
    check_units(mesh, where, min_extent_mm, max_extent_mm)
    return mesh


def _check_finite(vertices: NDArray[np.float64], where: str) -> None:
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise ConfigError(
            f"{int(bad.sum())} of {len(vertices)} vertices have NaN or infinite coordinates", path=where
        )


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


def _check_edges(faces: ArrayLike, where: str) -> None:
    """Refuse edges shared by more than two faces: inside/outside and normals are undefined there."""
    f = np.asarray(faces, np.int64)
    a, b = f.ravel(), np.roll(f, -1, axis=1).ravel()  # edges ab, bc, ca of each face
    _, uses = np.unique(np.minimum(a, b) * (int(f.max()) + 1) + np.maximum(a, b), return_counts=True)
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
    _degenerate_found(n, len(mesh.faces), where)
    mesh.update_faces(~degenerate)
    mesh.remove_unreferenced_vertices()
    mesh.metadata["degenerate_removed"] = n


def _degenerate_found(n: int, n_faces: int, where: str, stacklevel: int = 5) -> None:
    """ConfigError when all ``n_faces`` are degenerate, else the MeshWarning that ``n`` are removed (at the
    line that loaded the mesh: ``stacklevel`` counts the frames up to it)."""
    if n == n_faces:
        raise ConfigError(f"all {n} triangles have zero area; nothing to inspect", path=where)
    warnings.warn(
        f"{where}: removed {n} zero-area triangle(s) of {n_faces}", MeshWarning, stacklevel=stacklevel
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
    check_extent(mesh.extents, path, min_extent_mm, max_extent_mm)


def check_extent(
    extents_mm: ArrayLike,
    path: str | Path,
    min_extent_mm: float = MIN_EXTENT_MM,
    max_extent_mm: float = MAX_EXTENT_MM,
) -> None:
    """:func:`check_units` of a mesh whose bounding box has the sides ``extents_mm``."""
    largest = float(np.max(extents_mm))
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
    import trimesh

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
    import trimesh

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
