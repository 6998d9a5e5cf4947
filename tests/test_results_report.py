"""docs/results.md's generated tables equal what benchmarks.report renders from docs/data, and the
rendering follows the data (a changed figure changes the page; a missing data file says how to make it)."""
from __future__ import annotations

import json
import re

import pytest

from benchmarks import report


def test_results_page_matches_its_data():
    assert report.main(["check"]) == 0


def test_every_generated_block_has_a_section_and_data():
    blocks = report._BLOCK.findall(report.RESULTS.read_text())
    assert blocks, "docs/results.md has no generated block"
    for _, section_id, body, _ in blocks:
        assert section_id in report.SECTIONS
        assert (report.DATA / f"{section_id}.json").is_file(), f"docs/data/{section_id}.json is missing"
        assert "at commit" in body


def test_a_changed_figure_changes_the_page(tmp_path):
    section_id = next(p.stem for p in sorted(report.DATA.glob("*.json")))
    record = json.loads((report.DATA / f"{section_id}.json").read_text())
    page = f"x\n<!-- report:{section_id} -->\nstale\n<!-- /report:{section_id} -->\ny\n"
    first = report.rendered(page, report.DATA)
    assert "stale" not in first and first.startswith("x\n") and first.endswith("y\n")
    assert record["command"] in first and record["commit"] in first
    counted = [r for r in record["rows"] if isinstance(r.get("points"), int) and r["points"] > 0]
    for r in counted:
        r["points"] += 1234567
    (tmp_path / f"{section_id}.json").write_text(json.dumps(record))
    second = report.rendered(page, tmp_path)
    assert counted and second != first and any(f"{r['points']:,}" in second for r in counted)


def test_a_section_without_data_says_how_to_make_it(tmp_path):
    page = "<!-- report:table1 -->\n<!-- /report:table1 -->"
    text = report.rendered(page, tmp_path)
    assert "python -m benchmarks.report collect table1" in text and report.SECTIONS["table1"].command in text


def test_collect_keeps_the_rows_the_command_and_the_commit(tmp_path):
    out = tmp_path / "bench_x"
    out.mkdir()
    rows = [{"scene": "cornell", "points": 5}]
    (out / "results.json").write_text(json.dumps(rows))
    (out / "run.json").write_text(json.dumps({"commit": "abc1234"}))
    path = report.collect("table1", out, tmp_path / "data")
    record = json.loads(path.read_text())
    assert record["rows"] == rows and record["commit"] == "abc1234"
    assert record["command"].startswith(report.SECTIONS["table1"].command) and record["command"].endswith("--out bench_x")


def test_the_summary_lines_follow_the_rows():
    """Table 1's summary is computed from its rows: a PSAO row's PSNR raised by 10 dB raises the largest gain
    over SSAO by 10 dB."""
    rows = json.loads((report.DATA / "table1.json").read_text())["rows"]

    def largest_gain(text: str) -> float:
        line = next(ln for ln in text.splitlines() if "against SSAO" in ln)
        return float(line.split(" to ")[1].split(" dB")[0])

    top = max(r["density"] for r in rows if r.get("density"))
    best = max((r for r in rows if r.get("density") == top),
               key=lambda r: r["psnr"] - next(o["psnr"] for o in rows if o["scene"] == r["scene"] and o["method"] == "SSAO"))
    before = largest_gain(report.method_summary(rows))
    best["psnr"] += 10.0
    assert largest_gain(report.method_summary(rows)) == round(before + 10.0, 1)


def test_collect_takes_a_benchmark_whose_file_is_not_a_list_and_a_given_commit(tmp_path):
    """bench_progressive writes {scene: figures}: its rows are the scenes; --commit names the run's commit
    where the output directory has no run.json."""
    out = tmp_path / "bp"
    out.mkdir()
    scenes = {"courtyard": {"scene": "courtyard", "probes": 7}, "sponza": {"scene": "sponza", "probes": 9}}
    (out / "progressive.json").write_text(json.dumps(scenes))
    record = json.loads(report.collect("progressive", out, tmp_path / "data", commit="e1d1158").read_text())
    assert record["rows"] == list(scenes.values()) and record["commit"] == "e1d1158"


def test_an_unknown_commit_is_one_clear_line(tmp_path):
    out = tmp_path / "bp"
    out.mkdir()
    (out / "progressive.json").write_text("{}")
    with pytest.raises(SystemExit, match="no such commit"):
        report.main(["collect", "progressive", str(out), "--commit", "not-a-commit"])


def test_the_progressive_and_links_tables_follow_their_rows():
    """A changed figure of bench_progressive's and bench_links' data shows in the rendered table."""
    prog = json.loads((report.DATA / "progressive.json").read_text())["rows"]
    prog[0]["progressive_first_snapshot_s"] = 9.87
    assert "| 9.87 |" in report.progressive_table(prog)
    del prog[0]["page_first_frame_s"]  # a run with --skip-page
    assert report.progressive_table(prog).count(" - ") >= 1
    links = [{"link": {"rtt_ms": 150.0, "loss": 0.01, "mbit": 5.0}, "packets": {"lost": 3, "queue_dropped": 0},
              "loopback": {"updates_per_s": 29.9},
              "client": {"updates_per_s": 12.3, "behind_p50_s": 0.25, "behind_p95_s": 0.5, "stream_mbit_s": 1.5,
                         "snapshot_mb": 4.25}}]
    assert "| 150 | 1 | 5 | 12.3 | 29.9 | 0.250 | 0.500 | 1.50 | 4.25 | 3 / 0 |" in report.links_table(links)


# What a measured figure looks like in prose: a decimal, a thousands separator, a percentage, a ratio
# ("17x"), or a number with a unit.
_FIGURE = re.compile(r"\d\.\d|\d,\d{3}|\d\s*%|\b\d+(?:\.\d+)?x(?!\d)|\b\d+\s*(?:ms|s|dB|MB|kB|Mbit/s|B)\b")


def hand_written_figures(text: str) -> list[str]:
    """The figures of a results page outside its generated blocks, code (commands, settings and targets
    are written as code), image and link targets, and blockquotes (quotes of other sources)."""
    text = report._BLOCK.sub("", text)
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    text = re.sub(r"`[^`]*`", "", text)
    text = re.sub(r"!?\[[^\]]*\]\([^)]*\)", "", text)
    return [f"{m.group()!r} in {line.strip()[:80]!r}" for line in text.splitlines() if not line.startswith(">")
            for m in _FIGURE.finditer(line)]


def test_every_figure_of_the_page_is_generated():
    """No measured figure is written by hand: each is in a block that benchmarks.report renders."""
    assert hand_written_figures(report.RESULTS.read_text()) == []


def test_a_hand_written_figure_is_found():
    """Each kind of figure is found in prose; none in code, a blockquote or a generated block."""
    for figure in ("10,046 B a tick", "2.45x smaller", "0.2% holes", "in 58 ms", "at 36.2 dB", "17x faster"):
        assert hand_written_figures(f"**Bytes per tick**: {figure}.\n"), figure
    assert hand_written_figures("Intro at `--density 256`, 640x360 frames.\n\n> The paper: 34.07 dB.\n\n"
                                "<!-- report:x -->\n9.5 ms\n<!-- /report:x -->\n![a 2.5x chart](images/a_1.5.png)\n") == []


def test_a_run_all_section_is_the_benchmarks_entry_then_its_own_file(tmp_path):
    """collect of a run_all section keeps the benchmark's run_all.json entry and the file it wrote, and the
    commit of the run; a changed verdict or figure shows in the page; a run without the benchmark is one line."""
    out = tmp_path / "run_all"
    (out / "soak").mkdir(parents=True)
    entry = {"name": "soak", "command": "python -m benchmarks.bench_soak --minutes 1.5 --out out/run_all/soak", "rc": 0,
             "verdicts": [{"outcome": "PASS", "bench": "bench_soak", "what": "mirror digests different",
                           "value": "0", "op": "<=", "target": "0"}]}
    (out / "run_all.json").write_text(json.dumps({"quick": True, "commit": "abc1234", "benchmarks": [entry]}))
    (out / "soak" / "soak.json").write_text(json.dumps({"rss_end_mb": 356.25, "fresh": {"ok": True}, "samples": [1, 2]}))
    record = json.loads(report.collect("run_soak", out, tmp_path / "data").read_text())
    assert record["commit"] == "abc1234" and record["command"] == f"{report.RUN_ALL} --out run_all"
    page = report.rendered("<!-- report:run_soak -->\n<!-- /report:run_soak -->\n", tmp_path / "data")
    assert f"`{entry['command']}` (exit status 0)" in page and "| mirror digests different | 0 <= 0 | PASS |" in page
    assert "| `rss_end_mb` | 356.2 |" in page and "| `fresh.ok` | True |" in page and "samples" not in page
    record["rows"][0]["verdicts"][0].update(outcome="FAIL", value="3")
    (tmp_path / "data" / "run_soak.json").write_text(json.dumps(record))
    assert "| mirror digests different | 3 <= 0 | FAIL |" in report.rendered(page, tmp_path / "data")
    (out / "run_all.json").write_text(json.dumps({"quick": True, "commit": "abc1234", "benchmarks": []}))
    with pytest.raises(SystemExit, match="no entry for soak"):
        report.collect("run_soak", out, tmp_path / "data")


def test_every_benchmark_of_run_all_has_a_section_on_the_page():
    """Each benchmark run_all runs is on the results page: in a run_all section or a section of its own run."""
    from benchmarks import run_all

    own = {"quality": "table1", "scenes": "scenes", "baselines": "baselines", "progressive": "progressive",
           "links": "links"}
    on_page = {sid for _, sid, _, _ in report._BLOCK.findall(report.RESULTS.read_text())}
    for name in run_all.BENCHMARKS:
        assert own.get(name, f"run_{name}") in on_page, name
