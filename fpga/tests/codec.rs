//! The row codec's encoder in the RTL (`dpsa_codec`) against dpsa-core's `Encoder`, payload
//! for payload (needs `verilator`; `bash tests/run.sh` installs it).

use dpsa_fpga::codec::{self, Report};
use dpsa_fpga::model::{cache_dir, Model, Sources};

fn show(r: &Report) {
    println!(
        "{} streams, {} rows, {} pixels ({} valid), {} widths; rows: raw {}, coded intra {}, \
         coded predicted {}, plain mask {}, empty {}, stalled {}; escapes {}; resets {}, \
         period changes {}; mismatches {}",
        r.streams,
        r.rows,
        r.pixels,
        r.valid_pixels,
        r.widths,
        r.raw_rows,
        r.intra_rows,
        r.predicted_rows,
        r.plain_rows,
        r.empty_rows,
        r.stalled_rows,
        r.escapes,
        r.resets,
        r.period_changes,
        r.mismatches
    );
    if r.rows_coded_unstalled > 0 && r.rows_raw_unstalled > 0 {
        println!(
            "clocks past W: coded rows {:.1} a row ({:.1} past their payload words), raw rows \
             {:.3} a pixel",
            r.extra_clocks_coded as f64 / r.rows_coded_unstalled as f64,
            (r.extra_clocks_coded as f64 - r.words_coded as f64) / r.rows_coded_unstalled as f64,
            r.extra_clocks_raw as f64 / r.pixels_raw_unstalled as f64,
        );
    }
    for m in &r.first {
        println!("  {m}");
    }
}

/// Sixty million pixels in streams of every width class and row class: every payload of the
/// model equals the core's, and every class occurred.
#[test]
fn the_rtl_encoder_equals_the_cores() {
    let model = Model::codec_repo().unwrap_or_else(|e| panic!("{e}"));
    let t = std::time::Instant::now();
    let r = codec::run(&model, 0xc0dec, 60_000_000, 120_000).unwrap();
    show(&r);
    println!("{:.1} s", t.elapsed().as_secs_f64());
    assert!(r.pixels >= 60_000_000);
    assert!(
        r.widths as usize >= codec::WIDTHS.len() + 20,
        "{}",
        r.widths
    );
    assert!(r.raw_rows > 100 && r.plain_rows > 100, "{r:?}");
    assert!(r.predicted_rows > 1000 && r.intra_rows > 1000, "{r:?}");
    assert!(
        r.empty_rows > 100 && r.stalled_rows > 1000 && r.escapes > 1000,
        "{r:?}"
    );
    assert!(r.resets > 100 && r.period_changes > 100, "{r:?}");
    assert_eq!(r.mismatches, 0);
}

/// The comparison can fail: each of these one-token mutations of the encoder's RTL (the
/// predicted and the intra context thresholds, the accumulator's decay, the escape limit, the
/// gamma length, the plain-mask decision, the raw decision, the raw validity bytes' padding)
/// is caught on a million pixels.
#[test]
fn mutated_codec_rtl_is_caught() {
    let src = dpsa_fpga::fpga_dir().join("rtl");
    let text = std::fs::read_to_string(src.join("dpsa_codec.v")).unwrap();
    let mutations = [
        ("gp >= 20'd48", "gp >= 20'd47"),
        ("{5'd0, asel[20:5]}", "{6'd0, asel[20:6]}"),
        ("rn[15:4] != 12'd0", "rn[15:4] > 12'd1"),
        ("<= {1'b0, g_nb, 1'b0} - 6'd1", "<= {1'b0, g_nb, 1'b0}"),
        ("{1'b0, vbits} > w21", "{1'b0, vbits} >= w21"),
        ("gi >= 18'd16", "gi > 18'd16"),
        ("d_cbytes > d_rawlen;", "d_cbytes >= d_rawlen;"),
        ("+ 6'd8) & 6'h38)", "+ 6'd7) & 6'h38)"),
    ];
    for (from, to) in mutations {
        assert_eq!(text.matches(from).count(), 1, "{from} not in the RTL");
        let dir = tempfile::tempdir().unwrap();
        for e in std::fs::read_dir(&src).unwrap() {
            let p = e.unwrap().path();
            std::fs::copy(&p, dir.path().join(p.file_name().unwrap())).unwrap();
        }
        std::fs::write(dir.path().join("dpsa_codec.v"), text.replace(from, to)).unwrap();
        let model = Model::build(&Sources::codec_in_dir(dir.path()), &cache_dir())
            .unwrap_or_else(|e| panic!("{e}"));
        // A mutant that garbles the word count never finishes its row: the harness gives up
        // and the run fails, which catches it as well.
        let caught = match codec::run(&model, 11, 1_000_000, 60_000) {
            Ok(r) => {
                println!("{from} -> {to}: {} of {} rows differ", r.mismatches, r.rows);
                r.mismatches > 0
            }
            Err(e) => {
                println!("{from} -> {to}: the run failed: {e}");
                true
            }
        };
        assert!(caught, "mutation `{from}` -> `{to}` not caught");
    }
}
