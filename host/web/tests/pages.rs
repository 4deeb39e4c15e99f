//! The pages over a store written by the store's own API, served on a loopback port and read
//! by a plain HTTP/1.1 client: what each page shows, the links, the headers, what is refused,
//! and that serving leaves the store as it was.

mod common;

use common::{get, header, request, serve, store};
use dpsa_line::store::{Location, Store};
use dpsa_web::Site;

#[test]
fn the_pages_show_the_line_a_board_and_a_pad() {
    let dir = tempfile::tempdir().unwrap();
    let (loc, ids) = store(dir.path());
    let Location::Sqlite(file) = &loc else {
        unreachable!()
    };
    let before = std::fs::read(file).unwrap();
    let (addr, stop, h) = serve(Site {
        reviews: Default::default(),
        designs: Default::default(),
        spc: Default::default(),
        maps: None,
        map_cache: Default::default(),
        store: loc.clone(),
        line: "line-1".into(),
    });

    // The line: its three boards newest first, linked; the yield of the inspected ones; the
    // incomplete board's reason; the printer's newest correction. Not the other line's.
    let (st, hd, body) = get(&addr, "/");
    assert_eq!(st, 200);
    assert_eq!(
        header(&hd, "content-type"),
        Some("text/html; charset=utf-8")
    );
    assert_eq!(header(&hd, "content-security-policy"), Some(dpsa_web::CSP));
    assert_eq!(header(&hd, "x-content-type-options"), Some("nosniff"));
    let table = &body[body.find("Newest boards").unwrap()..];
    let rows: Vec<usize> = ["00000000000000a3", "00000000000000a2", "00000000000000a1"]
        .iter()
        .map(|r| {
            table
                .find(r)
                .unwrap_or_else(|| panic!("{r} not on the line page: {body}"))
        })
        .collect();
    assert!(rows[0] < rows[1] && rows[1] < rows[2], "not newest first");
    assert!(
        !body.contains("00000000000000b1"),
        "another line's board shown"
    );
    for id in &ids[..3] {
        assert!(body.contains(&format!("href=\"/board/{id}\"")), "{body}");
    }
    assert!(body.contains("<b>50.0 %</b>"), "yield: {body}");
    assert!(body.contains("camera 2 silent for 5 s"));
    assert!(body.contains("x 12.5 um"), "printer: {body}");
    // 2 boards an hour apart in 60 s: 120 an hour.
    assert!(body.contains("<b>120.0</b> boards an hour"), "{body}");

    // A board: its failures first, linked to their pads, the name escaped; its print.
    let (st, _, body) = get(&addr, &format!("/board/{}", ids[1]));
    assert_eq!(st, 200);
    let fail = body.find("U&lt;1&gt;-3").expect("escaped pad name");
    let warn = body.find(">R1-2<").expect("the warned pad");
    assert!(fail < warn, "failures first");
    assert!(!body.contains("U<1>-3"));
    assert!(body.contains(&format!("href=\"/board/{}/pad/2\"", ids[1])));
    assert!(!body.contains(">R1-1<"), "a passed pad listed");
    assert!(body.contains("Placement x 12.5"), "{body}");
    // Volume uncertainty in points: 1.5e5 um^3 of a nominal 1e7.
    assert!(body.contains("<td>1.5</td>"), "{body}");
    let (_, _, inc) = get(&addr, &format!("/board/{}", ids[2]));
    assert!(inc.contains("Never inspected: camera 2 silent"));

    // A pad: its values and its history over both inspected boards, this one marked.
    let (st, _, body) = get(&addr, &format!("/board/{}/pad/2", ids[1]));
    assert_eq!(st, 200);
    assert!(body.contains("Pad U&lt;1&gt;-3"), "{body}");
    assert!(body.contains("<td>31.0</td>"));
    assert_eq!(body.matches("<circle").count(), 2);
    assert!(body.contains("1 of 2 failed"));
    // Its kept heights: the image, the colour bar to 1.6 x its nominal height (98 um at 98 %:
    // 100 um, so 160 um, ticks to 150), the profile with the stencil's line; and the review form.
    let src = format!("/board/{}/pad/2/crop.png", ids[1]);
    assert!(body.contains(&format!("href=\"{src}\"")), "{body}");
    assert!(
        body.contains(">150</text>") && body.contains("um above"),
        "{body}"
    );
    assert!(body.contains("stencil 100 um"), "{body}");
    assert!(body.contains("package family QFN-16"));
    assert!(body.contains("Not reviewed yet"));
    assert!(body.contains("value=\"false_call\""));
    assert!(!body.contains("name=\"token\""));
    let (st, hd, png) = request(&addr, "GET", &src, &[], "");
    assert_eq!(st, 200);
    assert_eq!(header(&hd, "content-type"), Some("image/png"));
    let mut r = png::Decoder::new(std::io::Cursor::new(png))
        .read_info()
        .unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    assert_eq!((info.width, info.height), (30, 20));
    // x to the right, y up: the first column invalid (grey), the paste (31 um of 160) in the
    // middle.
    assert_eq!(&buf[..3], &dpsa_web::crop::INVALID_RGB);
    let mid = 3 * (10 * 30 + 15);
    assert_eq!(
        &buf[mid..mid + 3],
        &dpsa_formats::images::colour(31.0 / 160.0)
    );
    // A passed pad has no heights kept and no review.
    let (_, _, passed) = get(&addr, &format!("/board/{}/pad/0", ids[1]));
    assert!(!passed.contains("crop.png") && !passed.contains("<form"));
    let (st, _, _) = request(
        &addr,
        "GET",
        &format!("/board/{}/pad/0/crop.png", ids[1]),
        &[],
        "",
    );
    assert_eq!(st, 404);

    // Refused: unknown boards and pads, another line's board, paths that are no page.
    for path in [
        "/board/999999".to_owned(),
        "/board/abc".to_owned(),
        format!("/board/{}", ids[3]),
        format!("/board/{}/pad/9", ids[1]),
        format!("/board/{}/pad/-1", ids[1]),
        "/style.css/../../Cargo.toml".to_owned(),
        "/%2e%2e/%2e%2e/etc/passwd".to_owned(),
        "/../line.sqlite".to_owned(),
    ] {
        let (st, hd, _) = get(&addr, &path);
        assert_eq!(st, 404, "{path}");
        assert_eq!(header(&hd, "content-security-policy"), Some(dpsa_web::CSP));
    }
    let (st, hd, css) = get(&addr, "/style.css");
    assert_eq!(st, 200);
    assert_eq!(header(&hd, "content-type"), Some("text/css; charset=utf-8"));
    assert!(css.contains(".fail"));

    stop.send(()).unwrap();
    h.join().unwrap();
    // Serving wrote nothing.
    assert_eq!(std::fs::read(file).unwrap(), before);
}

/// A store the pages cannot read gives an error page, not a panic or an empty line.
#[test]
fn a_store_that_is_gone_is_said() {
    let dir = tempfile::tempdir().unwrap();
    let (addr, stop, h) = serve(Site {
        reviews: Default::default(),
        designs: Default::default(),
        spc: Default::default(),
        maps: None,
        map_cache: Default::default(),
        store: Location::Sqlite(dir.path().join("none.sqlite")),
        line: "line-1".into(),
    });
    let (st, _, body) = get(&addr, "/");
    assert_eq!(st, 503);
    assert!(body.contains("could not be read"), "{body}");
    assert!(!dir.path().join("none.sqlite").exists());
    stop.send(()).unwrap();
    h.join().unwrap();
}

/// Reviews from the pad's page are stored with who and when, shown on the pad and the board,
/// and counted per family on the line; a review from another site's page, of a pad that did
/// not warn or fail, without a reviewer or with a bad decision is refused and stores nothing;
/// a site with a token takes reviews only with it; beyond loopback without one, none.
#[test]
fn reviews_are_stored_from_the_page_and_refused_from_elsewhere() {
    let dir = tempfile::tempdir().unwrap();
    let (loc, ids) = store(dir.path());
    let (addr, stop, h) = serve(Site::new(loc.clone(), "line-1"));
    let pad2 = format!("/board/{}/pad/2", ids[1]);
    let post = |path: &str, headers: &[(&str, &str)], body: &str| {
        request(&addr, "POST", &format!("{path}/review"), headers, body)
    };
    let origin = format!("http://{addr}");
    let same = [
        ("Origin", origin.as_str()),
        ("Sec-Fetch-Site", "same-origin"),
    ];
    let (st, hd, _) = post(
        &pad2,
        &same,
        "reviewer=Ana+B&note=paste+on+the+mask&decision=false_call",
    );
    assert_eq!(st, 303);
    assert_eq!(header(&hd, "location"), Some(pad2.as_str()));
    let (st, _, _) = post(
        &format!("/board/{}/pad/1", ids[1]),
        &[],
        "reviewer=bo&decision=confirmed",
    );
    assert_eq!(
        st, 303,
        "a request without Origin (not a browser's cross-site form)"
    );
    // Refused, nothing stored.
    for (path, headers, body, want) in [
        (
            pad2.clone(),
            vec![("Origin", "http://evil.example")],
            "reviewer=x&decision=confirmed",
            403,
        ),
        (
            pad2.clone(),
            vec![("Sec-Fetch-Site", "cross-site")],
            "reviewer=x&decision=confirmed",
            403,
        ),
        (pad2.clone(), vec![], "reviewer=x&decision=maybe", 400),
        (pad2.clone(), vec![], "reviewer=+&decision=confirmed", 400),
        (pad2.clone(), vec![], "decision=confirmed", 422),
        (
            format!("/board/{}/pad/0", ids[1]),
            vec![],
            "reviewer=x&decision=confirmed",
            400,
        ),
        (
            format!("/board/{}/pad/2", ids[0]),
            vec![],
            "reviewer=x&decision=confirmed",
            400,
        ),
        (
            format!("/board/{}/pad/2", ids[3]),
            vec![],
            "reviewer=x&decision=confirmed",
            400,
        ),
    ] {
        let (st, hd, page) = post(&path, &headers, body);
        let page = String::from_utf8_lossy(&page);
        assert_eq!(st, want, "{path} {headers:?} {body}");
        // Every refusal is the site's page, with its headers.
        assert!(
            header(&hd, "content-security-policy").is_some() && page.contains("<h1>"),
            "{path} {body}: {hd:?} {page}"
        );
    }
    let big = format!("reviewer=x&decision=confirmed&note={}", "a".repeat(20_000));
    let (st, hd, page) = post(&pad2, &[], &big);
    let page = String::from_utf8_lossy(&page);
    assert_eq!(st, 413);
    assert!(
        header(&hd, "content-security-policy").is_some() && page.contains("<h1>"),
        "{hd:?} {page}"
    );

    let (_, _, body) = get(&addr, &pad2);
    assert!(
        body.contains("Ana B") && body.contains("paste on the mask"),
        "{body}"
    );
    assert!(body.contains("false call"));
    let (_, _, body) = get(&addr, &format!("/board/{}", ids[1]));
    assert!(
        body.contains("false call (Ana B)") && body.contains("confirmed (bo)"),
        "{body}"
    );
    let (_, _, body) = get(&addr, "/");
    let fam = &body[body.find("Reviewed calls per package family").unwrap()..];
    assert!(
        fam.contains("<td class=\"t\">QFN-16</td><td>1</td><td>0</td><td>1</td><td>100.0 %</td>"),
        "{fam}"
    );
    assert!(
        fam.contains("<td class=\"t\">R_0603</td><td>1</td><td>1</td><td>0</td><td>0.0 %</td>"),
        "{fam}"
    );
    let mut s = Store::open(&loc, "line-1").unwrap();
    assert_eq!(s.reviews(ids[1]).unwrap().len(), 2);
    assert!(s.reviews(ids[0]).unwrap().is_empty());
    s.check().unwrap();
    stop.send(()).unwrap();
    h.join().unwrap();

    // With a token: only with it.
    let mut site = Site::new(loc.clone(), "line-1");
    site.reviews = dpsa_web::review::Policy {
        token: Some("0123456789abcdef-token".into()),
        beyond_loopback: true,
    };
    let (addr, stop, h) = serve(site);
    let post = |body: &str| request(&addr, "POST", &format!("{pad2}/review"), &[], body);
    let (_, _, page) = get(&addr, &pad2);
    assert!(page.contains("name=\"token\""));
    assert_eq!(post("reviewer=c&decision=confirmed").0, 403);
    assert_eq!(
        post("reviewer=c&decision=confirmed&token=0123456789abcdef-toke").0,
        403
    );
    assert_eq!(
        post("reviewer=c&decision=confirmed&token=0123456789abcdef-token").0,
        303
    );
    stop.send(()).unwrap();
    h.join().unwrap();

    // Beyond loopback without a token: no form, no review.
    let mut site = Site::new(loc.clone(), "line-1");
    site.reviews.beyond_loopback = true;
    let (addr, stop, h) = serve(site);
    let (_, _, page) = get(&addr, &pad2);
    assert!(
        !page.contains("<form") && page.contains("Reviews are off"),
        "{page}"
    );
    let (st, _, _) = request(
        &addr,
        "POST",
        &format!("{pad2}/review"),
        &[],
        "reviewer=c&decision=confirmed",
    );
    assert_eq!(st, 403);
    stop.send(()).unwrap();
    h.join().unwrap();
    assert_eq!(
        Store::open(&loc, "line-1")
            .unwrap()
            .reviews(ids[1])
            .unwrap()
            .len(),
        3
    );
}

/// A board drawn by its program: every opening where the design puts it (x to the right, y
/// up), the calls over them in their colours, linked and labelled; a board of a program not
/// given says so instead.
#[test]
fn the_board_is_drawn_by_its_program() {
    let dir = tempfile::tempdir().unwrap();
    let prog = common::mini_program(dir.path());
    let design = dpsa_line::config::Design::load(&prog).unwrap();
    assert_eq!(design.pads.len(), 3);
    let hash = design.program_hash.clone();
    let loc = Location::Sqlite(dir.path().join("line.sqlite"));
    let ids = common::mini_boards(&loc, &[(0xc1, hash.as_str()), (0xc2, "another")]);
    let mut site = Site::new(loc, "line-1");
    site.designs = std::sync::Arc::new(dpsa_web::board_view::Designs::from(vec![design]));
    let (addr, stop, h) = serve(site);
    let (st, _, body) = get(&addr, &format!("/board/{}", ids[0]));
    assert_eq!(st, 200);
    // The design spans x 0.7..3.2 and y 0.85..2.2 mm: 368 px a mm from a 40 px margin. Pad 0
    // (0.6 x 0.3 at (1, 1)) is a rect at (40, 426.4); pad 2 (a 0.4 disc at (3, 2)) a circle
    // at (886.4, 113.6), y up.
    let svg = &body[body.find("<svg").unwrap()..];
    assert!(
        svg.contains("<rect x=\"40.0\" y=\"426.4\" width=\"220.80\" height=\"110.40\""),
        "{svg}"
    );
    assert!(
        svg.contains("<circle cx=\"886.4\" cy=\"113.6\" r=\"73.60\""),
        "{svg}"
    );
    // The calls: linked, titled, ringed and named (escaped); the failure drawn after the warning.
    let fail = svg
        .find(&format!(
            "<a href=\"/board/{}/pad/2\"><title>U&lt;1&gt;-3 fail: insufficient</title>",
            ids[0]
        ))
        .expect("the failure linked");
    let warn = svg
        .find(&format!(
            "<a href=\"/board/{}/pad/1\"><title>R1-2 warn: insufficient</title>",
            ids[0]
        ))
        .expect("the warning linked");
    assert!(warn < fail);
    assert!(svg.contains(">U&lt;1&gt;-3 insufficient</text>"));
    assert!(!svg.contains("/pad/0\""), "a passed pad linked");
    assert!(svg.contains(dpsa_web::board_view::FAIL) && svg.contains(">pass</text>"));
    assert!(svg.contains(" mm</text>") && !svg.contains("style="));
    // The pad page shows the pad's limits under the program (the defaults: the test's program
    // sets none); a board of a program not given says it shows none.
    let (_, _, pad) = get(&addr, &format!("/board/{}/pad/2", ids[0]));
    let w = dpsa_inspect::program::Windows::default();
    let v = &w.volume_pct;
    let want = format!(
        "warn outside {}-{}, fail outside {}-{}",
        v.warn[0], v.warn[1], v.fail[0], v.fail[1]
    );
    let row = &pad[pad.find("volume, % of the opening").unwrap()..pad.find("volume, um").unwrap()];
    assert!(row.contains(&want), "{want}: {row}");
    assert!(pad.contains(&format!(
        "warn above {}, fail above {}",
        w.offset_pct.warn, w.offset_pct.fail
    )));
    let (_, _, pad) = get(&addr, &format!("/board/{}/pad/2", ids[1]));
    assert!(pad.contains("No limits shown"), "{pad}");
    // Another program's board: not drawn, said.
    let (_, _, other) = get(&addr, &format!("/board/{}", ids[1]));
    assert!(
        !other.contains("<svg") && other.contains("its program was not given"),
        "{other}"
    );
    stop.send(()).unwrap();
    h.join().unwrap();
}

/// The SPC page studies the product's newest boards as `dpsa spc` does: a volume step on the
/// last three of 30 boards raises the board's volume alarm (limits from the first 25); the
/// board's mean volume is the mean of the stored values; its chart is a PNG of the plot's
/// size; an unknown product or chart is a 404.
#[test]
fn the_spc_page_shows_the_study_and_its_alarms() {
    let dir = tempfile::tempdir().unwrap();
    let loc = Location::Sqlite(dir.path().join("line.sqlite"));
    let all = spc_boards(&loc, 0..30);
    let (addr, stop, h) = serve(Site::new(loc, "line-1"));
    let (st, _, body) = get(&addr, "/spc");
    assert_eq!(st, 200, "{body}");
    assert!(
        body.contains("SPC: mini") && body.contains("<b>30</b>"),
        "{body}"
    );
    let open = &body[body.find("Open alarms").unwrap()..body.find("The board (").unwrap()];
    assert!(
        open.contains("board mini") && open.contains("WE1") && open.contains(">open<"),
        "{open}"
    );
    // The first board the step touches, linked.
    assert!(open.contains(">000000000000011b</a>"), "{open}");
    let mean = all.iter().sum::<f64>() / all.len() as f64;
    let table = &body[body.find("The board (").unwrap()..];
    assert!(
        table.contains(&format!("<td>{mean:.2}</td>")),
        "{mean:.2}: {table}"
    );
    let src = body
        .split("<img class=\"chart\" src=\"")
        .nth(1)
        .and_then(|r| r.split('"').next())
        .expect("the board's volume chart")
        .to_owned();
    assert_eq!(src, "/spc/mini/chart/board/0/volume_pct.png");
    let (st, hd, png) = request(&addr, "GET", &src, &[], "");
    assert_eq!(st, 200);
    assert_eq!(header(&hd, "content-type"), Some("image/png"));
    let r = png::Decoder::new(std::io::Cursor::new(png))
        .read_info()
        .unwrap();
    assert_eq!((r.info().width, r.info().height), dpsa_spc::plot::SIZE);
    for bad in [
        "/spc/none",
        "/spc/mini/chart/board/99/volume_pct.png",
        "/spc/mini/chart/shelf/0/volume_pct.png",
        "/spc/mini/chart/board/0/height_pct.png",
        "/spc/mini/chart/board/0/volume_pct",
    ] {
        assert_eq!(get(&addr, bad).0, 404, "{bad}");
    }
    stop.send(()).unwrap();
    h.join().unwrap();
}

/// The line page shows the open alarms of the newest study without waiting for one: first
/// that it is being made, then its alarm; a newer board marks it behind until the newer study
/// is made, which then ends on that board.
#[test]
fn the_line_page_shows_the_open_alarms() {
    let dir = tempfile::tempdir().unwrap();
    let loc = Location::Sqlite(dir.path().join("line.sqlite"));
    spc_boards(&loc, 0..30);
    let site = Site::new(loc.clone(), "line-1");
    let (addr, stop, h) = serve(site.clone());
    let (st, _, body) = get(&addr, "/");
    assert_eq!(st, 200, "{body}");
    assert!(
        body.contains("study of the newest boards is being made"),
        "{body}"
    );
    dpsa_web::spc::settle(&site);
    let (_, _, body) = get(&addr, "/");
    let open = &body[body.find("Open alarms").unwrap()..body.find("Newest boards").unwrap()];
    assert!(open.contains("Open alarms (2, mini)"), "{open}");
    assert!(
        open.contains("board mini") && open.contains("WE1") && open.contains("000000000000011b"),
        "{open}"
    );
    assert!(
        open.contains("up to board 000000000000011d.") && !open.contains("being made"),
        "{open}"
    );
    spc_boards(&loc, 30..31);
    let (_, _, body) = get(&addr, "/");
    assert!(body.contains("a newer study is being made"), "{body}");
    dpsa_web::spc::settle(&site);
    let (_, _, body) = get(&addr, "/");
    assert!(body.contains("up to board 000000000000011e."), "{body}");
    stop.send(()).unwrap();
    h.join().unwrap();
}

/// The pad page shows the pad's own SPC chart (its volume, the board the subgroup) from the
/// newest study: being made at first, then the chart (a PNG the chart route serves) with its
/// board count and mean (the mean of the pad's stored volumes).
#[test]
fn the_pad_page_shows_its_spc_chart() {
    let dir = tempfile::tempdir().unwrap();
    let loc = Location::Sqlite(dir.path().join("line.sqlite"));
    let all = spc_boards(&loc, 0..30);
    let site = Site::new(loc.clone(), "line-1");
    let (addr, stop, h) = serve(site.clone());
    let newest = Store::open(&loc, "line-1")
        .unwrap()
        .boards(1)
        .unwrap()
        .remove(0)
        .id;
    let page = format!("/board/{newest}/pad/1");
    let (st, _, body) = get(&addr, &page);
    assert_eq!(st, 200, "{body}");
    assert!(
        body.contains("study of the product's newest boards is being made"),
        "{body}"
    );
    dpsa_web::spc::settle(&site);
    let (_, _, body) = get(&addr, &page);
    let spc = &body[body.find("SPC: the pad's volume chart").unwrap()..];
    let src = spc
        .split("<img class=\"chart\" src=\"")
        .nth(1)
        .and_then(|r| r.split('"').next())
        .unwrap_or_else(|| panic!("no chart: {spc}"))
        .to_owned();
    assert!(
        src.starts_with("/spc/mini/chart/pad/") && src.ends_with("/volume_pct.png"),
        "{src}"
    );
    // Pad 1's volumes: every third value, from the second.
    let mean = all.iter().skip(1).step_by(3).sum::<f64>() / 30.0;
    assert!(
        spc.contains("boards <b>30</b>") && spc.contains(&format!("mean <b>{mean:.1}</b>")),
        "{mean:.1}: {spc}"
    );
    let (st, hd, _) = request(&addr, "GET", &src, &[], "");
    assert_eq!(st, 200);
    assert_eq!(header(&hd, "content-type"), Some("image/png"));
    stop.send(()).unwrap();
    h.join().unwrap();
}

/// Boards `boards` of product `mini` (three pads each; a volume step of 25 % from board 27
/// on) stored in `loc`; returns every pad's volume, board by board.
fn spc_boards(loc: &Location, boards: std::ops::Range<u64>) -> Vec<f64> {
    let mut s = Store::open(loc, "line-1").unwrap();
    let mut all = Vec::new();
    for b in boards {
        all.extend(spc_board(&mut s, b));
    }
    all
}

fn spc_board(s: &mut Store, b: u64) -> Vec<f64> {
    let mut all = Vec::new();
    {
        let id = s
            .begin_board(&dpsa_line::store::BoardStart {
                run_id: 0x100 + b,
                product: "mini".into(),
                program_hash: "p".into(),
                calibration_hash: "c".into(),
                started_unix_s: 1_700_000_000.0 + 10.0 * b as f64,
            })
            .unwrap();
        let pads: Vec<_> = (0..3u32)
            .map(|k| {
                let v = 100.0 + ((b as u32 * 7 + k * 3) % 5) as f64 - 2.0
                    + if b >= 27 { 25.0 } else { 0.0 };
                all.push(v);
                common::pad(k, &format!("R{k}-1"), "pass", Some(v))
            })
            .collect();
        s.finish_board(
            id,
            1_700_000_005.0 + 10.0 * b as f64,
            &[],
            &dpsa_line::store::Outcome::Inspected {
                verdict: "pass".into(),
                pads,
            },
        )
        .unwrap();
    }
    all
}

/// The board page zooms and pans over the map the line kept: the viewer on the page with the
/// calls placed by the kept registration; the map's description; tiles of the height above
/// the board's surface (the bow gone, the paste 100 um), drawn once and then served from the
/// cache; every other path under the map a 404; a damaged map said, never drawn.
#[test]
fn the_board_page_zooms_and_pans_over_its_kept_map() {
    use dpsa_formats::images::colour;
    use dpsa_formats::kept_map::DesignToBoard;
    let dir = tempfile::tempdir().unwrap();
    let prog = common::mini_program(dir.path());
    let design = dpsa_line::config::Design::load(&prog).unwrap();
    let hash = design.program_hash.clone();
    let loc = Location::Sqlite(dir.path().join("line.sqlite"));
    let ids = common::mini_boards(
        &loc,
        &[(0xd1, &hash), (0xd2, &hash), (0xd3, &hash), (0xd6, &hash)],
    );
    // The design lies on the board turned by 20 mrad and shifted: each opening's paste where
    // the transform puts it.
    let t = Some(DesignToBoard {
        rotation_rad: 0.02,
        tx_mm: 0.15,
        ty_mm: -0.1,
    });
    let on_board = |x: f64, y: f64| {
        let (s, c) = 0.02f64.sin_cos();
        (c * x - s * y + 0.15, s * x + c * y - 0.1)
    };
    let deposits: Vec<(f64, f64)> = [(1.0, 1.0), (2.0, 1.0), (3.0, 2.0)]
        .into_iter()
        .map(|(x, y)| on_board(x, y))
        .collect();
    let maps = dir.path().join("maps");
    // 5 x 3 mm at 10 um: 500 x 300 px, two levels.
    let size = (500, 300, 0.01);
    common::kept_map(&maps, "line-1", (ids[0], 0xd1), size, &deposits, t);
    common::kept_map(&maps, "line-1", (ids[1], 0xd2), size, &deposits, t);
    // Board 1's map damaged: cut short.
    let (png1, _) = dpsa_formats::kept_map::paths(&maps, "line-1", ids[1]);
    let bytes = std::fs::read(&png1).unwrap();
    std::fs::write(&png1, &bytes[..bytes.len() - 100]).unwrap();
    // Another line's map under an id this line has no map of.
    common::kept_map(&maps, "line-2", (ids[2], 0xd3), size, &deposits, t);
    // Under board 2's id in this line, the map of a board of another store (run 0x99).
    common::kept_map(&maps, "line-1", (ids[2], 0x99), size, &deposits, t);
    // A board the design could not be registered on: incomplete, its map kept without a
    // registration; and an incomplete board without a map.
    let mut s = Store::open(&loc, "line-1").unwrap();
    let mut incomplete = Vec::new();
    for run in [0xd4u64, 0xd5] {
        let id = s
            .begin_board(&dpsa_line::store::BoardStart {
                run_id: run,
                product: "mini".into(),
                program_hash: hash.clone(),
                calibration_hash: "c".into(),
                started_unix_s: 1_700_000_000.0,
            })
            .unwrap();
        let reason = "the design could not be registered on the map: no fiducial found";
        s.finish_board(
            id,
            1_700_000_001.0,
            &[],
            &dpsa_line::store::Outcome::Incomplete {
                reason: reason.into(),
            },
        )
        .unwrap();
        incomplete.push(id);
    }
    drop(s);
    common::kept_map(
        &maps,
        "line-1",
        (incomplete[0], 0xd4),
        size,
        &deposits,
        None,
    );

    let mut site = Site::new(loc.clone(), "line-1");
    site.designs = std::sync::Arc::new(dpsa_web::board_view::Designs::from(vec![design]));
    site.maps = Some(maps.clone());
    let cache = std::sync::Arc::clone(&site.map_cache);
    let (addr, stop, h) = serve(site);

    // The page: the viewer and its script; the calls placed on the map's pixels (u along
    // board x, v down from the map's top edge at y = 3 mm), the passed pad not marked.
    let b = ids[0];
    const RUN: &str = "00000000000000d1";
    let (st, _, page) = get(&addr, &format!("/board/{b}"));
    assert_eq!(st, 200);
    assert!(
        page.contains(&format!("data-map=\"/board/{b}/map/{RUN}/info.json\"")),
        "{page}"
    );
    assert!(page.contains("<script src=\"/js/mapview.js\"></script>"));
    for (k, (x, y), level, label) in [
        (1, (2.0, 1.0), "warn", "R1-2 insufficient"),
        (2, (3.0, 2.0), "fail", "U&lt;1&gt;-3 insufficient"),
    ] {
        let (bx, by) = on_board(x, y);
        let want = format!(
            "<a class=\"mapcall {level}\" href=\"/board/{b}/pad/{k}\" data-u=\"{:.1}\" \
             data-v=\"{:.1}\" title=\"{label}\">",
            bx / 0.01,
            (3.0 - by) / 0.01
        );
        assert!(page.contains(&want), "{want}\n{page}");
    }
    assert!(!page.contains(&format!("href=\"/board/{b}/pad/0\" data-u")));
    let (st, h1, js) = get(&addr, "/js/mapview.js");
    assert_eq!(st, 200);
    assert!(header(&h1, "content-type").unwrap().contains("javascript"));
    assert!(js.contains("mapview"));

    // The description: the map turned (5 mm of x across), two levels, the scale from the
    // bare board (0) to the paste's top (100 um).
    let (st, _, info) = get(&addr, &format!("/board/{b}/map/{RUN}/info.json"));
    assert_eq!(st, 200, "{info}");
    let info: serde_json::Value = serde_json::from_str(&info).unwrap();
    assert_eq!(
        (
            &info["width"],
            &info["height"],
            &info["levels"],
            &info["tile"]
        ),
        (&500.into(), &300.into(), &2.into(), &256.into()),
        "{info}"
    );
    assert!((info["y_top_mm"].as_f64().unwrap() - 3.0).abs() < 1e-9);
    let (lo, hi) = (
        info["range_um"][0].as_f64().unwrap(),
        info["range_um"][1].as_f64().unwrap(),
    );
    assert!(lo.abs() < 1.0 && (hi - 100.0).abs() < 1.0, "{info}");
    assert_eq!(cache.builds(), 1);

    // The finest level's tiles: the paste of pad 2 coloured as 100 um above the board, the
    // board beside it as 0, whatever the bow.
    let pixel = |z: u8, u: f64, v: f64| -> [u8; 4] {
        let (tx, ty) = ((u / 256.0) as u32, (v / 256.0) as u32);
        let (st, hd, png) = request(
            &addr,
            "GET",
            &format!("/board/{b}/map/{RUN}/{z}/{tx}/{ty}.png"),
            &[],
            "",
        );
        assert_eq!(st, 200);
        assert_eq!(header(&hd, "content-type"), Some("image/png"));
        assert!(header(&hd, "content-security-policy").is_some());
        let mut d = png::Decoder::new(std::io::Cursor::new(png));
        d.set_transformations(png::Transformations::EXPAND);
        let mut r = d.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
        r.next_frame(&mut buf).unwrap();
        assert_eq!(buf.len(), 256 * 256 * 4);
        let (pu, pv) = (u as usize % 256, v as usize % 256);
        buf[(pv * 256 + pu) * 4..][..4].try_into().unwrap()
    };
    let near = |got: [u8; 4], um: f64| {
        let want = colour(((um - lo) / (hi - lo)).clamp(0.0, 1.0));
        assert!(
            got[3] == 255 && (0..3).all(|i| got[i].abs_diff(want[i]) <= 8),
            "{got:?} is not {um} um's {want:?}"
        );
    };
    let (px, py) = on_board(3.0, 2.0);
    near(pixel(1, px / 0.01, (3.0 - py) / 0.01), 100.0);
    near(pixel(1, 450.0, 250.0), 0.0);
    near(pixel(1, 20.0, 20.0), 0.0);
    let drawn = cache.renders();
    // The same tiles again: from the cache, none drawn.
    near(pixel(1, 20.0, 20.0), 0.0);
    assert_eq!(cache.renders(), drawn);
    // Level 0 (the map halved) is one tile; beyond the map it is transparent.
    assert_eq!(pixel(0, 255.0, 200.0)[3], 0);
    assert_eq!(cache.builds(), 1);

    // Nothing else under the map: levels, tiles and names that are not there, text where a
    // number goes, traversal, another line's map, a board without one.
    for path in [
        format!("/board/{b}/map/{RUN}/2/0/0.png"),
        format!("/board/{b}/map/{RUN}/1/2/0.png"),
        format!("/board/{b}/map/{RUN}/1/0/2.png"),
        format!("/board/{b}/map/{RUN}/1/0/0.jpg"),
        format!("/board/{b}/map/{RUN}/1/0/-1.png"),
        format!("/board/{b}/map/{RUN}/x/0/0.png"),
        format!("/board/{b}/map/{RUN}/1/0/..%2f..%2fline.sqlite"),
        format!("/board/{b}/map/{RUN}/../../../line.sqlite"),
        format!("/board/{b}/map/{RUN}/%2e%2e/0/0.png"),
        format!("/board/{b}/map/{RUN}/map.json"),
        format!("/board/{b}/map/{RUN}"),
        format!("/board/{b}/map.json"),
        format!("/board/{b}/map/00000000000000D1/info.json"),
        format!("/board/{b}/map/d1/info.json"),
        format!("/board/{b}/map/00000000000000d2/info.json"),
        format!("/board/{b}/map/00000000000000d2/0/0/0.png"),
        format!("/board/{}/map/00000000000000d3/info.json", ids[2]),
        format!("/board/{}/map/00000000000000d3/0/0/0.png", ids[2]),
        format!("/board/{}/map/0000000000000099/info.json", ids[2]),
        "/board/9999/map/00000000000000d1/info.json".to_owned(),
    ] {
        let (st, _, _) = get(&addr, &path);
        assert_eq!(st, 404, "{path}");
    }
    // The map under board 2's id is another store's board's: not shown, said.
    let (_, _, page) = get(&addr, &format!("/board/{}", ids[2]));
    assert!(
        page.contains("is of another board (run 0000000000000099): not shown")
            && !page.contains("data-map="),
        "{page}"
    );
    // The unregistered board's map is shown, nothing marked on it, and said so; the other
    // incomplete board shows no map and says nothing of one.
    let (_, _, page) = get(&addr, &format!("/board/{}", incomplete[0]));
    assert!(
        page.contains(&format!(
            "data-map=\"/board/{}/map/00000000000000d4/info.json\"",
            incomplete[0]
        )) && page.contains("could not be registered on this map")
            && !page.contains("class=\"mapcall"),
        "{page}"
    );
    let (st, _, _) = get(
        &addr,
        &format!("/board/{}/map/00000000000000d4/info.json", incomplete[0]),
    );
    assert_eq!(st, 200);
    let (_, _, page) = get(&addr, &format!("/board/{}", incomplete[1]));
    assert!(!page.contains("The measured map"), "{page}");
    // A board without a kept map says so; a damaged one is said, never drawn.
    let (_, _, page) = get(&addr, &format!("/board/{}", ids[3]));
    assert!(page.contains("Not kept for this board"), "{page}");
    let (st, _, body) = get(
        &addr,
        &format!("/board/{}/map/00000000000000d2/info.json", ids[1]),
    );
    assert_eq!(st, 503);
    assert!(
        body.contains("kept map cannot be read") && body.contains("bytes where"),
        "{body}"
    );
    let (st, _, _) = get(
        &addr,
        &format!("/board/{}/map/00000000000000d2/0/0/0.png", ids[1]),
    );
    assert_eq!(st, 503);
    stop.send(()).unwrap();
    h.join().unwrap();

    // Pages without a maps directory show no map.
    let (addr, stop, h) = serve(Site::new(loc, "line-1"));
    let (_, _, page) = get(&addr, &format!("/board/{b}"));
    assert!(!page.contains("The measured map"), "{page}");
    let (st, _, _) = get(&addr, &format!("/board/{b}/map/{RUN}/info.json"));
    assert_eq!(st, 404);
    stop.send(()).unwrap();
    h.join().unwrap();
}
