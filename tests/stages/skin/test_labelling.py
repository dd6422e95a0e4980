"""Unlabelled takes, label templates and several subjects in one take (issue 15 item 2).

Simulated captures carry the true marker of every fragment, so labels and merges
are scored exactly; the real case is the shared Qualisys take beside a copy of
itself played backwards.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocapflow.pipeline import Context
from mocapflow.stages.metrics.cleaning import (
    gap_mask,
    score_merges,
    score_unlabelled,
    strip_labels,
)
from mocapflow.stages.motion.formats.c3d import read_c3d, write_c3d
from mocapflow.stages.motion.simulate.capture import simulate_capture
from mocapflow.stages.skin.clean import CleanError, clean
from mocapflow.stages.skin.labelling import (
    match_template,
    read_label_template,
    subject_groups,
    template_labelling,
)
from mocapflow.stages.skin.predict import choose_reference_frame, reference_pose

QUALISYS = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "c3d" / \
    "ezc3d-testFiles_Qualisys.c3d"

SEED = 3  # not a seed any clean parameter was tuned on
N_MARKERS, N_FRAMES = 200, 300


def _sim(motion: str, seed: int = SEED):
    return simulate_capture(n_markers=N_MARKERS, n_frames=N_FRAMES, motion=motion,
                            ctx=Context(rng=np.random.default_rng(seed)))


@pytest.fixture(scope="module")
def dynamic():
    return _sim("dynamic")


def _strip(m, truth, move=None):
    return strip_labels(m, truth["fragment_marker"], move=move)


def _merge_score(res, take, true):
    sc = score_unlabelled(take, true, res["markers"], res["report"]["merges"])
    assert sc["wrong_labels"] == 0
    return sc["wrong"], sc["ghosts_merged"], sc["kept_share"]


def _labelled_share(res, m, truth):
    """Share of real samples kept by a clean of the labelled take."""
    fm = np.asarray(truth["fragment_marker"])
    idx = {n: u for u, n in enumerate(m.fragment_labels)}
    merged = np.zeros(len(fm), dtype=bool)
    merged[[idx[g["fragment"]] for g in res["report"]["merges"]]] = True
    n = np.isfinite(m.fragments).all(-1).sum(0)
    lab = np.isfinite(m.positions).all(-1).sum()
    return (lab + n[(fm >= 0) & merged].sum()) / (lab + n[fm >= 0].sum())


def test_unlabelled_take_keeps_as_much_as_the_labelled_one(dynamic):
    """No labels at all: the reference frame's lasting trajectories become the markers
    and merging joins the rest, with no wrong merge and (within 1 point) as many real
    samples kept as from the labelled take."""
    m, truth = dynamic["markers"], dynamic["truth"]
    take, true = _strip(m, truth)
    with pytest.raises(CleanError, match="has no marker trajectories to clean"):
        clean(take.replace(fragments=take.fragments[:, :0], fragment_labels=[]), ctx=Context())
    res = clean(take, ctx=Context())
    info = res["report"]["labelling"]
    assert info["method"] == "reference_frame"
    assert info["labelled"] >= 0.97 * N_MARKERS
    wrong, ghosts, share = _merge_score(res, take, true)
    assert wrong == 0 and ghosts == 0
    labelled = _labelled_share(clean(m, ctx=Context()), m, truth)
    assert share >= labelled - 0.01, (share, labelled)
    assert share >= 0.95



@pytest.mark.slow
def test_a_limb_that_lost_its_labels_is_merged_by_the_markers_layout():
    """On a range of motion a whole arm loses its labels at once and comes back as new
    fragments; every prediction of its markers then comes from the trunk, 10-20 cm off,
    and no fragment passes the entry test.  The template rounds propose markers by the
    layout of the missing markers and judge the fragments again: measured (seed 3, 200
    markers, 300 frames) 73.2 % of the real samples merged without them, 93.3 % with
    them, no wrong merge either way."""
    sim = _sim("range_of_motion")
    m, truth = sim["markers"], sim["truth"]
    fm = np.asarray(truth["fragment_marker"])
    n = np.isfinite(m.fragments).all(-1).sum(0)
    idx = {f: u for u, f in enumerate(m.fragment_labels)}
    shares = {}
    for rounds in (0, 8):
        res = clean(m, template_merge_rounds=rounds, ctx=Context())
        sc = score_merges(res["report"]["merges"], m.fragment_labels, fm, m.labels)
        assert sc["wrong"] == 0 and sc["ghosts_merged"] == 0, sc["wrong_list"]
        merged = np.zeros(len(fm), dtype=bool)
        merged[[idx[g["fragment"]] for g in res["report"]["merges"]]] = True
        shares[rounds] = n[(fm >= 0) & merged].sum() / n[fm >= 0].sum()
        template = [g for g in res["report"]["merges"] if g.get("predictor") == "template"]
        assert bool(template) == (rounds > 0)
    assert shares[0] < 0.8 and shares[8] > 0.9, shares


def test_label_template_from_an_earlier_session(dynamic, tmp_path):
    """A new session's unlabelled take, turned 40° and moved, is labelled by the
    range-of-motion session's layout scaled ±8 % per axis with 8 mm placement noise:
    every label right, no wrong merge."""
    rom = _sim("range_of_motion")["markers"]
    ref, _, _ = reference_pose(rom.positions, choose_reference_frame(rom.positions))
    ok = np.isfinite(ref).all(1)
    noisy = ref[ok] * [0.92, 1.08, 0.95] + np.random.default_rng(1).normal(0, 0.008,
                                                                          (ok.sum(), 3))
    layout = tmp_path / "layout.json"
    layout.write_text(json.dumps({"labels": [lb for lb, k in zip(rom.labels, ok) if k],
                                  "positions": (noisy * 1000).tolist(), "unit": "mm"}))
    R = Rotation.from_rotvec([0, np.radians(40), 0]).as_matrix()
    m, truth = dynamic["markers"], dynamic["truth"]
    take, true = _strip(m, truth, move=lambda X: X @ R.T + [1.0, 0.0, -0.5])
    res = clean(take, label_template=str(layout), ctx=Context())
    idx = {n: u for u, n in enumerate(take.fragment_labels)}
    came = res["markers"].attrs["labelled_from"]
    right = sum(m.labels[true[idx[f]]] == lb for lb, f in came.items() if true[idx[f]] >= 0)
    assert len(came) >= 0.97 * N_MARKERS and right == len(came)
    assert res["markers"].labels == [lb for lb, k in zip(rom.labels, ok) if k]
    wrong, ghosts, _ = _merge_score(res, take, true)
    assert wrong == 0 and ghosts == 0
    # the same from the earlier session's own C3D (its reference pose, exact layout)
    c3d = write_c3d(rom.replace(fragments=rom.fragments[:, :0], fragment_labels=[]),
                    tmp_path / "rom.c3d")
    lab, info = template_labelling(take, read_label_template(c3d))
    came = lab.attrs["labelled_from"]
    assert info["matched"] >= 0.97 * N_MARKERS
    assert all(m.labels[true[idx[f]]] == lb for lb, f in came.items())
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"labels": ["a", "b"], "positions": [[0, 0, 0]]}))
    with pytest.raises(CleanError, match="bad.json: 2 labels for 1 positions"):
        clean(take, label_template=str(bad), ctx=Context())
    with pytest.raises(CleanError, match="label template .*nope.c3d not found"):
        clean(take, label_template=str(tmp_path / "nope.c3d"), ctx=Context())


def test_match_template_recovers_a_permutation():
    """Known answer: a shuffled, turned, scaled copy of a point layout."""
    rng = np.random.default_rng(0)
    T = rng.uniform(-0.3, 0.3, (80, 3)) * [1, 3, 1]
    perm = rng.permutation(80)
    R = Rotation.from_rotvec([0, 2.0, 0]).as_matrix()
    P = 1.05 * T[perm] @ R.T + [2.0, 0.1, 0.0]
    assign, info = match_template(P, T, up=np.array([0.0, 1.0, 0.0]))
    assert np.array_equal(assign, perm)
    assert info["residual_mm"] < 1.0


def _side_by_side(a, b, gap):
    """Take ``b`` beside ``a`` (``gap`` metres between their reference poses along x),
    labels kept apart by a suffix (no prefix: the subjects are found in space)."""
    ra = a.positions[choose_reference_frame(a.positions)]
    rb = b.positions[choose_reference_frame(b.positions)]
    shift = np.nanmax(ra[:, 0]) - np.nanmin(rb[:, 0]) + gap
    both = a.replace(
        positions=np.concatenate([a.positions, b.positions + [shift, 0, 0]], axis=1),
        labels=[f"{lb}_a" for lb in a.labels] + [f"{lb}_b" for lb in b.labels],
        residuals=None, status=None,
        fragments=np.concatenate([a.fragments, b.fragments + [shift, 0, 0]], axis=1),
        fragment_labels=[f"{lb}a" for lb in a.fragment_labels]
        + [f"{lb}b" for lb in b.fragment_labels])
    return both


def _fill_error(take, mask, truth):
    res = clean(take.replace(positions=np.where(mask[..., None], np.nan, take.positions)),
                merge=False, ctx=Context())
    return np.linalg.norm(res["markers"].positions - truth, axis=-1)[mask], res


def _assert_apart(res, n_a):
    """No surface triangle or neighbour joins the first ``n_a`` markers to the others."""
    surf = res["surface"]
    side = np.arange(len(surf.attrs["labels"])) >= n_a
    faces = np.asarray(surf.faces)
    assert (side[faces] == side[faces[:, :1]]).all()
    for i, row in enumerate(surf.attrs["neighbours"]):
        assert all(side[j] == side[i] for j in row)


@pytest.mark.parametrize("real", [False, True], ids=["simulated", "qualisys"])
def test_two_subjects_in_one_take(dynamic, real):
    """Two subjects 0.5 m apart: found in space, cleaned apart (no cross-subject
    triangle or neighbour), fill error of each within 10 % of that subject alone
    (same deleted samples; mean over 3 masks on the real take, 1 on the simulated)."""
    if real:
        if not QUALISYS.is_file():
            pytest.skip("shared data not found")
        a = read_c3d(QUALISYS)
        b = a.replace(positions=a.positions[::-1].copy(), residuals=None, status=None)
    else:
        a = dynamic["markers"]
        b = _sim("dynamic", seed=SEED + 1)["markers"]
        a, b = (x.replace(fragments=x.fragments[:, :0], fragment_labels=[]) for x in (a, b))
    both = _side_by_side(a, b, 0.5)
    Ma = a.positions.shape[1]
    rng = np.random.default_rng(11)
    err_alone, err_both = [], []
    for _ in range(3 if real else 1):
        ref = np.nanmean(both.positions, axis=0)
        mask = gap_mask(both.visible, ref, rate=both.rate, duration=0.3, fraction=0.1,
                        clustered=False, rng=rng)
        ea, _ = _fill_error(a, mask[:, :Ma], a.positions)
        eb, _ = _fill_error(b, mask[:, Ma:], b.positions)
        e2, res = _fill_error(both, mask, both.positions)
        err_alone.append(np.nanmean(np.r_[ea, eb]))
        err_both.append(np.nanmean(e2))
    assert sorted(res["report"]["subjects"]) == ["subject1", "subject2"]
    _assert_apart(res, Ma)
    ratio = np.mean(err_both) / np.mean(err_alone)
    print(f"fill error together / alone: {ratio:.4f} ({np.mean(err_both) * 1e3:.2f} mm)")
    assert 0.9 <= ratio <= 1.1, (err_both, err_alone)


def test_subjects_by_prefix_and_none():
    """``Name:`` prefixes split subjects even when they stand close; ``none`` keeps one;
    a small prefixed group (a prop) stays with the nearest subject."""
    rng = np.random.default_rng(0)
    ref = np.concatenate([rng.normal(0, 0.2, (30, 3)), rng.normal([0.3, 0, 0], 0.2, (30, 3)),
                          rng.normal([0.3, 0, 0], 0.05, (3, 3))])
    labels = [f"A:m{i}" for i in range(30)] + [f"B:m{i}" for i in range(30)] + \
        [f"Box:m{i}" for i in range(3)]
    from mocapflow.stages.motion.datatypes import Markers  # noqa: PLC0415
    mk = Markers(np.repeat(ref[None], 2, 0), labels, 100.0)
    groups = subject_groups(mk, ref)
    assert [g[0] for g in groups] == ["A", "B"]
    assert sorted(np.concatenate([g[1] for g in groups]).tolist()) == list(range(63))
    assert set(range(60, 63)) <= set(groups[1][1].tolist())
    assert len(subject_groups(mk, ref, mode="none")) == 1


def test_subjects_from_c3d_subjects_parameter():
    """``SUBJECTS:LABEL_PREFIXES`` names the subjects even without ``:`` in the labels."""
    from mocapflow.stages.motion.datatypes import Markers  # noqa: PLC0415
    rng = np.random.default_rng(1)
    ref = rng.normal(0, 0.2, (40, 3))
    labels = [f"S1_m{i}" for i in range(20)] + [f"S2_m{i}" for i in range(20)]
    params = {"SUBJECTS": {"parameters": {"LABEL_PREFIXES": {"value": ["S1_", "S2_"]}}}}
    mk = Markers(np.repeat(ref[None], 2, 0), labels, 100.0,
                 attrs={"c3d_parameters": params})
    groups = subject_groups(mk, ref)
    assert [g[0] for g in groups] == ["S1_", "S2_"]
    assert groups[0][1].tolist() == list(range(20))
    assert len(subject_groups(Markers(mk.positions, labels, 100.0), ref)) == 1  # overlapping


def test_a_body_part_apart_in_space_is_not_a_subject():
    """A sparse marker set leaves more than 0.3 m between a body's groups (btk's PiG
    calibration: 12 leg markers, 0.71 m across, apart from the 23 above them): they stay
    one subject; two whole bodies apart are still two."""
    from mocapflow.stages.motion.datatypes import Markers  # noqa: PLC0415
    pig = QUALISYS.parent / "btkdata_PiG_Calibration-FlatFoot-Hole.c3d"
    if not pig.is_file():
        pytest.skip("shared data not found")
    m = read_c3d(pig)
    ref = m.positions[choose_reference_frame(m.positions)]
    assert len(subject_groups(m, ref, min_span=0.0)) == 2  # the split the span rule stops
    assert [(n, len(i)) for n, i in subject_groups(m, ref)] == [("all", 35)]
    two = np.concatenate([ref, ref + [3.0, 0.0, 0.0]])
    mk = Markers(np.repeat(two[None], 2, 0), [f"m{i}" for i in range(70)], 100.0)
    assert [len(i) for _, i in subject_groups(mk, two)] == [35, 35]


def test_a_take_with_no_marker_trajectory_is_refused_in_one_line():
    """A C3D of rotation or analog data only (ezc3d's C3DRotationExample.c3d: POINT:USED 0)
    reaches clean with no marker and no fragment: one line naming the file and why."""
    from mocapflow.stages.motion.datatypes import Markers  # noqa: PLC0415

    empty = Markers(positions=np.zeros((85, 0, 3)), labels=[], rate=85.0,
                    attrs={"source": "C3DRotationExample.c3d", "n_points": 0})  # fmt: skip
    with pytest.raises(CleanError, match=r"^clean: C3DRotationExample.c3d has no marker "
                       r"trajectories to clean \(the file holds no points: analog or rotation "
                       r"data only\)$"):
        clean(empty, ctx=Context())
