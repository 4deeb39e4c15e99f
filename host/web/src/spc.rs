//! The SPC page (`/spc`, `/spc/PRODUCT`): `dpsa spc`'s study of a product's newest
//! [`SPC_BOARDS`] inspected boards on the line, as a process engineer reads it: the open
//! alarms (which rule, which scope, since which board, which pads pull it), the board's and
//! the print's charts with their capability, the package families and the components of
//! lowest volume capability, the stencil's recommendation. The same statistics as `dpsa spc`
//! (`dpsa_spc`: tested against numpy), with its default rules and alarm policy; the program
//! (limits, families) is the one whose hash the newest board carries, of those the pages were
//! given.
//!
//! A study reads every pad of every board in it, so it is kept ([`Cache`]) until a newer
//! board of the product is stored; the charts (PNG, `/spc/PRODUCT/chart/...`) are drawn from
//! the kept study.

use crate::html::{esc, frame, num, time};
use crate::Site;
use dpsa_line::store::Store;
use dpsa_spc::load::{Loaded, Source};
use dpsa_spc::study::{analyse, Metric, Options, Report, ScopeKind, Series};
use std::fmt::Write;
use std::sync::{Arc, Mutex};

/// Boards a study takes, the newest.
pub const SPC_BOARDS: usize = 100;

/// Components listed, lowest volume `Cpk` first.
pub const WORST_COMPONENTS: usize = 20;

/// The newest study made: its product, the newest board in it, the study and its report; and
/// whether a newer one is being made for the line page ([`open_alarms`]).
#[derive(Default)]
pub struct Cache(Mutex<Option<Kept>>, std::sync::atomic::AtomicBool);

/// A kept study: its product, the newest board in it, the study and its report.
type Kept = (String, i64, Arc<(Loaded, Report)>);

impl std::fmt::Debug for Cache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Cache")
    }
}

/// Why the SPC page could not be made.
#[derive(Debug, thiserror::Error)]
pub enum SpcError {
    /// The store.
    #[error(transparent)]
    Store(#[from] dpsa_line::store::StoreError),
    /// The study (too few boards, too large ...).
    #[error(transparent)]
    Load(#[from] dpsa_spc::load::LoadError),
    /// A chart could not be drawn.
    #[error(transparent)]
    Plot(#[from] dpsa_spc::plot::PlotError),
}

/// `text` for a URL's path segment: letters, digits and `-_.` as they are, the rest
/// percent-encoded.
pub fn segment(text: &str) -> String {
    let mut out = String::new();
    for b in text.bytes() {
        if b.is_ascii_alphanumeric() || b"-_.".contains(&b) {
            out.push(b as char);
        } else {
            let _ = write!(out, "%{b:02X}");
        }
    }
    out
}

/// The study of `product` (the newest inspected board's when `None`): kept, or made.
fn study(site: &Site, product: Option<&str>) -> Result<Option<Arc<(Loaded, Report)>>, SpcError> {
    let mut store = Store::open_read_only(&site.store, &site.line)?;
    let Some(newest) = store.inspected_boards(product, 1)?.into_iter().next() else {
        return Ok(None);
    };
    let mut cache = site.spc.0.lock().unwrap_or_else(|p| p.into_inner());
    if let Some((p, id, s)) = cache.as_ref() {
        if *p == newest.product && *id == newest.id {
            return Ok(Some(s.clone()));
        }
    }
    let program = site.designs.path(&newest.program_hash);
    let loaded = dpsa_spc::load::load(&Source {
        store: &site.store,
        line: &site.line,
        product: Some(&newest.product),
        program,
        last: SPC_BOARDS,
        read_only: true,
    })?;
    let report = analyse(
        &loaded.study,
        &loaded.product,
        &Options::with_default_policy(),
    );
    let s = Arc::new((loaded, report));
    *cache = Some((newest.product.clone(), newest.id, s.clone()));
    Ok(Some(s))
}

/// The open alarms the line page shows: those of the newest study made.
#[derive(Clone, Debug)]
pub struct Seen {
    /// The study's product.
    pub product: String,
    /// The newest board in the study (run id).
    pub upto_run_id: String,
    /// Its open alarms.
    pub open: Vec<dpsa_spc::study::Alarm>,
    /// Whether a newer board than the study's is stored (a newer study is being made).
    pub behind: bool,
}

/// The open alarms of the newest inspected board's product, from the kept study, without
/// waiting for one: a study of the paper board's 100 boards takes most of a second, and a line
/// stores a board a second. When the kept study is older than the newest board (or there is
/// none), a newer one is made in a thread of its own and the page shows the kept one, marked
/// as behind.
pub fn open_alarms(site: &Site) -> Result<LineAlarms, SpcError> {
    Ok(match kept_now(site, None)? {
        None => LineAlarms::NoBoard,
        Some((None, _)) => LineAlarms::Making,
        Some((Some((product, s)), current)) => {
            let report = &s.1;
            LineAlarms::Seen(Seen {
                product,
                upto_run_id: report
                    .boards
                    .last()
                    .map(|b| b.run_id.clone())
                    .unwrap_or_default(),
                open: report.alarms.iter().filter(|a| a.open).cloned().collect(),
                behind: !current,
            })
        }
    })
}

/// The kept study of `product` (the newest inspected board's when `None`), without waiting
/// for one: the kept study when it is of that product, and whether it ends on the product's
/// newest board. When it does not, a newer one is made in a thread of its own (one at a
/// time). `None`: no inspected board of the product.
#[allow(clippy::type_complexity)]
fn kept_now(
    site: &Site,
    product: Option<&str>,
) -> Result<Option<(Option<(String, Arc<(Loaded, Report)>)>, bool)>, SpcError> {
    use std::sync::atomic::Ordering;
    let mut store = Store::open_read_only(&site.store, &site.line)?;
    let Some(newest) = store.inspected_boards(product, 1)?.into_iter().next() else {
        return Ok(None);
    };
    let kept = site.spc.0.lock().unwrap_or_else(|p| p.into_inner()).clone();
    let current = kept
        .as_ref()
        .is_some_and(|(p, id, _)| *p == newest.product && *id == newest.id);
    if !current && !site.spc.1.swap(true, Ordering::AcqRel) {
        let site = site.clone();
        let product = newest.product.clone();
        std::thread::spawn(move || {
            if let Err(e) = study(&site, Some(&product)) {
                tracing::warn!("spc study for the pages: {e}");
            }
            site.spc.1.store(false, Ordering::Release);
        });
    }
    let kept = kept
        .filter(|(p, _, _)| *p == newest.product)
        .map(|(p, _, s)| (p, s));
    Ok(Some((kept, current)))
}

/// What the pad page can say of the pad's SPC chart.
#[derive(Clone, Debug)]
pub enum PadSpc {
    /// No study of the product is made yet (one is being made).
    Making,
    /// The study has no volume chart of the pad (too few boards, no spread, no such pad).
    None,
    /// The pad's volume series in the newest study, its chart's path, and whether newer
    /// boards are stored than the study's.
    Seen(Box<Series>, String, bool),
}

/// Pad `name`'s volume chart in the newest study of `product`, without waiting for one (a
/// newer study made in a thread of its own when the kept one is behind, as for the line page).
pub fn pad_chart(site: &Site, product: &str, name: &str) -> Result<PadSpc, SpcError> {
    Ok(match kept_now(site, Some(product))? {
        None => PadSpc::None,
        Some((None, _)) => PadSpc::Making,
        Some((Some((p, s)), current)) => {
            let pads = &s.1.pads;
            match pads
                .iter()
                .position(|x| x.name == name && x.metric == Metric::Volume && x.note.is_none())
            {
                Some(k) => PadSpc::Seen(
                    Box::new(pads[k].clone()),
                    chart_href(&p, ScopeKind::Pad, k, Metric::Volume),
                    !current,
                ),
                None => PadSpc::None,
            }
        }
    })
}

/// What the line page can say of the open alarms.
#[derive(Clone, Debug)]
pub enum LineAlarms {
    /// No inspected board is stored.
    NoBoard,
    /// No study is made yet (one is being made).
    Making,
    /// The newest study's.
    Seen(Seen),
}

/// Waits until no study for the line page is being made (tests).
pub fn settle(site: &Site) {
    while site.spc.1.load(std::sync::atomic::Ordering::Acquire) {
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
}

fn idx(v: Option<f64>) -> String {
    num(v, 2)
}

/// A table of series: the scope's name (when `named`), the measure, its figures.
fn series_table(
    out: &mut String,
    list: &[&Series],
    named: bool,
    chart: impl Fn(&Series) -> Option<String>,
) {
    out.push_str("<table><tr>");
    if named {
        out.push_str("<th class=\"t\">name</th><th>pads</th>");
    }
    out.push_str(
        "<th class=\"t\">measure</th><th>boards</th><th>mean</th><th>sigma within</th>\
         <th>sigma overall</th><th>limits</th><th>Cp</th><th>Cpk</th><th>Pp</th><th>Ppk</th>\
         <th class=\"t\">rules fired</th><th class=\"t\">chart</th></tr>",
    );
    for s in list {
        out.push_str("<tr>");
        if named {
            let _ = write!(
                out,
                "<td class=\"t\">{}</td><td>{}</td>",
                esc(&s.name),
                s.pads
            );
        }
        let fired: Vec<String> = s
            .firings
            .iter()
            .map(|(r, n)| format!("{} x{n}", r.id()))
            .collect();
        let _ = write!(
            out,
            "<td class=\"t\">{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td>\
             <td>{}</td><td>{}</td><td>{}</td><td>{}</td><td class=\"t\">{}</td>\
             <td class=\"t\">{}</td></tr>",
            esc(s.metric.label()),
            s.points,
            num(s.mean, 2),
            num(s.sigma_within, 3),
            num(s.sigma_overall, 3),
            s.limits.map_or("-".to_owned(), |l| format!(
                "{} .. {}",
                num(l.lsl, 1),
                num(l.usl, 1)
            )),
            idx(s.cp.p),
            idx(s.cp.k),
            idx(s.pp.p),
            idx(s.pp.k),
            esc(&fired.join(", ")),
            chart(s).map_or_else(
                || esc(s.note.as_deref().unwrap_or("-")),
                |href| format!("<a href=\"{href}\">chart</a>")
            ),
        );
    }
    out.push_str("</table>");
}

/// The link to a series' chart: `all` is the report's list of `kind` it is in (none for a
/// series without a chart).
fn link<'a>(
    all: &'a [Series],
    kind: ScopeKind,
    product: &'a str,
) -> impl Fn(&Series) -> Option<String> + 'a {
    move |s| {
        all.iter()
            .position(|b| b == s)
            .filter(|_| s.note.is_none())
            .map(|k| chart_href(product, kind, k, s.metric))
    }
}

/// The path of a chart: the series `k` of `kind`'s list in the report.
fn chart_href(product: &str, kind: ScopeKind, k: usize, m: Metric) -> String {
    format!(
        "/spc/{}/chart/{}/{k}/{}.png",
        segment(product),
        kind.id(),
        m.id()
    )
}

/// The SPC page of `product` (the newest board's when `None`); `None`: no such product.
pub fn page(site: &Site, product: Option<&str>) -> Result<Option<String>, SpcError> {
    let Some(s) = study(site, product)? else {
        if product.is_some() {
            return Ok(None);
        }
        return Ok(Some(frame(
            "SPC",
            "<p class=\"note\">No inspected board stored yet.</p>",
        )));
    };
    let (loaded, report) = &*s;
    let p = &loaded.product;
    let mut body = String::new();
    let (first, last) = (report.boards.first(), report.boards.last());
    let _ = write!(
        body,
        "<p class=\"figures\"><span>product <b>{}</b></span><span>boards <b>{}</b></span>\
         <span>from {} to {} UTC</span></p><p class=\"note\">The newest {} inspected boards of \
         the product on line {} under program {} ({}); rules: Western Electric's, alarms: {}; \
         centres and limits from the study's first {} boards.{}</p>",
        esc(p),
        report.boards.len(),
        first.map_or("-".to_owned(), |b| time(b.started_unix_s)),
        last.map_or("-".to_owned(), |b| time(b.started_unix_s)),
        SPC_BOARDS,
        esc(&site.line),
        esc(&loaded.program_hash),
        if loaded.with_program {
            "its limits and families"
        } else {
            "not given to the pages: no limits, no families"
        },
        dpsa_spc::study::DEFAULT_POLICY,
        report.baseline.map_or("every".to_owned(), |b| b
            .min(report.boards.len())
            .to_string()),
        if loaded.pruned > 0 {
            format!(
                " {} boards left out: their pad rows were pruned.",
                loaded.pruned
            )
        } else {
            String::new()
        }
    );
    if let Some(k) = report
        .board
        .iter()
        .position(|s| s.metric == Metric::Volume && s.note.is_none())
    {
        let _ = write!(
            body,
            "<p><img class=\"chart\" src=\"{}\" alt=\"the board's volume chart\"></p>",
            chart_href(p, ScopeKind::Board, k, Metric::Volume)
        );
    }
    // Alarms, open first.
    let open: Vec<_> = report.alarms.iter().filter(|a| a.open).collect();
    let _ = write!(body, "<h2>Open alarms ({})</h2>", open.len());
    if report.alarms.is_empty() {
        body.push_str("<p class=\"note\">No rule fired on a chart that raises alarms.</p>");
    } else {
        body.push_str(
            "<table><tr><th class=\"t\">state</th><th class=\"t\">scope</th><th class=\"t\">\
             measure</th><th class=\"t\">rule</th><th class=\"t\">since board</th><th class=\"t\">\
             first fired</th><th class=\"t\">last fired</th><th class=\"t\">pads pulling it\
             </th></tr>",
        );
        let mut list: Vec<_> = report.alarms.iter().collect();
        list.sort_by_key(|a| !a.open);
        // A board's run id, linked to its page.
        let board = |run: &str| match report.boards.iter().find(|b| b.run_id == run) {
            Some(b) => format!("<a href=\"/board/{}\">{}</a>", b.id, esc(run)),
            None => esc(run),
        };
        for a in list {
            let pads: Vec<String> = a
                .pads
                .iter()
                .map(|(n, v)| format!("{} {v:.1}", esc(n)))
                .collect();
            let _ = write!(
                body,
                "<tr><td class=\"t {c}\">{st}</td><td class=\"t\">{k} {n}</td><td class=\"t\">\
                 {m}</td><td class=\"t\">{r}: {rt}</td><td class=\"t\">{since}</td>\
                 <td class=\"t\">{ff}</td><td class=\"t\">{lf}</td><td class=\"t\">{pads}</td></tr>",
                c = if a.open { "fail" } else { "" },
                st = if a.open { "open" } else { "closed" },
                k = a.kind.id(),
                n = esc(&a.name),
                m = esc(a.metric.label()),
                r = a.rule.id(),
                rt = esc(a.rule_text),
                since = board(&a.since_run_id),
                ff = board(&a.first_fired_run_id),
                lf = board(&a.last_fired_run_id),
                pads = pads.join(", "),
            );
        }
        body.push_str("</table>");
    }
    // The board and the print, with their main charts shown.
    body.push_str("<h2>The board (every pad, the board as the subgroup)</h2>");
    let board: Vec<&Series> = report.board.iter().collect();
    series_table(
        &mut body,
        &board,
        false,
        link(&report.board, ScopeKind::Board, p),
    );
    if !report.print.is_empty() {
        body.push_str("<h2>The print's placement</h2>");
        let print: Vec<&Series> = report.print.iter().collect();
        series_table(
            &mut body,
            &print,
            false,
            link(&report.print, ScopeKind::Print, p),
        );
    }
    // Families and the components of lowest volume capability.
    let fam: Vec<&Series> = report
        .families
        .iter()
        .filter(|s| s.metric == Metric::Volume)
        .collect();
    if !fam.is_empty() {
        body.push_str("<h2>Package families: volume</h2>");
        series_table(
            &mut body,
            &fam,
            true,
            link(&report.families, ScopeKind::Family, p),
        );
    }
    let mut comps: Vec<&Series> = report
        .components
        .iter()
        .filter(|s| s.metric == Metric::Volume && s.cp.k.is_some())
        .collect();
    comps.sort_by(|a, b| a.cp.k.unwrap_or(0.0).total_cmp(&b.cp.k.unwrap_or(0.0)));
    comps.truncate(WORST_COMPONENTS);
    if !comps.is_empty() {
        let _ = write!(
            body,
            "<h2>Components of lowest volume Cpk ({} shown)</h2>",
            comps.len()
        );
        series_table(
            &mut body,
            &comps,
            true,
            link(&report.components, ScopeKind::Component, p),
        );
    }
    if let Some(c) = &report.stencil {
        let _ = write!(
            body,
            "<h2>The stencil</h2><p><b class=\"{}\">{}</b>: {}</p>",
            if c.recommend { "warn" } else { "pass" },
            if c.recommend {
                "clean it"
            } else {
                "no clean needed"
            },
            esc(&c.reasons.join("; "))
        );
    }
    Ok(Some(frame(&format!("SPC: {p}"), &body)))
}

/// The chart of the `k`-th series of `kind` in `product`'s study, as PNG; `None`: no such
/// series (or no chart for it).
pub fn chart_png(
    site: &Site,
    product: &str,
    kind: &str,
    k: usize,
    metric: &str,
) -> Result<Option<Vec<u8>>, SpcError> {
    let Some(s) = study(site, Some(product))? else {
        return Ok(None);
    };
    let (loaded, report) = &*s;
    let Some(kind) = ScopeKind::from_id(kind) else {
        return Ok(None);
    };
    let list = match kind {
        ScopeKind::Board => &report.board,
        ScopeKind::Print => &report.print,
        ScopeKind::Family => &report.families,
        ScopeKind::Component => &report.components,
        ScopeKind::Pad => &report.pads,
    };
    let Some(series) = list.get(k).filter(|s| s.metric.id() == metric) else {
        return Ok(None);
    };
    let study = &loaded.study;
    let members = study.members(kind, &series.name);
    let (chart, _, _) = study.chart(kind, &members, series.metric, report.baseline);
    let Ok(chart) = chart else {
        return Ok(None);
    };
    let (first, last) = match (study.boards().first(), study.boards().last()) {
        (Some(a), Some(b)) => (a.run_id.clone(), b.run_id.clone()),
        _ => return Ok(None),
    };
    let caption = dpsa_spc::plot::Caption {
        title: format!(
            "{} {} · {} · Cp {} · Cpk {}",
            kind.id(),
            series.name,
            series.metric.label(),
            idx(chart.cp.p),
            idx(chart.cp.k)
        ),
        y_label: series.metric.label().to_owned(),
        x_label: format!("{first} to {last}"),
    };
    Ok(Some(dpsa_spc::plot::png_bytes(
        &chart,
        &report.rules,
        &caption,
    )?))
}
