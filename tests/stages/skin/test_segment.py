"""Near-rigid segmentation (Park & Hodgins 2006 §5.2) on a synthetic limb with known parts."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.pipeline.codecs import decode, encode
from mocapflow.stages.motion.datatypes import Mesh
from mocapflow.stages.skin.segment import (
    mean_shift,
    part_frames,
    rotation_features,
    segment,
    triangle_rotations,
)
from mocapflow.stages.skin.segmentation import Segmentation, SegmentationError, adjusted_rand_index
from tests.stages.skin.conftest import deform_limb, limb_capture, rot_x, rot_y


@pytest.fixture(scope="module")
def limb():
    return limb_capture(noise=0.001)


@pytest.fixture(scope="module")
def limb_seg(limb):
    ctx = Context(part="limb")
    out = segment(limb["markers"], limb["surface"], ctx=ctx)
    return out, ctx


# --------------------------------------------------------------------------- metrics / pieces


def test_adjusted_rand_index_values():
    a = np.array([0, 0, 1, 1, 2, 2])
    assert adjusted_rand_index(a, np.array([5, 5, 3, 3, 9, 9])) == pytest.approx(1.0)
    # hand computation: table [[2,0],[1,1]] -> index 1, expected 2*3/6 = 1 -> ARI 0
    assert adjusted_rand_index([0, 0, 1, 1], [0, 0, 0, 1]) == pytest.approx(0.0)
    rng = np.random.default_rng(1)
    vals = [adjusted_rand_index(rng.integers(0, 4, 400), rng.integers(0, 4, 400))
            for _ in range(20)]  # fmt: skip
    assert abs(np.mean(vals)) < 0.01
    with pytest.raises(ValueError):
        adjusted_rand_index([0, 1], [0, 1, 2])


def test_mean_shift_finds_blobs():
    rng = np.random.default_rng(0)
    centres = np.array([[0, 0], [3, 0], [0, 3.0]])
    X = np.concatenate([c + rng.normal(0, 0.2, (50, 2)) for c in centres])
    labels, modes = mean_shift(X, 0.5)
    assert labels.max() + 1 == 3
    assert adjusted_rand_index(labels, np.repeat([0, 1, 2], 50)) == 1.0
    assert np.min(np.linalg.norm(modes[:, None] - centres[None], axis=-1), axis=1).max() < 0.15
    with pytest.raises(ValueError, match="bandwidth"):
        mean_shift(X, 0.0)


def test_triangle_rotations_of_rigid_motion(limb):
    ref = limb["surface"].vertices
    faces = limb["surface"].faces
    R = rot_y(0.7) @ rot_x(-0.4)
    pos = (ref @ R.T + [0.1, 0.2, 0.3])[None]
    rots = triangle_rotations(pos, ref, faces)
    assert np.abs(rots - R).max() < 1e-12
    pos[0, 5] = np.nan
    rots = triangle_rotations(pos, ref, faces)
    touched = (faces == 5).any(1)
    assert np.isnan(rots[0, touched]).all() and np.isfinite(rots[0, ~touched]).all()


def test_part_frames_are_eigenvectors():
    rng = np.random.default_rng(2)
    ref = rng.normal(size=(40, 3)) * [0.2, 0.05, 0.01] + [1, 2, 3]
    origins, axes = part_frames(ref, np.ones((40, 1)))
    assert np.allclose(origins[0], ref.mean(0))
    A = axes[0]
    assert np.allclose(A.T @ A, np.eye(3), atol=1e-12) and np.linalg.det(A) == pytest.approx(1)
    C = np.cov((ref - origins[0]).T, bias=True)
    lam = np.diag(A.T @ C @ A)
    assert np.all(np.diff(lam) < 0)  # decreasing variance
    assert np.allclose(A.T @ C @ A, np.diag(lam), atol=1e-12)


# --------------------------------------------------------------------------- the stage


def test_two_part_limb_found(limb, limb_seg):
    out, ctx = limb_seg
    seg = out["segmentation"]
    assert seg.n_parts == 2
    assert adjusted_rand_index(seg.hard_labels, limb["parts"]) == pytest.approx(1.0)
    assert np.allclose(seg.weights.sum(1), 1.0)
    assert not np.any((seg.weights > 0) & (seg.weights < 0.2))  # threshold 0.2
    assert out["report"]["n_parts"] == 2
    assert sum(len(p["markers"]) for p in out["report"]["parts"].values()) == len(seg.labels)
    for p in range(2):  # local frames: origin at the part's weighted mean
        w = seg.weights[:, p] / seg.weights[:, p].sum()
        assert np.allclose(seg.origins[p], w @ seg.reference)
        # the limb's long axis (y) is each part's first axis
        assert abs(seg.axes[p][1, 0]) > 0.95


def test_boundary_markers_share_parts():
    # joint exactly at ring 6 with a wide blend (±10 cm): ring 6 moves half with each
    # part -> shared about equally; rings 5 and 7 (20 % / 78 % blend) follow one part
    # far better -> not shared
    d = limb_capture(noise=0.0005)
    ref = d["surface"].vertices
    y = ref[:, 1]
    y6 = np.unique(y)[6]
    t = np.linspace(0, 1, d["markers"].n_frames)
    theta = np.deg2rad(55) * (1 - np.cos(2 * np.pi * 2 * t))
    twist = np.deg2rad(30) * np.sin(2 * np.pi * 3 * t)
    X = deform_limb(ref, theta, twist, 0.0, joints=(y6,), blend=0.1)
    out = segment(d["markers"].replace(positions=X), d["surface"], ctx=Context(part="wide"))
    seg = out["segmentation"]
    assert seg.n_parts == 2
    shared = (seg.weights > 0).sum(1) > 1
    ring6 = np.abs(y - y6) < 1e-9
    assert shared[ring6].mean() >= 0.8 and not shared[~ring6].any()
    assert np.all(np.abs(seg.weights[shared] - 0.5) < 0.2)
    assert sorted(out["report"]["boundary_markers"]) == sorted(
        np.asarray(seg.labels)[shared].tolist()
    )


def test_n_parts_merges_three_part_limb():
    d = limb_capture(noise=0.0005, joints=(0.2, 0.4), n_rings=16)
    out = segment(d["markers"], d["surface"], ctx=Context(part="3"))
    seg = out["segmentation"]
    assert seg.n_parts == 3
    assert adjusted_rand_index(seg.hard_labels, d["parts"]) > 0.95
    out2 = segment(d["markers"], d["surface"], n_parts=2, ctx=Context(part="3"))
    assert out2["segmentation"].n_parts == 2
    assert out2["report"]["merges"][-1]["reason"] == "reduce to n_parts=2"


def test_override_and_errors(limb, tmp_path):
    labels = limb["markers"].labels
    ctx = Context(part="o")
    out = segment(limb["markers"], limb["surface"], override={"tip": labels[-8:]}, ctx=ctx)
    seg = out["segmentation"]
    assert "tip" in seg.part_names and out["report"]["override"]
    p = seg.part_names.index("tip")
    assert set(np.flatnonzero(seg.hard_labels == p)) == set(range(len(labels) - 8, len(labels)))
    for name, info in out["report"]["parts"].items():  # warning iff < 10 members
        warned = any(f"{name!r} has" in w and "< 10" in w for w in ctx.warnings)
        assert warned == (info["n_members"] < 10)
    assert out["report"]["parts"]["tip"]["markers"] == labels[-8:]
    f = tmp_path / "parts.json"
    f.write_text(json.dumps({"tip": labels[-8:]}))
    out_f = segment(limb["markers"], limb["surface"], override_file=str(f), ctx=Context())
    assert np.array_equal(out_f["segmentation"].hard_labels, seg.hard_labels)
    with pytest.raises(SegmentationError, match="NOPE"):
        segment(limb["markers"], limb["surface"], override={"x": ["NOPE"]}, ctx=Context())
    f.write_text("[1, 2]")
    with pytest.raises(SegmentationError, match="parts.json"):
        segment(limb["markers"], limb["surface"], override_file=str(f), ctx=Context())


def test_markers_off_surface_are_left_out(limb):
    surf = limb["surface"]
    ref = surf.vertices.copy()
    ref[3] = np.nan  # never visible in the reference pose
    faces = surf.faces[~(surf.faces == 3).any(1)]
    ctx = Context()
    out = segment(limb["markers"], Mesh(ref, faces, attrs=surf.attrs), ctx=ctx)
    seg = out["segmentation"]
    assert "M003" not in seg.labels and len(seg.labels) == len(ref) - 1
    assert any("M003" in w for w in ctx.warnings)
    with pytest.raises(SegmentationError, match="not in the capture"):
        bad = Mesh(surf.vertices, surf.faces, attrs={"labels": ["X"] + surf.attrs["labels"][1:]})
        segment(limb["markers"], bad, ctx=Context())


def test_segmentation_codec_round_trip(limb_seg):
    seg = limb_seg[0]["segmentation"]
    back = decode(encode(seg))
    assert isinstance(back, Segmentation)
    for name in ("weights", "reference", "faces", "origins", "axes", "triangle_clusters"):
        assert np.array_equal(getattr(back, name), getattr(seg, name))
    assert back.labels == seg.labels and back.part_names == seg.part_names


def test_rotation_features_with_frames_where_nothing_is_measured():
    """Frames where no triangle is measured (a subject walking into the volume: ezc3d's
    ``BTS.c3d`` has no marker in its first 243 frames) fill with 0 and raise no NumPy
    warning; the other missing values take their column's mean as before."""
    rng = np.random.default_rng(0)
    R = rng.standard_normal((50, 12, 3, 3))
    R[:10] = np.nan  # no triangle measured
    R[20, 3] = np.nan  # one triangle hidden
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = rotation_features(R, max_frames=50, max_dims=1000)
    X = R.reshape(50, 12, 9).transpose(1, 0, 2).reshape(12, -1) / np.sqrt(50)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mean = np.nan_to_num(np.nanmean(X, axis=0))
    want = np.where(np.isfinite(X), X, mean)
    assert got.tobytes() == (want - want.mean(0)).tobytes()
    assert not got[:, : 10 * 9].any()  # the unmeasured frames' columns: 0
