"""Synchronisation: what the waits cost per view in device time, what the pair check costs on the host, and
how well `cell calibrate latency` finds the simulated projector's latency.

Run: .venv/bin/python bench/bench_sync.py  (results in docs/benchmarks.md, "Synchronisation").

Device time is the simulated clock (presents on the 60 Hz vblank grid, waits, exposures): what a real cell
with the same projector would spend capturing one 38-pattern stack, per trigger path. Host time is wall
clock; the pair check is compared with decoding the same stack, the step it guards.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from cell.calibration.latency import measure_latency
from cell.config import DEFAULT_CELL, load_cell_config
from cell.contracts import CameraSettings, TriggerMode
from cell.geometry import look_at
from cell.mesh import load_mesh
from cell.sensing.decode import decode
from cell.sensing.patterns import dissertation_gcls
from cell.sensing.scan import bad_pairs, capture_stack, pair_groups, pattern_pairs
from cell.sensing.stack import check_stack
from fakes.camera import SimCamera
from fakes.clock import SimClock
from fakes.projector import SimProjector
from fakes.sim.render import SceneRenderer
from fakes.sim.scene import Scene

ROOT = Path(__file__).resolve().parent.parent


def rig(trigger: TriggerMode, timing: dict | None = None, latency_frames: float = 2.0):
    cfg = load_cell_config(DEFAULT_CELL)
    proj = cfg.sensor.projector.model_copy(
        update={
            "timing": cfg.sensor.projector.timing.model_copy(update=timing or {}),
            "options": {"latency_frames": latency_frames},
        }
    )
    renderer = SceneRenderer(
        cfg.sensor, cfg.sim, Scene.from_meshes(load_mesh(ROOT / "recipes/parts/gauge.stl"), cfg.sim)
    )
    T_W_C = look_at((0.0, 0.0, 30.0 + cfg.sensor.standoff_mm), (0.0, 0.0, 30.0), up=(0.0, 1.0, 0.0))
    projector = SimProjector(proj)
    camera = SimCamera(
        cfg.sensor.camera, renderer, projector, lambda: T_W_C, SimClock(), np.random.default_rng(4)
    )
    projector.connect()
    projector.set_power(True)
    camera.connect()
    camera.configure(CameraSettings(cfg.sensor.camera.exposure_ms, trigger=trigger))
    return projector, camera


def main() -> None:
    ps = dissertation_gcls()
    print(f"## Device time per {len(ps)}-pattern stack (1024x768, 60 Hz, exposure 16 ms, latency 2 frames)")
    print("| path | waits for | device time per stack (s) |")
    print("|---|---|---|")
    cases = [
        ("software, uncalibrated", TriggerMode.SOFTWARE, {}, "4 frames (upper bound)"),
        ("software, calibrated", TriggerMode.SOFTWARE, {"latency_ms": 2000 / 60 + 0.5}, "2 frames + 0.5 ms"),
        ("hardware trigger (sequence)", TriggerMode.HARDWARE, {}, "nothing: sync out"),
    ]
    for label, trigger, timing, waits in cases:
        projector, camera = rig(trigger, timing)
        t0 = camera.clock.now()
        capture_stack(camera, projector, ps)
        print(f"| {label} | {waits} | {camera.clock.now() - t0:.3f} |")

    projector, camera = rig(TriggerMode.SOFTWARE)
    images = capture_stack(camera, projector, ps)
    pairs = pattern_pairs(ps)
    check, dec = [], []
    for _ in range(5):
        t = time.perf_counter()
        bad_pairs(images, pairs, pair_groups(ps, pairs), 8)
        check.append(time.perf_counter() - t)
        t = time.perf_counter()
        decode(check_stack(images, ps, camera.resolution, 8), ps, 8)
        dec.append(time.perf_counter() - t)
    check_ms, decode_ms = statistics.median(check) * 1e3, statistics.median(dec) * 1e3
    print("\n## Host time of the pair check, grouping included (median of 5)")
    print(f"pair check {check_ms:.1f} ms; decoding the same stack {decode_ms:.0f} ms")

    print("\n## cell calibrate latency on the simulated projector (camera noise on)")
    print("| true latency (frames) | true (ms) | measured (ms) | error (us) | spread of estimates (us) |")
    print("|---|---|---|---|---|")
    for frames in (1.0, 2.0, 2.5, 3.3):
        projector, camera = rig(TriggerMode.SOFTWARE, latency_frames=frames)
        m = measure_latency(camera, projector, exposure_ms=camera.settings.exposure_ms)
        truth = projector.latency_s
        error_us = (m.latency_s - truth) * 1e6
        print(
            f"| {frames:g} | {truth * 1e3:.3f} | {m.latency_s * 1e3:.3f} | {error_us:+.0f} "
            f"| {m.spread_s * 1e6:.0f} |"
        )


if __name__ == "__main__":
    main()
