"""Text of the line-based motion formats (BVH, ASF/AMC): decoding shared by their readers."""

from __future__ import annotations

__all__ = ["read_text"]


def read_text(path: str) -> str:
    """The text of a file: UTF-8 (a byte-order mark dropped), else Latin-1.

    Parameters
    ----------
    path : str

    Returns
    -------
    str
        Every byte decodes under Latin-1, so this never fails on content.
    """
    with open(path, "rb") as f:
        raw = f.read()
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("latin-1")
