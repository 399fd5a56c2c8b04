"""flexforce.smoother: factor-graph smoothing of the flexible-contact model (batch and fixed-lag)."""
