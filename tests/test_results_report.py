"""docs/results.md's generated tables equal what benchmarks.report renders from docs/data, and the
rendering follows the data (a changed figure changes the page; a missing data file says how to make it)."""
from __future__ import annotations

import json

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
