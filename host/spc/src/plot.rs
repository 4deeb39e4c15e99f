//! Control charts drawn as SVG and PNG with plotters.
//!
//! One image per chart: the points (individuals or subgroup means) over the boards with their
//! centre line and control limits (stepped where each board's subgroup size sets its own),
//! the points where a rule fired ringed in red with the rule's name, and the dispersion chart
//! (moving range or subgroup deviation) below with its limits. Text is DejaVu Sans, embedded
//! (the `dejavu` crate) and drawn through plotters' `ab_glyph` path, so the PNGs need no
//! system font library; the SVGs name the font and any viewer draws it.

use crate::chart::{Chart, Kind};
use crate::rules::{fires, Rule};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::Path;
use std::sync::Once;

/// Size of a chart image, px.
pub const SIZE: (u32, u32) = (1100, 700);

/// What the picture says besides the chart: its title and axis label.
#[derive(Clone, Debug)]
pub struct Caption {
    /// Title, e.g. `family 0402 · volume`.
    pub title: String,
    /// The measure's axis label.
    pub y_label: String,
    /// Under the x axis: the first and last board, e.g. their run ids.
    pub x_label: String,
}

/// Why a chart could not be drawn.
#[derive(Debug)]
pub struct PlotError(String);

impl std::fmt::Display for PlotError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "drawing a chart: {}", self.0)
    }
}

impl std::error::Error for PlotError {}

fn err<E: std::fmt::Display>(e: E) -> PlotError {
    PlotError(e.to_string())
}

fn register_font() -> Result<(), PlotError> {
    static ONCE: Once = Once::new();
    let mut result = Ok(());
    ONCE.call_once(|| {
        result = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        )
        .map_err(|_| PlotError("the embedded font is not a font".to_owned()));
    });
    result
}

/// Draws `chart` with the firings of `rules` to `svg` and `png` (either may be `None`).
pub fn draw(
    chart: &Chart,
    rules: &[Rule],
    caption: &Caption,
    svg: Option<&Path>,
    png: Option<&Path>,
) -> Result<(), PlotError> {
    register_font()?;
    if let Some(p) = svg {
        let root = SVGBackend::new(p, SIZE).into_drawing_area();
        paint(&root, chart, rules, caption)?;
        root.present().map_err(err)?;
    }
    if let Some(p) = png {
        image::save_buffer_with_format(
            p,
            &rgb(chart, rules, caption)?,
            SIZE.0,
            SIZE.1,
            image::ExtendedColorType::Rgb8,
            image::ImageFormat::Png,
        )
        .map_err(err)?;
    }
    Ok(())
}

/// `chart` painted into an RGB buffer of [`SIZE`] (the font registered).
fn rgb(chart: &Chart, rules: &[Rule], caption: &Caption) -> Result<Vec<u8>, PlotError> {
    register_font()?;
    let mut rgb = vec![0u8; SIZE.0 as usize * SIZE.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, SIZE).into_drawing_area();
        paint(&root, chart, rules, caption)?;
        root.present().map_err(err)?;
    }
    Ok(rgb)
}

/// `chart` as PNG bytes (as [`draw`] writes its file), for a page to serve.
pub fn png_bytes(chart: &Chart, rules: &[Rule], caption: &Caption) -> Result<Vec<u8>, PlotError> {
    let mut out = std::io::Cursor::new(Vec::new());
    image::write_buffer_with_format(
        &mut out,
        &rgb(chart, rules, caption)?,
        SIZE.0,
        SIZE.1,
        image::ExtendedColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .map_err(err)?;
    Ok(out.into_inner())
}

/// The corner of the upper chart with the fewest points (a third of the width, a third of
/// the height), where the legend hides none or the fewest.
fn emptiest_corner(pts: &[(f64, f64)], n: usize, lo: f64, hi: f64) -> SeriesLabelPosition {
    let (w, h) = (n as f64, hi - lo);
    let count = |right: bool, top: bool| {
        pts.iter()
            .filter(|&&(x, y)| {
                let fx = (x - 0.5) / w.max(1.0);
                let fy = (y - lo) / h.max(f64::MIN_POSITIVE);
                (if right { fx > 0.6 } else { fx < 0.4 }) && (if top { fy > 0.6 } else { fy < 0.4 })
            })
            .count()
    };
    [
        (SeriesLabelPosition::UpperRight, count(true, true)),
        (SeriesLabelPosition::UpperLeft, count(false, true)),
        (SeriesLabelPosition::LowerRight, count(true, false)),
        (SeriesLabelPosition::LowerLeft, count(false, false)),
    ]
    .into_iter()
    .min_by_key(|&(_, c)| c)
    .map_or(SeriesLabelPosition::UpperRight, |(p, _)| p)
}

/// Labels on the board axis: one per board up to 20, else about 10.
fn x_labels(n: usize) -> usize {
    if n <= 20 {
        n + 1
    } else {
        10
    }
}

/// A board number: whole positions only (the axis runs from 0.5 to `n + 0.5`).
fn whole(x: &f64) -> String {
    if (x - x.round()).abs() < 1e-6 && *x >= 0.5 {
        format!("{}", x.round())
    } else {
        String::new()
    }
}

/// `[lo, hi]` around every finite value of `vs`, with a margin; `[0, 1]` without any.
fn span<'a>(vs: impl Iterator<Item = &'a f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for &v in vs.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.08).max(hi.abs().max(1.0) * 1e-3);
    (lo - pad, hi + pad)
}

/// A limit line as steps over the points (each point's value held over `[i - 0.5, i + 0.5]`).
fn steps(v: &[Option<f64>], first: usize) -> Vec<Vec<(f64, f64)>> {
    let mut runs: Vec<Vec<(f64, f64)>> = Vec::new();
    let mut cur: Vec<(f64, f64)> = Vec::new();
    for (k, y) in v.iter().enumerate() {
        let x = (first + k) as f64;
        match y {
            Some(y) if y.is_finite() => {
                cur.push((x - 0.5, *y));
                cur.push((x + 0.5, *y));
            }
            _ => {
                if !cur.is_empty() {
                    runs.push(std::mem::take(&mut cur));
                }
            }
        }
    }
    if !cur.is_empty() {
        runs.push(cur);
    }
    runs
}

/// The grid, the axes and their names of one panel of `n` boards.
fn mesh<DB: DrawingBackend>(
    c: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    n: usize,
    y_desc: &str,
    x_desc: Option<&str>,
) -> Result<(), PlotError>
where
    DB::ErrorType: 'static,
{
    let mut m = c.configure_mesh();
    m.y_desc(y_desc)
        .x_labels(x_labels(n))
        .x_label_formatter(&whole)
        .light_line_style(WHITE.mix(0.0))
        .label_style(("sans-serif", 15))
        .axis_desc_style(("sans-serif", 16));
    if let Some(x) = x_desc {
        m.x_desc(x);
    }
    m.draw().map_err(err)
}

fn paint<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    chart: &Chart,
    rules: &[Rule],
    caption: &Caption,
) -> Result<(), PlotError>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE).map_err(err)?;
    let root = root.margin(10, 4, 4, 4);
    let root = root
        .titled(&caption.title, ("sans-serif", 24))
        .map_err(err)?;
    let (top, bottom) = root.split_vertically(SIZE.1 as i32 * 58 / 100);
    let n = chart.points.len();
    let x_range = 0.5f64..(n as f64 + 0.5);
    // The upper chart: points, centre, limits.
    let (lo, hi) = span(chart.points.iter().chain(&chart.lcl).chain(&chart.ucl));
    let mut c = ChartBuilder::on(&top)
        .margin(12)
        .x_label_area_size(30)
        .y_label_area_size(80)
        .build_cartesian_2d(x_range.clone(), lo..hi)
        .map_err(err)?;
    let upper_name = match chart.kind {
        Kind::IndividualsMovingRange => "individual values",
        Kind::MeanDeviation => "board means",
    };
    mesh(
        &mut c,
        n,
        &format!("{} ({upper_name})", caption.y_label),
        None,
    )?;
    let limit_style = ShapeStyle::from(&RED).stroke_width(2);
    for (k, line) in [&chart.ucl, &chart.lcl].into_iter().enumerate() {
        let v: Vec<Option<f64>> = line.iter().map(|&y| Some(y)).collect();
        let name = if k == 0 { "UCL" } else { "LCL" };
        let label = match (line.first(), line.iter().all(|&y| Some(&y) == line.first())) {
            (Some(y), true) => format!("{name} {y:.2}"),
            _ => format!("{name} (by board size)"),
        };
        for (r, run) in steps(&v, 1).into_iter().enumerate() {
            let drawn = c
                .draw_series(LineSeries::new(run, limit_style))
                .map_err(err)?;
            if r == 0 && k == 0 {
                drawn
                    .label(label.clone())
                    .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED));
            } else if r == 0 {
                drawn
                    .label(label.clone())
                    .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.mix(0.0)));
            }
        }
    }
    c.draw_series(LineSeries::new(
        [(0.5, chart.centre), (n as f64 + 0.5, chart.centre)],
        ShapeStyle::from(&GREEN.mix(0.9)).stroke_width(2),
    ))
    .map_err(err)?
    .label(if chart.baseline < n {
        format!("centre {:.2} (boards 1-{})", chart.centre, chart.baseline)
    } else {
        format!("centre {:.2}", chart.centre)
    })
    .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], GREEN));
    let pts: Vec<(f64, f64)> = chart
        .points
        .iter()
        .enumerate()
        .map(|(k, &y)| ((k + 1) as f64, y))
        .collect();
    c.draw_series(LineSeries::new(
        pts.clone(),
        ShapeStyle::from(&BLUE).stroke_width(1),
    ))
    .map_err(err)?;
    c.draw_series(pts.iter().map(|&p| Circle::new(p, 3, BLUE.filled())))
        .map_err(err)?;
    // The end of the baseline the limits come from.
    if chart.baseline < n {
        let xb = chart.baseline as f64 + 0.5;
        let dash = ShapeStyle::from(&BLACK.mix(0.6)).stroke_width(1);
        let (mut y, step) = (lo, (hi - lo) / 40.0);
        while y < hi {
            c.draw_series(LineSeries::new(
                [(xb, y), (xb, (y + step * 0.6).min(hi))],
                dash,
            ))
            .map_err(err)?;
            y += step;
        }
        c.draw_series([Text::new(
            "baseline | judged",
            (xb, hi),
            ("sans-serif", 13)
                .into_font()
                .color(&BLACK.mix(0.7))
                .pos(Pos::new(HPos::Center, VPos::Top)),
        )])
        .map_err(err)?;
    }
    // Fired points: ringed; the rules named where each starts firing (not again while it
    // goes on, which would only pile the names up).
    let mut fired = vec![false; n];
    let mut starts: Vec<Vec<&'static str>> = vec![Vec::new(); n];
    for &r in rules {
        let at = fires(r, &chart.points, &chart.z);
        for (k, &i) in at.iter().enumerate() {
            fired[i] = true;
            if k == 0 || at[k - 1] + 1 != i {
                starts[i].push(r.id());
            }
        }
    }
    for i in (0..n).filter(|&i| fired[i]) {
        let p = pts[i];
        c.draw_series([Circle::new(p, 7, ShapeStyle::from(&RED).stroke_width(2))])
            .map_err(err)?;
        // Names below a point under the centre, above one over it, stacked.
        let below = p.1 < chart.centre;
        for (k, id) in starts[i].iter().enumerate() {
            let off = 12 + 14 * k as i32;
            let dy = if below { off } else { -off - 10 };
            c.plotting_area()
                .draw(
                    &(EmptyElement::at(p)
                        + Text::new(*id, (-8, dy), ("sans-serif", 13).into_font().color(&RED))),
                )
                .map_err(err)?;
        }
    }
    c.configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .position(emptiest_corner(&pts, n, lo, hi))
        .draw()
        .map_err(err)?;
    // The lower chart.
    let d = &chart.dispersion;
    let first = match chart.kind {
        Kind::IndividualsMovingRange => 2,
        Kind::MeanDeviation => 1,
    };
    let flat: Vec<f64> = d
        .points
        .iter()
        .chain(&d.ucl)
        .chain(&d.lcl)
        .flatten()
        .copied()
        .collect();
    let (lo, hi) = span(flat.iter());
    let mut c = ChartBuilder::on(&bottom)
        .margin(12)
        .x_label_area_size(44)
        .y_label_area_size(80)
        .build_cartesian_2d(x_range, lo.min(0.0)..hi)
        .map_err(err)?;
    let lower_name = match chart.kind {
        Kind::IndividualsMovingRange => "moving range",
        Kind::MeanDeviation => "board standard deviation",
    };
    let x_desc = format!("board, oldest to newest ({})", caption.x_label);
    mesh(&mut c, n, lower_name, Some(&x_desc))?;
    for line in [&d.ucl, &d.lcl] {
        for run in steps(line, first) {
            c.draw_series(LineSeries::new(run, limit_style))
                .map_err(err)?;
        }
    }
    for run in steps(&d.centre, first) {
        c.draw_series(LineSeries::new(
            run,
            ShapeStyle::from(&GREEN.mix(0.9)).stroke_width(2),
        ))
        .map_err(err)?;
    }
    let dp: Vec<(f64, f64)> = d
        .points
        .iter()
        .enumerate()
        .filter_map(|(k, y)| y.map(|y| ((first + k) as f64, y)))
        .collect();
    c.draw_series(LineSeries::new(
        dp.clone(),
        ShapeStyle::from(&BLUE).stroke_width(1),
    ))
    .map_err(err)?;
    c.draw_series(dp.iter().map(|&p| Circle::new(p, 3, BLUE.filled())))
        .map_err(err)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capability::SpecLimits;
    use crate::chart::individuals;

    /// A chart with a point beyond its limits draws to both files: the PNG decodes to the
    /// chart's size with red (limits, the ringed point) and blue (points) in it, and the SVG
    /// names the rule that fired.
    #[test]
    fn a_chart_draws_to_svg_and_png() {
        let mut x: Vec<f64> = (0..30).map(|i| 100.0 + ((i * 7) % 5) as f64).collect();
        x[20] = 130.0;
        let c = individuals(&x, SpecLimits::default(), None).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let (svg, png) = (dir.path().join("c.svg"), dir.path().join("c.png"));
        let cap = Caption {
            title: "pad R1-1 · volume".into(),
            y_label: "volume, % of nominal".into(),
            x_label: "0000000000000001 to 000000000000001e".into(),
        };
        draw(&c, &[Rule::We1], &cap, Some(&svg), Some(&png)).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.contains("WE1") && text.contains("pad R1-1"));
        let img = image::open(&png).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), SIZE);
        let red = img
            .pixels()
            .filter(|p| p[0] > 200 && p[1] < 60 && p[2] < 60)
            .count();
        let blue = img
            .pixels()
            .filter(|p| p[2] > 200 && p[0] < 60 && p[1] < 60)
            .count();
        assert!(red > 500 && blue > 100, "red {red} blue {blue}");
        // Text was drawn (dark pixels of the title and labels).
        let dark = img
            .pixels()
            .filter(|p| p[0] < 80 && p[1] < 80 && p[2] < 80)
            .count();
        assert!(dark > 2000, "dark {dark}");
    }
}
