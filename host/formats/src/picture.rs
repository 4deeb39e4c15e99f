//! Text, lines and marks drawn over the report's images (plotters' bitmap backend on the
//! image's own buffer, DejaVu Sans embedded: no system font is needed).

use image::RgbImage;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::sync::Once;

/// The DejaVu Sans the text is drawn with, registered once as plotters' `sans-serif`.
fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // A font the crate embeds: it parses (its own tests say so); if it ever did not, the
        // text would be missing, not the image.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

/// Why a mark was not drawn.
pub type DrawError = Box<dyn std::error::Error>;

/// Draws on `img` through `paint` (errors of the drawing are dropped: a mark missing, never
/// an image missing).
pub fn draw(
    img: &mut RgbImage,
    paint: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<(), DrawError>,
) {
    register_font();
    let (w, h) = img.dimensions();
    let root = BitMapBackend::with_buffer(img, (w, h)).into_drawing_area();
    let _ = paint(&root);
    let _ = root.present();
}

/// An RGB colour for plotters.
pub fn rgb(c: [u8; 3]) -> RGBColor {
    RGBColor(c[0], c[1], c[2])
}

/// Text at `(x, y)` (its baseline's start), `size` px, in `colour` over a halo of `halo`
/// one pixel wide (readable over any picture).
pub fn text(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    (x, y): (i32, i32),
    size: f64,
    colour: [u8; 3],
    halo: [u8; 3],
    s: &str,
) -> Result<(), DrawError> {
    use plotters::style::text_anchor::{HPos, Pos, VPos};
    let at = |c: [u8; 3]| {
        ("sans-serif", size)
            .into_font()
            .color(&rgb(c))
            .pos(Pos::new(HPos::Left, VPos::Bottom))
    };
    for (dx, dy) in [
        (-1, 0),
        (1, 0),
        (0, -1),
        (0, 1),
        (-1, -1),
        (1, 1),
        (-1, 1),
        (1, -1),
    ] {
        root.draw(&Text::new(s.to_owned(), (x + dx, y + dy), at(halo)))
            .map_err(|e| e.to_string())?;
    }
    root.draw(&Text::new(s.to_owned(), (x, y), at(colour)))
        .map_err(|e| e.to_string())?;
    Ok(())
}

/// The width of `s` at `size` px, as drawn.
pub fn text_width(s: &str, size: f64) -> f64 {
    register_font();
    ("sans-serif", size)
        .into_font()
        .box_size(s)
        .map_or(0.6 * size * s.chars().count() as f64, |(w, _)| f64::from(w))
}
