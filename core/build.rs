//! Generates the lookup tables of `dpsa-core` (idsp style: tables are data, built once here).
//!
//! `ATAN`: `atan(i / 256)` for `i = 0..=256`, as a binary angle (`2^32` per turn), so the
//! first octant spans `0..=2^29`. Two guard entries repeat the last value so that linear
//! interpolation at `t = 1` never reads past the table.

use std::{env, fs, path::Path};

const SEGMENTS: usize = 256;

fn main() {
    let turn = 2f64.powi(32);
    let mut s = String::from(
        "/// `atan(i / 256)` in binary-angle units (2^32 per turn), i = 0..=256, plus a guard.\n",
    );
    s.push_str(&format!(
        "pub(crate) static ATAN: [u32; {}] = [\n",
        SEGMENTS + 2
    ));
    for i in 0..=SEGMENTS + 1 {
        let t = (i.min(SEGMENTS) as f64) / SEGMENTS as f64;
        let a = (t.atan() / (2.0 * std::f64::consts::PI) * turn).round() as u32;
        s.push_str(&format!("    {a},\n"));
    }
    s.push_str("];\n");
    let out = Path::new(&env::var("OUT_DIR").unwrap()).join("atan_table.rs");
    fs::write(out, s).unwrap();
    println!("cargo:rerun-if-changed=build.rs");
}
