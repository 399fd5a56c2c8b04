"""flexforce.compare.diagnostics: the model held against the measurements.

Residual consistency (:mod:`.residuals`) and the diagnosis that screens, refits and selects the
missing effects (:func:`diagnose`, tuned by a :class:`DiagnoseConfig`).  Inside: :mod:`.config`
(the tuning), :mod:`.candidates` (the effect registry, factories, plugins), :mod:`.fitting` (fits,
the refit's watch, the score), :mod:`.screening` (score tests, identifiability, the refit choice),
:mod:`.constancy` and :mod:`.checks` (a taken effect's checks), :mod:`.selection` (the rounds, the
second look), :mod:`.session` (a diagnosis's shared state), :mod:`.results` (typed results),
:mod:`.text` (their sentences) and :mod:`.diagnose` (the entry point).
"""

from flexforce.compare.diagnostics.config import DiagnoseConfig
from flexforce.compare.diagnostics.results import Candidate, Diagnosis, Snapshot
from flexforce.compare.diagnostics.run import diagnose, identifiability

__all__ = ["Candidate", "DiagnoseConfig", "Diagnosis", "Snapshot", "diagnose", "identifiability"]
