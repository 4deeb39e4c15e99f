"""The D-PSA least-squares phase in numpy float64, timed: the baseline of `dpsa board-bench`.

Reads what `dpsa board-bench` wrote into the directory given as the only argument:
  frames.u16   F x H x W little-endian u16 samples (one camera's frames, in order)
  rows.i64     R x (2 + n) int64: board row b, entry frame w, offsets o_w .. o_{w+n-1}
  meta.json    {"frames": F, "rows_per_frame": H, "width": W, "n": n, "f_x": cycles per row}
and prints one JSON object: {"pixels": R * W, "seconds": compute time, "mpx_s": ...}.

Per board row b the samples are I_j = frame[w + j][b - o_{w+j}], the shifts
theta_j = -2 pi f_x (o_{w+j} - o_w), the model rows [1, cos theta_j, -sin theta_j], and the
phase atan2(v3, v2) of the least-squares solution v = pinv(M) I. Everything is vectorised over
rows and columns (one gather, one batched pseudo-inverse, one einsum); only the compute is
timed, not reading the files.
"""

import json
import sys
import time

import numpy as np


def main(d):
    meta = json.load(open(f"{d}/meta.json"))
    f, h, w, n = meta["frames"], meta["rows_per_frame"], meta["width"], meta["n"]
    frames = np.fromfile(f"{d}/frames.u16", dtype="<u2").reshape(f, h, w)
    rows = np.fromfile(f"{d}/rows.i64", dtype="<i8").reshape(-1, 2 + n)
    t0 = time.perf_counter()
    b, first, offs = rows[:, 0], rows[:, 1], rows[:, 2:]
    k = first[:, None] + np.arange(n)[None, :]
    r = b[:, None] - offs
    samples = frames[k, r, :].astype(np.float64)  # (R, n, W)
    theta = -2.0 * np.pi * meta["f_x"] * (offs - offs[:, :1])
    m = np.stack([np.ones_like(theta), np.cos(theta), -np.sin(theta)], axis=2)  # (R, n, 3)
    pinv = np.linalg.pinv(m)  # (R, 3, n)
    v = np.einsum("rkn,rnw->rkw", pinv[:, 1:, :], samples)  # (R, 2, W)
    phase = np.arctan2(v[:, 1, :], v[:, 0, :])
    seconds = time.perf_counter() - t0
    px = int(phase.size)
    print(json.dumps({"pixels": px, "seconds": seconds, "mpx_s": px / seconds / 1e6}))


if __name__ == "__main__":
    main(sys.argv[1])
