#!/usr/bin/env python3
"""Writes pcb-top.pos (KiCad ASCII placement file) and pads.ref.csv (every top paste pad's
component and pad number, the reference the tests compare dpsa's naming with) from the
project's pcb.kicad_pcb (KiCad 5.1, not copied here: see README.md). Usage:
make_pos.py pcb.kicad_pcb"""
import math, re, sys

text = open(sys.argv[1]).read()
mods = re.split(r"\n  \(module ", text)[1:]
rows, pads = [], []
for m in mods:
    name = m.split()[0].split(":")[-1]
    layer = re.search(r"\(layer ([^)]+)\)", m).group(1)
    at = re.search(r"\n    \(at ([-\d. ]+)\)", m).group(1).split()
    x, y = float(at[0]), float(at[1])
    rot = float(at[2]) if len(at) > 2 else 0.0
    ref = re.search(r"fp_text reference (\S+)", m).group(1)
    val = re.search(r"fp_text value (\S+)", m).group(1)
    if layer != "F.Cu" or "*" in ref:
        continue
    t = math.radians(rot)
    n = 0
    for p in re.finditer(r"\(pad (\S+) smd \S+ \(at ([-\d. ]+)\).*?\(layers ([^)]*)\)", m):
        if "F.Paste" not in p.group(3):
            continue
        px, py = map(float, p.group(2).split()[:2])
        ax = x + px * math.cos(t) + py * math.sin(t)
        ay = y - px * math.sin(t) + py * math.cos(t)
        pads.append((ref, p.group(1).strip('"'), ax, -ay))
        n += 1
    if n:
        rows.append((ref, val, name, x, -y, rot))
with open("pcb-top.pos", "w") as f:
    f.write("### Module positions - created from pcb.kicad_pcb by make_pos.py ###\n")
    f.write("### Printed by Pcbnew version kicad (5.1.5)-3\n## Unit = mm, Angle = deg.\n## Side : top\n")
    f.write("# Ref     Val                  Package                    PosX       PosY       Rot  Side\n")
    for r in sorted(rows):
        f.write("%-9s %-20s %-26s %9.4f %10.4f %8.4f  top\n" % r)
    f.write("## End\n")
with open("pads.ref.csv", "w") as f:
    f.write("component,pad,x_mm,y_mm\n")
    for p in pads:
        f.write("%s,%s,%.4f,%.4f\n" % p)
