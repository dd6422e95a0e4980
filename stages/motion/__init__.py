"""Shared motion types, formats, kinematics, ingest/export and simulators."""

#: Modules of this package that register stages, codecs or exporters (the
#: ``mocapflow.stages`` entry point ``motion`` names this tuple).
STAGE_MODULES = (
    "datatypes",
    "formats.strokes",
    "ingest",
    "export",
    "simulate.motion",
    "simulate.capture",
)
