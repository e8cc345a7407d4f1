"""Rendered images against independent truth: stripe edges vs the plane homography, shadows vs occlusion
geometry, glare vs the mirror angle, signal level vs the shading equation, noise vs the sensor model."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from cell.config import MaterialConfig, SimConfig
from cell.geometry import invert, look_at, make_pose, transform_points
from fakes.sim.testing import small_rig, top_down_pose

QUIET = SimConfig(noise=False, seed=1)


def _white(rig) -> np.ndarray:
    p = rig.sensor.projector
    return np.full((p.height_px, p.width_px), 255, np.uint8)


def _plane_homography(K_a, T_a_W, K_b, T_b_W):
    """Homography from device a's pixels to device b's pixels induced by the plane z=0 of {W}."""
    H_a = K_a @ T_a_W[:3, [0, 1, 3]]
    H_b = K_b @ T_b_W[:3, [0, 1, 3]]
    return H_b @ np.linalg.inv(H_a)


def test_stripe_edges_land_where_the_plane_homography_says() -> None:
    T_W_C = look_at((15.0, -10.0, 400.0), (0.0, 0.0, 0.0), up=(0.2, 1.0, 0.0))
    rig = small_rig(distortion={}, sim=QUIET, T_W_C=T_W_C)
    proj = rig.sensor.projector
    u = np.arange(proj.width_px)
    period = 16
    stripes = (
        np.where((u // (period // 2)) % 2 == 1, 255, 0).astype(np.uint8)[None, :].repeat(proj.height_px, 0)
    )
    img = rig.renderer.render(T_W_C, stripes, 10.0, 0.0, None).astype(np.float64)
    inv = rig.renderer.render(T_W_C, 255 - stripes, 10.0, 0.0, None).astype(np.float64)
    d = img - inv
    lit = cv2.erode(rig.renderer.view(T_W_C).lit.astype(np.uint8), np.ones((3, 3))) > 0
    # projector edges sit between columns 8k-1 and 8k, i.e. at u = 8k - 0.5 (pixel centres are integers)
    H = _plane_homography(proj.K(), invert(T_W_C @ proj.T_C_P.matrix()), rig.sensor.camera.K(), invert(T_W_C))
    H_cp = np.linalg.inv(H)  # camera pixel -> projector pixel
    errors = []
    for y in range(d.shape[0]):
        row, ok = d[y], lit[y]
        xs = np.flatnonzero(ok[:-1] & ok[1:] & (np.sign(row[:-1]) != np.sign(row[1:])) & (row[:-1] != 0))
        for x0 in xs:
            xc = x0 + row[x0] / (row[x0] - row[x0 + 1])
            q = H_cp @ (xc, y, 1.0)
            u_e = (
                np.round((q[0] / q[2] + 0.5) / (period // 2)) * (period // 2) - 0.5
            )  # nearest projector edge
            line = H_cp[0] - u_e * H_cp[2]  # camera points whose projector column is u_e
            x_true = -(line[1] * y + line[2]) / line[0]
            errors.append(xc - x_true)
    errors = np.abs(errors)
    assert len(errors) > 500
    print(f"stripe edges: n={len(errors)} max={errors.max():.4f} rms={np.sqrt((errors**2).mean()):.4f} px")
    assert errors.max() < 0.05, f"max edge error {errors.max():.4f} px"


def test_shadow_behind_a_step_is_where_the_occlusion_geometry_says() -> None:
    lo, hi = np.array([-30.0, -30.0, 0.0]), np.array([30.0, 30.0, 40.0])
    box = trimesh.creation.box(bounds=[lo, hi])
    rig = small_rig(part_W=box, sim=QUIET)
    T_W_C = rig.T_W_C
    gt = rig.renderer.ground_truth(T_W_C)
    table = gt.hit & ~gt.part
    X = gt.points_W[table]
    C_p = (T_W_C @ rig.sensor.projector.T_C_P.matrix())[:3, 3]

    def blocked(margin: float) -> np.ndarray:  # slab test of the segment X -> C_p against the box
        d = C_p - X
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - margin - X) / d
            t2 = (hi + margin - X) / d
        tmin = np.nanmax(np.minimum(t1, t2), axis=1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=1)
        return (tmax >= np.maximum(tmin, 0)) & (tmin <= 1)

    inner, outer = blocked(-0.05), blocked(0.05)
    definite = inner == outer
    assert inner.sum() > 300  # a real shadow is in view
    assert (~definite).sum() < 0.02 * table.sum()
    lit = gt.lit[table]
    assert np.array_equal(lit[definite], ~inner[definite])

    # and the image shows it: fully shadowed table pixels get ambient light only
    img = rig.renderer.render(T_W_C, _white(rig), 10.0, 0.0, None).astype(float)
    shadow_img = np.zeros(gt.hit.shape, bool)
    shadow_img[table] = inner & definite
    core = cv2.erode(shadow_img.astype(np.uint8), np.ones((5, 5))) > 0
    cam = rig.sensor.camera
    k = (2**cam.bit_depth - 1) / cam.full_well_e
    ambient_dn = QUIET.ambient_e_per_ms * QUIET.table_material.albedo * 10.0 * k + cam.dark_offset_dn
    assert core.sum() > 100
    assert np.abs(img[core] - ambient_dn).max() <= 1.0
    assert img[gt.lit & ~gt.part].min() > ambient_dn + 100


def test_specular_glare_peaks_at_the_mirror_angle_pixel() -> None:
    n = np.array([np.sin(np.radians(15)), 0.03, np.cos(np.radians(15))])
    n /= np.linalg.norm(n)
    p0 = np.array([0.0, 0.0, 50.0])
    plate = trimesh.creation.box((250.0, 250.0, 1e-3))
    plate.apply_transform(make_pose(trimesh.geometry.align_vectors([0, 0, 1], n)[:3, :3], p0 - n * 5e-4))
    glossy = MaterialConfig(albedo=0.0, specular=1.0, shininess=5000.0)
    sim = SimConfig(noise=False, ambient_e_per_ms=0.0, part_material=glossy)
    rig = small_rig(part_W=plate, sim=sim, distortion={})
    T_W_C = rig.T_W_C
    C_c = T_W_C[:3, 3]
    C_p = (T_W_C @ rig.sensor.projector.T_C_P.matrix())[:3, 3]
    mirrored = C_p - 2 * np.dot(C_p - p0, n) * n  # projector centre reflected in the plane
    t = np.dot(p0 - C_c, n) / np.dot(mirrored - C_c, n)
    glare_W = C_c + t * (mirrored - C_c)
    glare_C = transform_points(invert(T_W_C), glare_W)
    cam = rig.sensor.camera
    expected = cam.K() @ (glare_C / glare_C[2])
    img = rig.renderer.render(T_W_C, _white(rig), 5.0, 0.0, None)
    assert img.max() < 2**cam.bit_depth - 1  # no saturation plateau
    y, x = np.unravel_index(np.argmax(img), img.shape)
    assert abs(x - expected[0]) <= 1.0 and abs(y - expected[1]) <= 1.0


def test_signal_level_follows_the_shading_equation() -> None:
    rig = small_rig(distortion={}, sim=QUIET)
    cam, proj = rig.sensor.camera, rig.sensor.projector
    T_W_C = rig.T_W_C
    e = rig.renderer.signal_e(T_W_C, _white(rig), 10.0)
    # the centre of the image sees the world origin on the table straight down
    X = np.array([0.0, 0.0, 0.0])
    C_p = (T_W_C @ proj.T_C_P.matrix())[:3, 3]
    r = np.linalg.norm(C_p - X)
    cos_i = (C_p - X)[2] / r
    alb = QUIET.table_material.albedo
    expected = 10.0 * (
        QUIET.ambient_e_per_ms * alb
        + proj.irradiance_e_per_ms * (proj.focus_distance_mm / r) ** 2 * alb * cos_i
    )
    centre = e[
        int(cam.cy_px - 0.5) : int(cam.cy_px + 1.5), int(cam.cx_px - 0.5) : int(cam.cx_px + 1.5)
    ].mean()
    assert centre == pytest.approx(expected, rel=2e-3)


@pytest.mark.parametrize(("bit_depth", "gain_db", "exposure_ms"), [(8, 12.0, 6.0), (12, 0.0, 10.0)])
def test_flat_field_noise_matches_the_sensor_model(
    bit_depth: int, gain_db: float, exposure_ms: float
) -> None:
    rig = small_rig(sim=SimConfig(seed=11), bit_depth=bit_depth)
    cam = rig.sensor.camera
    T_W_C = rig.T_W_C
    signal = rig.renderer.signal_e(T_W_C, _white(rig), exposure_ms).astype(np.float64)
    k = 10 ** (gain_db / 20) * (2**bit_depth - 1) / cam.full_well_e
    mean_model = signal * k + cam.dark_offset_dn
    std_model = np.sqrt(k**2 * (signal + cam.read_noise_e**2) + 1 / 12)  # + quantisation
    ok = (rig.renderer.view(T_W_C).lit) & (mean_model < 0.8 * (2**bit_depth - 1)) & (mean_model > 20)
    assert ok.sum() > 10000
    rng = np.random.default_rng(5)
    frames = np.stack([rig.renderer.render(T_W_C, _white(rig), exposure_ms, gain_db, rng) for _ in range(4)])
    z = (frames.astype(np.float64) - mean_model)[:, ok] / std_model[ok]
    assert abs(z.mean()) < 0.05  # mean within 5% of one noise sigma
    assert z.std() == pytest.approx(1.0, rel=0.05)
    assert (frames.astype(float)[:, ok].mean() / mean_model[ok].mean()) == pytest.approx(1.0, rel=0.05)


def test_saturation_clips_at_full_scale() -> None:
    rig = small_rig(sim=QUIET, bit_depth=8)
    img = rig.renderer.render(rig.T_W_C, _white(rig), 200.0, 0.0, None)
    assert img.dtype == np.uint8
    assert (img[rig.renderer.view(rig.T_W_C).lit] == 255).all()


def test_patterns_at_one_pose_share_one_ray_cast(monkeypatch: pytest.MonkeyPatch) -> None:
    rig = small_rig(sim=QUIET)
    calls = []
    original = rig.scene.cast
    monkeypatch.setattr(rig.scene, "cast", lambda *a: calls.append(1) or original(*a))
    pats = [np.full((96, 128), v, np.uint8) for v in (0, 128, 255)]
    stack = rig.renderer.render_stack(top_down_pose(), pats, 10.0, 0.0, None)
    assert stack.shape == (3, 120, 160) and len(calls) == 1
    assert (np.diff(stack.reshape(3, -1).mean(axis=1)) > 0).all()
    rig.renderer.render(top_down_pose(x_mm=5.0), pats[0], 10.0, 0.0, None)
    assert len(calls) == 2


def test_a_new_pose_is_computed_after_the_old_ones_are_dropped(monkeypatch: pytest.MonkeyPatch) -> None:
    """Within the cache's byte budget the old poses go before a new one is computed, not after it (a 5 MP
    pose's geometry is ~0.3 GB: two at once were a peak of the hires inspection); what is rendered from a
    pose computed again is the same image."""
    import fakes.sim.render as render

    rig = small_rig(sim=QUIET)
    r = rig.renderer
    held_when_computed = []
    original = r._compute_view
    monkeypatch.setattr(r, "_compute_view", lambda T: held_when_computed.append(len(r._cache)) or original(T))
    pat = np.full((96, 128), 200, np.uint8)
    a, b = top_down_pose(), top_down_pose(x_mm=5.0)
    first = r.render(a, pat, 10.0, 0.0, None)
    one_pose = render._nbytes(r.view(a))
    monkeypatch.setattr(render, "CACHE_BYTES", int(1.5 * one_pose))  # room for one pose, not two
    r.render(b, pat, 10.0, 0.0, None)
    assert held_when_computed == [0, 0] and list(r._cache) == [b.tobytes()]
    again = r.render(a, pat, 10.0, 0.0, None)
    assert held_when_computed == [0, 0, 0] and np.array_equal(again, first)
    monkeypatch.setattr(render, "CACHE_BYTES", 10 * one_pose)  # room for several: cache_size (3) poses kept
    for x in (10.0, 15.0):
        r.render(top_down_pose(x_mm=x), pat, 10.0, 0.0, None)
    assert held_when_computed == [0, 0, 0, 1, 2] and len(r._cache) == 3
    assert np.array_equal(r.render(a, pat, 10.0, 0.0, None), first)  # still cached: no new computation
    assert len(held_when_computed) == 5
