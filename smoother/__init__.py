"""flexforce.smoother."""
