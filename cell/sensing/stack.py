"""Checks that a captured image stack matches its pattern set before anything is decoded.

A bad stack must stop the scan with an error naming the frame, never decode into something that looks like
a valid cloud: missing or extra frames, wrong resolution, wrong bit depth (dtype), frames with no projector
light.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cell.errors import ConfigError
from cell.sensing.patterns import PatternSet


class StackError(ConfigError):
    """A captured stack does not fit its pattern set; ``field`` names the offending frame."""


def _dtype_for(bit_depth: int) -> type:
    return np.uint8 if bit_depth == 8 else np.uint16


def check_stack(
    stack: NDArray | Sequence[NDArray],
    patterns: PatternSet,
    resolution: tuple[int, int],
    bit_depth: int,
    min_signal_dn: float = 4.0,
    source: str = "image stack",
) -> NDArray:
    """Validate and return the stack as one (N, H, W) array.

    ``resolution`` is the camera's (width, height); ``bit_depth`` 8 needs uint8 frames, 10/12 need uint16.
    A coded frame is "all dark" when, on a 1/8 subsample, no pixel rises ``min_signal_dn`` above the black
    frame: the projector showed nothing (off, wrong source, lens cap).
    """
    frames = list(stack) if not isinstance(stack, np.ndarray) else [f for f in stack]
    names = patterns.names
    if len(frames) < len(names):
        raise StackError(
            f"{len(frames)} frames, expected {len(names)}: frame '{names[len(frames)]}' "
            f"(index {len(frames)}) and later ones are missing",
            path=source,
            field=names[len(frames)],
        )
    if len(frames) > len(names):
        raise StackError(
            f"{len(frames)} frames, expected {len(names)}: extra frame at index {len(names)} "
            f"after the last one '{names[-1]}'",
            path=source,
            field=f"frame {len(names)}",
        )
    w, h = resolution
    want = _dtype_for(bit_depth)
    for name, f in zip(names, frames):
        if f.ndim != 2 or f.shape != (h, w):
            raise StackError(
                f"frame '{name}' is {'x'.join(map(str, f.shape[::-1]))}, the camera gives "
                f"{w}x{h} single-channel images",
                path=source,
                field=name,
            )
        if f.dtype != want:
            raise StackError(
                f"frame '{name}' has dtype {f.dtype}, a {bit_depth}-bit camera gives "
                f"{np.dtype(want).name}; check the pixel format",
                path=source,
                field=name,
            )
    arr = np.stack(frames) if not isinstance(stack, np.ndarray) else stack
    if bit_depth < 16 and want == np.uint16 and arr[:, ::8, ::8].max() > 2**bit_depth - 1:
        raise StackError(
            f"values above {2**bit_depth - 1}: not {bit_depth}-bit data", path=source, field="bit_depth"
        )
    black = arr[patterns.index("black"), ::8, ::8].astype(np.int32)
    white = arr[patterns.index("white"), ::8, ::8].astype(np.int32) - black
    lifts = {}
    for i, name in enumerate(names):
        if name != "black":
            lifts[name] = arr[i, ::8, ::8].astype(np.int32) - black
    for i, name in enumerate(names):
        if name == "black" or lifts[name].max() >= min_signal_dn:
            continue
        # A stripe frame may be legitimately dark where the camera sees only its off-stripes: then its
        # complement must look like the white frame.
        partner = name[:-4] if name.endswith("_inv") else name + "_inv"
        tol = max(min_signal_dn, 0.25 * float(white.max()))
        if partner in lifts and white.max() >= min_signal_dn and np.abs(lifts[partner] - white).max() <= tol:
            continue
        raise StackError(
            f"frame '{name}' (index {i}) is all dark: no pixel is brighter than the black "
            "frame; is the projector on and showing the HDMI input?",
            path=source,
            field=name,
        )
    return arr
