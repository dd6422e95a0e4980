"""The motion-capture domain of mocapflow: data types, formats, kinematics, stage families.

Importing this package registers every built-in stage family with the engine (it
is the target of the ``mocapflow.stages`` entry point): every module of the
package and its sub-packages is imported for its ``@stage``, ``codec`` and
``exporter`` registrations.  Modules must therefore be cheap to import: import
heavy optional libraries (pyvista, matplotlib) inside the functions that use them.
"""

import pkgutil
from importlib import import_module


def _import_all() -> None:
    for info in pkgutil.walk_packages(__path__, prefix=f"{__name__}."):
        if not info.name.rsplit(".", 1)[-1].startswith("_"):
            import_module(info.name)


_import_all()
