"""flexforce.compare.ekf: the seed paper's extended Kalman filter, the baseline the smoothers are
benchmarked against.

:mod:`.filter` holds the filter (:class:`EKF`, :func:`run_ekf`); :mod:`.kernel` its compiled step.
"""

from flexforce.compare.ekf.filter import (
    EKF,
    IMU_LABELS,
    STATE_LABELS,
    EKFConfig,
    noise_model,
    paper_to_world,
    run_ekf,
    world_to_paper_cov,
)

__all__ = ["EKF", "EKFConfig", "run_ekf", "noise_model",
           "STATE_LABELS", "IMU_LABELS", "paper_to_world", "world_to_paper_cov"]
