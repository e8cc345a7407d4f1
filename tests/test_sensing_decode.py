"""Decoding against the simulator's ground truth (projector_uv per camera pixel) and bad-stack handling."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cell.config import MaterialConfig, SimConfig
from cell.contracts import CameraSettings, PixelFormat
from cell.geometry import make_pose
from cell.sensing.decode import Reason, decode
from cell.sensing.patterns import gcls_patterns, gcps_patterns
from cell.sensing.scan import capture_stack
from cell.sensing.stack import StackError, check_stack
from fakes.sim.testing import small_rig

GCLS = gcls_patterns(128, 96, 8, 8)  # 16 stripes of 8 px, 8 shifts of 1 px: 128 codes, 26 images
GCPS = gcps_patterns(128, 96, 8, 8)  # same 26 images: 8 phase steps


def _capture(rig, ps, bits: int = 8):
    rig.projector.connect()
    rig.projector.set_power(True)
    rig.camera.connect()
    rig.camera.configure(CameraSettings(exposure_ms=10.0, pixel_format=PixelFormat(f"Mono{bits}")))
    return check_stack(capture_stack(rig.camera, rig.projector, ps), ps, rig.camera.resolution, bits)


@pytest.fixture(scope="module")
def plate_rig():
    tilt = make_pose(trimesh.transformations.rotation_matrix(0.25, [0, 1, 0])[:3, :3], [0, 0, 20.0])
    plate = trimesh.creation.box((400, 300, 4), transform=tilt)
    return small_rig(part_W=plate, bit_depth=8, sim=SimConfig(seed=3))


@pytest.mark.parametrize("ps", [GCLS, GCPS], ids=["gcls", "gcps"])
def test_decoded_projector_coordinate_matches_ground_truth(plate_rig, ps) -> None:
    stack = _capture(plate_rig, ps)
    ad = decode(stack, ps).primary()
    truth = plate_rig.renderer.ground_truth(plate_rig.T_W_C).projector_uv[..., 0]
    ok = ad.valid
    assert ok.mean() > 0.9
    err = ad.u[ok] - truth[ok]
    rms = float(np.sqrt(np.mean(err**2)))
    assert rms < 0.1, rms  # the acceptance: RMS < 0.1 projector px at the default noise
    assert np.abs(err).max() < 0.6


def test_both_directions_decode_rows_and_columns_against_ground_truth(plate_rig) -> None:
    ps = gcls_patterns(128, 96, 8, 8, "both")  # row stripes are decoded along camera columns
    dec = decode(_capture(plate_rig, ps), ps)
    truth = plate_rig.renderer.ground_truth(plate_rig.T_W_C).projector_uv
    for axis, k in (("columns", 0), ("rows", 1)):
        ad = dec.axes[axis]
        assert ad.valid.mean() > 0.9, axis
        err = ad.u[ad.valid] - truth[..., k][ad.valid]
        assert np.sqrt(np.mean(err**2)) < 0.1 and np.abs(err).max() < 0.6, axis


def test_gcls_edges_land_within_a_tenth_of_a_pixel_on_a_12bit_camera() -> None:
    rig = small_rig(bit_depth=12, sim=SimConfig(seed=5))
    stack = _capture(rig, GCLS, 12)
    assert stack.dtype == np.uint16
    ad = decode(stack, GCLS, 12).primary()
    truth = rig.renderer.ground_truth(rig.T_W_C).projector_uv[..., 0]
    assert np.sqrt(np.mean((ad.u[ad.valid] - truth[ad.valid]) ** 2)) < 0.05


def test_shadow_and_glare_never_produce_points() -> None:
    block = trimesh.creation.box((60, 60, 40), transform=make_pose(translation_mm=(-10, 0, 20)))
    sim = SimConfig(seed=2, part_material=MaterialConfig(albedo=0.9, specular=40.0, shininess=8.0))
    rig = small_rig(part_W=block, bit_depth=8, sim=sim)
    stack = _capture(rig, GCLS)
    ad = decode(stack, GCLS).primary()
    gt = rig.renderer.ground_truth(rig.T_W_C)
    saturated = stack[GCLS.index("white")] == 255
    shadow = gt.hit & ~gt.lit
    assert saturated.sum() > 20 and shadow.sum() > 50  # the scene really has glare and a shadow
    assert not np.any(ad.valid & saturated)
    assert not np.any(ad.valid & shadow)
    assert np.all(ad.reasons[saturated] & Reason.SATURATED)
    assert np.mean((ad.reasons[shadow] & Reason.DARK) > 0) > 0.95


def test_bad_stacks_name_the_frame(plate_rig) -> None:
    stack = _capture(plate_rig, GCLS)
    res = plate_rig.camera.resolution
    with pytest.raises(StackError, match="col_shift7_inv"):
        check_stack(list(stack[:-1]), GCLS, res, 8)
    with pytest.raises(StackError, match="extra frame at index 26"):
        check_stack(list(stack) + [stack[0]], GCLS, res, 8)
    with pytest.raises(StackError, match="'white' is 80x60"):
        check_stack([s[::2, ::2] for s in stack], GCLS, res, 8)
    with pytest.raises(StackError, match="'white' has dtype uint16"):
        check_stack(stack.astype(np.uint16), GCLS, res, 8)
    dark = stack.copy()
    k = GCLS.index("col_gray2")
    dark[k] = dark[GCLS.index("black")]
    with pytest.raises(StackError, match="'col_gray2' .* all dark"):
        check_stack(dark, GCLS, res, 8)
