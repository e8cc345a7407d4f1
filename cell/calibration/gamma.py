"""Projector response (gamma) calibration: measure what the camera sees for uniform grey levels on a white
board, and build the look-up table that makes the projected intensity linear in the pattern value.

A non-linear projector bends the sinusoids of phase shifting into waves with harmonics, and the decoded phase
then ripples: planes come out wavy (a common complaint with open structured-light systems). Square-wave codes
(Gray, line shift) only use 0 and 255 and do not care.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cell.errors import CalibrationError
from cell.sensing.patterns import PatternSet


def grey_levels(n: int = 17) -> NDArray[np.uint8]:
    """``n`` evenly spaced grey levels from 0 to 255."""
    return np.rint(np.linspace(0, 255, n)).astype(np.uint8)


def measure_response(images: NDArray, levels: NDArray, min_swing_dn: float = 20.0) -> NDArray[np.float64]:
    """Normalised response r(g) = (I(g) - I(0)) / (I(255) - I(0)) per level, the median over the pixels whose
    swing I(255) - I(0) exceeds ``min_swing_dn``. ``images`` (n_levels, H, W) of uniform ``levels`` (which
    must start at 0 and end at 255)."""
    lv = np.asarray(levels)
    if lv[0] != 0 or lv[-1] != 255 or np.any(np.diff(lv.astype(int)) <= 0):
        raise CalibrationError("grey levels must increase strictly from 0 to 255")
    im = np.asarray(images, dtype=np.float64)
    if len(im) != len(lv):
        raise CalibrationError(f"{len(im)} images for {len(lv)} grey levels")
    swing = im[-1] - im[0]
    ok = swing > min_swing_dn
    if ok.sum() < 100:
        raise CalibrationError(
            "projector response: too few pixels lit by the projector (white - black below "
            f"{min_swing_dn} DN); is the white board in view and the projector on?"
        )
    return np.median((im[:, ok] - im[0, ok]) / swing[ok], axis=1)


def linearising_lut(levels: NDArray, response: NDArray) -> NDArray[np.uint8]:
    """LUT[256]: the pattern value to send so that the projected intensity is linear in the wanted value."""
    r = np.asarray(response, dtype=np.float64)
    if np.any(np.diff(r) <= -0.01):
        raise CalibrationError(
            "projector response is not monotonic; check exposure (saturation) and ambient light"
        )
    r = np.maximum.accumulate(r)
    wanted = np.arange(256) / 255.0
    return np.clip(np.rint(np.interp(wanted, r, np.asarray(levels, float))), 0, 255).astype(np.uint8)


def fitted_gamma(levels: NDArray, response: NDArray) -> float:
    """The exponent of the power law r = (g/255)^gamma that best fits the response (log-log least squares)."""
    g = np.asarray(levels, float) / 255.0
    r = np.asarray(response, float)
    ok = (g > 0.05) & (r > 1e-3) & (g < 1)
    return float(np.sum(np.log(g[ok]) * np.log(r[ok])) / np.sum(np.log(g[ok]) ** 2))


def apply_lut(patterns: PatternSet, lut: NDArray[np.uint8]) -> PatternSet:
    """The same pattern set with every frame sent through the projector LUT."""
    return dataclasses.replace(patterns, frames=np.asarray(lut, np.uint8)[patterns.frames])


def gamma_figures(levels: NDArray, response: NDArray) -> dict[str, Any]:
    return {
        "levels": [int(x) for x in levels],
        "response": [float(x) for x in response],
        "fitted_gamma": fitted_gamma(levels, response),
    }
