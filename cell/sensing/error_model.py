"""One-pixel height error of the reference-plane triangulation (dissertation eq 2.5, Tables 2.1-2.3).

With L = res * m (eq 2.4), h(m) = res*m*S / (d + res*m). A one-pixel error in L changes h by
h(m) - h(m-1) = res*S*d / ((d + res*m)(d + res*(m-1))), which expands to eq 2.5:
    dh = | res*S / (d + (2m-1)*res + m*(m-1)*res^2/d) |.
Units: res in mm/px on the reference plane, S (stand-off) and d (baseline) in mm, m in camera pixels.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def one_pixel_error(
    res_mm: ArrayLike, S_mm: ArrayLike, d_mm: ArrayLike, m_px: ArrayLike
) -> NDArray[np.float64]:
    """Height error (mm) caused by a one-pixel error in L at pixel distance ``m_px`` (eq 2.5); broadcasts."""
    res = np.asarray(res_mm, dtype=np.float64)
    S = np.asarray(S_mm, dtype=np.float64)
    d = np.asarray(d_mm, dtype=np.float64)
    m = np.asarray(m_px, dtype=np.float64)
    return np.abs(res * S / (d + (2 * m - 1) * res + m * (m - 1) * res**2 / d))


# The three tables of the dissertation: (title, varied parameter name, its values, fixed parameters).
M_ROWS: tuple[int, ...] = (53, 64, 87)
TABLES: tuple[tuple[str, str, tuple[float, ...], dict[str, float]], ...] = (
    (
        "Table 2.1. One-Pix Error Analysis, res=0.151, S=393.7, unit: mm",
        "d",
        (114.7, 213.4, 315.6, 429.3),
        {"res": 0.151, "S": 393.7},
    ),
    (
        "Table 2.2. One-Pix Error Analysis, d=429.3, S=393.7, unit: mm",
        "res",
        (0.192, 0.174, 0.151, 0.078),
        {"d": 429.3, "S": 393.7},
    ),
    (
        "Table 2.3. One-Pix Error Analysis, d=429.3, res=0.078, unit: mm",
        "S",
        (451.6, 434.7, 420.5, 393.7),
        {"d": 429.3, "res": 0.078},
    ),
)


def error_table(
    varied: str, values: tuple[float, ...], fixed: dict[str, float], m_rows: tuple[int, ...] = M_ROWS
) -> NDArray[np.float64]:
    """(len(m_rows), len(values)) array of eq 2.5 with one parameter (``res``, ``S`` or ``d``) varied."""
    params = {k: np.asarray(v, dtype=np.float64) for k, v in fixed.items()}
    params[varied] = np.asarray(values, dtype=np.float64)[None, :]
    m = np.asarray(m_rows, dtype=np.float64)[:, None]
    return one_pixel_error(params["res"], params["S"], params["d"], m)


def format_tables() -> str:
    """Tables 2.1-2.3 as text in the dissertation's layout (tab-separated columns, 4 decimals)."""
    blocks = []
    for title, varied, values, fixed in TABLES:
        table = error_table(varied, values, fixed)
        head = "\t" + "\t".join(f"{varied} = {v:g}" if varied != "res" else f"res={v:g}" for v in values)
        rows = [f"m={m}pix\t" + "\t".join(f"{x:.4f}" for x in row) for m, row in zip(M_ROWS, table)]
        blocks.append("\n".join([title, "", head, *rows]))
    return "\n\n".join(blocks)


def normal_error_per_pixel(
    points_C: NDArray[np.floating],
    normals_C: NDArray[np.floating],
    projector_centre_C: ArrayLike,
    projector_y_C: ArrayLike,
    fx_px: float,
) -> NDArray[np.float64]:
    """How far (mm, along the surface normal) a point moves when its decoded correspondence moves by one
    camera pixel along the row: eq 2.5 generalised to any surface orientation, to first order.

    The projector coordinate is what the decode gets wrong: an edge found dx pixels off gives the pixel the
    code of the surface point one pixel-footprint away, dP = Z (r' - r (n.r')/(n.r)) dx (r = (x_n, y_n, 1)
    the pixel's ray, r' = (1/fx, 0, 0) its change per pixel, n the normal); the point then moves along its own
    ray until it meets that code's projector plane (normal m, through the projector centre and its y axis), by
    (m.dP)/(m.r) ray lengths, of which n.r shows along the normal:
        e = Z |(m.r')(n.r) - (m.r)(n.r')| / |m.r|.
    For a plane facing the camera this is eq 2.5 (within the one-pixel step's discreteness, res/d ~ 0.1 %); a
    tilted plane scales it by cos(theta_p)/cos(theta_p0) in the epipolar plane (theta_p: the projector's
    incidence on the surface, theta_p0: on a plane facing the camera at the same point). The camera's own
    incidence cancels: a pixel's footprint grows as 1/cos(theta_c), but the point moves along the ray, whose
    part along the normal shrinks as cos(theta_c). ``points_C``, ``normals_C`` (..., 3) in {C} (mm, unit
    normals); NaN where either is."""
    p = np.asarray(points_C, dtype=np.float64)
    n = np.asarray(normals_C, dtype=np.float64)
    B = np.asarray(projector_centre_C, dtype=np.float64)
    y = np.asarray(projector_y_C, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        Z = p[..., 2]
        r = p / Z[..., None]
        m = np.cross(p - B, y)
        m /= np.linalg.norm(m, axis=-1, keepdims=True)
        dr = np.array([1.0 / fx_px, 0.0, 0.0])
        mr, nr = np.einsum("...k,...k->...", m, r), np.einsum("...k,...k->...", n, r)
        mdr, ndr = m @ dr, n @ dr
        return np.abs(Z * (mdr * nr - mr * ndr) / mr)
