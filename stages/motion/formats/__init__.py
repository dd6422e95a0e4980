"""File formats: C3D (:mod:`.c3d`, via ezc3d), BVH (:mod:`.bvh`), ASF/AMC (:mod:`.asf`),
pen strokes (:mod:`.strokes`); :mod:`.text` decodes the text formats."""
