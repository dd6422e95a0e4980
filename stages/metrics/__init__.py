"""Metrics of the benchmarks, after the definitions of ``shared/METRICS.md``.

Imports only :mod:`mocapflow.stages.motion`; registers nothing.

§1 Texture synthesis — :mod:`.quality`

* patch features (6-D rotation of every joint, root translation excluded)
  → :func:`~.quality.rotation_features`;
* diagonal cumulative sum ``C[t+1, k+1] = C[t, k] + c[t, k]`` (every window
  cost ``W(i, k, T)`` as a difference) → :func:`~.quality.diagonal_cumsum`;
* local diversity (T = 15, last window excluded) → :func:`~.quality.local_diversity`;
  coverage (T = 30, threshold 2.0, input → output) → :func:`~.quality.coverage`;
  global diversity (segments ≥ 30 frames) → :func:`~.quality.global_diversity`;
  all three → :func:`~.quality.patch_metrics`;
* seams: per-frame mean ‖acceleration‖ / ‖jerk‖ of FK positions
  → :func:`~.quality.acceleration_per_frame`, :func:`~.quality.jerk_per_frame`;
  their p99 (2 frames trimmed, overall or within a mask) →
  :func:`~.quality.acceleration_p99`, :func:`~.quality.jerk_p99`; the
  transitions and their ±5 frames → :func:`~.quality.seams_from_source`,
  :func:`~.quality.seam_mask`;
* verbatim-copy baseline (longest run copied consecutively)
  → :func:`~.quality.longest_verbatim_run`;
* foot skate (horizontal toe speed on contact frames) → :func:`~.quality.foot_skate`,
  contact frames by :func:`mocapflow.stages.motion.contacts.foot_contacts`.

§2 Variation, novelty — :mod:`.novelty`

* longest run of output frames equal to consecutive input frames
  → :func:`~.novelty.longest_copied_run`;
* DTW-aligned pose distance → :func:`~.novelty.dtw`, :func:`~.novelty.aligned_distance`;
  nearest pose → :func:`~.novelty.nearest_pose_distance`;
* temporal variation (std of the DTW warp slope) → :func:`~.novelty.warp_slope_std`;
* all of them, outputs against inputs and among the inputs → :func:`~.novelty.novelty_report`.

§3 Marker cleaning — :mod:`.cleaning`

* the protocol's deletions (originally visible samples; independent or
  clustered gaps) → :func:`~.cleaning.gap_mask`;
* wrong labels (P&H Table 1) against the true fragment map → :func:`~.cleaning.score_merges`;
* error over mean neighbour distance per body region (P&H Table 2)
  → :func:`~.cleaning.region_errors`.

§4 Skin deformation artifacts — :mod:`.mesh`

* triangles stretched beyond a factor of their rest edge lengths in some frame
  → :func:`~.mesh.stretched_triangles`; turned over against a reference
  deformation (the rigid mode) → :func:`~.mesh.flipped_triangles`; the
  measures themselves → :func:`~.mesh.triangle_edge_lengths`,
  :func:`~.mesh.triangle_normals`.
"""
