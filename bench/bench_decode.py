"""Decode + triangulate one GCLS stack at 1024x768 and 2448x2048, beside OpenCV contrib's GrayCodePattern
decode and a plain vectorised NumPy integer Gray decode of the same scene.

Stacks are synthesised (cv2.remap of each pattern through a smooth camera->projector map, blur, noise) so
that the camera size is free; run: ``.venv/bin/python bench/bench_decode.py``.
"""

from __future__ import annotations

import platform
import resource
import time
import tracemalloc

import cv2
import numpy as np

from cell.sensing.decode import decode
from cell.sensing.patterns import dissertation_gcls
from cell.sensing.triangulate import PinholeTriangulator


def synth(frames: list[np.ndarray], W: int, H: int, seed: int = 0) -> list[np.ndarray]:
    """Camera images of projector ``frames`` on a gently curved surface: ~0.6 projector px per camera px."""
    r, c = np.mgrid[0:H, 0:W].astype(np.float32)
    s = 1024 / W
    mx = (160 + 0.6 * s * c + 2e-5 * s * (c - W / 2) ** 2 / s + 0.01 * s * r).astype(np.float32)
    my = (0.37 * s * r * 1024 / 768 * 0.75 + 100).astype(np.float32)
    rng = np.random.default_rng(seed)
    out = []
    for f in frames:
        img = cv2.remap(f.astype(np.float32) / 255 * 200 + 10, mx, my, cv2.INTER_LINEAR)
        img = cv2.GaussianBlur(img, (0, 0), 0.8) + rng.normal(0, 1.5, (H, W)).astype(np.float32)
        out.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return out


def numpy_gray(images: list[np.ndarray], n_bits: int) -> np.ndarray:
    """Integer projector column from Gray patterns with inverses: bit = P > I, Gray -> binary by XOR."""
    acc = np.zeros(images[0].shape, np.int32)
    b = np.zeros(images[0].shape, np.int32)
    for k in range(n_bits):
        bit = (images[2 * k] > images[2 * k + 1]).view(np.uint8)
        b ^= bit
        acc = (acc << 1) | b
    return acc


def bench(W: int, H: int) -> dict[str, float]:
    ps = dissertation_gcls()
    stack = np.stack(synth(list(ps.frames), W, H))
    s = W / 1024
    K = np.array([[2017.0 * s, 0, (W - 1) / 2], [0, 2017.0 * s, (H - 1) / 2], [0, 0, 1]])
    T_C_P = np.eye(4)
    T_C_P[:3, 3] = (429.3, 0, 0)
    T_C_P[:3, :3] = cv2.Rodrigues(np.array([0, -0.8285, 0]))[0]
    tri = PinholeTriangulator(K, np.array([-0.08, 0.12, 0, 0, 0]), (W, H),
                              np.array([[2600.0, 0, 511.5], [0, 2600, 383.5], [0, 0, 1]]), T_C_P)
    decode(stack[:, :64], ps)  # warm-up
    tracemalloc.start()
    t = time.perf_counter()
    dec = decode(stack, ps)
    t_dec = time.perf_counter() - t
    cloud = tri.triangulate(dec)
    t_all = time.perf_counter() - t
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    res = {"gcls_decode_s": t_dec, "gcls_decode_triangulate_s": t_all, "peak_MiB_decode": peak,
           "valid_frac": float(cloud.valid.mean())}
    # plain NumPy integer Gray decode of a 10-bit Gray set with inverses
    gp = cv2.structured_light.GrayCodePattern.create(1024, 768)
    _, cv_patterns = gp.generate()
    gimgs = synth([p for p in cv_patterns], W, H, 1)
    n_col_bits = int(np.ceil(np.log2(1024)))
    t = time.perf_counter()
    numpy_gray(gimgs, n_col_bits)
    res["numpy_gray_int_s"] = time.perf_counter() - t
    black, white = synth([np.zeros((768, 1024), np.uint8), np.full((768, 1024), 255, np.uint8)], W, H, 2)
    t = time.perf_counter()
    gp.decode([gimgs, gimgs], None, [black, black], [white, white])  # two cameras, as the issue measured
    res["opencv_graycode_decode_s"] = time.perf_counter() - t
    return res


def plane_sigma_mm(points: np.ndarray) -> float:
    """RMS distance (mm) of points (N, 3) to their least-squares plane (SVD)."""
    c = points - points.mean(axis=0)
    return float(np.linalg.svd(c, full_matrices=False)[1][-1] / np.sqrt(len(points)))


def noise_sweep() -> list[tuple[str, float, float, float, float]]:
    """Flat tilted plate on the small simulated sensor (160x120 camera, 128x96 projector), GCLS (8 shifts) vs
    GCPS (8 phase steps), both 26 images, over read noise, defocus blur and ambient light. Returns rows
    (condition, GCLS sigma um, GCPS sigma um, GCLS valid %, GCPS valid %)."""
    import trimesh

    from cell.config import SimConfig
    from cell.contracts import CameraSettings, PixelFormat
    from cell.geometry import make_pose
    from cell.sensing.patterns import gcls_patterns, gcps_patterns
    from cell.sensing.scan import scan_view
    from fakes.sim.testing import small_rig

    tilt = make_pose(trimesh.transformations.rotation_matrix(0.2, [1, 0.3, 0])[:3, :3], [0, 0, 30.0])
    plate = trimesh.creation.box((400, 300, 4), transform=tilt)
    conditions = [("default (read 12 e, ambient 5 e/ms)", {}, {}),
                  ("read noise 60 e", {"read_noise_e": 60.0}, {}),
                  ("read noise 150 e", {"read_noise_e": 150.0}, {}),
                  ("blur: f/2 lens focused 60 mm off", {"f_number": 2.0, "focus_distance_mm": 340.0}, {}),
                  ("ambient 200 e/ms", {}, {"ambient_e_per_ms": 200.0}),
                  ("ambient 600 e/ms", {}, {"ambient_e_per_ms": 600.0})]
    rows = []
    for name, cam, sim in conditions:
        out = []
        for ps in (gcls_patterns(128, 96, 8, 8), gcps_patterns(128, 96, 8, 8)):
            rig = small_rig(part_W=plate, bit_depth=8, camera=cam, sim=SimConfig(seed=21, **sim))
            rig.projector.connect(); rig.projector.set_power(True); rig.camera.connect()  # noqa: E702
            rig.camera.configure(CameraSettings(exposure_ms=10.0, pixel_format=PixelFormat.MONO8))
            tri = PinholeTriangulator.from_sensor(rig.sensor)
            v = scan_view(rig.camera, rig.projector, ps, tri, bit_depth=8)
            pts = v.cloud.points_C[v.cloud.valid].astype(np.float64)
            out.append((1000 * plane_sigma_mm(pts), 100 * v.cloud.valid.mean()))
        rows.append((name, out[0][0], out[1][0], out[0][1], out[1][1]))
    return rows


if __name__ == "__main__":
    import sys

    if "--noise-sweep" in sys.argv:
        print("| condition | GCLS sigma (um) | GCPS sigma (um) | GCLS valid % | GCPS valid % |")
        print("|---|---|---|---|---|")
        for r in noise_sweep():
            print(f"| {r[0]} | {r[1]:.1f} | {r[2]:.1f} | {r[3]:.1f} | {r[4]:.1f} |")
        sys.exit(0)
    cv2.setNumThreads(1)
    print(f"machine: {platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores, "
          f"numpy {np.__version__}, OpenCV {cv2.__version__}")
    for W, H in ((1024, 768), (2448, 2048)):
        r = bench(W, H)
        print(f"{W}x{H}: " + ", ".join(f"{k} {v:.3f}" for k, v in r.items()))
    print(f"max RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
