"""Where the artefacts go in the measuring volume, laid out as VDI/VDE 2634 Part 2 does for one view.

The measuring volume {V} is the box the sensor measures in from one pose: the camera's field at the stand-off
(width x height) times the depth of field, centred on the optical axis at the stand-off. Its axes are the
camera's (x right, y down in the image, z away from the camera), so a pose in {V} maps to the world through
the commanded camera pose: ``T_W_V = T_W_C @ Trans(0, 0, standoff)``.

Sphere (10 positions, PF and PS): the eight corners of the volume, inset so that the whole sphere stays in
the field and the depth, and two on the optical axis a third of the depth before and behind the middle.
Ball bar (7 positions): the four space diagonals, two face diagonals (the field's diagonals at mid-depth) and
one axis-parallel position (along the field's long side). Plane (6 positions): flat at the near, middle and
far depth, tilted about the field's long axis both ways, and along a field diagonal tilted. Every bar and
plane is centred on the volume's centre line; its ends stay inside the field at their depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cell.config import SensorConfig
from cell.errors import ConfigError
from cell.geometry import make_pose
from cell.verification.stage import ArtefactName

PLANE_TILT_DEG = 20.0  # tilt of the tilted plane positions about their long axis
SPHERE_INSET = 0.85  # the corner spheres' centres at this fraction of the room the field leaves them


@dataclass(frozen=True)
class Volume:
    """The one-view measuring volume (mm): field width (x) and height (y) at the stand-off, depth (z)."""

    width_mm: float
    height_mm: float
    depth_mm: float
    standoff_mm: float

    @classmethod
    def of(cls, sensor: SensorConfig) -> Volume:
        cam, s = sensor.camera, sensor.standoff_mm
        return cls(cam.width_px * s / cam.fx_px, cam.height_px * s / cam.fy_px, sensor.depth_of_field_mm, s)

    @property
    def diagonal_mm(self) -> float:
        """L0 of the guideline: the volume's space diagonal."""
        return float(np.linalg.norm([self.width_mm, self.height_mm, self.depth_mm]))

    def half_field_at(self, z_mm: float) -> tuple[float, float]:
        """Half width and half height of the field at depth ``z_mm`` in {V} (it grows with distance)."""
        scale = (self.standoff_mm + z_mm) / self.standoff_mm
        return self.width_mm / 2 * scale, self.height_mm / 2 * scale


@dataclass(frozen=True)
class Position:
    """One artefact placement: a name for people, the artefact and its pose in {V} (mm)."""

    label: str
    artefact: ArtefactName
    T_V_A: NDArray[np.float64]


def _frame_with_x(direction: NDArray[np.float64], centre: NDArray[np.float64]) -> NDArray[np.float64]:
    """A pose at ``centre`` whose x axis is ``direction`` and whose y axis lies in the {V} xy-plane."""
    x = np.asarray(direction, dtype=np.float64)
    x = x / np.linalg.norm(x)
    y = np.cross((0.0, 0.0, 1.0), x)
    y = y / np.linalg.norm(y) if np.linalg.norm(y) > 1e-9 else np.array([0.0, 1.0, 0.0])
    return make_pose(np.column_stack([x, y, np.cross(x, y)]), centre)


def sphere_positions(vol: Volume, diameter_mm: float) -> list[Position]:
    """The ten sphere positions: the volume's eight corners (near and far, each corner of the field at that
    depth, inset by :data:`SPHERE_INSET` of the room left once the sphere's radius is taken off) and two on
    the optical axis, a third of the depth before and behind the middle."""
    r = diameter_mm / 2
    d = vol.depth_mm / 2
    if r >= min(d, vol.width_mm / 2, vol.height_mm / 2):
        raise ConfigError(
            f"a {diameter_mm:g} mm sphere does not fit the {vol.width_mm:.0f} x {vol.height_mm:.0f} x "
            f"{vol.depth_mm:.0f} mm measuring volume; use a smaller sphere",
            field="sphere.diameter_mm",
        )
    out = []
    for depth, z in (("near", -SPHERE_INSET * (d - r)), ("far", SPHERE_INSET * (d - r))):
        hw, hh = vol.half_field_at(z - r)  # the sphere's near side sees the smaller field
        for name, sx, sy in (
            ("top left", -1, -1),
            ("top right", 1, -1),
            ("bottom right", 1, 1),
            ("bottom left", -1, 1),
        ):
            centre = (sx * SPHERE_INSET * (hw - r), sy * SPHERE_INSET * (hh - r), z)
            out.append(Position(f"sphere, {depth} {name}", "sphere", make_pose(np.eye(3), centre)))
    for name, z in (("centre, near third", -d / 3), ("centre, far third", d / 3)):
        out.append(Position(f"sphere, {name}", "sphere", make_pose(np.eye(3), (0.0, 0.0, z))))
    return out


def ball_bar_positions(vol: Volume, length_mm: float, sphere_diameter_mm: float) -> list[Position]:
    """The seven ball-bar positions, scaled so that both spheres stay inside the volume."""
    w, h, d = vol.width_mm / 2, vol.height_mm / 2, vol.depth_mm / 2
    dirs = {
        "space diagonal 1": (w, h, d),
        "space diagonal 2": (-w, h, d),
        "space diagonal 3": (w, -h, d),
        "space diagonal 4": (-w, -h, d),
        "face diagonal 1": (w, h, 0.0),
        "face diagonal 2": (-w, h, 0.0),
        "axis-parallel x": (w, 0.0, 0.0),
    }
    r = sphere_diameter_mm / 2
    out = []
    for label, v in dirs.items():
        u = np.asarray(v) / np.linalg.norm(v)
        end = u * length_mm / 2
        hw, hh = vol.half_field_at(-abs(end[2]))  # the near end sees the smallest field
        if abs(end[0]) + r > hw or abs(end[1]) + r > hh or abs(end[2]) + r > d:
            raise ConfigError(
                f"a {length_mm:g} mm ball bar does not fit the {vol.width_mm:.0f} x {vol.height_mm:.0f} x "
                f"{vol.depth_mm:.0f} mm measuring volume along its {label}; use a shorter bar",
                field="ball_bar.centre_distance_mm",
            )
        out.append(Position(f"ball bar, {label}", "ball_bar", _frame_with_x(u, np.zeros(3))))
    return out


def plane_positions(vol: Volume, length_mm: float) -> list[Position]:
    """The six plane positions: flat near / middle / far, tilted +- about its long axis, diagonal tilted."""
    d = vol.depth_mm / 2
    z_near, z_far = -0.6 * d, 0.6 * d  # the tilted positions' edges stay inside the depth too
    hw, _ = vol.half_field_at(z_near)
    if length_mm / 2 > hw:
        raise ConfigError(
            f"a {length_mm:g} mm plane is longer than the field ({2 * hw:.0f} mm at the near end)",
            field="plane.length_mm",
        )
    tilt = np.deg2rad(PLANE_TILT_DEG)

    def pose(rx: float, yaw: float, z: float) -> NDArray[np.float64]:
        # the artefact's face normal (+z of {A}) must face the camera (-z of {V})
        flip = np.diag([1.0, -1.0, -1.0])
        cz, sz, cx, sx = np.cos(yaw), np.sin(yaw), np.cos(rx), np.sin(rx)
        Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1.0]])
        Rx = np.array([[1.0, 0, 0], [0, cx, -sx], [0, sx, cx]])
        return make_pose(Rz @ Rx @ flip, (0.0, 0.0, z))

    diag = np.arctan2(vol.height_mm, vol.width_mm)
    return [
        Position("plane, flat near", "plane", pose(0.0, 0.0, z_near)),
        Position("plane, flat middle", "plane", pose(0.0, 0.0, 0.0)),
        Position("plane, flat far", "plane", pose(0.0, 0.0, z_far)),
        Position("plane, tilted +", "plane", pose(tilt, 0.0, 0.0)),
        Position("plane, tilted -", "plane", pose(-tilt, 0.0, 0.0)),
        Position("plane, diagonal tilted", "plane", pose(tilt, diag, 0.0)),
    ]
