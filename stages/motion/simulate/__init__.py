"""Synthetic data with ground truth: procedural motion, dense-marker captures."""
