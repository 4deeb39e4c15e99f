#!/usr/bin/env python3
"""A small conveyor recording written the way a camera's frame grabber writes one
(docs/recording.md), by its own code: the measurement model of docs/model.md in a few lines
of plain Python (no numpy, no code of dpsa), 16-bit PNG frames by zlib.

usage: python3 make_recording.py OUT [--damage KIND]

Writes OUT/rec/ (manifest.json, frames/NNNNNN.png) and OUT/expected.json (the height of
every board row and column, um, that the recording shows). --damage writes a recording a
reader must refuse: missing-frame (a listed frame file absent), short-frame (a frame of
fewer rows than the manifest says), unknown-key (a misspelt manifest key), latch-text (a
latch that is not an integer), bit-depth (values above the stated bit depth).

The scene: a board W = 64 columns wide, flat at 0 um except a block 60 um high over board
rows 40..69 and columns 20..43, moving 3 rows per trigger under a fixed fringe of period
8 px; a camera of H = 16 rows, 12 bits.
"""
import json
import math
import os
import struct
import sys
import zlib

W, H = 64, 16
CPP = 10.25  # encoder counts per pixel of travel (a multiple of 2^-16)
STEP = 3  # rows per trigger
PERIOD = 8.0  # fringe period, px
T_Z = 500.0  # height per fringe turn, um
B, C = 2000.0, 1000.0  # background and contrast, DN
FRAMES = 36


def phi0(c):
    """Reference-plane phase of column c at image row 0, rad."""
    return 0.05 * c + 0.3 * math.sin(c / 9.0)


def height(b, c):
    """The board's height at board row b, column c, um."""
    return 60.0 if 40 <= b < 70 and 20 <= c < 44 else 0.0


def png16(path, rows):
    """A 16-bit greyscale PNG of `rows` (lists of ints)."""
    raw = b"".join(b"\x00" + struct.pack(">%dH" % len(r), *r) for r in rows)

    def chunk(kind, data):
        c = struct.pack(">I", len(data)) + kind + data
        return c + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", len(rows[0]), len(rows), 16, 0, 0, 0, 0)
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def main():
    out = sys.argv[1]
    damage = sys.argv[3] if len(sys.argv) > 3 and sys.argv[2] == "--damage" else None
    rec = os.path.join(out, "rec")
    os.makedirs(os.path.join(rec, "frames"), exist_ok=True)
    frames = []
    for k in range(FRAMES):
        latch = round(k * STEP * CPP)
        o = math.floor(latch / CPP + 0.5)
        img = []
        rows = H - 2 if damage == "short-frame" and k == 5 else H
        for r in range(rows):
            line = []
            for c in range(W):
                psi = 2 * math.pi * height(r + o, c) / T_Z
                v = B + C * math.cos(2 * math.pi * r / PERIOD + phi0(c) + psi)
                if damage == "bit-depth" and k == 7 and r == 3:
                    v = 5000
                line.append(int(round(v)))
            img.append(line)
        name = "frames/%06d.png" % k
        if not (damage == "missing-frame" and k == 9):
            png16(os.path.join(rec, name), img)
        frames.append({"seq": k, "latch": latch, "file": name})
    if damage == "latch-text":
        frames[4]["latch"] = "123"
    manifest = {
        "format": "dpsa-recording",
        "version": 1,
        "camera": {"id": 0, "width": W, "rows": H, "bit_depth": 12, "saturation": 4095},
        "calibration": {
            "counts_per_pixel": CPP,
            "fringe_period_px": PERIOD,
            "reference_phase_rad": [phi0(c) for c in range(W)],
            "height_per_turn_um": T_Z,
            "height_lsb_um": 0.25,
        },
        "processing": {"n": 4, "max_step_rows": 10, "min_modulation": 60.0, "max_noise_gain": 2.0},
        "frames": frames,
    }
    if damage == "unknown-key":
        manifest["camera"]["bitdepth"] = 12
    with open(os.path.join(rec, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1)
    last = math.floor(round((FRAMES - 1) * STEP * CPP) / CPP + 0.5) + H
    expected = {
        "first_row": 0,
        "rows": [[height(b, c) for c in range(W)] for b in range(last)],
    }
    with open(os.path.join(out, "expected.json"), "w") as f:
        json.dump(expected, f)


if __name__ == "__main__":
    main()
