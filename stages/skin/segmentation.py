"""The near-rigid parts of a marker surface (Park & Hodgins 2006, §5.2): type and codec.

:class:`Segmentation` is what the ``segment`` stage (:mod:`mocapflow.stages.skin.segment`)
produces and the deformation (:mod:`mocapflow.stages.skin.deform`) consumes: soft
weights ``α`` of every marker for every part, the reference pose, the marker
surface's triangles and each part's local frame.  It is stored with its own
codec (``"segmentation"``); :func:`adjusted_rand_index` compares two labelings.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from mocapflow.pipeline.codecs import Encoded, codec, component_coords, label_coord

__all__ = ["Segmentation", "SegmentationError", "adjusted_rand_index"]


class SegmentationError(ValueError):
    """The inputs of the segmentation are inconsistent or insufficient."""


@dataclass(eq=False)
class Segmentation:
    """Near-rigid parts of a marker surface.

    Parameters
    ----------
    labels : list of str
        ``M`` marker labels (the order of every per-marker array).
    part_names : list of str
        ``P`` part names.
    weights : (M, P) float ndarray
        Soft weights ``alpha`` of each marker for each part; rows sum to 1,
        zero where the marker does not belong to the part.
    reference : (M, 3) float ndarray
        Reference positions of the markers (metres).
    faces : (T, 3) int ndarray
        Triangles of the marker surface (marker indices).
    origins : (P, 3) float ndarray
        Origin of each part's local frame (weighted mean reference position).
    axes : (P, 3, 3) float ndarray
        Columns are the local axes of each part (eigenvectors of the reference
        covariance, decreasing variance, right-handed).
    triangle_clusters : (T,) int ndarray
        Raw mean-shift cluster of each triangle (before clean-up).
    attrs : dict
        Parameters and clean-up report.
    """

    labels: list[str]
    part_names: list[str]
    weights: np.ndarray
    reference: np.ndarray
    faces: np.ndarray
    origins: np.ndarray
    axes: np.ndarray
    triangle_clusters: np.ndarray
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.labels = [str(x) for x in self.labels]
        self.part_names = [str(x) for x in self.part_names]
        self.weights = np.asarray(self.weights, dtype=np.float64)
        self.reference = np.asarray(self.reference, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        self.origins = np.asarray(self.origins, dtype=np.float64)
        self.axes = np.asarray(self.axes, dtype=np.float64)
        self.triangle_clusters = np.asarray(self.triangle_clusters, dtype=np.int64)
        M, P = len(self.labels), len(self.part_names)
        if self.weights.shape != (M, P):
            raise SegmentationError(f"weights: expected {(M, P)}, got {self.weights.shape}")
        if self.reference.shape != (M, 3):
            raise SegmentationError(f"reference: expected {(M, 3)}, got {self.reference.shape}")
        if self.origins.shape != (P, 3) or self.axes.shape != (P, 3, 3):
            raise SegmentationError("origins/axes disagree with the number of parts")

    @property
    def n_parts(self) -> int:
        """Number of parts ``P``."""
        return len(self.part_names)

    def __repr__(self) -> str:
        """One line: markers, parts (the first few names), surface triangles."""
        names = ", ".join(repr(n[:24]) for n in self.part_names[:3])
        more = ", …" if self.n_parts > 3 else ""
        return (f"Segmentation({len(self.labels)} markers in {self.n_parts} parts"
                f"{': ' + names + more if names else ''}; {self.faces.shape[0]} triangles)")

    @property
    def hard_labels(self) -> np.ndarray:
        """``(M,)`` int: the part of largest weight of each marker."""
        return np.argmax(self.weights, axis=1)

    def members(self, p: int) -> np.ndarray:
        """Indices of the markers with a non-zero weight for part ``p``."""
        return np.flatnonzero(self.weights[:, p] > 0)


def _encode_segmentation(s: Segmentation) -> Encoded:
    return Encoded(
        "segmentation",
        {
            "weights": (s.weights, ("marker", "part")),
            "reference": (s.reference, ("marker", "xyz")),
            "faces": (s.faces, ("face", "corner")),
            "origins": (s.origins, ("part", "xyz")),
            "axes": (s.axes, ("part", "xyz", "axis")),
            "triangle_clusters": (s.triangle_clusters, ("face",)),
        },
        {"labels": s.labels, "part_names": s.part_names, "attrs": s.attrs},
        {"marker": label_coord(s.labels, "marker"), "part": label_coord(s.part_names, "part"),
         **component_coords("xyz")},
    )


def _decode_segmentation(e: Encoded) -> Segmentation:
    a = e.arrays
    return Segmentation(
        labels=e.attrs["labels"],
        part_names=e.attrs["part_names"],
        weights=a["weights"][0],
        reference=a["reference"][0],
        faces=a["faces"][0],
        origins=a["origins"][0],
        axes=a["axes"][0],
        triangle_clusters=a["triangle_clusters"][0],
        attrs=e.attrs.get("attrs", {}),
    )


codec("segmentation", encode=_encode_segmentation, decode=_decode_segmentation)(Segmentation)


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """Adjusted Rand index of two labelings (Hubert & Arabie 1985).

    Parameters
    ----------
    a, b : (N,) int ndarray
        Cluster labels of the same ``N`` items (any integer values).

    Returns
    -------
    float
        1 for identical partitions (up to renaming), about 0 for chance.
    """
    a = np.asarray(a).ravel()
    b = np.asarray(b).ravel()
    if a.shape != b.shape:
        raise ValueError(f"adjusted_rand_index: {a.shape} vs {b.shape} labels")
    n = a.size
    if n < 2:
        return 1.0
    _, ai = np.unique(a, return_inverse=True)
    _, bi = np.unique(b, return_inverse=True)
    table = sp.coo_matrix((np.ones(n), (ai, bi))).toarray()

    def pairs(x: np.ndarray) -> float:
        return float(np.sum(x * (x - 1)) / 2)

    sum_ij = pairs(table)
    sum_a = pairs(table.sum(1))
    sum_b = pairs(table.sum(0))
    expected = sum_a * sum_b / (n * (n - 1) / 2)
    maximum = (sum_a + sum_b) / 2
    if maximum == expected:
        return 1.0
    return float((sum_ij - expected) / (maximum - expected))
