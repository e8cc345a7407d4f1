"""Storage of a run folder: its size by kind of file, and lossless codecs for raw view images measured on a
run's own pattern stacks (docs/storage.md records the figures).

    .venv/bin/python bench/bench_storage.py sizes RUN_DIR [RUN_DIR ...]
    .venv/bin/python bench/bench_storage.py codecs RUN_DIR [--views 0,6,9]
    .venv/bin/python bench/bench_storage.py cloud RUN_DIR

``codecs`` reads the raw stacks a run kept (views/NNN/raw/, e.g. a failed run under the default retention)
and encodes each with every candidate: OpenCV's PNG at zlib levels 1-9, WebP lossless (8-bit only),
multi-page TIFF with deflate, NumPy's deflated .npz; and, when installed (not dependencies of the cell),
imagecodecs' JPEG-LS and JPEG-XL and zstandard. Sizes are per view; times are the encoding CPU time per view
(``time.process_time``: the shared machine's load changes wall times more).

``cloud`` shows what storing results/cloud.ply's coordinates as float32 changes: the run's stored cloud is
judged against its nominal (``inputs/``, the recipe's band, part frame = the nominal's frame) as stored, and
moved by a random amount within half a float32 step of every coordinate (what a float64 source could have
held and rounded to the same file); the figures of both are printed with their differences.
"""

from __future__ import annotations

import argparse
import io
import os
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from cell.view_files import PNG_PARAMS, load_raw_stack  # noqa: E402


def kind(rel: Path) -> str:
    """What a run-folder file is, for the size table: results and view files by name, raw frames together."""
    top = rel.parts[0]
    if top == "views" and "raw" in rel.parts:
        return "views/*/raw (raw images)"
    if top in ("views", "results"):
        return f"{top}/{'*/' if top == 'views' and len(rel.parts) > 2 else ''}{rel.name}"
    return top if len(rel.parts) > 1 else rel.name


def sizes(run: Path) -> None:
    total, count = Counter[str](), Counter[str]()
    for dirpath, _, files in os.walk(run):
        for f in files:
            p = Path(dirpath) / f
            k = kind(p.relative_to(run))
            total[k] += p.stat().st_size
            count[k] += 1
    print(f"\n{run}")
    for k, n in total.most_common():
        print(f"  {n / 1e6:8.2f} MB  {count[k]:5d} files  {k}")
    print(f"  {sum(total.values()) / 1e6:8.2f} MB  total")


def _frames(encode: Callable[[np.ndarray], bytes]) -> Callable[[np.ndarray], int]:
    return lambda stack: sum(len(encode(f)) for f in stack)


def _cv2(ext: str, *params: int) -> Callable[[np.ndarray], int]:
    return _frames(lambda f: cv2.imencode(ext, f, list(params))[1].tobytes())


def _npz(stack: np.ndarray) -> int:
    buf = io.BytesIO()
    np.savez_compressed(buf, stack=stack)
    return len(buf.getvalue())


def _tiff(stack: np.ndarray) -> int:
    ok, buf = cv2.imencodemulti(".tiff", list(stack), [cv2.IMWRITE_TIFF_COMPRESSION, 8])  # 8: deflate
    return len(buf) if ok else -1


def candidates(bit_depth: int) -> dict[str, Callable[[np.ndarray], int]]:
    out = {
        f"PNG (OpenCV), zlib level {k}": _cv2(".png", cv2.IMWRITE_PNG_COMPRESSION, k) for k in (1, 3, 6, 9)
    }
    out["PNG (OpenCV), zlib level 1, SUB filter, Huffman only (cell.view_files.PNG_PARAMS)"] = _cv2(
        ".png", *PNG_PARAMS
    )
    if bit_depth == 8:
        out["WebP lossless (OpenCV, 8-bit only)"] = _cv2(".webp", cv2.IMWRITE_WEBP_QUALITY, 101)
    out["TIFF multi-page, deflate (OpenCV)"] = _tiff
    out["NumPy .npz (deflate)"] = _npz
    try:
        import imagecodecs

        out["JPEG-LS (imagecodecs)"] = _frames(imagecodecs.jpegls_encode)
        out["JPEG-XL lossless, effort 3 (imagecodecs)"] = _frames(
            lambda f: imagecodecs.jpegxl_encode(f, lossless=True, effort=3)
        )
    except ImportError:
        print("(imagecodecs not installed: JPEG-LS and JPEG-XL left out)")
    try:
        import zstandard

        out["zstd level 3 (zstandard), whole stack"] = lambda s: len(zstandard.ZstdCompressor(3).compress(s))
    except ImportError:
        print("(zstandard not installed: zstd left out)")
    return out


def codecs(run: Path, views: list[int] | None) -> None:
    dirs = sorted(d for d in (run / "views").iterdir() if (d / "raw").is_dir())
    if views is not None:
        dirs = [d for d in dirs if int(d.name) in views]
    if not dirs:
        sys.exit(f"{run}: no view with raw images (views/NNN/raw/)")
    stacks = [load_raw_stack(d) for d in dirs]
    raw = sum(s.nbytes for s in stacks if s is not None) / len(stacks)
    s0 = stacks[0]
    assert s0 is not None
    n, h, w = s0.shape
    print(f"{len(stacks)} views of {n} frames {w}x{h} {s0.dtype}: {raw / 1e6:.2f} MB a view uncompressed")
    bit_depth = 8 if s0.dtype == np.uint8 else 16
    print(f"  {'codec':44s} {'MB a view':>10s} {'ratio':>6s} {'CPU s a view':>13s}")
    for name, encode in candidates(bit_depth).items():
        t = time.process_time()
        n = sum(encode(s) for s in stacks if s is not None)
        dt = (time.process_time() - t) / len(stacks)
        print(f"  {name:44s} {n / len(stacks) / 1e6:10.2f} {raw * len(stacks) / n:6.2f} {dt:13.2f}")


def cloud(run: Path) -> None:
    import json

    import trimesh
    import yaml

    from cell.analysis.errormap import NominalMesh
    from cell.analysis.judge import judge
    from cell.analysis.report import Tolerance, summarise
    from cell.analysis.report_files import read_ply_points, stored_points

    pts = read_ply_points(run / "results" / "cloud.ply")
    manifest = json.loads((run / "inputs" / "manifest.json").read_text())
    band = yaml.safe_load((run / "inputs" / manifest["recipe"]).read_text())["tolerance"]
    nominal = NominalMesh.from_trimesh(trimesh.load(run / "inputs" / manifest["cad"]))
    half = np.spacing(np.abs(pts).astype(np.float32)).astype(np.float64) / 2
    moved = pts + np.random.default_rng(0).uniform(-1, 1, pts.shape) * half
    assert np.array_equal(stored_points(moved), pts)  # both round to the stored file
    print(
        f"{len(pts)} points, |coordinate| up to {np.abs(pts).max():.1f} mm: rounded by up to "
        f"{half.max() * 1e6:.1f} nm"
    )
    docs = [
        summarise(judge(nominal, p, Tolerance(band["lower"], band["upper"]), min_defect_points=10), [])
        for p in (pts, moved)
    ]
    flat = [{**d["deviation"], **d["deviation"]["percentiles_mm"]} for d in docs]
    for k, a in flat[0].items():
        if isinstance(a, float):
            print(f"  {k:10s} {a:+.9f} {flat[1][k]:+.9f} mm  differ by {abs(a - flat[1][k]) * 1e6:.3f} nm")
    print(
        f"  verdict {docs[0]['verdict']} / {docs[1]['verdict']}, out of tolerance "
        f"{docs[0]['n_out_of_tolerance']} / {docs[1]['n_out_of_tolerance']}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("sizes", "codecs", "cloud"))
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--views", help="codecs: view indices, comma-separated (default: all with raw images)")
    a = ap.parse_args()
    if a.what == "sizes":
        for run in a.runs:
            sizes(run)
    elif a.what == "cloud":
        cloud(a.runs[0])
    else:
        codecs(a.runs[0], [int(v) for v in a.views.split(",")] if a.views else None)


if __name__ == "__main__":
    main()
