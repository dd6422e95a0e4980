"""Marker-cleaning scores against a simulated capture's ground truth (METRICS.md §3).

* :func:`gap_mask` — the protocol's deletions: only originally visible
  samples, ``duration``-second gaps in a share of the markers at once, placed
  independently or clustered around one marker;
* :func:`score_merges` — right and wrong merges of the clean stage against the
  true fragment -> marker map (P&H Table 1's "wrong labels");
* :func:`region_errors` — mean and max error per body region, normalised by
  each marker's mean neighbour distance (P&H Table 2);
* :func:`strip_labels` / :func:`score_unlabelled` — the same capture with every
  label stripped (all trajectories unlabelled fragments), and the merges and the
  real samples kept when the clean stage labels it itself.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mocapflow.stages.motion.simulate.markers import REGIONS

__all__ = ["gap_mask", "region_errors", "score_merges", "score_unlabelled", "strip_labels"]


def gap_mask(
    visible: np.ndarray,
    reference: np.ndarray,
    *,
    rate: float,
    duration: float,
    fraction: float,
    clustered: bool,
    rng: np.random.Generator,
    first_frame: int = 0,
) -> np.ndarray:
    """Samples to delete for a gap-filling benchmark (only originally visible ones).

    ``ceil(fraction × M)`` markers (at least one) each lose ``duration`` seconds
    at once: placed independently (random markers, each its own random start)
    or clustered (the markers nearest a random marker in ``reference``, one
    common start).

    Parameters
    ----------
    visible : (F, M) bool ndarray
        Originally visible samples.
    reference : (M, 3) float ndarray
        Marker layout for the clustered placement (NaN rows are never chosen).
    rate : float
    duration : float
        Gap length in seconds (capped at the capture length).
    fraction : float
        Share of the markers gapped at once.
    clustered : bool
    rng : numpy.random.Generator
    first_frame : int
        Gaps lie in frames ``first_frame`` and later (e.g. after a
        calibration pose that is not part of the motion under test).

    Returns
    -------
    (F, M) bool ndarray
    """
    F, M = visible.shape
    if not 0 <= first_frame < F:
        raise ValueError(f"gap_mask: first_frame {first_frame} outside the {F} frames")
    mask = np.zeros((F, M), dtype=bool)
    if first_frame:
        mask[first_frame:] = gap_mask(visible[first_frame:], reference, rate=rate,
                                      duration=duration, fraction=fraction,
                                      clustered=clustered, rng=rng)
        return mask
    L = int(min(F, max(1, round(duration * rate))))
    ok = np.flatnonzero(np.isfinite(reference).all(1) & visible.any(0))
    k = int(min(len(ok), max(1, np.ceil(fraction * M))))
    if k == 0:
        return mask
    if clustered:
        c = ok[rng.integers(len(ok))]
        d = np.linalg.norm(reference[ok] - reference[c], axis=1)
        chosen = ok[np.argsort(d)[:k]]
        s0 = int(rng.integers(0, F - L + 1))
        mask[s0:s0 + L, chosen] = True
    else:
        chosen = rng.choice(ok, size=k, replace=False)
        for m in chosen:
            s0 = int(rng.integers(0, F - L + 1))
            mask[s0:s0 + L, m] = True
    return mask & visible


def score_merges(
    merges: list[dict[str, Any]],
    fragment_labels: list[str],
    fragment_marker: np.ndarray,
    labels: list[str],
) -> dict[str, Any]:
    """Count right and wrong merges against the true fragment → marker map.

    Parameters
    ----------
    merges : list of dict
        ``report["merges"]`` of the clean stage (``fragment``, ``label``).
    fragment_labels : list of str
        The capture's fragment names (before cleaning).
    fragment_marker : (U,) int ndarray
        True marker per fragment (-1 ghost).
    labels : list of str

    Returns
    -------
    dict
        ``merged``, ``wrong``, ``ghosts_merged``, ``wrong_list``, ``mergeable``
        (fragments of real markers), ``missed`` (real fragments not merged).
    """
    fidx = {f: u for u, f in enumerate(fragment_labels)}
    lidx = {lb: i for i, lb in enumerate(labels)}
    wrong = []
    ghosts = 0
    merged = set()
    for mg in merges:
        u = fidx[mg["fragment"]]
        merged.add(u)
        t = int(fragment_marker[u])
        if t < 0:
            ghosts += 1
        if t != lidx[mg["label"]]:
            wrong.append({"fragment": mg["fragment"], "label": mg["label"],
                          "true": labels[t] if t >= 0 else "ghost"})
    real = np.flatnonzero(fragment_marker >= 0)
    return {"merged": len(merges), "wrong": len(wrong), "ghosts_merged": ghosts,
            "wrong_list": wrong, "mergeable": int(len(real)),
            "missed": int(len([u for u in real if u not in merged]))}


def region_errors(
    estimate: np.ndarray,
    truth_positions: np.ndarray,
    mask: np.ndarray,
    region: np.ndarray,
    mean_distance: np.ndarray,
    *,
    region_names: tuple[str, ...] | list[str] = REGIONS,
) -> dict[str, dict[str, float]]:
    """Mean and max error per body region, normalised by mean neighbour distance.

    Parameters
    ----------
    estimate, truth_positions : (F, M, 3) float ndarray
    mask : (F, M) bool ndarray
        Samples to score (e.g. filled holes).
    region : (M,) int ndarray
    mean_distance : (M,) float ndarray
        Each marker's mean neighbour distance (metres).
    region_names : sequence of str

    Returns
    -------
    dict
        ``region -> {"n", "mean", "max", "mean_mm", "max_mm", "unfilled"}``, plus
        ``"all"``.  ``unfilled`` counts masked samples left NaN (not in the errors).
    """
    err = np.linalg.norm(estimate - truth_positions, axis=-1)
    norm = err / mean_distance[None, :]
    out: dict[str, dict[str, float]] = {}
    groups = [(nm, region == k) for k, nm in enumerate(region_names)]
    groups.append(("all", np.ones(len(region), dtype=bool)))
    for nm, sel in groups:
        msk = mask & sel[None, :]
        if not msk.any():
            continue
        e, en = err[msk], norm[msk]
        ok = np.isfinite(e)
        out[nm] = {
            "n": int(ok.sum()),
            "unfilled": int((~ok).sum()),
            "mean": float(en[ok].mean()) if ok.any() else float("nan"),
            "max": float(en[ok].max()) if ok.any() else float("nan"),
            "mean_mm": float(e[ok].mean() * 1000) if ok.any() else float("nan"),
            "max_mm": float(e[ok].max() * 1000) if ok.any() else float("nan"),
        }
    return out


def strip_labels(markers: Any, fragment_marker: np.ndarray, *, seed: int = 7,
                 move: Any = None) -> tuple[Any, np.ndarray]:
    """The capture with every label stripped: labelled runs and fragments all become
    fragments ``*1 …`` in a shuffled order.

    Parameters
    ----------
    markers : Markers
        ``positions (F, M, 3)`` labelled, ``fragments (F, U, 3)``.
    fragment_marker : (U,) int ndarray
        True marker of each fragment (-1 ghost).
    seed : int
        Seed of the shuffle.
    move : callable, optional
        Applied to the ``(F, M + U, 3)`` trajectories (e.g. a rigid motion).

    Returns
    -------
    take : Markers
        No labelled markers, ``M + U`` fragments.
    true : (M + U,) int ndarray
        True marker of each new fragment (-1 ghost).
    """
    frags = np.concatenate([markers.positions, markers.fragments], axis=1)
    if move is not None:
        frags = move(frags)
    true = np.concatenate([np.arange(markers.positions.shape[1]),
                           np.asarray(fragment_marker, dtype=np.int64)])
    perm = np.random.default_rng(seed).permutation(frags.shape[1])
    take = markers.replace(positions=np.zeros((markers.n_frames, 0, 3)), labels=[],
                           residuals=None, status=None, fragments=frags[:, perm],
                           fragment_labels=[f"*{u + 1}" for u in range(frags.shape[1])])
    return take, true[perm]


def score_unlabelled(take: Any, true: np.ndarray, cleaned: Any,
                     merges: list[dict[str, Any]]) -> dict[str, Any]:
    """Merges of a clean of a stripped take (:func:`strip_labels`): a label's true
    marker is that of the trajectory it was made from
    (``cleaned.attrs["labelled_from"]``).

    Returns
    -------
    dict
        ``labels``, ``wrong_labels`` (two labels made from one true marker, or from
        a ghost), ``merged``, ``wrong``, ``ghosts_merged`` and ``kept_share``: share
        of the real trajectories' samples that are a label's or merged.
    """
    idx = {n: u for u, n in enumerate(take.fragment_labels)}
    came = cleaned.attrs["labelled_from"]
    label_true = {lb: int(true[idx[f]]) for lb, f in came.items()}
    made = list(label_true.values())
    wrong_labels = sum(t < 0 for t in made) + len(made) - len(set(made))
    wrong = sum(int(true[idx[g["fragment"]]]) != label_true[g["label"]] for g in merges)
    ghosts = sum(int(true[idx[g["fragment"]]]) < 0 for g in merges)
    kept = np.zeros(len(true), dtype=bool)
    kept[[idx[f] for f in came.values()]] = True
    kept[[idx[g["fragment"]] for g in merges]] = True
    n = np.isfinite(take.fragments).all(-1).sum(0)
    real = true >= 0
    return {"labels": len(came), "wrong_labels": int(wrong_labels), "merged": len(merges),
            "wrong": int(wrong), "ghosts_merged": int(ghosts),
            "kept_share": float(n[real & kept].sum() / max(n[real].sum(), 1))}
