#!/usr/bin/env bash
# The test command (README, CI): the firmware's cross build, rustfmt and clippy (host and
# target, warnings are errors), the workspace's docs (rustdoc warnings are errors), every test
# of the workspace (the firmware tests run it under QEMU) and the benchmark build. Installs
# what is missing; needs ../shared/data/real beside the repo.
set -euo pipefail
cd "$(dirname "$0")/.."
# One clean build: incremental state would only take disk (gigabytes over the workspace).
export CARGO_INCREMENTAL=0

have() { command -v "$1" >/dev/null 2>&1; }
as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }

if ! have cargo; then
    echo "== cargo not found: installing Debian's Rust toolchain"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq cargo rustc
fi

# The line's store tests (host/line) start a throwaway PostgreSQL server of their own with
# Debian's server programs (the package's own cluster is not used); they fail without them.
if ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then
    echo "== PostgreSQL's server programs not found: installing Debian's postgresql"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql
fi

# The FPGA front end's co-simulation (fpga/tests) builds the RTL with Debian's Verilator; it
# fails without it.
if ! have verilator; then
    echo "== verilator not found: installing Debian's verilator"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq verilator
fi

# The SPC statistics are checked against an independent numpy implementation
# (host/spc/tests/reference.py), run with Debian's Python.
if ! /usr/bin/python3 -c 'import numpy' >/dev/null 2>&1; then
    echo "== numpy for /usr/bin/python3 not found: installing Debian's python3-numpy"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3 python3-numpy
fi

# The operator's pages are tested in a real browser (host/web/tests/browser.rs): Debian's
# Chromium, headless, driven over WebDriver by its chromedriver.
if ! have chromedriver || ! { have chromium || have chromium-browser; }; then
    echo "== chromium or chromedriver not found: installing Debian's chromium and chromium-driver"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver
fi

# The pad's 3D view takes gl-matrix from the npm registry when dpsa-web is built
# (host/web/build.rs): with npm, else with curl.
if ! have npm && ! have curl; then
    echo "== neither npm nor curl found: installing Debian's curl"
    as_root apt-get update -qq
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq curl ca-certificates
fi

if [ ! -d ../shared/data/real ]; then
    echo "error: ../shared/data/real (real fringe stacks used by the tests) is missing" >&2
    exit 1
fi

echo "== firmware: Cortex-M7 build (installs the cross toolchain and QEMU if missing)"
elf=$(bash firmware/build.sh --install | tail -n 1)
echo "   $elf"

echo "== formatting and lints (host workspace, then the firmware for its target)"
cargo fmt --all --check
(cd firmware && cargo fmt --check)
cargo clippy --workspace --all-targets --locked -- -D warnings
bash firmware/build.sh --install --clippy
(cd fuzz && cargo fmt --check && cargo check --quiet)   # the fuzz target builds on dpsa-core alone

echo "== the production binary: dpsa without the simulator (program, pads, board --streams, inspect, decode, line, spc, serve)"
cargo build -p dpsa --no-default-features --locked --quiet
for c in program pads board inspect decode line spc serve; do
    if ! target/debug/dpsa help "$c" >/dev/null; then
        echo "error: the production binary has no \`$c\` command" >&2
        exit 1
    fi
done
# Without the simulator `board` takes the cameras' streams only; without them it says so.
said=$(target/debug/dpsa board /nonexistent --cal /nonexistent --out /nonexistent/map 2>&1 || true)
if ! grep -q "give the cameras' packet streams with --streams" <<<"$said"; then
    echo "error: the production binary's board does not ask for --streams" >&2
    exit 1
fi
prod=$(cargo tree -p dpsa --no-default-features -e normal,build --prefix none --locked | sed 's/ (\*)//' | sort -u)
echo "   $(echo "$prod" | wc -l) crates (the full binary: $(cargo tree -p dpsa -e normal,build --prefix none --locked | sed 's/ (\*)//' | sort -u | wc -l))"
for c in dpsa-sim zstd defmt-decoder lz4_flex heatshrink-lib rand_distr; do
    if echo "$prod" | grep -q "^$c v"; then
        echo "error: the production binary pulls $c" >&2
        exit 1
    fi
done

echo "== documentation (rustdoc warnings, e.g. broken intra-doc links, are errors)"
RUSTDOCFLAGS="-D warnings" cargo doc --no-deps --workspace --locked --quiet

echo "== unit, property and end-to-end tests (the firmware tests run it under QEMU)"
log=$(mktemp)
trap 'rm -f "$log"' EXIT
cargo test --workspace --locked 2>&1 | tee "$log"

echo "== benchmarks compile"
cargo bench --workspace --locked --no-run

# One closing line over every test binary (cargo's last line is a doc-test run of 0 tests).
passed=$(grep '^test result:' "$log" | grep -Eo '[0-9]+ passed' | awk '{s += $1} END {print s + 0}')
failed=$(grep '^test result:' "$log" | grep -Eo '[0-9]+ failed' | awk '{s += $1} END {print s + 0}')
echo "tests: $passed passed, $failed failed"
echo "target: $(du -sh target 2>/dev/null | cut -f1) on disk"
