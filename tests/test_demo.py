"""The demo and the comparison command end to end (shorter scenarios than the built-in ones)."""

from __future__ import annotations

import json
import re

import pytest

from flexforce.cli import main

SHORT_PUSH = """
name = "short-push"
description = "A push forward on the torso, 2.5 s."
robot = "romeo"
duration = 2.5

[[effects]]
type = "external-wrench"
link = "@base"
force = [30.0, 0.0, 0.0]
start = 1.0
duration = 0.15
"""


@pytest.fixture()
def scenario(tmp_path):
    path = tmp_path / "short-push.toml"
    path.write_text(SHORT_PUSH)
    return path


@pytest.mark.slow
def test_demo_writes_a_report_whose_json_holds_the_table(tmp_path, scenario, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--scenario", str(scenario), "-q"]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["estimators"]) == {"ekf", "fixed_lag", "batch"}
    for key, m in summary["estimators"].items():
        for q in ("force_N", "moment_Nm", "cop_m", "rotation_rad", "translation_m", "hand_m"):
            assert m["rmse"][q] is not None and m["rmse"][q] > 0, (key, q)
        assert m["nees"] is not None
    timings = json.loads((out / "timings.json").read_text())  # the cost, apart from the numbers
    assert set(timings["estimators"]) == set(summary["estimators"])
    for m in timings["estimators"].values():
        assert m["time_per_step_s"]["median"] is None or m["time_per_step_s"]["median"] > 0
    assert timings["estimators"]["ekf"]["time_per_step_s"]["median"] > 0
    assert summary["recording"]["hidden_effects"][0]["type"] == "external-wrench"
    assert summary["cramer_rao"]["rmse_bound"]["force_N"] > 0
    page = (out / "index.html").read_text()
    # every RMSE of the table is the summary's number, rounded as the table rounds it
    from flexforce.compare.reports.comparison import TABLE_COLUMNS

    shown = [c[0] for c in TABLE_COLUMNS if any(m["rmse"].get(c[0]) is not None
                                                for m in summary["estimators"].values())]
    for key, m in summary["estimators"].items():
        row = re.search(rf'<tr class="estimator"><th>{key}</th>(.*?)</tr>', page).group(1)
        cells = re.findall(r"<td>(.*?)</td>", row)
        assert cells[shown.index("force_N")] == f"{m['rmse']['force_N']:.3g}"
        assert cells[shown.index("cop_m")] == f"{m['rmse']['cop_m'] * 1e3:.3g}"
        assert cells[shown.index("rotation_rad")] == f"{m['rmse']['rotation_rad'] * 1e3:.3g}"
    for fig in ("forces.png", "flexibility.png", "errors.png", "residuals.png", "consistency.png"):
        assert (out / fig).stat().st_size > 10_000
    # the terminal table shows the same force RMSE
    assert f"{summary['estimators']['batch']['rmse']['force_N']:.3g}" in printed


def test_compare_aggregates_seeds(tmp_path, scenario):
    out = tmp_path / "cmp"
    scenario.write_text(SHORT_PUSH.replace("duration = 2.5", "duration = 1.2"))
    assert main(["compare", str(scenario), "--seeds", "2", "--estimators", "ekf,batch", "-o", str(out), "-q"]) == 0
    agg = json.loads((out / "summary.json").read_text())
    assert len(agg["recordings"]) == 2
    ekf = agg["estimators"]["ekf"]
    assert ekf["count"] == 2 and ekf["rmse"]["force_N"] > 0 and ekf["rmse_std"]["force_N"] >= 0
    per_seed = [json.loads((out / f"short-push-seed{s}" / "summary.json").read_text()) for s in range(2)]
    mean = sum(p["estimators"]["ekf"]["rmse"]["force_N"] for p in per_seed) / 2
    assert ekf["rmse"]["force_N"] == pytest.approx(mean)
    assert per_seed[0]["estimators"]["ekf"]["rmse"]["force_N"] != per_seed[1]["estimators"]["ekf"]["rmse"]["force_N"]


def test_compare_of_a_missing_bag_is_one_line(tmp_path, capsys):
    assert main(["compare", str(tmp_path / "nothing"), "-o", str(tmp_path / "o"), "-q"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "does not exist" in err
