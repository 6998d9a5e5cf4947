"""docs/results.md's tables, generated from the benchmarks' JSON output.

Each table of docs/results.md that this script owns sits between two markers,

    <!-- report:table1 -->
    ... generated: the table, then the command and commit that produced its data ...
    <!-- /report:table1 -->

and its data is one file, docs/data/ID.json: {"id", "command", "commit", "rows"}, where "rows" is what the
benchmark wrote (`psao bench`'s results.json, bench_scenes' bench_scenes.json), as a list of rows
(bench_progressive's scenes, bench_links' runs). The sections of the other benchmarks come from one
`python -m benchmarks.run_all --quick --out OUT` run: their rows are the benchmark's entry of
OUT/run_all.json (its command, exit status and verdicts), then what the benchmark wrote under OUT/NAME
(bench_clients' table, bench_video's results, a benchmark's summary of figures). The data files are kept in
the repository so that the page can be checked against them (`check`, run by the tests) and regenerated
without re-running hours of benchmarks.

    python -m benchmarks.report collect ID OUT_DIR   # after running SECTIONS[ID].command with --out OUT_DIR
                                                     # (ID run_all: every section of a run_all --out run)
        [--commit C]                                 # the commit the run was made at, when not HEAD
    python -m benchmarks.report write                # rewrite docs/results.md's generated blocks
    python -m benchmarks.report check                # exit 1 if docs/results.md differs from its data

`collect` records the commit given by --commit, else the run's from OUT_DIR/run.json (written by
`psao bench`) or OUT_DIR/run_all.json, else the repository's HEAD, marked "+local changes" when the working
tree differs from it.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from psao.eval.bench_cli import source_commit
from psao.eval.report import markdown_table

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results.md"
DATA = ROOT / "docs" / "data"


def table(head: list[str], lines: list[list[str]]) -> str:
    """A markdown table of the header and the lines' cells."""
    return "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head),
                      *("| " + " | ".join(cells) + " |" for cells in lines)]) + "\n"


def scenes_table(rows: list[dict]) -> str:
    """bench_scenes' rows: one line per model and density scale."""
    from benchmarks.bench_scenes import HEADER_COLUMNS, table_cells

    return table(list(HEADER_COLUMNS), [table_cells(r) for r in rows])


def span(values: list[float], fmt: str) -> str:
    """'a to b' of the values formatted, or the one value when they all format alike."""
    lo, hi = format(min(values), fmt), format(max(values), fmt)
    return lo if lo == hi else f"{lo} to {hi}"


def method_summary(rows: list[dict]) -> str:
    """What `psao bench`'s rows say, in figures computed from them: PSAO at each scene's highest density
    against every other method, its bias, what its higher density gains over its lower, and its frame cost."""
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    by = {(r["scene"], r["method"]): r for r in rows}
    psao = {s: sorted((r for r in rows if r["scene"] == s and r.get("density")), key=lambda r: r["density"])
            for s in scenes}
    psao = {s: ranked for s, ranked in psao.items() if ranked}
    if not psao:
        return ""
    tops = sorted({ranked[-1]["density"] for ranked in psao.values()}, reverse=True)
    top = (f"PSAO-{tops[0]:g}" if len(tops) == 1 else
           "PSAO at each scene's highest density (" + ", ".join(f"{d:g}" for d in tops) + ")")
    lines = []
    for other in dict.fromkeys(r["method"] for r in rows if not r.get("density")):
        pairs = [(psao[s][-1], by[(s, other)]) for s in psao if (s, other) in by]
        if pairs:
            gain = [a["psnr"] - b["psnr"] for a, b in pairs]
            lower = sum(a["flip"] < b["flip"] for a, b in pairs)
            cost = [a["client_ms_frame"] / b["client_ms_frame"] for a, b in pairs]
            lines.append(f"- {top} against {other}: {span(gain, '+.1f')} dB PSNR, a lower FLIP on {lower} of "
                         f"{len(pairs)} scenes, {span(cost, '.2f')} times its client ms per frame.")
    every = [r for ranked in psao.values() for r in ranked]
    lines.append(f"- PSAO's mean AO bias: at most {max(abs(r['bias']) for r in every):.4f} in magnitude (SSAO's: "
                 + ", ".join(f"{by[(s, 'SSAO')]['bias']:+.3f}" for s in scenes if (s, "SSAO") in by) + ").")
    pairs = [(ranked[0], ranked[-1]) for ranked in psao.values() if len(ranked) > 1]
    if pairs and len({(lo["density"], hi["density"]) for lo, hi in pairs}) == 1:
        lo, hi = pairs[0]
        lines.append(f"- PSAO-{hi['density']:g} against PSAO-{lo['density']:g}: "
                     f"{span([h['psnr'] - l['psnr'] for l, h in pairs], '+.1f')} dB PSNR.")
    return "\n" + "\n".join(lines) + "\n"


def bench_table(rows: list[dict]) -> str:
    """`psao bench`'s table, then the summary its figures give."""
    return markdown_table(rows) + method_summary(rows)


def figure(value, fmt: str) -> str:
    """value formatted, or '-' where the run has none (absent, None or NaN)."""
    return "-" if value is None or value != value else format(value, fmt)


def progressive_table(rows: list[dict]) -> str:
    """bench_progressive's scenes: how soon the client and the page see the scene, progressive against
    --no-progressive, and the PSNR of what the client shows as the grids arrive."""
    from benchmarks.bench_progressive import ANIMATED_SECONDS

    head = ["scene", "first snapshot s", "first snapshot s, --no-progressive", "page's first drawn frame s",
            "PSNR dB at first snapshot", "at the full grid's snapshot", "at end", "--no-progressive, from its first snapshot",
            "PSNR change across the swap, dB", f"--animate Updates/s, first {ANIMATED_SECONDS:g} s", "probes"]
    lines = []
    for r in rows:
        at = r.get("progressive_psnr_at_snapshots", [])
        early = r.get("animated_updates_early")
        lines.append([r["scene"], figure(r.get("progressive_first_snapshot_s"), ".2f"),
                      figure(r.get("plain_first_snapshot_s"), ".1f"), figure(r.get("page_first_frame_s"), ".2f"),
                      figure(at[0] if at else None, ".2f"), figure(at[1] if len(at) > 1 else None, ".2f"),
                      figure(r.get("progressive_psnr_at_end_db"), ".2f"), figure(r.get("full_bake_psnr_db"), ".2f"),
                      figure(r.get("swap_psnr_change_db"), "+.2f"),
                      figure(None if early is None else early / ANIMATED_SECONDS, ".1f"), f"{r['probes']:,}"])
    rays = sorted({(r["rays"], r["ref_rays"]) for r in rows})
    return table(head, lines) + "\n" + "; ".join(
        f"`--rays {a}`: PSNR of the AO the client shows at the visible probes against a {b}-ray trace" for a, b in rays
    ) + ". Seconds are from the start of the `psao serve` process; - where a scene has no movers (no `--animate` run).\n"


def links_table(rows: list[dict]) -> str:
    """bench_links' runs: per link setting, the client behind it and the loopback client beside it."""
    head = ["rtt ms", "loss %", "Mbit/s cap", "updates/s", "loopback client's updates/s", "s behind p50",
            "s behind p95", "stream Mbit/s", "snapshot MB", "packets lost / queue-dropped"]
    lines = []
    for r in rows:
        link, c = r["link"], r["client"]
        lines.append([f"{link['rtt_ms']:g}", f"{100 * link['loss']:g}",
                      "unlimited" if link["mbit"] is None else f"{link['mbit']:g}",
                      figure(c["updates_per_s"], ".1f"), figure(r["loopback"]["updates_per_s"], ".1f"),
                      figure(c["behind_p50_s"], ".3f"), figure(c["behind_p95_s"], ".3f"),
                      figure(c["stream_mbit_s"], ".2f"), figure(c["snapshot_mb"], ".2f"),
                      f"{r['packets']['lost']:,} / {r['packets']['queue_dropped']:,}"])
    return table(head, lines)


def verdicts_table(entry: dict) -> str:
    """One benchmark's entry of run_all.json: the command run_all ran, then a line per verdict it printed."""
    lines = [[v["what"], f"{v['value']} {v['op']} {v['target']}" if "op" in v else v["detail"] or "-", v["outcome"]]
             for v in entry["verdicts"]]
    status = f"exit status {entry['rc']}" + ("" if lines else ", no verdict at these settings")
    return (f"`{entry['command']}` ({status}):\n\n" +
            (table(["target", "measured", "verdict"], lines) if lines else ""))


def flat_figures(data: dict, prefix: str = "") -> list[tuple[str, object]]:
    """A benchmark's JSON summary as (dotted name, scalar) pairs, nested objects flattened; lists are
    left out (they are series for charts, not figures)."""
    pairs = []
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            pairs += flat_figures(value, f"{name}.")
        elif isinstance(value, (int, float, str, bool)) or value is None:
            pairs.append((name, value))
    return pairs


def figures_table(data: dict) -> str:
    """A benchmark's JSON summary as a table of its scalar figures."""
    def cell(value) -> str:
        if isinstance(value, bool) or value is None or isinstance(value, str):
            return str(value)
        return f"{value:,}" if isinstance(value, int) else format(value, ".4g")

    return table(["figure", "value"], [[f"`{name}`", cell(v)] for name, v in flat_figures(data)])


def clients_detail(data) -> str:
    """bench_clients' table.json: one line per client count."""
    from benchmarks.bench_clients import table as clients_table

    return clients_table(data) + "\n"


def video_detail(data) -> str:
    """bench_video's video_results.json: quality and cost per method, PSNR / FLIP per latency, cost per client."""
    from psao.eval.video_report import clients_markdown, latency_markdown, table1_markdown

    return (table1_markdown(data["rows"]) + "\nPSNR / FLIP against latency:\n\n" + latency_markdown(data["rows"]) +
            "\nServer ms per client (totals modelled):\n\n" + clients_markdown(data["clients"]))


def rows_list(data) -> str:
    """A list of row objects (bench_bake's, bench_tick's) as a table of their scalar figures."""
    rows = [dict(flat_figures(r)) for r in data]
    head = list(dict.fromkeys(k for r in rows for k in r))

    def cell(value) -> str:
        if value is None:
            return "-"
        if isinstance(value, float):
            return format(value, ".4g")
        return f"{value:,}" if isinstance(value, int) and not isinstance(value, bool) else str(value)

    return table([f"`{h}`" for h in head], [[cell(r.get(h)) for h in head] for r in rows])


def run_all_render(rows: list[dict]) -> str:
    """A run_all section: the benchmark's verdicts, then each detail file it wrote, rendered."""
    entry, details = rows[0], rows[1:]
    return verdicts_table(entry) + "".join("\n" + DETAIL_RENDER[d["render"]](d["data"]) for d in details)


DETAIL_RENDER: dict[str, Callable[[object], str]] = {
    "figures": figures_table, "clients": clients_detail, "video": video_detail, "rows": rows_list}


def link_quality_table(rows: list[dict]) -> str:
    """bench_links --quality: per client (loopback, or the link it is behind) its frames' PSNR against RTAO at
    the current pose, updates/s, seconds behind, stream and reconnects."""
    head = ["link", "PSNR dB (mean)", "PSNR dB (min)", "frames scored", "updates/s", "s behind p95",
            "stream Mbit/s", "reconnects"]
    lines = []
    for r in rows:
        link, c = r["link"], r["client"]
        label = "loopback" if link is None else (f"rtt {link['rtt_ms']:g} ms, loss {100 * link['loss']:g}%, "
                                                 + ("unlimited" if link["mbit"] is None else f"{link['mbit']:g} Mbit/s"))
        lines.append([label, figure(r["psnr_mean"], ".2f"), figure(min(r["psnr"], default=None), ".2f"),
                      str(len(r["psnr"])), figure(c["updates_per_s"], ".1f"), figure(c["behind_p95_s"], ".3f"),
                      figure(c["stream_mbit_s"], ".2f"), str(c["reconnects"])])
    return table(head, lines)


def link_fig5_table(rows: list[dict]) -> str:
    """bench_links --fig5: per method and link, its frames' PSNR against RTAO at the current pose, the stream it
    received, the video encoder's bitrate, and how late it was (PSAO: seconds its mirror was behind the server;
    video: a frame's round trip from request to arrival), 95th percentile."""
    head = ["method", "rtt ms", "Mbit/s cap", "PSNR dB (mean)", "PSNR dB (min)", "frames scored", "stream Mbit/s",
            "encoder Mbit/s", "s late p95"]
    lines = []
    for r in sorted(rows, key=lambda r: (r["method"], r["link"]["rtt_ms"], r["link"]["mbit"] or float("inf"))):
        link = r["link"]
        late = r["behind_p95_s"] if r["method"] == "psao" else r["round_trip_p95_s"]
        lines.append(["PSAO" if r["method"] == "psao" else "video", f"{link['rtt_ms']:g}",
                      "unlimited" if link["mbit"] is None else f"{link['mbit']:g}", figure(r["psnr_mean"], ".2f"),
                      figure(min(r["psnr"], default=None), ".2f"), str(len(r["psnr"])),
                      figure(r["stream_mbit_s"], ".2f"), figure(r.get("bitrate_mbit"), ".2f"), figure(late, ".3f")])
    return table(head, lines)


@dataclass(frozen=True)
class Section:
    command: str  # the command that writes the data, with --out OUT_DIR left to the runner
    data_file: str  # the file under --out that holds the rows
    render: Callable[[list[dict]], str]
    more_files: tuple[str, ...] = ()  # further files under --out whose rows follow (a benchmark of several runs)
    rows_of: Callable[[object], list[dict]] = list  # a data file's JSON -> its rows (default: the file is the list)
    more_rows_of: Callable[[object], list[dict]] | None = None  # the same for more_files (default: rows_of)


RUN_ALL = "python -m benchmarks.run_all --quick"


def run_all_section(name: str, detail: str | None = None, render: str = "figures") -> Section:
    """The section of benchmark `name` from a run_all --out run: its entry, then OUT/NAME/DETAIL if given."""
    def entry(record: dict) -> list[dict]:
        found = [b for b in record["benchmarks"] if b["name"] == name]
        if not found:
            raise SystemExit(f"report: error: run_all.json has no entry for {name}: run `{RUN_ALL} --out OUT` "
                             f"with {name} among the benchmarks")
        return found

    return Section(RUN_ALL, "run_all.json", run_all_render, (f"{name}/{detail}",) if detail else (),
                   rows_of=entry, more_rows_of=lambda data: [{"render": render, "data": data}])


SECTIONS: dict[str, Section] = {
    "table1": Section("psao bench builtin:cornell builtin:courtyard builtin:space builtin:robots --densities 256,512 "
                      "--tick-hz 60 --frames 4 --spp 512 --image-scale 0.5", "results.json", bench_table),
    "animated": Section("psao bench builtin:courtyard builtin:space builtin:robots --densities 256,512 --tick-hz 60 "
                        "--frames 4 --spp 512 --animate --stream-seconds 5 --image-scale 0.5", "results.json",
                        bench_table),
    "sponza": Section("psao bench ../shared/scenes/sponza/sponza_s_lod4.glb --densities 32,128 --tick-hz 60 "
                      "--frames 2 --spp 512 --image-scale 0.5", "results.json", bench_table),
    "baselines": Section("python -m benchmarks.bench_baselines --frames 3 --spp 512 --sponza-density 128 --mlp-steps 600 "
                         "--no-stream --image-scale 0.5", "results.json", bench_table, ("sponza/results.json",)),
    "scenes": Section("python -m benchmarks.bench_scenes --scales 1", "bench_scenes.json", scenes_table),
    "progressive": Section("python -m benchmarks.bench_progressive", "progressive.json", progressive_table,
                           rows_of=lambda scenes: list(scenes.values())),
    "links": Section("python -m benchmarks.bench_links --quick", "links.json", links_table,
                     rows_of=lambda record: record["runs"]),
    "run_points": run_all_section("points", "bench_points.json"),
    "run_bake": run_all_section("bake", "bench_bake.json", "rows"),
    "run_bandwidth": run_all_section("bandwidth", "bandwidth.json"),
    "run_render": run_all_section("render"),
    "run_tick": run_all_section("tick"),
    "run_static_hits": run_all_section("static_hits"),
    "run_culling": run_all_section("culling"),
    "run_clients": run_all_section("clients", "table.json", "clients"),
    "run_web": run_all_section("web"),
    "run_three": run_all_section("three", "bench_three.json"),
    "run_denoise": run_all_section("denoise"),
    "run_video": run_all_section("video", "video_results.json", "video"),
    "run_realtime": run_all_section("realtime", "bench_realtime.json"),
    "run_dask": run_all_section("dask"),
    "run_densify": run_all_section("densify"),
    "run_objects": run_all_section("objects"),
    "run_soak": run_all_section("soak", "soak.json"),
    "run_fuzz": run_all_section("fuzz"),
    "link_quality": Section("python -m benchmarks.bench_links --quality --seconds 8 --chart docs/images/links_quality.png",
                            "quality.json", link_quality_table, rows_of=lambda record: record["clients"]),
    "link_fig5": Section("python -m benchmarks.bench_links --fig5 --seconds 5 --chart docs/images/fig5_links.png",
                         "fig5.json", link_fig5_table, rows_of=lambda record: record["rows"]),
}

RUN_ALL_SECTIONS = [sid for sid, section in SECTIONS.items() if section.command == RUN_ALL]

_BLOCK = re.compile(r"(<!-- report:(\w+) -->\n)(.*?)(<!-- /report:\2 -->)", re.S)


def known_commit(commit: str) -> str:
    """`commit`'s short hash in this repository, or SystemExit naming it when there is no such commit."""
    import subprocess

    done = subprocess.run(["git", "rev-parse", "--short", "--verify", "--quiet", f"{commit}^{{commit}}"], cwd=ROOT,
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"report: error: --commit {commit}: no such commit in this repository")
    return done.stdout.strip()


def run_commit(out_dir: Path) -> str:
    """The commit the run in out_dir was made at: its run.json's or run_all.json's, else HEAD (+local changes
    if dirty)."""
    for name in ("run.json", "run_all.json"):
        if (out_dir / name).is_file():
            return json.loads((out_dir / name).read_text())["commit"]
    return source_commit()


def collect(section_id: str, out_dir: Path, data_dir: Path = DATA, commit: str | None = None) -> Path:
    """Store the rows of a finished run as the section's data file, with `commit` (default: run_commit)."""
    section = SECTIONS[section_id]
    more_rows_of = section.more_rows_of or section.rows_of
    rows = [*section.rows_of(json.loads((out_dir / section.data_file).read_text())),
            *(r for name in section.more_files for r in more_rows_of(json.loads((out_dir / name).read_text())))]
    data_dir.mkdir(parents=True, exist_ok=True)
    path = data_dir / f"{section_id}.json"
    record = {"id": section_id, "command": f"{section.command} --out {out_dir.name}",
              "commit": commit or run_commit(out_dir), "rows": rows}
    path.write_text(json.dumps(record, indent=1) + "\n")
    return path


def render_block(section_id: str, data_dir: Path = DATA) -> str:
    """The generated text of one block: the table, then the line naming its command and commit."""
    path = data_dir / f"{section_id}.json"
    if not path.is_file():
        return (f"*No data yet: run `{SECTIONS[section_id].command} --out OUT`, then "
                f"`python -m benchmarks.report collect {section_id} OUT` and `python -m benchmarks.report write`.*\n")
    record = json.loads(path.read_text())
    return (f"```\n{record['command']}\n```\n\n" + SECTIONS[section_id].render(record["rows"]) +
            f"\n*Generated by `python -m benchmarks.report` from docs/data/{section_id}.json, the output of the "
            f"command above at commit {record['commit']}.*\n")


def rendered(text: str, data_dir: Path = DATA) -> str:
    """`text` (a results page) with every generated block replaced by what its data gives."""
    def one(m: re.Match) -> str:
        if m.group(2) not in SECTIONS:
            raise SystemExit(f"report: error: docs/results.md has a block {m.group(2)!r} that no section renders")
        return m.group(1) + render_block(m.group(2), data_dir) + m.group(4)

    return _BLOCK.sub(one, text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.report", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="action", required=True)
    c = sub.add_parser("collect", help="store a finished run's rows as a section's data")
    c.add_argument("section", choices=[*sorted(SECTIONS), "run_all"],
                   help="a section, or run_all: every section of a run_all --out run")
    c.add_argument("out_dir", type=Path)
    c.add_argument("--commit", help="the commit the run was made at (default: OUT_DIR/run.json's, else HEAD)")
    sub.add_parser("write", help="rewrite docs/results.md's generated blocks from docs/data")
    sub.add_parser("check", help="exit 1 if docs/results.md's generated blocks differ from docs/data")
    args = ap.parse_args(argv)
    if args.action == "collect":
        ids = RUN_ALL_SECTIONS if args.section == "run_all" else [args.section]
        for sid in ids:
            section = SECTIONS[sid]
            missing = [n for n in (section.data_file, *section.more_files) if not (args.out_dir / n).is_file()]
            if missing:
                ap.error(f"{args.out_dir / missing[0]} does not exist: run the section's command first")
        commit = known_commit(args.commit) if args.commit else None
        for sid in ids:
            print(f"wrote {collect(sid, args.out_dir, commit=commit)}")
        return 0
    text = RESULTS.read_text()
    new = rendered(text)
    if args.action == "write":
        RESULTS.write_text(new)
        print(f"wrote {RESULTS}")
        return 0
    if new != text:
        print("docs/results.md differs from docs/data: run `python -m benchmarks.report write`", file=sys.stderr)
        return 1
    print("docs/results.md matches docs/data")
    return 0


if __name__ == "__main__":
    sys.exit(main())
