"""Display latency: how long after the display's present stamp a new pattern fully lights the scene.

Measured on the live cell through the device contracts only: the projector shows black, then white; the
camera (software trigger, the configured exposure E) is triggered at a delay d after the white frame's present
stamp. Over the pixels the projector lights, the white share f(d) of the image is 0 while the exposure ends
before the light arrives, 1 once it starts after, and on the ramp in between f = (d + E - L) / E for a steady
light source. Every ramp point gives L = d + E (1 - f); their mean is the latency, which does not depend on
the delay step. A DLP projector's bit planes bend the ramp within a frame, but black and white are all planes
on or off, so they do not.

The result goes into a calibration file (``calibration.latency`` in the cell config), which
:func:`cell.config.load_cell_config` puts into ``sensor.projector.timing.latency_ms``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cell.config import CellConfig, ProjectorConfig, config_fingerprint
from cell.contracts import Camera, Projector, TimedProjector
from cell.errors import CalibrationError, ConfigError, DeviceFault
from cell.storage import require_writable

KIND = "display_latency"
RAMP = (0.05, 0.95)  # white shares that count as on the ramp
MARGIN_MS = 0.5  # added to the measured latency for present-stamp jitter


@dataclass(frozen=True)
class LatencyMeasurement:
    """Delays tried (s after the present stamp), white share at each, the latency estimate and its spread."""

    delays_s: np.ndarray
    white_share: np.ndarray
    exposure_s: float
    latency_s: float
    spread_s: float

    @property
    def latency_ms(self) -> float:
        """What the scan should wait (ms): the measured latency plus the jitter margin."""
        return self.latency_s * 1e3 + MARGIN_MS


def measure_latency(
    camera: Camera,
    projector: Projector,
    *,
    exposure_ms: float,
    max_frames: float = 8.0,
    steps_per_frame: int = 4,
    timeout_ms: float = 2000.0,
) -> LatencyMeasurement:
    """Measure the display latency. The projector must be on (HDMI source), the camera connected in software
    trigger with ``exposure_ms``, and the view must see a surface the projector lights."""
    if not isinstance(projector, TimedProjector):
        raise DeviceFault(
            projector.name,
            "cannot measure latency: the projector does not stamp its presents (last_present_s)",
        )
    clock, timing = projector.clock, projector.timing
    period = 1.0 / timing.refresh_hz
    w, h = projector.resolution
    black, white = np.zeros((h, w), np.uint8), np.full((h, w), 255, np.uint8)
    exposure = exposure_ms * 1e-3

    def frame_after(image: np.ndarray, delay_s: float) -> np.ndarray:
        projector.show(image)
        clock.sleep(max(0.0, projector.last_present_s + delay_s - clock.now()))
        camera.trigger()
        return np.asarray(camera.grab(timeout_ms).pixels, np.float64)

    settle = max_frames * period + exposure
    dark = frame_after(black, settle)
    bright = frame_after(white, settle)
    contrast = bright - dark
    lit = contrast > 0.2 * max(float(contrast.max()), 1e-9)
    if np.count_nonzero(lit) < 100:
        raise CalibrationError(
            f"projector '{projector.name}' lights fewer than 100 camera pixels: aim the sensor at a matte "
            "surface within its depth of field, lamp on, source HDMI"
        )
    delays = np.arange(0.0, settle + 1e-12, period / steps_per_frame)
    shares = []
    for d in delays:
        frame_after(black, settle)  # the scene is dark again, whatever was shown before
        image = frame_after(white, float(d))
        shares.append(float(np.median((image[lit] - dark[lit]) / contrast[lit])))
    share = np.clip(np.asarray(shares), 0.0, 1.0)
    on_ramp = (share > RAMP[0]) & (share < RAMP[1])
    if np.count_nonzero(on_ramp) == 0:
        full = delays[share >= RAMP[1]]
        if len(full) == 0:
            raise CalibrationError(
                f"the white frame never fully reached the camera within {max_frames:g} frames of the "
                "present: raise max_frames or check that the projector shows the pattern display"
            )
        estimates = np.array([full[0]])  # exposure shorter than a delay step: bounded by the first full one
    else:
        estimates = delays[on_ramp] + exposure * (1.0 - share[on_ramp])
    return LatencyMeasurement(
        delays,
        share,
        exposure,
        float(np.mean(estimates)),
        float(np.ptp(estimates)) if len(estimates) else 0.0,
    )


def calibrate_latency(
    cfg: CellConfig, out: Path, *, max_frames: float = 8.0, steps_per_frame: int = 4, force: bool = False
) -> tuple[Path, dict[str, Any]]:
    """``cell calibrate latency``: measure the display latency on ``cfg``'s devices (the robot is not moved)
    and save it as ``out/latency.yaml`` (an existing one is replaced only with ``force``); returns (the file,
    its metadata)."""
    from cell.calibration.store import save_calibration
    from cell.devices import build_devices, ready_to_capture

    require_writable(out)  # before the measurement: a full disk or read-only folder would lose it
    devices = build_devices(cfg)
    with ready_to_capture(devices, cfg.sensor.camera) as settings:
        m = measure_latency(
            devices.camera,
            devices.projector,
            exposure_ms=settings.exposure_ms,
            max_frames=max_frames,
            steps_per_frame=steps_per_frame,
        )
    out.mkdir(parents=True, exist_ok=True)
    meta = latency_meta(m, cfg.sensor.projector)
    arrays = {"delays_s": m.delays_s, "white_share": m.white_share}
    made_for = config_fingerprint(cfg)
    return save_calibration(out / "latency", KIND, arrays, meta, force=force, made_for=made_for), meta


def latency_meta(m: LatencyMeasurement, projector: ProjectorConfig) -> dict[str, Any]:
    """Metadata of a latency calibration file (see :func:`cell.calibration.store.save_calibration`)."""
    return {
        "projector": {
            "name": projector.name,
            "model": projector.model,
            "refresh_hz": projector.timing.refresh_hz,
        },
        "latency_ms": round(m.latency_ms, 4),
        "figures": {
            "measured_ms": round(m.latency_s * 1e3, 4),
            "spread_ms": round(m.spread_s * 1e3, 4),
            "margin_ms": MARGIN_MS,
            "exposure_ms": m.exposure_s * 1e3,
            "delays_ms": [round(float(d) * 1e3, 4) for d in m.delays_s],
            "white_share": [round(float(s), 4) for s in m.white_share],
        },
    }


def load_latency(path: Path, projector: ProjectorConfig, cell_path: str | Path) -> float:
    """The latency (ms) of a calibration file, refused when it was measured on another projector or rate."""
    from cell.calibration.store import load_metadata

    meta = load_metadata(Path(path))
    if meta.get("kind") != KIND:
        raise ConfigError(f"{path} is a '{meta.get('kind')}' calibration, not {KIND}", path=str(cell_path))
    who = meta.get("projector", {})
    if who.get("name") != projector.name or who.get("refresh_hz") != projector.timing.refresh_hz:
        raise ConfigError(
            f"latency in {path} was measured on projector '{who.get('name')}' at {who.get('refresh_hz')} "
            f"Hz, this cell has '{projector.name}' at {projector.timing.refresh_hz:g} Hz: run "
            "`cell calibrate latency`",
            path=str(cell_path),
            field="calibration.latency",
        )
    return float(meta["latency_ms"])
