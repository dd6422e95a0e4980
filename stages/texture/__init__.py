"""Moradoff 2002."""

STAGE_MODULES = ("pyramid", "synth", "stickfigure")
