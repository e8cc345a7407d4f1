"""The report's files on disk: the cloud (PLY with its deviation field, CSV on request) and writing the whole
set of files so that a reader never finds half of one.

Every file of a report is first written to a hidden temporary file beside its target and flushed to disk;
only when all of them are written are they renamed into place, ``report.json`` last (it is what readers
look for first). An error raised while writing leaves the previous report as it was (or no report) and no
partial file; a process killed while writing leaves the same, plus hidden ``.NAME.*.partial`` files that
the next report removes. A folder that cannot take the files (a full disk, a read-only file system, no
permission) is a :class:`cell.errors.StorageError` naming it and the file (:mod:`cell.storage`): a run
under the controller pauses on it and is resumed once there is room; a command ends with one line. The
commands refuse such a folder before any work (:func:`cell.storage.require_writable`, exit code 2).

PLY: binary little-endian, vertex ``x y z`` float (float32, mm, part frame), ``deviation`` float (mm, +
outside the material), then optional fields (``isolated`` uchar: an out-of-tolerance point set aside as an
isolated outlier, not judged, written when there is one; ``uncertainty`` ushort: the point's standard
uncertainty u, cell.analysis.uncertainty, in steps of 0.1 um rounded up, 65535 where unknown:
:func:`encode_uncertainty`; the glass normals ``nx ny nz`` double). CloudCompare and MeshLab
show every field as a scalar field. float32 keeps 24 significant bits: a coordinate is rounded by at most half
a step of 2^-23 of its power of two, 7.6 nm below 256 mm, 15 nm below 512 mm (docs/storage.md), against the
sensor's 20-30 um noise; 16 bytes a point with the deviation instead of 28. Files written before (``x y z``
double) read as they are. An inspection judges the cloud as stored (:func:`stored_points`), so a rebuilt
report gives the same figures.
"""

from __future__ import annotations

import errno
import os
import secrets
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cell.errors import ConfigError, StorageError
from cell.storage import fsync_path, is_storage_error, storage_error

Writer = Callable[[Path], None]
COORDINATE_DTYPE = np.dtype("<f4")  # x, y, z in cloud.ply
_PLY_TYPES = {"double": "<f8", "float": "<f4", "uchar": "u1", "ushort": "<u2"}


def stored_points(points_mm: NDArray, in_place: bool = False) -> NDArray[np.float64]:
    """The points (N, 3, float64) as :func:`write_ply` stores them: each coordinate rounded to float32
    (``in_place``: rounded in ``points_mm`` itself, a float64 array the caller owns: no second array)."""
    if in_place:
        points_mm[...] = points_mm.astype(COORDINATE_DTYPE)
        return points_mm
    return np.asarray(points_mm).astype(COORDINATE_DTYPE).astype(np.float64)


UNCERTAINTY_STEP_MM = 1e-4  # u in cloud.ply: ushort steps of 0.1 um
_U_UNKNOWN = 65535  # u not known (NaN)


def encode_uncertainty(u_mm: NDArray) -> NDArray[np.uint16]:
    """u (mm) as cloud.ply stores it: ushort steps of 0.1 um, rounded up (a stored u is never smaller than
    the computed one, so the guarded rule stays on the safe side), at most 6.5534 mm (a U of 13 mm leaves no
    conformance zone in any band the cell measures); NaN (not known) as 65535. 2 bytes a point instead of 4:
    PLY has no 16-bit float type that CloudCompare or MeshLab read."""
    u = np.asarray(u_mm, dtype=np.float64)
    steps = np.nan_to_num(u, nan=0.0)  # a copy, then worked on in place (a million points' u: 16 MB an array)
    np.divide(steps, UNCERTAINTY_STEP_MM, out=steps)
    np.subtract(steps, 1e-6, out=steps)
    np.clip(np.ceil(steps, out=steps), 0, _U_UNKNOWN - 1, out=steps)
    codes = steps.astype(np.uint16)
    if not (finite := np.isfinite(u)).all():
        codes[~finite] = _U_UNKNOWN
    return codes


def decode_uncertainty(codes: NDArray) -> NDArray[np.float64]:
    """u (mm) from cloud.ply's ``uncertainty`` column: ushort steps (:func:`encode_uncertainty`), or float
    (float32 mm, clouds written by this branch before the ushort column)."""
    c = np.asarray(codes)
    if c.dtype.kind == "f":
        return c.astype(np.float64)
    u = c.astype(np.float64)
    u *= UNCERTAINTY_STEP_MM
    u[c == _U_UNKNOWN] = np.nan
    return u


def write_ply(
    path: Path,
    points_mm: NDArray,
    deviation_mm: NDArray | None = None,
    fields: Mapping[str, NDArray] | None = None,
) -> None:
    """A binary PLY of the points (coordinates as float32: :func:`stored_points`), with ``deviation``
    (float) when given and the extra per-point ``fields`` (bool as uchar, float64 as double, others as
    float, uint16 as ushort)."""
    columns: list[tuple[str, NDArray, str, str]] = [
        (c, np.asarray(points_mm)[:, k], COORDINATE_DTYPE.str, "float") for k, c in enumerate("xyz")
    ]
    if deviation_mm is not None:
        columns.append(("deviation", np.asarray(deviation_mm), "<f4", "float"))
    for name, values in (fields or {}).items():
        values = np.asarray(values)
        kind = {
            np.dtype(bool): ("u1", "uchar"),
            np.dtype(np.uint16): ("<u2", "ushort"),
            np.dtype(np.float64): ("<f8", "double"),
        }.get(values.dtype, ("<f4", "float"))
        columns.append((name, values, *kind))
    rec = np.empty(len(points_mm), dtype=[(n, t) for n, _, t, _ in columns])
    for name, values, _, _ in columns:
        rec[name] = values
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment units mm, part frame; deviation = signed distance to "
        f"the nominal, mm, + outside the material\nelement vertex {len(rec)}\n"
        + "".join(f"property {ply} {name}\n" for name, _, _, ply in columns)
        + "end_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())


def read_ply_points(path: Path) -> NDArray[np.float64]:
    """The x, y, z (N, 3, float64) of a PLY written by :func:`write_ply` (float, or double before), exactly
    as stored."""
    with open(path, "rb") as fh:
        head = b""
        while not head.endswith(b"end_header\n"):
            line = fh.readline()
            if not line:
                raise ConfigError("not a PLY file written by the cell (no end_header)", path=str(path))
            head += line
        props, n = [], 0
        for text in head.decode("ascii").splitlines():
            words = text.split()
            if words[:2] == ["element", "vertex"]:
                n = int(words[2])
            elif words[:1] == ["property"]:
                props.append((words[2], _PLY_TYPES[words[1]]))
        rec = np.fromfile(fh, dtype=np.dtype(props), count=n)
    if len(rec) != n:
        raise ConfigError(f"the PLY file is truncated ({len(rec)} of {n} points)", path=str(path))
    return np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)


def read_ply_field(path: Path, name: str) -> NDArray | None:
    """The per-point field ``name`` of a PLY written by :func:`write_ply` as stored (e.g. ``uncertainty``:
    :func:`decode_uncertainty` gives mm), or None when the file has no such field."""
    with open(path, "rb") as fh:
        props, n = [], 0
        while (line := fh.readline()) != b"end_header\n":
            if not line:
                raise ConfigError("not a PLY file written by the cell (no end_header)", path=str(path))
            words = line.decode("ascii").split()
            if words[:2] == ["element", "vertex"]:
                n = int(words[2])
            elif words[:1] == ["property"]:
                props.append((words[2], _PLY_TYPES[words[1]]))
        if name not in [p for p, _ in props]:
            return None
        rec = np.fromfile(fh, dtype=np.dtype(props), count=n)
    if len(rec) != n:
        raise ConfigError(f"the PLY file is truncated ({len(rec)} of {n} points)", path=str(path))
    return np.asarray(rec[name])


def write_csv(path: Path, points_mm: NDArray, deviation_mm: NDArray) -> None:
    """deviations.csv: x_mm,y_mm,z_mm,deviation_mm (5 decimals: 10 nm)."""
    np.savetxt(
        path,
        np.column_stack([points_mm, deviation_mm]),
        fmt="%.5f",
        delimiter=",",
        header="x_mm,y_mm,z_mm,deviation_mm",
        comments="",
    )


def _unwritable(exc: OSError, out_dir: Path, name: str | None) -> StorageError:
    """The StorageError (:mod:`cell.storage`) of a write into ``out_dir`` that failed for want of space or
    permission, naming the report file it was writing (not its temporary name)."""
    target = str(out_dir / name) if name else str(out_dir)
    named = OSError(exc.errno or errno.ENOSPC, exc.strerror or os.strerror(errno.ENOSPC), target)
    return storage_error(named, out_dir)


def write_file_set(out_dir: Path, writers: Mapping[str, Writer], remove: tuple[str, ...] = ()) -> None:
    """Write every file ``name -> writer(path)`` into ``out_dir`` all or none: each to a temporary file,
    then renamed into place in the given order (put ``report.json`` last); files named in ``remove`` (a
    previous report's that this one does not have) are deleted before the renames."""
    out_dir = Path(out_dir)
    temps: list[Path] = []
    name: str | None = None
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        # what a killed writer left (one writer per folder at a time: the run lock, an empty --out)
        for known in (*writers, *remove):
            for stale in out_dir.glob(f".{known}.*.partial"):
                stale.unlink(missing_ok=True)
        staged = {}
        for name, write in writers.items():
            tmp = out_dir / f".{name}.{os.getpid()}-{secrets.token_hex(4)}.partial"
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))  # the umask applies
            temps.append(tmp)
            write(tmp)
            fsync_path(tmp)
            staged[name] = tmp
        name = None
        for old in remove:
            (out_dir / old).unlink(missing_ok=True)
        for done, staged_tmp in staged.items():
            os.replace(staged_tmp, out_dir / done)
        fsync_path(out_dir)
    except OSError as exc:
        if is_storage_error(exc, out_dir):
            raise _unwritable(exc, out_dir, name) from exc
        raise
    finally:
        for tmp in temps:
            tmp.unlink(missing_ok=True)
