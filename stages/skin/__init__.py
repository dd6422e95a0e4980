"""Park & Hodgins 2006."""

STAGE_MODULES = ("clean", "rom", "segment", "mesh_fit", "deform", "render")
