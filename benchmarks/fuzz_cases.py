"""The cases of ``benchmarks/fuzz.py``: seeded mutations of C3D, BVH, ASF/AMC and stroke files.

Every case is generated here, from the shared sample files and from files our own
writers produce (nothing is stored): C3D byte flips, truncations, header words and
floats, parameter values, dimensions, types, offsets, names and labels; BVH token
edits, huge/zero/negative counts, nesting, non-finite numbers, duplicate names and
encodings; ASF/AMC and stroke-file number edits; and the hostile YAML configs of
``benchmarks/fuzz_configs.py``.  ``*_built`` cases are the hand-made files of the
issue (a 9-line BVH declaring 2,000,000,000 frames, 5,000 nested joints, labels that
are not UTF-8, ...); the rest are seeded random mutations.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import math
import re
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

from mocapflow.stages.motion.datatypes import Markers, Strokes
from mocapflow.stages.motion.formats.bvh import read_bvh, write_bvh
from mocapflow.stages.motion.formats.c3d import write_c3d
from mocapflow.stages.motion.formats.strokes import write_strokes_csv

HERE = Path(__file__).resolve().parent
DATA = (HERE.parent / ".." / "shared" / "data").resolve()


@dataclasses.dataclass
class Case:
    """One fuzz case: files written into a fresh directory and how to run them.

    ``files`` maps file names to bytes; ``part`` is the file the ingest node reads;
    ``node`` is the one-node config (stage and params), ``config`` the YAML text of
    a config case (``mocapflow plan``).
    """

    name: str
    kind: str
    files: dict[str, bytes] = dataclasses.field(default_factory=dict)
    part: str = ""
    node: dict = dataclasses.field(default_factory=dict)
    config: str | None = None




# --------------------------------------------------------------------------- sources


def _synthetic_markers(n_markers: int, n_frames: int, *, n_fragments: int = 0,
                       seed: int = 0) -> Markers:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1.0, 1.0, (n_frames, n_markers, 3)) + [0, 0, 1.0]
    pos[rng.random((n_frames, n_markers)) < 0.05] = np.nan
    res = np.where(np.isnan(pos[..., 0]), np.nan, rng.uniform(0, 2e-3, (n_frames, n_markers)))
    frag = np.full((n_frames, n_fragments, 3), np.nan)
    for j in range(n_fragments):
        frag[j : j + 3, j] = rng.uniform(-1, 1, (3, 3))
    return Markers(positions=pos, labels=[f"M{i:03d}" for i in range(n_markers)], rate=120.0,
                   first_frame=3, residuals=res, fragments=frag,
                   fragment_labels=[f"*{j + 1}" for j in range(n_fragments)])


def _bvh_head(text: str, frames: int) -> str:
    """A BVH text cut to its first ``frames`` frames (``Frames:`` rewritten)."""
    lines = text.splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.strip().lower().startswith("frame time"))
    f = next(i for i, ln in enumerate(lines) if ln.strip().lower().startswith("frames:"))
    lines[f] = f"Frames: {frames}"
    return "\n".join(lines[: k + 1 + frames]) + "\n"


def sources(work: Path) -> dict[str, dict[str, bytes]]:
    """Base files per kind: shared files (BVH/AMC cut to a few frames) and writer outputs."""
    work.mkdir(parents=True, exist_ok=True)
    out: dict[str, dict[str, bytes]] = {"c3d": {}, "bvh": {}, "amc": {}, "strokes": {}}
    for p in sorted((DATA / "c3d").glob("*.c3d")):
        out["c3d"][p.name] = p.read_bytes()
    for name, m in {"w_small.c3d": _synthetic_markers(5, 30, seed=1),
                    "w_labels2.c3d": _synthetic_markers(280, 6, n_fragments=4, seed=2)}.items():
        out["c3d"][name] = write_c3d(m, work / name).read_bytes()
    out["c3d"]["w_metres.c3d"] = write_c3d(_synthetic_markers(8, 20, seed=3),
                                           work / "w_metres.c3d", unit="m").read_bytes()
    for p in sorted((DATA / "bvh").glob("*.bvh")):
        out["bvh"][p.name] = _bvh_head(p.read_text(), 12).encode()
    full = DATA / "bvh" / "cmu_131_01.bvh"
    if full.is_file():
        out["bvh"]["full_cmu_131_01.bvh"] = full.read_bytes()
        (work / "head.bvh").write_bytes(out["bvh"]["cmu_131_01.bvh"])
        m = read_bvh(work / "head.bvh")
        out["bvh"]["w_cmu.bvh"] = write_bvh(m, work / "w_cmu.bvh").read_bytes()
        out["bvh"]["w_mm.bvh"] = write_bvh(m, work / "w_mm.bvh", unit="mm",
                                           precision=3).read_bytes()
    for subj in ("cmu_01", "cmu_11"):
        asf, amc = DATA / "bvh" / f"{subj}.asf", DATA / "bvh" / f"{subj}_01.amc"
        if asf.is_file() and amc.is_file():
            text = amc.read_text()
            cut = text.find("\n13\n")  # the first 12 frames
            out["amc"][subj] = asf.read_bytes() + b"\0" + text[: cut + 1].encode()
    uci = DATA / "strokes" / "uci_chartraj_mv_subset.csv"
    if uci.is_file():
        lines = uci.read_text().splitlines()
        out["strokes"]["uci.csv"] = ("\n".join(lines[:300]) + "\n").encode()
    omni = sorted((DATA / "strokes" / "omniglot_latin").rglob("*.txt"))
    if omni:
        out["strokes"]["omniglot.txt"] = omni[0].read_bytes()
    pts = np.cumsum(np.random.default_rng(4).normal(size=(40, 2)), axis=0)
    s = Strokes(points=pts, stroke_starts=[0, 25], rate=100.0, times=np.arange(40) / 100.0,
                attrs={"letter": "a", "example": 1})
    out["strokes"]["w_strokes.csv"] = write_strokes_csv([s, s], work / "w.csv").read_bytes()
    return out


# --------------------------------------------------------------------------- C3D mutators


def c3d_entries(buf: bytes) -> list[dict]:
    """Parameter-section entries of a valid C3D file: byte offsets of their fields."""
    pstart = (buf[0] - 1) * 512
    big = buf[pstart + 3] == 86

    def u16(o: int) -> int:
        return struct.unpack_from(">H" if big else "<H", buf, o)[0]

    groups: dict[int, str] = {}
    entries: list[dict] = []
    pos = pstart + 4
    while pos + 2 < len(buf):
        nchar, gid = struct.unpack_from("bb", buf, pos)
        if nchar == 0:
            break
        n = abs(nchar)
        e = {"pos": pos, "name": buf[pos + 2 : pos + 2 + n].decode("latin-1"), "gid": gid,
             "off_at": pos + 2 + n}
        if gid < 0:
            groups[-gid] = e["name"]
        else:
            q = e["off_at"] + 2
            ndim = buf[q + 1]
            e.update(type_at=q, ptype=struct.unpack_from("b", buf, q)[0], ndim_at=q + 1,
                     dims=list(buf[q + 2 : q + 2 + ndim]), data_at=q + 2 + ndim)
        entries.append(e)
        off = u16(e["off_at"])
        if off == 0:
            break
        pos = e["off_at"] + off
    for e in entries:
        e["full"] = f"{groups.get(e['gid'], '?')}:{e['name']}" if e["gid"] > 0 else e["name"]
    return entries


_INTS = (0, 1, 2, 255, 256, 0x7FFF, 0x8000, 0xFFFF)
_FLOATS = (0.0, -0.0, math.inf, -math.inf, math.nan, 1e30, -1e30, 1e-30, -1.0, 1.0, 1e4, -0.1)


def _pack_float(buf: bytearray, at: int, v: float) -> None:
    proc = buf[(buf[0] - 1) * 512 + 3] if len(buf) > (buf[0] - 1) * 512 + 3 else 84
    if proc == 86:
        struct.pack_into(">f", buf, at, v)
    elif proc == 85:  # DEC: x4, 16-bit words swapped
        b = struct.pack("<f", v * 4.0 if math.isfinite(v) else v)
        buf[at : at + 4] = b[2:4] + b[0:2]
    else:
        struct.pack_into("<f", buf, at, v)


def _pack_u16(buf: bytearray, at: int, v: int) -> None:
    big = buf[(buf[0] - 1) * 512 + 3] == 86
    struct.pack_into(">H" if big else "<H", buf, at, v & 0xFFFF)


def _c3d_ops() -> dict[str, Callable]:
    """``name -> op(rng, buf: bytearray, entries) -> description`` (``buf`` edited in place)."""

    def flips(lo_hi):
        def op(rng, buf, ents):
            lo, hi = lo_hi(buf, ents)
            idx = sorted(int(i) for i in rng.integers(lo, max(hi, lo + 1), rng.integers(1, 9)))
            for i in idx:
                buf[i] = int(rng.integers(0, 256))
            return f"bytes {idx[:4]} randomised"
        return op

    def pstart(b: bytearray) -> int:
        return (b[0] - 1) * 512

    def dstart(b: bytearray) -> int:
        return (struct.unpack_from("<H", b, 16)[0] - 1) * 512

    def truncate(rng, buf, ents):
        cut = int(rng.integers(0, len(buf)))
        del buf[cut:]
        return f"cut at byte {cut}"

    def extend(rng, buf, ents):
        extra = bytes(rng.integers(0, 256, int(rng.integers(1, 4096)), dtype=np.uint8))
        buf.extend(extra)
        return f"{len(extra)} random bytes appended"

    def header_word(rng, buf, ents):
        at = int(rng.choice([2, 4, 6, 8, 10, 16, 18]))
        v = int(rng.choice(_INTS))
        _pack_u16(buf, at, v)
        return f"header word at byte {at} = {v}"

    def header_float(rng, buf, ents):
        at = int(rng.choice([12, 20]))
        v = float(rng.choice(_FLOATS))
        _pack_float(buf, at, v)
        return f"header float at byte {at} = {v}"

    def param_value(rng, buf, ents):
        cands = [e for e in ents if e["gid"] > 0 and e["ptype"] in (1, 2, 4) and
                 e["full"].split(":")[0] in ("POINT", "ANALOG", "TRIAL")]
        e = cands[int(rng.integers(len(cands)))]
        if e["ptype"] == 4:
            v = float(rng.choice(_FLOATS))
            _pack_float(buf, e["data_at"], v)
        elif e["ptype"] == 2:
            v = int(rng.choice(_INTS))
            _pack_u16(buf, e["data_at"], v)
        else:
            v = int(rng.choice([0, 1, 127, 255]))
            buf[e["data_at"]] = v
        return f"{e['full']} = {v}"

    def param_dims(rng, buf, ents):
        cands = [x for x in ents if x["gid"] > 0 and x["dims"]]
        e = cands[int(rng.integers(len(cands)))]
        k = int(rng.integers(len(e["dims"])))
        v = int(rng.choice([0, 1, 2, 255, e["dims"][k] + 1, max(e["dims"][k] - 1, 0)]))
        buf[e["ndim_at"] + 1 + k] = v
        return f"{e['full']} dimension {k} = {v}"

    def param_type(rng, buf, ents):
        cands = [x for x in ents if x["gid"] > 0]
        e = cands[int(rng.integers(len(cands)))]
        v = int(rng.choice([-1, 1, 2, 4, 3, 0, 127]))
        struct.pack_into("b", buf, e["type_at"], v)
        return f"{e['full']} type = {v}"

    def param_offset(rng, buf, ents):
        e = ents[int(rng.integers(len(ents)))]
        v = int(rng.choice([0, 1, 2, 3, 0xFFFF, 0x8000, 512]))
        _pack_u16(buf, e["off_at"], v)
        return f"{e['full']} next-entry offset = {v}"

    def param_name(rng, buf, ents):
        e = ents[int(rng.integers(len(ents)))]
        which = int(rng.integers(3))
        if which == 0:
            v = int(rng.choice([0, 1, 127, -127, -len(e["name"])]))
            struct.pack_into("b", buf, e["pos"], v)
            return f"{e['full']} name length = {v}"
        if which == 1:
            v = int(rng.choice([0, 1, -1, 99, -99, 127]))
            struct.pack_into("b", buf, e["pos"] + 1, v)
            return f"{e['full']} group id = {v}"
        buf[e["pos"] + 2] = int(rng.choice([0, 7, 0xFF, 0x80]))
        return f"{e['full']} name byte"

    def labels(rng, buf, ents):
        cands = [e for e in ents if e["gid"] > 0 and e["ptype"] == -1 and len(e["dims"]) == 2
                 and e["full"] in ("POINT:LABELS", "POINT:LABELS2", "POINT:UNITS",
                                   "POINT:DESCRIPTIONS")] or [
            e for e in ents if e["gid"] > 0 and e["ptype"] == -1 and e["dims"]]
        e = cands[int(rng.integers(len(cands)))]
        width = e["dims"][0]
        count = e["dims"][1] if len(e["dims"]) > 1 else 1
        i = int(rng.integers(count))
        at = e["data_at"] + i * width
        kind = int(rng.integers(4))
        if kind == 0:  # not UTF-8
            buf[at : at + 2] = bytes([0xFF, 0xE4])[: min(2, width)]
            return f"{e['full']} entry {i} not UTF-8"
        if kind == 1 and count > 1:  # duplicate of entry 0
            j = (i + 1) % count
            buf[e["data_at"] + j * width : e["data_at"] + (j + 1) * width] = buf[
                e["data_at"] : e["data_at"] + width]
            return f"{e['full']} entry {j} = entry 0"
        if kind == 2:
            buf[at] = 0
            return f"{e['full']} entry {i} starts with NUL"
        buf[at : at + width] = b"XX".ljust(width)[:width]
        return f"{e['full']} entry {i} = 'XX'"

    def processor(rng, buf, ents):
        v = int(rng.choice([83, 84, 85, 86, 0, 255]))
        buf[pstart(buf) + 3] = v
        return f"processor type = {v}"

    def first_bytes(rng, buf, ents):
        at = int(rng.integers(2))
        v = int(rng.choice([0, 1, 2, 3, 0x50, 0xFF]))
        buf[at] = v
        return f"header byte {at} = {v}"

    return {
        "flip_header": flips(lambda b, e: (0, 512)),
        "flip_params": flips(lambda b, e: (pstart(b), min(dstart(b), len(b)))),
        "flip_data": flips(lambda b, e: (min(dstart(b), len(b) - 1), len(b))),
        "flip_any": flips(lambda b, e: (0, len(b))),
        "truncate": truncate, "extend": extend, "header_word": header_word,
        "header_float": header_float, "param_value": param_value, "param_dims": param_dims,
        "param_type": param_type, "param_offset": param_offset, "param_name": param_name,
        "labels": labels, "processor": processor, "first_bytes": first_bytes,
    }


def _float_frames(buf: bytearray, ents: list[dict]) -> None:
    """``POINT:FRAMES`` rewritten as a float parameter (which ezc3d cannot read)."""
    e = next(x for x in ents if x["full"] == "POINT:FRAMES")
    val = struct.unpack_from("<h", buf, e["data_at"])[0]
    buf[e["type_at"]] = 4
    buf[e["data_at"] : e["data_at"] + 2] = struct.pack("<f", float(val))
    struct.pack_into("<H", buf, e["off_at"], struct.unpack_from("<H", buf, e["off_at"])[0] + 2)
    ds = (struct.unpack_from("<H", buf, 16)[0] - 1) * 512
    del buf[ds - 2 : ds]  # the section's padding keeps the data block where it was


def c3d_built() -> dict[str, Callable]:
    """Targeted edits of our writer's small file: ``name -> edit(buf, entries)``."""

    def entry(ents, full):
        return next(x for x in ents if x["full"] == full)

    def label(i, data):
        def edit(buf, ents):
            e = entry(ents, "POINT:LABELS")
            at = e["data_at"] + i * e["dims"][0]
            buf[at : at + e["dims"][0]] = data(buf, e).ljust(e["dims"][0])[: e["dims"][0]]
        return edit

    def param(full, fmt, value):
        def edit(buf, ents):
            struct.pack_into(fmt, buf, entry(ents, full)["data_at"], value)
        return edit

    def coordinate(value):
        def edit(buf, ents):
            struct.pack_into("<f", buf, (struct.unpack_from("<H", buf, 16)[0] - 1) * 512, value)
        return edit

    def zero_points(buf, ents):
        struct.pack_into("<H", buf, 2, 0)
        struct.pack_into("<h", buf, entry(ents, "POINT:USED")["data_at"], 0)
        struct.pack_into("<h", buf, entry(ents, "ANALOG:USED")["data_at"], 0)

    def char_scalar(buf, ents):
        e = entry(ents, "POINT:USED")
        buf[e["type_at"]] = 0xFF  # -1: character data, and no dimensions

    def description(buf, ents):
        buf[entry(ents, "POINT")["off_at"] + 2] = 200

    return {
        "label_not_utf8": label(1, lambda b, e: b"\xff\xe4BB"),
        "label_duplicate": label(1, lambda b, e: bytes(b[e["data_at"] : e["data_at"] + 4])),
        "frames_65535": param("POINT:FRAMES", "<H", 0xFFFF),
        "frames_float": lambda buf, ents: _float_frames(buf, ents),
        "analog_rate_1e30": param("ANALOG:RATE", "<f", 1e30),
        "analog_used_32767": param("ANALOG:USED", "<h", 32767),
        "point_rate_nan": param("POINT:RATE", "<f", math.nan),
        "point_scale_zero": param("POINT:SCALE", "<f", 0.0),
        "char_param_no_dims": char_scalar,
        "description_length_200": description,
        "zero_points": zero_points,
        "coordinate_1e30": coordinate(1e30),
        "coordinate_inf": coordinate(math.inf),
        "processor_mips": lambda buf, ents: buf.__setitem__((buf[0] - 1) * 512 + 3, 86),
    }


def c3d_cases(src: dict[str, bytes], *, n: int = 240, seed: int = 13) -> list[Case]:
    """The targeted edits of :func:`c3d_built`, then ``n`` seeded mutations: operation
    ``k % ops`` on source ``k // ops % sources``."""
    out: list[Case] = []
    for name, edit in c3d_built().items():
        buf = bytearray(src["w_small.c3d"])
        edit(buf, c3d_entries(bytes(buf)))
        out.append(_ingest_case(f"c3d-built-{name}", "c3d", "take.c3d", bytes(buf),
                                "ingest_c3d", {}, name))
    ops = _c3d_ops()
    names, files = list(ops), sorted(src)
    for k in range(n):
        op, base = names[k % len(names)], files[(k // len(names)) % len(files)]
        rng = np.random.default_rng([seed, k])
        buf = bytearray(src[base])
        try:
            what = ops[op](rng, buf, c3d_entries(bytes(buf)))
        except (IndexError, ValueError, ZeroDivisionError):  # op does not apply to this file
            what = "unchanged"
        out.append(_ingest_case(f"c3d-{k:03d}-{op}", "c3d", "take.c3d", bytes(buf),
                                "ingest_c3d", {}, f"{base}: {what}"))
    return out


def _ingest_case(name: str, kind: str, part: str, data: bytes, stage: str, params: dict,
                 what: str) -> Case:
    return Case(name=f"{name} [{what}]", kind=kind, files={part: data}, part=part,
                node={"stage": stage, "params": params})


# --------------------------------------------------------------------------- BVH mutators


def _deep_bvh(depth: int, *, wide: bool = False, frames: int = 2) -> str:
    """A chain (or, ``wide``, a fan) of ``depth`` joints with 3 rotation channels each."""
    out = ["HIERARCHY", "ROOT J0", "{", "OFFSET 0 0 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    for i in range(1, depth):
        out += [f"JOINT J{i}", "{", "OFFSET 0 0.1 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
        if wide:
            out.append("}")
    out += ["}"] * (1 if wide else depth)
    row = " ".join(["1.5"] * 3 * depth)
    return "\n".join(out + ["MOTION", f"Frames: {frames}", "Frame Time: 0.01"]
                     + [row] * frames) + "\n"


_NINE = ("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 0\n}\nMOTION\n"
         "Frames: 2000000000\nFrame Time: 0.0083333\n")
_BAD_NUMBERS = ("inf", "-inf", "nan", "NaN", "1e308", "-1e308", "1e-320", "1e99999", "0x10",
                "--1", "1,5", "", "∞")
_BAD_TOKENS = ("{", "}", "JOINT", "End", "Site", "ROOT", "OFFSET", "CHANNELS", "MOTION",
               "HIERARCHY", "Frames:", "\x00", "é")


def _bvh_ops() -> dict[str, Callable]:
    """``name -> op(rng, text) -> (text or bytes, description)``."""

    def sub_line(text, start, value):
        lines = text.splitlines()
        i = next(i for i, ln in enumerate(lines) if ln.strip().lower().startswith(start))
        lines[i] = value
        return "\n".join(lines) + "\n"

    def frames(rng, t):
        v = str(rng.choice(["0", "-1", "2000000000", "10" * 15, "13", "11", "24", "1.5",
                            "abc", "", "0x10", "1e3"]))
        return sub_line(t, "frames:", f"Frames: {v}"), f"Frames: {v}"

    def frame_time(rng, t):
        v = str(rng.choice(["0", "-0.0083", "1e6", "1000", "1e-6", "1e-9", "1e-320", "5e-324",
                            "inf", "nan", "1e308", "abc"]))
        return sub_line(t, "frame time", f"Frame Time: {v}"), f"Frame Time: {v}"

    def channels(rng, t):
        v = str(rng.choice(["0", "7", "12", "1000000000", "-3", "inf", "nan", "x", "1.5"]))
        lines = t.splitlines()
        idx = [i for i, ln in enumerate(lines) if ln.strip().upper().startswith("CHANNELS")]
        i = idx[int(rng.integers(len(idx)))]
        toks = lines[i].split()
        lines[i] = " ".join([toks[0], v, *toks[2:]])
        return "\n".join(lines) + "\n", f"line {i + 1} CHANNELS count {v}"

    def channel_name(rng, t):
        lines = t.splitlines()
        idx = [i for i, ln in enumerate(lines) if ln.strip().upper().startswith("CHANNELS")]
        i = idx[int(rng.integers(len(idx)))]
        toks = lines[i].split()
        k = int(rng.integers(2, len(toks))) if len(toks) > 2 else 1
        toks[k] = str(rng.choice(["Xrotation", "Wrotation", "xrotation", "Xposition", "X"]))
        lines[i] = " ".join(toks)
        return "\n".join(lines) + "\n", f"line {i + 1} channel {toks[k]}"

    def token(choices, where):
        def op(rng, t):
            lines = t.splitlines()
            m = next(i for i, ln in enumerate(lines) if ln.strip().upper() == "MOTION")
            rows = range(1, m) if where == "hier" else range(m + 3, len(lines))
            i = list(rows)[int(rng.integers(len(rows)))]
            toks = lines[i].split() or [""]
            k = int(rng.integers(len(toks)))
            toks[k] = str(rng.choice(choices))
            lines[i] = " ".join(toks)
            return "\n".join(lines) + "\n", f"line {i + 1} token {k} = {toks[k]!r}"
        return op

    def offset_nonfinite(rng, t):
        lines = t.splitlines()
        idx = [i for i, ln in enumerate(lines) if ln.strip().upper().startswith("OFFSET")]
        i = idx[int(rng.integers(len(idx)))]
        v = str(rng.choice(["inf", "nan", "-inf", "1e308"]))
        lines[i] = f"OFFSET {v} {v} 0"
        return "\n".join(lines) + "\n", f"line {i + 1} OFFSET {v}"

    def duplicate_name(rng, t):
        lines = t.splitlines()
        idx = [i for i, ln in enumerate(lines) if ln.strip().upper().startswith(("JOINT", "ROOT"))]
        a, b = (idx[int(i)] for i in rng.choice(len(idx), 2, replace=False))
        lines[b] = lines[b].split()[0] + " " + " ".join(lines[a].split()[1:])
        return "\n".join(lines) + "\n", f"line {b + 1} takes the name of line {a + 1}"

    def lines_edit(rng, t):
        lines = t.splitlines()
        i = int(rng.integers(len(lines)))
        how = str(rng.choice(["delete", "duplicate", "swap"]))
        if how == "delete":
            del lines[i]
        elif how == "duplicate":
            lines.insert(i, lines[i])
        else:
            j = min(i + 1, len(lines) - 1)
            lines[i], lines[j] = lines[j], lines[i]
        return "\n".join(lines) + "\n", f"{how} line {i + 1}"

    def truncate(rng, t):
        cut = int(rng.integers(0, len(t)))
        return t[:cut], f"cut at character {cut}"

    def encoding(rng, t):
        how = str(rng.choice(["utf-16", "utf-16-le", "latin-1 name", "bad utf-8", "bom", "nul",
                              "cr", "long line"]))
        if how in ("utf-16", "utf-16-le"):
            return t.encode(how), how
        if how == "latin-1 name":
            return t.replace("ROOT ", "ROOT Hüfte_", 1).encode("latin-1", "replace"), how
        if how == "bad utf-8":
            return t.replace("ROOT ", "ROOT \xff\xfe", 1).encode("latin-1", "replace"), how
        if how == "bom":
            return b"\xef\xbb\xbf" + t.encode(), how
        if how == "nul":
            return t.replace("{", "{\x00", 3).encode(), how
        if how == "cr":
            return t.replace("\n", "\r").encode(), how
        return t.replace("OFFSET", "OFFSET " + "0 " * 200000, 1).encode(), how

    num = token(_BAD_NUMBERS, "hier")
    return {"frames": frames, "frame_time": frame_time, "channels": channels,
            "channel_name": channel_name, "hier_number": num,
            "hier_token": token(_BAD_TOKENS, "hier"), "frame_number": token(_BAD_NUMBERS, "mo"),
            "offset_nonfinite": offset_nonfinite, "duplicate_name": duplicate_name,
            "lines": lines_edit, "truncate": truncate, "encoding": encoding}


def bvh_cases(src: dict[str, bytes], *, n: int = 120, seed: int = 17) -> list[Case]:
    """``n - 12`` seeded mutations (every third resampled to 30 Hz) and 12 built files:
    the issue's 9-line ``Frames: 2000000000`` file, deep and wide hierarchies,
    ``Frame Time: 1e6`` before resampling, ``Frames: 0``."""
    ops = _bvh_ops()
    names = list(ops)
    files = sorted(k for k in src if not k.startswith("full_")) + [
        k for k in src if k.startswith("full_")]
    two = "HIERARCHY\nROOT A\n{\nOFFSET 0 0 0\nCHANNELS 3 Zrotation Xrotation Yrotation\n}\n"
    built = {
        "nine_lines": (_NINE, {}), "nine_lines_channels": (_NINE.replace(
            "CHANNELS 0", "CHANNELS 3 Zrotation Xrotation Yrotation"), {}),
        "frames_zero": (_NINE.replace("2000000000", "0"), {}),
        "frame_time_1e6_resampled": (two + "MOTION\nFrames: 2\nFrame Time: 1e6\n0 0 0\n0 0 0\n",
                                     {"rate": 120.0}),
        "frame_time_tiny_resampled": (two + "MOTION\nFrames: 2\nFrame Time: 1e-300\n0 0 0\n"
                                      "0 0 0\n", {"rate": 1e9}),
        "deep_5000": (_deep_bvh(5000), {}), "deep_20000": (_deep_bvh(20000, frames=1), {}),
        "deep_256": (_deep_bvh(256), {}), "deep_257": (_deep_bvh(257), {}),
        "wide_5000": (_deep_bvh(5000, wide=True), {}),
        "rate_huge": (two + "MOTION\nFrames: 2\nFrame Time: 0.01\n0 0 0\n0 0 0\n",
                      {"rate": 1e12}),
        "unit_huge": (two.replace("0 0 0", "1e300 0 0", 1) + "MOTION\nFrames: 1\n"
                      "Frame Time: 0.01\n0 0 0\n", {"unit": "ft"}),
    }
    out = [_ingest_case(f"bvh-built-{k}", "bvh", "take.bvh", t.encode(), "ingest_bvh", p, k)
           for k, (t, p) in built.items()]
    for k in range(n - len(out)):
        op, base = names[k % len(names)], files[(k // len(names)) % len(files)]
        rng = np.random.default_rng([seed, k])
        text = src[base].decode("utf-8")
        try:
            data, what = ops[op](rng, text)
        except (StopIteration, ValueError, IndexError):
            data, what = text, "unchanged"
        params = {"rate": 30.0} if k % 3 == 2 else {}
        out.append(_ingest_case(f"bvh-{k:03d}-{op}", "bvh", "take.bvh",
                                data if isinstance(data, bytes) else data.encode(),
                                "ingest_bvh", params, f"{base}: {what}"))
    return out


# --------------------------------------------------------------------------- ASF/AMC, strokes


def _replace_number(rng, text: str, pattern: str, values) -> tuple[str, str]:
    """Replace the first number of one random line matching ``pattern``."""
    lines = text.splitlines()
    idx = [i for i, ln in enumerate(lines) if re.search(pattern, ln)]
    if not idx:
        return text, "unchanged"
    i = idx[int(rng.integers(len(idx)))]
    v = str(rng.choice(values))
    lines[i] = re.sub(r"-?\d+(\.\d*)?(e-?\d+)?", v, lines[i], count=1)
    return "\n".join(lines) + "\n", f"line {i + 1}: {lines[i].strip()[:40]!r}"


def amc_cases(src: dict[str, bytes], *, n: int = 40, seed: int = 19) -> list[Case]:
    """``n`` mutations of an ASF/AMC pair (either file), read with ``ingest_amc``."""
    bad = ("inf", "nan", "-inf", "0", "-1", "1e308", "abc")
    asf_ops = {
        "units_length": "", "bone_length": r"^\s+length\s",
        "direction": r"direction", "axis": r"^\s+axis\s", "root_position": r"position",
        "id": r"^\s+id\s",
    }
    out: list[Case] = []
    subjects = sorted(src)
    for k in range(n):
        subj = subjects[k % len(subjects)]
        asf, amc = (x.decode() for x in src[subj].split(b"\0"))
        rng = np.random.default_rng([seed, k])
        op = k % 10
        if op == 0:  # the :units length (the first "length" line)
            v = str(rng.choice(bad))
            asf = re.sub(r"(?m)^(\s*length\s+)\S+", rf"\g<1>{v}", asf, count=1)
            what = f"units length {v}"
        elif op < 6:
            key = list(asf_ops)[op]
            asf, what = _replace_number(rng, asf, asf_ops[key], bad)
            what = f"{key} {what}"
        elif op == 6:
            amc, what = _replace_number(rng, amc, r"^[a-z]", bad)
        elif op == 7:
            names = re.findall(r"(?m)^\s*name (\S+)\s*$", asf)
            a, b = rng.choice(len(names), 2, replace=False)
            asf = re.sub(rf"(?m)^(\s*name ){re.escape(names[b])}(\s*)$", rf"\g<1>{names[a]}\2",
                         asf, count=1)
            what = f"bone {names[b]} renamed {names[a]}"
        elif op == 8:
            cut = int(rng.integers(len(amc)))
            amc, what = amc[:cut], f"AMC cut at {cut}"
        else:
            lines = amc.splitlines()
            i = int(rng.integers(3, len(lines)))
            lines[i] = str(rng.choice(["99999999999999999999", "-5", "root", "lfemur 1 2 3 4",
                                       ":RADIANS", "\xff"]))
            amc, what = "\n".join(lines) + "\n", f"AMC line {i + 1} = {lines[i]!r}"
        out.append(Case(name=f"amc-{k:03d} [{subj}: {what}]", kind="amc",
                        files={f"{subj}.asf": asf.encode("utf-8", "surrogateescape"),
                               f"{subj}_01.amc": amc.encode("utf-8", "surrogateescape")},
                        part=f"{subj}_01.amc", node={"stage": "ingest_amc", "params": {}}))
    return out


def strokes_cases(src: dict[str, bytes], *, n: int = 30, seed: int = 23) -> list[Case]:
    """``n`` mutations of the three stroke formats, read with ``ingest_strokes_set``."""
    vals = ("inf", "nan", "", "-inf", "1e308", "x", "99999999999999999999999")
    out: list[Case] = []
    files = sorted(src)
    for k in range(n):
        base = files[k % len(files)]
        text = src[base].decode()
        rng = np.random.default_rng([seed, k])
        op = (k // len(files)) % 5
        lines = text.splitlines()
        if op == 0:  # a number
            rows = [i for i, ln in enumerate(lines) if re.search(r"\d", ln) and "#" not in ln]
            i = rows[int(rng.integers(1, len(rows)))] if len(rows) > 1 else 0
            sep = "," if "," in lines[i] else " "
            fs = lines[i].split(sep)
            j = int(rng.integers(len(fs)))
            fs[j] = str(rng.choice(vals))
            lines[i] = sep.join(fs)
            what = f"line {i + 1} field {j} = {fs[j]!r}"
        elif op == 1:
            i = int(rng.integers(len(lines)))
            del lines[i]
            what = f"line {i + 1} deleted"
        elif op == 2:
            cut = int(rng.integers(len(text)))
            lines, what = text[:cut].splitlines() or [""], f"cut at {cut}"
        elif op == 3:  # deep / wrong JSON meta, or headers
            i = next((i for i, ln in enumerate(lines) if ln.startswith("# example")), 0)
            lines[i] = str(rng.choice(["# example 0 " + "[" * 100000 + "]" * 100000,
                                       '# example 0 {"rate": "abc"}', "# example 0 []",
                                       '# example 0 {"rate": -1, "attrs": 5}', "START",
                                       "BREAK", "letter,example"]))
            what = f"line {i + 1} = {lines[i][:30]!r}"
        else:
            lines = [ln.replace(",", ";") for ln in lines]
            what = "separator ';'"
        out.append(_ingest_case(f"strokes-{k:03d}", "strokes", base,
                                ("\n".join(lines) + "\n").encode(), "ingest_strokes_set", {},
                                f"{base}: {what}"))
    return out


def config_cases() -> list[Case]:
    """The hostile configs of ``benchmarks/fuzz_configs.py`` (``cases()``), if it exists."""
    path = HERE / "fuzz_configs.py"
    if not path.is_file():
        return []
    spec = importlib.util.spec_from_file_location("fuzz_configs", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return [Case(name=f"config-{name}", kind="config", config=text)
            for name, text in mod.cases()]


def all_cases(work: Path, *, quick: bool = False) -> list[Case]:
    """Every case of the suite (``quick``: the subset the default test run uses)."""
    src = sources(work / "sources")
    c3d, bvh = c3d_cases(src["c3d"]), bvh_cases(src["bvh"])
    amc, strokes = amc_cases(src["amc"]), strokes_cases(src["strokes"])
    if quick:  # the built cases (the issue's), a few seeded mutations of each kind
        built = [c for c in c3d + bvh if "-built-" in c.name]
        mutated = [c for c in c3d if "-built-" not in c.name]
        return built + mutated[1:5] + bvh[12:15] + amc[:2] + strokes[:2]
    return c3d + bvh + amc + strokes + config_cases()


