"""The robotic 3D surface inspection cell (import cell)."""

__version__ = "0.1.0"
