"""The report's deviation colours, banded by the tolerance: in tolerance neutral, beyond it saturated.

A metrology reader looks for what is out of tolerance first. So every deviation inside the band is a pale
grey, tinted faintly towards blue (below the nominal) or red (above) so that the shape of the part within
tolerance still shows; at a limit the colour jumps to a saturated blue (a dent, below the lower limit) or red
(excess, above the upper one) that deepens over one band width beyond it and stays there. The static views,
the 3D view (as a plotly colour scale with hard steps at the limits), the legend and the histogram all take
their colours from :class:`BandedScale`, so they agree exactly.

Deviations in mm, + outside the material. The reference (the neutral grey) is 0 when the band holds 0 (the
nominal is the ideal), else the band's centre (a one-sided band such as 0 .. +0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cell.analysis.formatting import signed

RGB = tuple[int, int, int]
NEUTRAL: RGB = (226, 226, 226)
PALE_LOW: RGB = (186, 208, 232)  # inside the band, at the lower limit
PALE_HIGH: RGB = (242, 204, 188)  # inside the band, at the upper limit
LOW: tuple[RGB, RGB] = ((33, 102, 212), (8, 29, 110))  # beyond the lower limit: at it, one width beyond
HIGH: tuple[RGB, RGB] = ((222, 38, 30), (110, 0, 10))  # beyond the upper limit
UNMEASURED: RGB = (105, 105, 105)  # hatching of the nominal surface that was not measured


def _hex(c: RGB) -> str:
    return "#{:02x}{:02x}{:02x}".format(*c)


def css_rgb(c: RGB) -> str:
    """rgb(r,g,b) for CSS and plotly."""
    return f"rgb({c[0]},{c[1]},{c[2]})"


def _mix(a: RGB, b: RGB, t: NDArray[np.float64]) -> NDArray[np.float64]:
    """Linear RGB blend from ``a`` (t = 0) to ``b`` (t = 1), (N, 3)."""
    return np.asarray(a, np.float64) + np.clip(t, 0.0, 1.0)[:, None] * (
        np.asarray(b, np.float64) - np.asarray(a, np.float64)
    )


@dataclass(frozen=True)
class BandedScale:
    """Colours of deviations (mm) for the tolerance band [lower_mm, upper_mm]."""

    lower_mm: float
    upper_mm: float

    @property
    def reference_mm(self) -> float:
        """Where the colour is plain neutral: 0 inside the band, else the band's centre."""
        return 0.0 if self.lower_mm <= 0.0 <= self.upper_mm else (self.lower_mm + self.upper_mm) / 2

    @property
    def span_mm(self) -> float:
        """How far beyond a limit the saturated colour deepens: one band width."""
        return max(self.upper_mm - self.lower_mm, 1e-9)

    @property
    def range_mm(self) -> tuple[float, float]:
        """The deviations the scale distinguishes; beyond them the deepest colour."""
        return self.lower_mm - self.span_mm, self.upper_mm + self.span_mm

    def zone(self, deviation_mm: ArrayLike) -> NDArray[np.int8]:
        """-1 below the lower limit, 0 inside the band (limits included), +1 above the upper limit."""
        d = np.asarray(deviation_mm, dtype=np.float64)
        return ((d > self.upper_mm).astype(np.int8) - (d < self.lower_mm).astype(np.int8)).astype(np.int8)

    def rgb(self, deviation_mm: ArrayLike) -> NDArray[np.uint8]:
        """(N, 3) uint8 colours of the deviations."""
        d = np.atleast_1d(np.asarray(deviation_mm, dtype=np.float64))
        lo, hi, ref, span = self.lower_mm, self.upper_mm, self.reference_mm, self.span_mm
        out = np.empty((len(d), 3))
        below, above = d < ref, d >= ref
        out[below] = _mix(NEUTRAL, PALE_LOW, (ref - d[below]) / max(ref - lo, 1e-12))
        out[above] = _mix(NEUTRAL, PALE_HIGH, (d[above] - ref) / max(hi - ref, 1e-12))
        zone = self.zone(d)
        out[zone < 0] = _mix(*LOW, (lo - d[zone < 0]) / span)
        out[zone > 0] = _mix(*HIGH, (d[zone > 0] - hi) / span)
        return (out + 0.5).astype(np.uint8)

    def stops(self) -> list[tuple[float, RGB]]:
        """The scale as (deviation mm, colour) stops over :attr:`range_mm`, linear between stops, with two
        stops at each limit (the step)."""
        lo, hi = self.lower_mm, self.upper_mm
        c0, c1 = self.range_mm
        return [
            (c0, LOW[1]),
            (lo, LOW[0]),
            (lo, PALE_LOW),
            (self.reference_mm, NEUTRAL),
            (hi, PALE_HIGH),
            (hi, HIGH[0]),
            (c1, HIGH[1]),
        ]

    def plotly_colorscale(self) -> list[list[float | str]]:
        """The stops as a plotly colour scale over ``cmin, cmax = range_mm`` (hard steps at the limits)."""
        c0, c1 = self.range_mm
        return [[(v - c0) / (c1 - c0), css_rgb(c)] for v, c in self.stops()]

    def css_gradient(self) -> str:
        """The stops as a CSS linear gradient from the low end to the high end."""
        c0, c1 = self.range_mm
        return (
            "linear-gradient(to right, "
            + ", ".join(f"{_hex(c)} {100 * (v - c0) / (c1 - c0):.2f}%" for v, c in self.stops())
            + ")"
        )

    def legend_html(self, width_px: int = 420) -> str:
        """A colour bar with marks and labels at the limits and the reference, the ends labelled as
        'or beyond', and a swatch of the hatching of what was not measured."""
        c0, c1 = self.range_mm

        def at(v: float) -> float:
            return 100 * (v - c0) / (c1 - c0)

        marks = [(self.lower_mm, "limit"), (self.upper_mm, "limit")]
        if self.lower_mm < self.reference_mm < self.upper_mm:
            marks.append((self.reference_mm, "ref"))
        ticks = "".join(
            f'<span class="tick {kind}" style="left:{at(v):.2f}%"></span>'
            f'<span class="ticklabel {kind}" style="left:{at(v):.2f}%">{signed(v)}</span>'
            for v, kind in marks
        )
        return (
            f'<div class="legend" style="width:{width_px}px"><div class="bar" style="background:'
            f'{self.css_gradient()}">{ticks}</div><div class="ends"><span>&le;&thinsp;{signed(c0)}</span>'
            f"<span>deviation, mm</span><span>&ge;&thinsp;{signed(c1)}</span></div>"
            '<div class="keys"><span><i class="sw" style="background:'
            f'{_hex(LOW[0])}"></i>below tolerance</span><span><i class="sw" style="background:'
            f'{_hex(NEUTRAL)}"></i>in tolerance</span><span><i class="sw" style="background:'
            f'{_hex(HIGH[0])}"></i>above tolerance</span><span><i class="sw hatch"></i>not measured</span>'
            "</div></div>"
        )


U_LOW: RGB = (174, 212, 178)  # U well under the target: pale green
U_TARGET: RGB = (250, 176, 40)  # U at the target (a quarter of the tolerance band): amber
U_HIGH: RGB = (140, 50, 0)  # U at twice the target or more: dark brown
AMBIGUOUS: RGB = (150, 60, 190)  # a point the guarded rule could not decide: purple


@dataclass(frozen=True)
class UncertaintyScale:
    """Colours of the expanded uncertainty U (mm) against the gauging target (U at most a quarter of the
    tolerance band): neutral to pale green up to the target, amber at it deepening to brown at twice it; the
    points the guarded rule left ambiguous in purple, whatever their U."""

    target_mm: float

    def rgb(self, U_mm: ArrayLike, ambiguous: ArrayLike | None = None) -> NDArray[np.uint8]:
        """(N, 3) uint8 colours of U (non-finite U: as beyond twice the target)."""
        U = np.atleast_1d(np.asarray(U_mm, dtype=np.float64))
        t = np.where(np.isfinite(U), U / max(self.target_mm, 1e-12), np.inf)
        out = _mix(NEUTRAL, U_LOW, np.minimum(t, 1.0))
        over = t > 1.0
        out[over] = _mix(U_TARGET, U_HIGH, t[over] - 1.0)
        if ambiguous is not None:
            out[np.asarray(ambiguous, dtype=bool)] = AMBIGUOUS
        return (out + 0.5).astype(np.uint8)

    def legend_html(self, width_px: int = 420) -> str:
        """A colour bar from 0 to twice the target with the target marked, and the ambiguous swatch."""
        stops = f"{_hex(NEUTRAL)} 0%, {_hex(U_LOW)} 50%, {_hex(U_TARGET)} 50%, {_hex(U_HIGH)} 100%"
        t = self.target_mm
        return (
            f'<div class="legend" style="width:{width_px}px"><div class="bar" style="background:'
            f'linear-gradient(to right, {stops})"><span class="tick" style="left:50%"></span>'
            f'<span class="ticklabel" style="left:50%">{t:.3f}</span></div><div class="ends"><span>0</span>'
            f"<span>U = k u, mm (target: a quarter of the band)</span><span>&ge;&thinsp;{2 * t:.3f}</span>"
            f'</div><div class="keys"><span><i class="sw" style="background:{_hex(AMBIGUOUS)}"></i>'
            "ambiguous (guarded rule)</span></div></div>"
        )
