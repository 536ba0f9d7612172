"""A small SVG plotter for the report's figures: axes, ticks, lines, dots, bands, histograms and legends.

matplotlib costs about a second to import and a fifth of a second per figure to lay out and draw; these figures
need none of its generality. A figure is drawn in pixels (96 per inch, as the PNGs were), every series is first
reduced to what its pixel width can show (`envelope`: the lowest and highest reading per pixel column, so spikes
stay visible), and the result is one SVG document with no script, font or link, embedded in the page.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from html import escape
from typing import Any

import numpy as np

from magcal_cli.streams import FloatArray

#: pixels per inch (the figures keep the size the 96-dpi PNGs had)
DPI = 96
#: font sizes in px (matplotlib's 8, 9 and 7 pt at 96 dpi)
FONT, TITLE, LEGEND = 10.5, 12.0, 9.5
FAMILY = "DejaVu Sans,Helvetica,Arial,sans-serif"
#: average glyph width as a fraction of the font size: where a legend entry or a label ends
CHAR = 0.56
GRID = "#b0b0b0"


def envelope(x: FloatArray, y: FloatArray, columns: int) -> tuple[FloatArray, FloatArray]:
    """At most two samples per pixel column: the lowest and the highest finite y of the column, in their order.

    x is sorted (time). A line through them covers every pixel the full series would (min/max decimation), so a
    one-sample spike stays visible; a column without a finite y gives one NaN (a gap in the line).
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.size <= 2 * columns or not np.isfinite(x[[0, -1]]).all() or x[-1] <= x[0]:
        return x, y
    col = np.minimum(((x - x[0]) * (columns / (x[-1] - x[0]))).astype(np.int64), columns - 1)
    starts = np.flatnonzero(np.r_[True, col[1:] != col[:-1]])
    order = np.lexsort((y, col))                         # per column: finite y ascending, NaN last
    finite = np.add.reduceat(np.isfinite(y).astype(np.int64), starts)
    lo, hi = order[starts], order[starts + np.maximum(finite, 1) - 1]
    pick = np.sort(np.where(finite[:, None] > 0, np.stack([lo, hi], axis=1), lo[:, None]), axis=1)
    keep = np.ones_like(pick, dtype=bool)
    keep[:, 1] = (pick[:, 1] != pick[:, 0]) & (finite > 0)
    idx = pick[keep]
    return x[idx], y[idx]


def nice_ticks(lo: float, hi: float, target: int = 6) -> FloatArray:
    """Round tick values (1, 2, 2.5 or 5 times a power of ten) inside [lo, hi], about `target` of them."""
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
        return np.array([lo]) if np.isfinite(lo) else np.zeros(0)
    raw = (hi - lo) / max(target - 1, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= raw * 0.999)
    first = math.ceil(lo / step - 1e-9) * step
    ticks: FloatArray = first + step * np.arange(int(math.floor((hi - first) / step + 1e-9)) + 1, dtype=np.float64)
    return ticks


def tick_labels(ticks: FloatArray) -> list[str]:
    """Tick labels with as many decimals as the step needs (and no '-0.0')."""
    if ticks.size < 2:
        return [f"{v:g}" for v in ticks]
    step = float(np.min(np.diff(ticks)))
    digits = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
    digits += 1 if step > 0 and abs(round(step / 10.0 ** -digits) - step / 10.0 ** -digits) > 1e-6 else 0
    out = [f"{v:.{digits}f}" for v in ticks]
    return [s.lstrip("-") if float(s) == 0.0 else s for s in out]


def _fmt(v: float) -> str:
    """A pixel coordinate, one decimal."""
    return f"{v:.1f}"


def text_width(s: str, size: float) -> float:
    """Estimated width in px of `s` at font size `size`."""
    return CHAR * size * len(s)


@dataclass
class Handle:
    """A legend entry: how its swatch is drawn ('line', 'dot', 'patch'), its colour and label."""

    kind: str
    color: str
    label: str
    alpha: float = 1.0
    dash: str = ""


@dataclass
class Axes:
    """One panel at (x, y, w, h) px in its figure; series are in data units and mapped when the figure is drawn."""

    box: tuple[float, float, float, float]
    items: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    xlim: tuple[float, float] | None = None
    ylim: tuple[float, float] | None = None
    xticks: Sequence[float] | None = None
    yticks: Sequence[float] | None = None
    xticklabels: bool = True                 # False: ticks only (panels that share the x axis of the one below)
    xlabel: str = ""
    ylabel: str = ""
    ylabel_color: str = "#000"
    title: str = ""
    equal: bool = False
    grid: bool = True
    off: bool = False
    right: bool = False                      # a twin: ticks and label on the right, no grid
    handles: list[Handle] = field(default_factory=list)
    legend_at: str = ""
    legend_cols: int = 1
    twins: list[Axes] = field(default_factory=list)

    # -- what a panel holds -----------------------------------------------------------------------------------
    def line(self, x: FloatArray, y: FloatArray, color: str, width: float = 1.07, alpha: float = 1.0,
             dash: str = "", label: str = "") -> None:
        """A polyline, min/max-decimated to the panel's pixel width; NaN breaks it."""
        xs, ys = envelope(x, y, max(int(self.box[2]), 1))
        self.items.append(("line", {"x": xs, "y": ys, "color": color, "width": width, "alpha": alpha, "dash": dash}))
        if label:
            self.handles.append(Handle("line", color, label, alpha, dash))

    def dots(self, x: FloatArray, y: FloatArray, color: str, size: float = 2.0, alpha: float = 1.0,
             label: str = "") -> None:
        """Round markers of diameter `size` px (one path: a zero-length stroke with round caps per point)."""
        self.items.append(("dots", {"x": np.asarray(x, dtype=np.float64), "y": np.asarray(y, dtype=np.float64),
                                    "color": color, "size": size, "alpha": alpha}))
        if label:
            self.handles.append(Handle("dot", color, label, alpha))

    def hline(self, y: float, color: str, width: float = 0.8, dash: str = "", label: str = "") -> None:
        """A horizontal line across the panel."""
        self.items.append(("hline", {"y": float(y), "color": color, "width": width, "dash": dash}))
        if label:
            self.handles.append(Handle("line", color, label, 1.0, dash))

    def vspan(self, a: float, b: float, color: str, alpha: float = 1.0) -> None:
        """A vertical band from x = a to b across the panel, behind the data."""
        self.items.insert(0, ("vspan", {"a": float(a), "b": float(b), "color": color, "alpha": alpha}))

    def band(self, x: FloatArray, lo: FloatArray, hi: FloatArray, color: str, alpha: float, label: str = "") -> None:
        """The area between lo and hi over x."""
        self.items.append(("band", {"x": np.asarray(x, dtype=np.float64), "lo": np.asarray(lo, dtype=np.float64),
                                    "hi": np.asarray(hi, dtype=np.float64), "color": color, "alpha": alpha}))
        if label:
            self.handles.append(Handle("patch", color, label, alpha))

    def stairs(self, counts: FloatArray, edges: FloatArray, color: str, alpha: float = 1.0) -> None:
        """A filled histogram (counts between consecutive edges)."""
        x = np.repeat(np.asarray(edges, dtype=np.float64), 2)
        y = np.r_[0.0, np.repeat(np.asarray(counts, dtype=np.float64), 2), 0.0]
        self.band(x, np.zeros_like(y), y, color, alpha)

    def legend(self, at: str, cols: int = 1) -> None:
        """Show the panel's legend: 'above' (right-aligned above the panel) or 'upper right' inside it."""
        self.legend_at, self.legend_cols = at, cols

    def twin(self) -> Axes:
        """A second y scale on the right of the same panel (shares x)."""
        other = Axes(self.box, right=True, grid=False)
        self.twins.append(other)
        return other

    # -- drawing ----------------------------------------------------------------------------------------------
    def _data_range(self, axis: str) -> tuple[float, float]:
        """Min and max of the finite data along 'x' or 'y' (spans count only along x, lines only along y)."""
        vals: list[FloatArray] = []
        for kind, d in self.items:
            if kind in ("line", "dots"):
                vals.append(np.asarray(d[axis], dtype=np.float64))
            elif kind == "band":
                vals += [np.asarray(d["x"], dtype=np.float64)] if axis == "x" else \
                        [np.asarray(d["lo"], dtype=np.float64), np.asarray(d["hi"], dtype=np.float64)]
            elif kind == "hline" and axis == "y":
                vals.append(np.array([d["y"]], dtype=np.float64))
        v = np.concatenate(vals) if vals else np.zeros(0)
        v = v[np.isfinite(v)]
        if v.size == 0:
            return 0.0, 1.0
        lo, hi = float(v.min()), float(v.max())
        if hi <= lo:
            lo, hi = lo - 0.5 * max(abs(lo), 1.0), hi + 0.5 * max(abs(hi), 1.0)
        return lo, hi

    def limits(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The x and y limits: the ones set, else the data's with a 5 % margin (equal scales if `equal`)."""
        def pad(r: tuple[float, float]) -> tuple[float, float]:
            return r[0] - 0.05 * (r[1] - r[0]), r[1] + 0.05 * (r[1] - r[0])
        xl = self.xlim or pad(self._data_range("x"))
        yl = self.ylim or pad(self._data_range("y"))
        if self.equal:                          # widen the narrower range so one unit is as long on both axes
            w, h = self.box[2], self.box[3]
            scale = max((xl[1] - xl[0]) / w, (yl[1] - yl[0]) / h)
            cx, cy = 0.5 * (xl[0] + xl[1]), 0.5 * (yl[0] + yl[1])
            xl, yl = (cx - 0.5 * scale * w, cx + 0.5 * scale * w), (cy - 0.5 * scale * h, cy + 0.5 * scale * h)
        return xl, yl

    def draw(self, out: list[str], clip: str, xl: tuple[float, float] | None = None, part: str = "all") -> None:
        """Append the panel's SVG: grid, series (clipped), spines, ticks, labels, title, legend. A twin draws its
        `part` "series" inside its panel's clipped group and its "frame" (scale, label) after it."""
        if self.off:
            return
        x0, y0, w, h = self.box
        lx, ly = self.limits()
        lx = xl or lx
        sx, sy = w / (lx[1] - lx[0]), h / (ly[1] - ly[0])

        def px(v: FloatArray) -> FloatArray:
            out_: FloatArray = x0 + (np.asarray(v, dtype=np.float64) - lx[0]) * sx
            return out_

        def py(v: FloatArray) -> FloatArray:
            out_: FloatArray = y0 + h - (np.asarray(v, dtype=np.float64) - ly[0]) * sy
            return out_

        xt = np.asarray(self.xticks, dtype=np.float64) if self.xticks is not None else nice_ticks(*lx, 7)
        yt = np.asarray(self.yticks, dtype=np.float64) if self.yticks is not None else nice_ticks(*ly, 6)
        xt = xt[(xt >= lx[0] - 1e-9 * abs(lx[1] - lx[0])) & (xt <= lx[1] + 1e-9 * abs(lx[1] - lx[0]))]
        yt = yt[(yt >= ly[0] - 1e-9 * abs(ly[1] - ly[0])) & (yt <= ly[1] + 1e-9 * abs(ly[1] - ly[0]))]
        if part == "series":
            out += [_item(kind, d, px, py, (x0, y0, w, h)) for kind, d in self.items]
            return
        if part == "all":
            if self.grid:
                g = "".join(f"M{_fmt(a)} {_fmt(y0)}v{_fmt(h)}" for a in px(xt)) + \
                    "".join(f"M{_fmt(x0)} {_fmt(b)}h{_fmt(w)}" for b in py(yt))
                out.append(f"<path d='{g}' stroke='{GRID}' stroke-opacity='0.3' stroke-width='0.8' fill='none'/>")
            out.append(f"<g clip-path='url(#{clip})'>")        # bands, then a twin's series, then this panel's
            out += [_item(kind, d, px, py, (x0, y0, w, h)) for kind, d in self.items if kind == "vspan"]
            for t in self.twins:
                t.draw(out, clip, lx, "series")
            out += [_item(kind, d, px, py, (x0, y0, w, h)) for kind, d in self.items if kind != "vspan"]
            out.append("</g>")
            for t in self.twins:
                t.draw(out, clip, lx, "frame")
        tick = []
        if not self.right:
            out.append(f"<path d='M{_fmt(x0)} {_fmt(y0)}V{_fmt(y0 + h)}H{_fmt(x0 + w)}' stroke='#000' "
                       "stroke-width='0.8' fill='none'/>")
            tick += [f"M{_fmt(a)} {_fmt(y0 + h)}v3.5" for a in px(xt)]
            tick += [f"M{_fmt(x0)} {_fmt(b)}h-3.5" for b in py(yt)]
            for a, s in zip(px(xt), tick_labels(xt), strict=True) if self.xticklabels else ():
                out.append(_text(a, y0 + h + 5 + FONT, s, FONT, "middle"))
        else:
            out.append(f"<path d='M{_fmt(x0 + w)} {_fmt(y0)}V{_fmt(y0 + h)}' stroke='#000' stroke-width='0.8'/>")
            tick += [f"M{_fmt(x0 + w)} {_fmt(b)}h3.5" for b in py(yt)]
        labels = tick_labels(yt)
        side, anchor = (x0 + w + 6, "start") if self.right else (x0 - 6, "end")
        for b, s in zip(py(yt), labels, strict=True):
            out.append(_text(side, b + 0.35 * FONT, s, FONT, anchor))
        out.append(f"<path d='{''.join(tick)}' stroke='#000' stroke-width='0.8'/>")
        if self.xlabel and not self.right:
            out.append(_text(x0 + 0.5 * w, y0 + h + 8 + 2.2 * FONT, self.xlabel, FONT, "middle"))
        if self.ylabel:
            room = max((text_width(s, FONT) for s in labels), default=0.0) + 10 + 0.3 * FONT
            lines = self.ylabel.split("\n")
            for k, s in enumerate(lines):
                off = room + (len(lines) - 1 - k) * 1.2 * FONT if not self.right else room + 0.8 * FONT + k * 1.2 * FONT
                xx = x0 - off if not self.right else x0 + w + off
                out.append(_text(xx, y0 + 0.5 * h, s, FONT, "middle", self.ylabel_color, rotate=True))
        if self.title:
            out.append(_text(x0 + 0.5 * w, y0 - 6, self.title, TITLE, "middle"))
        if self.legend_at and self.handles:
            rows = -(-len(self.handles) // self.legend_cols)
            if self.legend_at == "above":
                legend(out, self.handles, x0 + w, y0 - 3 - rows * 1.4 * LEGEND, "right", self.legend_cols)
            else:
                wide = max(legend_width([hd]) for hd in self.handles)
                tall = rows * 1.4 * LEGEND + 2
                spots = [(x0 + w - 4, y0 + 4), (x0 + 4 + wide, y0 + 4), (x0 + 4 + wide, y0 + h - 4 - tall),
                         (x0 + w - 4, y0 + h - 4 - tall)]         # upper right, upper left, lower left, lower right

                def covered(spot: tuple[float, float]) -> int:
                    """How many plotted points the legend box at `spot` would hide."""
                    n = 0
                    for kind, d in self.items:
                        if kind in ("line", "dots"):
                            a, b = px(d["x"]), py(d["y"])
                            n += int(np.sum((a >= spot[0] - wide) & (a <= spot[0]) & (b >= spot[1])
                                            & (b <= spot[1] + tall)))
                    return n

                x_, y_ = min(spots, key=covered)
                legend(out, self.handles, x_, y_, "right", 1)


def _text(x: float, y: float, s: str, size: float, anchor: str, color: str = "#000", rotate: bool = False) -> str:
    """A text element (baseline at y), optionally turned to read upwards about its anchor."""
    turn = f" transform='rotate(-90 {_fmt(x)} {_fmt(y)})'" if rotate else ""
    fill = f" fill='{color}'" if color != "#000" else ""
    return (f"<text x='{_fmt(x)}' y='{_fmt(y)}' font-size='{size}' text-anchor='{anchor}'{fill}{turn}>"
            f"{escape(s)}</text>")


def _path_d(xs: FloatArray, ys: FloatArray) -> str:
    """'M x y L x y ...' with a new M after every non-finite point (a gap)."""
    ok = np.isfinite(xs) & np.isfinite(ys)
    if not ok.any():
        return ""
    start = ok & ~np.r_[False, ok[:-1]]
    cmd = np.where(start, "M", "L")
    return "".join(f"{c}{a:.1f} {b:.1f}" for c, a, b, good in zip(cmd, xs, ys, ok, strict=True) if good)


def _item(kind: str, d: dict[str, Any], fx: Callable[[Any], FloatArray], fy: Callable[[Any], FloatArray],
          box: tuple[float, float, float, float]) -> str:
    """One series as SVG (fx, fy map data to pixels)."""
    x0, y0, w, h = box
    op = float(d.get("alpha", 1.0))
    opacity = f" opacity='{op:.2f}'" if op < 1.0 else ""
    color = d["color"]
    if kind == "line":
        dash = f" stroke-dasharray='{d['dash']}'" if d["dash"] else ""
        return (f"<path d='{_path_d(fx(d['x']), fy(d['y']))}' fill='none' stroke='{color}' "
                f"stroke-width='{d['width']}' stroke-linejoin='round'{dash}{opacity}/>")
    if kind == "dots":
        xs, ys = fx(d["x"]), fy(d["y"])
        ok = np.isfinite(xs) & np.isfinite(ys)
        # one dot per half pixel: more of them draw the same pixels (the first of each, in the series' order)
        cells = np.round(2 * xs[ok]).astype(np.int64) * (1 << 32) + np.round(2 * ys[ok]).astype(np.int64)
        first = np.sort(np.unique(cells, return_index=True)[1])
        pts = "".join(f"M{a:.1f} {b:.1f}h0" for a, b in zip(xs[ok][first], ys[ok][first], strict=True))
        return (f"<path d='{pts}' stroke='{color}' stroke-width='{d['size']}' stroke-linecap='round' "
                f"fill='none'{opacity}/>")
    if kind == "hline":
        dash = f" stroke-dasharray='{d['dash']}'" if d["dash"] else ""
        yy = float(fy(np.array([d["y"]]))[0])
        return f"<path d='M{_fmt(x0)} {_fmt(yy)}h{_fmt(w)}' stroke='{color}' stroke-width='{d['width']}'{dash}/>"
    if kind == "vspan":
        a, b = fx(np.array([d["a"], d["b"]]))
        return (f"<rect x='{_fmt(a)}' y='{_fmt(y0)}' width='{_fmt(max(b - a, 0.5))}' height='{_fmt(h)}' "
                f"fill='{color}'{opacity}/>")
    xs = fx(d["x"])
    top, bottom = fy(d["hi"]), fy(d["lo"])
    poly = np.concatenate([xs, xs[::-1]]), np.concatenate([top, bottom[::-1]])
    return f"<path d='{_path_d(*poly)}Z' fill='{color}' stroke='none'{opacity}/>"


def legend_width(row: list[Handle]) -> float:
    """Estimated width in px of one legend row."""
    return sum(24 + text_width(hd.label, LEGEND) + 12 for hd in row) - 12


def legend(out: list[str], handles: list[Handle], x: float, top: float, align: str, cols: int,
           markerscale: float = 1.0) -> None:
    """Legend entries in rows of `cols` from `top` down, each row's right end (align 'right') or centre ('center')
    at x."""
    rows = [handles[k:k + cols] for k in range(0, len(handles), cols)]
    for r, row in enumerate(rows):
        widths = [24 + text_width(hd.label, LEGEND) + 12 for hd in row]
        total = legend_width(row)
        left = x - total if align == "right" else x - 0.5 * total
        base = top + LEGEND + r * 1.4 * LEGEND
        for hd, wd in zip(row, widths, strict=True):
            mid = base - 0.35 * LEGEND
            op = f" opacity='{hd.alpha:.2f}'" if hd.alpha < 1 else ""
            if hd.kind == "line":
                dash = f" stroke-dasharray='{hd.dash}'" if hd.dash else ""
                out.append(f"<path d='M{_fmt(left)} {_fmt(mid)}h18' stroke='{hd.color}' stroke-width='1.5'{dash}/>")
            elif hd.kind == "dot":
                out.append(f"<circle cx='{_fmt(left + 9)}' cy='{_fmt(mid)}' r='{3.5 * markerscale / 2:.1f}' "
                           f"fill='{hd.color}'/>")
            else:
                out.append(f"<rect x='{_fmt(left)}' y='{_fmt(mid - 4)}' width='18' height='8' fill='{hd.color}'{op}/>")
            out.append(_text(left + 24, base, hd.label, LEGEND, "start"))
            left += wd


@dataclass
class Figure:
    """A figure of `width` x `height` px holding panels; `svg()` draws it."""

    width: float
    height: float
    axes: list[Axes] = field(default_factory=list)
    handles: list[Handle] = field(default_factory=list)
    legend_cols: int = 1
    markerscale: float = 1.0

    def grid(self, rows: int, cols: int, spec: dict[str, float]) -> list[list[Axes]]:
        """A rows x cols grid of panels placed as matplotlib's GridSpec places them (figure-fraction margins,
        wspace/hspace as fractions of the mean panel width/height)."""
        left, right = spec["left"] * self.width, spec["right"] * self.width
        top, bottom = (1 - spec["top"]) * self.height, (1 - spec["bottom"]) * self.height
        w = (right - left) / (cols + spec["wspace"] * (cols - 1))
        h = (bottom - top) / (rows + spec["hspace"] * (rows - 1))
        out = [[Axes((left + c * w * (1 + spec["wspace"]), top + r * h * (1 + spec["hspace"]), w, h))
                for c in range(cols)] for r in range(rows)]
        self.axes += [a for row in out for a in row]
        return out

    def legend(self, handles: list[Handle], cols: int, markerscale: float = 1.0) -> None:
        """A legend centred at the top of the figure."""
        self.handles, self.legend_cols, self.markerscale = handles, cols, markerscale

    def svg(self) -> str:
        """The figure as a standalone SVG document."""
        out = [f"<svg xmlns='http://www.w3.org/2000/svg' width='{self.width:.0f}' height='{self.height:.0f}' "
               f"viewBox='0 0 {self.width:.0f} {self.height:.0f}' font-family='{FAMILY}'>",
               f"<rect width='{self.width:.0f}' height='{self.height:.0f}' fill='#fff'/><defs>"]
        out += [f"<clipPath id='c{k}'><rect x='{_fmt(a.box[0])}' y='{_fmt(a.box[1])}' width='{_fmt(a.box[2])}' "
                f"height='{_fmt(a.box[3])}'/></clipPath>" for k, a in enumerate(self.axes)]
        out.append("</defs>")
        for k, a in enumerate(self.axes):
            a.draw(out, f"c{k}")
        if self.handles:
            legend(out, self.handles, 0.5 * self.width, 4, "center", self.legend_cols, self.markerscale)
        out.append("</svg>")
        return "".join(out)

    def uri(self) -> str:
        """The figure as a base64 data URI for an <img> (the page stays one file with no script)."""
        return "data:image/svg+xml;base64," + base64.b64encode(self.svg().encode("utf-8")).decode("ascii")
