"""Binary STL and PLY files read with numpy alone, for the commands that must start fast (``cell compare``):
importing trimesh costs about 1 s of CPU (it imports scipy.spatial and scipy.optimize), more than
CloudCompare's whole comparison of 200k points.

Only plain layouts are read here: a binary STL whose size matches its triangle count, and a binary PLY
(either endianness) whose vertex element holds scalar properties including x, y, z and whose face element,
if any, holds triangles in its one list property. Anything else -- ASCII files, quads, vertex normals or
colours on a mesh, list properties on vertices, a short file -- returns None, and the caller reads the file
with trimesh, which then gives its own result or error. What is read equals what trimesh reads
(``trimesh.load(..., process=False)``): float64 vertices and int64 faces in the file's order;
tests/test_mesh_files.py checks it file by file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

_STL_RECORD = np.dtype([("normals", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attributes", "<u2")])
_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
# vertex properties that make trimesh's mesh more than positions (merge_vertices then groups by them too)
_MESH_VERTEX_EXTRAS = {"nx", "ny", "nz", "red", "green", "blue", "alpha", "s", "t", "u", "v", "texture_u"}


@dataclass(frozen=True)
class PlyData:
    """A PLY file's vertex positions (N, 3) float64 and triangles (F, 3) int64 (None: no face element), and
    the names of its vertex properties."""

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64] | None
    vertex_properties: tuple[str, ...]


def read_binary_stl(path: str | os.PathLike[str]) -> tuple[NDArray[np.float64], NDArray[np.int64]] | None:
    """Vertices (3F, 3) and faces (F, 3) of a binary STL as trimesh loads it (one vertex per corner, not
    merged); None when the file is not a plain binary STL with at least one triangle."""
    with open(path, "rb") as fh:
        head = fh.read(84)
        if len(head) < 84:
            return None
        n = int(np.frombuffer(head, "<u4", count=1, offset=80)[0])
        if n == 0 or os.fstat(fh.fileno()).st_size != 84 + n * _STL_RECORD.itemsize:
            return None
        records = np.fromfile(fh, dtype=_STL_RECORD, count=n)
    if len(records) != n:
        return None
    vertices = records["vertices"].reshape(-1, 3).astype(np.float64)
    return vertices, np.arange(3 * n, dtype=np.int64).reshape(-1, 3)


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type); list properties: ("list", "count:item") name


def _header(fh: BinaryIO) -> tuple[str, list[_Element]] | None:
    """Format and elements of a PLY header (the file positioned after end_header), or None."""
    read = fh.readline
    if read().strip() != b"ply":
        return None
    fmt, elements = "", list[_Element]()
    for _ in range(10_000):
        line = read()
        if not line:
            return None
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            return (fmt, elements) if fmt else None
        if words[0] == "format" and len(words) == 3 and words[2] == "1.0":
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append(_Element(words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPES:
            elements[-1].properties.append((words[2], _PLY_TYPES[words[1]]))
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list":
            if words[2] not in _PLY_TYPES or words[3] not in _PLY_TYPES:
                return None
            elements[-1].properties.append((words[4], f"list:{_PLY_TYPES[words[2]]}:{_PLY_TYPES[words[3]]}"))
        else:
            return None
    return None


def read_ply(path: str | os.PathLike[str], mesh: bool) -> PlyData | None:
    """Vertices and triangles of a plain PLY (see the module's docstring), or None for trimesh to read.

    ``mesh``: read as a triangle mesh (vertex normals, colours or texture coordinates make it trimesh's),
    else as a cloud (only the positions matter; a face element is skipped)."""
    with open(path, "rb") as fh:
        parsed = _header(fh)
        if parsed is None:
            return None
        fmt, elements = parsed
        names = [e.name for e in elements]
        if (
            "vertex" not in names
            or any(n not in ("vertex", "face") for n in names)
            or len(set(names)) != len(names)
        ):
            return None
        vertex = elements[names.index("vertex")]
        props = [p for p, _ in vertex.properties]
        if vertex.count == 0 or not {"x", "y", "z"} <= set(props):
            return None
        if any(t.startswith("list") for _, t in vertex.properties):
            return None
        if mesh and _MESH_VERTEX_EXTRAS & set(props):
            return None
        face = elements[names.index("face")] if "face" in names else None
        if face is not None and (len(face.properties) != 1 or not face.properties[0][1].startswith("list")):
            return None
        if fmt not in ("binary_little_endian", "binary_big_endian"):
            return None
        order = "<" if fmt == "binary_little_endian" else ">"
        vertices = faces = None
        for element in elements:
            if element is vertex:
                dtype = np.dtype([(p, order + t) for p, t in element.properties])
                data = np.fromfile(fh, dtype=dtype, count=element.count)
                if len(data) != element.count:
                    return None
                vertices = np.column_stack([data[k].astype(np.float64) for k in ("x", "y", "z")])
            else:  # the face element: triangles only
                faces = _binary_triangles(fh, element, order)
                if faces is None:
                    return None
    assert vertices is not None
    return PlyData(vertices, faces, tuple(props))


def _binary_triangles(fh: BinaryIO, element: _Element, order: str) -> NDArray[np.int64] | None:
    """The face element's rows as (F, 3) int64, when every row is a triangle."""
    _, count_t, item_t = element.properties[0][1].split(":")
    dtype = np.dtype([("n", order + count_t), ("v", order + item_t, (3,))])
    data = np.fromfile(fh, dtype=dtype, count=element.count)
    if len(data) != element.count or (data["n"] != 3).any():
        return None
    return data["v"].astype(np.int64)


def read_plain_mesh(path: Path) -> tuple[NDArray[np.float64], NDArray[np.int64]] | None:
    """Vertices and faces of a plain binary STL or triangle PLY, as trimesh loads them; else None."""
    suffix = path.suffix.lower()
    if suffix == ".stl":
        return read_binary_stl(path)
    if suffix == ".ply":
        ply = read_ply(path, mesh=True)
        if ply is not None and ply.faces is not None and len(ply.faces):
            return ply.vertices, ply.faces
    return None
