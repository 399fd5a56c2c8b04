"""flexforce.datasets.sim: the simulator (pinocchio's multibody dynamics), its scenarios and the hidden
effects it plays as ground truth.

Independent of the estimators: it imports the data types and the robot model, nothing of
:mod:`flexforce.factors`, :mod:`flexforce.smoother` or :mod:`flexforce.compare`.
"""
