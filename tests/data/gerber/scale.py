#!/usr/bin/env python3
"""Large synthetic top paste layers for the reader's scale figures (docs/inspection.md,
"At scale"). Writes Gerber to stdout; nothing it makes is committed.

usage: python3 tests/data/gerber/scale.py KIND N > FILE
  column     N flashes of a 30 x 20 um pad in one step-and-repeat column (60 um apart)
  same       N flashes on one point (one pad)
  grid       N flashes on a 0.5 mm grid
  apertures  N aperture definitions, one flash each, on a 0.5 mm grid
  arcs       N full-circle arc strokes, on a 0.5 mm grid

Then: /usr/bin/time -v target/release/dpsa pads FILE
"""
import sys

kind, n = sys.argv[1], int(sys.argv[2])
w = sys.stdout.write
side = int(n ** 0.5) + 1


def c(v):
    """mm -> the 4.6 integer format."""
    return str(round(v * 1e6))


def at(i):
    return f"X{c((i % side) * 0.5)}Y{c((i // side) * 0.5)}"


w("%FSLAX46Y46*%\n%MOMM*%\n%ADD10R,0.030000X0.020000*%\n%ADD11C,0.100000*%\n")
if kind == "column":
    w(f"%SRX1Y{n}I0J0.06*%\nD10*\nX0Y0D03*\n%SR*%\n")
elif kind == "same":
    w("D10*\n")
    for _ in range(n):
        w("X1000000Y1000000D03*\n")
elif kind == "grid":
    w("D10*\n")
    for i in range(n):
        w(f"{at(i)}D03*\n")
elif kind == "apertures":
    for i in range(n):
        w(f"%ADD{12 + i}R,0.3X0.2*%\n")
    for i in range(n):
        w(f"D{12 + i}*\n{at(i)}D03*\n")
elif kind == "arcs":
    w("D11*\nG75*\n")
    for i in range(n):
        w(f"G01{at(i)}D02*\nG03{at(i)}I{c(0.1)}J0D01*\n")
else:
    sys.exit(f"unknown kind {kind!r}")
w("M02*\n")
