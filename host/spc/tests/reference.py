#!/usr/bin/python3
# Independent reference implementation of the SPC definitions in REFERENCE.md
# (same directory). The Rust tests of the dpsa-spc crate run this script and
# compare the crate's results against its output to 1e-9 relative.
#
# It was written from REFERENCE.md alone, not from the Rust sources, and follows
# that document literally: null handling, 0-based indices, strict comparisons
# and the output JSON keys.
#
# Usage: /usr/bin/python3 reference.py < input.json > output.json
#   input:  {"cases": [CASE, ...]}
#   output: {"results": [RESULT, ...]}   (same order)
#
# Only the standard library and numpy are used. A quantity that is undefined
# is written as null; NaN or infinity never appears in the output.
#
# Baseline (phase I): a case may carry "baseline": B. The control limits
# (centre, sigma_limits, lcl/ucl, z and the dispersion chart) then come from
# the first B points or subgroups only; mean, sigma_within, sigma_overall and
# the capability indices always use the whole series. A null or absent
# baseline means all of it. An invalid baseline makes every output null.

import json
import math
import sys

import numpy as np

RULE_KEYS = ["WE1", "WE2", "WE3", "WE4",
             "N1", "N2", "N3", "N4", "N5", "N6", "N7", "N8"]

# Constants for subgroup size 2 (moving range of two points).
D2_2 = 2.0 / math.sqrt(math.pi)
D3_2 = math.sqrt(2.0 - 4.0 / math.pi)
D4_2 = 1.0 + 3.0 * D3_2 / D2_2


def c4(m):
    """c4(m) = sqrt(2/(m-1)) * Gamma(m/2) / Gamma((m-1)/2), m >= 2, via lgamma."""
    return math.sqrt(2.0 / (m - 1)) * math.exp(math.lgamma(m / 2.0) - math.lgamma((m - 1) / 2.0))


# ---------------------------------------------------------------- capability

def capability(mean, sigma, lsl, usl):
    """Return (cp, cpu, cpl, cpk) for one sigma; all null if sigma is 0 or undefined."""
    if sigma is None or sigma == 0:
        return None, None, None, None
    cp = (usl - lsl) / (6.0 * sigma) if (lsl is not None and usl is not None) else None
    cpu = (usl - mean) / (3.0 * sigma) if usl is not None else None
    cpl = (mean - lsl) / (3.0 * sigma) if lsl is not None else None
    present = [v for v in (cpu, cpl) if v is not None]
    cpk = min(present) if present else None
    return cp, cpu, cpl, cpk


# ---------------------------------------------------------------- run rules

def run_rules(z, p):
    """Rule firings on z (and on the plotted points p for N3/N4).

    A rule fires at i when its window ending at i (points i-L+1..i) qualifies;
    only i >= L-1 are considered. Returns a dict key -> list of indices.
    """
    n = len(z)
    fired = {k: [] for k in RULE_KEYS}

    def windows(length):
        # yields (i, slice of z, slice of p) for each full window ending at i
        for i in range(length - 1, n):
            yield i, z[i - length + 1:i + 1], p[i - length + 1:i + 1]

    # WE1 = N1: single point beyond 3 sigma.
    for i in range(n):
        if abs(z[i]) > 3:
            fired["WE1"].append(i)

    # WE2 = N5: 2 of 3 beyond 2 sigma on the same side.
    for i, w, _ in windows(3):
        if sum(1 for v in w if v > 2) >= 2 or sum(1 for v in w if v < -2) >= 2:
            fired["WE2"].append(i)

    # WE3 = N6: 4 of 5 beyond 1 sigma on the same side.
    for i, w, _ in windows(5):
        if sum(1 for v in w if v > 1) >= 4 or sum(1 for v in w if v < -1) >= 4:
            fired["WE3"].append(i)

    # WE4: 8 in a row on one side of the centre.
    for i, w, _ in windows(8):
        if all(v > 0 for v in w) or all(v < 0 for v in w):
            fired["WE4"].append(i)

    # N2: 9 in a row on one side of the centre.
    for i, w, _ in windows(9):
        if all(v > 0 for v in w) or all(v < 0 for v in w):
            fired["N2"].append(i)

    # N3: 6 points strictly increasing or strictly decreasing (on the points).
    for i, _, q in windows(6):
        d = [q[j] - q[j - 1] for j in range(1, len(q))]
        if all(v > 0 for v in d) or all(v < 0 for v in d):
            fired["N3"].append(i)

    # N4: 14 points alternating up and down (13 differences, all non-zero,
    # each of opposite sign to the one before).
    for i, _, q in windows(14):
        d = [q[j] - q[j - 1] for j in range(1, len(q))]
        ok = all(v != 0 for v in d) and all(
            (d[j] > 0) != (d[j - 1] > 0) for j in range(1, len(d)))
        if ok:
            fired["N4"].append(i)

    # N7: 15 in a row within 1 sigma of the centre.
    for i, w, _ in windows(15):
        if all(abs(v) < 1 for v in w):
            fired["N7"].append(i)

    # N8: 8 in a row beyond 1 sigma, with points on both sides.
    for i, w, _ in windows(8):
        if all(abs(v) > 1 for v in w) and any(v > 1 for v in w) and any(v < -1 for v in w):
            fired["N8"].append(i)

    # Aliases.
    fired["N1"] = list(fired["WE1"])
    fired["N5"] = list(fired["WE2"])
    fired["N6"] = list(fired["WE3"])
    return fired


# ---------------------------------------------------------------- result assembly

def result(mean, sigma_within, sigma_overall, sigma_limits, centre, lsl, usl,
           lcl, ucl, z, disp, rules):
    # Capability always from the whole series (mean and the two sigmas);
    # centre and sigma_limits only feed the charts.
    cp, cpu, cpl, cpk = capability(mean, sigma_within, lsl, usl)
    pp, ppu, ppl, ppk = capability(mean, sigma_overall, lsl, usl)
    return {
        "mean": mean, "sigma_within": sigma_within, "sigma_overall": sigma_overall,
        "sigma_limits": sigma_limits,
        "cp": cp, "cpu": cpu, "cpl": cpl, "cpk": cpk,
        "pp": pp, "ppu": ppu, "ppl": ppl, "ppk": ppk,
        "centre": centre, "lcl": lcl, "ucl": ucl, "z": z,
        "dispersion": disp,
        "rules": {k: rules.get(k, []) for k in RULE_KEYS},
    }


def undefined_result(npoints, ndisp):
    """Case too short (or with an invalid baseline) to define anything: every
    quantity null (per-point lists keep their length, filled with null), no
    rule fires."""
    nulls = [None] * npoints
    dn = [None] * ndisp
    return result(None, None, None, None, None, None, None,
                  list(nulls), list(nulls), list(nulls),
                  {"centre": list(dn), "lcl": list(dn), "ucl": list(dn)}, {})


def baseline_of(case, count):
    """The baseline B of a case: `count` (all points / subgroups) when the key
    is null or absent, else the given whole number. Anything that is not a
    whole number (a boolean, 2.5, a string) gives None, which the callers
    treat like an out-of-range baseline: every output null."""
    b = case.get("baseline")
    if b is None:
        return count
    if isinstance(b, bool):
        return None
    if isinstance(b, int):
        return b
    if isinstance(b, float) and math.isfinite(b) and b.is_integer():
        return int(b)
    return None


# ---------------------------------------------------------------- individuals

def individuals(case):
    x = [float(v) for v in case["x"]]
    lsl, usl = case.get("lsl"), case.get("usl")
    n = len(x)
    b = baseline_of(case, n)
    # Need n >= 2 and a baseline 2 <= B <= n; otherwise nothing is defined.
    if n < 2 or b is None or not (2 <= b <= n):
        return undefined_result(n, max(n - 1, 0))

    # Whole-series quantities (these feed the capability indices).
    a = np.array(x, dtype=float)
    mean = float(np.mean(a))
    mr = [abs(x[i] - x[i - 1]) for i in range(1, n)]          # n-1 moving ranges
    mr_bar = float(np.mean(np.array(mr)))
    sigma_within = mr_bar / D2_2
    sigma_overall = float(np.std(a, ddof=1))

    # Limits from the baseline x[0..B] only: its mean, and the mean of the
    # B-1 moving ranges inside it (|x[i] - x[i-1]|, i = 1..B-1).
    centre = float(np.mean(a[:b]))
    mr_bar_b = float(np.mean(np.array(mr[:b - 1])))
    sigma_limits = mr_bar_b / D2_2

    lcl = [centre - 3.0 * sigma_limits] * n
    ucl = [centre + 3.0 * sigma_limits] * n
    # MR chart over all n-1 moving ranges, with the baseline's mr_bar_b.
    disp = {"centre": [mr_bar_b] * (n - 1),
            "lcl": [0.0] * (n - 1),
            "ucl": [D4_2 * mr_bar_b] * (n - 1)}

    if sigma_limits == 0:
        z, rules = [None] * n, {}
    else:
        z = [(v - centre) / sigma_limits for v in x]
        rules = run_rules(z, x)

    return result(mean, sigma_within, sigma_overall, sigma_limits, centre, lsl, usl,
                  lcl, ucl, z, disp, rules)


# ---------------------------------------------------------------- subgroups

def subgroups(case):
    groups = [[float(v) for v in g] for g in case["x"]]
    lsl, usl = case.get("lsl"), case.get("usl")
    k = len(groups)
    dof = sum(len(g) - 1 for g in groups)
    b = baseline_of(case, k)
    # Need k >= 2, dof >= 1, a baseline 2 <= B <= k, and dof_B >= 1 over the
    # first B subgroups; otherwise nothing is defined.
    if k < 2 or dof < 1 or b is None or not (2 <= b <= k):
        return undefined_result(k, k)
    dof_b = sum(len(g) - 1 for g in groups[:b])
    if dof_b < 1:
        return undefined_result(k, k)

    def pooled_sd(gs, d):
        # sqrt( sum (n_i - 1) s_i^2 / d ) over the subgroups of size >= 2.
        ss = 0.0
        for g in gs:
            if len(g) >= 2:
                s = float(np.std(np.array(g), ddof=1))
                ss += (len(g) - 1) * s * s
        return math.sqrt(ss / d)

    # Whole-series quantities (these feed the capability indices).
    allv = np.array([v for g in groups for v in g], dtype=float)
    mean = float(np.mean(allv))                                # grand mean
    xbar = [float(np.mean(np.array(g))) for g in groups]
    sigma_within = pooled_sd(groups, dof) / c4(dof + 1)
    sigma_overall = float(np.std(allv, ddof=1))

    # Limits from the first B subgroups only.
    basev = np.array([v for g in groups[:b] for v in g], dtype=float)
    centre = float(np.mean(basev))                             # their grand mean
    sigma_limits = pooled_sd(groups[:b], dof_b) / c4(dof_b + 1)

    # The S chart always from the baseline's within sigma; the means' limits from it over
    # sqrt(n_i) ("within") or from the baseline means' moving ranges ("between").
    sigma_s = sigma_limits
    between = case.get("mean_limits", "within") == "between"
    if between:
        mb = np.array(xbar[:b])
        sigma_limits = float(np.mean(np.abs(np.diff(mb)))) / D2_2

    lcl, ucl = [], []
    sc, sl, su = [], [], []
    z = []
    for g, xb in zip(groups, xbar):
        ni = len(g)
        sx = sigma_limits if between else sigma_limits / math.sqrt(ni)
        lcl.append(centre - 3.0 * sx)
        ucl.append(centre + 3.0 * sx)
        z.append((xb - centre) / sx if sigma_limits != 0 else None)
        if ni >= 2:                      # s chart limits for this subgroup size
            c = c4(ni)
            s_centre = c * sigma_s
            half = 3.0 * sigma_s * math.sqrt(1.0 - c * c)
            sc.append(s_centre)
            sl.append(max(0.0, s_centre - half))
            su.append(s_centre + half)
        else:                            # size-1 subgroup: no s chart point
            sc.append(None)
            sl.append(None)
            su.append(None)

    rules = run_rules(z, xbar) if sigma_limits != 0 else {}
    disp = {"centre": sc, "lcl": sl, "ucl": su}
    return result(mean, sigma_within, sigma_overall, sigma_limits, centre, lsl, usl,
                  lcl, ucl, z, disp, rules)


# ---------------------------------------------------------------- gauge R&R

def msa(case):
    P, A, r = case["parts"], case["appraisers"], case["trials"]
    keys = ["df", "ms", "repeatability", "reproducibility", "appraiser", "interaction", "grr",
            "part", "total", "pct_tolerance", "pct_total", "ndc"]
    x = np.asarray(case["x"], dtype=float)
    if min(P, A, r) < 2 or x.size != P * A * r:
        return {k: None for k in keys}
    X = x.reshape(P, A, r)
    grand = X.mean()
    m_p = X.mean(axis=(1, 2))
    m_a = X.mean(axis=(0, 2))
    m_pa = X.mean(axis=2)
    ss = np.array([
        A * r * np.sum((m_p - grand) ** 2),
        P * r * np.sum((m_a - grand) ** 2),
        r * np.sum((m_pa - m_p[:, None] - m_a[None, :] + grand) ** 2),
        np.sum((X - m_pa[:, :, None]) ** 2),
    ])
    df = np.array([P - 1, A - 1, (P - 1) * (A - 1), P * A * (r - 1)], dtype=float)
    ms = ss / df
    ev2 = ms[3]
    inter2 = max((ms[2] - ms[3]) / r, 0.0)
    app2 = max((ms[1] - ms[2]) / (P * r), 0.0)
    pv2 = max((ms[0] - ms[2]) / (A * r), 0.0)
    av2 = app2 + inter2
    grr = math.sqrt(ev2 + av2)
    total = math.sqrt(ev2 + av2 + pv2)
    tol = case.get("tolerance")
    return {
        "df": df.tolist(), "ms": ms.tolist(),
        "repeatability": math.sqrt(ev2), "reproducibility": math.sqrt(av2),
        "appraiser": math.sqrt(app2), "interaction": math.sqrt(inter2),
        "grr": grr, "part": math.sqrt(pv2), "total": total,
        "pct_tolerance": 600.0 * grr / tol if tol is not None and tol > 0 else None,
        "pct_total": 100.0 * grr / total if total > 0 else None,
        "ndc": math.floor(1.41 * math.sqrt(pv2) / grr) if grr > 0 else None,
    }


# ---------------------------------------------------------------- I/O

def clean(obj):
    """Replace any non-finite float by None so the JSON never holds NaN/Infinity."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, list):
        return [clean(v) for v in obj]
    if isinstance(obj, dict):
        return {k: clean(v) for k, v in obj.items()}
    return obj


def main():
    data = json.load(sys.stdin)
    out = []
    for case in data["cases"]:
        if case["kind"] == "individuals":
            out.append(individuals(case))
        elif case["kind"] == "subgroups":
            out.append(subgroups(case))
        elif case["kind"] == "msa":
            out.append(msa(case))
        else:
            raise ValueError("unknown case kind: %r" % case["kind"])
    json.dump(clean({"results": out}), sys.stdout, allow_nan=False)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
