"""The stage of the engine's scale benchmark (``benchmarks/engine.py --scale``).

It lives here, not in :mod:`mocapflow.pipeline.testing`, so that an older checkout
(``--baseline``) runs the very same graph: the benchmark loads this module in both
interpreters through ``MOCAPFLOW_STAGE_MODULES``.
"""

from __future__ import annotations

from mocapflow.pipeline import FilePath, stage
from mocapflow.pipeline.testing import read_numbers


@stage("scale_points", outputs=("values",))
def scale_points(path: FilePath) -> dict:
    """Read a text file of numbers as points.

    Returns
    -------
    values : (N, 3) float ndarray
        The numbers in file order, three per row.

    Raises
    ------
    ValueError
        The count of numbers is not a multiple of 3 (naming the file).
    """
    v = read_numbers(path)
    if v.size % 3:
        raise ValueError(f"{path}: {v.size} numbers, not a multiple of 3")
    return {"values": v.reshape(-1, 3)}
