#!/bin/sh
# Cargo runner (.cargo/config.toml): runs the firmware ELF under QEMU through `dpsa target-run`,
# which streams a recording in, writes the packet stream out and decodes the defmt log.
#   cargo run                                    the built-in default scene
#   cargo run -- RECORDING [target-run options]  a recording directory (paths relative to the
#                                                repository root: the runner works from there)
set -eu
here=$(cd "$(dirname "$0")" && pwd)
elf=$(cd "$(dirname "$1")" && pwd)/$(basename "$1")   # absolute: we change directory below
shift
cd "$here/.."   # the host workspace, away from this directory's cross-compiling config
dpsa() { cargo run --release --quiet -p dpsa -- "$@"; }
if [ $# -eq 0 ]; then
    rec=out/target/default-scene
    [ -f "$rec/manifest.json" ] || dpsa simulate --scene default --seed 1 --out "$rec"
    dpsa target-run --elf "$elf" "$rec" --out out/target/default-scene.dpsa
else
    dpsa target-run --elf "$elf" "$@"
fi
