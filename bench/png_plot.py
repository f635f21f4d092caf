"""A small scatter-plot writer with numpy and zlib only (matplotlib is not a dependency here):
panels of error against milliseconds (log scale), points coloured by kind, the Pareto frontier
drawn as a line through its ringed points, and a 3x5 pixel font for labels."""

from __future__ import annotations

import math

import numpy as np

from training.lightstage.png import write_png  # noqa: F401  (one PNG writer; part of this API)

_GLYPHS = {
    "0": "111101101101111", "1": "010110010010111", "2": "111001111100111",
    "3": "111001111001111", "4": "101101111001001", "5": "111100111001111",
    "6": "111100111101111", "7": "111001001001001", "8": "111101111101111",
    "9": "111101111001111", "A": "010101111101101", "B": "110101110101110",
    "C": "011100100100011", "D": "110101101101110", "E": "111100110100111",
    "F": "111100110100100", "G": "011100101101011", "H": "101101111101101",
    "I": "111010010010111", "J": "001001001101010", "K": "101101110101101",
    "L": "100100100100111", "M": "101111111101101", "N": "110101101101101",
    "O": "010101101101010", "P": "110101110100100", "Q": "010101101110011",
    "R": "110101110101101", "S": "011100010001110", "T": "111010010010010",
    "U": "101101101101111", "V": "101101101101010", "W": "101101111111101",
    "X": "101101010101101", "Y": "101101010010010", "Z": "111001010100111",
    ".": "000000000000010", "-": "000000111000000", ":": "000010000010000",
    "/": "001001010100100", "%": "101001010100101", "(": "010100100100010",
    ")": "010001001001010", ",": "000000000010100", "+": "000010111010000",
    "=": "000111000111000", "_": "000000000000111", "*": "000101010101000",
    "[": "110100100100110", "]": "011001001001011", " ": "000000000000000",
}
PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (148, 103, 189), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]
FRONTIER = (214, 39, 40)


class Canvas:
    def __init__(self, height: int, width: int):
        self.px = np.full((height, width, 3), 255, np.uint8)

    def rect(self, y0, x0, y1, x1, colour):
        h, w = self.px.shape[:2]
        y0, y1 = sorted((int(round(y0)), int(round(y1))))
        x0, x1 = sorted((int(round(x0)), int(round(x1))))
        self.px[max(y0, 0):min(y1 + 1, h), max(x0, 0):min(x1 + 1, w)] = colour

    def line(self, y0, x0, y1, x1, colour, width=1):
        n = int(max(abs(y1 - y0), abs(x1 - x0))) + 1
        for t in np.linspace(0.0, 1.0, n):
            y, x = y0 + t * (y1 - y0), x0 + t * (x1 - x0)
            self.rect(y - width // 2, x - width // 2, y + (width - 1) // 2,
                      x + (width - 1) // 2, colour)

    def ring(self, y, x, r, colour):
        for a in np.linspace(0, 2 * math.pi, 8 * r + 8, endpoint=False):
            self.rect(y + r * math.sin(a), x + r * math.cos(a), y + r * math.sin(a),
                      x + r * math.cos(a), colour)

    def text(self, y, x, s: str, colour=(0, 0, 0), scale=2, anchor="left"):
        width = len(s) * 4 * scale
        if anchor == "right":
            x -= width
        elif anchor == "centre":
            x -= width // 2
        for i, ch in enumerate(s.upper()):
            bits = _GLYPHS.get(ch, _GLYPHS["*"])
            for k, b in enumerate(bits):
                if b == "1":
                    r, c = divmod(k, 3)
                    yy, xx = y + r * scale, x + (i * 4 + c) * scale
                    self.rect(yy, xx, yy + scale - 1, xx + scale - 1, colour)


def _nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    step = (hi - lo) / max(n, 1)
    mag = 10 ** math.floor(math.log10(step)) if step > 0 else 1.0
    step = min((m * mag for m in (1, 2, 5, 10)), key=lambda s: abs(s - step))
    first = math.ceil(lo / step) * step
    return [first + i * step for i in range(int((hi - first) / step + 1e-9) + 1)]


def _fmt(v: float) -> str:
    return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"


def draw_panel(c: Canvas, top, left, h, w, title, xlabel, ylabel, points, kinds, refs=()):
    """points: dicts with ms, error, kind, frontier (bool), front (which frontier), label;
    refs: (error, label) drawn as dashed horizontal lines (baselines that take no time)."""
    c.text(top, left + w // 2, title, anchor="centre")
    y0, x0, y1, x1 = top + 40, left + 70, top + h - 50, left + w - 20
    c.rect(y0, x0, y1, x0, (0, 0, 0))
    c.rect(y1, x0, y1, x1, (0, 0, 0))
    pts = [p for p in points if p["ms"] and p["ms"] > 0 and p["error"] is not None]
    if not pts:
        c.text((y0 + y1) // 2, (x0 + x1) // 2, "NO DATA", anchor="centre")
        return
    lx = [math.log10(p["ms"]) for p in pts]
    xlo, xhi = math.floor(min(lx) * 4) / 4 - 0.1, math.ceil(max(lx) * 4) / 4 + 0.1
    errs = [p["error"] for p in pts] + [v for v, _ in refs]
    elo, ehi = min(0.0, min(errs)), max(errs) * 1.1 or 1.0

    def xy(p):
        return (y1 - (p["error"] - elo) / (ehi - elo) * (y1 - y0),
                x0 + (math.log10(p["ms"]) - xlo) / (xhi - xlo) * (x1 - x0))

    for e in range(math.floor(xlo), math.ceil(xhi) + 1):
        for m in (1, 2, 5):
            v = math.log10(m) + e
            if xlo <= v <= xhi:
                xx = x0 + (v - xlo) / (xhi - xlo) * (x1 - x0)
                c.rect(y1, xx, y1 + 4, xx, (0, 0, 0))
                c.text(y1 + 8, xx, _fmt(m * 10.0 ** e), anchor="centre")
    for v in _nice_ticks(elo, ehi):
        yy = y1 - (v - elo) / (ehi - elo) * (y1 - y0)
        c.rect(yy, x0 - 4, yy, x0, (0, 0, 0))
        c.text(yy - 5, x0 - 8, _fmt(v), anchor="right")
    c.text(y1 + 28, (x0 + x1) // 2, xlabel, anchor="centre")
    c.text(y0 - 18, left + 10, ylabel)
    for key in {p.get("front") for p in pts}:  # one line per frontier
        front = sorted((p for p in pts if p.get("frontier") and p.get("front") == key),
                       key=lambda p: p["ms"])
        for a, b in zip(front, front[1:]):
            (ya, xa), (yb, xb) = xy(a), xy(b)
            c.line(ya, xa, yb, xb, FRONTIER, width=2)
    for p in pts:
        y, x = xy(p)
        colour = PALETTE[kinds.index(p["kind"]) % len(PALETTE)]
        c.rect(y - 3, x - 3, y + 3, x + 3, colour)
        if p.get("frontier"):
            c.ring(y, x, 7, FRONTIER)
            c.text(y - 16, x + 6, p.get("label", "")[:24], scale=1)
    for v, label in refs:
        yy = y1 - (v - elo) / (ehi - elo) * (y1 - y0)
        for xx in range(int(x0) + 2, int(x1), 8):
            c.rect(yy, xx, yy, xx + 3, (128, 128, 128))
        c.text(yy - 9, x1, label[:40], (96, 96, 96), scale=1, anchor="right")
    for i, kind in enumerate(kinds):  # bottom left: the fast and accurate corner stays empty
        yy = y1 - 14 * (len(kinds) - i) - 4
        c.rect(yy, x0 + 10, yy + 6, x0 + 16, PALETTE[i % len(PALETTE)])
        c.text(yy, x0 + 22, kind[:34], scale=1)


def plot(path, panels, footer: str = "") -> None:
    """panels: (title, xlabel, ylabel, points[, refs]) tuples, drawn side by side."""
    ph, pw = 420, 520
    c = Canvas(ph + 30, pw * max(len(panels), 1))
    for i, (title, xlabel, ylabel, points, *refs) in enumerate(panels):
        kinds = sorted({p["kind"] for p in points})
        draw_panel(c, 10, i * pw, ph, pw, title, xlabel, ylabel, points, kinds,
                   refs[0] if refs else ())
    c.text(ph + 12, 10, footer[:150], scale=1)
    write_png(path, c.px)
