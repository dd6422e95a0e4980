"""The shared motion domain: types, formats, kinematics, geometry, contacts, ingest/export,
simulators.  Every paper package builds on it; it imports only the engine.

* **types** — :mod:`.datatypes`: ``Markers``, ``Skeleton``/``Motion``, ``Mesh``,
  ``Strokes``/``StrokesSet`` and their exact Zarr codecs (metres, frame-major).
* **formats** — :mod:`.formats`: ``c3d`` (via ezc3d, validated first), ``bvh``,
  ``asf`` (ASF skeletons, AMC motions), ``strokes`` (UCI, Omniglot, our CSV),
  ``text`` (decoding shared by the text formats).
* **kinematics** — :mod:`.rotations` (quaternion algebra, Euler angles, rotation
  tracks: continuity, heading), :mod:`.kinematics` (forward kinematics, End
  Sites, global positions, resampling), :mod:`.absolute_orientation` (Horn's
  rigid fit of point sets, batched).
* **geometry** — :mod:`.geometry`: mesh vertex normals.
* **contacts** — :mod:`.contacts`: runs of ``True``, toe and foot joints, foot contacts.
* **ingest / export** — :mod:`.ingest` (the ``ingest_*`` stages: one file in, one
  stored type out), :mod:`.export` (the exporters of ``mocapflow export``),
  :mod:`.mesh_export` (the ``mesh`` exporter: OBJ + PC2, VTP series, PLY).
* **simulate** — :mod:`.simulate`: synthetic data with ground truth (procedural
  skeleton, walk/run and range-of-motion stages, skinned bodies, the dense-marker
  capture stage).
"""

#: The modules of this family that register stages, codecs or exporters, each with
#: the names of the stages it defines: the ``mocapflow.stages`` entry point of the
#: family names this mapping, so the engine imports only the module of a stage it
#: needs (tests/test_architecture.py checks the names against the decorators).
STAGE_MODULES = {
    "datatypes": (),
    "ingest": ("ingest_amc", "ingest_bvh", "ingest_c3d", "ingest_strokes", "ingest_strokes_set"),
    "export": (),
    "mesh_export": (),
    "simulate.motion": ("simulate_range_of_motion", "simulate_walk"),
    "simulate.capture": ("simulate_capture",),
}
