"""flexforce: contact forces and floating-base kinematics of flexible legged robots.

Sub-packages (each a top-level folder of the source tree):

- :mod:`flexforce.factors`  -- the physics of the flexible-contact model (plain numpy) and its factors;
- :mod:`flexforce.smoother` -- factor-graph smoothing (batch and fixed-lag);
- :mod:`flexforce.datasets` -- Recording, robot model (pinocchio), simulator and scenarios, ROS bag I/O;
- :mod:`flexforce.compare`  -- the baseline EKF, metrics, diagnostics and reports.
"""

from flexforce.errors import FlexforceError

__all__ = ["FlexforceError", "__version__"]
__version__ = "0.1.0"
