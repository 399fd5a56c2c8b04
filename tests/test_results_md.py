"""docs/results.md is what benchmarks/results_md.py writes from the committed benchmark records.

The page is generated, never edited by hand: regenerating it from ``benchmarks/results/*.json`` must
give the committed file byte for byte, so a record rerun without the page, or a figure typed into the
page, fails here (the fix: ``python benchmarks/results_md.py``).
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _generator():
    spec = importlib.util.spec_from_file_location("results_md", ROOT / "benchmarks" / "results_md.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("results_md", module)
    spec.loader.exec_module(module)
    return module


def test_the_committed_page_is_what_the_generator_writes():
    committed = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    assert committed == _generator().render_all(ROOT / "benchmarks" / "results"), (
        "docs/results.md is stale or edited by hand: run python benchmarks/results_md.py")


def test_every_record_has_a_section_with_its_command():
    text = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    for path in sorted((ROOT / "benchmarks" / "results").glob("*.json")):
        assert f"## {path.stem}\n" in text, path.name
        section = text.split(f"## {path.stem}\n", 1)[1].split("\n## ", 1)[0]
        assert "Command: `" in section, f"{path.name}: no command"


def test_a_cited_figure_is_not_a_measurement():
    """The EKF benchmark keeps the authors' C++ time apart from what it measures, with its source."""
    record = json.loads((ROOT / "benchmarks" / "results" / "ekf_speed.json").read_text(encoding="utf-8"))
    assert "authors_cpp_us_per_step" not in record
    ref = record["cited_reference"]
    assert ref["measured_by_this_benchmark"] is False and ref["source"]
    text = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    assert "Cited, not measured here" in text


def test_an_unknown_record_gets_the_table_of_its_scalars(tmp_path):
    gen = _generator()
    (tmp_path / "new_bench.json").write_text(json.dumps(
        {"benchmark": "new_bench", "machine": {"cpus": 2}, "speed": {"median_ms": 0.41234, "runs": [1, 2]},
         "details": [{"a": 1}] * 10}))
    text = gen.render_all(tmp_path)
    assert "## new_bench" in text and "Machine: cpus 2." in text
    assert "| speed.median_ms | 0.4123 |" in text and "| speed.runs | 1, 2 |" in text
    assert "| details | (10 entries in the JSON) |" in text


def test_numbers_are_formatted_without_trailing_zeros():
    fmt = _generator().fmt
    assert [fmt(v) for v in (0.0, 3.0, 0.769, 66825.02, 1.0007e-15, True, None, [1, 2.5])] == [
        "0", "3", "0.769", "66825", "1e-15", "yes", "–", "1, 2.5"]
