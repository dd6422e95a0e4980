"""The range-of-motion (ROM) trial of a subject, shared by all of its trials.

Park & Hodgins (2006, §5.2) find the near-rigid parts once, on a separate
range-of-motion capture of the subject, and deform every other trial with
them.  Two stages make that a graph:

* ``ingest_rom`` reads the ROM C3D named by its ``rom`` param *once* for every
  part (the engine's file override: the node then has a single task that is
  broadcast to every part); left ``None``, it reads each part's own file, so
  each trial is segmented from itself (the behaviour without a ROM trial).
* ``match_markers`` gives a trial's markers in the segmentation's marker order,
  matched by label: markers of the segmentation that the trial lacks become
  missing (NaN) in every frame, trial markers the segmentation lacks are left
  out, each with a warning naming them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mocapflow.pipeline import Context, FilePath, stage
from mocapflow.stages.motion.datatypes import Markers
from mocapflow.stages.motion.ingest import ingest_c3d
from mocapflow.stages.skin.segmentation import Segmentation

__all__ = ["ingest_rom", "match_labels", "match_markers"]


@stage("ingest_rom", outputs=("markers", "report"), file_overrides={"path": "rom"})
def ingest_rom(path: FilePath, *, rom: FilePath | None = None, up: str = "auto",
               forward: str = "auto", ctx: Context) -> dict[str, Any]:
    """Read the range-of-motion trial: the ``rom`` C3D, or the part itself without one.

    Parameters
    ----------
    path : FilePath
        The part's C3D (wire it to ``part``).  When ``rom`` is set the engine
        passes the ``rom`` file here instead and runs the node once.
    rom : FilePath, optional
        A range-of-motion capture of the same subject and marker set.
    up, forward : str
        The file's up axis and facing, as for
        :func:`~mocapflow.stages.motion.ingest.ingest_c3d` (``"auto"``: found from the
        file); give the trial's (``ingest``'s) when it had to be set by hand.

    Returns
    -------
    dict
        ``markers``: :class:`Markers` ``(F, M, 3)`` of the ROM trial;
        ``report``: the ingest summary plus ``segmented_from`` (``"rom"`` or
        ``"trial"``), ``path`` (the file's name) and ``note`` (see
        :func:`mocapflow.stages.motion.ingest.markers_report`).
    """
    source = path if rom is None else rom
    out = ingest_c3d(source, up=up, forward=forward, ctx=ctx)
    if rom is None:
        note = (f"no range-of-motion trial given (param rom): the trial "
                f"{Path(path).name} is segmented from itself")
    else:
        note = f"segmentation from the range-of-motion trial {Path(rom).name}"
    report = {**out["report"], "segmented_from": "trial" if rom is None else "rom",
              "path": Path(source).name, "note": note}  # the name: no path in outputs
    return {"markers": out["markers"], "report": report}


def match_labels(
    labels: list[str], reference_labels: list[str]
) -> tuple[np.ndarray, list[str], list[str]]:
    """Columns of ``labels`` in the order of ``reference_labels``.

    Parameters
    ----------
    labels : list of str
        ``M`` labels of a trial.
    reference_labels : list of str
        ``N`` labels of the segmentation.

    Returns
    -------
    columns : (N,) int ndarray
        Index into ``labels`` of each reference label, -1 where the trial lacks it.
    absent : list of str
        Reference labels the trial lacks (in reference order).
    extra : list of str
        Trial labels the reference lacks (in trial order).
    """
    index = {m: i for i, m in enumerate(labels)}
    columns = np.array([index.get(m, -1) for m in reference_labels], dtype=np.int64)
    known = set(reference_labels)
    absent = [m for m, c in zip(reference_labels, columns) if c < 0]
    extra = [m for m in labels if m not in known]
    return columns, absent, extra


def _name_list(names: list[str], limit: int = 20) -> str:
    more = f", … ({len(names) - limit} more)" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


@stage("match_markers", outputs=("markers", "report"))
def match_markers(
    markers: Markers,
    segmentation: Segmentation,
    *,
    max_absent: float = 0.5,
    ctx: Context,
) -> dict[str, Any]:
    """A trial's markers in the segmentation's marker order, matched by label.

    Parameters
    ----------
    markers : Markers
        Cleaned trial, ``(F, M, 3)`` positions.
    segmentation : Segmentation
        Near-rigid parts (stage ``segment``, possibly of another trial: the
        range-of-motion capture), over ``N`` labelled markers.
    max_absent : float
        Largest share of the segmentation's markers the trial may lack; above it
        the marker sets are not the same and the stage fails.

    Returns
    -------
    dict
        ``markers``: :class:`Markers` ``(F, N, 3)`` in ``segmentation.labels``
        order (NaN for markers the trial lacks; fragments and attrs kept);
        ``report``: ``absent`` (segmentation markers missing from the trial),
        ``left_out`` (trial markers missing from the segmentation), counts.

    Raises
    ------
    ValueError
        When the trial lacks more than ``max_absent`` of the segmentation's
        markers (naming a few of them).
    """
    seg_labels = list(segmentation.labels)
    columns, absent, extra = match_labels(markers.labels, seg_labels)
    N = len(seg_labels)
    if N == 0:
        raise ValueError("match_markers: the segmentation has no markers")
    if len(absent) > max_absent * N:
        raise ValueError(
            f"match_markers: the trial lacks {len(absent)} of the segmentation's {N} markers "
            f"(more than max_absent = {max_absent:.0%}): is the segmentation from the same "
            f"marker set? missing: {_name_list(absent, 10)}"
        )
    if absent:
        ctx.warn(
            f"the trial lacks {len(absent)} markers of the segmentation (range-of-motion "
            f"trial); they are missing in every frame of the deformation: {_name_list(absent)}"
        )
    if extra:
        ctx.warn(
            f"{len(extra)} markers of the trial are not in the segmentation (absent from the "
            f"trial it was made from, off its marker surface, or kept apart as objects) and "
            f"are left out: "
            f"{_name_list(extra)}"
        )
    F = markers.n_frames
    present = columns >= 0
    pos = np.full((F, N, 3), np.nan)
    pos[:, present] = markers.positions[:, columns[present]]
    residuals = None
    if markers.residuals is not None:
        residuals = np.full((F, N), np.nan)
        residuals[:, present] = markers.residuals[:, columns[present]]
    out = markers.replace(positions=pos, labels=seg_labels, residuals=residuals)
    report = {
        "markers": N,
        "matched": int(present.sum()),
        "absent": absent,
        "left_out": extra,
    }
    return {"markers": out, "report": report}
