"""The state layout (:mod:`flexforce.datasets.layout`) is the one order of every estimate's state.

Its labels, slices and units agree with each other and with the users that name them: the
Estimate, the CSV export's ``std_`` columns, the physics core's ``STATE_DIM``, and the EKF whose
internal order (the paper's eq. (4)) is a permutation of the layout's blocks.
"""

from __future__ import annotations

import numpy as np
import pytest

from flexforce.compare.ekf import filter as E
from flexforce.datasets import estimate
from flexforce.datasets.io.export import csv_columns
from flexforce.datasets.layout import STATE, STATE_DIM, STATE_LABELS
from flexforce.errors import ConfigError
from flexforce.factors import core, so3


def test_blocks_slices_and_labels_agree():
    assert STATE.names == ("theta", "t", "w", "v", "dw", "a")
    assert [b.unit for b in STATE.blocks] == ["rad", "m", "rad/s", "m/s", "rad/s^2", "m/s^2"]
    assert STATE_DIM == STATE.dim == len(STATE_LABELS) == 18
    labels = np.array(STATE_LABELS)
    for b in STATE.blocks:
        assert b.frame.startswith("world")
        assert STATE[b.name] == b.index == slice(b.index.start, b.index.start + 3)
        assert tuple(labels[b.index]) == (f"{b.name}_x", f"{b.name}_y", f"{b.name}_z")
    # the blocks tile the state, in order, without gaps
    assert np.array_equal(np.concatenate([np.arange(18)[b.index] for b in STATE.blocks]), np.arange(18))
    assert np.array_equal(STATE.index(STATE.names), np.arange(18))


def test_users_take_the_layout():
    assert estimate.STATE_LABELS is STATE_LABELS
    assert core.STATE_DIM == STATE_DIM
    est = estimate.Estimate(estimator="x", t_ns=np.zeros(1, np.int64), contact_names=("left",), R=np.eye(3)[None],
                            t=np.zeros((1, 3)), w=np.zeros((1, 3)), v=np.zeros((1, 3)), dw=np.zeros((1, 3)),
                            a=np.zeros((1, 3)), wrench=np.zeros((1, 1, 6)), cop=np.zeros((1, 3)),
                            cov=np.zeros((1, 18, 18)))
    std_cols = [c for c in csv_columns(est) if c.startswith("std_")]
    assert std_cols == [f"std_{label}" for label in STATE_LABELS]


def test_ekf_order_is_a_permutation_of_the_layout():
    assert sorted(E.PAPER_ORDER) == sorted(STATE.names)
    assert sorted(E.PAPER_INDEX.tolist()) == list(range(18))
    # a labelled vector rearranged into the filter's order carries the filter's labels (theta as Omega)
    permuted = [STATE_LABELS[i] for i in E.PAPER_INDEX]
    assert [label.replace("theta_", "Omega_") for label in permuted] == list(E.STATE_LABELS)
    # the filter's slices name the blocks of PAPER_ORDER
    labels = np.array(E.STATE_LABELS)
    for name, sl in zip(("t", "Omega", "v", "w", "a", "dw"), (E.T, E.OM, E.V, E.W, E.A, E.DW)):
        assert tuple(labels[sl]) == (f"{name}_x", f"{name}_y", f"{name}_z")
    # units follow the permutation
    units = [STATE.block(n).unit for n in E.PAPER_ORDER]
    assert units == ["m", "rad", "m/s", "rad/s", "m/s^2", "rad/s^2"]


def test_ekf_conversion_at_zero_rotation_is_the_permutation():
    rng = np.random.default_rng(39)
    L = rng.normal(size=(18, 18))
    P_paper = L @ L.T
    M = E.paper_to_world(np.zeros(3))
    assert np.array_equal(M[E.PAPER_INDEX], np.eye(18))  # d_world[PAPER_INDEX] = d_paper
    P_world = np.empty_like(P_paper)
    P_world[np.ix_(E.PAPER_INDEX, E.PAPER_INDEX)] = P_paper
    np.testing.assert_array_equal(M @ P_paper @ M.T, P_world)
    np.testing.assert_array_equal(E.world_to_paper_cov(np.zeros(3), P_world), P_paper)


def test_ekf_conversion_away_from_zero_touches_only_the_rotation():
    Omega = np.array([0.3, -0.2, 0.5])
    M = E.paper_to_world(Omega)
    theta, Om = STATE["theta"], E.OM
    np.testing.assert_array_equal(M[theta, Om], so3.left_jacobian(Omega))
    M0 = E.paper_to_world(np.zeros(3))
    M[theta, Om] = M0[theta, Om]
    np.testing.assert_array_equal(M, M0)


def test_unknown_block_and_bad_order_are_refused():
    with pytest.raises(ConfigError, match="unknown state block 'Omega'"):
        STATE.block("Omega")
    with pytest.raises(ConfigError, match="not a permutation"):
        STATE.index(("t", "theta", "v", "w", "a"))
    with pytest.raises(ConfigError, match="not a permutation"):
        STATE.slices(("t", "t", "v", "w", "a", "dw"))
