"""Versioned calibration files: arrays in ``<name>.npz`` next to ``<name>.yaml`` metadata (camera and
projector
serials, resolutions, date, residual statistics), plus residual maps as PNG pictures.

An existing calibration is never replaced by a failed or worse one: :func:`save_calibration` compares the
``quality_key`` figure (lower is better) with the file on disk and refuses unless ``force``.
"""

from __future__ import annotations

import io
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from cell.errors import CalibrationError, ConfigError
from cell.runs import write_atomic

FORMAT_VERSION = 1
# calibration kind -> the field of the cell config's ``calibration:`` section that takes such a file
CONFIG_FIELDS = {
    "camera_intrinsics": "intrinsics",
    "projector": "projector",
    "projector_gamma": "gamma",
    "sensor_per_pixel": "sensor",
    "hand_eye": "hand_eye",
    "display_latency": "latency",
}


def config_lines(kind: str, path: str | Path) -> str | None:
    """The cell config lines that put calibration file ``path`` of ``kind`` to use, or None for a kind no
    single field takes (validation, kinematics with their hand-eye): routines print them, never edit the
    config themselves."""
    field = CONFIG_FIELDS.get(kind)
    return None if field is None else f"calibration:\n  {field}: {Path(path).resolve()}"


def _nested(d: dict[str, Any], key: str) -> float | None:
    cur: Any = d
    for part in key.split("."):
        if not isinstance(cur, dict) or part not in cur:
            return None
        cur = cur[part]
    return float(cur)


def save_calibration(
    path: Path,
    kind: str,
    arrays: dict[str, NDArray],
    meta: dict[str, Any],
    quality_key: str | None = None,
    force: bool = False,
    *,
    made_for: str | None = None,
) -> Path:
    """Write ``path``.yaml and ``path``.npz atomically; returns the YAML path. ``made_for`` is the
    fingerprint of the cell config the file was made with (:func:`cell.config.config_fingerprint`), recorded
    as ``cell_config_sha256`` so that a run can tell a current calibration from a stale one.

    If a calibration of the same kind exists at ``path`` and ``quality_key`` (a dotted key into ``meta``,
    lower is better) is given, the new one must not be worse unless ``force``."""
    path = Path(path)
    ypath, npath = path.with_suffix(".yaml"), path.with_suffix(".npz")
    if ypath.exists() and not force:
        old = load_metadata(ypath)
        if quality_key is None:
            raise CalibrationError(f"{ypath} exists; pass --force to replace it")
        new_q, old_q = _nested(meta, quality_key), _nested(old, quality_key)
        if old_q is not None and (new_q is None or new_q > old_q):
            raise CalibrationError(
                f"{ypath} exists and is better ({quality_key} {old_q:.6g} vs new "
                f"{new_q if new_q is None else f'{new_q:.6g}'}); kept it. Pass --force to "
                "replace it anyway"
            )
    full = {
        "format_version": FORMAT_VERSION,
        "kind": kind,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "arrays": npath.name,
        **({"cell_config_sha256": made_for} if made_for is not None else {}),
        **meta,
    }
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)  # type: ignore[arg-type]  # mypy maps **arrays onto allow_pickle
    write_atomic(npath, buf.getvalue())
    write_atomic(ypath, yaml.safe_dump(full, sort_keys=False).encode())
    return ypath


def load_metadata(path: Path) -> dict[str, Any]:
    """The YAML metadata of a calibration file; ConfigError if missing or not a calibration."""
    ypath = Path(path).with_suffix(".yaml")
    if not ypath.is_file():
        raise ConfigError("calibration file not found", path=str(ypath))
    # libyaml's parser where PyYAML has it (the same documents; 5.8 -> 0.75 ms of CPU for a calibrated
    # cell.yaml, PyYAML 6 on the 2-core machine: read again for each report)
    meta = yaml.load(ypath.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    if not isinstance(meta, dict) or "kind" not in meta:
        raise ConfigError("not a calibration file (no 'kind')", path=str(ypath))
    if meta.get("format_version") != FORMAT_VERSION:
        raise ConfigError(
            f"calibration format {meta.get('format_version')}, this cell reads {FORMAT_VERSION}",
            path=str(ypath),
            field="format_version",
        )
    return meta


def load_calibration(path: Path, kind: str) -> tuple[dict[str, Any], dict[str, NDArray]]:
    """(metadata, arrays) of a calibration of ``kind``."""
    meta = load_metadata(path)
    if meta["kind"] != kind:
        raise ConfigError(
            f"calibration of kind '{meta['kind']}', expected '{kind}'", path=str(path), field="kind"
        )
    npath = Path(path).with_suffix(".npz")
    if not npath.is_file():
        raise ConfigError("calibration arrays missing", path=str(npath))
    with np.load(npath) as z:
        return meta, {k: z[k] for k in z.files}


def save_map_png(path: Path, values: NDArray, lo: float | None = None, hi: float | None = None) -> None:
    """A colour picture (turbo colour map, NaN black) of a per-pixel map, scaled from ``lo`` to ``hi``."""
    v = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(v)
    lo = float(np.nanpercentile(v, 1)) if lo is None and ok.any() else (lo or 0.0)
    hi = float(np.nanpercentile(v, 99)) if hi is None and ok.any() else (hi or 1.0)
    scaled = np.clip((np.nan_to_num(v, nan=lo) - lo) / max(hi - lo, 1e-12), 0, 1)
    img = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[~ok] = 0
    ok_w, data = cv2.imencode(".png", img)
    write_atomic(Path(path), data.tobytes())
