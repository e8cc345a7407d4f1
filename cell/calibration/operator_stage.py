"""The operator as a board stage: on a cell without a motorised stage, each calibration target is placed by
hand. The routine says which target and roughly where (height above the table, tilt); the operator places it
and confirms on the console, or declines, which stops the routine with a DeviceFault naming this stage."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from cell.contracts import CalibrationBoard
from cell.errors import DeviceFault


class OperatorBoardStage:
    """:class:`cell.contracts.BoardStage` by console prompts. ``ask`` returns the operator's answer to a
    prompt (``input`` by default; tests pass a function)."""

    def __init__(self, name: str = "operator", ask: Callable[[str], str] = input) -> None:
        self.name = name
        self.ask = ask

    def connect(self) -> None:
        return None

    def close(self) -> None:
        return None

    def place(self, board: CalibrationBoard, T_W_Bd: NDArray[np.float64]) -> None:
        T = np.asarray(T_W_Bd, dtype=np.float64)
        tilt = float(np.degrees(np.arccos(np.clip(T[2, 2], -1.0, 1.0))))
        x, y, z = T[:3, 3]
        answer = self.ask(
            f"Place the {board.kind.value} target '{board.name}' with its origin near world "
            f"({x:.0f}, {y:.0f}, {z:.0f}) mm, tilted {tilt:.0f} deg; keep it still. Ready? [y/N] "
        )
        if answer.strip().lower() not in ("y", "yes"):
            raise DeviceFault(self.name, f"the operator did not place '{board.name}'; the routine stops here")

    def clear(self) -> None:
        self.ask("Take the calibration target out of the sensor's view, then press Enter. ")
