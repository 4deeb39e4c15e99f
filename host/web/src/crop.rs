//! A pad's kept heights ([`PadImage`]) as a person reads them: the height map around the pad
//! in false colour with axes in mm, the opening outlined, the profile's cut line and a colour
//! bar in um (inline SVG over the `crop.png` route's image), and the profile along the cut
//! with its axes (inline SVG).
//!
//! Board `x` to the right and `y` up, as a Gerber viewer shows the design. Presentation
//! attributes only: the Content-Security-Policy allows no inline style.

use dpsa_gerber::pads::Outline;
use dpsa_line::store::PadImage;
use std::fmt::Write;

/// The colour of a sample without a valid height.
pub const INVALID_RGB: [u8; 3] = [70, 70, 70];

/// The colour scale of a crop: 0 um (the local surface) to `top_um`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scale {
    /// The height drawn in the scale's last colour, um.
    pub top_um: f64,
}

impl Scale {
    /// The scale for a pad of nominal height `nominal_um` (the stencil's thickness): 0 to 1.6
    /// times it, as the report's gallery; without one, 0 to the crop's highest valid height
    /// (at least 10 um).
    pub fn for_pad(image: &PadImage, nominal_um: Option<f64>) -> Scale {
        let top_um = match nominal_um {
            Some(n) if n.is_finite() && n > 0.0 => 1.6 * n,
            _ => image
                .crop
                .heights_um
                .iter()
                .filter(|v| v.is_finite())
                .fold(10.0f64, |a, &v| a.max(f64::from(v))),
        };
        Scale { top_um }
    }

    /// The colour of height `h_um`.
    pub fn rgb(&self, h_um: f32) -> [u8; 3] {
        if h_um.is_finite() {
            dpsa_formats::images::colour((f64::from(h_um) / self.top_um).clamp(0.0, 1.0))
        } else {
            INVALID_RGB
        }
    }
}

/// The crop as an RGB PNG, one pixel a sample: column `ix` (board `x` to the right), row
/// `ny - 1 - iy` (board `y` up).
pub fn png(image: &PadImage, scale: Scale) -> Result<Vec<u8>, png::EncodingError> {
    let c = &image.crop;
    let mut rgb = Vec::with_capacity(3 * c.nx * c.ny);
    for v in (0..c.ny).rev() {
        for u in 0..c.nx {
            rgb.extend_from_slice(&scale.rgb(c.at(u, v)));
        }
    }
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, c.nx as u32, c.ny as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header()?;
        w.write_image_data(&rgb)?;
    }
    Ok(out)
}

/// An opening as an SVG element with `attrs`: `to` takes board mm to the drawing (board `y`
/// up, drawing `y` down), `px_per_mm` its scale.
pub fn outline_svg(
    outline: &Outline,
    to: impl Fn(f64, f64) -> (f64, f64),
    px_per_mm: f64,
    attrs: &str,
) -> String {
    match outline {
        Outline::Circle { centre, diameter } => {
            let (cx, cy) = to(centre[0], centre[1]);
            format!(
                "<circle cx=\"{cx:.1}\" cy=\"{cy:.1}\" r=\"{:.2}\" {attrs}/>",
                diameter / 2.0 * px_per_mm
            )
        }
        Outline::RoundRect {
            centre,
            size,
            radius,
            rotation_deg,
        } => {
            let (cx, cy) = to(centre[0], centre[1]);
            let (rw, rh) = (size[0] * px_per_mm, size[1] * px_per_mm);
            let r = radius.clamp(0.0, size[0].min(size[1]) / 2.0) * px_per_mm;
            // Counter-clockwise on the board is clockwise in the drawing (y flipped).
            let turn = if *rotation_deg == 0.0 {
                String::new()
            } else {
                format!(
                    " transform=\"rotate({:.3} {cx:.1} {cy:.1})\"",
                    -rotation_deg
                )
            };
            format!(
                "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{rw:.2}\" height=\"{rh:.2}\" \
                 rx=\"{r:.2}\"{turn} {attrs}/>",
                cx - rw / 2.0,
                cy - rh / 2.0
            )
        }
        Outline::Polygon { exterior, holes } => {
            let mut d = String::new();
            for ring in std::iter::once(exterior).chain(holes) {
                for (k, q) in ring.iter().enumerate() {
                    let (x, y) = to(q[0], q[1]);
                    let _ = write!(d, "{}{x:.1},{y:.1} ", if k == 0 { "M" } else { "L" });
                }
                d.push('Z');
            }
            format!("<path d=\"{d}\" fill-rule=\"evenodd\" {attrs}/>")
        }
    }
}

pub use dpsa_formats::labels::ticks;

/// A tick's label: as few decimals as its step needs.
fn label(v: f64, step: f64) -> String {
    let d = if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    };
    let v = if v.abs() < step * 1e-6 { 0.0 } else { v };
    format!("{v:.d$}")
}

/// Where the crop's cut runs: the sample row through the opening's centroid (clamped).
pub fn cut_row(image: &PadImage) -> usize {
    let c = &image.crop;
    let cy = image.crop.outline.centroid()[1];
    let iy = ((cy - c.y0_mm) / c.pitch_mm).round();
    (iy.max(0.0) as usize).min(c.ny.saturating_sub(1))
}

/// The crop drawn: the `crop.png` image at `src` with axes in board mm, the opening, the cut
/// line, and the colour bar.
pub fn crop_svg(image: &PadImage, scale: Scale, src: &str) -> String {
    let c = &image.crop;
    let (nx, ny, p) = (c.nx as f64, c.ny as f64, c.pitch_mm);
    let s = (360.0 / nx.max(ny)).clamp(1.0, 14.0);
    let (left, top, bottom, bar) = (56.0, 12.0, 44.0, 90.0);
    let (pw, ph) = (nx * s, ny * s);
    let (w, h) = (left + pw + 24.0 + bar, top + ph + bottom);
    // Board mm to the drawing: sample centres at half a sample in.
    let sx = |x: f64| left + ((x - c.x0_mm) / p + 0.5) * s;
    let sy = |y: f64| top + (ny - 0.5 - (y - c.y0_mm) / p) * s;
    let mut o = String::new();
    let _ = write!(
        o,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w:.0}\" height=\"{h:.0}\" \
         viewBox=\"0 0 {w:.1} {h:.1}\" role=\"img\" aria-label=\"heights above the local \
         surface around the pad\"><image class=\"crop\" href=\"{src}\" x=\"{left}\" y=\"{top}\" \
         width=\"{pw:.1}\" height=\"{ph:.1}\" preserveAspectRatio=\"none\"/>\
         <rect x=\"{left}\" y=\"{top}\" width=\"{pw:.1}\" height=\"{ph:.1}\" fill=\"none\" \
         stroke=\"#57606a\"/>"
    );
    // The opening.
    o.push_str(&outline_svg(
        &c.outline,
        |x, y| (sx(x), sy(y)),
        s / p,
        "fill=\"none\" stroke=\"#ffffff\" stroke-width=\"1.5\" stroke-dasharray=\"4 3\"",
    ));
    // The cut.
    let yc = c.y0_mm + cut_row(image) as f64 * p;
    let _ = write!(
        o,
        "<line x1=\"{left}\" x2=\"{:.1}\" y1=\"{:.1}\" y2=\"{:.1}\" stroke=\"#000000\" \
         stroke-width=\"1\"/><text x=\"{:.1}\" y=\"{:.1}\" font-size=\"11\" fill=\"#000000\">\
         cut</text>",
        left + pw,
        sy(yc),
        sy(yc),
        left + pw + 3.0,
        sy(yc) + 4.0
    );
    // Axes, mm.
    let (x_lo, x_hi) = (c.x0_mm - p / 2.0, c.x0_mm + (nx - 0.5) * p);
    let (y_lo, y_hi) = (c.y0_mm - p / 2.0, c.y0_mm + (ny - 0.5) * p);
    let tx = ticks(x_lo, x_hi, 4);
    let step_x = tx.windows(2).map(|t| t[1] - t[0]).next().unwrap_or(1.0);
    for t in &tx {
        let _ = write!(
            o,
            "<line x1=\"{x:.1}\" x2=\"{x:.1}\" y1=\"{y0:.1}\" y2=\"{y1:.1}\" stroke=\"#57606a\"/>\
             <text x=\"{x:.1}\" y=\"{ty:.1}\" font-size=\"11\" text-anchor=\"middle\" \
             fill=\"#1d232a\">{l}</text>",
            x = sx(*t),
            y0 = top + ph,
            y1 = top + ph + 4.0,
            ty = top + ph + 16.0,
            l = label(*t, step_x)
        );
    }
    let ty = ticks(y_lo, y_hi, 4);
    let step_y = ty.windows(2).map(|t| t[1] - t[0]).next().unwrap_or(1.0);
    for t in &ty {
        let _ = write!(
            o,
            "<line x1=\"{x0:.1}\" x2=\"{left}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"#57606a\"/>\
             <text x=\"{tx:.1}\" y=\"{yt:.1}\" font-size=\"11\" text-anchor=\"end\" \
             fill=\"#1d232a\">{l}</text>",
            x0 = left - 4.0,
            y = sy(*t),
            tx = left - 6.0,
            yt = sy(*t) + 4.0,
            l = label(*t, step_y)
        );
    }
    let _ = write!(
        o,
        "<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"12\" text-anchor=\"middle\" \
         fill=\"#1d232a\">board x, mm</text><text x=\"12\" y=\"{:.1}\" font-size=\"12\" \
         text-anchor=\"middle\" fill=\"#1d232a\" transform=\"rotate(-90 12 {:.1})\">board y, \
         mm</text>",
        left + pw / 2.0,
        top + ph + 34.0,
        top + ph / 2.0,
        top + ph / 2.0
    );
    // The colour bar, um.
    let (bx, bw) = (left + pw + 34.0, 14.0);
    let steps = 24;
    for k in 0..steps {
        let t0 = k as f64 / steps as f64;
        let rgb = dpsa_formats::images::colour(t0 + 0.5 / steps as f64);
        let _ = write!(
            o,
            "<rect x=\"{bx:.1}\" y=\"{:.1}\" width=\"{bw}\" height=\"{:.2}\" \
             fill=\"#{:02x}{:02x}{:02x}\"/>",
            top + ph * (1.0 - (k + 1) as f64 / steps as f64),
            ph / steps as f64 + 0.3,
            rgb[0],
            rgb[1],
            rgb[2]
        );
    }
    let tb = ticks(0.0, scale.top_um, 4);
    let step_b = tb.windows(2).map(|t| t[1] - t[0]).next().unwrap_or(1.0);
    for t in &tb {
        let y = top + ph * (1.0 - t / scale.top_um);
        let _ = write!(
            o,
            "<line x1=\"{:.1}\" x2=\"{:.1}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"#1d232a\"/>\
             <text x=\"{:.1}\" y=\"{:.1}\" font-size=\"11\" fill=\"#1d232a\">{}</text>",
            bx + bw,
            bx + bw + 4.0,
            bx + bw + 6.0,
            y + 4.0,
            label(*t, step_b)
        );
    }
    let _ = write!(
        o,
        "<rect x=\"{bx:.1}\" y=\"{top}\" width=\"{bw}\" height=\"{ph:.1}\" fill=\"none\" \
         stroke=\"#57606a\"/><text x=\"{bx:.1}\" y=\"{:.1}\" font-size=\"11\" \
         fill=\"#1d232a\">um above</text><text x=\"{bx:.1}\" y=\"{:.1}\" font-size=\"11\" \
         fill=\"#1d232a\">the surface</text></svg>",
        top + ph + 16.0,
        top + ph + 29.0
    );
    o
}

/// The profile along the cut: height above the local surface (um) against board `x` (mm),
/// the nominal height dashed when known, gaps where the map has no height.
pub fn profile_svg(image: &PadImage, nominal_um: Option<f64>) -> String {
    let c = &image.crop;
    let iy = cut_row(image);
    let pts: Vec<(f64, f32)> = (0..c.nx)
        .map(|ix| (c.centre(ix, iy).0, c.at(ix, iy)))
        .collect();
    let valid: Vec<f64> = pts
        .iter()
        .filter(|p| p.1.is_finite())
        .map(|p| f64::from(p.1))
        .collect();
    if valid.is_empty() {
        return "<p class=\"note\">No valid height along the cut.</p>".to_owned();
    }
    let nominal = nominal_um.filter(|n| n.is_finite() && *n > 0.0);
    let lo = valid.iter().fold(0.0f64, |a, &v| a.min(v)) - 5.0;
    let hi = valid
        .iter()
        .chain(nominal.as_ref())
        .fold(10.0f64, |a, &v| a.max(v))
        * 1.1;
    let (w, h, left, right, top, bottom) = (640.0, 240.0, 56.0, 12.0, 10.0, 44.0);
    let (pw, ph) = (w - left - right, h - top - bottom);
    let (x_lo, x_hi) = (
        c.x0_mm - c.pitch_mm / 2.0,
        c.x0_mm + (c.nx as f64 - 0.5) * c.pitch_mm,
    );
    let sx = |x: f64| left + pw * (x - x_lo) / (x_hi - x_lo);
    let sy = |v: f64| top + ph * (hi - v) / (hi - lo);
    let mut o = String::new();
    let _ = write!(
        o,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" \
         viewBox=\"0 0 {w} {h}\" role=\"img\" aria-label=\"profile along the cut\">\
         <rect x=\"{left}\" y=\"{top}\" width=\"{pw}\" height=\"{ph}\" fill=\"#fafbfc\" \
         stroke=\"#ccd\"/>"
    );
    let tv = ticks(lo, hi, 5);
    let step_v = tv.windows(2).map(|t| t[1] - t[0]).next().unwrap_or(1.0);
    for t in &tv {
        let _ = write!(
            o,
            "<line x1=\"{left}\" x2=\"{:.1}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"#e3e6ea\"/>\
             <text x=\"{:.1}\" y=\"{:.1}\" font-size=\"11\" text-anchor=\"end\" \
             fill=\"#1d232a\">{}</text>",
            left + pw,
            left - 6.0,
            sy(*t) + 4.0,
            label(*t, step_v),
            y = sy(*t)
        );
    }
    let tx = ticks(x_lo, x_hi, 5);
    let step_x = tx.windows(2).map(|t| t[1] - t[0]).next().unwrap_or(1.0);
    for t in &tx {
        let _ = write!(
            o,
            "<line x1=\"{x:.1}\" x2=\"{x:.1}\" y1=\"{:.1}\" y2=\"{:.1}\" stroke=\"#57606a\"/>\
             <text x=\"{x:.1}\" y=\"{:.1}\" font-size=\"11\" text-anchor=\"middle\" \
             fill=\"#1d232a\">{}</text>",
            top + ph,
            top + ph + 4.0,
            top + ph + 16.0,
            label(*t, step_x),
            x = sx(*t)
        );
    }
    let zero = sy(0.0);
    let _ = write!(
        o,
        "<line x1=\"{left}\" x2=\"{:.1}\" y1=\"{zero:.1}\" y2=\"{zero:.1}\" stroke=\"#57606a\"/>",
        left + pw
    );
    if let Some(n) = nominal {
        let _ = write!(
            o,
            "<line x1=\"{left}\" x2=\"{:.1}\" y1=\"{y:.1}\" y2=\"{y:.1}\" stroke=\"#9a6700\" \
             stroke-dasharray=\"6 4\"/><text x=\"{:.1}\" y=\"{:.1}\" font-size=\"11\" \
             text-anchor=\"end\" fill=\"#9a6700\">stencil {n:.0} um</text>",
            left + pw,
            left + pw - 4.0,
            sy(n) - 4.0,
            y = sy(n)
        );
    }
    let mut d = String::new();
    let mut pen = false;
    for &(x, v) in &pts {
        if v.is_finite() {
            let _ = write!(
                d,
                "{}{:.1},{:.1} ",
                if pen { "L" } else { "M" },
                sx(x),
                sy(f64::from(v))
            );
            pen = true;
        } else {
            pen = false;
        }
    }
    let _ = write!(
        o,
        "<path d=\"{d}\" fill=\"none\" stroke=\"#1f6feb\" stroke-width=\"1.8\"/>\
         <text x=\"{:.1}\" y=\"{:.1}\" font-size=\"12\" text-anchor=\"middle\" \
         fill=\"#1d232a\">board x, mm (at y = {:.3} mm)</text><text x=\"12\" y=\"{:.1}\" \
         font-size=\"12\" text-anchor=\"middle\" fill=\"#1d232a\" \
         transform=\"rotate(-90 12 {:.1})\">um above the surface</text></svg>",
        left + pw / 2.0,
        top + ph + 34.0,
        c.y0_mm + iy as f64 * c.pitch_mm,
        top + ph / 2.0,
        top + ph / 2.0
    );
    o
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_inspect::crop::PadCrop;

    fn image(outline: Outline) -> PadImage {
        let (nx, ny) = (40, 30);
        let heights_um = (0..nx * ny)
            .map(|k| {
                let (ix, iy) = (k / ny, k % ny);
                if (10..30).contains(&ix) && (10..20).contains(&iy) {
                    120.0
                } else if ix == 0 {
                    f32::NAN
                } else {
                    0.0
                }
            })
            .collect();
        PadImage {
            pad: 3,
            family: None,
            crop: PadCrop {
                x0_mm: 1.0,
                y0_mm: 2.0,
                pitch_mm: 0.025,
                nx,
                ny,
                heights_um,
                outline,
            },
        }
    }

    #[test]
    fn labels_take_the_decimals_of_their_step() {
        assert_eq!(label(1.2000000001, 0.2), "1.2");
        assert_eq!(label(150.0, 50.0), "150");
    }

    /// The PNG decodes to the crop turned so that x runs right and y up, invalid in grey.
    #[test]
    fn the_png_is_the_crop_with_y_up() {
        let im = image(Outline::Circle {
            centre: [1.5, 2.35],
            diameter: 0.25,
        });
        let scale = Scale::for_pad(&im, Some(120.0));
        assert_eq!(scale.top_um, 192.0);
        let bytes = png(&im, scale).unwrap();
        let dec = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut r = dec.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
        let info = r.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (40, 30));
        let at = |u: usize, v: usize| {
            let k = 3 * (v * 40 + u);
            [buf[k], buf[k + 1], buf[k + 2]]
        };
        for u in 0..40 {
            for v in 0..30 {
                let want = scale.rgb(im.crop.at(u, 29 - v));
                assert_eq!(at(u, v), want, "({u}, {v})");
            }
        }
        assert_eq!(at(0, 5), INVALID_RGB);
        assert_eq!(at(15, 15), dpsa_formats::images::colour(120.0 / 192.0));
    }

    /// The drawing holds the image, the opening, the cut at the opening's centre row, round
    /// ticks, and no inline style; the profile runs through the paste with a gap for the
    /// invalid sample.
    #[test]
    fn the_drawings_carry_their_axes_and_the_cut() {
        let im = image(Outline::RoundRect {
            centre: [1.5, 2.35],
            size: [0.5, 0.25],
            radius: 0.05,
            rotation_deg: 90.0,
        });
        assert_eq!(cut_row(&im), 14);
        let s = crop_svg(&im, Scale::for_pad(&im, None), "/x/crop.png");
        assert!(s.contains("href=\"/x/crop.png\""));
        assert!(s.contains("rotate(-90.000"));
        assert!(s.contains("board x, mm") && s.contains("um above"));
        assert!(!s.contains("style="));
        assert!(s.contains(">1.5<") || s.contains(">1.4<"), "{s}");
        let p = profile_svg(&im, Some(100.0));
        assert!(p.contains("stencil 100 um"));
        assert!(!p.contains("style="));
        // One pen-down (the first sample is invalid: the path starts at the second).
        let path = p.split("<path d=\"").nth(1).unwrap();
        let path = &path[..path.find('"').unwrap()];
        assert_eq!(path.matches('M').count(), 1);
        assert_eq!(path.matches('L').count(), 38);
    }
}
