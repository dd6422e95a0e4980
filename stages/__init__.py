"""The motion-capture domain of mocapflow, one package per concern.

* :mod:`mocapflow.stages.motion` — the shared motion types, file formats,
  kinematics, ingest/export, shared geometry and contact helpers, simulators;
* :mod:`mocapflow.stages.skin` — Park & Hodgins 2006 (skin deformation);
* :mod:`mocapflow.stages.texture` — Moradoff 2002 (textural motion synthesis);
* :mod:`mocapflow.stages.variation` — Lau, Bar-Joseph & Kuffner 2009 (variation);
* :mod:`mocapflow.stages.metrics` — motion-quality and novelty metrics.

Importing a module imports only what it uses.  Each stage family registers its
stages with the engine through its own ``mocapflow.stages`` entry point (the
family's :func:`register`), so the engine loads a family only when it needs it.
A paper package imports :mod:`~mocapflow.stages.motion` and
:mod:`~mocapflow.stages.metrics`, never another paper's package.
"""
