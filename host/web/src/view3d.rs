//! The pad's 3D view: the heights the line kept around a call as a lit surface the operator
//! turns with the mouse, on the pad's page.
//!
//! - **What draws it**: `pad3d.js`, this crate's own WebGL (about 150 lines: one mesh, one
//!   light); its 4 x 4 matrices from **gl-matrix** 3.4.4 (MIT, 53 kB minified), taken from the
//!   npm registry at build time, checked against its pinned SHA-512 and bundled into the
//!   binary (`build.rs`): no CDN, the page works offline. Chosen over three.js (about 700 kB
//!   for one surface) and regl (85 kB, but it generates its code with `Function`, which the
//!   pages' Content-Security-Policy forbids: no `unsafe-eval`).
//! - **What it draws**: the samples of `heights.json` (the kept crop above the pad's local
//!   surface, 0.1 um steps) as two triangles a cell, none over an invalid sample; coloured on
//!   the crop's own scale; heights exaggerated by the round factor that puts the scale's top
//!   at about a third of the crop's width (said under the view).
//! - **Page weight**: the library once (cached a day), the script (6 kB) and the JSON (about
//!   5 bytes a sample).

use crate::crop::Scale;
use dpsa_line::store::PadImage;
use std::fmt::Write;

/// gl-matrix's minified build (empty in a build made without npm: no 3D view).
pub const LIBRARY: &str = include_str!(concat!(env!("OUT_DIR"), "/gl-matrix-min.js"));

/// Where the pages load [`LIBRARY`] from (its version in the name: cached a day).
pub const LIBRARY_PATH: &str = "/js/gl-matrix-3.4.4.min.js";

/// The view's script.
pub const SCRIPT: &str = include_str!("pad3d.js");

/// Where the pages load [`SCRIPT`] from.
pub const SCRIPT_PATH: &str = "/js/pad3d.js";

/// The kept heights as the view reads them: `nx`, `ny`, `pitch_mm`, `top_um` (the colour
/// scale's top) and `heights` (um above the local surface to 0.1 um, `null` where invalid;
/// sample `(ix, iy)` at `ix * ny + iy`, board `x` then `y`).
pub fn json(image: &PadImage, scale: Scale) -> String {
    let c = &image.crop;
    let mut out = String::with_capacity(64 + 6 * c.heights_um.len());
    let _ = write!(
        out,
        "{{\"nx\":{},\"ny\":{},\"pitch_mm\":{},\"top_um\":{},\"heights\":[",
        c.nx,
        c.ny,
        finite(c.pitch_mm),
        finite(scale.top_um)
    );
    for (i, h) in c.heights_um.iter().enumerate() {
        if i > 0 {
            out.push(',');
        }
        if h.is_finite() {
            let _ = write!(out, "{:.1}", h);
        } else {
            out.push_str("null");
        }
    }
    out.push_str("]}");
    out
}

/// `v`, or 0 when it is not finite (JSON has no NaN).
fn finite(v: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// The factor the view multiplies heights by: the largest 1, 2 or 5 x 10^k that keeps the
/// scale's top (um) within a third of the crop's larger side, at least 1.
pub fn exaggeration(image: &PadImage, scale: Scale) -> f64 {
    let c = &image.crop;
    let side_um = c.nx.max(c.ny) as f64 * c.pitch_mm * 1000.0;
    let want = side_um / 3.0 / scale.top_um.max(1e-9);
    if !(want.is_finite() && want > 1.0) {
        return 1.0;
    }
    dpsa_formats::labels::scale_bar_mm(want)
}

/// The pad page's section for board `id`'s pad `k` with its kept heights.
pub fn section(id: i64, k: u32, image: &PadImage, scale: Scale) -> String {
    if LIBRARY.is_empty() {
        return "<h2>The pad in 3D</h2><p class=\"note\">This build has no 3D view: npm was not \
                available when it was built (see host/web/build.rs).</p>"
            .to_owned();
    }
    let ex = exaggeration(image, scale);
    format!(
        "<h2>The pad in 3D</h2><canvas id=\"pad3d\" width=\"640\" height=\"420\" \
         data-src=\"/board/{id}/pad/{k}/heights.json\" data-exaggeration=\"{ex}\"></canvas>\
         <p class=\"note\">The same heights as a surface, heights times {ex}; drag to turn it, \
         the wheel to come closer. Grey where the map has no valid height.</p>\
         <script src=\"{LIBRARY_PATH}\"></script><script src=\"{SCRIPT_PATH}\"></script>"
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_gerber::pads::Outline;
    use dpsa_inspect::crop::PadCrop;

    fn image(nx: usize, ny: usize, pitch_mm: f64) -> PadImage {
        PadImage {
            pad: 3,
            family: None,
            crop: PadCrop {
                x0_mm: 1.0,
                y0_mm: 2.0,
                pitch_mm,
                nx,
                ny,
                heights_um: (0..nx * ny)
                    .map(|i| if i == 1 { f32::NAN } else { i as f32 * 0.25 })
                    .collect(),
                outline: Outline::Circle {
                    centre: [1.0, 2.0],
                    diameter: 0.1,
                },
            },
        }
    }

    #[test]
    fn the_json_is_every_sample_in_order_with_null_for_invalid() {
        let im = image(3, 2, 0.025);
        let j = json(&im, Scale { top_um: 160.0 });
        assert_eq!(
            j,
            "{\"nx\":3,\"ny\":2,\"pitch_mm\":0.025,\"top_um\":160,\"heights\":\
             [0.0,null,0.5,0.8,1.0,1.2]}"
        );
    }

    #[test]
    fn the_exaggeration_puts_the_top_near_a_third_of_the_side() {
        // 40 samples of 25 um: a 1 mm side; a third is 333 um; the top 160 um: x2.
        let im = image(40, 30, 0.025);
        assert_eq!(exaggeration(&im, Scale { top_um: 160.0 }), 2.0);
        // A top taller than a third of the side: not flattened below x1.
        assert_eq!(exaggeration(&im, Scale { top_um: 900.0 }), 1.0);
        assert_eq!(
            exaggeration(&image(400, 30, 0.025), Scale { top_um: 160.0 }),
            20.0
        );
    }
}
