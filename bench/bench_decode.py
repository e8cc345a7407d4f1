"""Decode + triangulate one GCLS stack at 1024x768 and 2448x2048, beside OpenCV contrib's GrayCodePattern
decode and a plain vectorised NumPy integer Gray decode of the same scene.

Stacks are synthesised (cv2.remap of each pattern through a smooth camera->projector map, blur, noise) so
that the camera size is free; run: ``.venv/bin/python bench/bench_decode.py``.
"""

from __future__ import annotations

import platform
import resource
import time

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


def _rss_mib(field: str) -> float:
    """VmRSS (current) or VmHWM (peak since the last reset) of this process, MiB (Linux /proc)."""
    for line in open("/proc/self/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak_rss() -> None:
    """Reset VmHWM to the current RSS (Linux >= 4.0), so a later VmHWM is the peak of what follows."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def bench(W: int, H: int, repeats: int = 5) -> dict[str, float]:
    """Best-of-``repeats`` wall times (s) of every decoder on the same synthetic scene, and the peak memory
    the GCLS decode + triangulation adds on top of the stack (MiB; RSS, so numba's allocations count too)."""
    ps = dissertation_gcls()
    stack = np.stack(synth(list(ps.frames), W, H))
    s = W / 1024
    K = np.array([[2017.0 * s, 0, (W - 1) / 2], [0, 2017.0 * s, (H - 1) / 2], [0, 0, 1]])
    T_C_P = np.eye(4)
    T_C_P[:3, 3] = (429.3, 0, 0)
    T_C_P[:3, :3] = cv2.Rodrigues(np.array([0, -0.8285, 0]))[0]
    tri = PinholeTriangulator(
        K,
        np.array([-0.08, 0.12, 0, 0, 0]),
        (W, H),
        np.array([[2600.0, 0, 511.5], [0, 2600, 383.5], [0, 0, 1]]),
        T_C_P,
    )
    tri.triangulate(decode(np.ascontiguousarray(stack[:, :64]), ps))  # warm-up: numba cache / compile
    rss0 = _rss_mib("VmRSS")
    _reset_peak_rss()
    t_dec = t_all = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        dec = decode(stack, ps)
        t1 = time.perf_counter()
        cloud = tri.triangulate(dec)
        t2 = time.perf_counter()
        t_dec, t_all = min(t_dec, t1 - t), min(t_all, t2 - t)
        del dec, cloud
    peak = _rss_mib("VmHWM") - rss0
    cloud = tri.triangulate(decode(stack, ps))
    res = {
        "gcls_decode_s": t_dec,
        "gcls_decode_triangulate_s": t_all,
        "peak_extra_MiB": peak,
        "valid_frac": float(cloud.valid.mean()),
    }
    # plain NumPy integer Gray decode of a 10-bit Gray set with inverses
    gp = cv2.structured_light.GrayCodePattern.create(1024, 768)
    _, cv_patterns = gp.generate()
    gimgs = synth([p for p in cv_patterns], W, H, 1)
    n_col_bits = int(np.ceil(np.log2(1024)))
    res["numpy_gray_int_s"] = min(_timed(lambda: numpy_gray(gimgs, n_col_bits)) for _ in range(repeats))
    black, white = synth([np.zeros((768, 1024), np.uint8), np.full((768, 1024), 255, np.uint8)], W, H, 2)
    # two cameras, as the issue measured; slow, so best of 2
    res["opencv_graycode_decode_s"] = min(
        _timed(lambda: gp.decode([gimgs, gimgs], None, [black, black], [white, white])) for _ in range(2)
    )
    return res


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def plane_sigma_mm(points: np.ndarray) -> float:
    """RMS distance (mm) of points (N, 3) to their least-squares plane (SVD)."""
    c = points - points.mean(axis=0)
    return float(np.linalg.svd(c, full_matrices=False)[1][-1] / np.sqrt(len(points)))


# Defocus (simulator thin lens, fakes/sim/optics.py). The small sensor's lenses are short (camera
# f = 400 px x 4.65 um = 1.9 mm) so even f/2 hardly blurs; a larger pixel pitch at the same focal length in
# pixels keeps the geometry and gives a longer lens (camera 40 um -> f = 16 mm, projector 50 um -> f = 14 mm)
# whose f-number and focus distance then blur meaningfully.
CAMERA_DEFOCUS = {"pixel_pitch_um": 40.0, "f_number": 1.4, "focus_distance_mm": 300.0}
PROJECTOR_DEFOCUS = {"pixel_pitch_um": 50.0, "f_number": 1.0, "focus_distance_mm": 350.0}


def _plate_scan(ps, cam: dict, proj: dict, sim: dict, noise: bool):
    import trimesh

    from cell.config import SimConfig
    from cell.contracts import CameraSettings, PixelFormat
    from cell.geometry import make_pose
    from cell.sensing.scan import scan_view
    from fakes.sim.testing import small_rig

    tilt = make_pose(trimesh.transformations.rotation_matrix(0.2, [1, 0.3, 0])[:3, :3], [0, 0, 30.0])
    plate = trimesh.creation.box((400, 300, 4), transform=tilt)
    rig = small_rig(
        part_W=plate, bit_depth=8, camera=cam, projector=proj, sim=SimConfig(seed=21, noise=noise, **sim)
    )
    rig.projector.connect()
    rig.projector.set_power(True)
    rig.camera.connect()
    rig.camera.configure(CameraSettings(exposure_ms=10.0, pixel_format=PixelFormat.MONO8))
    v = scan_view(rig.camera, rig.projector, ps, PinholeTriangulator.from_sensor(rig.sensor), bit_depth=8)
    return rig, v


def _blur_px(rig) -> tuple[float, float]:
    """Median defocus sigma over the plate: camera px, projector px (the simulator's thin-lens formula)."""
    from cell.geometry import transform_points
    from fakes.sim.optics import blur_sigma_px

    gt = rig.renderer.ground_truth(rig.T_W_C)
    P = gt.points_C[gt.hit]
    P_P = transform_points(np.linalg.inv(rig.sensor.projector.T_C_P.matrix()), P)
    return (
        float(np.median(blur_sigma_px(rig.sensor.camera, P[:, 2]))),
        float(np.median(blur_sigma_px(rig.sensor.projector, P_P[:, 2]))),
    )


def noise_sweep() -> list[tuple]:
    """Flat tilted plate on the small simulated sensor (160x120 camera, 128x96 projector), GCLS (8 shifts) vs
    GCPS (8 phase steps), both 26 images, over read noise, defocus and ambient light; every condition also
    noise-free (SimConfig.noise=False), which leaves only the systematic error (GCPS: phase harmonics of
    8-bit sinusoids resampled per DMD pixel; GCLS: edge interpolation). Rows: (condition, camera blur px,
    projector blur px, then per codec: sigma um, noise-free sigma um, valid %)."""
    from cell.sensing.patterns import gcls_patterns, gcps_patterns

    conditions = [
        ("default (read 12 e, ambient 5 e/ms)", {}, {}, {}),
        ("read noise 60 e", {"read_noise_e": 60.0}, {}, {}),
        ("read noise 150 e", {"read_noise_e": 150.0}, {}, {}),
        ("camera defocus (16 mm f/1.4 focused at 300 mm)", CAMERA_DEFOCUS, {}, {}),
        ("projector defocus (14 mm f/1 focused at 350 mm)", {}, PROJECTOR_DEFOCUS, {}),
        ("both defocused", CAMERA_DEFOCUS, PROJECTOR_DEFOCUS, {}),
        ("both defocused + read noise 60 e", {**CAMERA_DEFOCUS, "read_noise_e": 60.0}, PROJECTOR_DEFOCUS, {}),
        ("ambient 200 e/ms", {}, {}, {"ambient_e_per_ms": 200.0}),
        ("ambient 600 e/ms", {}, {}, {"ambient_e_per_ms": 600.0}),
    ]
    rows = []
    for name, cam, proj, sim in conditions:
        row: list = [name]
        for ps in (gcls_patterns(128, 96, 8, 8), gcps_patterns(128, 96, 8, 8)):
            for noise in (True, False):
                rig, v = _plate_scan(ps, cam, proj, sim, noise)
                if len(row) == 1:
                    row += list(_blur_px(rig))
                pts = v.cloud.points_C[v.cloud.valid].astype(np.float64)
                row.append(1000 * plane_sigma_mm(pts))
                if noise:
                    valid = 100 * v.cloud.valid.mean()
            row.append(valid)
        rows.append(tuple(row))
    return rows


if __name__ == "__main__":
    import sys

    if "--noise-sweep" in sys.argv:
        print(
            "| condition | blur sigma cam / proj px | GCLS sigma (um) | GCLS noise-free | GCLS valid % "
            "| GCPS sigma (um) | GCPS noise-free | GCPS valid % |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for r in noise_sweep():
            print(
                f"| {r[0]} | {r[1]:.2f} / {r[2]:.2f} | {r[3]:.1f} | {r[4]:.1f} | {r[5]:.1f} | {r[6]:.1f} "
                f"| {r[7]:.1f} | {r[8]:.1f} |"
            )
        sys.exit(0)
    cv2.setNumThreads(1)  # GrayCodePattern single-threaded as in the issue; GCLS kernels use numba threads
    import os

    import numba

    cpu = next(
        (ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")),
        platform.machine(),
    )
    print(
        f"machine: {cpu}, nproc {os.cpu_count()}, numba threads {numba.get_num_threads()}, "
        f"load average {os.getloadavg()[0]:.2f}, numpy {np.__version__}, OpenCV {cv2.__version__}, "
        f"numba {numba.__version__}"
    )
    for W, H in ((1024, 768), (2448, 2048)):
        r = bench(W, H)
        print(f"{W}x{H}: " + ", ".join(f"{k} {v:.3f}" for k, v in r.items()))
    print(
        f"load average after {os.getloadavg()[0]:.2f}; "
        f"max RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB"
    )
