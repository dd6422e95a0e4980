"""Lau, Bar-Joseph & Kuffner 2009, *Modeling Spatial and Temporal Variation in Motion Data*.

A few similar clips → a second-order dynamic Bayesian network (prior and
transition networks, greedy structure search scored by leave-one-out kernel
regression) → sampled spatial and temporal variants → IK clean-up of the feet.

Paper → function (modules of ``mocapflow.stages.variation``):

§4 input clips
    motion ↔ DOF trajectories (root heading) → ``dofs.motion_to_dofs``, ``dofs.dofs_to_motion``
    the clips type; motions, pen strokes ↔ clips → ``clips.Clips``,
    ``clips.clips_from_motions``, ``clips.clips_from_strokes``
    clips from ingested parts → ``inputs.clips`` (the ``clips`` stage); one cyclic
    take cut into cycles → ``cycles.cut_cycles``
§5 prior network (``X[0], X[1]``)
    instances → ``training.prior_data``; structure → ``search.search_prior``
§5 transition network (``X[t], X[t+1] → X[t+2]``)
    instances → ``training.transition_data``; structure → ``search.search_transition``
Lau Eq. 5–6 conditional densities
    kernel regression on the k nearest instances → ``kernel.kernel_regression``;
    bandwidth → ``kernel.bandwidth2``
§5 leave-one-out kernel-regression score
    → ``scores.prior_node_fit`` (many parent sets at once: ``scores.prior_node_fits``),
    ``scores.transition_node_fits`` (one-step or propagated)
§5 greedy structure search
    prior: add / delete / reverse with restarts → ``search.search_prior``;
    transition: add / delete per node → ``search.search_transition``;
    learning composed → ``learn.learn`` (the ``learn`` stage); the model →
    ``model.VariationModel``
§6 sampling (spatial variation)
    prior network, frames 0 and 1 → ``sample.Sampler.sample_prior``; one step of
    the transition network (Eq. 5–6 for every DOF, batched over agents) →
    ``sample.Sampler.transition``; the network unrolled, frame by frame for any
    number of agents → ``sample.Sampler.stream``; cut into variants →
    ``sample.Sampler.run``; into consecutive loopable cycles →
    ``sample.Sampler.cycles``; the stage (``variants`` and the ``predicted``
    means) → ``sample.sample``
temporal variation
    → ``sample.Sampler.run``: the second-order transition network regresses the
    delta on position and velocity (``training.transition_data``), so timing
    varies with the draws; cyclic variants are whole cycles (``one_cycle``), so
    their lengths vary as the inputs'; the inputs' time warps onto a reference
    cycle → ``warp.time_warps`` (in ``learn.learn``), one drawn per variant →
    ``warp.sample_time_warp``, played → ``warp.apply_time_warp`` (in ``sample.sample``)
§7 IK clean-up, Lau Eq. 7 with w₁ = 1, w₂ = 5 and q̄ = the predicted mean
    Eq. 7 without constraints over a clip, within joint limits →
    ``ik_solver.eq7_track``; one limb over a clip with its targets →
    ``ik_solver.solve_limb`` (by ``ik_solver.projected_gauss_newton``); joint
    limits from the inputs' range → ``ik.joint_limits``; contacts (whole
    stances, ``ik.stance_runs``) and targets → ``ik._clip_constraints``,
    ``ik._limb_constraints``; a clip cleaned → ``ik._clean_clip``; the stage → ``ik.ik``
§8 noise baselines and amplitude matching
    → ``sample.strawman_noise``, ``sample.perlin_noise``, ``sample.matched_amplitude``;
    the stage → ``sample.sample_noise``
§9 selection of similar inputs
    threshold from a trusted set → ``similar.likelihood_threshold``; removal →
    ``similar.select_similar`` (both score with ``similar.heldout_log_likelihood``);
    in the ``clips`` stage with ``similar_threshold``
Fig. 1 (right), Fig. 6
    → ``plots.variation_plots``

Departures the module docstrings state (each can be switched off):

* per-node bandwidth chosen by held-out likelihood when ``kernel_width=None``
  (``kernel.bandwidth2``, ``kernel.KERNEL_GRID``);
* offset retention ``λ`` of the transition mean, ``half_life`` (``training.retention_of``),
  lowered per DOF to the value calibrated on the held-out clips' offsets,
  ``calibrate_retention`` (``scores.transition_node_retention``, ``learn.learn``);
* the phase DOFs (``training.with_phase``): normalised time ``_phase`` for
  non-cyclic clips, which also ends variants; the cycle phase
  ``(cos φ, sin φ)`` for cyclic clips, a parent of every transition node
  (``learn._phase_parents``; without it the walk's mean dynamics come to rest),
  where cyclic variants start and loops are cut;
* sparse candidate parents, ``candidates`` (Friedman et al. 1999; ``search``);
* the time warp as a Gaussian over the inputs' warps drawn once per variant, not a
  DOF of the network (``warp``; ``learn(time_warp=False)`` or
  ``sample(time_warp=False)`` leave it out);
* AR(1)-correlated sampling noise, ``noise_time``, with the long-run variance
  of white noise (``sample.Sampler.stream``; ``None`` is the paper's white noise);
* single-precision neighbour search, and the optional phase-window search of
  crowds (``sample.Sampler``, ``window``);
* IK over whole clips instead of frame by frame, joint limits as bounds
  (``range_margin``, at most ``range_fraction`` of a DOF's own range) and
  corrections that ease in and out (``ease``; 0 is Eq. 7 alone) (``ik``).
"""

#: The modules of this family that register stages, codecs or exporters, each with
#: the names of the stages it defines: the ``mocapflow.stages`` entry point of the
#: family names this mapping, so the engine imports only the module of a stage it
#: needs (tests/test_architecture.py checks the names against the decorators).
STAGE_MODULES = {
    "clips": (),
    "inputs": ("clips",),
    "model": (),
    "learn": ("learn",),
    "sample": ("sample", "sample_noise"),
    "ik": ("ik",),
    "plots": ("variation_plots",),
    "report_figures": (),  # figures of the report page (mocapflow report)
}
