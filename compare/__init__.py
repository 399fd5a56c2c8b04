"""flexforce.compare."""
