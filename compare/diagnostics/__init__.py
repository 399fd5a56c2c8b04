"""flexforce.compare.diagnostics: the model held against the measurements.

Residual consistency (:mod:`.residuals`) and the diagnosis that screens, refits and selects the
missing effects (:mod:`.diagnose`).
"""
