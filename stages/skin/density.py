"""Whether a capture is dense enough for Park & Hodgins' deformation, and which markers
are on objects rather than on the body.

The paper's captures carry ~350 markers, 17 near-rigid parts of ~20 markers each;
the shared real captures carry 26–55 (clinical and sports marker sets).  The
method's per-part model needs, per part, at least 10 markers for the quadratic
(P&H Eq. 6: 9 monomials per axis plus the rigid transform; ``deform``'s
``min_quadratic_markers``) and 3 for the rigid fit, and the residual (Eq. 7)
only helps between markers that are a few centimetres apart.  The rule
(:func:`marker_density`):

    a capture suits the method when the median nearest-neighbour spacing of its
    body markers in the reference pose is at most ``MAX_SPACING`` (75 mm), at
    least ``MIN_COVERED`` (75 %) of its body markers lie in near-rigid parts of at
    least ``MIN_PART_MARKERS`` (10) markers, and there are at least ``MIN_PARTS`` (2)
    parts: a trial in which the body never bends at a joint (a static standing
    trial) segments into one rigid part, where the per-part models say nothing (c3d.org
    sample28 ``standing.C3D``, 32 body markers 45 mm apart, one part: it passed the
    first two tests and was deformed with the quadratic and residual terms).

Measured (reference pose of ``clean``, parts of ``segment``): the demo's simulated
350-marker capture 59 mm, 95 %; ``ezc3d-testFiles_Qualisys.c3d`` 90 mm, 62 %;
``pyomeca_markers_analogs.c3d`` 36 mm, 62 %; ``ktk_kinematics_racing_full.c3d``
43 mm, 24 %; the 35-marker Plug-in-Gait calibration 129 mm, 89 % (one static part).
Below the rule, ``fit_mesh`` fits the template upright (scale, turn about the up
axis and shift; :func:`~mocapflow.stages.skin.mesh_fit.upright_fit`) and
``deform`` skins it rigidly per part (``mode="rigid"``), with one warning from
``segment``.

Markers on objects (a box, a wheelchair, a calibration wand, a sync marker) are
kept apart from the body like a second subject (:func:`object_markers`): by name
(:data:`OBJECT_WORDS` in the label's subject prefix ``prefix:`` or its stem) and by
place (markers not connected to the largest group of markers by links shorter
than ``link`` in the reference pose).
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = [
    "MAX_SPACING",
    "MIN_COVERED",
    "MIN_PARTS",
    "MIN_PART_MARKERS",
    "OBJECT_WORDS",
    "density_warning",
    "marker_density",
    "object_markers",
]

#: Largest median nearest-neighbour marker spacing (m) the method suits.
MAX_SPACING = 0.075
#: Markers of a part for the quadratic (P&H Eq. 6); deform's ``min_quadratic_markers``.
MIN_PART_MARKERS = 10
#: Smallest fraction of the body's markers in parts of at least MIN_PART_MARKERS.
MIN_COVERED = 0.75
#: Fewest near-rigid parts: one part is a body that never bent at a joint in the trial.
MIN_PARTS = 2
#: Words naming objects, matched at the start of a word of the label's prefix
#: (``boite:avant_gauche``) or, without a prefix, of the label (``WheelchairFront``).
OBJECT_WORDS = ("box", "boite", "wheelchair", "chair", "wand", "probe", "sync", "ball",
                "object", "prop", "table", "plate", "racket", "stick", "calib", "cube")


def _words(text: str) -> list[str]:
    """Lower-case words of a label: split at non-letters and camel case."""
    return [w.lower() for w in re.findall(r"[A-Z]?[a-z]+|[A-Z]+(?![a-z])", text)]


def _named_object(label: str) -> bool:
    """The label names an object (by its prefix, else by its stem)."""
    head = label.split(":", 1)[0] if ":" in label else label
    words = _words(head)
    if ":" not in label and re.match(r"^[LR]_", label):  # side-prefixed: a body marker
        return False
    return any(w.startswith(o) for w in words for o in OBJECT_WORDS)


def object_markers(labels: list[str], reference: np.ndarray, *,
                   link: float = 0.6) -> np.ndarray:
    """Markers on objects, not on the body: by name, or apart from the body in space.

    Parameters
    ----------
    labels : list of str
        ``M`` marker labels.
    reference : (M, 3) float ndarray
        Reference pose (metres; NaN: unknown, never an object by place).
    link : float
        Markers closer than this (m), or than 4 x the median nearest-neighbour
        distance if larger, are connected; markers not connected to the largest
        group (of the markers not named as objects) are objects.  A body marker
        set has no gap this wide between neighbouring markers (the largest in the
        shared captures: a head 0.26 m from the sternum and acromion).

    Returns
    -------
    (M,) bool ndarray
        True on object markers.
    """
    ref = np.asarray(reference, dtype=np.float64)
    named = np.array([_named_object(str(lb)) for lb in labels], dtype=bool)
    body = np.flatnonzero(~named & np.isfinite(ref).all(1))
    out = named.copy()
    if len(body) >= 2:
        tree = cKDTree(ref[body])
        nn = float(np.median(tree.query(ref[body], k=2)[0][:, 1]))
        pairs = tree.query_pairs(max(link, 4.0 * nn), output_type="ndarray")
        import scipy.sparse as sp  # noqa: PLC0415 (small)

        A = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                          shape=(len(body), len(body)))  # fmt: skip
        _, comp = connected_components(A, directed=False)
        main = np.argmax(np.bincount(comp))
        out[body[comp != main]] = True
    return out


def marker_density(reference: np.ndarray, part: np.ndarray) -> dict[str, Any]:
    """The density rule of Park & Hodgins' deformation on one body's markers.

    Parameters
    ----------
    reference : (M, 3) float ndarray
        The body's markers in the reference pose (metres).
    part : (M,) int ndarray
        Near-rigid part of each marker (hard labels of ``segment``).

    Returns
    -------
    dict
        ``markers``, ``spacing_mm`` (median nearest-neighbour distance),
        ``part_markers`` (markers per part), ``covered`` (fraction of the markers
        in parts of at least :data:`MIN_PART_MARKERS`), ``suited`` (bool: also at
        least :data:`MIN_PARTS` parts) and
        ``rule`` (the rule in words).
    """
    ref = np.asarray(reference, dtype=np.float64)
    part = np.asarray(part, dtype=np.int64)
    M = len(ref)
    spacing = float(np.median(cKDTree(ref).query(ref, k=2)[0][:, 1])) if M >= 2 else np.inf
    counts = np.bincount(part, minlength=int(part.max()) + 1 if M else 0)
    covered = float(np.sum(counts[part] >= MIN_PART_MARKERS) / M) if M else 0.0
    n_parts = int(np.count_nonzero(counts))
    suited = bool(spacing <= MAX_SPACING and covered >= MIN_COVERED and n_parts >= MIN_PARTS)
    return {
        "markers": int(M),
        "spacing_mm": round(spacing * 1000, 1),
        "part_markers": [int(c) for c in counts if c],
        "covered": round(covered, 3),
        "suited": suited,
        "rule": (f"median marker spacing <= {MAX_SPACING * 1000:.0f} mm and >= "
                 f"{MIN_COVERED:.0%} of the markers in near-rigid parts of >= "
                 f"{MIN_PART_MARKERS} markers, in >= {MIN_PARTS} parts"),
    }  # fmt: skip


def density_warning(density: dict[str, Any], name: str = "capture") -> str:
    """The one warning of a capture below the rule (names the capture and the numbers)."""
    return (
        f"{name}: {density['markers']} body markers, spacing {density['spacing_mm']:.0f} mm, "
        f"{density['covered']:.0%} in parts of >= {MIN_PART_MARKERS} markers, "
        f"{len(density['part_markers'])} part(s): below the "
        f"density Park & Hodgins' deformation needs ({density['rule']}; their captures: "
        "~350 markers); falling back to rigid skinning of the fitted body"
    )
