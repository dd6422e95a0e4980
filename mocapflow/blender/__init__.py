"""The Blender add-on of mocapflow, shipped as package data (``mocapflow blender-addon``).

The add-on's sources (``addon.py``, which becomes the add-on's ``__init__.py``, and
``c3d.py``) run inside Blender with Blender's Python and modules only (no NumPy:
Debian's Blender runs on the system Python, which may not have it).  They
never import mocapflow; they run the ``mocapflow`` command.  This module only packs
them: :func:`write_addon` writes the installable zip (or the add-on folder).
Importing it does not import ``bpy``.
"""

from __future__ import annotations

import zipfile
from importlib import resources
from pathlib import Path

__all__ = ["ADDON_NAME", "addon_files", "write_addon"]

#: The add-on's module name in Blender (its folder in the zip).
ADDON_NAME = "mocapflow_blender"

#: Source file in this package -> file name inside the add-on folder.
_FILES = {"addon.py": "__init__.py", "c3d.py": "c3d.py"}


def addon_files() -> dict[str, bytes]:
    """The add-on's files: ``"<ADDON_NAME>/<name>" -> content``, read as package data."""
    root = resources.files(__name__)
    return {f"{ADDON_NAME}/{dst}": root.joinpath(src).read_bytes()
            for src, dst in _FILES.items()}


def write_addon(out: str | Path) -> Path:
    """Write the add-on: a zip when ``out`` ends in ``.zip`` (Blender: Preferences >
    Add-ons > Install...), else the folder ``out/mocapflow_blender`` (copy it to
    Blender's ``scripts/addons``).

    Parameters
    ----------
    out : str or Path

    Returns
    -------
    Path
        The zip, or the add-on folder.

    Raises
    ------
    FileNotFoundError
        ``out``'s parent folder does not exist.
    """
    out = Path(out)
    if not out.parent.is_dir():
        raise FileNotFoundError(f"blender-addon: folder {out.parent} does not exist")
    files = addon_files()
    if out.suffix == ".zip":
        with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
            for name, data in files.items():
                z.writestr(name, data)
        return out
    for name, data in files.items():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_bytes(data)
    return out / ADDON_NAME
