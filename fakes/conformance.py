"""The type checker's proof that every simulated and replay device satisfies its contract.

``cell.contracts`` declares the device kinds as runtime-checkable Protocols, but ``isinstance`` against a
Protocol only checks that the member *names* exist. Each function below returns an implementation as its
Protocol, so mypy (``make typecheck``) checks the members' signatures and types too: a device whose method
drifts from its contract fails the lint, not a run. Nothing here runs; a new implementation adds a line.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cell.contracts import (
        BoardStage,
        Camera,
        Clock,
        GlassRig,
        Projector,
        Robot,
        SequenceProjector,
        TimedProjector,
    )
    from cell.verification.stage import ArtefactStage
    from drivers.dlpc350 import HidTransport
    from drivers.serial_projector import PatternDisplay
    from drivers.serial_transport import Transport
    from fakes.artefact_stage import SimArtefactStage
    from fakes.camera import SimCamera
    from fakes.clock import SimClock
    from fakes.dlpc350_peer import Dlpc350Peer, SimPatternDisplay
    from fakes.glass_rig import SimGlassCamera, SimGlassRig
    from fakes.projector import SimProjector
    from fakes.projector_emulator import EscVp21Projector, ExpectedProtocol
    from fakes.replay import ReplayCamera, ReplayGlassRig, ReplayProjector, ReplayRigCamera, ReplayRobot
    from fakes.robot import SimRobot
    from fakes.stage import SimBoardStage


# --------------------------------------------------------------------------------------------- simulated
def _sim_projector(x: SimProjector) -> Projector:
    return x


def _sim_projector_timed(x: SimProjector) -> TimedProjector:
    return x


def _sim_projector_sequence(x: SimProjector) -> SequenceProjector:
    return x


def _sim_camera(x: SimCamera) -> Camera:
    return x


def _sim_robot(x: SimRobot) -> Robot:
    return x


def _sim_clock(x: SimClock) -> Clock:
    return x


def _sim_glass_rig(x: SimGlassRig) -> GlassRig:
    return x


def _sim_glass_camera(x: SimGlassCamera) -> Camera:
    return x


def _sim_board_stage(x: SimBoardStage) -> BoardStage:
    return x


def _sim_artefact_stage(x: SimArtefactStage) -> ArtefactStage:
    return x


# --------------------------------------------------------------------------------------------- replay
def _replay_projector(x: ReplayProjector) -> Projector:
    return x


def _replay_camera(x: ReplayCamera) -> Camera:
    return x


def _replay_robot(x: ReplayRobot) -> Robot:
    return x


def _replay_glass_rig(x: ReplayGlassRig) -> GlassRig:
    return x


def _replay_rig_camera(x: ReplayRigCamera) -> Camera:
    return x


# --------------------------------------------------------------------------------------------- driver peers
# the emulated far ends the drivers' tests plug in where the hardware link would be
def _escvp21_transport(x: EscVp21Projector) -> Transport:
    return x


def _expected_protocol_transport(x: ExpectedProtocol) -> Transport:
    return x


def _dlpc350_peer(x: Dlpc350Peer) -> HidTransport:
    return x


def _sim_pattern_display(x: SimPatternDisplay) -> PatternDisplay:
    return x
