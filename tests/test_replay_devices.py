"""Recording proxy + replay fakes: each contract test is run against a real driver wrapped in
RecordingProxy (GenICam on viky.cti, UR on the fake controller), the fixture is saved, and the same contract
test must pass against the replay fake built from it, consuming every recorded call."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cell.contracts import Camera, PixelFormat, ProjectorSource, Robot
from cell.errors import DeviceProtocolError
from cell.geometry import pose_from_xyz_rpy
from drivers.genicam_camera import GenICamCamera, viky_cti
from drivers.recording import RecordingProxy
from drivers.serial_projector import SerialProjector
from drivers.ur_robot import URRobot
from fakes.projector_emulator import ExpectedProtocol, load_transcript
from fakes.replay import ReplayCamera, ReplayProjector, ReplayRobot
from fakes.ur_controller import FakeURController
from tests.contracts.camera_contract import CameraContract
from tests.contracts.robot_contract import RobotContract
from tests.test_driver_genicam_camera import camera_config
from tests.test_driver_serial_projector import SESSION, projector_config, run_session
from tests.test_driver_ur_robot import (
    FACING_X,
    fake_controller_server,  # noqa: F401 - stops the fakes' forkserver
    fresh_host,
    robot_config,
)

pytestmark = pytest.mark.timeout(60)


def record_then_replay(
    tmp_path: Path, make_real: Callable[[], Any], replay_cls: type, test: Callable[..., None], *extra: Any
) -> None:
    real = RecordingProxy(make_real())
    skipped = None
    try:
        test(real, *extra)
    except pytest.skip.Exception as exc:
        skipped = exc
    fixture = real.save(tmp_path / "fixture")
    replay = replay_cls(fixture=fixture)
    if skipped is not None:
        with pytest.raises(pytest.skip.Exception):
            test(replay, *extra)
        return
    test(replay, *extra)
    assert replay.remaining == 0


CAMERA_TESTS = [
    ("test_identity_and_resolution", ()),
    ("test_connect_and_close_are_idempotent", ()),
    ("test_configure_round_trip", ()),
    ("test_grab_after_trigger_returns_a_frame", (PixelFormat.MONO8,)),
    ("test_grab_after_trigger_returns_a_frame", (PixelFormat.MONO12,)),
    ("test_frame_ids_and_timestamps_increase", ()),
    ("test_grab_without_trigger_times_out_in_time", ()),
    ("test_free_run_grabs_without_trigger", ()),
]


@pytest.mark.skipif(viky_cti() is None or not viky_cti().is_file(), reason="viky.cti not installed")
@pytest.mark.parametrize("name,extra", CAMERA_TESTS, ids=[f"{n}{list(map(str, e))}" for n, e in CAMERA_TESTS])
def test_camera_contract_on_replay(tmp_path: Path, name: str, extra: tuple) -> None:
    contract = CameraContract()
    contract.timeout_ms = 500.0
    options = {"ignore_missing": ["ExposureTime", "Gain"]}
    record_then_replay(
        tmp_path,
        lambda: GenICamCamera(camera_config(**options)),
        ReplayCamera,
        getattr(contract, name),
        *extra,
    )
    assert isinstance(ReplayCamera(fixture=tmp_path / "fixture"), Camera)


ROBOT_TESTS = [
    "test_connect_state_close",
    "test_move_linear_reaches_the_pose",
    "test_refuses_a_pose_outside_the_envelope",
]


@pytest.mark.parametrize("name", ROBOT_TESTS)
def test_robot_contract_on_replay(tmp_path: Path, name: str) -> None:
    pose = pose_from_xyz_rpy([450.0, 100.0, 400.0], [np.pi, 0.0, 0.3])
    extra = () if name == "test_connect_state_close" else (pose,)
    test = getattr(RobotContract(), name)
    with FakeURController(fresh_host(), joints=FACING_X) as fake:
        real = RecordingProxy(URRobot(robot_config(fake.host)))
        test(real, *extra)
    replay = ReplayRobot(fixture=real.save(tmp_path / "fixture"))
    assert isinstance(replay, Robot)
    test(replay, *extra)
    assert replay.remaining == 0


def test_projector_session_replays_and_is_strict(tmp_path: Path) -> None:
    with ExpectedProtocol(load_transcript(SESSION)) as transport:
        real = RecordingProxy(SerialProjector(projector_config(), transport=transport))
        recorded_status = run_session(real)
    replay = ReplayProjector(fixture=real.save(tmp_path / "p"))
    assert repr(run_session(replay)) == repr(recorded_status)  # repr: temperature is NaN, and NaN != NaN
    assert replay.remaining == 0
    strict = ReplayProjector(fixture=tmp_path / "p")
    strict.connect()
    with pytest.raises(DeviceProtocolError, match="recorded as set_power"):
        strict.set_source(ProjectorSource.HDMI)  # out of order: the session powered on first
