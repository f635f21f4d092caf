"""Where measurements are written: one Markdown file (and its JSON) per benchmark or evaluation,
saying the command that produced it and the machine it ran on, and its plots (matplotlib).

    report.write(ROOT / "bench/results/yale", "Real faces: CroppedYale", command, body_md, data)

The README and the model cards link these files; nothing else carries the figures.
"""

from __future__ import annotations

import datetime
import json
import os
import pathlib
import platform
import textwrap


def cpu_name() -> str:
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict:
    """The machine a figure was measured on, with the load that shared it."""
    import onnxruntime as ort

    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {"platform": platform.platform(), "cpu": cpu_name(), "cores": os.cpu_count(),
            "load_avg_1_5_15": [round(x, 2) for x in load],
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "python": platform.python_version(), "onnxruntime": ort.__version__,
            "providers": ort.get_available_providers()}


def machine_line(m: dict) -> str:
    end = m.get("load_avg_end")
    return (f"{m['cpu']}, {m['cores']} cores, {m['platform']}; onnxruntime {m['onnxruntime']} "
            f"({', '.join(m['providers'])}); load average {m['load_avg_1_5_15'][0]} at the start"
            + (f", {end} at the end" if end is not None else "") + f"; {m['date']}")


def write(stem: str | os.PathLike, title: str, command: str, machine_text: str, body: str,
          data=None) -> pathlib.Path:
    """Write ``stem.md`` (title, command, machine, then ``body``) and, given ``data``,
    ``stem.json``. Returns the Markdown path."""
    stem = pathlib.Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    md = stem.with_name(stem.name + ".md")
    md.write_text(f"# {title}\n\nCommand: `{command}`\n\nMachine: {machine_text}\n\n"
                  f"{body.strip()}\n", encoding="utf-8")
    if data is not None:
        stem.with_name(stem.name + ".json").write_text(json.dumps(data, indent=2) + "\n",
                                                      encoding="utf-8")
    return md


class Lines:
    """A ``print`` that also keeps what it printed, for a report of the same text."""

    def __init__(self):
        self.lines: list[str] = []

    def __call__(self, text="", **_):
        print(text, flush=True)
        self.lines.append(str(text))

    def text(self) -> str:
        return "\n".join(self.lines)


# Plots: matplotlib's tab10 colours in order, without its red, which marks what a plot is about
# (the Pareto frontier).
COLOURS = ("C0", "C1", "C2", "C4", "C5", "C6", "C7", "C8", "C9")
HIGHLIGHT = "#d62728"  # tab10's red
PANEL_PIXELS = (520, 450)  # width, height of one panel
DPI = 100


def figure(panels: int, footer: str = ""):
    """(figure, axes): ``panels`` matplotlib axes side by side, PANEL_PIXELS each, with ``footer``
    (the machine, what the plot shows) in small type below them. Save with ``figure.savefig``.
    Built without pyplot: no global state and no display needed."""
    from matplotlib.figure import Figure

    n = max(int(panels), 1)
    fig = Figure(figsize=(PANEL_PIXELS[0] * n / DPI, PANEL_PIXELS[1] / DPI), dpi=DPI,
                 layout="constrained")
    axes = fig.subplots(1, n, squeeze=False)[0]
    if footer:  # wrapped to the figure's width (about 100 characters of 7-point type a panel)
        fig.supxlabel(textwrap.fill(footer, 100 * n), fontsize=7, color="dimgrey")
    return fig, list(axes)
