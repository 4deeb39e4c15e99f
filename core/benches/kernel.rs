//! Host benchmark of the per-pixel kernel (`v = P i`, phase, height, mask) and of the whole
//! streaming pipeline. Host times are context only; the firmware benchmark reports Cortex-M7
//! instruction counts.
//!
//! `cargo bench -p dpsa-core --bench kernel`

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use dpsa_core::{
    bench,
    bench::Window,
    fixed::types::{U16F16, U20F12, U8F8},
    height::Scale,
    phase::from_rad,
    pipeline::{Pipeline, State},
    Config, Row, Sink, Trigger,
};
use std::hint::black_box;

const W: usize = 2048;

fn config() -> Config {
    Config {
        width: W as u16,
        rows: 40,
        n: 4,
        camera: 0,
        counts_per_pixel: U16F16::from_num(10),
        fx: 1 << 27,
        lsb_per_turn: U16F16::from_num(2000),
        saturation: 4095,
        min_modulation: U20F12::from_num(60),
        max_noise_gain: U8F8::from_num(2),
        max_step_rows: 10,
    }
}

/// Four lines of a flat board seen with shifts 0, -99, -180, -281 degrees.
fn lines() -> Vec<Vec<u16>> {
    let th = [0.0f64, -99.0, -180.0, -281.0];
    th.iter()
        .map(|t| {
            (0..W)
                .map(|c| (1800.0 + 700.0 * (0.3 + 0.01 * c as f64 + t.to_radians()).cos()) as u16)
                .collect()
        })
        .collect()
}

fn kernel(c: &mut Criterion) {
    let cfg = config();
    let th = [0.0f64, -99.0, -180.0, -281.0];
    let shifts: Vec<u32> = th.iter().map(|t| from_rad(t.to_radians())).collect();
    let win = Window::solve(&shifts, U8F8::from_num(2)).unwrap();
    let scale = Scale::new(&cfg);
    let l = lines();
    let refp: Vec<u32> = (0..W).map(|c| from_rad(0.01 * c as f64)).collect();
    let mut g = c.benchmark_group("kernel");
    g.throughput(Throughput::Elements(W as u64));
    g.bench_function(BenchmarkId::new("row", W), |b| {
        let mut out = vec![0i16; W];
        b.iter(|| {
            for col in 0..W {
                let s = [l[0][col], l[1][col], l[2][col], l[3][col]];
                let acc = bench::pixel(&win, &s, cfg.saturation);
                out[col] = scale.pixel(&acc, refp[col]).unwrap_or(0);
            }
            black_box(&out);
        })
    });
    g.finish();
    // The phase + height stage alone, every build this CPU runs (`Kernel::all`), over the
    // reduced pixels of the same row.
    let coef = bench::Coef::of(&win, cfg.saturation).unwrap();
    let gate = scale.gate(coef.frac);
    let v: Vec<bench::V> = (0..W)
        .map(|col| {
            let s = [l[0][col], l[1][col], l[2][col], l[3][col]];
            bench::pixel_v(&coef, &s, cfg.saturation)
        })
        .collect();
    // The accumulate stage alone on the same four lines as a packed pool holds them
    // (Mono12p), 64 columns a call as the pipeline makes them, every build this CPU runs.
    let packed: Vec<Vec<u8>> = l
        .iter()
        .map(|line| {
            let mut b = vec![0u8; dpsa_core::frames::mono12p::stored_len(W)];
            dpsa_core::frames::mono12p::pack(line, &mut b);
            b
        })
        .collect();
    let pl: Vec<&[u8]> = packed.iter().map(|b| &b[..]).collect();
    let mut g = c.benchmark_group("accumulate_packed");
    g.throughput(Throughput::Elements(W as u64));
    for k in dpsa_core::lanes::Kernel::all() {
        g.bench_function(BenchmarkId::new(k.name(), W), |b| {
            let mut out = vec![[0i32; 2]; 64];
            b.iter(|| {
                for c0 in (0..W).step_by(64) {
                    bench::block_packed_with(
                        k,
                        &coef,
                        black_box(&pl),
                        c0,
                        cfg.saturation,
                        &mut out,
                    );
                    black_box(&out);
                }
            })
        });
    }
    g.finish();
    // The same on 16-bit lines (the pool of a camera of more than 12 bits).
    let wide: Vec<&[u16]> = l.iter().map(|line| &line[..]).collect();
    let mut g = c.benchmark_group("accumulate_wide");
    g.throughput(Throughput::Elements(W as u64));
    for k in dpsa_core::lanes::Kernel::all() {
        g.bench_function(BenchmarkId::new(k.name(), W), |b| {
            let mut out = vec![[0i32; 2]; 64];
            b.iter(|| {
                for c0 in (0..W).step_by(64) {
                    bench::block_with(k, &coef, black_box(&wide), c0, cfg.saturation, &mut out);
                    black_box(&out);
                }
            })
        });
    }
    g.finish();
    let mut g = c.benchmark_group("phase_height");
    g.throughput(Throughput::Elements(W as u64));
    for k in dpsa_core::lanes::Kernel::all() {
        g.bench_function(BenchmarkId::new(k.name(), W), |b| {
            let (mut h, mut m) = (vec![0i16; W], vec![0u8; W / 8]);
            b.iter(|| black_box(k.row(&scale, &gate, black_box(&v), 0, &refp, &mut h, &mut m)))
        });
    }
    g.finish();
    c.bench_function("solve/window n=4", |b| {
        b.iter(|| Window::solve(black_box(&shifts), U8F8::from_num(2)))
    });
}

struct Null;
impl Sink for Null {
    type Error = ();
    fn row(&mut self, r: &Row<'_>) -> Result<(), ()> {
        black_box(r.heights);
        Ok(())
    }
}

fn pipeline(c: &mut Criterion) {
    let cfg = config();
    let refp = vec![0u32; W];
    // Fringe phase 2 pi r / 32 along the rows, as the projector throws it.
    let frame: Vec<Vec<u16>> = (0..cfg.rows as usize)
        .map(|r| {
            (0..W)
                .map(|c| {
                    (1800.0
                        + 700.0 * (r as f64 / 32.0 * std::f64::consts::TAU + 0.01 * c as f64).cos())
                        as u16
                })
                .collect()
        })
        .collect();
    let mut g = c.benchmark_group("pipeline");
    // 8 new rows per frame at the default 8 px step.
    g.throughput(Throughput::Elements(8 * W as u64));
    g.bench_function("frame 40x2048 n=4", |b| {
        let mut state = State::new(&cfg);
        let mut p = Pipeline::new(cfg, &refp, state.memory()).unwrap();
        let mut k = 0u32;
        b.iter(|| {
            p.begin_frame(
                Trigger {
                    seq: k,
                    latch: k as i64 * 80,
                },
                &mut Null,
            )
            .unwrap();
            for (r, line) in frame.iter().enumerate() {
                p.push_line(r as u16, line, &mut Null).unwrap();
            }
            p.end_frame(&mut Null).unwrap();
            k += 1;
        })
    });
    g.finish();
}

criterion_group!(benches, kernel, pipeline);
criterion_main!(benches);
