"""The robotic 3D surface inspection cell (import cell)."""

import sys

__version__ = "0.1.0"


def _defer_cascadio() -> None:
    """Keep trimesh from loading OpenCASCADE at import time.

    trimesh imports ``cascadio`` (its STEP reader, a 1 s-CPU shared library) whenever ``import trimesh`` runs,
    which was a third of a whole ``cell compare``. Only STEP files need it: while trimesh is first imported,
    ``cascadio`` is marked unimportable, and :func:`cell.mesh.load_mesh` imports it and registers trimesh's
    STEP loader the first time a STEP file is read.
    """
    if "trimesh" in sys.modules or "cascadio" in sys.modules:
        return
    sys.modules["cascadio"] = None  # type: ignore[assignment]  # `import cascadio` raises ImportError
    try:
        import trimesh  # noqa: F401
    finally:
        del sys.modules["cascadio"]


_defer_cascadio()
