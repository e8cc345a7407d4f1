"""One structured-light view through the device contracts: show each pattern, trigger, grab, then check,
decode and triangulate. The jobs under the controller grab through :func:`capture_stack` (and decode
later, while the robot moves); ``cell scan`` (:func:`cell.scan_run.scan_in_cell`) calls :func:`scan_view`.

Synchronisation (docs/hardware.md, "Synchronisation"): a projector shows a frame some time after it was
presented at its input (its latency), so

* software trigger: after each present the scan waits, on the projector's clock, until the present stamp
  plus the latency (``timing``: measured by ``cell calibrate latency``, else an upper bound), then triggers;
* hardware trigger: the projector's sync or trigger output exposes the camera; the frames are placed by the
  camera's frame ids (a skipped id is a lost frame) and a lost one is captured again.

Either way every pattern/inverse pair is checked: the two images must add up to white + black wherever the
pattern has contrast. A pair that does not (an old or mixed frame: the latency grew, a vertical blank was
missed) is captured again, one frame period later each time, up to ``timing.max_recaptures`` times; then the
view fails with a retryable error that names the projector.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray

from cell.contracts import Camera, Frame, Projector, SequenceProjector, TimedProjector, TriggerMode
from cell.errors import ConfigError, DeviceProtocolError, DeviceTimeout
from cell.sensing.decode import Decoded, DecodeParams, Reason, decode
from cell.sensing.patterns import PatternSet
from cell.sensing.stack import check_stack
from cell.sensing.triangulate import (
    SensorCloud,
    Triangulator,
)

MIN_CONTRAST = 0.1  # of the camera's range: pixels darker in white - black are not checked
MAX_PAIR_ERROR = 0.25  # |a + b - (white + black)| above this share of the contrast marks a bad pixel
MAX_BAD_SHARE = 0.01  # a pair with more bad pixels than this (of the checked ones) is re-captured
MIN_PIXELS = 100  # fewer lit (or wrong) pixels than this are not evidence either way
MAX_SAMPLES = 50_000  # pixels checked per image, evenly spread


@dataclass
class ViewScan:
    """What one view produced: the organised cloud in {C}, the decoding, timings (s) per stage, and what
    synchronisation re-captured."""

    cloud: SensorCloud
    decoded: Decoded
    timings_s: dict[str, float] = field(default_factory=dict)
    capture: CaptureLog | None = None

    def reason_counts(self) -> dict[str, int]:
        """Pixels per reason (a pixel can count under several) and valid points."""
        r = self.cloud.reasons
        out = {str(reason.name).lower(): int(np.count_nonzero(r & np.uint8(reason))) for reason in Reason}
        out["valid"] = int(np.count_nonzero(r == 0))
        return out


@dataclass
class CaptureLog:
    """What synchronisation did during one stack: re-captured frames by name and the final extra wait (s)."""

    recaptured: list[str] = field(default_factory=list)
    extra_wait_s: float = 0.0


def pattern_pairs(patterns: PatternSet) -> list[tuple[int, int]]:
    """(pattern, inverse) frame indices, white/black first: every pair whose images must add up alike."""
    names = patterns.names
    pairs = []
    if "white" in names and "black" in names:
        pairs.append((names.index("white"), names.index("black")))
    pairs += [(i, names.index(n + "_inv")) for i, n in enumerate(names) if n + "_inv" in names]
    return pairs


def pair_groups(patterns: PatternSet, pairs: list[tuple[int, int]]) -> list[int]:
    """Group number of each pair (after white/black): pairs whose pattern + inverse light the same projector
    pixels (one coded axis) must give the same camera sum."""
    keys: dict[bytes, int] = {}
    out = []
    step = max(1, patterns.frames[0].size // MAX_SAMPLES)
    flat = patterns.frames.reshape(len(patterns), -1)[:, ::step]
    for a, b in pairs[1:]:
        lit = (flat[a].astype(np.uint16) + flat[b]).tobytes()
        out.append(keys.setdefault(lit, len(keys)))
    return out


def bad_pairs(
    images: list[NDArray | None], pairs: list[tuple[int, int]], groups: list[int], bit_depth: int
) -> list[tuple[int, int]]:
    """Pairs whose images are inconsistent: white not brighter than black, or pattern + inverse differing
    from the other pairs of its group (the per-pixel median: a minority of bad pairs cannot move it) where
    the pattern has contrast. A missing image makes its pair bad."""
    if not pairs or any(images[i] is None for i in pairs[0]):
        return list(pairs)
    iw, ib = pairs[0]
    size = np.asarray(images[iw]).size
    step = max(1, size // MAX_SAMPLES)  # an old or mixed frame spans the image: a pixel sample shows it

    def sample(k: int) -> NDArray[np.float32]:
        return np.asarray(images[k]).reshape(-1)[::step].astype(np.float32)

    white, black = sample(iw), sample(ib)
    contrast = white - black
    top = float(2**bit_depth - 1)
    lit = (contrast > MIN_CONTRAST * top) & (white < 0.98 * top)  # saturation breaks a + b = constant
    n_lit = np.count_nonzero(lit)
    wrong_way = np.count_nonzero(contrast < -MIN_CONTRAST * top)
    brightest = np.max(np.stack([sample(k) for k, im in enumerate(images) if im is not None]), axis=0)
    brighter_than_white = np.count_nonzero(brightest - white > MIN_CONTRAST * top)
    if max(wrong_way, brighter_than_white) > max(MAX_BAD_SHARE * n_lit, MIN_PIXELS):
        return list(pairs)  # white/black themselves are old or mixed frames: all of it again
    if n_lit < MIN_PIXELS:
        return []  # the projector lights nothing the camera sees: nothing to check, nothing to measure
    tolerance = MAX_PAIR_ERROR * contrast[lit]
    out = []
    for group in sorted(set(groups)):
        members = [pair for pair, g in zip(pairs[1:], groups, strict=True) if g == group]
        sums, kept = [], []
        for a, b in members:
            if images[a] is None or images[b] is None:
                out.append((a, b))
                continue
            sums.append(sample(a)[lit] + sample(b)[lit])
            kept.append((a, b))
        if not sums:
            continue
        reference = np.median(np.stack(sums), axis=0) if len(sums) >= 3 else (white + black)[lit]
        for pair, total in zip(kept, sums, strict=True):
            if np.count_nonzero(np.abs(total - reference) > tolerance) > MAX_BAD_SHARE * total.size:
                out.append(pair)
    return out


def _camera_trigger_mode(camera: Camera) -> TriggerMode:
    settings = getattr(camera, "settings", None)
    return TriggerMode(settings.trigger) if settings is not None else TriggerMode.SOFTWARE


def _check_exposure(camera: Camera, timing: Any) -> None:
    settings = getattr(camera, "settings", None)
    if timing is None or settings is None:
        return
    try:
        timing.check_exposure(settings.exposure_ms, f"camera '{camera.name}' exposure")
    except ValueError as exc:
        raise ConfigError(str(exc), field="sensor.camera.exposure_ms") from exc


class _Capture:
    """Captures single patterns on one projector/camera pair with the right waits."""

    def __init__(self, camera: Camera, projector: Projector, timeout_ms: float) -> None:
        self.camera, self.projector, self.timeout_ms = camera, projector, timeout_ms
        self.timed = isinstance(projector, TimedProjector)
        self.timing = getattr(projector, "timing", None) if self.timed else None
        self.latency_s = self.timing.assumed_latency_s() if self.timing is not None else 0.0
        self.period_s = 1.0 / self.timing.refresh_hz if self.timing is not None else 0.0
        self.extra_s = 0.0
        self.hardware = _camera_trigger_mode(camera) is TriggerMode.HARDWARE

    def after_present(self) -> Frame | None:
        """The frame of what was just presented; None when a hardware-triggered frame was lost."""
        if self.hardware:  # the sync output starts the exposure: nothing to wait for here
            try:
                return self.camera.grab(self.timeout_ms)
            except DeviceTimeout:
                return None
        if self.timed:
            clock = self.projector.clock  # type: ignore[attr-defined]
            due = self.projector.last_present_s + self.latency_s + self.extra_s  # type: ignore[attr-defined]
            clock.sleep(max(0.0, due - clock.now()))
        self.camera.trigger()
        return self.camera.grab(self.timeout_ms)

    def one(self, image: NDArray[np.uint8]) -> Frame | None:
        self.projector.show(image)
        return self.after_present()


def capture_stack(
    camera: Camera,
    projector: Projector,
    patterns: PatternSet,
    timeout_ms: float = 2000.0,
    *,
    bit_depth: int | None = None,
    log: CaptureLog | None = None,
) -> list[NDArray]:
    """Show every frame of ``patterns`` in order and grab one camera image of each, synchronised as the
    module docstring says (the camera's trigger mode chooses the path); re-capture inconsistent pairs."""
    log = log if log is not None else CaptureLog()
    cap = _Capture(camera, projector, timeout_ms)
    _check_exposure(camera, cap.timing)
    n = len(patterns)
    frames = list(patterns.frames)
    projector.load_sequence(frames)
    sequencer = projector if cap.hardware and isinstance(projector, SequenceProjector) else None
    if sequencer is not None:
        got = sequencer.run_sequence(camera, n, timeout_ms)
    else:
        got = []
        for _ in range(n):
            projector.step()
            got.append(cap.after_present())
    images: list[NDArray | None] = [None if f is None else f.pixels for f in got]

    def retake(indices: list[int]) -> None:
        """Capture ``indices`` again (twice if lost again): one by one, or, on a projector that plays its
        stored sequence by itself (DLP pattern mode, possibly from flash), by running the sequence again."""
        log.recaptured += [patterns.names[k] for k in indices]
        if sequencer is None:
            for k in indices:
                images[k] = _retake(cap, frames[k])
            return
        for _ in range(2):  # a second loss in a row: let the pair check count it as missing
            again = sequencer.run_sequence(camera, n, timeout_ms)
            for k in indices:
                frame = again[k]
                if images[k] is None or frame is not None:
                    images[k] = None if frame is None else frame.pixels
            if all(again[k] is not None for k in indices):
                return

    lost_first = [k for k, f in enumerate(got) if f is None]
    if lost_first:
        retake(lost_first)
    depth = bit_depth or _bit_depth(camera, images)
    pairs = pattern_pairs(patterns)
    groups = pair_groups(patterns, pairs)
    limit = cap.timing.max_recaptures if cap.timing is not None else 1
    for attempt in range(limit + 1):
        bad = bad_pairs(images, pairs, groups, depth)
        if not bad:
            break
        if not cap.hardware:  # the light came later than waited for: wait one frame longer from now on
            cap.extra_s += cap.period_s
        if attempt == limit:
            names = ", ".join(patterns.names[a] for a, _ in bad[:4])
            raise DeviceProtocolError(
                projector.name,
                f"pattern/inverse pair(s) {names} inconsistent after {limit} re-capture(s), waiting up to "
                f"{(cap.latency_s + cap.extra_s) * 1e3:.1f} ms after each present: the display latency has "
                "changed or frames are being mixed; run `cell calibrate latency` and check the sync wiring",
            )
        retake([k for a, b in ([pairs[0]] if pairs[0] not in bad else []) + bad for k in (a, b)])
    log.extra_wait_s = cap.extra_s
    lost = [patterns.names[k] for k, im in enumerate(images) if im is None]
    if lost:
        raise DeviceTimeout(camera.name, f"frame(s) of {', '.join(lost[:4])} lost twice in a row")
    return [im for im in images if im is not None]


def _retake(cap: _Capture, image: NDArray[np.uint8]) -> NDArray | None:
    frame = cap.one(image)
    if frame is None:
        frame = cap.one(image)  # a second loss in a row: let the pair check count it as missing
    return None if frame is None else frame.pixels


def _bit_depth(camera: Camera, images: list[NDArray | None]) -> int:
    """The camera's configured bit depth; without settings (replay) 8 for uint8 frames, else 12."""
    settings = getattr(camera, "settings", None)
    if settings is not None:
        return settings.pixel_format.bit_depth
    first = next((im for im in images if im is not None), None)
    return 8 if first is None or first.dtype == np.uint8 else 12


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
    the camera configured (software or hardware trigger) with ``bit_depth`` pixels."""
    t0 = time.perf_counter()
    log = CaptureLog()
    images = capture_stack(camera, projector, patterns, timeout_ms, bit_depth=bit_depth, log=log)
    t1 = time.perf_counter()
    stack = check_stack(images, patterns, camera.resolution, bit_depth, source=f"camera '{camera.name}'")
    decoded = decode(stack, patterns, bit_depth, params)
    t2 = time.perf_counter()
    cloud = triangulator.triangulate(decoded)
    t3 = time.perf_counter()
    timings = {"capture": t1 - t0, "decode": t2 - t1, "triangulate": t3 - t2}
    return ViewScan(cloud, decoded, timings, log)


# ------------------------------------------------------------------------ a view's files (cell scan, --from)
# masks.png colours (BGR) per reason, painted in this order so the last listed wins where several apply.
MASK_COLOURS: tuple[tuple[Reason, tuple[int, int, int]], ...] = (
    (Reason.NO_CODE, (60, 60, 60)),
    (Reason.DARK, (120, 0, 0)),  # dark blue: shadow / no projector light
    (Reason.LOW_CONTRAST, (0, 200, 255)),  # amber
    (Reason.INCONSISTENT, (255, 0, 255)),  # magenta
    (Reason.SATURATED, (0, 0, 255)),  # red: glare
)


def masks_image(cloud: SensorCloud) -> NDArray[np.uint8]:
    """BGR picture of the reasons: valid pixels in grey by contrast, the others in the
    :data:`MASK_COLOURS`."""
    grey = np.clip(np.nan_to_num(cloud.contrast) * 255, 0, 255).astype(np.uint8)
    img = np.repeat(grey[..., None], 3, axis=2)
    for reason, colour in MASK_COLOURS:
        img[(cloud.reasons & np.uint8(reason)) > 0] = colour
    return img


def write_ply(path: Path, points: NDArray) -> None:
    """Binary PLY of (N, 3) points (mm), through trimesh's exporter."""
    trimesh.PointCloud(np.asarray(points, dtype=np.float64)).export(str(path), file_type="ply")
