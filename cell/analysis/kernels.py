"""The compare path's compiled kernels (error map, point grid, depth buffer), loaded without starting numba.

A fresh ``cell compare`` spent more CPU starting numba (its import, then building its CPU target context on
the first call of a kernel, even one loaded from numba's cache: ~1.6 s) than CloudCompare spends on the
whole comparison. So the same kernels -- the numba functions of :mod:`cell.analysis._triangle_grid`,
:mod:`cell.analysis._point_grid_kernels` and :mod:`cell.analysis._picture_kernels`, not a second copy -- are
also compiled ahead of time by numba's ``numba.pycc`` into a C extension module, which imports in under a
millisecond and needs neither numba nor LLVM at run time. ``make venv`` builds it (``python -m
cell.analysis.kernels``; gcc and the Python headers needed) into the user's cache folder
(:func:`cell.user_cache.cache_dir`), named by a hash of the kernels' source, their signatures and the numba,
numpy and Python versions: a stale build is never loaded. A successful build removes the older ones.

:func:`get` gives numba's jit function (parallel where the kernel is), unless the process has asked for the
ahead-of-time build with :func:`prefer_aot` and it was found: ``cell compare`` does, first thing
(:mod:`cell.commands.compare`); an inspection does not. Without the build, or when it cannot be looked up,
numba's jit runs. The two give the same bits (each point is computed alone, in the same order of operations;
tests/test_analysis_kernels.py checks it). ``CELL_KERNELS=jit`` makes :func:`prefer_aot` decline.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import os
import sys
import sysconfig
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from cell.user_cache import cache_dir

_F1, _F2, _F3 = "f8[::1]", "f8[:, ::1]", "f8[:, :, ::1]"
_I1, _I2 = "i8[::1]", "i8[:, ::1]"
# name: (module, numba signature), as the callers pass them (C-contiguous arrays)
SIGNATURES: dict[str, tuple[str, str]] = {
    "build_grid": (
        "cell.analysis._triangle_grid",
        f"Tuple(({_I1}, {_I1}, {_F2}))({_F2}, {_F2}, {_F1}, f8, {_I1})",
    ),
    "signed_closest": (
        "cell.analysis._triangle_grid",
        f"Tuple(({_F1}, {_F2}, {_I1}, i1[::1]))"
        f"({_F2}, {_I1}, {_F2}, {_I1}, {_I1}, {_F2}, {_F1}, f8, {_I1}, {_I2}, {_F3}, {_F2})",
    ),
    "_bin": ("cell.analysis._point_grid_kernels", f"Tuple(({_I1}, {_I1}))({_F2}, {_F1}, f8, {_I1})"),
    "_nearest_other": (
        "cell.analysis._point_grid_kernels",
        f"Tuple(({_I1}, {_F1}))({_F2}, {_I1}, {_I1}, {_I1}, {_F1}, f8, {_I1})",
    ),
    "_radius_labels": (
        "cell.analysis._point_grid_kernels",
        f"{_I1}({_F2}, f8, {_I1}, {_I1}, {_F1}, f8, {_I1})",
    ),
    "zbuffer": ("cell.analysis._picture_kernels", f"Tuple(({_I1}, {_F1}))({_I1}, {_F1}, i8)"),
}


def build_key() -> str:
    """Hash of what the ahead-of-time build is made from: the kernel modules' source, the signatures, and
    the numba (its ``_version.py``, read without importing numba), numpy and Python versions (16 hex
    digits)."""
    import numpy

    h = hashlib.sha256()
    for module in [*sorted({m for m, _ in SIGNATURES.values()}), "numba"]:
        spec = importlib.util.find_spec(module)
        assert spec is not None and spec.origin is not None
        origin = Path(spec.origin)
        h.update((origin.with_name("_version.py") if module == "numba" else origin).read_bytes())
    h.update(repr(sorted(SIGNATURES.items())).encode())
    h.update(f"{numpy.__version__} {sys.version}".encode())
    return h.hexdigest()[:16]


def aot_path() -> Path:
    """Where the ahead-of-time build of the current kernels is (or would be) kept."""
    return cache_dir() / f"_cell_kernels_{build_key()}{sysconfig.get_config_var('EXT_SUFFIX')}"


def load_aot(path: Path | None = None) -> ModuleType | None:
    """The ahead-of-time build at ``path`` (default :func:`aot_path`), or None when it has not been built
    (or cannot load)."""
    path = path or aot_path()
    if not path.is_file():
        return None
    name = path.name.split(".", 1)[0]
    try:
        spec = importlib.util.spec_from_file_location(name, path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except (ImportError, OSError):
        return None
    return module


def jit(name: str) -> Callable[..., Any]:
    """numba's jit function ``name`` (imports numba)."""
    module, _ = SIGNATURES[name]
    return getattr(importlib.import_module(module), name)


_aot: ModuleType | None = None  # the ahead-of-time build, once prefer_aot() has found it


def prefer_aot() -> bool:
    """Hand out the ahead-of-time build's kernels from now on in this process, when it is there; whether it
    is. Any failure to find or load it (no home folder for the cache, an unreadable cache folder, a build
    that does not load) leaves numba's jit kernels in use."""
    global _aot
    _aot = None
    if os.environ.get("CELL_KERNELS") == "jit":
        return False
    try:
        _aot = load_aot()
    except (OSError, RuntimeError):  # PermissionError; Path.home() without a home folder
        pass
    return _aot is not None


def get(name: str) -> Callable[..., Any]:
    """Kernel ``name`` of :data:`SIGNATURES`: the ahead-of-time build's after :func:`prefer_aot` found it,
    else numba's jit function."""
    return getattr(_aot, name) if _aot is not None else jit(name)


def build(dest: Path | None = None) -> Path:
    """Compile the kernels ahead of time with ``numba.pycc`` into ``dest`` (default :func:`aot_path`) and
    return it. Written whole or not at all (built in a temporary folder beside it, then renamed). Then the
    other builds in that folder (older kernels, same Python) and the temporary folders of builds killed
    more than :data:`STALE_BUILD_S` ago are removed."""
    import tempfile
    import warnings

    dest = dest or aot_path()
    dest.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pycc's pending deprecation
        from numba.pycc import CC
    with tempfile.TemporaryDirectory(dir=dest.parent, prefix=".build-") as tmp:
        cc = CC(dest.name.split(".", 1)[0])
        cc.output_dir = tmp
        for name, (_, signature) in SIGNATURES.items():
            cc.export(name, signature)(jit(name).py_func)  # type: ignore[attr-defined]
        cc.compile()
        (built,) = Path(tmp).glob(f"{cc.name}*")
        os.replace(built, dest)
    _remove_old_builds(dest)
    return dest


STALE_BUILD_S = 600.0  # a build takes ~10 s: an older .build-* folder is a killed one, not one under way


def _remove_old_builds(kept: Path) -> None:
    """Remove the builds beside ``kept`` named like it with another key, and stale ``.build-*`` folders."""
    import shutil
    import time

    suffix = sysconfig.get_config_var("EXT_SUFFIX")
    for path in kept.parent.iterdir():
        name = path.name
        if path != kept and path.is_file() and name.startswith("_cell_kernels_") and name.endswith(suffix):
            key = name.removeprefix("_cell_kernels_").removesuffix(suffix)
            if len(key) == 16 and all(c in "0123456789abcdef" for c in key):
                path.unlink(missing_ok=True)
        elif name.startswith(".build-") and path.is_dir() and not path.is_symlink():
            if time.time() - path.stat().st_mtime > STALE_BUILD_S:
                shutil.rmtree(path, ignore_errors=True)


if __name__ == "__main__":
    path = aot_path()
    if path.is_file() and "--force" not in sys.argv:
        print(f"compiled kernels present: {path}")
    else:
        print(f"compiled kernels built: {build(path)}")
