"""Projector pattern sets: GCLS (Gray code + line shifting) and the GCPS baseline (Gray code + phase
shifting).

Conventions (projector pixels, OpenCV pixel-centre convention): projector pixel ``i`` covers the continuous
coordinate ``[i - 0.5, i + 0.5]``. Along the coded axis the coded range is ``[0, n_codes * shift_px)`` pixels
starting at ``offset_px``. Gray stripe ``k`` covers pixels ``[k*stripe, (k+1)*stripe)``; line-shift pattern
``j`` is a square wave of half-period ``stripe_px`` whose edges sit at pixel boundaries
``j*shift_px + k*stripe_px - 0.5``. Over all ``n_shifts`` patterns the edges fall every ``shift_px`` pixels:
``2**n_gray * n_shifts`` codes (dissertation 2.1.4: 64 stripes x 12 shifts = 768 codes; 0.4 mm spacing:
shift 2 px, 6 shifts, 384 codes). The shift patterns' bits form a Johnson (twisted-ring) code of period
``2*n_shifts`` codes, which the Gray stripe index unwraps (see decode.py). Every coded frame has its inverse.
GCPS replaces the line shifts by ``n_phase`` sinusoids of period ``2*stripe_px`` (two Gray stripes), so a
one-stripe Gray error at a boundary is still unwrapped correctly.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import NDArray

from cell.errors import ConfigError

if TYPE_CHECKING:
    from cell.config import ProjectorConfig

# The measuring code's line-shift edge width (projector px). A sharp edge (1) spans 1/k camera pixels where
# one camera pixel sees k projector pixels; where k > 1 (surfaces facing the projector, seen obliquely by the
# camera) it falls between two camera samples and its zero crossing locks to the camera's pixel grid. A ramp
# spans more camera pixels but has a gentler slope, which lets the noise in where the code is sparse. 1.5 px
# (grey levels 40 / 215 beside each boundary) is the worst-case best measured on the calibrated default cell's
# spheres (PF, um, at near bottom left / far top left / centre far third: sharp 52.1 / 41.5 / 63.4, 1.5 px
# 37.5 / 42.6 / 44.3, 2 px 28.5 / 50.7 / 29.5; docs/verification.md): chosen from {1, 1.5, 2} on those
# same spheres.
MEASURING_EDGE_PX = 1.5

Codec = Literal["gcls", "gcps", "graycode"]  # graycode: plain Gray code, cell/sensing/graycode.py
Axis = Literal["columns", "rows"]
Direction = Literal["columns", "rows", "both"]


@dataclass(frozen=True)
class AxisCode:
    """The coding of one projector axis. ``columns``: stripes vary along projector x (vertical stripes)."""

    axis: Axis
    n_gray: int
    stripe_px: int
    n_shifts: int  # GCLS line shifts (0 for GCPS)
    n_phase: int  # GCPS phase steps (0 for GCLS)
    offset_px: int  # first coded projector pixel along the axis

    @property
    def shift_px(self) -> int:
        return self.stripe_px // self.n_shifts if self.n_shifts else 0

    @property
    def extent_px(self) -> int:
        """Coded length along the axis, projector pixels."""
        return (1 << self.n_gray) * self.stripe_px

    @property
    def n_codes(self) -> int:
        """Distinct edge positions (GCLS) or Gray stripes (GCPS)."""
        return (1 << self.n_gray) * (self.n_shifts if self.n_shifts else 1)


@dataclass(frozen=True)
class PatternSet:
    """A projector sequence: frames (N, H, W) uint8 with a name per frame, and how it was coded."""

    codec: Codec
    width_px: int
    height_px: int
    codes: tuple[AxisCode, ...]
    names: tuple[str, ...]
    frames: NDArray[np.uint8] = field(repr=False)
    edge_px: float = 1.0  # GCLS: the line shifts' edge width, projector px (shift_profile; 1: sharp)

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def code(self, axis: Axis) -> AxisCode:
        for c in self.codes:
            if c.axis == axis:
                return c
        raise KeyError(f"pattern set codes no {axis}")


def gray_bits(index: NDArray[np.int64], n_bits: int) -> NDArray[np.uint8]:
    """(n_bits, ...) Gray-code bits of integer ``index``, most significant first."""
    g = index ^ (index >> 1)
    return np.stack([((g >> (n_bits - 1 - b)) & 1).astype(np.uint8) for b in range(n_bits)])


def shift_profile(x: NDArray[np.int64], j: int, code: AxisCode, edge_px: float = 1.0) -> NDArray[np.float64]:
    """Line-shift pattern ``j`` at projector pixels ``x`` (0..1): the square wave of half-period
    ``stripe_px`` averaged over a box of ``edge_px`` projector pixels centred on each pixel. ``edge_px`` 1 is
    the plain square wave (0/1); wider boxes turn each edge into a grey ramp symmetric about its boundary, so
    that the pattern minus its inverse still crosses zero exactly at ``j*shift_px + k*stripe_px - 0.5`` (for
    any projector response: the two frames mirror each other there) but over more camera pixels."""
    if edge_px < 1.0 or edge_px > code.stripe_px:
        raise ConfigError(f"line-shift edge width {edge_px} px: give 1 to {code.stripe_px} projector pixels")
    sub = (np.arange(32) + 0.5) / 32 - 0.5  # 32 samples across a box of width 1
    xs = x[:, None] + 0.5 + edge_px * sub[None, :] - j * code.shift_px  # from the boundary at -0.5
    return np.mean(np.floor(xs / code.stripe_px) % 2, axis=1)


def _axis_frames(
    code: AxisCode, length: int, edge_px: float = 1.0
) -> tuple[list[str], list[NDArray[np.uint8]]]:
    """1-D profiles (values 0..255) of one axis' coded frames, with names; each pattern followed by its
    inverse. ``edge_px``: the line shifts' edge width (:func:`shift_profile`)."""
    x = np.arange(length, dtype=np.int64) - code.offset_px  # pixel index within the coded range
    inside = (x >= 0) & (x < code.extent_px)
    names: list[str] = []
    profiles: list[NDArray[np.uint8]] = []
    tag = "col" if code.axis == "columns" else "row"

    def add(name: str, bits: NDArray[np.uint8]) -> None:
        on = np.where(inside, bits, 0).astype(np.uint8) * 255
        off = np.where(inside, 1 - bits, 0).astype(np.uint8) * 255
        names.extend([name, name + "_inv"])
        profiles.extend([on, off])

    stripe = np.clip(x, 0, code.extent_px - 1) // code.stripe_px
    for b, bits in enumerate(gray_bits(stripe, code.n_gray)):
        add(f"{tag}_gray{b}", bits)
    for j in range(code.n_shifts):
        level = np.rint(255 * shift_profile(x, j, code, edge_px))
        names.extend([f"{tag}_shift{j}", f"{tag}_shift{j}_inv"])
        profiles.extend(
            [np.where(inside, level, 0).astype(np.uint8), np.where(inside, 255 - level, 0).astype(np.uint8)]
        )
    for k in range(code.n_phase):
        # Sampled at pixel centres; phase 0 at the coded range's left boundary x = -0.5.
        theta = 2 * np.pi * (x + 0.5) / (2 * code.stripe_px) - 2 * np.pi * k / code.n_phase
        v = np.where(inside, np.rint(127.5 + 127.5 * np.cos(theta)), 0).astype(np.uint8)
        names.append(f"{tag}_phase{k}")
        profiles.append(v)
    return names, profiles


def _axis_code(
    axis: Axis, length: int, stripe_px: int, n_gray: int | None, n_shifts: int, n_phase: int
) -> AxisCode:
    if stripe_px < 2:
        raise ConfigError(f"stripe width {stripe_px} px: must be at least 2 projector pixels")
    if n_shifts and stripe_px % n_shifts:
        raise ConfigError(f"stripe width {stripe_px} px is not a multiple of {n_shifts} shifts")
    if n_gray is None:
        n_gray = max(1, int(np.ceil(np.log2(length / stripe_px))))
    extent = (1 << n_gray) * stripe_px
    if extent > 2 * length:
        raise ConfigError(
            f"{n_gray} Gray patterns of {stripe_px} px stripes span {extent} px, "
            f"far more than the projector's {length} px"
        )
    offset = max(0, (length - extent) // 2)  # centre the coded range when it is shorter than the axis
    return AxisCode(axis, n_gray, stripe_px, n_shifts, n_phase, offset)


def _assemble(
    codec: Codec, width: int, height: int, codes: list[AxisCode], edge_px: float = 1.0
) -> PatternSet:
    names = ["white", "black"]
    frames = [np.full((height, width), 255, np.uint8), np.zeros((height, width), np.uint8)]
    for code in codes:
        n, profiles = _axis_frames(code, width if code.axis == "columns" else height, edge_px)
        names += n
        for p in profiles:
            frames.append(
                np.broadcast_to(p[None, :] if code.axis == "columns" else p[:, None], (height, width)).copy()
            )
    return PatternSet(codec, width, height, tuple(codes), tuple(names), np.stack(frames), edge_px)


def _axes(direction: Direction) -> list[Axis]:
    if direction not in ("columns", "rows", "both"):
        raise ConfigError(f"direction '{direction}': use columns, rows or both")
    return ["columns", "rows"] if direction == "both" else [direction]


def gcls_patterns(
    width_px: int = 1024,
    height_px: int = 768,
    stripe_px: int = 12,
    n_shifts: int = 12,
    direction: Direction = "columns",
    n_gray: int | None = None,
    edge_px: float = 1.0,
) -> PatternSet:
    """GCLS set: white, black, then per axis Gray patterns and line-shift square waves, each with its inverse.

    ``n_gray=None`` picks the fewest Gray patterns whose stripes cover the axis; ``edge_px`` is the width of
    the line shifts' edges in projector pixels (:func:`shift_profile`; 1: sharp).
    """
    if n_shifts < 1:
        raise ConfigError("GCLS needs at least one line shift")
    codes = [
        _axis_code(a, width_px if a == "columns" else height_px, stripe_px, n_gray, n_shifts, 0)
        for a in _axes(direction)
    ]
    return _assemble("gcls", width_px, height_px, codes, edge_px)


def gcps_patterns(
    width_px: int = 1024,
    height_px: int = 768,
    stripe_px: int = 12,
    n_phase: int = 4,
    direction: Direction = "columns",
    n_gray: int | None = None,
) -> PatternSet:
    """GCPS baseline: white, black, Gray patterns with inverses, then ``n_phase`` sinusoids of period
    2*stripe."""
    if n_phase < 3:
        raise ConfigError("phase shifting needs at least 3 steps")
    codes = [
        _axis_code(a, width_px if a == "columns" else height_px, stripe_px, n_gray, 0, n_phase)
        for a in _axes(direction)
    ]
    return _assemble("gcps", width_px, height_px, codes)


def _gray_bits(projector: ProjectorConfig) -> int | None:
    """6 Gray patterns (the dissertation's 64 stripes of 12 px) on a projector of 768 px or more, else as
    few as cover it."""
    return 6 if projector.width_px >= 768 else None


def measuring_patterns(projector: ProjectorConfig, direction: Direction = "columns") -> PatternSet:
    """The cell's measuring code for ``projector`` (inspection, validation, verification, the hand-eye's
    gauge scans, and the cycle-time model that counts its frames): GCLS, 12 px Gray stripes and 12 line
    shifts of 1 px, the shifts' edges ramped over ``MEASURING_EDGE_PX`` projector pixels."""
    w, h = projector.width_px, projector.height_px
    return gcls_patterns(w, h, 12, 12, direction, n_gray=_gray_bits(projector), edge_px=MEASURING_EDGE_PX)


def sensor_calibration_patterns(projector: ProjectorConfig) -> PatternSet:
    """The per-pixel sensor calibration's code (dissertation 5.1.1): GCLS in both directions, 12 px stripes
    and 6 shifts of 2 px, so that the code points of both axes cross."""
    w, h = projector.width_px, projector.height_px
    return gcls_patterns(w, h, 12, 6, "both", n_gray=_gray_bits(projector))


def projector_calibration_patterns(projector: ProjectorConfig) -> PatternSet:
    """The projector-intrinsics routine's code (the projector as an inverse camera): GCPS with 16 px stripes
    and 4 phase steps on both axes, so every board corner gets both projector coordinates."""
    return gcps_patterns(projector.width_px, projector.height_px, 16, 4, "both")


def uniform_patterns(projector: ProjectorConfig, levels: Sequence[int]) -> PatternSet:
    """Uniform grey frames at ``levels`` (0..255), named black (0), white (255) and grey_<level>, so that the
    stack check finds its black and white frames: the board routines' lighting (white, black) and the
    projector response's levels. They code nothing; the set keeps the GCPS set's codes only for its type."""
    w, h = projector.width_px, projector.height_px
    frames = np.stack([np.full((h, w), g, np.uint8) for g in levels])
    names = tuple({0: "black", 255: "white"}.get(int(g), f"grey_{int(g)}") for g in levels)
    return replace(gcps_patterns(w, h, 16, 4, "columns"), names=names, frames=frames)


def gcps_baseline_patterns(projector: ProjectorConfig) -> PatternSet:
    """The GCPS baseline ``cell scan --codec gcps`` compares the measuring code with: the same Gray stripes
    and 24 phase steps, as many images as :func:`measuring_patterns` (38 at XGA)."""
    w, h = projector.width_px, projector.height_px
    return gcps_patterns(w, h, 12, 24, "columns", n_gray=_gray_bits(projector))


def dissertation_gcls(
    spacing: Literal["full", "0.4mm"] = "full", direction: Direction = "columns"
) -> PatternSet:
    """The dissertation's example sets on a 1024x768 projector: 6 Gray patterns -> 64 stripes of 12 px, then
    12 shifts of 1 px (768 codes) or, for 0.4 mm point spacing, 6 shifts of 2 px (384 codes)."""
    return gcls_patterns(1024, 768, 12, 12 if spacing == "full" else 6, direction, n_gray=6)
