"""File formats: C3D (via ezc3d), BVH, ASF/AMC, pen strokes."""
