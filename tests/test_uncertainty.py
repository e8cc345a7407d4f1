"""The per-point uncertainty model (cell/analysis/uncertainty.py, cell/sensing/noise.py, error_model.py)
against analytic values and the simulator's truth: the one-pixel model of eq 2.5 (Tables 2.1-2.3) and its
first-order generalisation against a triangulation, the photon-transfer noise estimate against the simulated
camera's noise, the quantisation curve against the simulator's projector coordinates, the merge of views and
the pose part after an alignment."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from cell.analysis import uncertainty
from cell.analysis.merge import bin_view, merge_bins
from cell.analysis.uncertainty import (
    MergeShares,
    PointRows,
    combine,
    datum_alignment_map,
    pose_uncertainty_of_points,
    posterior_covariance,
    stats,
)
from cell.geometry import invert, look_at, make_pose, transform_points
from cell.sensing import noise
from cell.sensing.decode import decode
from cell.sensing.error_model import TABLES, error_table, normal_error_per_pixel, one_pixel_error
from cell.sensing.incidence import measured_normals
from cell.sensing.noise import (
    code_phase,
    edge_sigma_px,
    estimate_image_noise,
    pair_names,
    quantisation,
)
from cell.sensing.patterns import measuring_patterns
from cell.sensing.triangulate import PinholeTriangulator
from fakes.sim.testing import small_rig

S, D = 393.7, 429.3  # the prototype's stand-off and baseline (Tables 2.1-2.3)


def _fronto_error(res: float, S_mm: float, d: float, m: float) -> float:
    """normal_error_per_pixel of a plane facing the camera, on the optical axis, at the height h of eq 2.4
    (L = res m above the reference plane), for a rectified sensor (projector at (d, 0, 0))."""
    h = res * m * S_mm / (d + res * m)
    p = np.array([0.0, 0.0, S_mm - h])
    return float(normal_error_per_pixel(p, np.array([0.0, 0.0, -1.0]), [d, 0, 0], [0, 1, 0], S_mm / res))


@pytest.mark.parametrize("table", range(3))
def test_one_pixel_model_facing_the_camera_is_eq_2_5(table: int) -> None:
    """A plane facing the camera: the per-point model is eq 2.5 (to the one-pixel step's discreteness,
    res / (d + L) < 0.2 %) at every entry of Tables 2.1-2.3."""
    _, varied, values, fixed = TABLES[table]
    expected = error_table(varied, values, fixed)
    for i, m in enumerate((53, 64, 87)):
        for j, v in enumerate(values):
            p = {**fixed, varied: v}
            got = _fronto_error(p["res"], p["S"], p["d"], m)
            # eq 2.5 is the difference h(m) - h(m-1); the model is the derivative at m - 1/2
            assert got == pytest.approx(expected[i, j], rel=2e-3)
            assert got == pytest.approx(float(one_pixel_error(p["res"], p["S"], p["d"], m)), rel=2e-3)


def _pinhole(tilt_deg: float, axis: str) -> tuple[PinholeTriangulator, np.ndarray, np.ndarray, np.ndarray]:
    """A rectified pinhole sensor (camera at the origin, projector at (D, 0, 0) turned to the field centre)
    looking at a plane through (0, 0, S) tilted by ``tilt_deg`` about ``axis``; returns the triangulator,
    the true points (H, W, 3), the plane's normal and the true projector coordinate u (H, W)."""
    fx, W, H = 1000.0, 64, 48
    K = np.array([[fx, 0, W / 2 - 0.5], [0, fx, H / 2 - 0.5], [0, 0, 1]])
    beta = math.atan2(D, S)
    c, s = math.cos(beta), math.sin(beta)
    T_C_P = np.eye(4)
    T_C_P[:3, :3] = [[c, 0, -s], [0, 1, 0], [s, 0, c]]  # aimed at the camera axis at the stand-off
    T_C_P[:3, 3] = [D, 0, 0]
    Kp = np.array([[2600.0, 0, 511.5], [0, 2600.0, 383.5], [0, 0, 1]])
    tri = PinholeTriangulator(K, np.zeros(5), (W, H), Kp, T_C_P)
    t = math.radians(tilt_deg)
    n = np.array([math.sin(t), 0, -math.cos(t)]) if axis == "y" else np.array([0, math.sin(t), -math.cos(t)])
    rays = np.stack([tri.xn, tri.yn, np.ones_like(tri.xn)], -1)
    z = (n @ [0, 0, S]) / (rays @ n)
    P = rays * z[..., None]
    P_P = (P - T_C_P[:3, 3]) @ T_C_P[:3, :3]
    u = Kp[0, 0] * P_P[..., 0] / P_P[..., 2] + Kp[0, 2]
    return tri, P, n, u


@pytest.mark.parametrize(("tilt", "axis"), [(0.0, "y"), (30.0, "y"), (-40.0, "y"), (50.0, "x"), (-60.0, "y")])
def test_one_pixel_model_matches_a_triangulation_of_a_shifted_code(tilt: float, axis: str) -> None:
    """Each pixel given the code of its neighbour one pixel along the row (a correspondence one pixel off),
    triangulated: the point moves along the normal as the model says (first order: within 2 %)."""
    tri, P, n, u = _pinhole(tilt, axis)
    moved = tri.depth(np.roll(u, -1, axis=1))  # the code the surface shows one pixel to the right
    rays = np.stack([tri.xn, tri.yn, np.ones_like(tri.xn)], -1)
    shift = np.abs(((rays * moved[..., None]) - P) @ n)[:, 1:-1]
    model = normal_error_per_pixel(P, np.broadcast_to(n, P.shape), [D, 0, 0], [0, 1, 0], 1000.0)[:, 1:-1]
    np.testing.assert_allclose(model, shift, rtol=0.02)


def test_projector_incidence_scales_it_and_camera_incidence_cancels() -> None:
    """At any point and for any surface normal the one-pixel error is the value for a plane facing the camera
    (eq 2.5) times cos(theta_p) / cos(theta_p0), the projector's incidence on the surface over its incidence
    on that plane: how the camera sees the surface does not enter (its footprint and the share of the ray
    along the normal cancel)."""
    rng = np.random.default_rng(5)
    facing = np.array([0.0, 0.0, -1.0])
    for p in (np.array([0.0, 0.0, S]), np.array([60.0, -40.0, S - 20.0]), np.array([-80.0, 55.0, S + 30.0])):
        to_proj = (np.array([D, 0, 0]) - p) / np.linalg.norm(np.array([D, 0, 0]) - p)
        e0 = normal_error_per_pixel(p, facing, [D, 0, 0], [0, 1, 0], 1000.0)
        for _ in range(20):
            n = rng.normal(size=3)
            n[2] = -abs(n[2]) - 0.3  # facing the camera
            n /= np.linalg.norm(n)
            ratio = normal_error_per_pixel(p, n, [D, 0, 0], [0, 1, 0], 1000.0) / e0
            assert ratio == pytest.approx(abs(n @ to_proj) / abs(facing @ to_proj), rel=1e-9)


# ----------------------------------------------------------------------------------- noise from the images
def test_photon_transfer_line_from_pattern_pairs() -> None:
    """Pairs that add up to W + B with Gaussian noise of variance a + b * level: the fit finds a and b (of
    the pair: 2a and b) from the stack alone."""
    ps = measuring_patterns(small_rig().sensor.projector)
    rng = np.random.default_rng(3)
    H, W = 120, 160
    white = rng.uniform(60, 220, (H, W))
    black = 0.05 * white
    a, b = 2.0, 0.08  # per frame: var = a + b * level (DN^2)
    stack = np.zeros((len(ps.names), H, W), np.float64)
    stack[ps.index("white")], stack[ps.index("black")] = white, black
    for i, j in pair_names(ps):
        f = rng.uniform(0, 1, (H, W))  # any split of the light between pattern and inverse
        stack[i] = black + f * (white - black)
        stack[j] = black + (1 - f) * (white - black)
    noisy = stack + rng.standard_normal(stack.shape) * np.sqrt(a + b * stack)
    frames = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    noise = estimate_image_noise(frames, ps, np.ones((H, W), bool))
    assert noise.beta_dn == pytest.approx(b, rel=0.05)
    assert noise.alpha_dn2 == pytest.approx(2 * a + 2 / 12, rel=0.1)  # two frames' read noise and rounding


@pytest.fixture(scope="module")
def plate_views() -> dict:
    """Twelve noise draws of one view of a tilted plate by the small simulated sensor (12-bit), decoded, with
    the simulator's true projector coordinate of every pixel."""
    plate = trimesh.creation.box(extents=(300, 300, 4))
    plate.apply_transform(trimesh.transformations.rotation_matrix(math.radians(25), [0, 1, 0]))
    plate.apply_translation((0, 0, 40))
    pose = look_at((0, 0, 440), (0, 0, 40), up=(0, 1, 0))
    rig = small_rig(part_W=plate, T_W_C=pose)
    cam = rig.sensor.camera
    ps = measuring_patterns(rig.sensor.projector)
    gt = rig.renderer.ground_truth(pose)
    rng = np.random.default_rng(11)
    stacks = [
        rig.renderer.render_stack(pose, list(ps.frames), cam.exposure_ms, cam.gain_db, rng, cam.bit_depth)
        for _ in range(12)
    ]
    decoded = [decode(s, ps, cam.bit_depth) for s in stacks]
    return {"rig": rig, "ps": ps, "gt": gt, "stacks": stacks, "decoded": decoded}


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # pixels without a code in some draw: NaN medians
def test_edge_noise_predicts_the_scatter_of_decoded_codes(plate_views: dict) -> None:
    """The per-pixel spread of the decoded projector coordinate over twelve noise draws, in camera pixels,
    against sigma_x from the stack's own noise: rms ratio within 0.7-1.4."""
    ps, decoded, stacks = plate_views["ps"], plate_views["decoded"], plate_views["stacks"]
    code = ps.codes[0]
    u = np.stack([d.primary().u for d in decoded]).astype(np.float64)
    ok = np.isfinite(u).all(0) & plate_views["gt"].part
    ok[:, :3] = ok[:, -3:] = False
    codes_per_px = np.abs(np.nanmedian(np.gradient(u, axis=2), axis=0))  # projector px per camera px
    spread_px = u.std(0, ddof=1) / codes_per_px
    noise = estimate_image_noise(stacks[0], ps, ok, 12)
    sigma = edge_sigma_px(decoded[0], decoded[0].primary(), noise, code.shift_px, code.offset_px)
    use = ok & np.isfinite(sigma)
    ratio = np.sqrt(np.mean(spread_px[use] ** 2)) / np.sqrt(np.mean(sigma[use] ** 2))
    assert 0.85 < ratio < 1.18, ratio  # measured 1.01


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_quantisation_curve_seen_in_the_points_is_the_decoders_bias(plate_views: dict) -> None:
    """The sub-code error estimated from the view's own points (no truth) against the decoder's true mean
    error by phase (decoded minus the simulator's projector coordinate, in camera pixels): the same curve."""
    rig, ps, gt, decoded = plate_views["rig"], plate_views["ps"], plate_views["gt"], plate_views["decoded"]
    code = ps.codes[0]
    tri = PinholeTriangulator.from_sensor(rig.sensor)
    cloud = tri.triangulate(decoded[0])
    valid = cloud.valid & gt.part
    T = rig.sensor.projector.T_C_P.matrix()
    normals = measured_normals(cloud.points_C, valid)
    g = normal_error_per_pixel(cloud.points_C, normals, T[:3, 3], T[:3, 1], rig.sensor.camera.fx_px)
    phase = code_phase(decoded[0].primary(), code.shift_px, code.offset_px)
    noise = estimate_image_noise(plate_views["stacks"][0], ps, valid, 12)
    sigma = edge_sigma_px(decoded[0], decoded[0].primary(), noise, code.shift_px, code.offset_px)
    q = quantisation(cloud.points_C, normals, valid, g, phase, sigma)
    u = np.stack([d.primary().u for d in decoded]).astype(np.float64)
    codes_per_px = np.abs(np.nanmedian(np.gradient(u, axis=2), axis=0))
    bias_px = (np.nanmean(u, axis=0) - gt.projector_uv[..., 0]) / codes_per_px
    # the points move opposite to the code (the projector sits on +x): compare the curves' shape and size
    k = np.minimum((phase * 10).astype(int), 9)
    use = valid & np.isfinite(bias_px)
    truth = np.array([np.mean(bias_px[use & (k == b)]) for b in range(10)])
    truth -= truth.mean()
    assert abs(np.corrcoef(truth, q.curve_px)[0, 1]) > 0.9  # measured 0.98
    # Measured with sharp line-shift edges: 0.0043 px from the points, 0.0043 px true. With the ramped edges
    # (MEASURING_EDGE_PX, issue 18) the decoder's curve is smaller, 0.0031 px true, and the points show 0.0038
    # px: the estimate errs on the large side (u stays conservative), not more than 5 % below the truth
    true_rms = np.sqrt(np.mean(truth**2))
    assert 0.95 * true_rms <= q.rms_px <= 1.3 * true_rms, (q.rms_px, true_rms)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_quantisation_in_bands_is_the_whole_images(
    plate_views: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The per-pixel figures taken in bands of rows that do not divide the image (the memory cut for 5 MP
    views) are, to the bit, those of one band over the whole image: the code phase, the edge noise and the
    quantisation's curve, scatter and pixels."""
    rig, ps, decoded = plate_views["rig"], plate_views["ps"], plate_views["decoded"]
    code = ps.codes[0]
    cloud = PinholeTriangulator.from_sensor(rig.sensor).triangulate(decoded[0])
    valid = cloud.valid & plate_views["gt"].part
    T = rig.sensor.projector.T_C_P.matrix()
    normals = measured_normals(cloud.points_C, valid)
    g = normal_error_per_pixel(cloud.points_C, normals, T[:3, 3], T[:3, 1], rig.sensor.camera.fx_px)
    image_noise = estimate_image_noise(plate_views["stacks"][0], ps, valid, 12)
    got = []
    for rows in (valid.shape[0], 7):
        monkeypatch.setattr(noise, "BAND_ROWS", rows)
        axis = decoded[0].primary()
        phase = code_phase(axis, code.shift_px, code.offset_px)
        sigma = edge_sigma_px(decoded[0], axis, image_noise, code.shift_px, code.offset_px)
        got.append((phase, sigma, quantisation(cloud.points_C, normals, valid, g, phase, sigma).to_json()))
    (phase, sigma, q), (phase_b, sigma_b, q_b) = got
    assert q["pixels"] > 1000 and np.isfinite(sigma).sum() > 1000
    assert np.array_equal(phase, phase_b, equal_nan=True) and np.array_equal(sigma, sigma_b, equal_nan=True)
    assert q == q_b


# ------------------------------------------------------------------------------------------ merge and pose
def _merged_u(views: list[np.ndarray], weights: list[np.ndarray], u: list[np.ndarray]) -> np.ndarray:
    """The merged decode u of views merged as the registration merges them (binned, summed)."""
    binned = [bin_view(v, w, x, 0.2) for v, w, x in zip(views, weights, u, strict=True)]
    acc = MergeShares(len(views))
    n = len(views)
    merged = merge_bins(0.2, lambda k: binned[k], [None] * n, [np.eye(4)] * n, acc)
    assert merged is not None
    return acc.decode(merged)


def test_merged_u_averages_views_and_not_one_views_neighbours() -> None:
    """Two views of one voxel with u 0.03 and 0.04 merged with weights 1/u^2: 1/sqrt(1/0.03^2 + 1/0.04^2);
    two points of one view in a voxel (shared edges) keep their u: they are not independent."""
    a = np.array([[0.05, 0.05, 0.05]])
    views = [a, a + 0.01]
    u = [np.array([0.03]), np.array([0.04])]
    w = [1 / x**2 for x in u]
    assert _merged_u(views, w, u)[0] == pytest.approx(1 / math.sqrt(1 / 0.03**2 + 1 / 0.04**2))
    one = _merged_u([np.vstack([a, a + 0.01])], [np.ones(2)], [np.array([0.03, 0.03])])
    assert one[0] == pytest.approx(0.03)


def test_pose_u_in_chunks_is_each_points_own(monkeypatch: pytest.MonkeyPatch) -> None:
    """The pose u taken a few points at a time (chunks that do not divide the cloud) equals each point's own
    sqrt(l C l^T), l its shares times its row, less the alignment map's part, computed point by point."""
    rng = np.random.default_rng(7)
    n, m = 3, 11
    shares = rng.random((m, n))
    shares /= shares.sum(1, keepdims=True)
    rows = rng.normal(size=(m, 6))
    A = rng.normal(size=(6 * n, 6 * n))
    C, B = A @ A.T, rng.normal(size=(6, 6 * n))
    monkeypatch.setattr(uncertainty, "POINTS_PER_CHUNK", 4)
    points, normals = rng.normal(size=(m, 3)) * 50, rng.normal(size=(m, 3))
    centre, lever = np.array([1.0, -2.0, 3.0]), 80.0
    made = PointRows(points, normals, centre, lever)  # the rows made a chunk at a time
    want = np.column_stack([np.cross(points - centre, normals) / lever, normals])
    assert made[2:9] == pytest.approx(want[2:9])
    # the points given in another frame and the normals per face: the same rows, bit for bit
    T, face = (
        make_pose(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [5.0, -7.0, 2.0]),
        rng.permutation(m),
    )
    moved = PointRows(transform_points(invert(T), points), normals[np.argsort(face)], centre, lever, T, face)
    assert np.allclose(moved[2:9], made[2:9], rtol=0, atol=1e-12)
    assert np.array_equal(
        moved[2:9], PointRows(transform_points(T, moved.points), normals, centre, lever)[2:9]
    )
    with ThreadPoolExecutor(2) as pool:  # the chunks on two threads: each point's own value, as on one
        for Bm in (None, B):
            got = pose_uncertainty_of_points(shares, rows, C, Bm)
            for i in range(m):
                l_i = np.kron(shares[i], rows[i]) - (0 if Bm is None else rows[i] @ Bm)
                assert got[i] == pytest.approx(math.sqrt(l_i @ C @ l_i), rel=1e-12)
            assert np.array_equal(pose_uncertainty_of_points(shares, rows, C, Bm, pool), got)
            one = pose_uncertainty_of_points(shares, made, C, Bm)
            assert np.array_equal(pose_uncertainty_of_points(shares, made, C, Bm, pool), one)
            # the rows made per chunk give the u of the rows made at once (np.cross)
            assert one == pytest.approx(pose_uncertainty_of_points(shares, want, C, Bm), rel=1e-12)


def test_pose_error_after_a_datum_alignment() -> None:
    """Two views of a plate seen from above (z) with independent z errors of 0.2 mm: under kinematic
    alignment every point keeps its view's 0.2 mm; three datums measured by view 0 alone take view 0's error
    out (its points then have none) and put it, with opposite sign, on view 1's: sqrt(2) * 0.2 mm there."""
    sigma = 0.2
    C = np.zeros((12, 12))
    for v in range(2):
        C[6 * v + 5, 6 * v + 5] = sigma**2  # z translation only
    pts = np.array([[-20.0, 0.0, 0.0], [20.0, 0.0, 0.0]])
    normals = np.array([[0.0, 0.0, 1.0]] * 2)
    shares = np.array([[1.0, 0.0], [0.0, 1.0]])  # point 0 from view 0, point 1 from view 1
    rows = np.column_stack([np.cross(pts, normals), normals])
    assert pose_uncertainty_of_points(shares, rows, C, None) == pytest.approx([sigma, sigma])
    datums = np.array([[-30.0, -10.0, 0.0], [-30.0, 10.0, 0.0], [-10.0, 0.0, 0.0]])
    B = datum_alignment_map(
        datums, np.tile([0.0, 0.0, 1.0], (3, 1)), np.tile([1.0, 0.0], (3, 1)), np.zeros(3), 1.0
    )
    assert pose_uncertainty_of_points(shares, rows, C, B) == pytest.approx(
        [0.0, math.sqrt(2) * sigma], abs=1e-9
    )
    # overlaps that fix view 1's z to view 0's: the posterior of their difference shrinks (a view the
    # refinement held has no overlaps in its information: tests/test_view_refinement.py)
    info = np.zeros((12, 12))
    info[5, 5] = info[11, 11] = 1e6
    info[5, 11] = info[11, 5] = -1e6
    C = posterior_covariance(info, 2, [sigma, sigma], [1e-3, 1e-3], 1.0)
    assert C[5, 5] + C[11, 11] - 2 * C[5, 11] < 1e-5 and C[5, 5] == pytest.approx(sigma**2 / 2, rel=1e-3)


def test_stats_and_combine_are_numpys_own() -> None:
    """stats: numpy's median, 95th percentile (linear) and max of the finite values, rounded to 5 decimals,
    for odd and even counts and ties; combine: the root of the squares summed in the terms' order, bit for
    bit (a scalar term broadcast)."""
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 10, 11, 1000, 1001):
        x = np.round(rng.gamma(2.0, 0.01, size=n), 4)
        x[rng.random(n) < 0.1] = np.nan
        f = x[np.isfinite(x)]
        want = {"median": None, "p95": None, "max": None}
        if len(f):
            want = {
                k: round(float(v), 5)
                for k, v in (("median", np.median(f)), ("p95", np.percentile(f, 95)), ("max", f.max()))
            }
        assert stats(x) == want
    a, b = rng.random(7), rng.random(7)
    assert np.array_equal(combine(a, b, 0.25), np.sqrt(a**2 + b**2 + 0.25**2))
