//! The board outline (profile, KiCad `Edge.Cuts`): its box gives the board corner.
//!
//! The outline layer is read as Gerber like the paste layer; its drawn lines are pads of the
//! class `stroke C w`. The board edge is the middle of the line, so the box of what is drawn
//! is shrunk by half the widest line's width on every side. Without an outline the paste
//! layer's box stands in (the corner then lies inside the board by the paste-free margin).

use dpsa_gerber::PasteLayer;

/// `[xmin, ymin, xmax, ymax]` of the board edge, mm, from its outline layer; None when the
/// layer draws nothing.
pub fn board_box(layer: &PasteLayer) -> Option<[f64; 4]> {
    if layer.pads.is_empty() {
        return None;
    }
    let half = layer
        .pads
        .iter()
        .filter_map(|p| {
            p.aperture
                .as_deref()?
                .strip_prefix("stroke C ")?
                .parse::<f64>()
                .ok()
        })
        .fold(0.0f64, f64::max)
        / 2.0;
    let b = layer.bbox_mm;
    if b[2] - b[0] <= 2.0 * half || b[3] - b[1] <= 2.0 * half {
        return None;
    }
    Some([b[0] + half, b[1] + half, b[2] - half, b[3] - half])
}
