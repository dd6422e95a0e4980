"""Lau, Bar-Joseph & Kuffner 2009."""

STAGE_MODULES = ("clips", "learn", "sample", "ik", "plots")
