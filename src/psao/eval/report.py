"""Benchmark outputs: the Table 1 style table (Markdown and CSV), charts and side-by-side images.

A result row is a dict with: scene, method ("PSAO-N", a baseline: "SSAO", "GTAO", ..., or the video
competitor "Video-BM"), density (N or None), tick_hz (or None),
psnr, ssim, flip, stream_mbit_s, snapshot_mb, server_ms_tick, client_ms_frame, points, holes. Video rows
(video: True) stream at tick_hz = their frame rate; their server_ms_tick is per client per frame.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from psao.eval.metrics import magma

CSV_FIELDS = ["scene", "method", "density", "tick_hz", "psnr", "ssim", "flip", "bias", "stream_mbit_s", "snapshot_mb",
              "updates_per_s", "server_ms_tick", "anim_tick_ms", "animated", "stream_animated", "bake_trace_s", "client_ms_frame", "points", "holes", "frames", "spp",
              "weight_bytes", "train_s", "trained_on"]


def format_cell(v, digits: int) -> str:
    """A table cell: v with `digits` decimals, or "-" where there is no finite value."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{digits}f}"


def write_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, CSV_FIELDS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") if r.get(k) is not None else "" for k in CSV_FIELDS})


def table_rows(rows: list[dict]) -> list[dict]:
    """One row per scene and method: quality, and the stream at every tick rate measured."""
    out: dict[tuple, dict] = {}
    for r in rows:
        key = (r["scene"], r["method"])
        row = out.setdefault(key, {**r, "mbit": {}})
        if r.get("tick_hz"):
            row["mbit"][r["tick_hz"]] = r.get("stream_mbit_s")
            row["server_ms_tick"] = r.get("server_ms_tick")
    return list(out.values())


def markdown_table(rows: list[dict]) -> str:
    """Table 1 of the paper, per scene: PSNR, SSIM, FLIP and Mbit/s for SSAO and PSAO at each density."""
    merged = table_rows(rows)
    rates = sorted({hz for r in merged for hz in r["mbit"]})
    ups = {}  # achieved updates per second at the highest rate (an animated server may fall behind)
    for r in rows:
        if rates and r.get("tick_hz") == rates[-1]:
            ups[(r["scene"], r["method"])] = r.get("updates_per_s")
    head = ["scene", "method", "PSNR (dB) ↑", "SSIM ↑", "FLIP ↓", "mean AO bias"] + [f"Mbit/s, --tick-hz {hz:g}" for hz in rates] + \
        (["updates/s achieved"] if rates else []) + ["snapshot MB", "weights kB", "client ms/frame", "server ms/tick",
                                                     "bake trace s", "points"]
    animated = any(r.get("anim_tick_ms") is not None for r in merged)
    if animated:
        head += ["animated tick ms"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in merged:
        cells = [r["scene"], r["method"], format_cell(r["psnr"], 2), format_cell(r["ssim"], 3), format_cell(r["flip"], 3),
                 f"{round(r['bias'], 3) + 0.0:+.3f}" if r.get("bias") is not None else "-"]
        streams = r["density"] or r.get("video")  # PSAO and the video competitor send; SSAO does not
        cells += [format_cell(r["mbit"].get(hz), 3) if streams else "-" for hz in rates]
        if rates:
            cells.append(format_cell(ups.get((r["scene"], r["method"])), 1) if r["density"] else "-")
        cells += [format_cell(r.get("snapshot_mb"), 2) if r["density"] else "-",
                  format_cell(r["weight_bytes"] / 1e3, 1) if r.get("weight_bytes") else "-", format_cell(r.get("client_ms_frame"), 1),
                  format_cell(r.get("server_ms_tick"), 2) if streams else "-",
                  format_cell(r.get("bake_trace_s"), 1) if r["density"] else "-",
                  f"{r['points']:,}" if r.get("points") else "-"]
        if animated:
            cells.append(format_cell(r.get("anim_tick_ms"), 1) if r.get("anim_tick_ms") is not None else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def scene_styles(rows):
    """A chart colour per scene of the rows (the same scene, the same colour in every chart)."""
    scenes = sorted({r["scene"] for r in rows})
    colours = dict(zip(scenes, ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown",
                                "tab:pink", "tab:gray"] * 4))
    return scenes, colours


BASELINE_MARKERS = {"SSAO": "s", "GTAO": "^", "NNAO": "D", "MLP": "P", "AOGAN": "X"}


def runtime_chart(rows: list[dict], path: Path) -> None:
    """FLIP and PSNR against server ms per tick (PSAO) and client ms per frame (PSAO and every baseline)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    merged = table_rows(rows)
    scenes, colours = scene_styles(merged)
    fig, axes = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    for r in merged:  # an animated evaluation ran the real tick: plot that one
        if r.get("anim_tick_ms") is not None:
            r["server_ms_tick"] = r["anim_tick_ms"]
    for col, (xkey, xlabel) in enumerate([("server_ms_tick", "server ms per tick (PSAO)"),
                                          ("bake_trace_s", "server s to trace the whole grid (bake)"),
                                          ("client_ms_frame", "client GPU ms per frame")]):
        for row, (ykey, ylabel) in enumerate([("flip", "FLIP (lower is better)"), ("psnr", "PSNR dB (higher is better)")]):
            ax = axes[row, col]
            for s in scenes:
                for method_kind, marker in (("PSAO", "o"), *BASELINE_MARKERS.items()):
                    pts = [r for r in merged if r["scene"] == s and (r["method"] == method_kind or (
                        method_kind == "PSAO" and r["method"].startswith("PSAO-")))]
                    if xkey != "client_ms_frame" and method_kind != "PSAO":
                        continue  # the baselines have no server
                    pts = [r for r in pts if r.get(xkey) is not None and math.isfinite(r[xkey])]
                    pts.sort(key=lambda r: r.get("density") or 0)
                    if not pts:
                        continue
                    ax.plot([r[xkey] for r in pts], [r[ykey] for r in pts], marker=marker, color=colours[s],
                            linestyle="-" if method_kind == "PSAO" else "none", label=f"{s} {method_kind}")
                    for r in pts:
                        if r.get("density"):
                            ax.annotate(f"N={r['density']:g}", (r[xkey], r[ykey]), fontsize=7,
                                        textcoords="offset points", xytext=(3, 3))
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3)
    ticks = [r.get("server_ms_tick") for r in merged if r.get("density")]
    if ticks and all(t is not None and math.isfinite(t) and t < 0.5 for t in ticks):
        axes[0, 0].text(0.5, 0.5, "static scenes: the server traces\nnothing per tick (< 0.5 ms)",
                        transform=axes[0, 0].transAxes, ha="center", fontsize=9, alpha=0.7)
    handles, labels = axes[0, 2].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside right center", fontsize=8)
    fig.suptitle("Runtime versus error against RTAO (circles PSAO-N; squares SSAO, triangles GTAO, diamonds NNAO, "
                 "plus MLP, crosses AOGAN (CPU ms))")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def bandwidth_chart(rows: list[dict], path: Path) -> None:
    """PSNR and FLIP against the data PSAO sends: the snapshot (MB, once per connection) per density, one
    line per scene, SSAO as a dotted line (it sends nothing); and the stream after the snapshot (Mbit/s)
    against the server's tick rate, per scene and density."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    merged = table_rows(rows)
    scenes, colours = scene_styles(merged)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2), constrained_layout=True)
    for ax, (ykey, ylabel) in zip(axes[:2], [("psnr", "PSNR dB (higher is better)"), ("flip", "FLIP (lower is better)")]):
        for s in scenes:
            pts = sorted([r for r in merged if r["scene"] == s and r.get("density") and r.get("snapshot_mb")],
                         key=lambda r: r["density"])
            if pts:
                ax.plot([r["snapshot_mb"] for r in pts], [r[ykey] for r in pts], marker="o", color=colours[s],
                        label=f"{s} PSAO")
                for r in pts:
                    ax.annotate(f"N={r['density']:g}", (r["snapshot_mb"], r[ykey]), fontsize=7,
                                textcoords="offset points", xytext=(3, 3))
            for r in merged:
                if r["scene"] == s and r["method"] == "SSAO":
                    ax.axhline(r[ykey], color=colours[s], linestyle=":", linewidth=1)
        ax.set_xscale("log")
        ax.set_xlabel("PSAO snapshot MB (log)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, which="both")
    ax = axes[2]
    for s in scenes:
        ps = [r for r in rows if r["scene"] == s and r.get("density") and r.get("tick_hz")]
        for d in sorted({r["density"] for r in ps}):
            pts = sorted([r for r in ps if r["density"] == d], key=lambda r: r["tick_hz"])
            ax.plot([r["tick_hz"] for r in pts], [r["stream_mbit_s"] for r in pts], marker="o", color=colours[s],
                    alpha=0.5 + 0.5 * (d == max(r["density"] for r in ps)), label=f"{s} N={d:g}")
    ax.set_yscale("symlog", linthresh=0.01)
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("server tick rate (Hz)")
    ax.set_ylabel("stream Mbit/s after the snapshot")
    ax.grid(alpha=0.3, which="both")
    handles, labels = axes[0].get_legend_handles_labels()
    h2, l2 = axes[2].get_legend_handles_labels()
    if handles or h2:
        fig.legend(handles + h2, labels + l2, loc="outside right center", fontsize=7)
    fig.suptitle("Bandwidth versus quality (dotted: SSAO, which sends nothing; a static scene streams ~0 after its snapshot)")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _grey(img: np.ndarray) -> np.ndarray:
    g = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=2)


def _label(panel: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw

    im = Image.fromarray(panel)
    d = ImageDraw.Draw(im)
    d.rectangle([0, 0, 7 * len(text) + 8, 16], fill=(0, 0, 0))
    d.text((4, 2), text, fill=(255, 255, 255))
    return np.asarray(im)


def side_by_side(reference: np.ndarray, methods: list[tuple[str, np.ndarray, np.ndarray, dict]], path: Path,
                 scale: float = 1.0) -> None:
    """Top row: RTAO, then each method's AO; bottom row: each method's FLIP error map (magma), labelled
    with its scores. `scale` < 1 shrinks the PNG (documentation images)."""
    from PIL import Image

    top = [_label(_grey(reference), "RTAO reference")]
    bottom = [_label(np.zeros_like(top[0]), "FLIP error maps below: magma, 0 (black) to 1")]
    for name, ao, fmap, s in methods:
        top.append(_label(_grey(ao), name))
        bottom.append(_label(magma(fmap), f"FLIP {name}: {s['flip']:.3f}  PSNR {s['psnr']:.1f} dB"))
    img = np.vstack([np.hstack(top), np.hstack(bottom)])
    im = Image.fromarray(img)
    if scale != 1.0:
        im = im.resize((max(1, int(im.width * scale)), max(1, int(im.height * scale))), Image.LANCZOS)
    im.save(path, optimize=True)
