"""How an artefact gets to a verification position: the artefact-stage contract and its real implementation.

On a real cell the technician places the artefact by hand on its stand at the position the procedure names
(``OperatorStage``); a motorised stage would be another implementation. The simulated cell's stage
(fakes/artefact_stage.py) puts the artefact mesh into the simulated scene. cell/devices.py builds the one the
cell config calls for; the procedure sees only :class:`ArtefactStage`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

ArtefactName = Literal["sphere", "ball_bar", "ball_bar_long", "plane"]


class ArtefactStage(Protocol):
    """Puts one artefact at a pose in the world and takes it away."""

    def place(self, artefact: ArtefactName, T_W_A: NDArray[np.float64], label: str) -> None:
        """Put ``artefact`` at ``T_W_A`` (artefact frame in the world, mm; cell.verification.artefacts defines
        the artefact frames). ``label`` names the position for people. Returns when it is in place."""
        ...

    def clear(self) -> None:
        """Take every artefact away."""
        ...


class OperatorStage:
    """The technician places the artefact by hand: the procedure prints where and waits for confirmation."""

    def __init__(self, ask: Callable[[str], str] = input, say: Callable[[str], None] = print):
        self._ask, self._say = ask, say

    def place(self, artefact: ArtefactName, T_W_A: NDArray[np.float64], label: str) -> None:
        T = np.asarray(T_W_A, dtype=np.float64)
        axis = T[:3, 0] if artefact != "plane" else T[:3, 2]
        what = "bar axis" if artefact != "plane" else "face normal"
        along = (
            "" if artefact == "sphere" else f", {what} along ({axis[0]:+.2f}, {axis[1]:+.2f}, {axis[2]:+.2f})"
        )
        self._say(
            f"Place the {artefact.replace('_', ' ')} at position '{label}': centre at world "
            f"({T[0, 3]:.0f}, {T[1, 3]:.0f}, {T[2, 3]:.0f}) mm{along}; within a few mm and degrees is enough."
        )
        self._ask("Press Enter when it is in place and still. ")

    def clear(self) -> None:
        self._say("Remove the artefact from the measuring volume.")
        self._ask("Press Enter when the volume is clear. ")
