"""Independent reference for the Gerber paste-layer corpus: gerbonara parses, shapely (GEOS)
unions. For every file given (or every layer file under this folder when none is given) it
prints one JSON object, keyed by the path relative to this folder:

    {"pads": N, "bbox_mm": [xmin, ymin, xmax, ymax], "units": "mm"|"inch",
     "generator": "...", "objects": N, "area_mm2": A}

or {"error": "..."} when gerbonara cannot read the file. Pads are connected dark areas:
each object's primitives (`to_primitives(unit=MM)`) become shapely shapes (circles, line
caps and arcs with 64 segments per quarter turn, the arcs of region outlines included),
dark objects are unioned, clear ones subtracted in file order, pieces under 1e-6 mm^2
dropped. The box is the union's bounds (zeros when empty).

    python reference.py [--check reference.json] [FILE...]

With --check it compares its results with the committed JSON and exits 1 on any difference
(the committed file is then stale). This is data tooling, not part of dpsa.
"""
import json
import math
import os
import re
import sys
import warnings

import shapely
from gerbonara import GerberFile
from gerbonara import graphic_primitives as gp
from gerbonara.utils import MM
from shapely import affinity
from shapely.geometry import LineString, Point, Polygon, box
from shapely.ops import unary_union

HERE = os.path.dirname(os.path.abspath(__file__))
# Layer files in the corpus: everything but the READMEs, licences and scripts.
NOT_LAYER = re.compile(r"(^readme|^licen[cs]e|^copying|\.py$|\.json$|\.md$|\.txt$)", re.I)


def arc_points(cx, cy, x1, y1, x2, y2, clockwise):
    """Points along a circular arc from (x1, y1) to (x2, y2) around the ABSOLUTE centre (cx, cy)
    (gerbonara's primitives carry absolute centres), 64 per quarter turn, both ends included.
    Coincident ends are a full circle (gerbonara's `Arc.is_circle`)."""
    a0 = math.atan2(y1 - cy, x1 - cx)
    a1 = math.atan2(y2 - cy, x2 - cx)
    sw = (a0 - a1) % (2 * math.pi) if clockwise else (a1 - a0) % (2 * math.pi)
    if math.isclose(x1, x2, abs_tol=1e-6) and math.isclose(y1, y2, abs_tol=1e-6):
        sw = 2 * math.pi
    r = math.hypot(x1 - cx, y1 - cy)
    d = -1 if clockwise else 1
    n = max(1, math.ceil(64 * sw / (math.pi / 2)))
    return [(cx + r * math.cos(a0 + d * sw * i / n), cy + r * math.sin(a0 + d * sw * i / n))
            for i in range(n + 1)]


def prim_shape(p):
    if isinstance(p, gp.Circle):
        return Point(p.x, p.y).buffer(p.r, quad_segs=64)
    if isinstance(p, gp.Line):
        return LineString([(p.x1, p.y1), (p.x2, p.y2)]).buffer(p.width / 2, quad_segs=64)
    if isinstance(p, gp.Rectangle):
        r = box(p.x - p.w / 2, p.y - p.h / 2, p.x + p.w / 2, p.y + p.h / 2)
        return affinity.rotate(r, p.rotation, origin=(p.x, p.y), use_radians=True)
    if isinstance(p, gp.ArcPoly):
        # A region: straight sides and arcs (KiCad 5's rounded pads, Allegro's outlines).
        pts = []
        for (x1, y1), (x2, y2), (clockwise, (cx, cy)) in p.segments:
            pts.append((x1, y1))
            if clockwise is not None:
                pts.extend(arc_points(cx, cy, x1, y1, x2, y2, clockwise)[1:-1])
        return Polygon(pts).buffer(0) if len(pts) >= 3 else None
    if isinstance(p, gp.Arc):
        pts = arc_points(p.cx, p.cy, p.x1, p.y1, p.x2, p.y2, p.clockwise)
        return LineString(pts).buffer(p.width / 2, quad_segs=64)
    raise TypeError(type(p))


def generator(g, path):
    """What the file says made it: %TF.GenerationSoftware, else a known header comment."""
    gen = g.generator_hints[0] if getattr(g, "generator_hints", None) else None
    with open(path, "rb") as f:
        head = f.read(4000).decode("latin-1")
    m = re.search(r"TF\.GenerationSoftware,([^*%]*)", head)
    if m:
        return m.group(1).strip()
    for pat in (r"EasyEDA[^*,]*", r"Created by KiCad \(PCBNEW [^)]*\)", r"\(created by PCBNEW [^*]*",
                r"EAGLE Gerber[^*]*", r"Creator: [^*]*", r"Mentor Graphics[^*]*",
                r"PADS[^*]*generated Gerber", r"DipTrace[^*]*", r"Cadence Allegro[^*]*", r"Layer_Color",
                r"%AMOC8\*\s*5,1,8,0,0,1\.08239X\$1,22\.5"):
        m = re.search(pat, head)
        if m:
            if pat == r"Layer_Color":
                return "Altium (Layer_Color header)"
            if pat.startswith("%AMOC8"):
                return "EAGLE (no header; its OC8 macro)"
            return m.group(0).strip()
    return gen or "unknown"


def reference(path):
    g = GerberFile.open(path)
    acc = shapely.geometry.GeometryCollection()
    dark_run = []
    objs = 0
    for obj in g.objects:
        objs += 1
        prims = obj.to_primitives(unit=MM)
        pairs = [(prim_shape(p), p) for p in prims]
        pairs = [(s, p) for s, p in pairs if s is not None and not s.is_empty]
        dark = [s for s, p in pairs if getattr(p, "polarity_dark", True)]
        clear = [s for s, p in pairs if not getattr(p, "polarity_dark", True)]
        if obj.polarity_dark:
            piece = unary_union(dark)
            if clear:
                piece = piece.difference(unary_union(clear))
            dark_run.append(piece)
        else:
            acc = unary_union([acc] + dark_run)
            dark_run = []
            acc = acc.difference(unary_union(dark))
    acc = unary_union([acc] + dark_run)
    polys = list(acc.geoms) if hasattr(acc, "geoms") else [acc]
    polys = [p for p in polys if not p.is_empty and p.area > 1e-6]
    if polys:
        b = unary_union(polys).bounds
        bbox = [round(v, 5) for v in b]
    else:
        bbox = [0.0, 0.0, 0.0, 0.0]
    unit = g.unit.shorthand if g.unit is not None else "?"
    return {
        "pads": len(polys),
        "bbox_mm": bbox,
        "units": "inch" if unit == "in" else unit,
        "generator": generator(g, path),
        "objects": objs,
        "area_mm2": round(sum(p.area for p in polys), 4),
    }


def corpus_files():
    out = []
    for d in sorted(os.listdir(HERE)):
        full = os.path.join(HERE, d)
        if not os.path.isdir(full):
            continue
        for f in sorted(os.listdir(full)):
            if not NOT_LAYER.search(f):
                out.append(os.path.join(d, f))
    return out


def main(argv):
    warnings.simplefilter("ignore")  # gerbonara's notes on odd syntax go to stderr otherwise
    check = None
    if argv[:1] == ["--check"]:
        check, argv = argv[1], argv[2:]
    rels = [os.path.relpath(os.path.abspath(a), HERE) for a in argv] or corpus_files()
    result = {}
    for rel in rels:
        try:
            result[rel] = reference(os.path.join(HERE, rel))
        except Exception as e:  # gerbonara's own refusal is a result too
            result[rel] = {"error": f"{type(e).__name__}: {e}"}
    text = json.dumps(result, indent=1, sort_keys=True) + "\n"
    if check is None:
        sys.stdout.write(text)
        return 0
    with open(check) as f:
        committed = json.load(f)
    if committed != json.loads(text):
        stale = sorted(k for k in set(committed) | set(result) if committed.get(k) != result.get(k))
        sys.stderr.write(f"{check} is stale for: {', '.join(stale)}; regenerate it with "
                         f"`python reference.py > reference.json`\n")
        sys.stdout.write(text)
        return 1
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
