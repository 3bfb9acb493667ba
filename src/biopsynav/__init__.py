"""biopsynav."""
