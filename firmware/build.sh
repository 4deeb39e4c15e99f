#!/usr/bin/env bash
# Builds the firmware ELF (release) and prints its absolute path as the last line of stdout.
#
# Two routes to a Cortex-M7 toolchain, chosen automatically:
# - rustup: where `rustup target list --installed` has thumbv7em-none-eabihf (a dev laptop):
#   plain `cargo build --release`, linked by rust-lld.
# - debian: otherwise. Debian's rustc-web/cargo-web with the library source (rust-web-src)
#   rebuild `core` for the target (-Zbuild-std, allowed by RUSTC_BOOTSTRAP=1), linked by
#   arm-none-eabi-ld from binutils-arm-none-eabi.
# DPSA_FIRMWARE_ROUTE=rustup|debian forces a route.
#
# --install: apt-get installs what is missing first (the route's packages and qemu-system-arm).
# --clippy:  instead of building, runs clippy for the target with -D warnings (same route; the
#            Debian route needs rust-web-clippy, which --install also brings).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
install=0
clippy=0
for arg in "$@"; do
    case "$arg" in
        --install) install=1 ;;
        --clippy) clippy=1 ;;
        *) echo "error: unknown option $arg (known: --install, --clippy)" >&2; exit 2 ;;
    esac
done

have() { command -v "$1" >/dev/null 2>&1; }
as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }

route=${DPSA_FIRMWARE_ROUTE:-}
if [ -z "$route" ]; then
    if have rustup && rustup target list --installed 2>/dev/null | grep -qx thumbv7em-none-eabihf; then
        route=rustup
    else
        route=debian
    fi
fi

pkgs=()
have qemu-system-arm || pkgs+=(qemu-system-arm)
if [ "$route" = debian ]; then
    { [ -x /usr/bin/rustc ] && /usr/bin/rustc --version | grep -q '^rustc 1\.9'; } || pkgs+=(rustc-web)
    { [ -x /usr/bin/cargo ] && /usr/bin/cargo --version | grep -q '^cargo 1\.9'; } || pkgs+=(cargo-web)
    [ -d /usr/lib/rustlib/src/rust/library/core ] || pkgs+=(rust-web-src)
    have arm-none-eabi-ld || pkgs+=(binutils-arm-none-eabi)
    [ $clippy = 0 ] || [ -x /usr/bin/cargo-clippy ] || pkgs+=(rust-web-clippy)
fi
if [ ${#pkgs[@]} -gt 0 ]; then
    if [ $install = 1 ]; then
        echo "== firmware: installing ${pkgs[*]}" >&2
        as_root apt-get update -qq >&2
        as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${pkgs[@]}" >&2
    else
        echo "error: the firmware ($route route) needs: ${pkgs[*]} (run: bash firmware/build.sh --install)" >&2
        exit 1
    fi
fi

# A build started from inside another cargo (tests, `dpsa target-run`) must not inherit its
# flags or target directory: the link scripts come from .cargo/config.toml.
unset RUSTFLAGS CARGO_ENCODED_RUSTFLAGS CARGO_BUILD_TARGET CARGO_BUILD_RUSTFLAGS RUSTC_WRAPPER
export CARGO_TARGET_DIR="$here/target"
cd "$here"
if [ $clippy = 1 ]; then
    if [ "$route" = rustup ]; then
        cargo clippy --release --locked -- -D warnings
    else
        # Debian's cargo must find Debian's cargo-clippy, not a rustup proxy earlier in PATH.
        PATH=/usr/bin:$PATH RUSTC=/usr/bin/rustc RUSTC_BOOTSTRAP=1 /usr/bin/cargo clippy --release --locked \
            -Zbuild-std=core -Zbuild-std-features=compiler-builtins-mem \
            --config 'target.thumbv7em-none-eabihf.linker="arm-none-eabi-ld"' -- -D warnings
    fi
    exit 0
fi
if [ "$route" = rustup ]; then
    cargo build --release --locked >&2
else
    RUSTC=/usr/bin/rustc RUSTC_BOOTSTRAP=1 /usr/bin/cargo build --release --locked \
        -Zbuild-std=core -Zbuild-std-features=compiler-builtins-mem \
        --config 'target.thumbv7em-none-eabihf.linker="arm-none-eabi-ld"' >&2
fi
echo "$here/target/thumbv7em-none-eabihf/release/dpsa-firmware"
