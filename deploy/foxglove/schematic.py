"""Draw a schematic of a Foxglove layout, filled with a vistrack MCAP recording (matplotlib).

The machine vistrack is built on has no Foxglove app, so the README's picture of the layout is
drawn, not captured: each panel of ``vistrack.json`` where the layout puts it, with its title
and what it shows from a real recording (the camera frame with its two overlays, the plotted
fields against time, the last parameters). Foxglove's own look differs; the picture says so.

    python deploy/foxglove/schematic.py run.mcap deploy/foxglove/layout-schematic.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after choosing the backend
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Rectangle  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

HERE = Path(__file__).resolve().parent
TITLE_H = 0.035  # height of a panel's title bar, figure fraction
PAD = 0.004


def read(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """topic -> [(log time ns, decoded message)] of an MCAP file (mcap-ros2-support)."""
    topics: dict[str, list[tuple[int, Any]]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, obj in reader.iter_decoded_messages(log_time_order=False):
            topics.setdefault(channel.topic, []).append((message.log_time, obj))
    return topics


def rects(node: Any, x: float, y: float, w: float, h: float) -> dict[str, tuple]:
    """Panel id -> (x, y, w, h) in figure fractions, as Foxglove splits its mosaic."""
    if isinstance(node, str):
        return {node: (x, y, w, h)}
    f = node.get("splitPercentage", 50) / 100
    if node["direction"] == "row":
        return {**rects(node["first"], x, y, w * f, h),
                **rects(node["second"], x + w * f, y, w * (1 - f), h)}
    return {**rects(node["first"], x, y + h * (1 - f), w, h * f),
            **rects(node["second"], x, y, w, h * (1 - f))}


def stamp(obj: Any) -> int:
    return obj.header.stamp.sec * 10**9 + obj.header.stamp.nanosec


def field(obj: Any, path: str) -> float:
    for name in path.split("."):
        obj = getattr(obj, name)
    return float(obj)


def draw_image(ax, config: dict, data: dict, t_frac: float = 0.6) -> None:
    mode = config["imageMode"]
    frames = data.get(mode["imageTopic"], [])
    if not frames:
        ax.text(0.5, 0.5, "no frame in the recording", ha="center", transform=ax.transAxes)
        return
    _, img = frames[int(t_frac * (len(frames) - 1))]
    pixels = np.frombuffer(img.data, np.uint8).reshape(img.height, img.step)[:, :img.width]
    ax.imshow(pixels, cmap="gray", vmin=0, vmax=255)
    for topic, settings in mode.get("annotations", {}).items():
        if not settings.get("visible"):
            continue
        match = [m for _, m in data.get(topic, []) if stamp(m) == stamp(img)]
        for m in match:
            color = (m.outline_color.r, m.outline_color.g, m.outline_color.b,
                     m.outline_color.a)
            if m.type == 4:  # POINTS
                ax.scatter([p.x for p in m.points], [p.y for p in m.points], s=m.scale ** 2,
                           color=color)
            elif m.type == 0:  # CIRCLE, radius = scale
                ax.add_patch(Circle((m.position.x, m.position.y), m.scale, fill=False,
                                    color=color, linewidth=1.5))
                ax.plot(m.position.x, m.position.y, "+", color=color, markersize=10)
    ax.set_axis_off()


def draw_plot(ax, config: dict, data: dict) -> None:
    t0 = min((t for series in data.values() for t, _ in series), default=0)
    for s in config["paths"]:
        topic, _, path = s["value"].partition(".")
        rows = data.get(topic, [])
        ax.plot([(t - t0) / 1e9 for t, _ in rows], [field(m, path) for _, m in rows],
                color=s.get("color"), label=s.get("label", path), linewidth=1)
    ax.legend(fontsize=7, loc="upper right")
    ax.tick_params(labelsize=7)
    ax.set_xlabel("s", fontsize=7, labelpad=0)
    ax.grid(alpha=0.3)


def _lines(obj: Any, indent: str = "") -> list[str]:
    out = []
    for name in getattr(obj, "__slots__", []):
        value = getattr(obj, name)
        if hasattr(value, "__slots__"):
            out += [f"{indent}{name}:"] + _lines(value, indent + "  ")
        else:
            out.append(f"{indent}{name}: {value}")
    return out


def draw_raw(ax, config: dict, data: dict) -> None:
    rows = data.get(config["topicPath"], [])
    text = "\n".join(_lines(rows[-1][1])) if rows else "no message in the recording"
    ax.text(0.01, 0.98, text, va="top", ha="left", family="monospace", fontsize=7,
            transform=ax.transAxes)
    ax.set_axis_off()


DRAW = {"Image": draw_image, "Plot": draw_plot, "RawMessages": draw_raw}


def schematic(recording: Path, out: Path, layout: Path = HERE / "vistrack.json") -> None:
    spec = json.loads(layout.read_text())
    data = read(recording)
    fig = plt.figure(figsize=(16, 9), dpi=100)
    fig.text(0.005, 0.985, f"SCHEMATIC of the Foxglove layout {layout.name}, not a screenshot: "
             "each panel where the layout places it, drawn with matplotlib from a vistrack MCAP "
             f"recording ({recording.name})", fontsize=10, va="top", weight="bold")
    for panel, (x, y, w, h) in rects(spec["layout"], 0.0, 0.0, 1.0, 0.96).items():
        kind = panel.split("!")[0]
        config = spec["configById"][panel]
        fig.patches.append(Rectangle((x + PAD, y + PAD), w - 2 * PAD, h - 2 * PAD,
                                     transform=fig.transFigure, fill=False, color="#444"))
        fig.text(x + 2 * PAD, y + h - 2 * PAD, f"{kind}: {config.get('foxglovePanelTitle', '')}",
                 fontsize=9, va="top", color="#222", weight="bold")
        left, bottom = 0.035 if kind == "Plot" else 0.005, 0.04 if kind == "Plot" else 0.005
        ax = fig.add_axes((x + left * (kind == "Plot") + 2 * PAD, y + bottom + 2 * PAD,
                           w - left - 4 * PAD, h - TITLE_H - bottom - 4 * PAD))
        DRAW[kind](ax, config, data)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path, help="an MCAP file of vistrack record")
    parser.add_argument("out", type=Path, help="the PNG to write")
    parser.add_argument("--layout", type=Path, default=HERE / "vistrack.json")
    args = parser.parse_args()
    schematic(args.recording, args.out, args.layout)


if __name__ == "__main__":
    main()
