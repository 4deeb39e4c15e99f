//! The pages: what each reads from the store (opened read-only for the page) and its layout.

use crate::html::{class, esc, frame, history_svg, num, time};
use crate::Site;
use dpsa_line::store::{PadRow, Review, Store, StoreError, StoredBoard, StoredPrint};
use std::fmt::Write;

/// Why a page could not be made.
#[derive(Debug, thiserror::Error)]
pub enum PageError {
    /// The store.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// A pad's image could not be encoded.
    #[error("the pad's image could not be encoded: {0}")]
    Png(#[from] png::EncodingError),
}

/// Boards the line page lists.
pub const LINE_BOARDS: usize = 50;

/// Boards of a pad's history.
pub const HISTORY_BOARDS: usize = 100;

/// Print rows searched for a board's own (its product's newest).
const PRINT_ROWS: usize = 1000;

fn open(site: &Site) -> Result<Store, StoreError> {
    Store::open_read_only(&site.store, &site.line)
}

/// The board page's measured map (`tiles`, `mapview.js`): the viewer, the calls placed on
/// the map by the registration the line kept with it; or why there is none (said for an
/// inspected board only: an incomplete one has a map only when the design could not be
/// registered on it). Reads the map's description only: the pyramid is built when the viewer
/// asks for it.
#[allow(clippy::too_many_arguments)]
fn map_section(
    site: &Site,
    id: i64,
    run: &str,
    inspected: bool,
    program_hash: &str,
    pads: &[PadRow],
    body: &mut String,
) {
    let Some(dir) = &site.maps else { return };
    let k = match dpsa_formats::kept_map::read_meta(dir, &site.line, id) {
        // A map kept under this id by another store (another board): never shown as this one.
        Ok(Some(k)) if k.run_id != run => {
            let _ = write!(
                body,
                "<h2>The measured map</h2><p class=\"incomplete\">The map kept under this \
                 board's id is of another board (run {}): not shown.</p>",
                esc(&k.run_id)
            );
            return;
        }
        Ok(Some(k)) => k,
        Ok(None) if !inspected => return,
        Ok(None) => {
            body.push_str(
                "<h2>The measured map</h2><p class=\"note\">Not kept for this board: the line \
                 keeps its newest boards' maps only (LINE.toml's [maps] keep_boards), each \
                 written just after its board is stored (reload).</p>",
            );
            return;
        }
        Err(e) => {
            let _ = write!(
                body,
                "<h2>The measured map</h2><p class=\"incomplete\">The kept map cannot be read: \
                 {}</p>",
                esc(&e.to_string())
            );
            return;
        }
    };
    let g = &k.grid;
    let y_top = g.y0_mm + g.width as f64 * g.pitch_mm;
    let _ = write!(
        body,
        "<h2>The measured map</h2><div id=\"mapview\" class=\"mapview\" \
         data-map=\"/board/{id}/map/{run}/info.json\" data-tiles=\"/board/{id}/map/{run}/\">\
         <p class=\"maptools\">\
         <button type=\"button\" id=\"map-in\" title=\"zoom in\">+</button><button \
         type=\"button\" id=\"map-out\" title=\"zoom out\">&minus;</button><button \
         type=\"button\" id=\"map-fit\">whole board</button><span id=\"map-status\">loading \
         the map&hellip;</span></p><div id=\"mapframe\" class=\"mapframe\">"
    );
    let calls = k
        .design_to_board
        .and_then(|_| crate::board_view::call_centres(&site.designs, program_hash, pads));
    for (p, c) in calls.iter().flatten() {
        let Some(t) = &k.design_to_board else { break };
        let (x, y) = t.apply(c[0], c[1]);
        let (u, v) = ((x - g.x0_mm) / g.pitch_mm, (y_top - y) / g.pitch_mm);
        let label = format!(
            "{} {}",
            p.name,
            p.class.as_deref().unwrap_or(p.level.as_str())
        );
        let _ = write!(
            body,
            "<a class=\"mapcall {c}\" href=\"/board/{id}/pad/{k}\" data-u=\"{u:.1}\" \
             data-v=\"{v:.1}\" title=\"{t}\"><span>{t}</span></a>",
            c = class(&p.level),
            k = p.pad,
            t = esc(&label)
        );
    }
    let _ = write!(
        body,
        "</div><p class=\"mapfoot\"><canvas id=\"mapbar\" width=\"420\" height=\"44\">\
         </canvas><span id=\"map-scale\"></span><span id=\"map-at\"></span></p></div>\
         <p class=\"note\">The height above the local board surface (the bow and warp taken \
         out), as measured and kept by the line (board x to the right, y up): drag to pan, the \
         wheel or + and &minus; to zoom{calls}.</p><script src=\"{js}\"></script>",
        calls = match (&calls, &k.design_to_board) {
            (_, None) =>
                "; the design could not be registered on this map, so nothing is \
                          marked on it",
            (Some(c), _) if !c.is_empty() => {
                ", the calls ringed and linked to their pad's page"
            }
            (Some(_), _) => "",
            (None, _) => {
                "; the calls are not marked: the board's program was not given to the pages"
            }
        },
        js = crate::tiles::SCRIPT_PATH
    );
}

/// Whether board `id` of this line is stored with run id `run` (16 hex digits): what the map
/// routes check before they build a board's pyramid.
pub fn board_has_run(site: &Site, id: i64, run: &str) -> Result<bool, StoreError> {
    Ok(open(site)?
        .board(id)?
        .is_some_and(|b| format!("{:016x}", b.run_id) == run))
}

/// A pad's nominal height (the stencil's thickness), um: its height over its height in %.
fn nominal_um(p: &PadRow) -> Option<f64> {
    let (h, pct) = (p.height_um?, p.height_pct?);
    let n = h / pct * 100.0;
    (pct > 0.0 && n.is_finite() && n > 0.0).then_some(n)
}

/// A decision as a person reads it.
fn decision_text(r: &Review) -> &'static str {
    match r.decision {
        dpsa_line::store::Decision::Confirmed => "confirmed",
        dpsa_line::store::Decision::FalseCall => "false call",
    }
}

/// A board's result: its verdict, or `incomplete`, or `open`.
fn result(b: &StoredBoard) -> &str {
    b.verdict.as_deref().unwrap_or(b.state.as_str())
}

/// A pad's volume uncertainty in points of %: its um^3 over the nominal volume.
fn volume_u_pct(p: &PadRow) -> Option<f64> {
    let (u, v, pct) = (p.uncertainty_um3?, p.volume_um3?, p.volume_pct?);
    (v != 0.0).then(|| u * pct / v)
}

fn print_row(store: &mut Store, b: &StoredBoard) -> Result<Option<StoredPrint>, StoreError> {
    Ok(store
        .prints(&b.product, PRINT_ROWS)?
        .into_iter()
        .find(|r| r.board_id == b.id))
}

/// The open SPC alarms of the newest board's product (from the newest study made; see
/// [`crate::spc::open_alarms`]), linked to the SPC page.
fn open_alarms(site: &Site, body: &mut String) {
    match crate::spc::open_alarms(site) {
        Ok(crate::spc::LineAlarms::NoBoard) => {}
        Ok(crate::spc::LineAlarms::Seen(seen)) => {
            let href = format!("/spc/{}", crate::spc::segment(&seen.product));
            let _ = write!(
                body,
                "<h2>Open alarms ({n}, {p})</h2><p class=\"note\">From the <a href=\"{href}\">SPC \
                 study</a> up to board {upto}{behind}.</p>",
                n = seen.open.len(),
                p = esc(&seen.product),
                upto = esc(&seen.upto_run_id),
                behind = if seen.behind {
                    "; newer boards are stored and a newer study is being made (reload)"
                } else {
                    ""
                },
            );
            if !seen.open.is_empty() {
                body.push_str(
                    "<table><tr><th class=\"t\">scope</th><th class=\"t\">measure</th>\
                     <th class=\"t\">rule</th><th class=\"t\">since board</th>\
                     <th class=\"t\">pads pulling it</th></tr>",
                );
                for a in &seen.open {
                    let pads: Vec<String> = a.pads.iter().map(|(n, _)| esc(n)).collect();
                    let _ = write!(
                        body,
                        "<tr><td class=\"t fail\">{} {}</td><td class=\"t\">{}</td>\
                         <td class=\"t\">{}: {}</td><td class=\"t\">{}</td>\
                         <td class=\"t\">{}</td></tr>",
                        a.kind.id(),
                        esc(&a.name),
                        esc(a.metric.label()),
                        a.rule.id(),
                        esc(a.rule_text),
                        esc(&a.since_run_id),
                        pads.join(", "),
                    );
                }
                body.push_str("</table>");
            }
        }
        Ok(crate::spc::LineAlarms::Making) => body.push_str(
            "<h2>Open alarms</h2><p class=\"note\">The SPC study of the newest boards is being \
             made (reload).</p>",
        ),
        Err(e) => {
            let _ = write!(
                body,
                "<h2>Open alarms</h2><p class=\"note\">The SPC study could not be made: {}</p>",
                esc(&e.to_string())
            );
        }
    }
}

/// The pad's SPC chart (its volume, the board the subgroup, from the newest study of the
/// product; see [`crate::spc::pad_chart`]) with its capability.
fn pad_spc(site: &Site, product: &str, name: &str, body: &mut String) {
    body.push_str("<h2>SPC: the pad's volume chart</h2>");
    match crate::spc::pad_chart(site, product, name) {
        Ok(crate::spc::PadSpc::Seen(s, href, behind)) => {
            let _ = write!(
                body,
                "<p><img class=\"chart\" src=\"{href}\" alt=\"the pad's volume chart\"></p>\
                 <p class=\"figures\"><span>boards <b>{}</b></span><span>mean <b>{}</b> %</span>\
                 <span>Cp <b>{}</b></span><span>Cpk <b>{}</b></span><span>Pp <b>{}</b></span>\
                 <span>Ppk <b>{}</b></span></p><p class=\"note\">From the <a href=\"/spc/{}\">SPC \
                 study</a> of the product's newest boards{}.</p>",
                s.points,
                num(s.mean, 1),
                num(s.cp.p, 2),
                num(s.cp.k, 2),
                num(s.pp.p, 2),
                num(s.pp.k, 2),
                crate::spc::segment(product),
                if behind {
                    "; newer boards are stored and a newer study is being made (reload)"
                } else {
                    ""
                },
            );
        }
        Ok(crate::spc::PadSpc::Making) => body.push_str(
            "<p class=\"note\">The SPC study of the product's newest boards is being made \
             (reload).</p>",
        ),
        Ok(crate::spc::PadSpc::None) => body.push_str(
            "<p class=\"note\">The SPC study has no volume chart of this pad (too few boards, \
             or no spread).</p>",
        ),
        Err(e) => {
            let _ = write!(
                body,
                "<p class=\"note\">The SPC study could not be made: {}</p>",
                esc(&e.to_string())
            );
        }
    }
}

/// The line: its newest boards with their results, the yield and the throughput over them,
/// the printer's newest correction.
pub fn line(site: &Site) -> Result<String, PageError> {
    let mut store = open(site)?;
    let boards = store.boards(LINE_BOARDS)?;
    let mut body = String::new();
    let inspected: Vec<&StoredBoard> = boards.iter().filter(|b| b.state == "inspected").collect();
    let good = inspected
        .iter()
        .filter(|b| matches!(b.verdict.as_deref(), Some("pass" | "warn")))
        .count();
    let incomplete = boards.iter().filter(|b| b.state == "incomplete").count();
    let span = match (boards.last(), boards.first()) {
        (Some(a), Some(z)) if boards.len() > 1 => z.started_unix_s - a.started_unix_s,
        _ => f64::NAN,
    };
    let per_hour = (span > 0.0).then(|| (boards.len() - 1) as f64 * 3600.0 / span);
    let _ = write!(
        body,
        "<p class=\"figures\"><span>boards shown <b>{}</b></span>\
         <span>yield (pass or warn of inspected) <b>{}</b></span>\
         <span>incomplete <b>{incomplete}</b></span>\
         <span>throughput <b>{}</b> boards an hour</span></p>",
        boards.len(),
        if inspected.is_empty() {
            "-".to_owned()
        } else {
            format!("{:.1} %", 100.0 * good as f64 / inspected.len() as f64)
        },
        num(per_hour, 1),
    );
    if let Some(newest) = boards.first() {
        if let Some(p) = store.prints(&newest.product, 1)?.first() {
            let c = &p.print.proposal;
            let _ = write!(
                body,
                "<h2>The printer ({})</h2><p>Correction in force after board {:016x}: x {} um, \
                 y {} um, theta {} mdeg. {}</p>",
                esc(&newest.product),
                p.run_id,
                num(Some(c.correction.x_um), 1),
                num(Some(c.correction.y_um), 1),
                num(Some(c.correction.rotation_mdeg), 1),
                esc(&c.reason)
            );
        }
    }
    open_alarms(site, &mut body);
    body.push_str(
        "<h2>Newest boards</h2><table><tr><th class=\"t\">run id</th><th class=\"t\">product\
         </th><th class=\"t\">started (UTC)</th><th class=\"t\">result</th><th>pads</th>\
         <th>rows lost</th></tr>",
    );
    for b in &boards {
        let lost: u64 = b.cameras.iter().map(|c| c.missing_rows).sum();
        let r = result(b);
        let _ = write!(
            body,
            "<tr><td class=\"t\"><a href=\"/board/{id}\">{run:016x}</a></td><td class=\"t\">{p}\
             </td><td class=\"t\">{t}</td><td class=\"t {c}\">{r}{why}</td><td>{n}</td>\
             <td>{lost}</td></tr>",
            id = b.id,
            run = b.run_id,
            p = esc(&b.product),
            t = time(b.started_unix_s),
            c = class(r),
            r = esc(r),
            why = b
                .incomplete_reason
                .as_deref()
                .map(|w| format!(": {}", esc(w)))
                .unwrap_or_default(),
            n = b.pads,
        );
    }
    body.push_str("</table>");
    if boards.is_empty() {
        body.push_str("<p class=\"note\">No board stored yet.</p>");
    }
    let families = store.family_reviews()?;
    body.push_str("<h2>Reviewed calls per package family</h2>");
    if families.is_empty() {
        body.push_str(
            "<p class=\"note\">No call reviewed yet: open a pad that warned or failed and mark \
             it confirmed or a false call.</p>",
        );
    } else {
        body.push_str(
            "<table><tr><th class=\"t\">family</th><th>reviewed</th><th>confirmed</th>\
             <th>false calls</th><th>false-call rate</th></tr>",
        );
        for f in &families {
            let _ = write!(
                body,
                "<tr><td class=\"t\">{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                esc(f.family.as_deref().unwrap_or("(none)")),
                f.confirmed + f.false_calls,
                f.confirmed,
                f.false_calls,
                f.false_call_rate()
                    .map_or("-".to_owned(), |r| format!("{:.1} %", 100.0 * r)),
            );
        }
        body.push_str(
            "</table><p class=\"note\">Each pad's newest review counts once, on every board \
             of the line.</p>",
        );
    }
    Ok(frame(&format!("Line {}", site.line), &body))
}

/// Board `id` (this line's; `None`: no such board): its result, cameras, print placement and
/// every pad that warned or failed, failures first, each linked to its page.
pub fn board(site: &Site, id: i64) -> Result<Option<String>, PageError> {
    let mut store = open(site)?;
    let Some(b) = store.board(id)? else {
        return Ok(None);
    };
    let pads = store.pads(id)?;
    let print = print_row(&mut store, &b)?;
    let mut body = String::new();
    let r = result(&b);
    let count = |l: &str| pads.iter().filter(|p| p.level == l).count();
    let _ = write!(
        body,
        "<p class=\"figures\"><span>result <b class=\"{}\">{}</b></span><span>product <b>{}</b>\
         </span><span>pads <b>{}</b> ({} pass, {} warn, {} fail)</span><span>started {} UTC\
         </span></p>",
        class(r),
        esc(r),
        esc(&b.product),
        b.pads,
        count("pass"),
        count("warn"),
        count("fail"),
        time(b.started_unix_s)
    );
    if b.state == "inspected" {
        match crate::board_view::board_svg(&site.designs, &b.program_hash, id, &pads) {
            Some(svg) => {
                let _ = write!(
                    body,
                    "<h2>The board</h2><div class=\"board\">{svg}</div><p class=\"note\">Every \
                     opening of the program where the design puts it; the calls coloured, \
                     ringed, named and linked to their pad's page.</p>"
                );
            }
            None => body.push_str(
                "<p class=\"note\">The board is not drawn: its program was not given to the \
                 pages (dpsa serve --program PROG).</p>",
            ),
        }
    }
    if b.state != "open" {
        let run = format!("{:016x}", b.run_id);
        let inspected = b.state == "inspected";
        map_section(site, id, &run, inspected, &b.program_hash, &pads, &mut body);
    }
    if let Some(why) = &b.incomplete_reason {
        let _ = write!(
            body,
            "<p class=\"incomplete\">Never inspected: {}</p>",
            esc(why)
        );
    }
    if let Some(p) = &print {
        match &p.print.placement {
            Some(m) => {
                let _ = write!(
                    body,
                    "<h2>The print</h2><p>Placement x {} &plusmn; {} um, y {} &plusmn; {} um, \
                     rotation {} &plusmn; {} mdeg, stretch {} &plusmn; {} ppm ({} pads, {} set \
                     aside).",
                    num(Some(m.x_um), 1),
                    num(Some(m.uncertainty[0]), 1),
                    num(Some(m.y_um), 1),
                    num(Some(m.uncertainty[1]), 1),
                    num(Some(m.rotation_mdeg), 1),
                    num(Some(m.uncertainty[2]), 1),
                    num(Some(m.stretch_ppm), 0),
                    num(Some(m.uncertainty[3]), 0),
                    m.pads,
                    m.outliers
                );
            }
            None => body.push_str("<h2>The print</h2><p>No placement on this board."),
        }
        let c = &p.print.proposal;
        let _ = write!(
            body,
            " The printer's correction after it: x {} um, y {} um, theta {} mdeg ({}).</p>",
            num(Some(c.correction.x_um), 1),
            num(Some(c.correction.y_um), 1),
            num(Some(c.correction.rotation_mdeg), 1),
            esc(&c.reason)
        );
    }
    if !b.cameras.is_empty() {
        body.push_str(
            "<h2>Cameras</h2><table><tr><th>camera</th><th>rows</th><th>rows lost</th>\
             <th>packets lost</th><th>damaged</th></tr>",
        );
        for c in &b.cameras {
            let _ = write!(
                body,
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                c.camera, c.rows, c.missing_rows, c.missing_packets, c.damaged_packets
            );
        }
        body.push_str("</table>");
    }
    let reviews = store.reviews(id)?;
    let mut flagged: Vec<&PadRow> = pads.iter().filter(|p| p.level != "pass").collect();
    flagged.sort_by_key(|p| (p.level != "fail", p.pad));
    if b.state == "inspected" {
        let _ = write!(
            body,
            "<h2>Pads that warned or failed ({})</h2>",
            flagged.len()
        );
    }
    if !flagged.is_empty() {
        body.push_str(
            "<table><tr><th class=\"t\">pad</th><th class=\"t\">result</th><th class=\"t\">\
             class</th><th>volume %</th><th>&plusmn; %</th><th>height um</th><th>area %</th>\
             <th>offset x um</th><th>offset y um</th><th>coverage</th>\
             <th class=\"t\">review</th></tr>",
        );
        for p in flagged {
            let _ = write!(
                body,
                "<tr><td class=\"t\"><a href=\"/board/{id}/pad/{k}\">{name}</a></td>\
                 <td class=\"t {c}\">{l}</td><td class=\"t\">{cl}</td><td>{v}</td><td>{u}</td>\
                 <td>{h}</td><td>{a}</td><td>{ox}</td><td>{oy}</td><td>{cov}</td>\
                 <td class=\"t\">{rv}</td></tr>",
                k = p.pad,
                name = esc(&p.name),
                c = class(&p.level),
                l = esc(&p.level),
                cl = esc(p.class.as_deref().unwrap_or("")),
                v = num(p.volume_pct, 1),
                u = num(volume_u_pct(p), 1),
                h = num(p.height_um, 1),
                a = num(p.area_pct, 1),
                ox = num(p.offset_x_um, 1),
                oy = num(p.offset_y_um, 1),
                cov = num(Some(p.coverage), 3),
                rv = reviews.iter().rev().find(|r| r.pad == p.pad).map_or(
                    "-".to_owned(),
                    |r| format!("{} ({})", decision_text(r), esc(&r.reviewer))
                ),
            );
        }
        body.push_str("</table>");
    }
    Ok(Some(frame(&format!("Board {:016x}", b.run_id), &body)))
}

/// Pad `k` of board `id` (`None`: no such board or pad): its values with their uncertainty
/// and its history on the line (the product's newest boards), this board marked.
pub fn pad(site: &Site, id: i64, k: u32) -> Result<Option<String>, PageError> {
    let mut store = open(site)?;
    let Some(b) = store.board(id)? else {
        return Ok(None);
    };
    let Some(p) = store.pads(id)?.into_iter().find(|p| p.pad == k) else {
        return Ok(None);
    };
    let mut history = store.pad_history(&b.product, k, HISTORY_BOARDS)?;
    history.reverse();
    let image = store.pad_image(id, k)?;
    let reviews: Vec<Review> = store
        .reviews(id)?
        .into_iter()
        .filter(|r| r.pad == k)
        .collect();
    let mut body = String::new();
    // The program's limits of this pad (its overrides applied), when the program was given.
    let w = site.designs.windows(&b.program_hash, k);
    let window = |f: fn(&dpsa_inspect::program::Windows) -> &dpsa_inspect::program::Window| {
        w.as_ref().map_or(String::new(), |w| {
            let x = f(w);
            format!(
                "warn outside {}-{}, fail outside {}-{}",
                x.warn[0], x.warn[1], x.fail[0], x.fail[1]
            )
        })
    };
    let offset = w.as_ref().map_or(String::new(), |w| {
        format!(
            "% of the opening's width: warn above {}, fail above {}",
            w.offset_pct.warn, w.offset_pct.fail
        )
    });
    let _ = write!(
        body,
        "<p>Board <a href=\"/board/{id}\">{run:016x}</a> ({prod}), pad index {k}: \
         <b class=\"{c}\">{l}</b> {cl}</p><table>\
         <tr><th class=\"t\">measure</th><th>value</th><th>standard uncertainty</th>\
         <th class=\"t\">limits</th></tr>\
         <tr><td class=\"t\">volume, % of the opening</td><td>{v}</td><td>{u}</td>\
         <td class=\"t\">{lv}</td></tr>\
         <tr><td class=\"t\">volume, um&sup3;</td><td>{vu}</td><td>{uu}</td><td></td></tr>\
         <tr><td class=\"t\">height, um</td><td>{h}</td><td></td><td></td></tr>\
         <tr><td class=\"t\">height, % of the stencil</td><td>{hp}</td><td></td>\
         <td class=\"t\">{lh}</td></tr>\
         <tr><td class=\"t\">area, mm&sup2;</td><td>{a}</td><td></td><td></td></tr>\
         <tr><td class=\"t\">area, % of the opening</td><td>{ap}</td><td></td>\
         <td class=\"t\">{la}</td></tr>\
         <tr><td class=\"t\">offset x, um</td><td>{ox}</td><td></td><td class=\"t\">{lo}</td></tr>\
         <tr><td class=\"t\">offset y, um</td><td>{oy}</td><td></td><td class=\"t\">{lo}</td></tr>\
         <tr><td class=\"t\">coverage (valid pixels)</td><td>{cov}</td><td></td><td></td></tr>\
         </table>{note}",
        lv = window(|w| &w.volume_pct),
        lh = window(|w| &w.height_pct),
        la = window(|w| &w.area_pct),
        lo = offset,
        note = if w.is_none() {
            "<p class=\"note\">No limits shown: the board's program was not given to the \
             pages (dpsa serve --program PROG).</p>"
        } else {
            ""
        },
        run = b.run_id,
        prod = esc(&b.product),
        c = class(&p.level),
        l = esc(&p.level),
        cl = esc(p.class.as_deref().unwrap_or("")),
        v = num(p.volume_pct, 1),
        u = num(volume_u_pct(&p), 2),
        vu = num(p.volume_um3, 0),
        uu = num(p.uncertainty_um3, 0),
        h = num(p.height_um, 1),
        hp = num(p.height_pct, 1),
        a = num(p.area_mm2, 4),
        ap = num(p.area_pct, 1),
        ox = num(p.offset_x_um, 1),
        oy = num(p.offset_y_um, 1),
        cov = num(Some(p.coverage), 3),
    );
    let nominal = nominal_um(&p);
    match &image {
        Some(im) => {
            let scale = crate::crop::Scale::for_pad(im, nominal);
            let _ = write!(
                body,
                "<h2>Heights above the pad's local surface</h2><div class=\"pictures\">{}{}</div>\
                 <p class=\"note\">As the line measured this board: board x to the right, y up \
                 (a Gerber viewer's view); the opening dashed in white, the profile's cut in \
                 black; grey where the map has no valid height{}.</p>",
                crate::crop::crop_svg(im, scale, &format!("/board/{id}/pad/{k}/crop.png")),
                crate::crop::profile_svg(im, nominal),
                im.family
                    .as_deref()
                    .map(|f| format!("; package family {}", esc(f)))
                    .unwrap_or_default()
            );
            body.push_str(&crate::view3d::section(id, k, im, scale));
        }
        None if p.level != "pass" => body.push_str(
            "<p class=\"note\">No heights kept for this pad (the line keeps them for the \
             first 200 calls of a board, while its pad rows are kept).</p>",
        ),
        None => {}
    }
    let _ = write!(
        body,
        "<h2>Volume, % of the opening, over the product's last {} inspected boards on the \
         line</h2>",
        history.len()
    );
    let values: Vec<Option<f64>> = history.iter().map(|h| h.3).collect();
    let mark = history.iter().position(|h| h.0 == id);
    body.push_str(&history_svg(&values, mark, &[]));
    let fails = history.iter().filter(|h| h.2 == "fail").count();
    let _ = write!(
        body,
        "<p class=\"note\">This board in red; {fails} of {} failed.</p>",
        history.len()
    );
    pad_spc(site, &b.product, &p.name, &mut body);
    if p.level != "pass" {
        body.push_str("<h2>Review</h2>");
        if reviews.is_empty() {
            body.push_str("<p class=\"note\">Not reviewed yet.</p>");
        } else {
            body.push_str(
                "<table><tr><th class=\"t\">when (UTC)</th><th class=\"t\">who</th>\
                 <th class=\"t\">decision</th><th class=\"t\">note</th></tr>",
            );
            for r in &reviews {
                let _ = write!(
                    body,
                    "<tr><td class=\"t\">{}</td><td class=\"t\">{}</td><td class=\"t\">{}</td>\
                     <td class=\"t\">{}</td></tr>",
                    time(r.reviewed_unix_s),
                    esc(&r.reviewer),
                    decision_text(r),
                    esc(r.note.as_deref().unwrap_or(""))
                );
            }
            body.push_str("</table><p class=\"note\">The newest decision counts.</p>");
        }
        if site.reviews.open() {
            let _ = write!(
                body,
                "<form class=\"review\" method=\"post\" action=\"/board/{id}/pad/{k}/review\">\
                 <label>reviewer <input name=\"reviewer\" required maxlength=\"100\"></label>\
                 <label>note <input name=\"note\" maxlength=\"2000\"></label>{tok}\
                 <button name=\"decision\" value=\"confirmed\">confirmed</button>\
                 <button name=\"decision\" value=\"false_call\">false call</button></form>",
                tok = if site.reviews.needs_token() {
                    "<label>token <input name=\"token\" type=\"password\" required></label>"
                } else {
                    ""
                }
            );
        } else {
            body.push_str(
                "<p class=\"note\">Reviews are off: these pages are served beyond loopback \
                 without a token.</p>",
            );
        }
    }
    Ok(Some(frame(&format!("Pad {}", p.name), &body)))
}

/// Pad `k`'s kept heights of board `id` (this line's) and their colour scale (the pad page's);
/// `None`: no such board, pad or kept heights.
fn kept(
    site: &Site,
    id: i64,
    k: u32,
) -> Result<Option<(dpsa_line::store::PadImage, crate::crop::Scale)>, PageError> {
    let mut store = open(site)?;
    if store.board(id)?.is_none() {
        return Ok(None);
    }
    let Some(im) = store.pad_image(id, k)? else {
        return Ok(None);
    };
    let nominal = store
        .pads(id)?
        .into_iter()
        .find(|p| p.pad == k)
        .and_then(|p| nominal_um(&p));
    let scale = crate::crop::Scale::for_pad(&im, nominal);
    Ok(Some((im, scale)))
}

/// Pad `k`'s kept heights of board `id` for the 3D view, as JSON ([`crate::view3d::json`]);
/// `None` without them.
pub fn heights_json(site: &Site, id: i64, k: u32) -> Result<Option<String>, PageError> {
    Ok(kept(site, id, k)?.map(|(im, scale)| crate::view3d::json(&im, scale)))
}

/// The PNG of pad `k`'s kept heights on board `id`, on the pad page's colour scale; `None`
/// without them.
pub fn crop_png(site: &Site, id: i64, k: u32) -> Result<Option<Vec<u8>>, PageError> {
    match kept(site, id, k)? {
        Some((im, scale)) => Ok(Some(crate::crop::png(&im, scale)?)),
        None => Ok(None),
    }
}
