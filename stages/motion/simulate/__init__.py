"""Synthetic data with ground truth: procedural motion, skinned bodies, dense-marker captures.

* motion — :mod:`.skeleton` (the 31-joint CMU-named humanoid), :mod:`.gait`
  (walk / run cycles), :mod:`.range_of_motion` (joint groups flexed in turn),
  :mod:`.motion` (their stages ``simulate_walk``, ``simulate_range_of_motion``);
* bodies — :mod:`.body` (the skinned ``Body`` type, posing and skinning),
  :mod:`.capsules` (procedural capsule bodies), :mod:`.makehuman` (the MakeHuman mesh);
* captures — :mod:`.capture` (the ``simulate_capture`` stage), :mod:`.markers`
  (marker layout, body regions), :mod:`.skin_dynamics` (bulges, jiggle,
  breathing), :mod:`.optical` (cameras, occlusion, fragmentation).
"""
