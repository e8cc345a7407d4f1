"""The GlassRig contract (tests/contracts/glass_rig_contract.py) against every implementation: the simulated
rig (rig_small.yaml with tiny central regions of interest of distinct sizes, rendering the nominal pane), the
GenICam rig on viky.cti (three simulated GenTL devices, software trigger), and the replay rig served from a
fixture that each contract test records through RecordingProxy(GenICamGlassRig) just before it runs on the
replay. Truth: the cameras' configured image sizes (frame order shows in the shapes), the recorded frames
themselves for the replay, and the recorded call order for its strictness."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from cell.errors import ConfigError, DeviceProtocolError
from cell.glass.config import GlassRigConfig, load_glass_rig
from cell.mesh import load_mesh
from drivers.genicam_camera import viky_cti
from drivers.glass_rig import GenICamGlassRig
from drivers.recording import RecordingProxy
from fakes.glass_rig import SimGlassRig
from fakes.replay import ReplayGlassRig
from tests.contracts.glass_rig_contract import GlassRigContract
from tests.test_driver_glass_rig import rig_config

pytestmark = pytest.mark.timeout(30)
needs_viky = pytest.mark.skipif(
    viky_cti() is None or not viky_cti().is_file(), reason="viky.cti not installed"
)

GLASS = Path(__file__).resolve().parent.parent / "recipes" / "glass"
ROI = [(96, 72), (80, 60), (64, 48), (112, 84)]  # (width, height) per sim camera: distinct, so order shows


def sim_config() -> GlassRigConfig:
    """rig_small.yaml with each camera reading a small central region of interest (same lens and pixels)."""
    base = load_glass_rig(GLASS / "rig_small.yaml")
    cams = []
    for cam, (w, h) in zip(base.cameras, ROI):
        dx, dy = (cam.width_px - w) / 2, (cam.height_px - h) / 2
        cams.append(
            cam.model_copy(
                update={"width_px": w, "height_px": h, "cx_px": cam.cx_px - dx, "cy_px": cam.cy_px - dy}
            )
        )
    return GlassRigConfig.model_validate({**base.model_dump(), "cameras": [c.model_dump() for c in cams]})


@pytest.fixture(scope="module")
def nominal_pane():
    return load_mesh(GLASS / "panes" / "pane_nominal.stl")


class TestSimGlassRig(GlassRigContract):
    @pytest.fixture
    def glass_rig(self, nominal_pane) -> Iterator[SimGlassRig]:
        rig = SimGlassRig(sim_config(), nominal_pane)
        yield rig
        rig.close()

    def test_frames_show_the_pane(self, glass_rig: SimGlassRig) -> None:
        """Not blank: the screen's dots seen in the pane make dark and bright pixels in every frame."""
        glass_rig.connect()
        frames = glass_rig.grab_all(self.timeout_ms)
        assert [f.pixels.shape for f in frames] == [(h, w) for w, h in ROI]
        assert all(np.ptp(f.pixels) > 10 for f in frames)


@needs_viky
class TestGenICamGlassRig(GlassRigContract):
    @pytest.fixture
    def glass_rig(self) -> Iterator[GenICamGlassRig]:
        rig = GenICamGlassRig(rig_config(), {"trigger": "software"})
        yield rig
        rig.close()


@needs_viky
class TestReplayGlassRig(GlassRigContract):
    """Each contract test first runs on the real rig through RecordingProxy, then on the replay of what it
    recorded, which must serve every recorded call."""

    @pytest.fixture
    def glass_rig(self, request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ReplayGlassRig]:
        cfg = rig_config()
        real = GenICamGlassRig(cfg, {"trigger": "software"})
        proxy = RecordingProxy(real)
        try:
            getattr(request.instance, request.function.__name__)(proxy)
        finally:
            real.close()
        replay = ReplayGlassRig(cfg, fixture=proxy.save(tmp_path / "fixture"))
        yield replay
        assert replay.remaining == 0


def _recorded(tmp_path: Path, grabs: int = 2) -> tuple[GlassRigConfig, Path, list[list]]:
    cfg = rig_config()
    proxy = RecordingProxy(GenICamGlassRig(cfg, {"trigger": "software"}))
    proxy.connect()
    try:
        frames = [proxy.grab_all(500.0) for _ in range(grabs)]
    finally:
        proxy.close()
    return cfg, proxy.save(tmp_path / "fixture"), frames


@needs_viky
def test_replay_serves_the_recorded_frames_and_is_strict(tmp_path: Path) -> None:
    cfg, fixture, recorded = _recorded(tmp_path)
    replay = ReplayGlassRig(cfg, fixture=fixture)
    replay.connect()
    for want in recorded:
        got = replay.grab_all(500.0)
        assert len(got) == len(want)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g.pixels, w.pixels)
            assert (g.timestamp_s, g.frame_id, g.metadata) == (w.timestamp_s, w.frame_id, w.metadata)
    replay.close()
    assert replay.remaining == 0
    with pytest.raises(DeviceProtocolError, match="past the end"):
        replay.grab_all(500.0)

    out_of_order = ReplayGlassRig(cfg, fixture=fixture)
    with pytest.raises(DeviceProtocolError, match="recorded as connect"):
        out_of_order.grab_all(500.0)  # the recording connected first
    other_args = ReplayGlassRig(cfg, fixture=fixture)
    other_args.connect()
    with pytest.raises(DeviceProtocolError, match=r"recorded as grab_all\(500\.0,\)"):
        other_args.grab_all(1000.0)  # a different timeout than recorded
    with pytest.raises(DeviceProtocolError, match="not recorded"):
        other_args.cameras[0].trigger()  # per-camera calls never went through the rig's proxy


@needs_viky
def test_replay_refuses_a_fixture_of_another_rig(tmp_path: Path) -> None:
    cfg, fixture, _ = _recorded(tmp_path, grabs=0)
    with pytest.raises(ConfigError, match="recorded rig"):
        ReplayGlassRig(cfg.model_copy(update={"name": "another-rig"}), fixture=fixture)
    with pytest.raises(ConfigError, match="fixture not found"):
        ReplayGlassRig(cfg, fixture=tmp_path / "nothing-here")
