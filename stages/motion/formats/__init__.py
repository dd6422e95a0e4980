"""File formats: C3D (:mod:`.c3d`, via ezc3d, checked first by :mod:`.c3d_check`), BVH
(:mod:`.bvh`), ASF/AMC (:mod:`.asf`), pen strokes (:mod:`.strokes`); :mod:`.text` decodes
the text formats.

Every reader fails with one typed error (``C3DError``, ``BVHError``, ``ASFError`` /
``AMCError``, ``StrokesFileError``) naming the file and the field, and checks declared
sizes against the file before allocating.
"""

#: Farthest from the origin (or from its parent) a point or joint a reader returns may be,
#: in metres: beyond it the file's scale or unit is wrong (or the file corrupt).
MAX_DISTANCE_M = 1e6
