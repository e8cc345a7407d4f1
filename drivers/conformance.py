"""The type checker's proof that every real driver satisfies its contract (see ``fakes/conformance.py``).

Each function returns a driver as the Protocol it implements, so mypy (``make typecheck``) checks the
members' signatures and types, which ``isinstance`` against a runtime-checkable Protocol does not. Nothing
here runs, and nothing is imported at run time (the hardware libraries stay unloaded); a new driver adds a
line.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cell.calibration.operator_stage import OperatorBoardStage
    from cell.contracts import (
        BoardStage,
        Camera,
        Clock,
        GlassRig,
        Projector,
        Robot,
        SequenceProjector,
        SystemClock,
        TimedProjector,
    )
    from cell.verification.stage import ArtefactStage, OperatorStage
    from drivers.aravis_camera import AravisCamera
    from drivers.dlpc350 import Dlpc350Projector, HidapiTransport, HidTransport
    from drivers.genicam_camera import GenICamCamera
    from drivers.glass_rig import GenICamGlassRig
    from drivers.hdmi_display import HdmiDisplay
    from drivers.serial_projector import PatternDisplay, SerialProjector
    from drivers.serial_transport import PySerialTransport, RecordingTransport, Transport
    from drivers.ur_robot import URRobot


# --------------------------------------------------------------------------------------------- devices
def _serial_projector(x: SerialProjector) -> Projector:
    return x


def _serial_projector_timed(x: SerialProjector) -> TimedProjector:
    return x


def _dlpc350_projector(x: Dlpc350Projector) -> Projector:
    return x


def _dlpc350_projector_timed(x: Dlpc350Projector) -> TimedProjector:
    return x


def _dlpc350_projector_sequence(x: Dlpc350Projector) -> SequenceProjector:
    return x


def _genicam_camera(x: GenICamCamera) -> Camera:
    return x


def _aravis_camera(x: AravisCamera) -> Camera:
    return x


def _ur_robot(x: URRobot) -> Robot:
    return x


def _genicam_glass_rig(x: GenICamGlassRig) -> GlassRig:
    return x


# the operator as a device: the technician places targets by hand (the real cell's stages)
def _operator_board_stage(x: OperatorBoardStage) -> BoardStage:
    return x


def _operator_artefact_stage(x: OperatorStage) -> ArtefactStage:
    return x


def _system_clock(x: SystemClock) -> Clock:
    return x


# --------------------------------------------------------------------------------------------- links
def _hdmi_display(x: HdmiDisplay) -> PatternDisplay:
    return x


def _pyserial_transport(x: PySerialTransport) -> Transport:
    return x


def _recording_transport(x: RecordingTransport) -> Transport:
    return x


def _hidapi_transport(x: HidapiTransport) -> HidTransport:
    return x
