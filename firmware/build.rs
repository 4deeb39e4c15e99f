//! Puts the repository's `memory.x` (the one memory map, at the repository root) on the
//! linker search path; `link.x` of cortex-m-rt includes it.
use std::{env, fs, path::PathBuf};

fn main() {
    let out = PathBuf::from(env::var("OUT_DIR").unwrap());
    let map = PathBuf::from(env::var("CARGO_MANIFEST_DIR").unwrap()).join("../memory.x");
    fs::copy(&map, out.join("memory.x")).expect("memory.x at the repository root");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed={}", map.display());
    println!("cargo:rerun-if-changed=build.rs");
}
