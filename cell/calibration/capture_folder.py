"""Capture folders: structured-light images captured elsewhere (another tool, another cell, a public data
set), described by a small manifest, read for the offline routines
(``cell calibrate intrinsics|projector|sensor --from DIR``, ``cell scan --from DIR``).
Layout and manifest: docs/capture-folders.md.

The manifest (``capture.yaml`` in the folder, validated by :class:`CaptureManifest`) names the camera and
projector resolution, the code (GCLS, GCPS, or the plain Gray code of OpenCV's ``GrayCodePattern``), the order
of the images in each pose folder and the calibration board. Each pose is one folder of images, one per
projected frame. A pose may be stored as a region of interest of the sensor (``roi_px``, as a camera's
OffsetX/OffsetY readout): board corners and decoded maps are returned in full-sensor pixels, so intrinsics
stay those of the whole sensor.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import Field, model_validator

from cell.calibration.intrinsics import MIN_CORNERS, CharucoView, detect_charuco
from cell.config import read_yaml, validate
from cell.errors import CalibrationError, ConfigError
from cell.schema import PositiveFloat, Strict
from cell.sensing.decode import AxisDecode, Decoded, Reason, decode
from cell.sensing.graycode import graycode_patterns, opencv_order
from cell.sensing.patterns import PatternSet, gcls_patterns, gcps_patterns
from cell.sensing.stack import StackError, check_stack

MANIFEST = "capture.yaml"
PosInt = Annotated[int, Field(gt=0)]


class CameraSpec(Strict):
    """The camera that took the images: full sensor size (px) and pixel depth."""

    width_px: PosInt
    height_px: PosInt
    bit_depth: Literal[8, 10, 12, 16] = Field(8, description="8: 8-bit files; 10/12/16: 16-bit files")
    serial: str | None = Field(None, description="recorded in the calibration file when given")


class ProjectorSpec(Strict):
    """The projector that showed the patterns (px)."""

    width_px: PosInt
    height_px: PosInt
    serial: str | None = None


class CodeSpec(Strict):
    """Which pattern set was projected. ``graycode``: OpenCV's GrayCodePattern (one Gray bit per projector
    pixel); ``gcls`` / ``gcps``: the cell's own sets (:mod:`cell.sensing.patterns`) with these parameters."""

    kind: Literal["gcls", "gcps", "graycode"] = Field(description="graycode: OpenCV GrayCodePattern")
    direction: Literal["columns", "rows", "both"] = Field("both", description="coded projector axes")
    stripe_px: PosInt | None = Field(None, description="gcls/gcps: Gray stripe width, projector px")
    n_shifts: PosInt = Field(6, description="gcls: line shifts")
    n_phase: Annotated[int, Field(ge=3)] = Field(4, description="gcps: phase steps")
    n_gray: PosInt | None = Field(None, description="gcls/gcps: Gray patterns (default: cover the axis)")
    edge_px: Annotated[float, Field(ge=1)] = Field(
        1.0, description="gcls: line-shift edge width, projector px (1: sharp; the measuring code ramps them)"
    )

    @model_validator(mode="after")
    def _stripe_needed(self) -> CodeSpec:
        if self.kind != "graycode" and self.stripe_px is None:
            raise ValueError(f"code '{self.kind}' needs stripe_px (the Gray stripe width in projector px)")
        return self

    def patterns(self, projector: ProjectorSpec) -> PatternSet:
        w, h = projector.width_px, projector.height_px
        if self.kind == "graycode":
            return graycode_patterns(w, h, self.direction)
        assert self.stripe_px is not None  # _stripe_needed
        if self.kind == "gcls":
            return gcls_patterns(
                w, h, self.stripe_px, self.n_shifts, self.direction, self.n_gray, self.edge_px
            )
        return gcps_patterns(w, h, self.stripe_px, self.n_phase, self.direction, self.n_gray)


class BoardSpec(Strict):
    """The calibration board. ``squares``: squares across and down (a chessboard's inner corners are one
    fewer each way). ChArUco boards also need the marker size and the ArUco dictionary's OpenCV name."""

    kind: Literal["chessboard", "charuco"]
    squares: tuple[PosInt, PosInt] = Field(description="squares across, down (not inner corners)")
    square_mm: PositiveFloat
    marker_mm: PositiveFloat | None = Field(None, description="charuco: ArUco marker side")
    dictionary: str = Field("DICT_5X5_100", description="charuco: OpenCV ArUco dictionary name")
    image: str = Field("white", description="frame in which the board is found")

    @model_validator(mode="after")
    def _charuco_fields(self) -> BoardSpec:
        if self.kind == "charuco":
            if self.marker_mm is None:
                raise ValueError("a ChArUco board needs marker_mm")
            if not hasattr(cv2.aruco, self.dictionary):
                raise ValueError(f"unknown ArUco dictionary '{self.dictionary}' (e.g. DICT_5X5_100)")
        elif min(self.squares) < 3:
            raise ValueError("a chessboard needs at least 3 squares each way")
        return self


class PoseSpec(Strict):
    """One pose: a folder of images. ``roi_px``: where the images' top-left pixel lies on the sensor;
    ``height_mm``: for the per-pixel sensor calibration, the board's height above the reference plane."""

    dir: str = Field(description="pose folder, relative to the capture folder")
    roi_px: tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0)]] = Field(
        (0, 0), description="sensor pixel (x, y) of the images' top-left pixel"
    )
    height_mm: float | None = Field(
        None, description="sensor routine: board height above the reference plane"
    )


class CaptureManifest(Strict):
    """``capture.yaml``: what a capture folder holds (docs/capture-folders.md)."""

    version: Literal[1] = 1
    camera: CameraSpec
    projector: ProjectorSpec
    code: CodeSpec
    order: Literal["cell", "opencv"] | list[str] = Field(
        "cell",
        description="image order in each pose folder: 'cell' (white, black, then each pattern and its "
        "inverse), 'opencv' (GrayCodePattern.generate() order, then white, then black) or frame names",
    )
    images: str = Field(
        "*.png", description="glob of the images in a pose folder; sorted by name, numbers by value"
    )
    board: BoardSpec | None = None
    poses: list[PoseSpec] | None = Field(None, description="default: every sub-folder, sorted by name")


class ChessboardTarget:
    """A plain chessboard's inner-corner grid (board frame, z = 0, mm), row by row as OpenCV's
    findChessboardCorners orders them. It offers the one method of cv2.aruco.CharucoBoard that
    :mod:`cell.calibration.intrinsics` and :mod:`cell.calibration.projector` use, so both boards share
    them."""

    def __init__(self, inner: tuple[int, int], square_mm: float):
        self.inner = inner
        x, y = np.meshgrid(np.arange(inner[0]) * square_mm, np.arange(inner[1]) * square_mm)
        self._pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]).astype(np.float32)

    def getChessboardCorners(self) -> NDArray[np.float32]:
        """The corners in the board frame; named as cv2.aruco.CharucoBoard names it."""
        return self._pts


Board = cv2.aruco.CharucoBoard | ChessboardTarget


@dataclass
class CapturePose:
    """One pose of a capture folder: its image files in pattern order."""

    name: str
    files: list[Path]
    roi_px: tuple[int, int]
    height_mm: float | None


@dataclass
class CaptureFolder:
    """A validated capture folder: manifest, the pattern set it names and its poses."""

    root: Path
    manifest: CaptureManifest
    patterns: PatternSet
    poses: list[CapturePose]

    @property
    def camera_size(self) -> tuple[int, int]:
        return self.manifest.camera.width_px, self.manifest.camera.height_px

    @property
    def projector_size(self) -> tuple[int, int]:
        return self.manifest.projector.width_px, self.manifest.projector.height_px

    def _read(self, pose: CapturePose, f: Path) -> NDArray:
        """One image of ``pose``, checked against the camera's pixel depth and the sensor size."""
        want = np.uint8 if self.manifest.camera.bit_depth == 8 else np.uint16
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ConfigError("cannot read this image (corrupt or not an image)", path=str(f))
        if img.ndim == 3:  # colour files of a grey camera: convert, as the capturing tools do
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        if img.dtype != want:
            raise ConfigError(
                f"{img.dtype} image, a {self.manifest.camera.bit_depth}-bit camera gives "
                f"{np.dtype(want).name}; check camera.bit_depth in {MANIFEST}",
                path=str(f),
            )
        (x0, y0), (W, H) = pose.roi_px, self.camera_size
        if x0 + img.shape[1] > W or y0 + img.shape[0] > H:
            raise ConfigError(
                f"{img.shape[1]}x{img.shape[0]} image at roi_px {pose.roi_px} does not fit the "
                f"{W}x{H} camera of {MANIFEST}",
                path=str(f),
            )
        return img

    def stack(self, pose: CapturePose) -> NDArray:
        """The pose's images as one checked (N, h, w) stack in pattern order (h, w: the pose's ROI)."""
        frames = [self._read(pose, f) for f in pose.files]
        size = frames[0].shape
        for f, img in zip(pose.files, frames, strict=True):
            if img.shape != size:
                raise ConfigError(
                    f"{img.shape[1]}x{img.shape[0]} image, the pose's first image {pose.files[0].name} is "
                    f"{size[1]}x{size[0]}: every image of a pose must have the same size",
                    path=str(f),
                )
        try:
            return check_stack(
                frames, self.patterns, (size[1], size[0]), self.manifest.camera.bit_depth, source=""
            )
        except StackError as exc:  # name the file of the offending frame (source "": no prefix to repeat)
            names = self.patterns.names
            f = pose.files[names.index(exc.field)] if exc.field in names else self.root / pose.name
            raise StackError(str(exc), path=str(f), field=exc.field) from exc

    def decode(self, pose: CapturePose, stack: NDArray | None = None) -> Decoded:
        """Decode a pose; the maps are returned on the full sensor (NaN and DARK outside the pose's ROI)."""
        s = self.stack(pose) if stack is None else stack
        return _on_sensor(
            decode(s, self.patterns, self.manifest.camera.bit_depth), pose.roi_px, self.camera_size
        )

    def _board_spec(self) -> BoardSpec:
        b = self.manifest.board
        if b is None:
            raise ConfigError(
                f"no board: add a 'board:' section to {MANIFEST}", path=str(self.root / MANIFEST)
            )
        return b

    def board(self) -> Board:
        """The manifest's board as the object the calibration functions take."""
        b = self._board_spec()
        if b.kind == "chessboard":
            return ChessboardTarget((b.squares[0] - 1, b.squares[1] - 1), b.square_mm)
        assert b.marker_mm is not None  # BoardSpec._charuco_fields
        return cv2.aruco.CharucoBoard(
            b.squares,
            b.square_mm,
            b.marker_mm,
            cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, b.dictionary)),
        )

    def find_board(self, pose: CapturePose, board: Board) -> CharucoView:
        """Board corners in the pose's board image (only that file is read), in full-sensor pixels;
        CalibrationError naming the pose and file when the board is not found."""
        f = pose.files[self.patterns.index(self._board_spec().image)]
        img = self._read(pose, f)
        view = (
            _find_chessboard(img, board)
            if isinstance(board, ChessboardTarget)
            else detect_charuco(img, board)
        )
        if view is None:
            b = self._board_spec()
            raise CalibrationError(
                f"pose '{pose.name}': the {b.kind} board ({b.squares[0]}x{b.squares[1]} squares) was not "
                f"found in {f}; check the board in {MANIFEST}, or remove the pose"
            )
        return CharucoView(view.corners_px + np.asarray(pose.roi_px, np.float64), view.ids)

    def iter_poses(self) -> Iterator[tuple[CapturePose, NDArray]]:
        """Each pose with its checked stack (one pose's images in memory at a time)."""
        for pose in self.poses:
            yield pose, self.stack(pose)


def _find_chessboard(image: NDArray, board: ChessboardTarget) -> CharucoView | None:
    """All inner corners of a plain chessboard (OpenCV's sector-based detector, sub-pixel), or None."""
    img = (
        image
        if image.dtype == np.uint8
        else cv2.convertScaleAbs(image, alpha=255.0 / max(float(image.max()), 1.0))
    )
    ok, corners = cv2.findChessboardCornersSB(
        img, board.inner, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    )
    if not ok or corners is None or len(corners) < MIN_CORNERS:
        return None
    n = board.inner[0] * board.inner[1]
    return CharucoView(corners.reshape(-1, 2).astype(np.float64), np.arange(n, dtype=np.int32))


def _on_sensor(dec: Decoded, roi_px: tuple[int, int], size: tuple[int, int]) -> Decoded:
    """``dec`` of an ROI placed on the full sensor of ``size`` (w, h)."""
    x0, y0 = roi_px
    h, w = dec.contrast.shape
    if (x0, y0) == (0, 0) and (w, h) == size:
        return dec
    W, H = size

    def pad(a: NDArray, fill: float) -> NDArray:
        out = np.full((H, W), fill, a.dtype)
        out[y0 : y0 + h, x0 : x0 + w] = a
        return out

    axes = {
        k: AxisDecode(
            a.axis, pad(a.u, np.nan), pad(a.reasons, int(Reason.DARK)), pad(a.sharpness, 0), a.n_edges
        )
        for k, a in dec.axes.items()
    }
    return Decoded(axes, pad(dec.contrast, 0), pad(dec.modulation_dn, 0), dict(dec.extra))


def _natural(path: Path) -> list[int | str]:
    """Sort key: the file name with its numbers compared by value (img_2 before img_10)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def code_spec(patterns: PatternSet) -> dict[str, object]:
    """The manifest's ``code:`` section that names ``patterns`` (a set of :mod:`cell.sensing.patterns` or
    :mod:`cell.sensing.graycode`), so that a stack stored with it is read back in its code
    (:func:`cell.view_files.save_raw_stack`)."""
    axes = [c.axis for c in patterns.codes]
    direction = "both" if len(axes) == 2 else axes[0]
    if patterns.codec == "graycode":
        return {"kind": "graycode", "direction": direction}
    c = patterns.codes[0]
    spec: dict[str, object] = {"kind": patterns.codec, "direction": direction, "stripe_px": c.stripe_px}
    spec |= {"n_shifts": c.n_shifts} if patterns.codec == "gcls" else {"n_phase": c.n_phase}
    if len({a.n_gray for a in patterns.codes}) == 1:
        spec["n_gray"] = c.n_gray
    if patterns.codec == "gcls" and patterns.edge_px != 1.0:
        spec["edge_px"] = patterns.edge_px
    return spec


def load_capture_folder(path: str | Path) -> CaptureFolder:
    """Read and check a capture folder's manifest and file lists (counts); images are read per pose later.

    ConfigError naming the manifest field, or the pose folder and the first missing or extra image."""
    root = Path(path)
    if not root.is_dir():
        raise ConfigError("capture folder not found", path=str(root))
    mpath = root / MANIFEST
    m = validate(CaptureManifest, read_yaml(mpath), mpath)
    try:
        ps = m.code.patterns(m.projector)
    except ConfigError as exc:
        raise ConfigError(str(exc), path=str(mpath), field="code") from exc
    if m.order == "cell":
        order = list(ps.names)
    elif m.order == "opencv":
        if m.code.kind != "graycode":
            raise ConfigError(
                "order 'opencv' is the GrayCodePattern order; use it with code kind 'graycode'",
                path=str(mpath),
                field="order",
            )
        order = opencv_order(ps)
    else:
        order = list(m.order)
        if sorted(order) != sorted(ps.names):
            missing = sorted(set(ps.names) - set(order))
            extra = sorted(set(order) - set(ps.names))
            raise ConfigError(
                f"the order must list each of the code's {len(ps.names)} frames once; missing {missing}, "
                f"unknown {extra}",
                path=str(mpath),
                field="order",
            )
    if m.board is not None and m.board.image not in ps.names:
        raise ConfigError(f"no frame '{m.board.image}' in the code", path=str(mpath), field="board.image")
    specs = m.poses
    if specs is None:
        specs = [PoseSpec(dir=p.name) for p in sorted(root.iterdir()) if p.is_dir()]
    if not specs:
        raise ConfigError("no pose folders", path=str(root))
    poses = []
    for spec in specs:
        pdir = root / spec.dir
        if not pdir.is_dir():
            raise ConfigError(f"pose folder '{spec.dir}' not found", path=str(pdir), field="poses")
        files = sorted(pdir.glob(m.images), key=_natural)
        if len(files) != len(order):
            which = (
                f"the first missing is frame '{order[len(files)]}' (index {len(files)})"
                if len(files) < len(order)
                else f"extra: {', '.join(f.name for f in files[len(order) :][:3])}"
            )
            raise ConfigError(
                f"{len(files)} images match '{m.images}', the {m.code.kind} code ({m.code.direction}) "
                f"needs {len(order)}; {which}",
                path=str(pdir),
            )
        by_name = dict(zip(order, files, strict=True))
        poses.append(CapturePose(spec.dir, [by_name[n] for n in ps.names], spec.roi_px, spec.height_mm))
    return CaptureFolder(root, m, ps, poses)
