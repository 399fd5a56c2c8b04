"""The Estimate: what every estimator (EKF, batch and fixed-lag smoothers) returns.

One type for all, so that every comparison is like for like (DESIGN.md, "Data flow").  Shapes:
``N`` steps, ``C`` contacts.  The state covariance is over world-frame increments in the state
layout of :mod:`flexforce.datasets.layout`: ``(theta, t, w, v, dw, a)``, 18 components.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flexforce.datasets.layout import STATE_LABELS as STATE_LABELS  # re-exported; defined by the layout
from flexforce.datasets.quantities import FlexibleMotion, Stamped
from flexforce.datasets.safeio import safe_output
from flexforce.errors import DataError


@dataclass
class Estimate(FlexibleMotion, Stamped):
    """Per-step estimate of the flexibility state, contact wrenches and CoP, with uncertainty."""

    estimator: str
    """``ekf``, ``batch``, ``fixed_lag`` (or a user's name)."""
    t_ns: np.ndarray
    """(N,) int64 time stamps, ns (those of the Recording)."""
    contact_names: tuple[str, ...]
    """Names of the C contacts (those of the Recording)."""
    cop: np.ndarray
    """(N, 3) centre of pressure, m (NaN without vertical force)."""
    cov: np.ndarray | None = None
    """(N, 18, 18) marginal covariance of the state (world-frame increments, in the order of
    :data:`flexforce.datasets.layout.STATE`)."""
    wrench_cov: np.ndarray | None = None
    """(N, 6, 6) covariance of the total contact wrench."""
    contact_wrench_cov: np.ndarray | None = None
    """(N, C, 6, 6) covariance of each contact's wrench (world axes, about the world origin, like
    :attr:`wrench`); zero while the contact is inactive."""
    cop_cov: np.ndarray | None = None
    """(N, 2, 2) covariance of the CoP's x and y, m^2."""
    wrench_excess: np.ndarray | None = None
    """(N, C, 6) what the contact law asked of each contact beyond what a contact can carry (a
    pulling normal force, a tangential force outside the friction cone, a CoP off the sole), world
    axes about the world origin like :attr:`wrench`, which holds the rest
    (:mod:`flexforce.factors.contact_limits`); zero where nothing was limited, None: not limited.
    ``wrench + wrench_excess`` is the contact law's wrench."""
    residuals: dict[str, np.ndarray] = field(default_factory=dict)
    """Whitened residual of each factor family: name -> (N, k), NaN where the family is absent."""
    residual_labels: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Axis labels of each residual family, with units, e.g. ``("F_x [N]", ...)``."""
    residual_sigma: dict[str, np.ndarray] = field(default_factory=dict)
    """Noise standard deviation behind each whitened residual, in the physical unit of its
    labels: name -> (k,) or (N, k).  Physical residual = whitened residual * sigma."""
    innovation: np.ndarray | None = None
    """(N, 6) EKF innovation (gyro, accelerometer), rad/s and m/s^2."""
    innovation_cov: np.ndarray | None = None
    """(N, 6, 6) its covariance."""
    time_per_step: np.ndarray | None = None
    """(N,) wall-clock seconds spent on each step (update time for the fixed-lag smoother)."""
    total_time: float = 0.0
    """Wall-clock seconds for the whole run."""
    effects: dict = field(default_factory=dict)
    """Estimated effect parameters (name -> JSON-serialisable values)."""
    meta: dict = field(default_factory=dict)
    """Free-form description of the run: the samples a sensor gate rejected, the noise sigmas, solver
    details (JSON-serialisable)."""

    def state_std(self) -> np.ndarray | None:
        """(N, 18) standard deviations of the state components (:data:`STATE_LABELS`)."""
        if self.cov is None:
            return None
        return np.sqrt(np.maximum(np.diagonal(self.cov, axis1=1, axis2=2), 0.0))

    # ------------------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write to a compressed ``.npz`` file (arrays plus a JSON header); return its path.

        The file is written aside and moved into place when complete
        (:func:`flexforce.datasets.safeio.safe_output`): an interrupted save leaves the previous
        file, and a second writer of the same file is refused with an :class:`OutputError`.
        """
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {}
        for name in ("t_ns", "R", "t", "w", "v", "dw", "a", "wrench", "cop", "cov", "wrench_cov", "contact_wrench_cov",
                     "cop_cov", "wrench_excess", "innovation", "innovation_cov", "time_per_step"):
            value = getattr(self, name)
            if value is not None:
                arrays[name] = value
        for fam, value in self.residuals.items():
            arrays[f"residual/{fam}"] = value
        for fam, value in self.residual_sigma.items():
            arrays[f"residual_sigma/{fam}"] = np.asarray(value)
        header = {"estimator": self.estimator, "contact_names": list(self.contact_names),
                  "total_time": self.total_time, "effects": self.effects, "meta": self.meta,
                  "residual_labels": {k: list(v) for k, v in self.residual_labels.items()}}
        arrays["header"] = np.array(json.dumps(header))
        with safe_output(path) as tmp:  # complete or not at all, one writer at a time
            np.savez_compressed(tmp, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Estimate:
        """Read a file written by :meth:`save`."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as f:
                header = json.loads(str(f["header"]))
                data = {k: f[k] for k in f.files if k != "header"}
        except (OSError, ValueError, KeyError) as err:
            raise DataError(f"cannot read estimate {path}: {err}; expected a file written by flexforce run") from err
        residuals = {k.split("/", 1)[1]: data.pop(k) for k in list(data) if k.startswith("residual/")}
        sigmas = {k.split("/", 1)[1]: data.pop(k) for k in list(data) if k.startswith("residual_sigma/")}
        return cls(estimator=header["estimator"], contact_names=tuple(header["contact_names"]),
                   total_time=header["total_time"], effects=header["effects"], meta=header["meta"],
                   residuals=residuals, residual_sigma=sigmas,
                   residual_labels={k: tuple(v) for k, v in header["residual_labels"].items()}, **data)
