"""Motion-quality and novelty metrics."""
