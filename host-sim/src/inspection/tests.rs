//! The measurement and registration against a synthetic map with known deposits: openings,
//! printed deposits (shifted, scaled, missing, bridged), fiducials, a warped board, pixel
//! integration and noise, all written here independently of the simulator.

use super::map::BoardMap;
use super::measure::{measure_all, Instructions, PadMeasurement, Placed};
use super::pads::{Outline, Pad, Point, Rigid};
use super::program::Program;
use super::register::register;
use super::verdict::{judge, Class, Level};
use crate::board::resample::BoardGrid;
use crate::board::Grid;
use crate::error::chain;
use dpsa_inspect::noise::NoiseModel;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

struct Dep {
    outline: Outline,
    height: f64,
    wall: f64,
}

fn smooth(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

impl Dep {
    fn at(&self, q: Point) -> f64 {
        let d = self.outline.signed_distance(q);
        if d >= 0.0 {
            0.0
        } else {
            self.height * smooth(-d / self.wall)
        }
    }
}

/// Volume by integration on a 2 um grid, um mm^2.
fn volume(d: &Dep) -> f64 {
    let b = d.outline.bbox();
    let s = 0.002;
    let mut v = 0.0;
    let mut x = b[0] + s / 2.0;
    while x < b[2] {
        let mut y = b[1] + s / 2.0;
        while y < b[3] {
            v += d.at([x, y]);
            y += s;
        }
        x += s;
    }
    v * s * s
}

fn warp(q: Point) -> f64 {
    20.0 + 3.0 * q[0] - 2.0 * q[1] + 0.4 * (q[0] - 6.0).powi(2)
}

struct Scene {
    map: BoardMap,
    pads: Vec<Pad>,
    program: Program,
    truth_t: Rigid,
    deps: Vec<(usize, Dep)>,
}

fn pad(i: usize, outline: Outline) -> Pad {
    Pad {
        index: i,
        outline,
        component: Some(format!("U{}", i / 4)),
        pin: Some(format!("{}", i % 4 + 1)),
        aperture: None,
    }
}

fn rr(c: Point, w: f64, h: f64) -> Outline {
    Outline::RoundRect {
        centre: c,
        size: [w, h],
        radius: 0.0,
        rotation_deg: 0.0,
    }
}

/// The map of `deps` on a warped board: pixel integration (4 x 4), noise, a few invalid
/// pixels.
fn render(grid: &BoardGrid, deps: &[(usize, Dep)], seed: u64) -> Vec<f32> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0, 1.3).unwrap();
    let mut data = vec![0f32; grid.rows * grid.width];
    for i in 0..grid.rows {
        for j in 0..grid.width {
            let (x, y) = grid.centre(i, j);
            let mut s = 0.0;
            // Pixel integration, 4 x 4 sub-samples.
            for a in 0..4 {
                for b in 0..4 {
                    let q = [
                        x + (f64::from(a) - 1.5) / 4.0 * grid.pitch_mm,
                        y + (f64::from(b) - 1.5) / 4.0 * grid.pitch_mm,
                    ];
                    let mut h = warp(q);
                    for (_, d) in deps {
                        let bb = d.outline.bbox();
                        if q[0] > bb[0] - 0.01
                            && q[0] < bb[2] + 0.01
                            && q[1] > bb[1] - 0.01
                            && q[1] < bb[3] + 0.01
                        {
                            h += d.at(q);
                        }
                    }
                    s += h;
                }
            }
            data[i * grid.width + j] = (s / 16.0 + noise.sample(&mut rng)) as f32;
        }
    }
    // A few invalid pixels.
    for k in 0..200 {
        let n = data.len();
        data[(k * 7919) % n] = f32::NAN;
    }
    data
}

fn scene(seed: u64) -> Scene {
    let pads = vec![
        pad(0, rr([3.0, 3.0], 1.0, 0.6)),
        pad(1, rr([3.0, 4.5], 1.0, 0.6)), // nominal
        pad(2, rr([5.0, 3.0], 0.6, 0.6)), // missing
        pad(3, rr([5.0, 4.0], 0.6, 0.6)), // bridged to 4 (gap 0.3)
        pad(4, rr([5.0, 4.9], 0.6, 0.6)),
        pad(5, rr([7.0, 3.0], 0.8, 0.8)), // offset by 0.3 along x
        pad(
            6,
            Outline::Circle {
                centre: [7.0, 5.0],
                diameter: 0.6,
            },
        ), // excess
        pad(7, rr([9.0, 3.0], 0.9, 0.9)), // insufficient
        pad(
            8,
            Outline::RoundRect {
                centre: [9.0, 5.0],
                size: [1.2, 0.5],
                radius: 0.1,
                rotation_deg: 30.0,
            },
        ),
    ];
    let fids: Vec<Point> = vec![[1.0, 1.0], [11.0, 1.0], [1.0, 8.0]];
    let t = Rigid {
        rotation_rad: 0.2f64.to_radians(),
        tx: 0.2,
        ty: -0.15,
    };
    let stencil = 100.0;
    let mut deps: Vec<(usize, Dep)> = Vec::new();
    for p in &pads {
        let o = p.outline.transformed(&t);
        let (h, o) = match p.index {
            2 => continue,
            5 => (
                95.0,
                o.transformed(&Rigid {
                    rotation_rad: 0.0,
                    tx: 0.3 * t.rotation_rad.cos(),
                    ty: 0.3 * t.rotation_rad.sin(),
                }),
            ),
            6 => (170.0, o),
            7 => (35.0, o),
            _ => (95.0, o),
        };
        deps.push((
            p.index,
            Dep {
                outline: o,
                height: h,
                wall: 0.03,
            },
        ));
    }
    // The bridge: a strip joining 3 and 4, 70 um.
    deps.push((
        3,
        Dep {
            outline: rr([5.0, 4.45], 0.2, 0.5).transformed(&t),
            height: 70.0,
            wall: 0.02,
        },
    ));
    for f in &fids {
        deps.push((
            usize::MAX,
            Dep {
                outline: Outline::Circle {
                    centre: t.apply(*f),
                    diameter: 1.0,
                },
                height: 35.0,
                wall: 0.01,
            },
        ));
    }
    let grid = BoardGrid {
        x0_mm: 0.0,
        y0_mm: 0.0,
        pitch_mm: 0.0278,
        rows: 432,
        width: 324,
    };
    let data = render(&grid, &deps, seed);
    let mut program = Program::new("x.gbr");
    program.stencil_um = stencil;
    program.fiducials.points_mm = fids;
    Scene {
        map: BoardMap {
            board_id: None,
            grid,
            heights: Grid {
                width: grid.width,
                rows: grid.rows,
                data,
            },
        },
        pads,
        program,
        truth_t: t,
        deps,
    }
}

/// Every pad of `s` measured with the openings placed by `t`, on `instructions`.
fn measured(s: &Scene, t: &Rigid, instructions: Instructions) -> Vec<PadMeasurement> {
    let placed = Placed::new(&s.pads, t, &s.program.fiducials.points_mm, 1.0);
    let noise = NoiseModel::measure(&s.map, &placed, s.program.measure.surface_guard_mm);
    measure_all(
        instructions,
        &s.map,
        &s.pads,
        &placed,
        t,
        &s.program,
        &noise,
    )
}

#[test]
fn registration_measurement_and_verdicts_on_a_known_board() {
    let s = scene(5);
    let reg = register(&s.map, &s.program).unwrap();
    // Registration against the true transform, at the pads.
    for p in &s.pads {
        let c = p.outline.centroid();
        let (a, b) = (reg.transform.apply(c), s.truth_t.apply(c));
        let e = (a[0] - b[0]).hypot(a[1] - b[1]) * 1000.0;
        assert!(e < 3.0, "pad {} placed {e:.2} um off", p.index);
    }
    assert!(reg.residual_um < 3.0, "{reg:?}");
    let m = measured(&s, &reg.transform, Instructions::best());
    for p in &s.pads {
        let k = p.index;
        let truth: f64 = s
            .deps
            .iter()
            .filter(|(i, _)| *i == k)
            .map(|(_, d)| volume(d))
            .sum();
        let truth_pct = 100.0 * truth / (p.outline.area() * s.program.stencil_um);
        let call = judge(&m[k], &s.program.windows_for(p));
        eprintln!(
            "pad {k}: volume {:.2} % (truth {truth_pct:.2}), height {:.2} um, offset {:?} um, area {:.1} %, shape {:.1} %, {:?}",
            m[k].volume_pct, m[k].height_um, m[k].offset_um, m[k].area_pct, m[k].shape_pct, call
        );
        assert!(m[k].unmeasurable.is_none());
        if k != 3 && k != 4 {
            assert!(
                (m[k].volume_pct - truth_pct).abs() < 1.5,
                "pad {k}: {:.2} vs {truth_pct:.2}",
                m[k].volume_pct
            );
        }
        let expect = match k {
            2 => Some(Class::Missing),
            3 | 4 => Some(Class::Bridge),
            5 => Some(Class::Offset),
            6 => Some(Class::Excess),
            7 => Some(Class::Insufficient),
            _ => None,
        };
        match expect {
            Some(c) => assert_eq!((call.level, call.class), (Level::Fail, Some(c)), "pad {k}"),
            None => assert_ne!(call.level, Level::Fail, "pad {k}: {call:?}"),
        }
    }
    // The offset pad: 300 um along the design x.
    assert!((m[5].offset_um[0] - 300.0).abs() < 10.0 && m[5].offset_um[1].abs() < 10.0);
    // Nominal pads: height over the opening's interior is the printed 95 um.
    for k in [0, 1, 8] {
        assert!(
            (m[k].height_um - 95.0).abs() < 1.0,
            "pad {k}: {}",
            m[k].height_um
        );
        assert!(m[k].offset_um[0].abs() < 5.0 && m[k].offset_um[1].abs() < 5.0);
    }
}

/// The per-pad work gives the same values to the bit on the baseline instructions and on
/// AVX2 (where this processor has it), on boards with bridges, smears, missing and offset
/// deposits, and a pad over invalid pixels.
#[test]
fn the_measurement_is_the_same_on_every_instruction_set() {
    if Instructions::best() != Instructions::Avx2 {
        eprintln!("this processor has no AVX2: the baseline against itself");
    }
    for seed in [5, 6, 8] {
        let mut s = scene(seed);
        let reg = register(&s.map, &s.program).unwrap();
        if seed == 6 {
            let o = s.pads[1].outline.transformed(&reg.transform);
            let (ri, rj) = s.map.window(o.bbox());
            for i in ri {
                for j in rj.clone() {
                    s.map.heights.data[i * s.map.grid.width + j] = f32::NAN;
                }
            }
        }
        let on = |i| {
            // Every float in its shortest exact decimal (NaN as null): equal text, equal bits.
            measured(&s, &reg.transform, i)
                .iter()
                .map(|p| serde_json::to_string(p).unwrap())
                .collect::<Vec<_>>()
        };
        let (base, avx2) = (on(Instructions::Baseline), on(Instructions::Avx2));
        assert_eq!(base.len(), s.pads.len());
        for (k, (a, b)) in base.iter().zip(&avx2).enumerate() {
            assert_eq!(a, b, "seed {seed}, pad {k}");
        }
    }
}

#[test]
fn pads_off_the_map_or_on_invalid_pixels_are_not_measurable() {
    let mut s = scene(6);
    let reg = register(&s.map, &s.program).unwrap();
    // Invalidate pad 1's opening.
    let o = s.pads[1].outline.transformed(&reg.transform);
    let (ri, rj) = s.map.window(o.bbox());
    for i in ri {
        for j in rj.clone() {
            s.map.heights.data[i * s.map.grid.width + j] = f32::NAN;
        }
    }
    s.pads.push(pad(9, rr([30.0, 3.0], 0.5, 0.5)));
    let m = measured(&s, &reg.transform, Instructions::best());
    for k in [1, 9] {
        let call = judge(&m[k], &s.program.windows);
        assert_eq!(
            (call.level, call.class),
            (Level::Fail, Some(Class::NotMeasurable)),
            "pad {k}"
        );
    }
}

#[test]
fn missing_fiducials_are_an_error() {
    let mut s = scene(7);
    s.program.fiducials.points_mm = vec![[1.0, 1.0], [6.0, 8.5], [11.5, 8.5]];
    let e = register(&s.map, &s.program).unwrap_err().to_string();
    assert!(e.contains("found 1 of 3"), "{e}");
    s.program.fiducials.points_mm.clear();
    assert!(register(&s.map, &s.program).is_err());
}

#[test]
fn truth_comparison_and_report_files() {
    let s = scene(8);
    let i = super::run::inspect(&s.map, &s.pads, &s.program).unwrap();
    let deps = &s.deps;
    let height = |q: Point| -> f64 {
        deps.iter()
            .filter(|(k, _)| *k != usize::MAX)
            .map(|(_, d)| d.at(q))
            .sum()
    };
    let defects: Vec<Option<String>> = (0..s.pads.len())
        .map(|k| match k {
            2 => Some("missing".to_string()),
            3 | 4 => Some("bridge".into()),
            5 => Some("offset".into()),
            6 => Some("excess".into()),
            7 => Some("insufficient".into()),
            _ => None,
        })
        .collect();
    let truth = super::evaluate::PrintTruthView {
        transform: s.truth_t,
        defects,
        height: &height,
    };
    let e = super::evaluate::evaluate(&i, &s.pads, &s.program, &truth);
    let tp = &e.pads;
    // The truth's volume by the cell equals the deposit's own (the cells hold them whole).
    for k in [0usize, 1, 6, 7, 8] {
        let v: f64 = s
            .deps
            .iter()
            .filter(|(j, _)| *j == k)
            .map(|(_, d)| volume(d))
            .sum();
        let pct = 100.0 * v / (s.pads[k].outline.area() * s.program.stencil_um);
        assert!(
            (tp[k].volume_pct - pct).abs() < 0.3,
            "pad {k}: {} vs {pct}",
            tp[k].volume_pct
        );
        assert!(
            (tp[k].height_um
                - if k == 6 {
                    170.0
                } else if k == 7 {
                    35.0
                } else {
                    95.0
                })
            .abs()
                < 0.5
        );
    }
    assert!((tp[5].offset_um[0] - 300.0).abs() < 2.0);
    let r = super::evaluate::with_evaluation(
        super::run::InspectionReport::build("b", "p", &i, &s.pads, 0.0),
        &e,
    );
    let d = &e.detection;
    assert_eq!(
        (
            d.injected,
            d.detected,
            d.missed,
            d.wrong_class,
            d.false_fail
        ),
        (6, 6, 0, 0, 0),
        "{d:?}"
    );
    let t = &e.report;
    let v = t.large.volume_err_pct.as_ref().unwrap();
    assert!(v.n == 3 && v.rms < 1.0, "{v:?}");
    assert!(t.registration_error_um < 3.0);
    // The report carries them as `truth.*` and `detection`, where they were before the split.
    let json = serde_json::to_value(&r).unwrap();
    let keys: Vec<&str> = json
        .as_object()
        .unwrap()
        .keys()
        .map(|k| k.as_str())
        .collect();
    assert_eq!(json["truth"]["volume_err_pct"]["n"], 3);
    assert_eq!(json["detection"]["injected"], 6);
    let text = serde_json::to_string(&r).unwrap();
    let at = |k: &str| text.find(&format!("\"{k}\":")).unwrap();
    assert!(at("registration") < at("truth") && at("truth") < at("detection"));
    assert!(at("detection") < at("timing"), "{keys:?}");
    assert!(r.summary().contains("defects: 6 injected, 6 detected"));

    let dir = tempfile::tempdir().unwrap();
    let value = serde_json::to_value(&r).unwrap();
    let n = super::report::write(
        dir.path(),
        &s.map,
        &s.pads,
        &i,
        &s.program,
        &value,
        super::report::Names {
            unit: "b",
            recipe: "p",
        },
        || Ok(value.clone()),
    )
    .unwrap();
    assert_eq!(n, 6);
    let csv = std::fs::read_to_string(dir.path().join("pads.csv")).unwrap();
    assert_eq!(csv.lines().count(), s.pads.len() + 1);
    assert!(csv.lines().nth(3).unwrap().contains("Failed"));
    let cfx: serde_json::Value = serde_json::from_slice(
        &std::fs::read(dir.path().join("cfx_units_inspected.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(
        cfx["MessageName"],
        "CFX.Production.TestAndInspection.UnitsInspected"
    );
    let unit = &cfx["MessageBody"]["InspectedUnits"][0];
    assert_eq!(unit["OverallResult"], "Failed");
    assert_eq!(
        unit["Inspections"][0]["Measurements"]
            .as_array()
            .unwrap()
            .len(),
        s.pads.len()
    );
    assert_eq!(
        unit["Inspections"][0]["DefectsFound"]
            .as_array()
            .unwrap()
            .len(),
        6
    );
    if let Ok(keep) = std::env::var("DPSA_KEEP_INSPECTION") {
        let _ = std::fs::remove_dir_all(&keep);
        let _ = std::process::Command::new("cp")
            .arg("-r")
            .arg(dir.path())
            .arg(&keep)
            .status();
    }
    // The overview: board x to the right (the map's rows across), y up, with its margins.
    let ov = image::open(dir.path().join("overview.png")).unwrap();
    let frame = dpsa_inspect::report::OverviewFrame::of(&s.map.grid, 2400);
    assert_eq!(frame.size, (s.map.grid.rows, s.map.grid.width));
    assert_eq!((ov.width(), ov.height()), frame.image);
}

/// Without fiducials the design is registered by its paste pattern: the same board as
/// above (a missing, a bridged and an offset deposit among nine) placed within a few um of
/// the true transform, and the report says so.
#[test]
fn registration_by_the_paste_pattern_without_fiducials() {
    let mut s = scene(5);
    s.program.fiducials.points_mm.clear();
    let reg = super::register_paste::register_paste(&s.map, &s.pads, &s.program).unwrap();
    assert_eq!(reg.method, "paste pattern");
    assert!(reg.fiducials.is_empty());
    let used = reg.pads_used.unwrap();
    assert!((5..=8).contains(&used), "{used} pads used");
    let mut worst: f64 = 0.0;
    for p in &s.pads {
        let c = p.outline.centroid();
        let (a, b) = (reg.transform.apply(c), s.truth_t.apply(c));
        let e = (a[0] - b[0]).hypot(a[1] - b[1]) * 1000.0;
        assert!(e < 6.0, "pad {} placed {e:.2} um off", p.index);
        worst = worst.max(e);
    }
    eprintln!(
        "paste pattern: {used} pads kept, residual {:.1} um, worst pad {worst:.1} um from the truth",
        reg.residual_um
    );
    assert!(reg.residual_um < 6.0, "{}", reg.residual_um);
    // `inspect` takes it when the program lists no fiducials; the summary names it.
    let i = super::run::inspect(&s.map, &s.pads, &s.program).unwrap();
    assert_eq!(i.registration.method, "paste pattern");
}

/// Thirty openings of random sizes at random places (no pattern that repeats), printed at a
/// true placement 1.2 mm and 0.3 deg from the program's nominal one: found within a few um.
#[test]
fn registration_by_the_paste_pattern_finds_a_board_far_from_its_nominal_place() {
    use rand::RngExt;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(41);
    let mut pads: Vec<Pad> = Vec::new();
    for _ in 0..100_000 {
        if pads.len() == 30 {
            break;
        }
        let c = [rng.random_range(2.0..10.0), rng.random_range(2.0..7.0)];
        let (w, h) = (rng.random_range(0.2..0.8), rng.random_range(0.2..0.8));
        let o = rr(c, w, h);
        let b = o.bbox();
        // Keep openings 0.3 mm apart.
        if pads.iter().all(|p| {
            let q = p.outline.bbox();
            b[0] > q[2] + 0.3 || q[0] > b[2] + 0.3 || b[1] > q[3] + 0.3 || q[1] > b[3] + 0.3
        }) {
            pads.push(pad(pads.len(), o));
        }
    }
    assert_eq!(pads.len(), 30, "placing the openings");
    let truth = Rigid {
        rotation_rad: 0.1f64.to_radians(),
        tx: 0.3,
        ty: -0.2,
    };
    let deps: Vec<(usize, Dep)> = pads
        .iter()
        .map(|p| {
            (
                p.index,
                Dep {
                    outline: p.outline.transformed(&truth),
                    height: 95.0,
                    wall: 0.03,
                },
            )
        })
        .collect();
    let s = scene(9);
    let map = BoardMap {
        heights: Grid {
            data: render(&s.map.grid, &deps, 9),
            ..s.map.heights.clone()
        },
        ..s.map.clone()
    };
    let mut program = s.program.clone();
    program.fiducials.points_mm.clear();
    // Nominal: the true placement's shift less (1.2, -0.6) mm, turned 0.3 deg less.
    program.placement.orientation_deg = 0.1 - 0.3;
    let a = program.placement.orientation_deg.to_radians();
    let (sn, cs) = a.sin_cos();
    let (tx, ty) = (truth.tx - 1.2, truth.ty + 0.6);
    // nominal(p) = R(a) p + t, with t = -R(a) origin.
    program.placement.design_origin_mm = [-(cs * tx + sn * ty), -(-sn * tx + cs * ty)];
    let reg = super::register_paste::register_paste(&map, &pads, &program).unwrap();
    assert_eq!(reg.pads_used, Some(30));
    for p in &pads {
        let c = p.outline.centroid();
        let (a, b) = (reg.transform.apply(c), truth.apply(c));
        let e = (a[0] - b[0]).hypot(a[1] - b[1]) * 1000.0;
        assert!(e < 6.0, "pad {} placed {e:.2} um off", p.index);
    }
    assert!(
        (reg.shift_mm[0] - 1.2).hypot(reg.shift_mm[1] + 0.6) < 0.05,
        "{:?}",
        reg.shift_mm
    );
}

/// A board with no paste, and a pattern that repeats (one row of equal pads at a 0.5 mm
/// pitch) are refused, never registered at a plausible wrong place.
#[test]
fn registration_by_the_paste_pattern_refuses_what_it_cannot_tell() {
    let mut s = scene(6);
    s.program.fiducials.points_mm.clear();
    let flat = BoardMap {
        heights: Grid {
            data: render(&s.map.grid, &[], 6),
            ..s.map.heights.clone()
        },
        ..s.map.clone()
    };
    let e = super::register_paste::register_paste(&flat, &s.pads, &s.program)
        .unwrap_err()
        .to_string();
    assert!(e.contains("was not found"), "{e}");

    let row: Vec<Pad> = (0..16)
        .map(|k| pad(k, rr([2.0 + 0.5 * k as f64, 4.0], 0.25, 0.8)))
        .collect();
    let deps: Vec<(usize, Dep)> = row
        .iter()
        .map(|p| {
            (
                p.index,
                Dep {
                    outline: p.outline.clone(),
                    height: 95.0,
                    wall: 0.03,
                },
            )
        })
        .collect();
    let periodic = BoardMap {
        heights: Grid {
            data: render(&s.map.grid, &deps, 6),
            ..s.map.heights.clone()
        },
        ..s.map.clone()
    };
    let e = super::register_paste::register_paste(&periodic, &row, &s.program)
        .unwrap_err()
        .to_string();
    assert!(e.contains("repeats"), "{e}");
}

#[test]
fn an_evaluation_error_reaches_the_caller_with_its_whole_chain() {
    // A print truth that is not one: the evaluation's error, through `InspectError`, prints
    // as the print truth's own error does (its sentence, then the parser's), as it did when
    // the inspection returned `anyhow`.
    let s = scene(5);
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("print.json");
    std::fs::write(&bad, b"{nope").unwrap();
    let Err(direct) = super::simulated::PrintTruth::load(&bad, s.pads.len()) else {
        panic!("{{nope is not a print truth");
    };
    let direct = chain(&direct);
    assert!(direct.contains("is not a dpsa print truth: "), "{direct}");
    let i = super::run::inspect(&s.map, &s.pads, &s.program).unwrap();
    let mut ev = super::evaluate::PrintEvaluation::new(&bad, dir.path());
    let e = super::run::Evaluate::evaluate(&mut ev, &s.map, &s.pads, &s.program, &i, false)
        .unwrap_err();
    let through = dpsa_inspect::InspectError::Evaluation(e);
    assert_eq!(chain(&through), direct);
}
