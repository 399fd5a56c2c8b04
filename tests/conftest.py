"""Shared test helpers."""

from __future__ import annotations

from pathlib import Path

# The real iCub recordings live in shared/, beside the checkout (../shared/data/icub).
ICUB_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "icub"


def occam_gradient_skips(prob, traj, monkeypatch) -> tuple[list[bool], object, object]:
    """The Occam gradient of ``prob``'s global columns at ``traj`` with its skipped columns
    (``_jacobians_held``) and with every column differenced: ``(held, skipped, every)``, ``held``
    the verdict per column."""
    import numpy as np

    from flexforce.smoother import evidence
    from flexforce.smoother.linearize import global_columns

    cidx = np.asarray(global_columns(prob), dtype=int)
    real = evidence._jacobians_held
    held: list[bool] = []

    def spy(*args):
        held.append(real(*args))
        return held[-1]

    with monkeypatch.context() as patch:
        patch.setattr(evidence, "_jacobians_held", spy)
        skipped = evidence.occam_gradient(prob, traj, cidx)
        patch.setattr(evidence, "_jacobians_held", lambda *args: False)
        every = evidence.occam_gradient(prob, traj, cidx)
    return held, skipped, every
