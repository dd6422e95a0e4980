"""Data types: validation and exact codec round trips."""

import numpy as np
import pytest

from mocapflow.pipeline.codecs import decode, digest_encoded, encode
from mocapflow.stages.motion.datatypes import Markers, Mesh, Motion, Skeleton, Strokes


def _skeleton():
    return Skeleton(
        names=["root", "a", "b"],
        parents=[-1, 0, 1],
        offsets=[[0, 0, 0], [0, 0.5, 0], [0, 0.25, 0]],
        channels=[
            ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"],
            ["Zrotation", "Xrotation", "Yrotation"],
            ["Xrotation", "Yrotation", "Zrotation"],
        ],
        end_parents=[2],
        end_offsets=[[0, 0.1, 0]],
    )


def test_markers_round_trip_keeps_nan_fragments_and_attrs():
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(7, 4, 3))
    pos[2, 1] = np.nan
    frag = np.full((7, 2, 3), np.nan)
    frag[3:5, 0] = 1.0
    m = Markers(pos, list("abcd"), 69.9926, first_frame=704, residuals=np.abs(pos[..., 0]),
                fragments=frag, fragment_labels=["*1", "*2"], attrs={"source_unit": "mm"})
    back = decode(encode(m))
    np.testing.assert_array_equal(back.positions, m.positions)
    np.testing.assert_array_equal(back.fragments, m.fragments)
    np.testing.assert_array_equal(back.residuals, m.residuals)
    assert (back.labels, back.rate, back.first_frame) == (m.labels, 69.9926, 704)
    assert back.fragment_labels == ["*1", "*2"] and back.attrs == {"source_unit": "mm"}
    assert digest_encoded(encode(back)) == digest_encoded(encode(m))
    assert m.visible.sum() == 7 * 4 - 1
    sub = m.take_frames(np.array([1, 3, 4]))
    np.testing.assert_array_equal(sub.positions, pos[[1, 3, 4]])
    np.testing.assert_array_equal(sub.residuals, m.residuals[[1, 3, 4]])
    np.testing.assert_array_equal(sub.fragments, frag[[1, 3, 4]])
    assert sub.fragment_labels == ["*1", "*2"] and m.take_frames(slice(2, 5)).n_frames == 3


def test_motion_round_trip_and_rotation_order():
    sk = _skeleton()
    q = np.tile([1.0, 0, 0, 0], (5, 3, 1))
    mot = Motion(sk, np.arange(15.0).reshape(5, 3), q, 120.0, attrs={"source_unit": "cm"})
    back = decode(encode(mot))
    np.testing.assert_array_equal(back.rotations, q)
    np.testing.assert_array_equal(back.skeleton.end_offsets, sk.end_offsets)
    assert back.skeleton.names == sk.names and back.skeleton.channels == sk.channels
    assert sk.rotation_order(0) == "ZXY" and sk.rotation_order(2) == "XYZ"
    assert sk.children(0) == [1] and sk.index("b") == 2


def test_mesh_and_strokes_round_trip():
    mesh = Mesh(np.random.default_rng(1).normal(size=(3, 4, 3)), [[0, 1, 2], [1, 2, 3]], rate=30)
    back = decode(encode(mesh))
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    assert back.animated and back.rate == 30
    s = Strokes(np.arange(20.0).reshape(10, 2), [0, 4], 200.0, attrs={"letter": "a"})
    sb = decode(encode(s))
    assert [len(x) for x in sb.strokes()] == [4, 6] and sb.attrs["letter"] == "a"


@pytest.mark.parametrize(
    "build, message",
    [
        (lambda: Markers(np.zeros((2, 3, 3)), ["a"], 100), "1 labels for 3 markers"),
        (lambda: Markers(np.zeros((2, 3)), [], 100), r"expected \(F, M, 3\)"),
        (lambda: Skeleton(["a", "b"], [-1, 1], np.zeros((2, 3)), [[], []]), "parent"),
        (lambda: Mesh(np.zeros((3, 3)), [[0, 1, 3]]), "out of range"),
        (lambda: Strokes(np.zeros((4, 2)), [1], 10), "start with 0"),
        (
            lambda: Motion(_skeleton(), np.zeros((4, 3)), np.zeros((5, 3, 4)), 30),
            "frame count",
        ),
    ],
)
def test_invalid_data_is_rejected_with_a_reason(build, message):
    with pytest.raises(ValueError, match=message):
        build()
