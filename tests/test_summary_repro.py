"""summary.json holds what the estimates are and compares byte for byte between two identical runs;
what they cost on the machine (time per step, total time, peak memory) is in timings.json beside it,
and the report's tables show both."""

from __future__ import annotations

import json
import re

import pytest

from flexforce.cli import main
from flexforce.compare.reports import comparison

SHORT_STAND = """
name = "short-stand"
description = "Standing still, 0.5 s."
robot = "romeo"
duration = 0.5
seed = 3
"""

TIMING_KEYS = {"time_per_step_s", "total_time_s", "peak_memory_mb", "seconds"}
"""Keys that measure the machine, not the estimate."""


def keys(value) -> set[str]:
    """Every key of a JSON value, at any depth."""
    if isinstance(value, dict):
        return set(value).union(*(keys(v) for v in value.values()))
    if isinstance(value, list):
        return set().union(*(keys(v) for v in value))
    return set()


@pytest.fixture()
def scenario(tmp_path, monkeypatch):
    """A 0.5 s standing scenario file; the report's figures left out (they take seconds to draw and
    the JSON files are written before them)."""
    monkeypatch.setattr(comparison, "FIGURES", {})
    path = tmp_path / "short-stand.toml"
    path.write_text(SHORT_STAND)
    return path


def run(scenario, out, *options) -> None:
    assert main(["compare", str(scenario), "--estimators", "ekf,fixed-lag", "-o", str(out), "-q", *options]) == 0


def test_two_identical_runs_write_the_same_summary(scenario, tmp_path, capsys):
    for name in ("one", "two"):
        run(scenario, tmp_path / name)
    capsys.readouterr()
    one, two = ((tmp_path / name / "summary.json").read_bytes() for name in ("one", "two"))
    assert one == two
    summary = json.loads(one)
    assert not keys(summary) & TIMING_KEYS
    times = json.loads((tmp_path / "one" / "timings.json").read_text())
    assert set(times["machine"]) == {"python", "processor", "cpus", "platform"}
    for group in ("estimators", "baselines", "peers"):
        assert set(times[group]) == set(summary[group]), group
    for group in ("estimators", "peers"):
        for key, row in times[group].items():
            assert row["time_per_step_s"]["median"] > 0 and row["total_time_s"] > 0, key
            assert set(row) == {"time_per_step_s", "total_time_s", "peak_memory_mb"}
    assert times["baselines"]["leg_odometry"]["time_per_step_s"] == {}
    # the report's timing column shows timings.json's numbers
    page = (tmp_path / "one" / "index.html").read_text()
    for key in ("ekf", "fixed_lag"):
        row = re.search(rf'<tr class="estimator"><th>{key}</th>(.*?)</tr>', page).group(1)
        median = times["estimators"][key]["time_per_step_s"]["median"]
        assert f"<td>{median * 1e6:.3g}</td>" in row, key
        assert f"<td>{times['estimators'][key]['total_time_s']:.3g}</td>" in row, key


def test_several_recordings_keep_their_timings_apart(scenario, tmp_path, capsys):
    """The aggregate of several recordings: summary.json without timing, timings.json with each
    row's time per step over the recordings, shown in the index's table."""
    out = tmp_path / "seeds"
    run(scenario, out, "--seeds", "2")
    capsys.readouterr()
    summary = json.loads((out / "summary.json").read_text())
    assert not keys(summary) & TIMING_KEYS
    assert summary["estimators"]["ekf"]["count"] == 2
    times = json.loads((out / "timings.json").read_text())
    assert set(times["estimators"]) == set(summary["estimators"]) == {"ekf", "fixed_lag"}
    per = [json.loads((out / f"short-stand-seed{s}" / "timings.json").read_text()) for s in (0, 1)]
    for key, row in times["estimators"].items():
        medians = sorted(p["estimators"][key]["time_per_step_s"]["median"] for p in per)
        assert row["time_per_step_s"]["median"] == pytest.approx(sum(medians) / 2), key
        assert row["time_per_step_s"]["p99"] == max(p["estimators"][key]["time_per_step_s"]["p99"] for p in per)
    assert not keys(json.loads((out / "short-stand-seed0" / "summary.json").read_text())) & TIMING_KEYS
    page = (out / "index.html").read_text()
    assert f"{times['estimators']['ekf']['time_per_step_s']['median'] * 1e6:.3g}" in page
