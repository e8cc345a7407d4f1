"""Generate the demo parts of the cell: a sheet-metal B-pillar (nominal, dented, undented) and a slot gauge.

Run ``.venv/bin/python recipes/parts/make_parts.py [--out DIR]`` (default: this folder). The output is
deterministic: no random numbers, fixed sampling. Units are millimetres; every part rests on the table plane
z = 0 and is centred on the world origin in x/y, so part coordinates are world coordinates (T_W_P = identity).

Pillar: a hat-section profile (flange, filleted 70 deg wall, top face, wall, flange) of 2 mm sheet, offset
+-1 mm from its mid-surface, swept along a gently curved rising spine ~450 mm long while the hat narrows from
120 to 80 mm, with a round raised emboss on the top face. Vertices live on a (station x profile point x skin)
grid, so faces come from index arithmetic and all variants share one topology.

Gauge: the dissertation's precision gauge (Fig. 5.4, slots 32, 24, 14 and 6 um deep). Chapter 5 gives no block
or slot size, so the block is 150 x 100 x 30 mm with four 10 mm wide slots across the top face (along y).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent


# ------------------------------------------------------------------------------------------------ pillar
@dataclass(frozen=True)
class PillarSpec:
    """Dimensions of the demo B-pillar (mm, deg). Widths and heights refer to the sheet's mid-surface."""

    length_mm: float = 450.0  # spine chord along x
    bow_mm: float = 25.0  # plan-view sag of the spine (y) at mid-length
    rise_mm: float = 20.0  # the spine climbs this much (z) from end to end, quadratically
    width_start_mm: float = 120.0  # hat width between the wall feet at the wide (s = 0) end
    width_end_mm: float = 80.0  # ... and at the narrow end
    height_mm: float = 30.0  # flange to top face
    wall_angle_deg: float = 70.0  # side wall against the flange plane
    flange_mm: float = 18.0  # flange run beyond the wall foot
    fillet_mm: float = 5.0  # bend radius of the mid-surface at the four bends
    thickness_mm: float = 2.0
    stations: int = 91  # samples along the spine
    # profile intervals: flange, bend, wall, bend, top, bend, wall, bend, flange
    profile_intervals: tuple[int, ...] = (3, 4, 4, 4, 24, 4, 4, 4, 3)
    emboss_at: float = 0.22  # emboss centre: fraction of spine arc length (lateral offset 0)
    emboss_height_mm: float = 6.0
    emboss_flat_radius_mm: float = 12.0
    emboss_ramp_mm: float = 10.0  # cosine ramp width around the flat top


@dataclass(frozen=True)
class DentSpec:
    """The known dent of the 'actual' pillar: a radial cosine pushed into the material on the top face."""

    at: float = 0.68  # fraction of spine arc length, snapped to the nearest top-face vertex
    lateral_mm: float = 12.0  # offset across the top face (+ = towards +u)
    depth_mm: float = 0.6
    radius_mm: float = 15.0


OK_VARIATION_MM = 0.05  # 'actual_ok': smooth springback bow along the spine, far inside +-0.3 mm tolerance


def _filleted_profile(
    corners: np.ndarray, radius: float, intervals: tuple[int, ...]
) -> tuple[np.ndarray, ...]:
    """Sample a polyline, inner corners rounded by ``radius``: points and unit normals (left of travel).

    ``intervals`` alternates straight / arc counts, starting and ending with a straight.
    """
    pts, tans = [], []
    start = corners[0]
    for i in range(1, len(corners) - 1):
        d_in = corners[i] - corners[i - 1]
        d_out = corners[i + 1] - corners[i]
        d_in, d_out = d_in / np.linalg.norm(d_in), d_out / np.linalg.norm(d_out)
        turn = np.arctan2(d_in[0] * d_out[1] - d_in[1] * d_out[0], d_in @ d_out)  # signed, + = left
        tangent_len = radius * np.tan(abs(turn) / 2)
        a, b = corners[i] - d_in * tangent_len, corners[i] + d_out * tangent_len
        # straight start -> a
        t = np.arange(intervals[2 * (i - 1)])[:, None] / intervals[2 * (i - 1)]
        pts.append(start + t * (a - start))
        tans.append(np.repeat(d_in[None], len(t), axis=0))
        # arc a -> b around the centre on the inside of the turn
        left = np.array([-d_in[1], d_in[0]])
        centre = a + np.sign(turn) * radius * left
        alpha0 = np.arctan2(*(a - centre)[::-1])
        ang = alpha0 + turn * np.arange(intervals[2 * i - 1]) / intervals[2 * i - 1]
        pts.append(centre + radius * np.stack([np.cos(ang), np.sin(ang)], axis=1))
        tans.append(np.sign(turn) * np.stack([-np.sin(ang), np.cos(ang)], axis=1))
        start = b
    end, d_last = corners[-1], (corners[-1] - corners[-2]) / np.linalg.norm(corners[-1] - corners[-2])
    t = np.arange(intervals[-1] + 1)[:, None] / intervals[-1]
    pts.append(start + t * (end - start))
    tans.append(np.repeat(d_last[None], len(t), axis=0))
    p, tan = np.concatenate(pts), np.concatenate(tans)
    return p, np.stack([-tan[:, 1], tan[:, 0]], axis=1)


def _hat_corners(spec: PillarSpec, width: float) -> np.ndarray:
    """Mid-surface polyline of the hat in profile coordinates (u lateral, v up); flange mid-plane v = t/2."""
    run = spec.height_mm / np.tan(np.deg2rad(spec.wall_angle_deg))
    v0, v1, half = spec.thickness_mm / 2, spec.thickness_mm / 2 + spec.height_mm, width / 2
    return np.array(
        [
            [-half - spec.flange_mm, v0],
            [-half, v0],
            [-half + run, v1],
            [half - run, v1],
            [half, v0],
            [half + spec.flange_mm, v0],
        ]
    )


def _top_face_slice(spec: PillarSpec) -> slice:
    """Profile indices on the flat top face (both ends included)."""
    first = sum(spec.profile_intervals[:4])
    return slice(first, first + spec.profile_intervals[4] + 1)


def _spine(spec: PillarSpec, s: np.ndarray) -> tuple[np.ndarray, ...]:
    """Spine points C(s) and the sweep frame: lateral B (horizontal) and up U, each (M, 3)."""
    c = np.stack([spec.length_mm * (s - 0.5), spec.bow_mm * np.sin(np.pi * s), spec.rise_mm * s**2], axis=1)
    dc = np.stack(
        [np.full_like(s, spec.length_mm), spec.bow_mm * np.pi * np.cos(np.pi * s), 2 * spec.rise_mm * s],
        axis=1,
    )
    tangent = dc / np.linalg.norm(dc, axis=1, keepdims=True)
    lateral = np.cross([0.0, 0.0, 1.0], tangent)
    lateral /= np.linalg.norm(lateral, axis=1, keepdims=True)
    return c, lateral, np.cross(tangent, lateral)


def _cosine_cap(r: np.ndarray, flat: float, ramp: float) -> np.ndarray:
    """1 inside ``flat``, a half-cosine down to 0 over ``ramp``, 0 beyond (C1-smooth bump shape)."""
    x = np.clip((r - flat) / ramp, 0.0, 1.0)
    return 0.5 * (1 + np.cos(np.pi * x))


@dataclass
class PillarGrid:
    """The pillar's vertices as a grid plus what the variants need: (M, N, 2, 3) arrays, skin 0 = outer."""

    vertices: np.ndarray
    normals: np.ndarray  # outward mid-surface normal per (station, profile point), (M, N, 3)
    arclength: np.ndarray  # spine arc length per station, (M,)
    top: slice  # profile indices of the top face
    faces: np.ndarray


def build_pillar(spec: PillarSpec = PillarSpec()) -> PillarGrid:
    """Nominal pillar grid, already placed on the table and centred in x/y."""
    m = spec.stations
    s = np.linspace(0.0, 1.0, m)
    centre, lateral, up = _spine(spec, s)
    seg = np.linalg.norm(np.diff(centre, axis=0), axis=1)
    arclength = np.concatenate([[0.0], np.cumsum(seg)])
    widths = spec.width_start_mm + (spec.width_end_mm - spec.width_start_mm) * s
    profiles = [
        _filleted_profile(_hat_corners(spec, w), spec.fillet_mm, spec.profile_intervals) for w in widths
    ]
    mid = np.stack([p for p, _ in profiles])  # (M, N, 2)
    nrm2 = np.stack([n for _, n in profiles])  # (M, N, 2)

    top = _top_face_slice(spec)
    sigma_e = spec.emboss_at * arclength[-1]
    r = np.hypot(arclength[:, None] - sigma_e, mid[:, top, 0])
    bump = spec.emboss_height_mm * _cosine_cap(r, spec.emboss_flat_radius_mm, spec.emboss_ramp_mm)
    mid[:, top, 1] += bump  # a stamped emboss lifts the whole sheet, both skins

    half_t = spec.thickness_mm / 2
    skins = np.stack([mid + half_t * nrm2, mid - half_t * nrm2], axis=2)  # (M, N, 2 skins, 2)
    vertices = (
        centre[:, None, None, :]
        + skins[..., :1] * lateral[:, None, None, :]
        + skins[..., 1:] * up[:, None, None, :]
    )
    normals = nrm2[..., :1] * lateral[:, None, :] + nrm2[..., 1:] * up[:, None, :]
    # (emboss slopes tilt the true normal; variants use these normals only on the flat top and for the bow)

    lo, hi = vertices.reshape(-1, 3).min(axis=0), vertices.reshape(-1, 3).max(axis=0)
    vertices = vertices - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    return PillarGrid(vertices, normals, arclength, top, _pillar_faces(m, mid.shape[1]))


def _pillar_faces(m: int, n: int) -> np.ndarray:
    """Triangles of the closed swept shell for a grid flattened as index = (station * N + point) * 2 + skin.

    The cross-section loop runs along the outer skin, across the flange tip, back along the inner skin and
    across the other tip; consecutive stations join loop edges with two triangles; both end caps are strips of
    quads between the outer and inner skin.
    """
    idx = np.arange(m * n * 2).reshape(m, n, 2)
    loop = np.concatenate([idx[:, :, 0], idx[:, ::-1, 1]], axis=1)  # (M, 2N) around the cross-section
    a, b = loop[:-1], np.roll(loop, -1, axis=1)[:-1]
    c, d = np.roll(loop, -1, axis=1)[1:], loop[1:]
    tube = np.concatenate([np.stack([a, c, b], -1), np.stack([a, d, c], -1)], axis=1).reshape(-1, 3)
    caps = []
    for k, flip in ((0, False), (m - 1, True)):
        o0, o1, i0, i1 = idx[k, :-1, 0], idx[k, 1:, 0], idx[k, :-1, 1], idx[k, 1:, 1]
        tri = np.concatenate([np.stack([o0, o1, i1], -1), np.stack([o0, i1, i0], -1)])
        caps.append(tri[:, ::-1] if flip else tri)
    return np.concatenate([tube, *caps])


def pillar_mesh(grid: PillarGrid, vertices: np.ndarray | None = None) -> trimesh.Trimesh:
    """A Trimesh of the grid (optionally with displaced vertices of the same shape)."""
    v = grid.vertices if vertices is None else vertices
    return trimesh.Trimesh(v.reshape(-1, 3), grid.faces, process=False)


def dent_pillar(grid: PillarGrid, dent: DentSpec = DentSpec()) -> tuple[np.ndarray, dict]:
    """Dented vertices and the dent's truth (centre on the nominal outer surface, depth, radius, direction).

    The centre is snapped to an outer top-face vertex so the deepest point of the piecewise-linear dent is the
    stated depth. Both skins move along -normal (sheet metal dents as a whole).
    """
    top = grid.top
    k = int(np.argmin(np.abs(grid.arclength - dent.at * grid.arclength[-1])))
    outer_top = grid.vertices[k, top, 0]
    # lateral coordinate of the top-face points relative to the face centre line
    centre_line = outer_top.mean(axis=0)
    side = outer_top[-1] - outer_top[0]
    side /= np.linalg.norm(side)
    j = top.start + int(np.argmin(np.abs((outer_top - centre_line) @ side - dent.lateral_mm)))
    centre = grid.vertices[k, j, 0]
    direction = -grid.normals[k, j]
    r = np.linalg.norm(grid.vertices[:, :, 0] - centre, axis=-1)  # measured on the outer skin
    push = dent.depth_mm * _cosine_cap(r, 0.0, dent.radius_mm)  # (M, N)
    if np.any(push[:, : top.start] > 0) or np.any(push[:, top.stop :] > 0):
        raise ValueError("dent reaches beyond the top face; move it or make it smaller")
    moved = grid.vertices - (push[..., None] * grid.normals)[:, :, None, :]
    truth = {
        "part": "pillar_actual.stl",
        "nominal": "pillar_nominal.stl",
        "kind": "dent",
        "centre_mm": centre.tolist(),
        "depth_mm": dent.depth_mm,
        "radius_mm": dent.radius_mm,
        "profile": "radial cosine: depth * 0.5 * (1 + cos(pi * r / radius)) for r < radius",
        "direction": direction.tolist(),
        "direction_meaning": "unit vector of the displacement: into the material (minus the outward normal)",
        "signed_deviation_mm": -dent.depth_mm,
        "max_other_deviation_mm": 0.0,
    }
    return moved, truth


def bow_pillar(grid: PillarGrid, amplitude_mm: float = OK_VARIATION_MM) -> tuple[np.ndarray, dict]:
    """Undented 'actual_ok' vertices: a smooth half-sine springback bow along the outward normal."""
    bow = amplitude_mm * np.sin(np.pi * grid.arclength / grid.arclength[-1])  # (M,)
    moved = grid.vertices + (bow[:, None, None] * grid.normals)[:, :, None, :]
    truth = {
        "part": "pillar_actual_ok.stl",
        "nominal": "pillar_nominal.stl",
        "kind": "within tolerance",
        "profile": "amplitude * sin(pi * spine_arclength / spine_length) along the outward normal",
        "max_deviation_mm": amplitude_mm,
    }
    return moved, truth


# ------------------------------------------------------------------------------------------------ gauge
@dataclass(frozen=True)
class GaugeSpec:
    """The slot gauge (mm). Slots run along y across the whole top face, left (-x) to right (+x)."""

    size_mm: tuple[float, float, float] = (150.0, 100.0, 30.0)
    slot_width_mm: float = 10.0
    slot_centres_x_mm: tuple[float, ...] = (-45.0, -15.0, 15.0, 45.0)
    slot_depths_um: tuple[float, ...] = (32.0, 24.0, 14.0, 6.0)


def build_gauge(spec: GaugeSpec = GaugeSpec()) -> tuple[trimesh.Trimesh, dict]:
    """The gauge as a watertight prism: its x-z profile (top edge with four shallow notches) extruded along y.

    The profile is cut into columns between consecutive x breakpoints; each column is a convex polygon whose
    vertical sides may carry an extra vertex where the neighbour steps down, so each column is fanned from its
    own centroid (trimesh's polygon triangulation needs shapely and earcut, not installed here).
    """
    sx, sy, sz = spec.size_mm
    half_w = spec.slot_width_mm / 2
    xs = [-sx / 2]
    heights = []
    for xc, depth_um in zip(spec.slot_centres_x_mm, spec.slot_depths_um, strict=True):
        xs += [xc - half_w, xc + half_w]
        heights += [sz, sz - depth_um * 1e-3]
    xs.append(sx / 2)
    heights.append(sz)
    xs_a, h = np.array(xs), np.array(heights)

    profile_pts: list[tuple[float, float]] = []
    columns: list[list[int]] = []

    def vid(x: float, z: float) -> int:
        key = (x, z)
        if key not in profile_pts:
            profile_pts.append(key)
        return profile_pts.index(key)

    for j in range(len(h)):
        x0, x1 = xs_a[j], xs_a[j + 1]
        poly = [vid(x0, 0.0), vid(x1, 0.0)]  # counter-clockwise in (x, z)
        if j + 1 < len(h) and h[j + 1] < h[j]:
            poly.append(vid(x1, h[j + 1]))
        poly += [vid(x1, h[j]), vid(x0, h[j])]
        if j > 0 and h[j - 1] < h[j]:
            poly.append(vid(x0, h[j - 1]))
        columns.append(poly)
    p2 = np.array(profile_pts)
    n2 = len(p2)

    # boundary of the whole profile, counter-clockwise, from the columns' edges used once
    edges = [(a, b) for poly in columns for a, b in zip(poly, poly[1:] + poly[:1], strict=True)]
    boundary = [e for e in edges if (e[1], e[0]) not in edges]

    # vertices: profile at y = -sy/2 (front) and y = +sy/2 (back), then one centroid per column and side
    centroids = np.array([p2[poly].mean(axis=0) for poly in columns])
    xz = np.concatenate([p2, p2, centroids, centroids])
    y = np.concatenate(
        [
            np.full(n2, -sy / 2),
            np.full(n2, sy / 2),
            np.full(len(columns), -sy / 2),
            np.full(len(columns), sy / 2),
        ]
    )
    vertices = np.stack([xz[:, 0], y, xz[:, 1]], axis=1)

    faces = []
    for c, poly in enumerate(columns):
        cf, cb = 2 * n2 + c, 2 * n2 + len(columns) + c
        for a, b in zip(poly, poly[1:] + poly[:1], strict=True):
            faces.append((cf, a, b))  # front cap: CCW in (x, z) has normal x cross z = -y, outward
            faces.append((cb, b + n2, a + n2))  # back cap: reversed, normal +y
    for a, b in boundary:  # side walls along y
        faces += [(a, b + n2, b), (a, a + n2, b + n2)]
    mesh = trimesh.Trimesh(vertices, np.array(faces), process=False)

    slots = [
        {
            "index": i,
            "depth_um": d,
            "x_range_mm": [xc - half_w, xc + half_w],
            "y_range_mm": [-sy / 2, sy / 2],
            "floor_z_mm": sz - d * 1e-3,
        }
        for i, (xc, d) in enumerate(zip(spec.slot_centres_x_mm, spec.slot_depths_um, strict=True))
    ]
    truth = {
        "part": "gauge.stl",
        "size_mm": list(spec.size_mm),
        "top_z_mm": sz,
        "slot_width_mm": spec.slot_width_mm,
        "slots": slots,
        "source": "Shi, Fig. 5.4: slots 32+-1, 24+-1, 14+-2, 6+-2 um; block and slot sizes chosen here",
    }
    return mesh, truth


# ------------------------------------------------------------------------------------------------ output
def _check_solid(mesh: trimesh.Trimesh, name: str) -> None:
    """Fail loudly if a generated part is not a closed, consistently wound, outward solid on z = 0."""
    if not (mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0):
        raise RuntimeError(
            f"{name}: not a closed outward solid (watertight={mesh.is_watertight}, "
            f"winding={mesh.is_winding_consistent}, volume={mesh.volume:.1f})"
        )
    if abs(mesh.bounds[0, 2]) > 1e-9:
        raise RuntimeError(f"{name}: lowest point at z = {mesh.bounds[0, 2]} mm, not on the table")


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def make_parts(out: Path = HERE) -> list[Path]:
    """Write every demo part and truth file into ``out``; return the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    spec, dent = PillarSpec(), DentSpec()
    grid = build_pillar(spec)
    nominal = pillar_mesh(grid)
    dented, dent_truth = dent_pillar(grid, dent)
    bowed, ok_truth = bow_pillar(grid)
    gauge, gauge_truth = build_gauge()
    dent_truth["pillar_spec"] = asdict(spec)
    written = []
    for name, mesh in (
        ("pillar_nominal.stl", nominal),
        ("pillar_actual.stl", pillar_mesh(grid, dented)),
        ("pillar_actual_ok.stl", pillar_mesh(grid, bowed)),
        ("gauge.stl", gauge),
    ):
        _check_solid(mesh, name)
        mesh.export(out / name, file_type="stl")
        written.append(out / name)
    for name, data in (
        ("pillar_actual.truth.json", dent_truth),
        ("pillar_actual_ok.truth.json", ok_truth),
        ("gauge.truth.json", gauge_truth),
    ):
        _write_json(out / name, data)
        written.append(out / name)
    return written


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=HERE, help="output folder (default: recipes/parts)")
    args = parser.parse_args(argv)
    for path in make_parts(args.out):
        print(path)


if __name__ == "__main__":
    main()
