"""One structured-light view through the device contracts: show each pattern, trigger, grab, then check,
decode and triangulate. The controller and ``cell scan`` both call :func:`scan_view`."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cell.contracts import Camera, Projector
from cell.sensing.decode import Decoded, DecodeParams, Reason, decode
from cell.sensing.patterns import PatternSet
from cell.sensing.stack import check_stack
from cell.sensing.triangulate import SensorCloud, Triangulator


@dataclass
class ViewScan:
    """What one view produced: the organised cloud in {C}, the decoding, and timings (s) per stage."""

    cloud: SensorCloud
    decoded: Decoded
    timings_s: dict[str, float] = field(default_factory=dict)

    def reason_counts(self) -> dict[str, int]:
        """Pixels per reason (a pixel can count under several) and valid points."""
        r = self.cloud.reasons
        out = {reason.name.lower(): int(np.count_nonzero(r & np.uint8(reason))) for reason in Reason}
        out["valid"] = int(np.count_nonzero(r == 0))
        return out


def capture_stack(
    camera: Camera, projector: Projector, patterns: PatternSet, timeout_ms: float = 2000.0
) -> list[NDArray]:
    """Show every frame of ``patterns`` in order and grab one camera image of each (software trigger)."""
    projector.load_sequence(list(patterns.frames))
    images = []
    for _ in range(len(patterns)):
        projector.step()
        camera.trigger()
        images.append(camera.grab(timeout_ms).pixels)
    return images


def scan_view(
    camera: Camera,
    projector: Projector,
    patterns: PatternSet,
    triangulator: Triangulator,
    *,
    bit_depth: int,
    params: DecodeParams = DecodeParams(),
    timeout_ms: float = 2000.0,
) -> ViewScan:
    """Capture, check, decode and triangulate one view. Devices must be connected, the projector on HDMI and
    the camera in software-trigger mode with ``bit_depth`` pixels."""
    t0 = time.perf_counter()
    images = capture_stack(camera, projector, patterns, timeout_ms)
    t1 = time.perf_counter()
    stack = check_stack(images, patterns, camera.resolution, bit_depth, source=f"camera '{camera.name}'")
    decoded = decode(stack, patterns, bit_depth, params)
    t2 = time.perf_counter()
    cloud = triangulator.triangulate(decoded)
    t3 = time.perf_counter()
    return ViewScan(cloud, decoded, {"capture": t1 - t0, "decode": t2 - t1, "triangulate": t3 - t2})
