"""The F/T reference held against the rigid robot's dynamics (compare.metrics.reference_checks): on a
simulated step whose F/T are the true contact forces plus known offsets, the checks give back the
offsets; with ground truth there is nothing to check."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from flexforce.compare.metrics import contact_frame_wrench, reference_checks
from flexforce.compare.reports.comparison import reference_sentences
from flexforce.datasets.sim.scenario import Scenario
from flexforce.datasets.sim.simulator import Simulator

OFFSETS = (5.0, -3.0)
"""N: the F/T offsets added to the true normal forces of the left and the right foot."""


@pytest.fixture(scope="module")
def step():
    sc = Scenario.load("step")
    sc.duration = 5.0  # the CoM over the left foot, the right foot's swing and landing
    return Simulator(sc).run()


def with_ft(rec, offsets):
    """``rec`` without its truth, its F/T the true contact wrenches with ``offsets`` added to F_z."""
    ft = contact_frame_wrench(rec.truth.R, rec.truth.t, rec.truth.wrench, rec)
    ft[:, :, 2] += np.asarray(offsets)
    return dataclasses.replace(rec, truth=None, ft=ft)


def test_none_with_truth_or_without_ft(step):
    assert reference_checks(step) is None
    assert reference_checks(dataclasses.replace(step, truth=None, ft=None)) is None


def test_offsets_found(step):
    rec = with_ft(step, OFFSETS)
    ref = reference_checks(rec, skip=0.5)
    # the right foot swings: its true force is exactly 0 there, so its reading is the offset
    assert set(ref["unloaded"]) == {"right_foot"}
    assert ref["unloaded"]["right_foot"]["mean_N"] == pytest.approx(OFFSETS[1], abs=1e-9)
    assert ref["unloaded"]["right_foot"]["samples"] == int((~rec.contact_active[rec.time >= 0.5, 1]).sum())
    # standing on both feet the sum is off by both offsets; the flexibility's own vertical motion
    # (left out of m (g + c_z'')) measured at -1.16 N on average here: margin 0.44 N
    ds = ref["total"]["double_support"]
    assert ds["mean_N"] == pytest.approx(sum(OFFSETS), abs=1.6)
    # without offsets the mean is that of the flexibility alone, well below the offsets' sum
    clean = reference_checks(with_ft(step, (0.0, 0.0)), skip=0.5)["total"]["double_support"]
    assert abs(clean["mean_N"]) < 1.6
    assert ds["mean_N"] - clean["mean_N"] == pytest.approx(sum(OFFSETS), abs=1e-6)


def test_sentences(step):
    summary = {"reference_checks": reference_checks(with_ft(step, OFFSETS), skip=0.5)}
    text = " ".join(reference_sentences(summary))
    assert "-3.0 N (right_foot" in text
    assert "above it in double support" in text
    assert reference_sentences({}) == []
