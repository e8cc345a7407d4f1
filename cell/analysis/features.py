"""Feature-based coarse alignment from curvature labels (dissertation 4.2, eqs 4.16-4.20).

1. Surface gradients: each point's k nearest neighbours are expressed in a local frame (u, v tangent, w along
   the normal from PCA) and the quadric w = f(u, v) = k0 + k1 u + k2 v + k3 u^2 + k4 u v + k5 v^2 (eq 4.18) is
   fitted by least squares; f_u = k1, f_v = k2, f_uu = 2 k3, f_uv = k4, f_vv = 2 k5 (eqs 4.19-4.20).
2. Gaussian curvature K (4.16) and mean curvature H (4.17) at the point. With w along the *outward* normal a
   convex bump has H < 0 (a sphere of radius R: K = 1/R^2, H = -1/R).
3. Labels by the signs of K and H (Besl & Jain's HK classes): flat, peak, pit, ridge, valley, saddle, then
   "neighbourhood voting": each point takes the most frequent label among its neighbours.
4. Matching: points of one non-flat label that touch form a feature patch (centroid, label, size). Triples of
   cloud patches are matched to nominal patches of the same labels whose pairwise distances agree; each
   hypothesis (Horn on the centroids) is scored by how many patches land on a same-label patch, and the
   winner is refined on all of them. The result is coarse (patch centroids, ~ the point spacing); refine it
   with :func:`cell.analysis.registration.icp_point_to_plane`.

The batched fits use numpy's stacked ``solve``/``eigh`` (no per-point Python loop); the patch matching is a
small combinatorial search over tens of patches, not points.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cell.analysis.registration import horn_quaternion
from cell.errors import ConfigError
from cell.geometry import Pose, transform_points


class Shape(IntEnum):
    """HK surface classes."""

    FLAT = 0
    PEAK = 1  # K > 0, H < 0: convex cap
    PIT = 2  # K > 0, H > 0: concave cup
    RIDGE = 3  # K ~ 0, H < 0: convex cylinder-like
    VALLEY = 4  # K ~ 0, H > 0: concave cylinder-like
    SADDLE = 5  # K < 0


@dataclass(frozen=True)
class Curvature:
    """Per point: Gaussian curvature ``K`` (1/mm^2), mean curvature ``H`` (1/mm), unit ``normals``."""

    K: NDArray[np.float64]
    H: NDArray[np.float64]
    normals: NDArray[np.float64]


def curvature(
    points_mm: ArrayLike,
    k: int = 24,
    normals: ArrayLike | None = None,
    viewpoint_mm: ArrayLike | None = None,
) -> Curvature:
    """K and H of every point from a local quadric fit (eqs 4.16-4.20).

    The normal sign (it sets the sign of H) follows ``normals`` when given (e.g. the nominal's face
    normals), else points towards ``viewpoint_mm`` (the sensor), else away from the cloud's centroid.
    """
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if len(p) < k:
        raise ConfigError(f"curvature needs at least k = {k} points, got {len(p)}")
    _, idx = cKDTree(p).query(p, k)
    d = p[idx] - p[:, None, :]  # (N, k, 3) neighbours relative to the point
    c = d - d.mean(1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", c, c))
    n = vec[:, :, 0]
    if normals is not None:
        ref = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    elif viewpoint_mm is not None:
        ref = np.asarray(viewpoint_mm, dtype=np.float64) - p
    else:
        ref = p - p.mean(0)
    n *= np.where(np.einsum("ij,ij->i", n, ref) < 0, -1.0, 1.0)[:, None]
    u = vec[:, :, 2]
    v = np.cross(n, u)
    uu, vv, ww = (np.einsum("nki,ni->nk", d, a) for a in (u, v, n))
    A = np.stack([np.ones_like(uu), uu, vv, uu * uu, uu * vv, vv * vv], -1)  # (N, k, 6)
    AtA = np.einsum("nki,nkj->nij", A, A) + 1e-12 * np.eye(6)
    coef = np.linalg.solve(AtA, np.einsum("nki,nk->ni", A, ww)[..., None])[..., 0]
    fu, fv, fuu, fuv, fvv = coef[:, 1], coef[:, 2], 2 * coef[:, 3], coef[:, 4], 2 * coef[:, 5]
    g = 1 + fu * fu + fv * fv
    K = (fuu * fvv - fuv * fuv) / g**2
    H = (fuu + fvv + fuu * fv * fv - 2 * fu * fv * fuv + fvv * fu * fu) / (2 * g**1.5)
    return Curvature(K=K, H=H, normals=n)


def hk_labels(
    curv: Curvature, points_mm: ArrayLike, eps_h: float = 0.02, k_vote: int = 12
) -> NDArray[np.int64]:
    """Labels (:class:`Shape`) from the signs of K and H, then majority voting over ``k_vote`` neighbours.

    ``eps_h`` (1/mm): |H| below it is flat (radius > 1/eps_h mm); |K| below ``eps_h^2`` counts as zero.
    """
    K, H = curv.K, curv.H
    eps_k = eps_h * eps_h
    lab = np.full(len(K), Shape.FLAT, np.int64)
    lab[(np.abs(K) <= eps_k) & (H < -eps_h)] = Shape.RIDGE
    lab[(np.abs(K) <= eps_k) & (H > eps_h)] = Shape.VALLEY
    lab[(K > eps_k) & (H < 0)] = Shape.PEAK
    lab[(K > eps_k) & (H > 0)] = Shape.PIT
    lab[K < -eps_k] = Shape.SADDLE
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    _, idx = cKDTree(p).query(p, min(k_vote, len(p)))
    votes = (lab[idx][..., None] == np.arange(len(Shape))).sum(1)  # (N, 6) label counts among neighbours
    return np.argmax(votes, 1)


@dataclass(frozen=True)
class Patches:
    """Feature patches: ``centre_mm`` (P, 3), ``label`` (P,), ``size`` (P,) points, largest first."""

    centre_mm: NDArray[np.float64]
    label: NDArray[np.int64]
    size: NDArray[np.int64]


def feature_patches(points_mm: NDArray, labels: NDArray, link_mm: float, min_points: int = 20) -> Patches:
    """Connected groups (points closer than ``link_mm``) of one non-flat label, at least ``min_points``."""
    centres, labs, sizes = [], [], []
    for lab in np.unique(labels):
        if lab == Shape.FLAT:
            continue
        sel = np.flatnonzero(labels == lab)
        pairs = cKDTree(points_mm[sel]).query_pairs(link_mm, output_type="ndarray")
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(sel), len(sel)))
        n, comp = connected_components(g, directed=False)
        size = np.bincount(comp, minlength=n)
        for c in np.flatnonzero(size >= min_points):
            centres.append(points_mm[sel[comp == c]].mean(0))
            labs.append(lab)
            sizes.append(size[c])
    if not centres:
        return Patches(np.empty((0, 3)), np.empty(0, np.int64), np.empty(0, np.int64))
    order = np.argsort(-np.asarray(sizes), kind="stable")
    return Patches(np.asarray(centres)[order], np.asarray(labs)[order], np.asarray(sizes)[order])


@dataclass(frozen=True)
class FeatureAlignment:
    """``T``: cloud frame into the part frame; ``n_matched`` patches agreeing; the patches of both sides."""

    T: Pose
    n_matched: int
    rms_mm: float
    cloud: Patches
    nominal: Patches


def feature_align(
    nominal_mesh: trimesh.Trimesh,
    cloud_mm: ArrayLike,
    viewpoint_mm: ArrayLike | None = None,
    n_samples: int = 20_000,
    k: int = 24,
    eps_h: float = 0.02,
    match_mm: float | None = None,
    max_patches: int = 12,
) -> FeatureAlignment:
    """Coarse ``T_P_cloud`` by matching curvature-label patches of the cloud to those of the nominal."""
    cloud = np.asarray(cloud_mm, dtype=np.float64).reshape(-1, 3)
    if len(cloud) > n_samples:
        cloud = cloud[np.random.default_rng(0).choice(len(cloud), n_samples, replace=False)]
    nom, fi = trimesh.sample.sample_surface_even(nominal_mesh, n_samples, seed=0)
    spacing = float(np.sqrt(nominal_mesh.area / len(nom)))
    link = 2.5 * spacing
    match_mm = 4 * spacing if match_mm is None else match_mm
    lab_n = hk_labels(curvature(nom, k, normals=nominal_mesh.face_normals[fi]), nom, eps_h)
    cc = curvature(cloud, k, viewpoint_mm=viewpoint_mm)
    lab_c = hk_labels(cc, cloud, eps_h)
    pn = feature_patches(nom, lab_n, link)
    pc = feature_patches(cloud, lab_c, link)
    pn = Patches(pn.centre_mm[: 3 * max_patches], pn.label[: 3 * max_patches], pn.size[: 3 * max_patches])
    pc = Patches(pc.centre_mm[:max_patches], pc.label[:max_patches], pc.size[:max_patches])
    if len(pc.label) < 3 or len(pn.label) < 3:
        raise ConfigError(
            f"feature alignment found {len(pc.label)} cloud and {len(pn.label)} nominal feature patches; "
            "it needs >= 3 on each side (a part with distinct curved features, or use datums)"
        )
    best = _match(pc, pn, match_mm)
    if best is None:
        raise ConfigError("feature alignment found no consistent match of feature patches; use datums")
    T, ci, ni = best
    res = transform_points(T, pc.centre_mm[ci]) - pn.centre_mm[ni]
    return FeatureAlignment(T, len(ci), float(np.sqrt(np.mean(np.sum(res**2, 1)))), pc, pn)


def _match(pc: Patches, pn: Patches, tol: float) -> tuple[Pose, NDArray, NDArray] | None:
    """Best-supported rigid map of cloud patch centroids onto same-label nominal ones (see module doc)."""
    dc = np.linalg.norm(pc.centre_mm[:, None] - pc.centre_mm[None], axis=2)
    dn = np.linalg.norm(pn.centre_mm[:, None] - pn.centre_mm[None], axis=2)
    same = pc.label[:, None] == pn.label[None]  # (C, N) label-compatible pairs
    best: tuple[int, float, Pose, NDArray, NDArray] | None = None
    for i, j, m in itertools.combinations(range(len(pc.label)), 3):
        if min(dc[i, j], dc[i, m], dc[j, m]) < 2 * tol:
            continue  # too close to fix a rotation
        for a in np.flatnonzero(same[i]):
            for b in np.flatnonzero(same[j] & (np.abs(dn[a] - dc[i, j]) < tol)):
                cands = same[m] & (np.abs(dn[a] - dc[i, m]) < tol) & (np.abs(dn[b] - dc[j, m]) < tol)
                for c in np.flatnonzero(cands):
                    if len({a, b, c}) < 3:
                        continue
                    T = horn_quaternion(pc.centre_mm[[i, j, m]], pn.centre_mm[[a, b, c]])
                    moved = transform_points(T, pc.centre_mm)
                    dist = np.linalg.norm(moved[:, None] - pn.centre_mm[None], axis=2)
                    dist[~same] = np.inf
                    ni = np.argmin(dist, 1)
                    ok = dist[np.arange(len(ni)), ni] < tol
                    score = (int(ok.sum()), -float(dist[np.arange(len(ni)), ni][ok].sum()))
                    if best is None or score > best[:2]:
                        best = (*score, T, np.flatnonzero(ok), ni[ok])
    if best is None:
        return None
    _, _, T, ci, ni = best
    if len(ci) >= 3:
        T = horn_quaternion(pc.centre_mm[ci], pn.centre_mm[ni])
    return T, ci, ni
