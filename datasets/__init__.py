"""flexforce.datasets."""
