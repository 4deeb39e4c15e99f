//! Why the core does not use `micromath`: its f32 `atan2` against f64, beside the core's integer
//! `atan2`, on the same grid of (y, x) pairs at the modulations a pixel sees. Prints JSON.
//!
//! `cargo run --release -p dpsa-core --example micromath_atan2`

use dpsa_core::phase;
use micromath::F32Ext;
use std::f64::consts::{PI, TAU};

/// Largest and rms absolute angle error (rad) of `f` against f64 `atan2` over the grid.
fn errors(f: impl Fn(f64, f64) -> f64) -> (f64, f64) {
    let (mut max, mut sum, mut count) = (0f64, 0f64, 0u64);
    for i in 0..8192 {
        let a = (i as f64 + 0.37) / 8192.0 * TAU;
        // Modulation radii from the validity threshold (60 DN) to a full-scale 12-bit fringe,
        // in the kernel's Q20.12 scaling.
        for r in [60.0f64, 300.0, 1000.0, 4000.0] {
            let (y, x) = (r * 4096.0 * a.sin(), r * 4096.0 * a.cos());
            let mut d = (f(y, x) - y.atan2(x)).rem_euclid(TAU);
            if d > PI {
                d = TAU - d;
            }
            max = max.max(d);
            sum += d * d;
            count += 1;
        }
    }
    (max, (sum / count as f64).sqrt())
}

fn main() {
    let (mm_max, mm_rms) = errors(|y, x| F32Ext::atan2(y as f32, x as f32) as f64);
    let (ours_max, ours_rms) = errors(|y, x| phase::to_rad(phase::atan2(y as i32, x as i32)));
    // Height error of a phase error at the default calibration: 500 um per turn, 0.25 um LSB.
    let lsb = |rad: f64| rad / TAU * 500.0 / 0.25;
    println!(
        "{{\n  \"micromath_atan2\": {{ \"max_rad\": {mm_max:.3e}, \"rms_rad\": {mm_rms:.3e}, \"max_lsb\": {:.3} }},\n  \
         \"core_atan2\": {{ \"max_rad\": {ours_max:.3e}, \"rms_rad\": {ours_rms:.3e}, \"max_lsb\": {:.4} }}\n}}",
        lsb(mm_max),
        lsb(ours_max)
    );
}
