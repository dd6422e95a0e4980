"""The template fitted to the real shared captures below Park & Hodgins' density.

Every shared C3D runs through ``configs/skin.yaml`` to ``segment`` (one store in a
temporary folder); its segmentation's reference pose is then fitted by ``fit_mesh`` with
the graph's params (``marker_offset`` 7 mm, the procedural template of 13,000 vertices
or ``--vertices``), the limbs left in the template's T-pose (``pose_limbs=False``) and
turned to the named elbow, wrist, knee and ankle markers (the default,
:mod:`mocapflow.stages.skin.limb_pose`).  Per capture and fit: the scale, the median and
90th-percentile distance (mm) of all markers to the fitted body, the median and largest
distance of the named joint markers, the joints named and the bones turned.

Run: ``python benchmarks/sparse_fit.py [--vertices N] [--only SUBSTRING]`` (about a
minute).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mocapflow.pipeline import Context
from mocapflow.pipeline.cli import main as cli
from mocapflow.pipeline.codecs import decode
from mocapflow.pipeline.store import Store
from mocapflow.stages.skin.binding import closest_points_on_triangles
from mocapflow.stages.skin.marker_regions import joint_landmark
from mocapflow.stages.skin.mesh_fit import fit_mesh, template_mesh

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("MOCAPFLOW_DATA", ROOT.parent / "shared" / "data"))
MARKER_OFFSET = 0.007  # configs/skin.yaml's fit node


def segmentations(paths: list[Path], store_dir: str) -> dict[str, object]:
    """``{file name: segmentation}`` from one run of the skin graph to ``segment``."""
    args = ["run", str(ROOT / "configs" / "skin.yaml"), "--store", store_dir, "--executor",
            "sync", "--json", "-q", "--target", "segment"]  # fmt: skip
    for p in paths:
        args += ["--parts", str(p)]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        code = cli(args)
    if code:
        raise SystemExit(f"skin graph failed: {buf.getvalue()[-2000:]}")
    store = Store(store_dir)
    return {Path(t["part"]).name: decode(store.load("segment", t["key"], "segmentation"))
            for t in json.loads(buf.getvalue())["tasks"] if t["node"] == "segment"}


def row(name: str, seg, template, pose: bool) -> str:
    out = fit_mesh(template, seg, marker_offset=MARKER_OFFSET, pose_limbs=pose, ctx=Context())
    mesh, rep = out["mesh"], out["report"]
    ok = np.isfinite(seg.reference).all(1)
    d = np.full(len(seg.labels), np.nan)
    d[ok] = closest_points_on_triangles(seg.reference[ok], mesh.vertices, mesh.faces)[2] * 1000
    joints = np.array([joint_landmark(label) is not None for label in seg.labels]) & ok
    limbs = rep.get("limbs") or {}
    cells = [name, "turned" if pose else "T-pose", f"{rep['scale']:.2f}",
             f"{np.nanmedian(d):.0f} / {np.nanpercentile(d, 90):.0f}",
             f"{np.median(d[joints]):.0f} / {d[joints].max():.0f}" if joints.any() else "-",
             ", ".join(limbs.get("joints", {})) or "-",
             ", ".join(f"{b} {v:.0f}°" for b, v in limbs.get("turned_deg", {}).items()) or "-"]
    return "| " + " | ".join(cells) + " |"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vertices", type=int, default=13000, help="procedural template size")
    ap.add_argument("--only", default=None, help="substring of the file names to run")
    args = ap.parse_args(argv)
    paths = sorted(p for p in (DATA / "c3d").glob("*.c3d")
                   if args.only is None or args.only in p.name)  # fmt: skip
    if not paths:
        print(f"no C3D in {DATA / 'c3d'} (set MOCAPFLOW_DATA)", file=sys.stderr)
        return 1
    t0 = time.perf_counter()
    template = template_mesh(n_vertices=args.vertices, ctx=Context())["mesh"]
    with tempfile.TemporaryDirectory(prefix="sparse-fit-") as tmp:
        segs = segmentations(paths, tmp)
    print(f"# Upright fit on the shared captures ({args.vertices}-vertex procedural template, "
          f"marker offset {MARKER_OFFSET * 1000:.0f} mm)\n")
    print("| capture | limbs | scale | all markers: median / p90 mm | joint markers: median / "
          "max mm | joints named | bones turned |")
    print("|---|---|---|---|---|---|---|")
    for name, seg in sorted(segs.items()):
        if (seg.attrs.get("density") or {}).get("suited") is not False:
            print(f"| {name} | dense: the non-rigid fit, not this one | | | | | |")
            continue
        for pose in (False, True):
            print(row(name, seg, template, pose), flush=True)
    print(f"\n(wall time {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
