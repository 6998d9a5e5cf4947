"""Outputs of `psao bench --video`: tables (Markdown), JSON, charts and side-by-side frames.

Rows come from video_bench.compare_scene: kind "video" (method Video-BM or Video-raw, the server's AO
before encoding) or "psao" (PSAO-N), each at one latency, plain or reprojected (video only).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from psao.eval.errors import EvalError
from psao.eval.report import format_cell, scene_styles, side_by_side


def _lat0(rows):
    return min(r["latency_ms"] for r in rows)


def _scene_methods(rows: list[dict]) -> list[tuple[str, str]]:
    """(scene, method) pairs in the order they first appear."""
    return list(dict.fromkeys((r["scene"], r["method"]) for r in rows))


def table1_markdown(rows: list[dict]) -> str:
    """Quality at the smallest latency, Mbit/s and the server's cost per client."""
    L0 = _lat0(rows)
    head = ["scene", "method", "Mbit/s", "PSNR (dB) ↑", "SSIM ↑", "FLIP ↓", "decoded vs rendered dB",
            "server rays / client / frame",
            "trace ms / client / frame", "denoise ms / client / frame", "encode ms / client / frame", "server ms / tick (shared)",
            "send ms / client / tick", "snapshot MB"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        if r["latency_ms"] != L0 or r["reprojected"]:
            continue
        v = r["kind"] == "video"
        lines.append("| " + " | ".join([
            r["scene"], r["method"], format_cell(r.get("mbit_s"), 3), format_cell(r["psnr"], 2), format_cell(r["ssim"], 3),
            format_cell(r["flip"], 3), format_cell(r.get("codec_psnr"), 1), f"{r['rays_per_frame']:,.0f}" if v else "-",
            format_cell(r.get("trace_ms_frame"), 1) if v else "-", format_cell(r.get("filter_ms_frame"), 1) if v else "-",
            format_cell(r.get("encode_ms_frame"), 2) if v else "-",
            "-" if v else format_cell(r.get("server_ms_tick"), 1), "-" if v else format_cell(r.get("send_ms_tick"), 2),
            "-" if v else format_cell(r.get("snapshot_mb"), 2)]) + " |")
    return "\n".join(lines) + "\n"


def latency_markdown(rows: list[dict]) -> str:
    """PSNR / FLIP per method at every latency (video plain and reprojected)."""
    lats = sorted({r["latency_ms"] for r in rows})
    head = ["scene", "method"] + [f"{L:g} ms" for L in lats] + [f"{L:g} ms reproj." for L in lats if L > 0]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, method in _scene_methods(rows):
        got = {(r["latency_ms"], r["reprojected"]): r for r in rows if r["scene"] == scene and r["method"] == method}
        cells = [scene, method]
        for L, rep in [(L, False) for L in lats] + [(L, True) for L in lats if L > 0]:
            r = got.get((L, rep))
            cells.append(f"{r['psnr']:.2f} / {r['flip']:.3f}" if r else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def clients_markdown(cost_rows: list[dict]) -> str:
    counts = sorted({r["clients"] for r in cost_rows})
    head = ["scene", "method", "Mbit/s per client"] + [f"ms / client @{n}" for n in counts] + \
        [f"total ms @{n} (modelled)" for n in counts]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene, method in _scene_methods(cost_rows):
        got = {r["clients"]: r for r in cost_rows if r["scene"] == scene and r["method"] == method}
        first = next(iter(got.values()))
        lines.append("| " + " | ".join([scene, method, format_cell(first["mbit_s"], 3)]
                                       + [format_cell(got[n]["ms_per_client"], 2) for n in counts]
                                       + [format_cell(got[n]["ms_total"], 1) for n in counts]) + " |")
    return "\n".join(lines) + "\n"


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def bandwidth_chart(rows: list[dict], path: Path) -> None:
    """Per scene (columns): PSNR and FLIP (rows) against Mbit/s, log scale; PSAO over its densities and
    the video over its bitrates, solid at the smallest latency, dashed at the largest (video:
    reprojected). The uncompressed video's quality is a dotted line."""
    plt = _plt()
    scenes, _ = scene_styles(rows)
    L0, L1 = _lat0(rows), max(r["latency_ms"] for r in rows)
    fig, axes = plt.subplots(2, len(scenes), figsize=(4.6 * len(scenes), 7), squeeze=False, constrained_layout=True)
    for col, s in enumerate(scenes):
        for row, (key, label) in enumerate([("psnr", "PSNR dB (higher is better)"), ("flip", "FLIP (lower is better)")]):
            ax = axes[row, col]
            for kind, colour, marker in (("psao", "tab:blue", "o"), ("video", "tab:red", "s")):
                for L, rep, style in ((L0, False, "-"), (L1, kind == "video" and L1 > 0, "--")):
                    if style == "--" and L1 == L0:
                        continue
                    pts = [r for r in rows if r["scene"] == s and r["kind"] == kind and r["latency_ms"] == L
                           and r["reprojected"] == rep and r.get("mbit_s")]
                    pts.sort(key=lambda r: r["mbit_s"])
                    if not pts:
                        continue
                    x = [max(r["mbit_s"], 1e-3) for r in pts]
                    ax.plot(x, [r[key] for r in pts], marker=marker, linestyle=style, color=colour,
                            label=f"{'PSAO' if kind == 'psao' else 'video'} {L:g} ms{' reproj.' if rep else ''}")
                    if style == "-":
                        for r, xv in zip(pts, x):
                            ax.annotate(r["method"].split("-", 1)[1], (xv, r[key]), fontsize=7,
                                        textcoords="offset points", xytext=(3, 3))
            raw = [r for r in rows if r["scene"] == s and r["method"] == "Video-raw" and r["latency_ms"] == L0]
            if raw:
                ax.axhline(raw[0][key], color="tab:red", linestyle=":", linewidth=1, label="video before encoding")
            idle = [r for r in rows if r["scene"] == s and r["kind"] == "psao" and r["latency_ms"] == L0
                    and r.get("mbit_s") == 0]  # a static scene: nothing streamed after the snapshot
            if idle:
                top = max(idle, key=lambda r: r.get("density") or 0)
                ax.axhline(top[key], color="tab:blue", linestyle=":", linewidth=1,
                           label="PSAO, densest, 0 Mbit/s after its snapshot")
                ax.annotate(top["method"], (0.02, top[key]), xycoords=("axes fraction", "data"), fontsize=7,
                            color="tab:blue", textcoords="offset points", xytext=(0, 3))
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(plt.NullFormatter())
            ax.set_xlabel("Mbit/s (log)")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3, which="both")
            if row == 0:
                ax.set_title(s)
    legend = {}  # every panel's lines, once per label (a static scene's panel has no PSAO curve)
    for ax in axes.flat:
        for h, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, h)
    if legend:
        fig.legend(list(legend.values()), list(legend), loc="outside lower center", ncol=6, fontsize=8)
    fig.suptitle("Quality against bandwidth: PSAO (densities) and per-client AO video (bitrates)")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def latency_chart(rows: list[dict], path: Path) -> None:
    """Per scene: PSNR against latency for each PSAO density and each video bitrate (plain solid,
    reprojected dashed)."""
    plt = _plt()
    scenes, _ = scene_styles(rows)
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.6 * len(scenes), 4), squeeze=False, constrained_layout=True)
    cmap = plt.get_cmap("viridis")
    for col, s in enumerate(scenes):
        ax = axes[0, col]
        methods = []
        for r in rows:
            if r["scene"] == s and r["method"] not in methods and r["method"] != "Video-raw":
                methods.append(r["method"])
        for k, m in enumerate(methods):
            kind = "psao" if m.startswith("PSAO") else "video"
            colour = cmap(k / max(len(methods) - 1, 1))
            for rep, style in ((False, "-"), (True, "--")):
                pts = sorted([r for r in rows if r["scene"] == s and r["method"] == m and
                              (r["reprojected"] == rep or (rep and r["latency_ms"] == 0))],
                             key=lambda r: r["latency_ms"])
                if rep and (kind == "psao" or len(pts) < 2):
                    continue
                ax.plot([r["latency_ms"] for r in pts], [r["psnr"] for r in pts], style,
                        marker="o" if kind == "psao" else "s", color=colour,
                        label=f"{m}{' reproj.' if rep else ''}")
        ax.set_xlabel("latency ms")
        ax.set_ylabel("PSNR dB")
        ax.set_title(s)
        ax.grid(alpha=0.3)
    handles, labels = axes[0, -1].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside right center", fontsize=7)
    fig.suptitle("Quality against latency (circles PSAO, squares video; dashed: reprojected with the client's depth)")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def clients_chart(cost_rows: list[dict], path: Path) -> None:
    """Server milliseconds per client (per video frame / per PSAO tick) and modelled total against the
    number of clients, log-log, one line per scene and method."""
    plt = _plt()
    scenes, colours = scene_styles(cost_rows)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
    idle = []
    for s in scenes:
        methods = [m for _, m in _scene_methods([r for r in cost_rows if r["scene"] == s])]
        video = [m for m in methods if not m.startswith("PSAO")]
        # The video's cost hardly depends on its bitrate (tracing dominates): one line, the middle bitrate.
        shown = [m for m in methods if m.startswith("PSAO")] + video[len(video) // 2:len(video) // 2 + 1]
        for m in shown:
            pts = sorted([r for r in cost_rows if r["scene"] == s and r["method"] == m], key=lambda r: r["clients"])
            if all(r["ms_total"] <= 0 for r in pts):
                idle.append(f"{s} {m}")
                continue
            style = "-" if pts[0]["kind"] == "psao" else "--"
            for ax, key in zip(axes, ("ms_per_client", "ms_total")):
                ax.plot([r["clients"] for r in pts], [max(r[key], 1e-3) for r in pts], style,
                        marker="o" if style == "-" else "s", color=colours[s], label=f"{s} {m}")
    for ax, label in zip(axes, ("server ms per client per frame / tick (measured per client)",
                                "server ms per frame / tick, all clients (modelled)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("clients")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both")
    if idle:
        axes[0].text(0.02, 0.02, "0 ms per tick (static scene, nothing to trace): " + ", ".join(idle),
                     transform=axes[0].transAxes, fontsize=7, wrap=True)
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(handles, labels, loc="outside right center", fontsize=7)
    fig.suptitle("Server cost with many clients (solid PSAO: one tick shared; dashed video: one render per client)")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_outputs(rows: list[dict], images: list[dict], cost_rows: list[dict], out: Path,
                  image_scale: float = 1.0) -> list[Path]:
    out = Path(out)
    text = "## Video vs PSAO at the smallest latency\n\n" + table1_markdown(rows) + \
        "\n## PSNR / FLIP against latency\n\n" + latency_markdown(rows) + \
        "\n## Server cost against clients\n\n" + clients_markdown(cost_rows)
    (out / "video_table.md").write_text(text)
    (out / "video_results.json").write_text(json.dumps({"rows": rows, "clients": cost_rows}, indent=1,
                                                       default=_json_default))
    written = [out / "video_table.md", out / "video_results.json"]
    for name, draw, data in (("video_bandwidth_quality.png", bandwidth_chart, rows),
                             ("video_latency.png", latency_chart, rows), ("video_clients.png", clients_chart, cost_rows)):
        draw(data, out / name)
        written.append(out / name)
    for im in images:
        p = out / f"frame_video_{im['scene']}.png"
        side_by_side(im["reference"], im["panels"], p, scale=image_scale)
        written.append(p)
    return written


def _json_default(v):
    if hasattr(v, "item"):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    raise TypeError(f"not JSON serialisable: {type(v)}")


# Per-client server costs of a row: measured by a short run under the benchmark lock, merged into the
# quality runs' rows (quality and bytes do not depend on machine load; milliseconds do).
VIDEO_COST_KEYS = ("rays_per_frame", "trace_ms_frame", "filter_ms_frame", "encode_ms_frame")
PSAO_COST_KEYS = ("server_ms_tick", "send_ms_tick", "snapshot_encode_s")


def merge_costs(rows: list[dict], cost_rows: list[dict], source: str) -> list[dict]:
    """The rows with their server costs replaced by those of the same scene and method in cost_rows
    (smallest latency, not reprojected), and `costs_from` naming where they came from; a row with no
    match keeps none (NaN), so no figure measured under load is shown as if measured under the lock."""
    L0 = _lat0(cost_rows)
    source_of = {(r["scene"], r["method"]): r for r in cost_rows if r["latency_ms"] == L0 and not r["reprojected"]}
    out = []
    for r in rows:
        keys = VIDEO_COST_KEYS if r["kind"] == "video" else PSAO_COST_KEYS
        src = source_of.get((r["scene"], r["method"]))
        out.append({**r, **{k: (src.get(k) if src else float("nan")) for k in keys},
                    "costs_from": source if src else None})
    return out


def read_results(folder: Path) -> dict:
    """video_results.json of a `psao bench` run with the video method: {"rows": [...], "clients": [...]}."""
    path = Path(folder) / "video_results.json"
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise EvalError(f"{path}: not a video benchmark result ({exc})") from None
