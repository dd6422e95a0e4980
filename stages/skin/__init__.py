"""Park & Hodgins 2006, "Capturing and Animating Skin Deformation in Human Motion".

Dense marker captures (~350 markers) are cleaned (§4, stage ``clean``), cut into
near-rigid parts on a range-of-motion trial (§5, stages ``ingest_rom``,
``segment``, ``match_markers``), and drive a detailed mesh fitted to the subject
(stages ``template_mesh``, ``fit_mesh``, ``deform``), rendered off-screen
(``render``, ``render_modes``, ``render_error``).  Each section and equation of
the paper lives in one function (modules of this package):

§4 cleaning (the stage)                  clean.clean
§4.1 labels of an unlabelled take:       labelling.reference_labelling (reference frame's
  the marker-surface vertices            trajectories), labelling.template_labelling (an
                                         earlier session's layout: labelling.match_template)
  several subjects in one take           labelling.subject_groups, labelling.fragment_subjects
  (beyond the paper)                     (each cleaned apart: clean._clean_subjects)
  reference pose                         predict.reference_pose, predict.choose_reference_frame
§4.1 marker surface                      surface.build_marker_surface (automatic: triangulate,
                                         manifold), surface.read_surface_file (manual)
  one-ring neighbours                    surface.one_ring
  local frames (t, b, n)                 surface.local_frames
§4.2 rigid prediction from >= 3          predict.predict_missing (Horn fits: predict._neighbour_fit)
  neighbours, greedy, estimates re-used
  trajectory merging                     merge.merge_fragments (rounds: merge._merge_rounds)
  ε₁ = α₁·d̄, ε₂ = α₂·d̄                   merge._tolerances
  entry / tube / ambiguity tests         merge._judge_fragment
  another unmerged fragment as close     merge._rival_fragment
  in the same frames (beyond the paper)
  a missing marker with no prediction    merge._blind_rival
  near the chosen one (beyond the paper)
  a missing marker near the chosen one   merge._swap_rival
  with the chosen one seen as another
  unmerged fragment (beyond the paper)
  continuity across a break or short     merge.continue_breaks (carried by the
  gap (beyond the paper)                 neighbours' rigid motion: merge._carry;
                                         longest gap: merge.bridge_frames)
  fragments left, against the final      assign.assign_fragments (exact gaps:
  filling, jointly (beyond the paper)    assign._exact_gap_jumps; one assignment per
                                         frame window: assign._decide); rounds:
                                         clean._fill_merge_rounds
§4.3 hole filling (dispatcher)           fill.fill_holes
  local PCA of marker + one-ring,        local_pca.train_local_pca
  training frames aligned (P&H Eq. 5)
  coefficients from visible members      local_pca.model_estimates_batch
  average of the models with the marker  fill._average_estimates
  passes re-using estimates              fill.fill_by_local_pca
  sparse captures (beyond the paper):    fill_blend.fill_by_validated_blend (each run of
  local fill, whole-body PCA without     holes scored on copies of it moved nearby:
  complete frames, spline, rigid body,   fill_blend._shifted_runs, where the marker
                                         moves as at the run's ends:
                                         fill_blend._placed_copies, fill_blend.MOTION_MATCH,
  blended by validation on the take      fill_blend._validation_errors; models compared
                                         on the copies they all reached:
                                         fill_blend._validation_mse; on long runs per
                                         distance from the nearer measured end:
                                         fill_blend._validation_profile),
                                         lowrank.whole_body_pca, fill_blend._rigid_body_fill
                                         (most rigid / nearest donors) at least a share of
                                         the carries' disagreement:
                                         fill_blend.RIGID_DISAGREEMENT_SHARE, at least its
                                         miss at the gap's ends beyond the trajectory's own:
                                         fill_checks._end_excess; a member the
                                         gap shows far off (from the others, or missing the
                                         trajectory at the gap's ends) left out:
                                         fill_checks._outlying_estimates,
                                         fill_checks._boundary_misses; what the take's
                                         samples never do (off the rigid partners, a jump
                                         beyond the fastest step, erratic) left out:
                                         fill_checks._keep_plausible,
                                         fill_checks._jumps_in_runs; the spline not
                                         through a one-frame glitch beside the gap:
                                         fill_checks._isolated_spikes
§4.4 smoothing x ← x − λ Δ⁴x in the      clean.smooth_local (the iteration, every run
  local frames                           at once: clean._smooth_runs)
§5.1–5.2 near-rigid segmentation         segment.segment
  triangle rotation sequences            segment.triangle_rotations, segment.rotation_features
  mean-shift clustering                  segment.mean_shift
  markers' parts, clean-up               segment.marker_labels_from_triangles,
                                         segment.clean_up_parts
  soft weights α (Gaussian likelihood    segment.soft_weights
  of the rigid-fit error, α < 0.2 out)
  part local frames                      segment.part_frames
  the parts (type, codec)                segmentation.Segmentation
  range-of-motion trial                  rom.ingest_rom, rom.match_markers
§5.3 detailed mesh registration          mesh_fit.fit_detailed_mesh (Allen et al. 2003 style);
                                         below the density, mesh_fit.upright_fit (named
                                         markers on their region: marker_regions), the
                                         limbs turned to named joint markers
                                         (mesh_fit._posed_fit, limb_pose.pose_limbs; an
                                         addition)
  vertex weights β (barycentric α)       binding.bind_mesh (a limb's skin held to its
                                         limb's and the body's parts: limb_pose.limb_binding)
  rigid: Horn per part                   parts._rigid_fits (in parts.fit_part)
  quadratic p̂ ≈ A q(p̄) (P&H Eq. 6)       parts._quadratic_fits, kernels.quadratic_basis
  RBF residual, cubic B-spline           parts._residual_fits, kernels.rbf_matrix,
  (P&H Eq. 7)                            kernels.cubic_bspline, kernels._solve_kernel
  vertices moved and blended             parts.evaluate_part, blend.vertex_operator,
  (P&H Eq. 8–9)                          blend.deform_positions (bit-reproducible:
                                         sparse rows, sums in a fixed order, no BLAS);
                                         the stage deform.deform
rendering (Figure 7: modes side by side) render.render_frames, render.render_modes

Departures from the paper (each module docstring says why, with measurements):

* the marker surface is automatic, not hand-made (triangulate, manifold), and
  every neighbour carries a rigidity weight, with rigid two-ring supplements
  where the one-ring straddles a joint (rigidity);
* merging: predictions carry the marker's own local coordinates from the ends
  of its gap (predict.local_targets), are trusted one depth at a time, a
  fragment must stay within ε₁ on average, rivals within AMBIGUITY_RATIO make it
  ambiguous, d̄ is capped by the nearest-marker distance, and fragments left
  are judged again against the PCA fill (clean._pca_merge_rounds, param
  ``pca_merge_rounds``), then against the final filling, jointly: a fragment
  that continues an exact gap, else one assignment problem per frame window
  (linear_sum_assignment, ε₁ the cost cap, refused within
  assign.ASSIGNMENT_RATIO; param ``fill_merge_rounds``; the paper merged the
  rest by hand);
* hole filling: the default is a wider regression (``fill_model="regression"``:
  fill.fill_by_regression, regress.regression_estimates), the paper's local PCA
  fills what it cannot reach (``"pca"``: the paper alone); on captures of at
  most fill_blend.WHOLE_BODY_MAX_MARKERS (120) markers the fill is then blended with a
  whole-body PCA (Gløersen & Federolf R2 trained on the filled take, no complete
  frame needed), a spline in time and a rigid-body fill, weighted per run of
  holes by their errors on copies of it knocked out nearby, where the marker moves
  as at the run's ends (fill_blend.fill_by_validated_blend); a neighbour's model
  weighs fill.NEIGHBOUR_MODEL_WEIGHT (0.1) in the §4.3 average; interior holes no
  model reaches are interpolated in time, then rigidly predicted
  (fill.fill_by_rigid_fit);
* smoothing: measured runs only (filled samples keep the fill's estimate),
  measurements moved by at most clean.MAX_CORRECTION_SIGMA noise deviations,
  rarely measured neighbours out of the frames (clean.frame_weights);
* segmentation: the clean-up of the clusters is automatic (``merge_rms``,
  ``min_part_markers``, ``n_parts``; the paper adjusted its parts by hand), the
  Gaussian width is relative to each marker's best fit unless ``sigma`` is set;
* deformation: sharpened weights β ∝ β_bary^4 (``beta_sharpness``), a ridge
  toward rigid on the quadratic (``quadratic_damping`` 0.3; 0 = P&H Eq. 6), an
  optional thin-plate residual (``residual_kernel``), the B-spline dilation
  shrunk until the system is well conditioned (kernels._well_conditioned_kernel),
  the quadratic held at the edge of its markers' box (``support_margin``,
  parts.PartModel.basis) and each vertex's non-rigid displacement softly clamped
  at the part markers' deviation from rigid (``clamp_margin``, parts.soft_clamp);
  β diffused over the mesh where a blend between parts would stretch an edge
  beyond ``max_blend_stretch`` (2.5; widening._widen_blends,
  binding.blend_smoothing_operator); with ``unflip`` (the graph's config) the
  vertices of triangles turned over against the rigid mode pulled back
  (deform.unflip_triangles); the paper exactly: ``beta_sharpness=1,
  quadratic_damping=0, residual_kernel="cubic_bspline", support_margin=None,
  clamp_margin=None, max_blend_stretch=None`` (and ``unflip`` false).
"""

#: The modules of this family that register stages, codecs or exporters, each with
#: the names of the stages it defines: the ``mocapflow.stages`` entry point of the
#: family names this mapping, so the engine imports only the module of a stage it
#: needs (tests/test_architecture.py checks the names against the decorators).
STAGE_MODULES = {
    "clean": ("clean",),
    "rom": ("ingest_rom", "match_markers"),
    "segment": ("segment",),
    "segmentation": (),
    "mesh_fit": ("fit_mesh", "template_mesh"),
    "deform": ("deform",),
    "render": ("render", "render_error", "render_modes"),
    "report_figures": (),  # figures of the report page (mocapflow report)
}
