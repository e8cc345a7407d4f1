"""Error map of 1M points vs ~200k triangles, side by side with peer libraries; link clustering 2448x2048.

Run: .venv/bin/python bench/bench_errormap.py [n_points]   (peers from bench/requirements-peers.txt, optional)
"""

from __future__ import annotations

import sys
import time

import numpy as np
import trimesh

from cell.analysis.errormap import NominalMesh, signed_distance
from cell.analysis.linkfilter import link_cluster


def torus(nu: int = 448, nv: int = 224, R: float = 60.0, r: float = 20.0) -> trimesh.Trimesh:
    """A closed, wavy torus with 2 * nu * nv triangles (mm)."""
    u, v = np.meshgrid(
        np.linspace(0, 2 * np.pi, nu, endpoint=False),
        np.linspace(0, 2 * np.pi, nv, endpoint=False),
        indexing="ij",
    )
    rr = r + 0.5 * np.sin(5 * u) * np.cos(3 * v)
    xyz = np.stack(
        [(R + rr * np.cos(v)) * np.cos(u), (R + rr * np.cos(v)) * np.sin(u), rr * np.sin(v)], -1
    ).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, ((i + 1) % nu) * nv + j
    c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return trimesh.Trimesh(xyz, f, process=False)


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def main(n: int = 1_000_000) -> None:
    mesh = torus()
    rng = np.random.default_rng(0)
    p, fi = trimesh.sample.sample_surface(mesh, n, seed=1)
    p = p + mesh.face_normals[fi] * rng.normal(0, 0.5, (n, 1))
    t_prep, nm = timed(lambda: NominalMesh.from_trimesh(mesh))
    signed_distance(nm, p[:100])  # JIT warm-up (cached on disk after the first run)
    t_ours, em = timed(lambda: signed_distance(nm, p))
    ref = em.deviation_mm
    print(f"{len(mesh.faces)} triangles, {n} points; ours: prepare {t_prep:.2f} s, query {t_ours:.2f} s")
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    peers = []
    try:
        import igl

        peers.append(
            (
                "libigl signed_distance (AABB, pseudonormal)",
                lambda: igl.signed_distance(p, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)[0],
            )
        )
    except Exception as exc:  # noqa: BLE001 - a missing peer is reported, not fatal
        print("libigl unavailable:", exc)
    try:
        import point_cloud_utils as pcu

        peers.append(
            (
                "point-cloud-utils closest_points_on_mesh (unsigned)",
                lambda: pcu.closest_points_on_mesh(p, V, F)[0],
            )
        )
    except Exception as exc:  # noqa: BLE001
        print("point-cloud-utils unavailable:", exc)
    try:
        import open3d as o3d

        def o3d_run():
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh.as_open3d))
            return scene.compute_signed_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()

        peers.append(("open3d RaycastingScene (float32)", o3d_run))
    except Exception as exc:  # noqa: BLE001
        print("open3d unavailable:", exc)
    for name, fn in peers:
        t, d = timed(fn)
        d = np.asarray(d, dtype=np.float64).ravel()
        line = f"{name}: {t:.2f} s"
        if len(d) == n:
            off = np.abs(ref) > 1e-6
            if d.min() < 0:
                line += f", sign agreement {np.mean(np.sign(d[off]) == np.sign(ref[off])):.6f}"
            line += f", max |d| diff {np.max(np.abs(np.abs(d) - np.abs(ref))):.2e} mm"
        print(line)
    y, x = np.mgrid[0:2048, 0:2448] * 0.1
    z = (50 + 0.2 * x + 0.5 * np.sin(x / 3) + rng.normal(0, 0.01, x.shape)).astype(np.float32)
    z[rng.random(z.shape) < 0.01] = np.nan
    link_cluster(z[:64, :64])
    ts = [timed(lambda: link_cluster(z, 0.3, 200))[0] for _ in range(3)]
    print(f"link clustering 2448x2048: best of 3 {min(ts):.3f} s")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000)
