"""`cell compare` against CloudCompare's command-line C2M distance, whole process, side by side.

Run: .venv/bin/python bench/bench_compare.py [n_points] [rounds] [big_points] [--base=DIR]
     (CloudCompare: Debian package `cloudcompare`, installed by `make bench`; DIR: an older tree, e.g.
     `git archive f94ac49 | tar -x -C /tmp/base`, whose `cell compare` runs in the same rounds)

Inputs (generated, seeded): a 20,480-triangle sphere of radius 50 mm (STL) and N points sampled on it
with 0.02 mm of normal noise and a 0.5 mm deep dent (binary PLY, float64). Each round runs both tools once,
one after the other, as separate processes with their default outputs: `cell compare NOMINAL CLOUD --out DIR`
(report.json, report.html with pictures, cloud.ply with the deviation field) and
`CloudCompare -SILENT -O CLOUD -O MESH -C2M_DIST` (the cloud with its distance field in CloudCompare's BIN
format). The median and best wall time of each are printed with the machine's load average. Then both
tools' distances are compared point by point (CloudCompare exported as ASCII for that). Last, `cell compare`
of BIG points (default 5M) against the same mesh: wall time and peak resident memory (GNU time's maximum RSS).
First the compare path's kernels are compiled ahead of time if they are not yet (as `make venv` does).
"""

from __future__ import annotations

import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

REPO = Path(__file__).resolve().parent.parent
CELL = [sys.executable, "-m", "cell"]
NO_TABLE = ["--table-z", "none"]  # the sphere stands on no table: every point compared, as by CloudCompare
CC_ENV = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
VERDICT_CODES = (0, 4, 5)  # pass, fail (the dent is out of tolerance), incomplete: docs/exit-codes.md


def write_cloud(path: Path, points: np.ndarray) -> None:
    """Binary little-endian PLY of float64 vertices (both tools read it)."""
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
        "property double x\nproperty double y\nproperty double z\nend_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(np.ascontiguousarray(points, dtype="<f8").tobytes())


def make_inputs(folder: Path, n: int) -> tuple[Path, Path]:
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=50.0)
    nominal = folder / "nominal.stl"
    mesh.export(nominal)
    rng = np.random.default_rng(0)
    p, f = trimesh.sample.sample_surface(mesh, n, seed=1)
    offset = rng.normal(0.0, 0.02, n)
    dent = np.linalg.norm(p - (0.0, 0.0, 50.0), axis=1) < 8.0
    offset[dent] -= 0.5
    cloud = folder / f"cloud{n}.ply"
    write_cloud(cloud, p + mesh.face_normals[f] * offset[:, None])
    return nominal, cloud


def child_cpu() -> float:
    """CPU seconds (user + system) used so far by this process's finished children."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_cell(nominal: Path, cloud: Path, out: Path, tree: Path = REPO) -> float:
    t = time.perf_counter()
    proc = subprocess.run(
        [*CELL, "compare", str(nominal), str(cloud), "--out", str(out), *NO_TABLE],
        cwd=tree,
        env={**os.environ, "PYTHONPATH": str(tree)},
        capture_output=True,
    )
    if proc.returncode not in VERDICT_CODES:
        sys.exit(f"cell compare failed ({proc.returncode}): {proc.stderr.decode()[-1000:]}")
    return time.perf_counter() - t


def run_cloudcompare(nominal: Path, cloud: Path, export_ascii: bool = False) -> float:
    fmt = ["-C_EXPORT_FMT", "ASC", "-PREC", "9"] if export_ascii else []
    cmd = ["CloudCompare", "-SILENT", *fmt, "-O", str(cloud), "-O", str(nominal), "-C2M_DIST"]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, env=CC_ENV, capture_output=True)
    return time.perf_counter() - t


def read_cell_deviation(ply: Path) -> np.ndarray:
    """The ``deviation`` property of cell's cloud.ply, whatever the other vertex properties' types."""
    types = {"float": "f4", "double": "f8", "uchar": "u1", "char": "i1", "int": "i4", "uint": "u4"}
    data = ply.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    n = int(re.search(r"element vertex (\d+)", "\n".join(header)).group(1))
    props = [line.split()[1:] for line in header if line.startswith("property ")]
    rec = np.frombuffer(data[end:], dtype=[(name, "<" + types[t]) for t, name in props], count=n)
    return rec["deviation"].astype(np.float64)


def agreement(folder: Path, nominal: Path, cloud: Path, cell_out: Path) -> str:
    for old in folder.glob("*_C2M_DIST_*"):
        old.unlink()
    run_cloudcompare(nominal, cloud, export_ascii=True)
    (asc,) = folder.glob("*_C2M_DIST_*.asc")
    cc = np.loadtxt(asc, usecols=3)
    ours = read_cell_deviation(cell_out / "cloud.ply")
    if len(cc) != len(ours):
        return f"point counts differ: CloudCompare {len(cc)}, cell {len(ours)}"
    diff = np.abs(cc - ours)
    return (
        f"{len(cc)} points; |cell - CloudCompare| max {diff.max() * 1e6:.0f} nm, "
        f"median {np.median(diff) * 1e6:.1f} nm (cell's cloud.ply stores float32 deviations)"
    )


def big_run(folder: Path, nominal: Path, n: int) -> str:
    _, cloud = make_inputs(folder, n)
    proc = subprocess.run(
        [
            "/usr/bin/time",
            "-f",
            "%e %U %S %M",
            *CELL,
            "compare",
            str(nominal),
            str(cloud),
            "--out",
            str(folder / "big"),
            *NO_TABLE,
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    if proc.returncode not in VERDICT_CODES:
        return f"failed: {proc.stderr[-500:]}"
    wall, user, system, kb = proc.stderr.strip().splitlines()[-1].split()
    return (
        f"{n} points: {float(wall):.1f} s wall, CPU (user+sys) {float(user) + float(system):.1f} s, "
        f"peak RSS {int(kb) / 1024**2:.2f} GB"
    )


def main(n: int = 200_000, rounds: int = 5, big: int = 5_000_000, base: Path | None = None) -> None:
    if shutil.which("CloudCompare") is None:
        sys.exit("CloudCompare not found: apt-get install cloudcompare (make bench does)")
    print(f"nproc {os.cpu_count()}, load average {os.getloadavg()}, {rounds} rounds")
    # the compare path's kernels compiled ahead of time, as `make venv` leaves them (cell/analysis/kernels.py)
    built = subprocess.run(
        [sys.executable, "-m", "cell.analysis.kernels"],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
    )
    print((built.stdout or built.stderr[-500:]).strip())
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        nominal, cloud = make_inputs(folder, n)
        trees = {"cell compare": REPO} | ({f"cell compare ({base})": base} if base else {})
        for tree in trees.values():  # numba's on-disk cache and the OS file cache
            run_cell(nominal, cloud, folder / f"warm{len(str(tree))}", tree)
        wall: dict[str, list[float]] = {name: [] for name in [*trees, "CloudCompare -C2M_DIST"]}
        cpu: dict[str, list[float]] = {name: [] for name in wall}
        for k in range(rounds):  # interleaved: every tool sees the same load
            for name, tree in trees.items():
                c = child_cpu()
                wall[name].append(run_cell(nominal, cloud, folder / f"cell{k}{len(name)}", tree))
                cpu[name].append(child_cpu() - c)
            c = child_cpu()
            wall["CloudCompare -C2M_DIST"].append(run_cloudcompare(nominal, cloud))
            cpu["CloudCompare -C2M_DIST"].append(child_cpu() - c)
        print(f"{n} points vs 20480 triangles, whole process, default outputs:")
        for name in wall:
            print(
                f"  {name:24s} wall median {statistics.median(wall[name]):6.2f} s  best "
                f"{min(wall[name]):6.2f} s; CPU (user+sys) median {statistics.median(cpu[name]):5.2f} s"
            )
        cc = "CloudCompare -C2M_DIST"
        med = {name: (statistics.median(wall[name]), statistics.median(cpu[name])) for name in wall}
        for name in trees:
            print(
                f"  {name}: ratio (median) {med[name][0] / med[cc][0]:.2f}x, "
                f"(best) {min(wall[name]) / min(wall[cc]):.2f}x, (CPU) {med[name][1] / med[cc][1]:.2f}x"
            )
        print("agreement: " + agreement(folder, nominal, cloud, folder / f"cell0{len('cell compare')}"))
        if big:
            print("large cloud: " + big_run(folder, nominal, big))
    print(f"load average after {os.getloadavg()}")


if __name__ == "__main__":
    numbers = [int(a) for a in sys.argv[1:] if not a.startswith("--")]
    older = [Path(a.split("=", 1)[1]) for a in sys.argv[1:] if a.startswith("--base=")]
    main(*numbers, base=older[0] if older else None)
