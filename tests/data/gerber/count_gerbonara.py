"""Independent pad count: gerbonara parses, shapely (GEOS) unions. Run once by hand."""
import math, sys
from gerbonara import GerberFile
from gerbonara.utils import MM
from gerbonara import graphic_primitives as gp
import shapely
from shapely.geometry import Point, LineString, Polygon, box
from shapely import affinity
from shapely.ops import unary_union

def prim_shape(p):
    if isinstance(p, gp.Circle):
        return Point(p.x, p.y).buffer(p.r, quad_segs=64)
    if isinstance(p, gp.Line):
        return LineString([(p.x1, p.y1), (p.x2, p.y2)]).buffer(p.width / 2, quad_segs=64)
    if isinstance(p, gp.Rectangle):
        r = box(p.x - p.w / 2, p.y - p.h / 2, p.x + p.w / 2, p.y + p.h / 2)
        return affinity.rotate(r, p.rotation, origin=(p.x, p.y), use_radians=True)
    if isinstance(p, gp.ArcPoly):
        pts = [tuple(q) for q in p.outline]
        return Polygon(pts).buffer(0) if len(pts) >= 3 else None
    if isinstance(p, gp.Arc):
        n = 64
        cx, cy = p.cx + p.x1, p.cy + p.y1
        a0 = math.atan2(p.y1 - cy, p.x1 - cx); a1 = math.atan2(p.y2 - cy, p.x2 - cx)
        sw = (a0 - a1) % (2 * math.pi) if p.clockwise else (a1 - a0) % (2 * math.pi)
        r = math.hypot(p.x1 - cx, p.y1 - cy); d = -1 if p.clockwise else 1
        pts = [(cx + r * math.cos(a0 + d * sw * i / n), cy + r * math.sin(a0 + d * sw * i / n)) for i in range(n + 1)]
        return LineString(pts).buffer(p.width / 2, quad_segs=64)
    raise TypeError(type(p))

def pads(path):
    g = GerberFile.open(path)
    acc = shapely.geometry.GeometryCollection()
    dark_run = []
    objs = 0
    for obj in g.objects:
        objs += 1
        shapes = [prim_shape(p) for p in obj.to_primitives(unit=MM)]
        shapes = [s for s in shapes if s is not None and not s.is_empty]
        dark = [s for s, p in zip(shapes, obj.to_primitives(unit=MM)) if getattr(p, 'polarity_dark', True)]
        clear = [s for s, p in zip(shapes, obj.to_primitives(unit=MM)) if not getattr(p, 'polarity_dark', True)]
        if obj.polarity_dark:
            piece = unary_union(dark)
            if clear:
                piece = piece.difference(unary_union(clear))
            dark_run.append(piece)
        else:
            acc = unary_union([acc] + dark_run); dark_run = []
            acc = acc.difference(unary_union(dark))
    acc = unary_union([acc] + dark_run)
    polys = list(acc.geoms) if hasattr(acc, 'geoms') else [acc]
    polys = [p for p in polys if p.area > 1e-6]
    return objs, polys

for path in sys.argv[1:]:
    objs, polys = pads(path)
    polys.sort(key=lambda p: (round(p.centroid.x, 3), round(p.centroid.y, 3)))
    area = sum(p.area for p in polys)
    print(f"{path}: objects {objs} pads {len(polys)} area {area:.3f} mm2")
    for p in polys[:2] + polys[-1:]:
        print(f"   centroid ({p.centroid.x:.4f}, {p.centroid.y:.4f}) area {p.area:.4f}")
