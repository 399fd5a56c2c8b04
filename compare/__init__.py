"""flexforce.compare: the seed paper's EKF (the baseline), metrics, diagnostics and reports."""
