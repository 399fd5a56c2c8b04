"""flexforce.factors."""
