"""Gap filling on sparse captures: the local fill blended with four other models, each
scored per run of holes on copies of it (beyond Park & Hodgins 2006).

:func:`fill_by_validated_blend` is called by :func:`mocapflow.stages.skin.fill.fill_holes`
(``whole_body``) after its local fill; :func:`_interpolate_interior` (the spline member,
which in the blend skips the measured samples :func:`fill_checks._isolated_spikes` flags)
is also the last resort of the paper's passes
(:func:`~mocapflow.stages.skin.fill.fill_by_local_pca`).  The checks that leave a
member out of a run beyond what its copies say (what the gap itself shows, what the
take's measured samples never do) are in :mod:`~mocapflow.stages.skin.fill_checks`.

On sparse captures (at most :data:`WHOLE_BODY_MAX_MARKERS` markers,
``whole_body``), :func:`fill_by_validated_blend` blends the local fill
with a whole-body PCA trained on the take
(:func:`mocapflow.stages.skin.lowrank.whole_body_pca`), a cubic spline in
time and two rigid-body fills from 3 donors (the most rigid, the nearest),
each weighted per run of holes by its error on copies of that run knocked
out nearby, the models compared on the copies they all reached.  On the real shared
C3Ds (26-55 markers) the local fill alone had the lowest mean error (or
within 5 % of it) in 38-75 % of the gap protocol's configurations; see
``benchmarks/clean.py`` for the blend's table.  Comparing the models on
the copies they all reached (a spline was shut out of every run with a
copy on the take's edge) and adding the nearest-donor rigid-body fill, on
mask seeds 200-209 (not used while tuning): PiG calibration 50 -> 67 %
(worst ratio to the best peer 3.10 -> 2.23), Qualisys 83 -> 92 % (1.54 ->
1.23), Eb015pr 83 -> 92 % (1.18 -> 1.10).  With the copies kept where the
spline reaches them, a fifth copy on the run's own margins, the copies'
errors combined geometrically (:func:`_shifted_runs`,
:func:`_validation_mse`) and a model given twice counted once
(:func:`_earlier_twins`), on the same-sample criterion (ours within
5 % of every peer on the samples it filled), mask seeds 400-409 (drawn after
the tuning): PiG 17 of 18 configurations (worst 1.23, 0.5 s holes in one
marker), Qualisys 11 of 12 (1.06).  With a member far from all the others in
the gap left out (:func:`fill_checks._outlying_estimates`: the copies cannot see what the
marker does inside its own gap; PiG LFHD turning with the head near the take's
end 7.7 -> 1.1 mm, LPSI over its recorded 30 mm jump 32.8 -> 4.9 mm), on mask
seeds 570-589 (20 repetitions, drawn after all tuning): PiG 18 of 18 (worst
0.97), Qualisys 12 of 12 (0.96); seeds 550-569: PiG 16 of 18 (1.16); the
90 repetitions of seeds 500-589 pooled: PiG 18 of 18 (0.97), Qualisys 12 of
12 (0.95).  With the members that miss the measured trajectory at the gap's
ends left out too (:func:`fill_checks._boundary_misses`, :data:`fill_checks.BOUNDARY_GUARD`;
Eb015pr, the right foot and shank gone for 0.5 s: RSK2-4 41.7-48.3 -> 4.1-11.4 mm; that
configuration's worst ratio on mask seeds 530-539 1.39 -> 0.98), 10 repetitions:
mask seeds 620-629 (drawn after all tuning): PiG 16 of 18 (worst 1.22),
Qualisys 11 of 12 (1.06), Eb015pr 24 of 24 (1.02; 23 of 24, 1.17 without the
rule), racing 24 of 24 (0.79), pyomeca 24 of 24 (0.95); seeds 610-619 (one
racing repetition inspected for the guard): 18 of 18 (1.03), 12 of 12 (0.96),
24 of 24 (0.96), 24 of 24 (0.83), 24 of 24 (0.94).  What is left loses on holes
in one marker (the 1 % configurations), where one run decides a repetition and
one or two repetitions a 10-20 repetition mean: copies 15-30 frames away see
motion its gap does not (the PiG calibration's left wrist, Qualisys' R_IAS), a
copy at the take's end shows one model 30 mm off and the geometric mean damps
it (PiG RBHD), or the spline alone is right and nothing says so (PiG LFIN over
frames 31-40, seed 605 of the 0.1 s / 1 % / independent masks: spline 0.06 mm,
the four others 0.7-0.9 mm and agreeing, validated alike: blend 0.41 mm; that
configuration's worst ratio over seeds 600-609, 1.74).  20 repetitions (as
METRICS §3 asks), mask seeds 630-649: PiG 17 of 18 (worst 1.20: seed 646, a
spline with 3 samples after its hole left out, see :data:`SPLINE_MIN_SUPPORT_SHARE`),
Qualisys 12 of 12 (0.97), Eb015pr 24 of 24 (0.94), racing 24 of 24 (0.91),
pyomeca 24 of 24 (1.00).  With the spline's copies given the support its hole has
(:func:`_gap_support`), mask seeds 650-669 (20 repetitions, drawn after that
change): PiG 18 of 18 (worst 0.98), Qualisys 12 of 12 (0.94), Eb015pr 24 of 24
(0.92), racing 24 of 24 (0.88), pyomeca 24 of 24 (0.96); the coefficient of
variation of ours' mean error over the repetitions, median over a file's
configurations, 51-78 %.  On its own samples (a spline or rigid-body fill leaves
edge holes unfilled, which ours fills) PiG 0.1 s / 30 % / clustered is 1.37 x the
spline: 0.099 mm over 2,200 samples against 0.072 mm over the 2,070 it filled
(0.98 x on those).  ``ktk_kinematics_basket_sprint.c3d`` (120 Hz, 3,678 frames, 26
markers on a wheelchair, its push-rim, the arm and the trunk; 39 % of the samples
missing, no complete frame, so no G&F), mask seeds 670-679 (10 repetitions, run after
the regression's fits were batched, which cut a repetition from 44 to 30 CPU-s):
on the same samples 22 of 24 configurations within 5 % of the spline and the
rigid-body fill, but 0.1 s / 10 % / independent at 1.11 x and 0.1 s / 1 % /
clustered at 4.91 x the spline (one repetition, seed 677: the push-rim marker
SWL:Marker1 moving 22 mm a frame, frames 2904-2915 knocked out: spline 0.86 mm, ours
44.6 mm).  That marker is missing for most of the sprint (runs 2175-2413, 2415-2670,
2672-2880, 2894-2902), and each validation pass knocks out the copies of all its runs
at once: the 12-frame copy lies inside gaps of 231, 777, 238 and 928 frames, where the
spline is scored at 407 mm and the local fill at 176 mm.  Spread of ours' mean over the
repetitions 173 % (median over configurations).  Copies are now placed where they pose
the run's own problem (:func:`_placed_copies`): that repetition 44.6 -> 0.86 mm; the
six 0.1 s configurations on the same seeds: 0.1 s / 1 % / clustered 4.91 -> 0.91 x the
spline but 1.51 -> 1.59 x the rigid-body fill (single-marker holes where the rigid fill
is best: seeds 675, 678, 679), 0.1 s / 10 % / independent 1.11 -> 0.73 x, the others
0.39-0.92 x.  On fresh mask seeds 680-689 (10 repetitions, drawn after the change), same
samples: PiG 17 of 18 (worst 1.06), Qualisys 12 of 12 (0.98), Eb015pr 24 of 24 (1.01),
pyomeca 24 of 24 (0.98), racing 23 of 24 but 0.5 s / 1 % / independent at 1.30 x
G&F (0.87 x before the change: seed 684, Sternum over frames 385-421, 3 samples
knocked out: no start qualified for any copy of that run, so the local fill alone, 88.8
mm off where the whole-body PCA was 5.3 mm; falling back to the shifted place gives
31.9 mm there, but buried the basket copy above again, 9.96 mm: not kept).  The rigid-body
fills are misjudged alike where the run's donors are missing at every copy
(ArmL:Marker1 over 2 s, seed 672: rigid 1.16 mm, its two carries agreeing within
0.75 mm, scored at 9.7 mm on copies carried by other donors; ours 1.76 mm).
Two changes since: a run with no start on measured samples is copied where the copies
placed on measured samples leave room (:func:`_placed_copies`' second pass: that
Sternum run 88.8 -> 23 mm, the basket copy above stays at 0.86 mm), and a rigid-body
fill is scored on the copies where the run's own donors are measured, where it has any
(:func:`_donors_at_copies`: basket SWL:Marker1 over frames 1818-1829, 0.1 s / 1 % /
clustered, seed 679, carried 0.64 mm off by its push-rim donors and scored 24-32 mm
off on copies carried by others: 2.05 -> 0.66 mm).  Fresh mask seeds 690-699 (10
repetitions, drawn after both), same samples: PiG 17 of 18 (worst 1.14, 0.1 s / 10 % /
independent, 0.08 against the spline's 0.07 mm; 1.07 with the first change alone),
Qualisys 12 of 12 (0.93), Eb015pr 24 of 24 (0.95), racing 24 of 24 (0.88; 0.86),
pyomeca 24 of 24 (1.02); the donor rule alone moves the five files' pooled mean error
by +0.02 to +1.0 % (397 of 1,020 cases changed: 186 better, 211 worse).
basket_sprint, same seeds (the 0.1 s configurations on all ten; the 0.5-2 s ones on
690-694 and some on 695-696, for lack of time; many masks miss its sparse samples,
so 3-10 repetitions have samples): 22 of 24 within 5 % of the spline and the
rigid-body fill, 0.1 s / 10 % / clustered at 6.57 x (seed 699: one knocked-out sample
502 mm off, :func:`_count_once`) and 0.1 s / 1 % / clustered at 1.24 x; with
:func:`_count_once` (its configurations re-run): 23 of 24, worst 1.24 x (0.21 against
the spline's 0.11 mm on seed 695's 12 samples, 0.39 against 0.13 on seed 699's), the
other 0.96 x; PiG, Qualisys, Eb015pr, pyomeca re-run: 17 of 18 (1.14), 12 of 12
(0.93), 24 of 24 (0.95), 24 of 24 (0.96).  Fresh mask seeds 710-719, every
configuration of all six files, 10 repetitions: pyomeca 0.1 s / 1 % / independent at
1.22 x the rigid-body fill (0.16 against 0.13 mm), which :data:`RIGID_DISAGREEMENT_DURATION`
came from (its seed 714); the 0.5-2 s configurations, whose outputs that leaves
unchanged, with the 0.1 s ones on fresh seeds 720-729 after it, same samples: PiG 17 of
18 (worst 1.11, 0.1 s / 1 % / independent, spline), Eb015pr 24 of 24 (0.99), Qualisys 11
of 12 (1.06), racing 24 of 24 (0.64), pyomeca 24 of 24 (0.95), basket_sprint 22 of 24
(1.15, 2 s / 10 % / independent).  Each method's mean over its own samples: basket 18
of 24, 4.91 x the rigid-body fill at 2 s / 1 % / independent, which leaves 34 % of
those samples unfilled.  A run no copy could score kept the local fill alone
(basket 0.1 s / 10 % / independent, seed 717: ForearmL:Marker4, 90.6 mm off where
the other four members agree within 4-9 mm of the truth); it now goes to the members'
medoid (:func:`_consensus_where_unscored`): that case 20.6 -> 1.26 mm mean over its
masked samples.  On fresh seeds 730-761 (38 cases, every file, basket's 24
configurations) the masked samples change in one case only (basket 1 s / 30 % /
independent, seed 756: 17.55 -> 17.37 mm); the other files had no unscored run and are
bit-identical.  Seeds 770-779, basket's six 0.1 s configurations (60 cases): one
changes, the other way (0.1 s / 30 % / independent, seed 774: 1.24 -> 1.40 mm; its
ForearmL:Marker3 run 1910-1921 went from the local fill, 7.6 mm off, to the rigid-body
fill, 9.4 mm off); the table's criteria read the same.  basket's own holes hold 55
unscored runs (3 frames median, 41 at most): where the medoid replaces the local fill
(51 runs), the local fill lies a median 42.3 mm (90th percentile 225 mm, at most 4.1 m)
from the measured samples either side, the medoid 13.9 mm (39, 83 mm), nearer in 45.
A member standing apart from the others' inverse-variance weighted mean is left out
(:data:`fill_checks.CONSENSUS_FACTOR`, :data:`fill_checks.CONSENSUS_MARGIN`): basket 0.1 s / 1 % /
independent on seeds 770-789, same samples, 1.23 -> 0.95 x the rigid-body fill (seed 788: BodyL:C7,
the spline 6.7 mm off, blend 3.13 -> 0.13 mm).  Fresh mask seeds 810-819 (1,260 cases, every
configuration of all six files), against the rule before: 54 cases change, 38 for the
better; the pooled error x 0.979 (basket) to 1.000 (racing); basket 0.1 s / 1 % /
independent 0.82 x the spline and 0.37 x the rigid-body fill.  Those seeds show two
failures the rule leaves as they were: PiG 15 of 18 configurations within 5 % on the
same samples (0.1 s holes: 1.06 and 1.13 x the spline at 1 %, where it and ours are
0.02-0.17 mm off, 1.05 x at 10 % / independent), and basket 0.1 s / 10 % / clustered at
3.07 x the spline (seed 814: WheelchairL:Marker2 missing over frames 2333-2581, one
sample knocked out beside that gap, where the local fill and the whole-body PCA are
2.4-2.7 m off and the spline 0.28 m: blend 1.61 m).  What the marker's measured
samples never do is now taken out (:data:`fill_checks.PLAUSIBILITY_LIMIT`: a member's samples next
to a step 0.1 m longer than the marker's fastest measured step, :func:`fill_checks._jumps_in_runs`,
and a member more than 0.1 m RMS off the distances the marker keeps to its rigid partners,
:func:`fill_checks._keep_plausible`; samples nothing plausible is left for, and the blend's own
jumps, stay holes): that wheelchair sample stays a hole and SWL:Marker2's three, 129-140 mm off,
are filled as the spline fills them.  basket_sprint as captured loses the head, trunk and
hand for its last ~1,550 frames: the fill's worst step beyond the marker's fastest 8.1 m
-> 0.10 m, 3,447 more of its samples left holes; the other five shared takes as captured
are unchanged.  Fresh mask seeds 830-839 (every configuration of the six files), against
the rule off on the same masks: pooled error on the samples both filled x 0.944 (basket,
86 of 240 cases changed, 353 masked samples left holes) to 1.009 (Qualisys); the
same-sample criteria read as with the rule off except basket 0.1 s / 1 % / independent
(0.87 -> 1.06 x the spline: seed 832, two samples 34.5 -> 49.7 mm), and basket on its own
samples 16 -> 18 of 24 configurations within 5 %.  On those seeds, with or without
the rule, racing 0.1 s / 1 % / independent is 1.34 x G&F, pyomeca 0.5 s / 30 % /
clustered 1.26 x the spline, basket 0.1 s / 1 % / clustered 3.34 x the spline and PiG
0.1 s / 1 % / independent 1.18 x: the misses of earlier seeds were not the only ones.
The third marker of a cluster (1-2 surface neighbours, so no local model;
:func:`~mocapflow.stages.skin.fill._thinly_connected_holes`) has been a blend run since,
filled by the four other members, and the copies of a cluster's gap knock it out with the
rest of the cluster as the gap does: Eb015pr 0.5 s / 30 % / clustered, mask seed 843,
RFT2-3 83.9-94.7 -> 16.7-27.7 mm, RSK1-4 24-58 -> 9-15 mm.  Fresh mask seeds 840-849
(every configuration of the six files), same samples: PiG 17 of 18 (worst 1.15, 0.1 s /
1 % / independent, the spline; unchanged by it), Eb015pr 24 of 24 (0.99; 23 of 24 and
1.25 before it), Qualisys 12 of 12 (0.96), racing 24 of 24 (0.91), pyomeca 24 of 24
(0.91), basket_sprint 22 of 24 (1.21, 0.5 s / 30 % / clustered, the spline; unchanged).
The same code on fresh seeds 850-859: PiG 15 of 18 (1.23: 1 s / 10 % / clustered, the
rigid-body fill; 0.1 s / 1 % at 1.21 and 1.11 x the spline), Qualisys 11 of 12 (1.29,
0.1 s / 1 % / independent, the rigid-body fill), basket 20 of 24 (1.63), the other three
files all within 5 %.  Tried and dropped: a prior for the spline on short holes (on runs
of at most 0.2 s the other members' validated mean squared errors doubled for the
weights).  Offline on the stored blend states of seeds 820-829: PiG 16 -> 18 of 18, the
other files -1.0 to +0.7 %.  Fresh seeds 850-859: PiG 15 -> 17 of 18, but Qualisys 0.1 s
/ 1 % / independent 1.29 -> 1.64 x the rigid-body fill (L_FME, frames 156-175, seed 854:
the spline 8.5 mm off, the blend 1.5 -> 4.3 mm).  Bounded to runs whose spline validated
within 0.2 mm, on fresh seeds 860-869: PiG 17 -> 17 of 18, pyomeca 0.1 s / 1 % /
clustered 1.04 -> 1.06 x the spline (seeds 868-869: the spline, validated within 0.2 mm,
0.13-0.21 mm off in the gap where the rigid-body fill is 0.04-0.05), pooled errors
unchanged within 0.01 %: at a tenth of a millimetre the spline is not the better model
often enough to be preferred.  Validation copies are placed where the marker moves as it
does at its run's ends (:data:`MOTION_MATCH`; basket_sprint's ScapularSpineL at the
sprint's start, seed 874: 31.5 -> 5.2 mm).  Fresh mask seeds 880-889 (every configuration
of the six files), same samples: PiG 14 of 18 (worst 1.26, 0.5 s / 1 % / clustered, the
rigid-body fill; the same four misses with the copies placed as before), Eb015pr 24 of 24
(0.91), Qualisys 12 of 12 (0.99), racing 24 of 24 (0.80), pyomeca 24 of 24 (0.96),
basket_sprint 23 of 24 (2.00, 0.1 s / 10 % / independent, the spline: seed 882,
WheelchairL:Marker4 knocked out over frames 2877-2888, joining its own holes into a
34-frame run; the rigid-body fills reach none of the knocked-out samples and the local
fill, validated at 4 mm, is 283 mm off there).  A member jumping beside half the samples it
estimates in a run now leaves all of it (:data:`fill_checks.ERRATIC_SHARE`): that
repetition 27.3 -> 2.7 mm.  Fresh mask seeds 890-899, same samples: PiG 14 of 18 (worst
1.14), Eb015pr 24 of 24 (0.95), Qualisys 12 of 12 (0.98), racing 24 of 24 (0.69), pyomeca
24 of 24 (0.87), basket_sprint 23 of 24 (2.47, 0.1 s / 10 % / clustered, seed 892: a
248-frame run whose copies are scored over the whole run, not near its measured ends,
``test_samples_near_a_long_run_s_end_go_to_the_members_right_there``); on basket's seeds
890-894 the criteria are the same with the rule off (2 of 120 cases change).  Each
member's error is now taken as at least its miss of the trajectory at the run's ends
beyond the trajectory's own (:func:`fill_checks._end_excess`, PiG's head over 0.5 s, seed
894: 9.30 -> 7.43 mm, the spline 7.10), and runs of at least :data:`PROFILE_MIN_LENGTH`
frames are weighted per sample by the copies' error at its distance from the nearer
measured end (:func:`_validation_profile`; basket seed 892: 109 -> 10.7 mm).  Fresh mask
seeds 900-909, same samples, before -> after: PiG 16 of 18 -> 16 of 18 (worst 1.11 ->
1.11, single-marker 0.5 s holes where the copies misjudge the rigid-body fills), Qualisys
11 of 12 -> 12 of 12 (1.06 -> 1.04), Eb015pr 24 of 24 (0.89 -> 0.88), racing 24 of 24
(0.96 -> 1.03), pyomeca 23 of 24 (1.06 -> 1.06); the five files' pooled mean error
-2.0 to +1.9 %; basket_sprint (after) 23 of 24 (worst 1.77, 0.1 s / 1 % / independent:
seed 907's ForearmL:Marker4, 8 samples at the end of a 66-frame run, 102 mm against the
spline's 48 mm, the same with the code before the change).  That end is read since from the
trajectory's nearest samples within :data:`fill_checks.END_REACH` frames, in a row or not (the
marker is seen there at 2449, 2451, 2454: 102 -> 48.9 mm).  Fresh mask seeds 910-919, same
samples: PiG 17 of 18 (worst 1.10, 0.1 s / 10 % / clustered, the spline), Qualisys 11 of 12
(1.07, 0.5 s / 1 % / independent, G&F), Eb015pr 24 of 24 (0.93), racing 24 of 24 (0.91),
pyomeca 22 of 24 (1.17, 0.5 s / 1 % / clustered, the rigid-body fill: seed 915's
Daphnee:SCAP_IA over 0.5 s, every member validated at 0.5-2.5 mm, the local fill best at 0.54
and 2.6 mm off in the gap, the nearest-donor fill 0.78 mm off).  On those five files 58 of the
1,020 cases read an end of a knocked-out run differently with the reach; 3 of them change (the
58's pooled error x 0.9998) and the criteria read the same as without it.

See :mod:`mocapflow.stages.skin.fill` for the local fill it starts from.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import numpy as np
from scipy.interpolate import CubicSpline

from mocapflow.stages.motion.absolute_orientation import absolute_orientation_batch
from mocapflow.stages.motion.contacts import true_runs
from mocapflow.stages.skin.fill_checks import (
    BOUNDARY_GUARD,
    _end_excess,
    _isolated_spikes,
    _jumps_in_runs,
    _keep_plausible,
    _outlying_estimates,
    _take_bounds,
)
from mocapflow.stages.skin.lowrank import whole_body_pca
from mocapflow.stages.skin.predict import finite_rows
from mocapflow.stages.skin.regress import predictor_ranking
from mocapflow.stages.skin.surface import MarkerSurface

__all__ = [
    "BLEND_MODELS",
    "BLEND_POWER",
    "MOTION_FLOOR",
    "MOTION_MATCH",
    "MOTION_WINDOW",
    "PROFILE_EDGES",
    "PROFILE_MIN_LENGTH",
    "RIGID_BODY_POOL",
    "RIGID_DISAGREEMENT_SHARE",
    "RIGID_MODELS",
    "SPLINE_MIN_SUPPORT_SHARE",
    "VALIDATION_SHIFTS",
    "WHOLE_BODY_MAX_MARKERS",
    "fill_by_validated_blend",
]

#: ``fill_holes(whole_body=None)`` blends in the whole-body model on captures with
#: at most this many markers (sparse lab sets; on dense captures the local
#: models have the neighbours they need and the SVDs would cost seconds).
WHOLE_BODY_MAX_MARKERS = 120

#: Donors of the rigid-body estimate: the most rigid of this many nearest markers
#: first (a cluster's own markers; ranking by rigidity alone over 40 preferred a
#: foot marker to a shank cluster's third marker on Eb015pr).
RIGID_BODY_POOL = 6

#: Copies of each run of holes that :func:`fill_by_validated_blend` scores the
#: models on: moved by these multiples of 1.5 times its length (nearby motion);
#: 0: the run's own margins, :data:`VALIDATION_MARGIN` of its length on each side
#: (:func:`_shifted_runs`).
VALIDATION_SHIFTS = (-1, 1, -2, 2, 0)

#: Length of the margins scored as a run's copy 0 in :data:`VALIDATION_SHIFTS`, as a
#: share of the run's length (at least 2 frames each side): the samples next to the
#: run, where the moved copies can miss what the marker does there (a still wrist
#: in its gap on the PiG calibration, moving 15-30 frames away).
VALIDATION_MARGIN = 0.5

#: A validation copy is placed where its marker moves as it does at its run's ends
#: (:func:`_placed_copies`): the mean step over :data:`MOTION_WINDOW` each side
#: of the copy within this factor of the run's, both with :data:`MOTION_FLOOR` added.
#: ``ktk_kinematics_basket_sprint.c3d`` (120 Hz) sits still over its first 1,500 frames
#: and sprints from about 1,550 to 2,100, where its trunk markers leave the volume:
#: ``BodyL:ScapularSpineL`` knocked out over frames 1555-1794 (the sprint's start, the
#: marker moving 10 mm a frame at the gap's ends; gap protocol 2 s / 1 % / independent,
#: mask seed 874) had its backward copies over frames 835-1074 and 1195-1434, where the
#: athlete sat still, and the spline, scored there at 3.7-9.7 mm (the other members 5-55
#: mm) and unable to reach the forward copies, held 74 % of the blend; in the gap it is 43
#: mm off, the other members 5-8 mm: blend 31.5 mm.  Copied where the marker moves 7-20 mm
#: a frame (frames 1796-2035 and 1829-2068), the spline is scored at 44 mm, the
#: rigid-body fill at 12: blend 5.2 mm.
MOTION_MATCH = 3.0

#: See :data:`MOTION_MATCH` (m/s): below it a marker counts as still (noise, sway).
MOTION_FLOOR = 0.05

#: See :data:`MOTION_MATCH` (s): the time each side of a run or copy whose steps give
#: its motion (at least 2 frames; fewer where fewer are measured).
MOTION_WINDOW = 0.1

#: Weights of :func:`fill_by_validated_blend`: ∝ (mean squared validation error)^-p.
BLEND_POWER = 2.0

#: Validation copies of a hole are kept this share of its length (up to
#: ``interpolate``, at least 2 frames) from the take's ends, so that the spline reaches
#: them (:func:`_shifted_runs`).  It was also the least support the blend's spline had
#: to have on each side of the hole itself: a cubic through the 4 samples left before a
#: 0.5 s hole near the start of the PiG calibration swung 17-169 mm off while the
#: copies, moved into the take with full support, gave it the weight.  The copies now
#: take the support the hole has (:func:`_gap_support`), which scores such a spline as
#: it is (that hole 1.03 -> 0.84 mm mean), and the spline of a hole with 2 samples on a
#: side is a member: PiG, the head turning over the take's last 53 frames, 3 samples
#: after the hole, blend 6.3 -> 3.0 mm
#: (``test_a_spline_short_of_samples_on_one_side_is_scored_as_it_is``).
SPLINE_MIN_SUPPORT_SHARE = 0.2

#: The estimates :func:`fill_by_validated_blend` weighs, in order.
BLEND_MODELS = ("local", "whole_body", "spline", "rigid_body", "rigid_nearest")

#: Indices in :data:`BLEND_MODELS` of the rigid-body fills (most rigid, nearest donors).
RIGID_MODELS = (BLEND_MODELS.index("rigid_body"), BLEND_MODELS.index("rigid_nearest"))

#: A rigid-body fill's blend weight comes from a validation error of at least this
#: share of how far its two carries (from before and from after the gap) disagree,
#: root mean square over the run (:func:`fill_by_validated_blend`): the marker's
#: motion against its donors between the gap's two ends.  The carries assume the
#: marker rigid with its donors; where it moves against them within the gap,
#: copies of the gap at other times (where it may not) vouch for them wrongly.
#: With the carries blended linearly the error is the part of that motion that is
#: not linear in time: on the real PiG calibration (gap protocol, 0.5 s, 10 %,
#: clustered, mask seed 104) the whole head (LFHD, RFHD, LBHD, RBHD) is gone for
#: 0.5 s while it turns against the trunk: carries 56-70 mm apart, the rigid-body
#: fills 15-18 mm off (about a quarter), validated at 0.5-0.6 mm, so they had half
#: the weight.  Tried instead and dropped: scaling their validation error by the
#: ratio of the squared disagreement in the gap to that in its copies (gap
#: protocol, PiG + Qualisys seeds 100-109 and 200-209, Eb015pr / pyomeca / racing
#: 200-204: as good or worse in every file, e.g. Qualisys worst ratio 1.15 against
#: 1.07); stacking the members (non-negative weights minimising the blend's own
#: validation error, ridge 0.1: PiG 15 -> 13 of 18 within 5 %); a sharper
#: ``BLEND_POWER`` 3 or 4 (Qualisys 10 -> 10 and 9 of 12, worst 1.07 -> 1.17, 1.24).
RIGID_DISAGREEMENT_SHARE = 0.25

#: Runs shorter than this (s) get a proportionally smaller :data:`RIGID_DISAGREEMENT_SHARE` (with
#: the take's rate, :func:`~mocapflow.stages.skin.fill.fill_holes`' ``rate``).  The linear blend of
#: the carries misses the part of the marker's motion against its donors that is not linear in time:
#: for a smooth motion ``d(t)`` over a gap of ``T`` about ``|d''| T² / (2 √30)`` (rms of the
#: parabola), against a disagreement of about ``|d'| T``, so the share grows with ``T``; 0.25 was
#: set on 0.5 s gaps (the head above) and is kept for longer ones.  At 0.1 s the full share raised
#: the rigid fills of a wrist marker turning slowly against its donors (pyomeca, ``Daphnee:STYLr``,
#: gap protocol 0.1 s / 1 % / independent, mask seed 714: carries 2.8 mm apart, so validated at 0.71
#: mm against 0.34 from its copies) above the spline's 0.69 though 0.20 mm off in the gap against
#: the spline's 1.05.
RIGID_DISAGREEMENT_DURATION = 0.5


def _spline_support_needed(length: int, support: int, min_support_share: float) -> int:
    """Frames a validation copy of a hole of ``length`` frames is kept from the take's ends
    (:func:`_shifted_runs`): ``min_support_share`` of its length, at least 2 (the fewest
    measured samples :func:`_interpolate_interior` interpolates from) and at most
    ``support``."""
    return max(2, min(support, int(np.ceil(min_support_share * length))))


def _interpolate_interior(X: np.ndarray, measured: np.ndarray, holes: np.ndarray,
                          support: int,
                          sides: tuple[np.ndarray, np.ndarray] | None = None) -> int:
    """Cubic interpolation (in place) of interior holes still empty, from up to
    ``support`` measured samples on each side; a hole with fewer than 2 on a side is
    left empty.  ``sides``, optional ``(labels (F, M) int, limits (R, 2) int)``: a hole
    with samples labelled ``r >= 0`` takes at most ``limits[r]`` measured samples before
    and after it (the smallest over its labels; :func:`_gap_support`).  Returns the
    samples filled."""
    obs = finite_rows(measured)
    todo = holes & ~finite_rows(X)
    n = 0
    for m in np.flatnonzero(todo.any(0)):
        d = np.diff(np.concatenate([[0], todo[:, m].astype(np.int8), [0]]))
        for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
            before = after = support
            if sides is not None:
                lab = sides[0][a:b, m]
                if (lab >= 0).any():
                    before, after = np.minimum(sides[1][lab[lab >= 0]].min(0), support)
            seen = np.flatnonzero(obs[:a, m])
            left = seen[max(len(seen) - before, 0):]
            right = b + np.flatnonzero(obs[b:, m])[:after]
            if len(left) < 2 or len(right) < 2:
                continue  # an edge hole: nothing (or too little) to interpolate between
            idx = np.concatenate([left, right])
            X[a:b, m] = CubicSpline(idx, measured[idx, m], axis=0)(np.arange(a, b))
            n += b - a
    return n


def _runs(holes: np.ndarray) -> list[tuple[int, int, int]]:
    """``(marker, start, stop)`` of every run of holes, marker by marker."""
    return [(int(m), a, b) for m in np.flatnonzero(holes.any(0))
            for a, b in true_runs(holes[:, m])]


def _measured_before(measured: np.ndarray) -> np.ndarray:
    """``(F + 1, M)`` int: the samples of ``measured (F, M)`` before each frame (and in all)."""
    return np.concatenate([np.zeros((1, measured.shape[1]), np.int64),
                           np.cumsum(measured, axis=0)])


def _gap_support(measured: np.ndarray, runs: list[tuple[int, int, int]],
                 support: int) -> np.ndarray:
    """``(R, 2)`` int: the measured samples (``measured (F, M)`` bool) a spline of each run
    has before and after it, at most ``support`` each (:func:`_interpolate_interior`)."""
    seen = _measured_before(measured)
    m, a, b = (np.array([run[i] for run in runs], dtype=np.int64) for i in range(3))
    return np.minimum(np.stack([seen[a, m], seen[-1, m] - seen[b, m]], 1), support)


#: Edges (frames) of the bins of a hole's samples by their distance from its nearer
#: measured end (:func:`_profile_bins`): each model is scored per bin on the copies
#: (:func:`_validation_profile`), its error growing away from the ends at its own rate.
PROFILE_EDGES = (2, 5, 10, 20, 40)


#: Runs of at least this many frames (twice the last of :data:`PROFILE_EDGES`: their
#: middle reaches the last bin) are weighted per bin (:func:`_profile_weights`); shorter
#: ones by their copies' whole error.  On every run, PiG calibration's right arm over 50
#: frames (``test_a_spline_right_where_the_spatial_members_share_an_error_is_kept``) went
#: 1.95 -> 2.09 mm (the plain spline 1.43): in the middle bins the copies scored the local
#: fill at 2.4-4.7 mm where it is 4.9-12.3 mm off, the whole run's copies at 1.8-4.3 mm
#: against the spline's 0.8-2.3, which the spline's near-end bins had lowered; and on the
#: five smaller shared C3Ds (mask seeds 890-899) PiG was 15 of 18 configurations within
#: 5 % against 16 of 18 with this bound.  basket_sprint's 248-frame run of seed 892
#: (``test_samples_near_a_long_run_s_end_go_to_the_members_right_there``) is what the
#: profile is for: 109 -> 10.7 mm.
PROFILE_MIN_LENGTH = 2 * PROFILE_EDGES[-1]


def _profile_bins(frames: np.ndarray, lo: np.ndarray, hi: np.ndarray, F: int) -> np.ndarray:
    """The bin (:data:`PROFILE_EDGES`) of each hole sample at ``frames`` by its distance from
    the nearer measured end of its hole ``lo..hi-1`` (arrays alike); a hole on the take's
    edge is measured on one side only; a hole of the whole take is in the last bin."""
    d = np.minimum(np.where(lo > 0, frames - lo, F), np.where(hi < F, hi - 1 - frames, F))
    return np.searchsorted(PROFILE_EDGES, d, side="right")


def _shifted_runs(runs: list[tuple[int, int, int]], shape: tuple[int, int],
                  k: int, *, support: int = 0, measured: np.ndarray | None = None,
                  motion: tuple[np.ndarray, float, int] | None = None) -> np.ndarray:
    """``(F, M)`` int: each run's copy moved by ``k`` times its length plus half of it
    (at least 5 frames), kept inside the take, labelled with the run's index (-1
    elsewhere).  Runs of equal start and length (gaps at once) move together.

    With ``support`` (the spline's, :func:`_interpolate_interior`), a copy is kept
    :func:`_spline_support_needed` frames (:data:`SPLINE_MIN_SUPPORT_SHARE`) from the
    take's ends where the take is long enough, so that every model can be scored on
    it: a 1 s hole in the 3 s PiG calibration had every copy moved onto an end, the
    spline (the best model on that still subject) was never scored and took no weight
    (1 s holes in 30 % of the markers at once, mask seeds 100-109: blend 1.60 mm mean,
    spline 0.94 mm).
    With ``measured`` (``(F, M)`` bool, the take's measured samples), a copy poses the
    run's own problem: :func:`_placed_copies` moves it on from that place to where it
    lands on measured samples only, apart from the marker's other holes and copies (and,
    with ``motion``, where the marker moves as at the run's ends).
    With ``k`` 0, the copy is the run's margins instead: the
    :data:`VALIDATION_MARGIN` share of its length (at least 2 frames) before and
    after it, within the take, knocked out together with the run itself.
    """
    F, M = shape
    out = np.full(shape, -1, dtype=np.int64)
    if k != 0 and measured is not None:
        return _placed_copies(runs, measured, k, support=support, motion=motion)
    for r, (m, a, b) in enumerate(runs):
        L = b - a
        if k == 0:
            w = max(2, int(round(VALIDATION_MARGIN * L)))
            out[max(a - w, 0):a, m] = r
            out[b:b + w, m] = r
            continue
        edge = _spline_support_needed(L, support, SPLINE_MIN_SUPPORT_SHARE) if support else 0
        if F - L - 2 * edge < 0:
            edge = 0
        s0 = int(np.clip(a + k * (L + max(L // 2, 5)), edge, F - L - edge))
        out[s0:s0 + L, m] = r
    return out


def _steps(positions: np.ndarray) -> np.ndarray:
    """``(F + 1, M, 2)``: at row ``t``, the summed length (``[..., 0]``, m) and the number
    (``[..., 1]``) of each marker's measured steps that end before frame ``t`` (a step ends
    on its later frame and is measured where both its frames are; ``positions (F, M, 3)``,
    NaN where not measured)."""
    d = np.linalg.norm(np.diff(positions, axis=0), axis=-1)  # (F - 1, M)
    seen = np.isfinite(d)
    per = np.stack([np.where(seen, d, 0.0), seen.astype(float)], -1)
    zero = np.zeros((2,) + per.shape[1:])
    return np.concatenate([zero, np.cumsum(per, axis=0)])  # row t: steps ending before t


def _end_motion(steps: np.ndarray, m: np.ndarray, a: np.ndarray, b: np.ndarray,
                window: int) -> np.ndarray:
    """Mean measured step (m per frame) of markers ``m`` over ``window`` frames before
    ``a`` and from ``b`` on (the frames either side of a gap ``a..b-1``), their means over
    the markers, one per start ``a`` ``(S,)``; NaN where no step is measured there.
    ``steps`` ``(F + 1, M, 2)`` from :func:`_steps`; ``m (G,)``, ``a`` and ``b`` ``(S,)``."""
    F = steps.shape[0] - 1
    a, b = a[:, None], b[:, None]
    lo1, hi1 = np.clip(a - window + 1, 1, F), np.clip(a, 1, F)  # steps within a-window..a-1
    lo2, hi2 = np.clip(b + 1, 1, F), np.clip(b + window, 1, F)  # within b..b+window-1
    tot = (steps[hi1, m] - steps[lo1, m]) + (steps[hi2, m] - steps[lo2, m])  # (S, G, 2)
    seen = tot[..., 1] > 0
    mean = np.where(seen, tot[..., 0] / np.maximum(tot[..., 1], 1), 0.0)
    markers = seen.sum(1)
    return np.where(markers > 0, mean.sum(1) / np.maximum(markers, 1), np.nan)


def _placed_copies(runs: list[tuple[int, int, int]], measured: np.ndarray, k: int, *,
                   support: int, motion: tuple[np.ndarray, float, int] | None = None
                   ) -> np.ndarray:  # fmt: skip
    """``(F, M)`` int: the validation copies of :func:`_shifted_runs` (shift ``k`` != 0)
    placed so that each poses its run's own problem, labelled with the run's index.

    Runs of equal start and length (gaps at once) move together.  A group's copy goes to
    the start nearest ``k`` × (its length plus half of it, at least 5 frames) from the
    run, at or beyond it in ``k``'s direction (else on the other side), where every
    marker of the group is measured (``measured (F, M)``) over the copy and one frame on
    each side, no copy placed before of one of its markers lies within ``support`` frames
    (so the copy's gap has the run's length, and the spline's samples next to it are not
    knocked out by another run's copy), and the take's ends are
    :func:`_spline_support_needed` frames away; with ``motion`` (``(steps, floor,
    window)``: :func:`_steps` of the positions, :data:`MOTION_FLOOR` in m per frame and
    :data:`MOTION_WINDOW` in frames), only the
    starts where the group's markers move as at the run's ends (:func:`_end_motion`
    within :data:`MOTION_MATCH`) while any such start exists.  Groups are placed in the order of
    ``runs``; then the groups with no such start are copied where the same holds but for
    the measured samples (nearest the same place), so that their runs are still scored on
    what is measured there, away from the copies placed on measured samples; no such
    start either, no copy.  Without that second pass the real racing take's sternum marker
    (measured in 21 of 700 frames), knocked out over frames 408-410 (0.5 s / 1 % /
    independent, mask seed 684), got no copy of its 37-frame run, the local fill, never
    scored, decided alone and the blend came out 88.8 mm off (the whole-body fill: 5.3 mm);
    with it, 23 mm.

    Without this, the copies were moved by the shift alone, and in a take with long holes
    they merged with the marker's holes and with the copies of its other runs, knocked out
    in the same pass: ``ktk_kinematics_basket_sprint.c3d``, the push-rim marker
    SWL:Marker1, missing over frames 2175-2413, 2415-2670, 2672-2880 and 2894-2902, and
    knocked out over 2904-2915 (gap protocol 0.1 s / 1 % / clustered, mask seed 677):
    its 12-frame copies lay in gaps of 231, 777, 238 and 928 frames, the spline, 0.86 mm
    off in the gap, was scored at 407 mm and the blend came out 44.6 mm off; with the
    copies placed, 0.86 mm.
    """
    F, M = measured.shape
    out = np.full((F, M), -1, dtype=np.int64)
    near = np.zeros((F, M), dtype=bool)  # within `support` frames of a copy placed
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for r, (m, a, b) in enumerate(runs):
        groups.setdefault((a, b), []).append((r, m))
    fallback = []
    for on_measured in (True, False):
        for (a, b), members in (groups.items() if on_measured else fallback):
            L = b - a
            ms = np.array([m for _, m in members])
            edge = _spline_support_needed(L, support, SPLINE_MIN_SUPPORT_SHARE) if support else 0
            if F - L - 2 * edge < 2:
                edge = 0
            ok = ~near[:, ms].any(1)
            if on_measured:
                ok &= measured[:, ms].all(1)
            free = np.concatenate([[0], np.cumsum(ok)])
            starts = np.arange(max(edge, 1), F - L - max(edge, 1) + 1)  # frames s-1..s+L free
            starts = starts[free[starts + L + 1] - free[starts - 1] == L + 2]
            if not len(starts):
                if on_measured:
                    fallback.append(((a, b), members))
                continue
            if motion is not None:
                steps, floor, window = motion
                own = _end_motion(steps, ms, np.array([a]), np.array([b]), window)
                there = _end_motion(steps, ms, starts, starts + L, window)
                ratio = np.abs(np.log((there + floor) / (own + floor)))
                alike = starts[ratio <= np.log(MOTION_MATCH)]  # False where NaN
                if len(alike):
                    starts = alike
            nominal = a + k * (L + max(L // 2, 5))
            ahead = starts[(starts - nominal) * np.sign(k) >= 0]
            pick = ahead if len(ahead) else starts
            s0 = int(pick[np.argmin(np.abs(pick - nominal))])
            for r, m in members:
                out[s0:s0 + L, m] = r
            near[max(s0 - support, 0):s0 + L + support, ms] = True
    return out


def _rigid_body_fill(positions: np.ndarray, holes: np.ndarray,
                     reference: np.ndarray, *,
                     donors: Literal["rigid", "nearest"] = "rigid",
                     disagreement: np.ndarray | None = None,
                     donor_sets: dict | None = None) -> np.ndarray:
    """Rigid-body estimates of the holes from 3 donors (as Vicon's rigid-body fill).

    Per run of holes, 3 donors measured through it and at the marker's last /
    first measured frame around it carry the marker from those frames through
    the gap (Horn fit of the donors at the anchor frame onto the donors at
    each gap frame), the two blended linearly.  ``donors="rigid"``: the most
    rigid of the marker's :data:`RIGID_BODY_POOL` nearest markers first (then
    of its 40 nearest; :func:`~mocapflow.stages.skin.regress.predictor_ranking`);
    ``"nearest"``: the nearest in the reference pose (Vicon's choice, the
    better one when a segment's cluster is the nearest markers).

    ``disagreement``, optional ``(F, M)`` float array: set to the distance between the
    two carries (from before and from after the gap) at the holes carried from both,
    NaN elsewhere (how far the marker moves against its donors within the gap).
    ``donor_sets``, optional dict: set to ``{(marker, start, stop): donors}`` (a
    ``frozenset`` of marker indices) for every run of holes carried.

    Returns
    -------
    (F, M, 3) float ndarray
        Estimates at ``holes``, NaN elsewhere and where no 3 donors qualify.
    """
    F, M, _ = positions.shape
    vis = finite_rows(positions)
    out = np.full(positions.shape, np.nan)
    markers = np.flatnonzero(holes.any(0))
    src, tgt, anchor, frame, mark, wt, side = [], [], [], [], [], [], []
    if donors == "nearest":
        known = np.isfinite(reference).all(1)
        dist = np.linalg.norm(reference[markers, None] - reference[None], axis=-1)
        dist[:, ~known] = np.inf
        dist[np.arange(len(markers)), markers] = np.inf
        ranked = [o[np.isfinite(d[o])] for d, o in zip(dist, np.argsort(dist, axis=1))]
    elif donors == "rigid":
        near = predictor_ranking(positions, reference, markers, pool=RIGID_BODY_POOL)
        wide = predictor_ranking(positions, reference, markers, pool=40)
        ranked = [np.concatenate([c1, c2[~np.isin(c2, c1)]]) for c1, c2 in zip(near, wide)]
    else:
        raise ValueError(f"rigid-body fill: donors must be 'rigid' or 'nearest', got {donors!r}")
    for m, cand in zip(markers, ranked):
        for a, b in true_runs(holes[:, m]):
            anchors = [f for f in (a - 1, b) if 0 <= f < F and vis[f, m]]
            if not anchors:
                continue
            need = vis[a:b][:, cand].all(0) & vis[anchors][:, cand].all(0)
            d = cand[need][:3]
            if len(d) < 3:
                continue
            if donor_sets is not None:
                donor_sets[(int(m), a, b)] = frozenset(d.tolist())
            s = (np.arange(a, b) - a + 1) / (b - a + 1)
            for f in anchors:
                src.append(np.broadcast_to(positions[f, d], (b - a, 3, 3)))
                tgt.append(positions[a:b][:, d])
                anchor.append(np.broadcast_to(positions[f, m], (b - a, 3)))
                frame.append(np.arange(a, b))
                mark.append(np.full(b - a, m))
                wt.append(np.ones(b - a) if len(anchors) == 1 else (1 - s if f < a else s))
                side.append(np.full(b - a, 0.0 if len(anchors) == 1 else (1.0 if f < a else -1.0)))
    if disagreement is not None:
        disagreement[:] = np.nan
    if not src:
        return out
    R, t = absolute_orientation_batch(np.concatenate(src), np.concatenate(tgt))
    e = np.einsum("nij,nj->ni", R, np.concatenate(anchor)) + t
    f, m, w = np.concatenate(frame), np.concatenate(mark), np.concatenate(wt)
    acc = np.zeros((F, M, 3))
    np.add.at(acc, (f, m), e * w[:, None])
    got = np.zeros((F, M), dtype=bool)
    got[f, m] = True
    out[got] = acc[got]
    if disagreement is not None:
        sd = np.concatenate(side)
        two = sd != 0
        diff = np.zeros((F, M, 3))
        np.add.at(diff, (f[two], m[two]), e[two] * sd[two, None])
        both = np.zeros((F, M), dtype=bool)
        both[f[two], m[two]] = True
        disagreement[both] = np.linalg.norm(diff[both], axis=-1)
    return out


def fill_by_validated_blend(
    X: np.ndarray,
    positions: np.ndarray,
    holes: np.ndarray,
    surface: MarkerSurface,
    *,
    interpolate: int,
    local_fill: Callable[[np.ndarray], np.ndarray],
    n_shifts: int = len(VALIDATION_SHIFTS),
    rate: float | None = None,
) -> tuple[np.ndarray, dict[str, float]]:
    """The local fill blended with a whole-body PCA, a spline and two rigid-body fills.

    Five estimates of every hole (:data:`BLEND_MODELS`, :func:`_blend_members`):
    the local fill ``X`` (regression, PCA passes, rigid fallback); the
    whole-body PCA trained on the take completed by it
    (:func:`~mocapflow.stages.skin.lowrank.whole_body_pca`, Gløersen &
    Federolf R2 without complete frames); for interior holes, a cubic spline
    in time through ``interpolate`` measured samples each side (at least 2;
    its copies take the samples the hole has, :func:`_gap_support`); and the
    rigid-body fill from 3 donors (:func:`_rigid_body_fill`), the most rigid
    nearby markers and the 3 nearest (Vicon's choice).  Which is best
    depends on the capture, the marker, the gap's length and what else is
    missing with it, so each is scored on the take itself: every run of
    holes is copied next to itself (:func:`_shifted_runs`, ``n_shifts`` of
    :data:`VALIDATION_SHIFTS`; runs that start together move together, so a
    cluster's gaps are validated as a cluster; kept far enough from the take's
    ends for the spline to reach them, and placed where each copy's gap is its run's
    length and, given ``rate``, where the marker moves as at the run's ends,
    :data:`MOTION_MATCH`, :func:`_placed_copies`) onto measured samples, which
    are knocked out and filled by the same models (the local fill without the
    blend; :func:`_validation_errors`).  A run's models are compared on the
    copies that every model able to estimate the whole run estimated in full
    (:func:`_validation_mse`: a copy moved onto the take's edge, where a
    spline cannot reach, no longer shuts the spline out of the run), and its
    estimates are averaged with weights ∝ (mean squared error on those
    copies)^-:data:`BLEND_POWER` (on runs of at least :data:`PROFILE_MIN_LENGTH` frames,
    each sample by the copies' error at its distance from the run's nearer measured end:
    :func:`_validation_profile`), a rigid-body fill's (:data:`RIGID_MODELS`)
    error taken as at least :data:`RIGID_DISAGREEMENT_SHARE` of how far its
    carries from before and after the gap disagree (the marker moving against
    its donors there, which the copies need not see; a smaller share on runs
    shorter than :data:`RIGID_DISAGREEMENT_DURATION` when ``rate`` is given), every
    model's error taken as at least its miss of the measured trajectory at the run's ends
    beyond the trajectory's own (:func:`fill_checks._end_excess`), a model whose estimate
    repeats an earlier one's counted once (:func:`_earlier_twins`), the
    models the gap itself shows far off left out of it (:func:`fill_checks._outlying_estimates`:
    an estimate far beyond its and the others' validated errors from the others'
    median, sooner where it does not join the measured trajectory at the gap's ends, or
    missing those ends alone; what the marker does inside its own gap, which no copy
    sees); a run with no copy scored keeps the local fill.  What the marker's measured
    samples never do is taken out: a model's samples next to a jump longer than the marker
    ever steps leave the blend and the tests there, all of its samples of a run where
    they are half of them (:func:`fill_checks._jumps_in_runs`, :data:`fill_checks.ERRATIC_SHARE`), a
    model off the distances the marker keeps to its rigid partners leaves the run
    (:func:`fill_checks._keep_plausible`), and samples no model is left for, or where the blend
    itself jumps, stay holes.

    Parameters
    ----------
    X : (F, M, 3) float ndarray
        The local fill (``holes`` filled where it could).
    positions : (F, M, 3) float ndarray
        Measured positions, NaN at holes.
    holes : (F, M) bool ndarray
    surface : MarkerSurface
    interpolate : int
        Measured samples on each side of a spline.
    local_fill : callable
        The local fill of the validation copies: ``(F, M, 3)`` positions with NaN at holes
        to the same with the holes filled (:func:`~mocapflow.stages.skin.fill.fill_holes`
        with its own arguments, without the blend).
    n_shifts : int
        Copies of each run (the first of :data:`VALIDATION_SHIFTS`).
    rate : float, optional
        Frames per second (see :data:`RIGID_DISAGREEMENT_DURATION` and
        :data:`MOTION_MATCH`; None: the full share on every run, copies placed
        whatever the motion there).

    Returns
    -------
    filled : (F, M, 3) float ndarray
    weights : dict
        Mean weight of each of :data:`BLEND_MODELS` over the filled holes.
    """
    F, M, _ = X.shape
    disagreement = {k: np.full(holes.shape, np.nan) for k in RIGID_MODELS}
    donor_sets: dict[int, dict] = {k: {} for k in RIGID_MODELS}
    spikes = _isolated_spikes(positions)  # the spline does not ring through them
    est = _blend_members(X, positions, holes, surface, interpolate=interpolate,
                         disagreement=disagreement, donor_sets=donor_sets, spikes=spikes)
    runs = _runs(holes)
    run = np.full((F, M), -1, dtype=np.int64)
    for r, (m, a, b) in enumerate(runs):
        run[a:b, m] = r
    # the models that estimate the whole of a run are the ones its copies compare
    full = np.ones((len(BLEND_MODELS), len(runs)), dtype=bool)
    reach = finite_rows(est) | ~holes[None]  # (K, F, M)
    for r, (m, a, b) in enumerate(runs):
        full[:, r] = reach[:, a:b, m].all(1)
    errs, ok, profile = _validation_errors(
        positions, holes, runs, surface, interpolate=interpolate, local_fill=local_fill,
        shifts=VALIDATION_SHIFTS[:n_shifts], donor_sets=donor_sets, rate=rate, spikes=spikes)
    mse = _validation_mse(errs, ok, full)
    floor = np.zeros_like(mse)
    _floor_rigid_errors(floor, disagreement, run, _disagreement_shares(runs, rate))
    mse = np.maximum(mse, floor)  # what the outlier tests compare
    floor = np.maximum(floor, _end_excess_floor(est, runs, positions, mse))
    wr = _blend_weights(np.maximum(mse, floor))
    twins = _earlier_twins(est, runs)
    _consensus_where_unscored(wr, mse, est, runs, full, twins)
    _count_once(wr, twins)  # a model given twice weighs once
    bounds = _take_bounds(positions, np.unique([m for m, _, _ in runs]))
    jumps = _jumps_in_runs(est, runs, positions, bounds)  # steps no measured sample makes
    est = np.where(jumps[..., None], np.nan, est)  # those samples out of every test
    wr[_outlying_estimates(est, runs, mse, wr, positions)] = 0.0  # far off in the gap
    unfit = _keep_plausible(wr, est, runs, positions, bounds)  # off its rigid partners
    w = np.where(holes[None], wr[:, np.maximum(run, 0)], 0.0)  # (K, F, M)
    wpr = np.maximum(_validation_profile(profile, ok, full), floor[..., None])
    wpr = np.where(np.isfinite(wpr), np.maximum(wpr, 1e-12) ** -BLEND_POWER, np.nan)
    _count_once(wpr, twins)
    wp = _profile_weights(wpr, runs, run, holes)
    w = np.where((w > 0) & np.isfinite(wp), wp, w)  # the copies' error at that distance
    have = finite_rows(est) & holes[None]  # (K, F, M)
    wf = np.where(have, w, 0.0)
    tot = wf.sum(0)
    blend = (np.nan_to_num(est) * wf[..., None]).sum(0) / np.maximum(tot, 1e-300)[..., None]
    out = X.copy()
    sel = holes & (tot > 0)
    out[sel] = blend[sel]
    nothing = holes & (tot == 0) & (unfit[0, np.maximum(run, 0)] | jumps[0])
    out[nothing] = np.nan  # no plausible member: the local fill is not either
    out[_jumps_in_runs(out[None], runs, positions, bounds, erratic=False)[0]] = np.nan  # parting
    share = wf[:, sel] / tot[sel]
    return out, {n: float(share[k].mean()) if sel.any() else 0.0
                 for k, n in enumerate(BLEND_MODELS)}


#: Two blend members whose estimates of a run agree within this (m) are one model
#: (:func:`_earlier_twins`): the same donors, their terms added in another order.
SAME_ESTIMATE_TOLERANCE = 1e-9


def _earlier_twins(est: np.ndarray, runs: list[tuple[int, int, int]]) -> np.ndarray:
    """``(K, R)`` int: the first earlier model whose estimate of run ``r`` is model ``k``'s
    (within :data:`SAME_ESTIMATE_TOLERANCE` at every sample; ``est`` ``(K, F, M, 3)``,
    :func:`_blend_members`), -1 where none is: ``>= 0`` marks a repeated estimate.

    On a sparse capture the most rigid markers near a marker are often its 3 nearest:
    the two rigid-body fills then give one estimate, which weighed twice in the blend
    (PiG calibration, left wrist, 0.1 s holes: both at 0.59-0.82 mm where the spline
    was 0.25-0.36 mm, blend 0.36-0.61 mm; counted once 0.29-0.53 mm)."""
    K = est.shape[0]
    out = np.full((K, len(runs)), -1, dtype=np.int64)
    for r, (m, a, b) in enumerate(runs):
        e = est[:, a:b, m]  # (K, L, 3)
        fin = np.isfinite(e).all((1, 2))
        for k in range(1, K):
            if fin[k]:
                out[k, r] = next((j for j in range(k) if fin[j] and np.abs(e[k] - e[j]).max()
                                  <= SAME_ESTIMATE_TOLERANCE), -1)
    return out


def _count_once(weights: np.ndarray, twins: np.ndarray) -> None:
    """Set the weights ``(K, R)`` (or ``(K, R, B)``, NaN where unscored) of the repeated
    estimates (``twins (K, R)``: the earlier model giving each, :func:`_earlier_twins`) to
    0, in place, the first model giving it taking the largest weight of them: the estimate
    weighs once, as much as its best validated giver.  Before, the repeat alone lost its
    weight: on basket_sprint (0.1 s / 10 % / clustered, mask seed 699) the local fill of
    SWL:Marker2's run 2242-2259 was the spline's (1.04 mm off, validated 1.09 mm against
    the local fill's 48 mm on other copies), the spline's weight went, the rigid-body fills
    could not reach the knocked-out sample and the whole-body PCA filled it alone, 502 mm
    off."""
    repeated = twins >= 0
    for k, r in zip(*np.nonzero(repeated)):
        j = twins[k, r]
        while twins[j, r] >= 0:  # the first giver of that estimate
            j = twins[j, r]
        weights[j, r] = np.fmax(weights[j, r], weights[k, r])
    weights[repeated] = 0.0


def _floor_rigid_errors(mse: np.ndarray, disagreement: dict[int, np.ndarray],
                        run: np.ndarray, share: float | np.ndarray = RIGID_DISAGREEMENT_SHARE,
                        ) -> None:  # fmt: skip
    """Raise the validation errors ``mse`` ``(K, R)`` of the rigid-body fills, in place, to
    ``share``² (:data:`RIGID_DISAGREEMENT_SHARE`, or one per run ``(R,)``,
    :func:`_disagreement_shares`) × the mean squared disagreement of their carries over
    each run (``disagreement``: ``{model index: (F, M)}``, :func:`_rigid_body_fill`; ``run``
    ``(F, M)``: the run of each hole, -1 elsewhere).  A model not scored on a run (NaN)
    stays unscored; a run carried from one side only is not raised."""
    R = mse.shape[1]
    for k, dis in disagreement.items():
        at = (run >= 0) & np.isfinite(dis)
        n = np.bincount(run[at], minlength=R)
        d2 = np.bincount(run[at], weights=dis[at] ** 2, minlength=R) / np.maximum(n, 1)
        mse[k] = np.maximum(mse[k], share ** 2 * d2)  # NaN stays NaN


def _end_excess_floor(est: np.ndarray, runs: list[tuple[int, int, int]],
                      positions: np.ndarray, mse: np.ndarray) -> np.ndarray:
    """``(K, R)``: the square of each member's end excess on each run
    (:func:`fill_checks._end_excess`; 0 where unknown), a floor of its mean squared error,
    at most :data:`fill_checks.BOUNDARY_GUARD`² × the run's least validated one (``mse (K,
    R)``): the ends tell apart members the copies scored alike and never hand a run to
    members they scored far worse.  Without that bound, a rigid patch on a random walk
    (``test_clean``'s rigid capture), whose exact members miss the carried trajectory by
    its next random step, was handed to the others: 22 mm off where it had been exact."""
    out = np.zeros((est.shape[0], len(runs)))
    for r, (m, a, b) in enumerate(runs):
        out[:, r] = np.nan_to_num(_end_excess(est[:, a:b, m], positions, m, a, b)) ** 2
    best = np.nanmin(np.where(np.isfinite(mse), mse, np.inf), axis=0)  # inf: none scored
    return np.minimum(out, BOUNDARY_GUARD ** 2 * best)


def _profile_weights(weights: np.ndarray, runs: list[tuple[int, int, int]], run: np.ndarray,
                     holes: np.ndarray) -> np.ndarray:
    """``(K, F, M)``: each hole sample's weights ``(K, R, B)`` by its distance from its run's
    nearer measured end (:func:`_profile_bins`); NaN off the holes."""
    out = np.full((weights.shape[0],) + holes.shape, np.nan)
    f, m = np.nonzero(holes)
    r = run[f, m]
    a = np.array([x[1] for x in runs], dtype=np.int64)
    b = np.array([x[2] for x in runs], dtype=np.int64)
    long = (b - a)[r] >= PROFILE_MIN_LENGTH
    f, m, r = f[long], m[long], r[long]
    out[:, f, m] = weights[:, r, _profile_bins(f, a[r], b[r], holes.shape[0])]
    return out


def _disagreement_shares(runs: list[tuple[int, int, int]], rate: float | None
                         ) -> float | np.ndarray:  # fmt: skip
    """The share of :func:`_floor_rigid_errors` per run ``(R,)``:
    :data:`RIGID_DISAGREEMENT_SHARE` × the run's duration ÷
    :data:`RIGID_DISAGREEMENT_DURATION`, at most the share (``rate`` None: the share)."""
    if rate is None or not runs:
        return RIGID_DISAGREEMENT_SHARE
    frames = np.array([b - a for _, a, b in runs], dtype=float)
    return RIGID_DISAGREEMENT_SHARE * np.minimum(
        1.0, frames / (rate * RIGID_DISAGREEMENT_DURATION))


def _blend_members(X: np.ndarray, positions: np.ndarray, holes: np.ndarray,
                   surface: MarkerSurface, *, interpolate: int,
                   disagreement: dict[int, np.ndarray] | None = None,
                   spline_sides: tuple[np.ndarray, np.ndarray] | None = None,
                   donor_sets: dict[int, dict] | None = None,
                   spikes: np.ndarray | None = None) -> np.ndarray:
    """``(K, F, M, 3)``: the estimates of :data:`BLEND_MODELS` at ``holes`` (NaN elsewhere
    and where a model cannot estimate), ``X`` being the local fill; ``disagreement``,
    optional ``{model index: (F, M) array}``: the rigid-body fills' (filled in, see
    :func:`_rigid_body_fill`); ``spline_sides``: the spline's support per hole
    (``sides`` of :func:`_interpolate_interior`); ``donor_sets``, optional ``{model
    index: dict}``: the rigid-body fills' donors per run (filled in, see
    :func:`_rigid_body_fill`); ``spikes``, optional ``(F, M)`` bool: measured samples the
    spline does not interpolate through (:func:`fill_checks._isolated_spikes`)."""
    dis = disagreement or {}
    dons = donor_sets or {}
    low = whole_body_pca(X, finite_rows(positions), holes)
    spl = np.full_like(positions, np.nan)
    through = positions if spikes is None else np.where(spikes[..., None], np.nan, positions)
    _interpolate_interior(spl, through, holes, interpolate, sides=spline_sides)
    rig = _rigid_body_fill(positions, holes, surface.reference,
                           disagreement=dis.get(RIGID_MODELS[0]),
                           donor_sets=dons.get(RIGID_MODELS[0]))
    near = _rigid_body_fill(positions, holes, surface.reference, donors="nearest",
                            disagreement=dis.get(RIGID_MODELS[1]),
                            donor_sets=dons.get(RIGID_MODELS[1]))
    return np.stack([np.where(holes[..., None], X, np.nan), low, spl, rig, near])


def _validation_errors(positions: np.ndarray, holes: np.ndarray,
                       runs: list[tuple[int, int, int]], surface: MarkerSurface, *,
                       interpolate: int, local_fill: Callable[[np.ndarray], np.ndarray],
                       shifts: tuple[int, ...],
                       donor_sets: dict[int, dict] | None = None,
                       rate: float | None = None,
                       spikes: np.ndarray | None = None,
                       ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Each model's errors on the validation copies of each run.

    Every run of holes is copied next to itself (:func:`_shifted_runs`, once
    per shift) onto measured samples, which are knocked out and estimated by
    the models (``local_fill``, the local fill without the blend; the spline with at
    most the measured samples the run itself has on each side, :func:`_gap_support`, so that a
    spline short of samples at the hole is scored as it will be used).
    With ``donor_sets`` (``{model index: {(marker, start, stop): donors}}``, the
    rigid-body fills' donors of each run, :func:`_rigid_body_fill`), a rigid-body fill
    is scored only on the copies where the run's own donors are measured, where it has
    any (:func:`_donors_at_copies`).  With ``rate`` (frames per second), a copy is
    placed where its marker moves as at its run's ends (:data:`MOTION_MATCH`).  ``spikes``
    (``(F, M)`` bool, :func:`fill_checks._isolated_spikes`): samples the spline does not
    interpolate through, on the copies as on the run.

    Returns
    -------
    mse : (K, S, R) float ndarray
        Mean squared error of model ``k`` on copy ``s`` of run ``r``.
    ok : (K, S, R) bool ndarray
        The copy has measured samples and the model estimated all of them.
    profile : (K, S, R, B) float ndarray
        The same per bin of the copy's samples by their distance from its nearer measured
        end (:func:`_profile_bins`); NaN where the bin has no sample or the model missed one.
    """
    F, M, _ = positions.shape
    obs = finite_rows(positions)
    n_runs = len(runs)
    K = len(BLEND_MODELS)
    support = _gap_support(obs, runs, interpolate)
    motion = ((_steps(positions), MOTION_FLOOR / rate, max(2, round(MOTION_WINDOW * rate)))
              if rate else None)
    mse = np.zeros((K, len(shifts), n_runs))
    B = len(PROFILE_EDGES) + 1
    profile = np.full((K, len(shifts), n_runs, B), np.nan)
    ok = np.zeros((K, len(shifts), n_runs), dtype=bool)
    same = np.ones((K, len(shifts), n_runs), dtype=bool)  # carried with the run's donors
    for s, k in enumerate(shifts):
        moved = _shifted_runs(runs, (F, M), k, support=interpolate, measured=obs,
                              motion=motion)
        val = (moved >= 0) & obs
        if not val.any():
            continue
        Pv = np.where(val[..., None], np.nan, positions)
        Xv = local_fill(Pv)
        ev = _blend_members(Xv, Pv, holes | val, surface, interpolate=interpolate,
                            spline_sides=(np.where(val, moved, -1), support), spikes=spikes)
        err = ((ev[:, val] - positions[val][None]) ** 2).sum(-1)  # (K, n)
        for j, sets in (donor_sets or {}).items():
            same[j, s] = _donors_at_copies(moved, runs, sets, obs & ~val)
        rid = moved[val]
        cnt = np.bincount(rid, minlength=n_runs)
        span_f, span_m = np.nonzero(moved >= 0)
        lo, hi = np.full(n_runs, F), np.zeros(n_runs, dtype=np.int64)
        np.minimum.at(lo, moved[span_f, span_m], span_f)
        np.maximum.at(hi, moved[span_f, span_m], span_f + 1)
        at = rid * B + _profile_bins(np.nonzero(val)[0], lo[rid], hi[rid], F)
        cnt_b = np.bincount(at, minlength=n_runs * B)
        for j in range(K):
            fin = np.isfinite(err[j])
            mse[j, s] = np.bincount(rid[fin], weights=err[j][fin], minlength=n_runs) / \
                np.maximum(cnt, 1)
            ok[j, s] = (cnt > 0) & (np.bincount(rid[~fin], minlength=n_runs) == 0)
            full_b = (cnt_b > 0) & (np.bincount(at[~fin], minlength=n_runs * B) == 0)
            profile[j, s] = np.where(full_b, np.bincount(at[fin], weights=err[j][fin],
                                                         minlength=n_runs * B)
                                     / np.maximum(cnt_b, 1), np.nan).reshape(n_runs, B)
    ok &= same | ~(ok & same).any(1, keepdims=True)  # the run's donors, where they carry any
    return mse, ok, profile


def _donors_at_copies(moved: np.ndarray, runs: list[tuple[int, int, int]], own: dict,
                      measured: np.ndarray) -> np.ndarray:
    """``(R,)`` bool: the donors a rigid-body fill carries each run with (``own``:
    ``{(marker, start, stop): donors}``, :func:`_rigid_body_fill`) are all measured
    (``measured (F, M)``, in the copies' pass) over the run's copy in ``moved``
    (``(F, M)``, :func:`_shifted_runs`) and one frame on each side, so that the fill
    carries the copy as it carries the run.  True where the run is not carried or has no
    copy."""
    F, _ = moved.shape
    out = np.ones(len(runs), dtype=bool)
    seen = _measured_before(measured)
    hit, col = np.nonzero(moved >= 0)
    rid = moved[hit, col]
    lo = np.full(len(runs), F, dtype=np.int64)
    hi = np.full(len(runs), -1, dtype=np.int64)
    np.minimum.at(lo, rid, hit)
    np.maximum.at(hi, rid, hit)
    for r in np.flatnonzero(hi >= 0):
        d = own.get(runs[r])
        if d is None:
            continue
        a, b = max(lo[r] - 1, 0), min(hi[r] + 2, F)
        out[r] = bool((seen[b, list(d)] - seen[a, list(d)] == b - a).all())
    return out


def _validation_mse(mse: np.ndarray, ok: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """``(K, R)``: each model's validation error on a run, the geometric mean of its mean
    squared errors on the run's copies.

    Geometric, so that one copy on a glitch does not decide the run: on the PiG
    calibration a copy moved onto LPSI's first 6 frames (jumps of 30 mm) raised all
    five models' arithmetic means to 4-18 mm (0.1-0.7 mm with that copy elsewhere),
    and the blend of a 0.1 s hole the spline fills within 0.1 mm came out 0.6 mm off.
    A run's models are compared on the same copies: those that every model in
    ``usable`` (``(K, R)`` bool: it estimates the whole run) estimated in
    full (a spline cannot reach a copy moved onto the take's edge, where every
    model does worse); when no copy is common, each model's own full copies.
    NaN where a model estimated no copy in full.

    Tried and dropped: every copy a model was scored on counted, each copy's difficulty
    fitted from the models scored on it (least squares, ``log mse = a_model + b_copy``).
    basket_sprint's ``ArmL:Marker4`` (0.1 s / 1 % / independent, mask seed 779), whose
    rigid-body fills were scored on the run's margins alone (copy 0), so that all five
    models were judged there (23-72 mm each; in the gap 3.3-9.5 mm): blend 5.14 -> 3.36 mm
    (the spline's 3.37), and basket's six 0.1 s configurations on mask seeds 770-779, same
    samples, 5 -> 6 of 6 within 5 % (worst 1.26 -> 1.00).  But the copies that are hard for
    the spatial models are not hard for the spline: the push-rim run of
    ``test_a_rigid_fill_is_judged_where_its_own_donors_carry_it`` (copies at which the
    local and whole-body fills erred by 76-120 mm, the spline by 0.9-1.3) gave the spline
    the run over the rigid-body fill, 0.64 -> 1.76 mm; and a rigid capture's exact models
    (errors of 1e-30 on some copies) set the scale of all the others.  ``mse`` and ``ok`` are
    ``(K, S, R)`` (:func:`_validation_errors`).
    """
    return _geometric_mean(mse, _common_copies(ok, usable))


def _common_copies(ok: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """``(K, S, R)`` bool: the copies :func:`_validation_mse` scores each model on."""
    common = (ok | ~usable[:, None]).all(0) & ok.any(0)  # (S, R)
    return np.where(common.any(0)[None, None], common[None] & ok, ok)


def _geometric_mean(mse: np.ndarray, use: np.ndarray) -> np.ndarray:
    """The geometric mean over axis 1 of ``mse`` where ``use`` (NaN where none is)."""
    n = use.sum(1)
    log_mse = np.log(np.maximum(np.where(use, mse, 1.0), np.finfo(float).tiny))
    return np.where(n > 0, np.exp((log_mse * use).sum(1) / np.maximum(n, 1)), np.nan)


def _validation_profile(profile: np.ndarray, ok: np.ndarray, usable: np.ndarray
                        ) -> np.ndarray:  # fmt: skip
    """``(K, R, B)``: :func:`_validation_mse` per bin of the samples' distance from the
    nearer measured end (``profile (K, S, R, B)``, :func:`_validation_errors`), on the
    same copies; NaN where no such copy has samples in the bin."""
    use = _common_copies(ok, usable)[..., None] & np.isfinite(profile)
    return _geometric_mean(profile, use)


def _blend_weights(mse: np.ndarray) -> np.ndarray:
    """``(K, R)`` blend weights of each run from the validation errors ``mse`` ``(K, R)``:
    ∝ mse^-:data:`BLEND_POWER`; a run with no model scored keeps the local fill."""
    wr = np.where(np.isfinite(mse), np.maximum(mse, 1e-12) ** -BLEND_POWER, 0.0)
    wr[0, ~np.isfinite(mse).any(0)] = 1.0  # nothing scored: the local fill only
    return wr


def _consensus_where_unscored(weights: np.ndarray, mse: np.ndarray, est: np.ndarray,
                              runs: list[tuple[int, int, int]], full: np.ndarray,
                              twins: np.ndarray) -> None:  # fmt: skip
    """Give each run that no model was scored on (no validation copy of it could be placed
    on measured samples; ``mse (K, R)`` all NaN, :func:`_validation_mse`) to the member
    whose estimate lies nearest the others' (the medoid: the least sum of RMS distances over
    the run to the other members that estimate all of it, ``full (K, R)``, an estimate given
    twice counted once: ``twins (K, R)``, :func:`_earlier_twins`), in place in
    ``weights (K, R)`` (:func:`_blend_weights`, which gives such a run to the local fill);
    with fewer than 3 such members there is no majority to follow and the local fill keeps
    it.  Runs any model was scored on are left as they are.

    basket_sprint (120 Hz, 26 markers), the 0.1 s / 10 % / independent mask of seed 717:
    ``ForearmL:Marker4``, frames 3234-3246, had no copy scored; the local fill alone was
    90.6 mm off where the four other members agreed within 4-9 mm of the truth."""
    for r in np.flatnonzero(~np.isfinite(mse).any(0)):
        m, a, b = runs[r]
        # an estimate given twice (the two rigid-body fills on the same donors) is one voice
        members = np.flatnonzero(full[:, r] & (twins[:, r] < 0)
                                 & np.isfinite(est[:, a:b, m]).all((1, 2)))  # fmt: skip
        if len(members) < 3:
            continue
        e = est[members, a:b, m]  # (n, L, 3)
        d = np.sqrt(np.mean(np.sum((e[:, None] - e[None]) ** 2, -1), -1))  # (n, n) RMS
        weights[:, r] = 0.0
        weights[members[np.argmin(d.sum(1))], r] = 1.0
