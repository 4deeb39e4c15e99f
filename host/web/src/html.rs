//! The pages' HTML: escaping, the frame every page shares, numbers and times, and the pad
//! history's chart (inline SVG with presentation attributes only: the Content-Security-Policy
//! allows no inline style).

use std::fmt::Write;

/// The site's one style sheet (`/style.css`).
pub const STYLE: &str = "\
body { font: 15px/1.4 system-ui, sans-serif; margin: 0 1.5em 2em; color: #1d232a; }
header { border-bottom: 1px solid #ccd; padding: .6em 0; margin-bottom: 1em; }
header a { font-weight: 600; text-decoration: none; color: #1d232a; }
h1 { font-size: 1.4em; margin: .4em 0; }
h2 { font-size: 1.1em; margin: 1.4em 0 .4em; }
table { border-collapse: collapse; }
th, td { padding: .25em .7em; border-bottom: 1px solid #e3e6ea; text-align: right; }
th { background: #f3f5f7; }
td.t, th.t { text-align: left; }
.pass { color: #17753a; } .warn { color: #9a6700; font-weight: 600; }
.fail { color: #b42318; font-weight: 700; } .incomplete { color: #5b2bb0; font-weight: 600; }
.figures span { display: inline-block; margin-right: 2em; }
.figures b { font-size: 1.3em; }
.note { color: #57606a; }
.board svg { max-width: 100%; height: auto; }
img.chart { max-width: 100%; height: auto; border: 1px solid #e3e6ea; }
header a.nav { font-weight: 400; margin-left: 1.5em; }
.pictures { display: flex; flex-wrap: wrap; gap: 1.5em; align-items: flex-start; }
image.crop { image-rendering: pixelated; }
form.review { display: flex; flex-wrap: wrap; gap: .8em; align-items: center; margin: .8em 0; }
form.review input { font: inherit; padding: .2em .4em; }
form.review button { font: inherit; padding: .3em 1em; cursor: pointer; }
.maptools button { font: inherit; min-width: 2.2em; padding: .2em .6em; margin-right: .4em; cursor: pointer; }
.maptools span { margin-left: 1em; color: #57606a; }
.mapframe { position: relative; overflow: hidden; height: 620px; max-width: 1200px; background: #1f2a36; cursor: grab; touch-action: none; user-select: none; }
.mapframe.dragging { cursor: grabbing; }
.maptiles img { position: absolute; max-width: none; }
.maptiles.pixels img { image-rendering: pixelated; }
a.mapcall { position: absolute; width: 18px; height: 18px; margin: -11px 0 0 -11px; border: 2px solid #d4a017; border-radius: 50%; }
a.mapcall.fail { border-color: #ff4d4f; }
a.mapcall span { position: absolute; left: 20px; top: -4px; white-space: nowrap; font-size: 12px; color: #fff; background: rgba(31, 42, 54, .75); padding: 0 .3em; }
a.mapcall:hover span { background: #1f2a36; text-decoration: underline; }
a.mapcall.nolabel span { display: none; }
a.mapcall.nolabel:hover span { display: inline; z-index: 1; }
.mapfoot { display: flex; align-items: flex-start; gap: 2em; margin: .4em 0; }
#map-scale { display: inline-block; border-bottom: 3px solid #1d232a; text-align: center; font-size: 12px; }
#map-at { color: #57606a; font-size: 13px; min-width: 14em; }
";

/// The site's icon (`/icon.svg`): a deposit of paste on a pad.
pub const ICON: &str = "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"0 0 16 16\">\
<rect x=\"1\" y=\"11\" width=\"14\" height=\"3\" fill=\"#b08d57\"/>\
<path d=\"M3 11 Q4 4 8 4 Q12 4 13 11 Z\" fill=\"#8a8f98\"/></svg>";

/// `text` with `& < > " '` escaped, for element content and quoted attributes.
pub fn esc(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// A whole page: `title` (escaped here) and `body` (HTML, escaped by the caller).
pub fn frame(title: &str, body: &str) -> String {
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <title>{t} - dpsa</title><link rel=\"stylesheet\" href=\"/style.css\">\
         <link rel=\"icon\" type=\"image/svg+xml\" href=\"/icon.svg\"></head>\
         <body><header><a href=\"/\">dpsa: the line</a> <a class=\"nav\" href=\"/spc\">SPC</a>\
         </header><h1>{t}</h1>\n{body}\n\
         </body></html>\n",
        t = esc(title)
    )
}

/// `v` with `digits` decimals, `-` for none or NaN.
pub fn num(v: Option<f64>, digits: usize) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x:.digits$}"),
        _ => "-".to_owned(),
    }
}

/// Unix seconds as `YYYY-MM-DD HH:MM:SS` UTC (`-` for a time that is not one).
pub fn time(unix_s: f64) -> String {
    if !unix_s.is_finite() || unix_s.abs() > 1e12 {
        return "-".to_owned();
    }
    let [y, m, d, h, mi, s] = dpsa_formats::time::utc(unix_s.floor() as i64);
    format!("{y:04}-{m:02}-{d:02} {h:02}:{mi:02}:{s:02}")
}

/// The CSS class of a level or state: `pass`, `warn`, `fail`, `incomplete`, else none.
pub fn class(level: &str) -> &'static str {
    match level {
        "pass" => "pass",
        "warn" => "warn",
        "fail" => "fail",
        "incomplete" => "incomplete",
        _ => "",
    }
}

/// A pad's history as a chart: `points` oldest first (`None`: not measured), the one at
/// `mark` drawn larger; a dashed line at each of `lines` (e.g. the fail window).
pub fn history_svg(points: &[Option<f64>], mark: Option<usize>, lines: &[f64]) -> String {
    let (w, h, left, bottom, top) = (640.0, 220.0, 48.0, 24.0, 10.0);
    let vals: Vec<f64> = points
        .iter()
        .flatten()
        .copied()
        .chain(lines.iter().copied())
        .collect();
    let (lo, hi) = vals
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        return "<p class=\"note\">No measured value to chart.</p>".to_owned();
    }
    let pad = ((hi - lo) * 0.1).max(1.0);
    let (lo, hi) = (lo - pad, hi + pad);
    let n = points.len().max(2) as f64;
    let x = |i: usize| left + (w - left - 8.0) * i as f64 / (n - 1.0);
    let y = |v: f64| top + (h - top - bottom) * (hi - v) / (hi - lo);
    let mut s = String::new();
    let _ = write!(
        s,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" \
         viewBox=\"0 0 {w} {h}\" role=\"img\" aria-label=\"history\">\
         <rect x=\"{left}\" y=\"{top}\" width=\"{}\" height=\"{}\" fill=\"#fafbfc\" \
         stroke=\"#ccd\"/>",
        w - left - 8.0,
        h - top - bottom
    );
    for k in 0..=4 {
        let v = lo + (hi - lo) * k as f64 / 4.0;
        let _ = write!(
            s,
            "<text x=\"{}\" y=\"{:.1}\" font-size=\"11\" text-anchor=\"end\" fill=\"#57606a\">\
             {v:.1}</text>",
            left - 4.0,
            y(v) + 4.0
        );
    }
    for &l in lines {
        let _ = write!(
            s,
            "<line x1=\"{left}\" x2=\"{}\" y1=\"{:.1}\" y2=\"{:.1}\" stroke=\"#b42318\" \
             stroke-dasharray=\"5 4\"/>",
            w - 8.0,
            y(l),
            y(l)
        );
    }
    let mut path = String::new();
    for (i, v) in points.iter().enumerate() {
        if let Some(v) = v {
            let _ = write!(
                path,
                "{}{:.1},{:.1}",
                if path.is_empty() { "M" } else { " L" },
                x(i),
                y(*v)
            );
        }
    }
    let _ = write!(
        s,
        "<path d=\"{path}\" fill=\"none\" stroke=\"#1f6feb\" stroke-width=\"1.5\"/>"
    );
    for (i, v) in points.iter().enumerate() {
        if let Some(v) = v {
            let r = if Some(i) == mark { 5.0 } else { 2.5 };
            let c = if Some(i) == mark {
                "#b42318"
            } else {
                "#1f6feb"
            };
            let _ = write!(
                s,
                "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"{r}\" fill=\"{c}\"/>",
                x(i),
                y(*v)
            );
        }
    }
    let _ = write!(
        s,
        "<text x=\"{left}\" y=\"{}\" font-size=\"11\" fill=\"#57606a\">oldest</text>\
         <text x=\"{}\" y=\"{}\" font-size=\"11\" text-anchor=\"end\" fill=\"#57606a\">newest\
         </text></svg>",
        h - 6.0,
        w - 8.0,
        h - 6.0
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_is_escaped() {
        assert_eq!(esc("R1-<b>&\"x'"), "R1-&lt;b&gt;&amp;&quot;x&#39;");
        assert!(frame("<t>", "").contains("<title>&lt;t&gt; - dpsa</title>"));
    }

    /// Against dates known by hand.
    #[test]
    fn times_are_utc_dates() {
        assert_eq!(time(0.0), "1970-01-01 00:00:00");
        assert_eq!(time(951_782_400.0), "2000-02-29 00:00:00");
        assert_eq!(time(1_700_000_000.5), "2023-11-14 22:13:20");
        assert_eq!(time(-86_400.0), "1969-12-31 00:00:00");
        assert_eq!(time(f64::NAN), "-");
    }

    #[test]
    fn a_history_without_values_says_so() {
        assert!(history_svg(&[None, None], None, &[]).contains("No measured value"));
        let s = history_svg(&[Some(100.0), None, Some(90.0)], Some(2), &[50.0, 150.0]);
        assert_eq!(s.matches("<circle").count(), 2);
        assert_eq!(s.matches("stroke-dasharray").count(), 2);
        assert!(!s.contains("style="));
    }
}
