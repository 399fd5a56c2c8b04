"""flexforce: contact forces and floating-base kinematics of flexible legged robots.

The public API (``import flexforce as ff``)::

    rec = ff.simulate("stand", seed=1)                  # or ff.load_recording(path, robot="icub"),
                                                        # or ff.Recording.from_arrays(...)
    est = ff.run_estimator("fixed-lag", rec)            # an Estimate; run_ekf/run_batch/run_fixed_lag
    comp = ff.compare_estimators(rec, estimators=("ekf", "batch"))  # metrics against the truth
    diag = ff.diagnose(rec)                             # which effects the nominal model misses

=========================  ======================================================================
data                       :class:`Recording` (what an estimator reads), :class:`Estimate` (what
                           it returns), :class:`RobotConfig` (a robot's TOML), :class:`ModelConfig`
                           (an estimator's model of the robot)
recordings                 :func:`load_recording` (a bag), :func:`simulate` (a scenario),
                           :meth:`Recording.from_arrays` (plain arrays)
estimators                 :func:`run_estimator` by name; :func:`run_ekf` with :class:`EKFConfig`,
                           :func:`run_batch` with :class:`BatchConfig`, :func:`run_fixed_lag`
                           with :class:`FixedLagConfig`
comparison, diagnosis      :func:`compare_estimators`, :func:`diagnose`
effects                    :class:`Effect` (the protocol of a model extension), :data:`EFFECTS`
                           (the catalogue: name -> class)
errors                     :class:`FlexforceError` and one subclass per layer: :class:`ConfigError`,
                           :class:`DataError` (:class:`BagError`), :class:`ModelError`,
                           :class:`EstimatorError`, :class:`OutputError`
=========================  ======================================================================

Everything else lives in the sub-packages (each a top-level folder of the source tree):
:mod:`flexforce.factors` (the physics and the effects), :mod:`flexforce.smoother` (factor-graph
smoothing), :mod:`flexforce.datasets` (data types, robots, bag I/O, the simulator),
:mod:`flexforce.compare` (the EKF, metrics, diagnostics, reports).
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import TYPE_CHECKING, Any

from flexforce.errors import (
    BagError,
    ConfigError,
    DataError,
    EstimatorError,
    FlexforceError,
    ModelError,
    OutputError,
)

# The sub-packages are other folders of the source tree ([tool.setuptools.package-dir]): run from the
# repository's root, this folder is found first (the current directory leads sys.path) and holds none of
# them; they are then taken from the installed copy's flexforce folder further down sys.path (a strict
# editable install's link tree).  An installed copy alone has one such folder: nothing changes.
__path__ = pkgutil.extend_path(__path__, __name__)

if TYPE_CHECKING:
    from flexforce.api import load_recording, simulate
    from flexforce.compare.diagnostics import diagnose
    from flexforce.compare.ekf import EKFConfig, run_ekf
    from flexforce.compare.estimators import run_estimator
    from flexforce.compare.runner import compare as compare_estimators
    from flexforce.datasets.estimate import Estimate
    from flexforce.datasets.recording import Recording
    from flexforce.datasets.robot import RobotConfig
    from flexforce.factors.effects import EFFECTS, Effect
    from flexforce.factors.model import ModelConfig
    from flexforce.smoother import BatchConfig, FixedLagConfig, run_batch, run_fixed_lag

__version__ = "0.1.0"

__all__ = [
    "Recording", "Estimate", "RobotConfig", "ModelConfig",
    "load_recording", "simulate",
    "run_estimator", "run_ekf", "EKFConfig", "run_batch", "BatchConfig", "run_fixed_lag", "FixedLagConfig",
    "compare_estimators", "diagnose",
    "Effect", "EFFECTS",
    "FlexforceError", "ConfigError", "DataError", "BagError", "ModelError", "EstimatorError", "OutputError",
    "__version__",
]

_LAZY = {
    "Recording": "flexforce.datasets.recording",
    "Estimate": "flexforce.datasets.estimate",
    "RobotConfig": "flexforce.datasets.robot",
    "ModelConfig": "flexforce.factors.model",
    "load_recording": "flexforce.api",
    "simulate": "flexforce.api",
    "run_estimator": "flexforce.compare.estimators",
    "run_ekf": "flexforce.compare.ekf",
    "EKFConfig": "flexforce.compare.ekf",
    "run_batch": "flexforce.smoother",
    "BatchConfig": "flexforce.smoother",
    "run_fixed_lag": "flexforce.smoother",
    "FixedLagConfig": "flexforce.smoother",
    "compare_estimators": "flexforce.compare.runner",
    "diagnose": "flexforce.compare.diagnostics",
    "Effect": "flexforce.factors.effects",
    "EFFECTS": "flexforce.factors.effects",
}
"""Public name -> the module it comes from, imported on first use: ``import flexforce`` stays quick
(numpy, pinocchio, numba and gtsam load with the first name that needs them)."""

_SOURCE_NAME = {"compare_estimators": "compare"}
"""Public name -> its name in its module, where the two differ."""


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    # ``compare_estimators`` is the runner's ``compare`` (``flexforce.compare`` names the sub-package)
    value = getattr(importlib.import_module(module), _SOURCE_NAME.get(name, name), None)
    if value is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r} ({module} lacks it)")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
