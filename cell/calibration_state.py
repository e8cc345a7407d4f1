"""The calibration an inspection measures with, as the run records it: which files, how old, made for which
cell config, how good, and whether the recipe's ``requires_calibration`` is met.

A calibration file (cell.calibration.store) records ``created_utc`` and, since issue 12, the fingerprint of
the cell config it was made for (``cell_config_sha256`` = :func:`cell.config.config_fingerprint`). A file made
for another version of the config is stale: the robot, the sensor or the scene changed after it was made.
Quality limits (below) catch a calibration that converged badly.
"""

from __future__ import annotations

import time
from datetime import datetime
from pathlib import Path
from typing import Any

from cell.calibration.store import load_metadata
from cell.config import CalibrationFiles, CellConfig, config_fingerprint

# a calibration whose recorded residual exceeds these is poor (reprojection rms of a camera or of the
# projector-camera stereo fit; rms of the hand-eye or sensor fit in mm); ``quality.acceptable: false`` too
QUALITY_LIMITS = {"rms_px": 1.0, "rms_mm": 0.1}


def _age_s(created: str | None, path: Path, now: float) -> tuple[float, str]:
    """Age in seconds from the file's ``created_utc`` (else its modification time) and which it used."""
    if created:
        try:
            return now - datetime.fromisoformat(created).timestamp(), "created_utc"
        except ValueError:
            pass
    return now - path.with_suffix(".yaml").stat().st_mtime, "mtime"


def file_state(field: str, path: Path, fingerprint: str, now: float) -> dict[str, Any]:
    """One calibration file: name, kind, creation, age, the config it was made for, quality and problems."""
    meta = load_metadata(path)
    created = meta.get("created_utc")
    age, age_from = _age_s(created, Path(path), now)
    made_for = meta.get("cell_config_sha256")
    quality = meta.get("quality") or {}
    problems = []
    if made_for is None:
        problems.append(
            f"{field}: {Path(path).name} records no cell_config_sha256, so nothing tells which cell "
            "config it was made for; recalibrate"
        )
    elif made_for != fingerprint:
        problems.append(
            f"{field}: {Path(path).name} is stale: it was made for another version of the cell "
            "config (robot, sensor or scene changed since); recalibrate"
        )
    if quality.get("acceptable") is False:
        problems.append(f"{field}: {Path(path).name} is marked not acceptable by its routine")
    for key, limit in QUALITY_LIMITS.items():
        value = quality.get(key)
        if isinstance(value, int | float) and value > limit:
            problems.append(f"{field}: {Path(path).name} is poor: quality.{key} = {value:.4g} > {limit}")
    return {
        "field": field,
        "file": Path(path).name,
        "kind": meta.get("kind"),
        "created_utc": created,
        "age_days": round(age / 86400.0, 4),
        "age_from": age_from,
        "made_for_this_config": None if made_for is None else made_for == fingerprint,
        "quality": {k: v for k, v in quality.items() if isinstance(v, int | float | bool)},
        "problems": problems,
    }


def calibration_state(cfg: CellConfig, required: bool, now: float | None = None) -> dict[str, Any]:
    """The run's calibration: every file the cell config names, and ``incomplete_reasons`` (non-empty only
    when ``required``): a missing geometry or hand-eye calibration, or a stale or poor file."""
    now = time.time() if now is None else now
    fingerprint = config_fingerprint(cfg)
    cal = cfg.calibration
    files = [
        file_state(field, getattr(cal, field), fingerprint, now)
        for field in CalibrationFiles.model_fields
        if getattr(cal, field) is not None
    ]
    reasons: list[str] = []
    if required:
        if cal.sensor is None and (cal.intrinsics is None or cal.projector is None):
            missing = [f for f in ("intrinsics", "projector") if getattr(cal, f) is None]
            reasons.append(
                f"the recipe requires calibration; the cell has no {' and no '.join(missing)} "
                "calibration (nor a sensor calibration): run `cell calibrate`"
            )
        if cal.hand_eye is None:
            reasons.append(
                "the recipe requires calibration; the cell has no hand-eye calibration: run "
                "`cell calibrate handeye`"
            )
        reasons += [p for f in files for p in f["problems"]]
    return {
        "required": required,
        "cell_config_sha256": fingerprint,
        "files": files,
        "incomplete_reasons": reasons,
    }
