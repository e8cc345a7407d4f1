"""The SPC page's trend chart: per run (in time order) the mean and the extreme deviation of one series, with
the tolerance band, drawn by matplotlib as inline SVG (no script, no external asset)."""

from __future__ import annotations

import io
from typing import Any


def trend_svg(series: Any, title: str) -> str:
    """SVG of a :class:`cell.results.SpcSeries`: mean (blue dots) and extreme (red crosses) per run, mm,
    with its capability's band as dashed lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = list(range(1, len(series.trend) + 1))
    means = [p.mean_mm for p in series.trend]
    extremes = [p.extreme_mm for p in series.trend]
    fig, ax = plt.subplots(figsize=(9.6, 3.0), dpi=100)
    try:
        ax.plot(runs, means, "o-", color="#1f5fbf", label="mean")
        ax.plot(runs, extremes, "x--", color="#c62828", label="extreme", markersize=9)
        cap = series.capability
        for band in (cap.lower_mm, cap.upper_mm):
            if band is not None:
                ax.axhline(band, color="#59636e", linestyle=":", linewidth=1.2)
        ax.axhline(0.0, color="#999", linewidth=0.6)
        ax.set_xlabel("run (oldest first)")
        ax.set_ylabel("deviation (mm)")
        ax.set_title(title, loc="left", fontsize=12)
        ax.set_xticks(runs)
        ax.legend(loc="upper right", fontsize=9, frameon=False)
        ax.grid(alpha=0.25)
        fig.tight_layout()
        out = io.StringIO()
        fig.savefig(out, format="svg")
    finally:
        plt.close(fig)
    svg = out.getvalue()
    return svg[svg.index("<svg") :]  # inline: without the XML prolog and doctype
