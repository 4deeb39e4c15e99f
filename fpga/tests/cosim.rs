//! The RTL against dpsa-core, bit for bit (needs `verilator`; `bash tests/run.sh` installs it).

use dpsa_fpga::cosim::{self, Report};
use dpsa_fpga::model::{cache_dir, Model, Sources};

fn show(r: &Report) {
    println!(
        "{} pixels in {} windows, n 3..8: {:?}; valid {}, saturated {}, low modulation {}, \
         valid by the gate's exact path {}; mismatches {}",
        r.pixels,
        r.windows,
        &r.by_n[3..],
        r.valid,
        r.saturated,
        r.low_modulation,
        r.exact_gate,
        r.mismatches
    );
    for m in &r.first {
        println!("  {m}");
    }
}

/// The ROM the RTL loads is the core's `atan` table, entry for entry.
#[test]
fn the_rtl_table_is_the_cores() {
    let text = std::fs::read_to_string(dpsa_fpga::fpga_dir().join("rtl/atan.hex")).unwrap();
    let rom: Vec<u32> = text
        .lines()
        .filter(|l| !l.starts_with("//") && !l.trim().is_empty())
        .map(|l| u32::from_str_radix(l.trim(), 16).unwrap())
        .collect();
    assert_eq!(rom, dpsa_core::phase::atan_table());
}

/// Ten million pixels of every class, every n in 3..=8, uniform and per-column scales: the
/// model's V, flags, phases and heights equal the core's.
#[test]
fn the_rtl_equals_the_core_on_ten_million_pixels() {
    let model = Model::repo().unwrap_or_else(|e| panic!("{e}"));
    let r = cosim::run(&model, 0x5eed, 10_000_000, 4096).unwrap();
    show(&r);
    assert_eq!(r.pixels, 10_000_000);
    assert!(r.by_n[3..].iter().all(|&c| c > 1_000_000), "{:?}", r.by_n);
    assert!(r.valid > 1_000_000 && r.saturated > 1_000_000 && r.low_modulation > 100_000);
    assert!(
        r.exact_gate > 1_000,
        "the gate's exact path barely exercised"
    );
    assert_eq!(r.mismatches, 0);
}

/// The comparison can fail: each of these one-token mutations of the RTL (a saturation
/// boundary in the accumulate stage, the zero-modulation test of the gate, a quotient bit of
/// the divider, the interpolation's rounding) is caught on 200,000 pixels.
#[test]
fn mutated_rtl_is_caught() {
    let src = dpsa_fpga::fpga_dir().join("rtl");
    let text = std::fs::read_to_string(src.join("dpsa_pixel.v")).unwrap();
    let mutations = [
        (
            "if (x_s1[16*j +: 16] >= sat)",
            "if (x_s1[16*j +: 16] > sat)",
        ),
        ("(c2_s8 >= thr2 && c2_s8 != 64'd0)", "(c2_s8 >= thr2)"),
        (
            "wire ge = r >= {1'b0, d_in};",
            "wire ge = r > {1'b0, d_in};",
        ),
        ("((prod_s31 + 32'd128) >> 8)", "((prod_s31 + 32'd127) >> 8)"),
    ];
    for (from, to) in mutations {
        assert_eq!(text.matches(from).count(), 1, "{from} not in the RTL");
        let dir = tempfile::tempdir().unwrap();
        for e in std::fs::read_dir(&src).unwrap() {
            let p = e.unwrap().path();
            std::fs::copy(&p, dir.path().join(p.file_name().unwrap())).unwrap();
        }
        std::fs::write(dir.path().join("dpsa_pixel.v"), text.replace(from, to)).unwrap();
        let model = Model::build(&Sources::in_dir(dir.path()), &cache_dir())
            .unwrap_or_else(|e| panic!("{e}"));
        let r = cosim::run(&model, 7, 200_000, 4096).unwrap();
        println!(
            "{from} -> {to}: {} of {} pixels differ",
            r.mismatches, r.pixels
        );
        assert!(r.mismatches > 0, "mutation `{from}` -> `{to}` not caught");
        // Caught by its own effect, not because the model broke (every pixel wrong: e.g. a
        // table it could not load).
        assert!(
            r.mismatches < r.pixels / 2,
            "mutation `{from}` -> `{to}`: a broken model"
        );
    }
}
