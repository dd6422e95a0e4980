"""Moradoff 2002, "Constrained Synthesis of Textural Motion for Animation".

An input motion is turned into a Gaussian tree over its joint angles (stage
``pyramid``) and synthesized, coarsest level first, into a longer (or looping,
constrained, path-following) motion (stage ``synth``); ``stickfigure`` renders
a strip of poses.  Each section of the thesis lives in one function (modules
of this package); the module docstrings cite the neighbourhood search,
meeting points and son selection together as Moradoff §3.5–3.7, and so does
this table:

Moradoff §3.4 Gaussian multi-resolution   pyramid.build_pyramid (the stage: pyramid.pyramid)
  tree over the joint angles              levels by rate: pyramid.levels_for_rate
  binomial filter, filter size 4          pyramid.binomial_filter, pyramid.downsample
  quaternion-aware filtering              pyramid.downsample_quaternions
  root as heading-frame velocities        pyramid.root_features
  3-D pose representation per level       pyramid.level_positions
Moradoff ch. 3 the synthesis (the stage)  synth.synth: inputs checked (synth._levels_used,
                                          synth._check_constraints), source track
                                          (synth.synthesize_source), motion
                                          (assemble.assemble_motion), report (synth._synth_report)
  constraints as anchors on every level   synth._anchors (i >> l at j >> l)
Moradoff §3.5–3.7 neighbourhood distance  neighbourhood.window_cost (per slot pair:
  on velocities, ‖d‖∞ + ‖d‖₀.₅             neighbourhood.slot_distance; features and cost unit:
                                          neighbourhood.level_view; slot weights:
                                          neighbourhood.slot_pair_weights; per pair:
                                          neighbourhood.pair_distance, tabulated for the
                                          coarsest search: neighbourhood.pair_tables)
  three-level neighbourhood (ancestor,    search.LevelSearch.cost_rows (search.LevelSearch.cost,
  current, finer)                         ._ancestor_cost, ._finer_cost)
  random choice among the k best          search.LevelSearch.choose, search.LevelSearch._draw
  coarsest level: gaps grown from both    search.LevelSearch.fill_gap (both fronts in one
  anchors, alternating fronts that see    output, SearchParams.alternate; one node:
  each other                              search.LevelSearch.fill); coarsest level driven by
                                          synth._coarsest_level
  meeting point: the summed sequence      search.LevelSearch._meet (±meeting_window around
  cost decides                            where the fronts met; search.LevelSearch.sequence_costs);
                                          refine.LevelRefinement._rejoin (searched again at
                                          every finer level; followed to its finest seam:
                                          synth._follow_meetings)
  level weights (the thesis weights the   synth params ancestor_weight, current_weight,
  coarser level higher)                   finer_weight -> SearchParams.level_weights; default
                                          1/1/1, measured (a departure, below)
  constrained frames with their           refine.LevelRefinement._join_windows (no join
  neighbourhood                           within ``slots`` of a constraint)
  son selection                           refine.LevelRefinement.son_track (the level:
                                          refine.LevelRefinement.refine)
  candidate acceleration (children of     refine.LevelRefinement._candidate_lines,
  the parent's 3 best ±candidate_range)   search.LevelSearch.candidates
  pose term of a finest-level join (an    refine.LevelRefinement.line_costs and
  addition: SearchParams.pose_weight,     ._pose_lines (neighbourhood.pose_distance,
  pose_lines, pose_span)                  6-D joint rotations)
  max_run kept by the finer levels        refine.LevelRefinement._join_windows, ._rejoin
                                          (._run_cap, ._verbatim_start)
  a front after a settled run (same       search.LevelSearch.after_run_costs (read by
  costs, tabulated once per level)        search.LevelSearch.fill and ._jump_earlier; row
                                          minima: .jump_costs)
Moradoff §3.7.2 graph path                graph.transition_costs, graph.transition_graph,
                                          graph.graph_path (DFS under a cost bound, keeping
                                          max_run: graph._min_cost_to_end, graph._run_limit_kept,
                                          nodes without a jump edge given their cheapest
                                          jump where it cannot: graph._with_escapes;
                                          variety / usage_weight draw: graph.jump_window,
                                          graph._drawn_order); per gap: synth._graph_level
                                          (run limit less refinement's reach:
                                          synth._graph_run_limit)
seams cross-faded between their two      smoothing.transition_blend (before the smoothing;
input lines (an addition)                 the feet follow the mix: assemble._planted_velocity,
                                          assemble._foot_ik)
Moradoff §3.8 adaptive local smoothing    smoothing.adaptive_smoothing (with the input's floor
                                          and jerk limit: assemble._smooth_seams)
  after every level (``smooth_levels``)   assemble.smooth_level (a coarser level's output in its
                                          own representation), read by the next finer level's
                                          ancestor windows: synth._SmoothedParentRefinement
  acceleration test                       smoothing.seam_test
  Gaussian of width 5 on quaternions      smoothing.gaussian_taps, smoothing.filter_quaternions
                                          (only the frames inside a window are filtered)
  constrained frames pinned               smoothing._pin
Moradoff §3.10 root trajectory            root.integrate_root (placed at the first constraint:
                                          assemble._place_root)
  new root paths (polyline, spline,       root.PathCurve, root.follow_path, root.figure_eight
  e.g. a figure-8)                        (warnings: assemble._place_root)
closed paths looped (not in the thesis)   root.follow_path (``cyclic``: stride paced to whole
                                          laps, root.PACE_TOLERANCE); legs take up the paced
                                          root (assemble.PATH_IK in assemble._foot_ik)
loops (cyclic output; not in the thesis)  the ``loop`` param: wrapped gaps (search.gaps_of),
                                          wrapped positions in search.LevelSearch and
                                          refine.verbatim_runs, the last → first seam smoothed
                                          (smoothing.adaptive_smoothing, ``cyclic``)
stance feet (after smoothing)             root.plant_feet (assemble._planted_velocity),
                                          root.foot_corrections, root.apply_foot_ik,
                                          root.two_bone_ik, root.leg_chains (assemble._foot_ik)

Departures from the thesis (the module docstrings say why):

* any output length (not a multiple of the input's), any number of meeting
  points per output (one per gap), loops (synth);
* variety: at the coarsest level the k best are drawn only within the
  ``variety`` quantile of the input's own best-jump costs
  (search.LevelSearch.jump_threshold; ``variety=1`` is the thesis' plain draw
  among the k best), ranked by cost plus ``usage_weight`` windows per use of
  the input they would play next (coverage), a new draw only once the last
  transition has ``slots`` verbatim nodes behind it
  (search.LevelSearch._settled), and a run reaching ``max_run`` of the input
  must jump where the jump fits best (search.LevelSearch._jump_earlier); the
  graph path draws its successors the same way (graph.graph_path), its cost
  bound widened by one ``variety`` window per jump ``max_run`` forces;
* levels: 4 at 30 fps and one more per doubling of the rate by default
  (pyramid.levels_for_rate; the thesis used 3-5 at 30 fps);
* paths: the sway kept around the path is high-passed again, a loop on a
  closed path is paced to whole laps and the legs take up the paced root
  (root, assemble.PATH_IK);
* level weights: equal by default.  Weighting the coarser level higher, as the
  thesis does (ancestor 2 : current 1 : finer 0.5), raised the GANimator local
  diversity (patch distance to the input, lower is better) on all three benchmark
  inputs (1,024 frames, seeds 0-2: salsa 0.141 -> 0.165, walk 0.216 -> 0.266,
  figure-8 walk 0.183 -> 0.217) with jerk and skate about equal;
* smoothing runs once, at the finest level, by default; ``smooth_levels="every"``
  smooths every level as the thesis does (each coarser level before the next finer
  one is refined from it).  It measured no better (``benchmarks/texture.py --seeds 5
  --no-speed --no-cases --smooth-levels every``, 1,024 frames from the first 512
  input frames (the whole take when shorter) at 30 fps, seeds 0-4, finest ->
  every): seam jerk-p99 ratio salsa 0.55 -> 0.43, walk 0.75 -> 0.74, figure-8 walk
  0.87 -> 0.89; skate ratio 0.93 -> 0.93, 0.97 -> 0.96, 0.96 -> 0.93; coverage 1.00
  on all; GANimator local diversity 0.157 -> 0.148, 0.211 -> 0.205, 0.175 -> 0.169
  but global diversity 0.165 -> 0.147, 0.192 -> 0.180, 0.164 -> 0.166 (closer to the
  input on both, as a lower ``variety`` is); CPU s (pyramid + synthesis) 0.21 ->
  0.24, 0.17 -> 0.21, 0.19 -> 0.22; and the figure-8 walk's longest verbatim run
  leaves ``max_run`` + 5 % of the input (93 frames): 96 in seeds 0-4 (finest 86),
  over it in 4 of seeds 0-19 (up to 105; finest at most 91);
* smoothing: a seam also fails the test while its jerk exceeds
  ``jerk_tolerance`` × the input's p99 jerk (smoothing.seam_test, over the whole
  cross-fade); its frame counts are the thesis' at 30 fps and scale with the
  synthesis rate (smoothing.SMOOTHING_RATE);
* seams are first cross-faded between the two input lines they join
  (``transition_blend`` 0.33 s, smoothing.transition_blend): the Gaussian alone
  low-passes the frames around a seam, which leaves the input's patch space
  (GANimator local diversity); the search's pose term compares 6-D joint rotations
  and is on (``pose_weight`` 0.03, ``pose_lines`` 2), with ``variety`` 0.45 and
  ``max_run`` 0.25 — the measurements are in search.SearchParams.  Where the local
  diversity comes from (1,024 frames from the first 512 input frames, seeds 0-2, per
  15-frame output window): only the windows that touch a seam count (verbatim windows 0,
  windows only the foot IK changed 0.005-0.012); in the windows the Gaussian reaches
  (38-52 % of them) the cut itself, copied with no fade, already costs salsa 0.284, walk
  0.233, figure-8 walk 0.198 per window, and the cross-fade, the Gaussian and the foot
  IK raise that to 0.336, 0.320, 0.250 (windows with a fade only: 0.256 -> 0.277, 0.207
  -> 0.251, 0.174 -> 0.204).  Left out as measured no better: GenMM-style voting of the
  nearest input patches over the frames the fade and the Gaussian rewrote (1-3 rounds):
  15-frame patches widen every fade (salsa 0.158 -> 0.18), 5-7-frame ones lower the
  local diversity (walk 0.190 -> 0.17) only with the jerk at 1.3-2.2 × the input's, and
  not once the seam test smooths the voted seams again; and the shortest cross-fade (¼,
  ½, ¾ of ``transition_blend``) that passes the seam test (walk 0.190 -> 0.188).  A
  stronger pose term trades local for global diversity (seeds 0-4, ``pose_weight`` 0.15,
  ``pose_lines`` 4, ``transition_blend`` 0.6: local diversity ÷ the GenMM baseline's
  salsa 1.51 -> 1.27, walk 1.46 -> 1.13, figure-8 walk 1.08 -> 1.00; global diversity
  0.144 -> 0.123, 0.182 -> 0.149, 0.210 -> 0.192 against the baseline's 0.108, 0.162,
  0.210).

How refinement keeps the coarse plan (the drawn line tried first, joins
``MIN_RUN_FRAMES`` apart, no bridge of a few frames into the input's end) is
in :mod:`~mocapflow.stages.texture.refine`.
"""

#: The modules of this family that register stages, codecs or exporters, each with
#: the names of the stages it defines: the ``mocapflow.stages`` entry point of the
#: family names this mapping, so the engine imports only the module of a stage it
#: needs (tests/test_architecture.py checks the names against the decorators).
STAGE_MODULES = {
    "pyramid": ("pyramid",),
    "synth": ("synth",),
    "stickfigure": ("stickfigure",),
    "report_figures": (),  # figures of the report page (mocapflow report)
}
