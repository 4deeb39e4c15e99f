//! Phase of an ordinary phase-shifting image stack (real captures, any steps), with the same
//! fixed-point kernel as the pipeline and an independent f64 least squares beside it.

use crate::{Result, SimError};
use dpsa_core::fixed::types::{U16F16, U20F12, U8F8};
use dpsa_core::{bench, bench::Window, height::Scale, phase};
use dpsa_formats::calibration::wrap_phase;
use nalgebra::{DMatrix, DVector};
use serde::Serialize;
use std::path::Path;

/// Largest image `dpsa phase` decodes, pixels (64 Mpx), checked from the header before
/// decoding. Memory is about 60 bytes per pixel of one image, plus 2 bytes per pixel per image.
pub const MAX_PIXELS: u64 = 64 << 20;

/// A stack of same-size greyscale images with their phase steps.
pub struct Stack {
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Significant bits (8 or 16).
    pub bit_depth: u8,
    /// `images[j]` row-major.
    pub images: Vec<Vec<u16>>,
    /// Phase step of each image, rad: `I_j = B + C cos(Phi + step_j)`.
    pub steps_rad: Vec<f64>,
}

impl Stack {
    /// Loads PNG/JPEG/TIFF images (8 or 16 bit; colour is converted to luma).
    pub fn load(paths: &[impl AsRef<Path>], steps_deg: &[f64]) -> Result<Stack> {
        if paths.len() != steps_deg.len() {
            return Err(SimError::Refused(format!(
                "{} images but {} steps: give one --step per --image",
                paths.len(),
                steps_deg.len()
            )));
        }
        if !(3..=8).contains(&paths.len()) {
            return Err(SimError::Refused(format!(
                "a stack needs 3 to 8 images, got {}",
                paths.len()
            )));
        }
        let mut images = Vec::new();
        let mut dims = None;
        let mut bit_depth = 8;
        for p in paths {
            let p = p.as_ref();
            let reader = || -> Result<image::ImageReader<std::io::BufReader<std::fs::File>>> {
                crate::files::check_regular(p).map_err(|e| {
                    SimError::Refused(format!("{} {}", p.display(), crate::files::io_cause(&e)))
                })?;
                image::ImageReader::open(p)
                    .map_err(|e| {
                        SimError::Refused(format!("{} {}", p.display(), crate::files::io_cause(&e)))
                    })?
                    .with_guessed_format()
                    .map_err(|e| {
                        SimError::Refused(format!("{} {}", p.display(), crate::files::io_cause(&e)))
                    })
            };
            // The header first: the pixel limit is checked before anything is decoded.
            let (w, h) = reader()?
                .into_dimensions()
                .map_err(|e| SimError::Refused(format!("cannot decode {}: {e}", p.display())))?;
            let px = u64::from(w) * u64::from(h);
            if px > MAX_PIXELS {
                return Err(SimError::Refused(format!(
                    "{} is {w} x {h} = {px} pixels, more than the {MAX_PIXELS} (64 Mpx) dpsa phase takes per image",
                    p.display()
                )));
            }
            let mut limits = image::Limits::default();
            limits.max_image_width = Some(w);
            limits.max_image_height = Some(h);
            limits.max_alloc = Some(px * 8 + (1 << 20));
            let mut r = reader()?;
            r.limits(limits);
            let img = r
                .decode()
                .map_err(|e| SimError::Refused(format!("cannot decode {}: {e}", p.display())))?;
            let sixteen = matches!(
                img.color(),
                image::ColorType::L16
                    | image::ColorType::La16
                    | image::ColorType::Rgb16
                    | image::ColorType::Rgba16
            );
            let (w, h, data) = if sixteen {
                let g = img.to_luma16();
                (g.width() as usize, g.height() as usize, g.into_raw())
            } else {
                let g = img.to_luma8();
                (
                    g.width() as usize,
                    g.height() as usize,
                    g.into_raw().into_iter().map(u16::from).collect(),
                )
            };
            if sixteen {
                bit_depth = 16;
            }
            match dims {
                None => dims = Some((w, h)),
                Some(d) if d != (w, h) => {
                    return Err(SimError::Refused(format!(
                        "{} is {}x{}, the first image is {}x{}",
                        p.display(),
                        w,
                        h,
                        d.0,
                        d.1
                    )));
                }
                _ => {}
            }
            images.push(data);
        }
        let (width, height) = dims.ok_or_else(|| SimError::Refused("no images".into()))?;
        let steps_rad = steps_deg.iter().map(|d| d.to_radians()).collect();
        Ok(Stack {
            width,
            height,
            bit_depth,
            images,
            steps_rad,
        })
    }
}

/// Result of both paths on a stack.
pub struct StackPhase {
    /// Fixed-point phase (rad) per pixel, `None` where invalid.
    pub fixed: Vec<Option<f64>>,
    /// f64 least-squares phase per pixel, `None` where invalid.
    pub reference: Vec<Option<f64>>,
}

/// JSON report of `dpsa phase`.
#[derive(Serialize, Debug, Clone)]
pub struct PhaseReport {
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Pixels per image (`width x height`).
    pub total_pixels: usize,
    /// Pixels valid in both the fixed-point and the f64 result.
    pub valid_pixels: usize,
    /// Pixels valid in exactly one of the two.
    pub valid_mismatch: usize,
    /// RMS of the wrapped phase difference `fixed - ref` over the pixels valid in both,
    /// rad (0 when none).
    pub fixed_vs_ref_rms_rad: f64,
    /// Largest wrapped `|fixed - ref|` over the same pixels, rad.
    pub fixed_vs_ref_max_rad: f64,
    /// Modulation a valid pixel must reach, DN.
    pub min_modulation: f64,
    /// Noise gain `g` of the phase steps (1 for an ideal equally spaced set).
    pub noise_gain: f64,
}

/// Runs the fixed-point kernel and the f64 reference on every pixel.
///
/// A pixel is valid when no sample is saturated (`>= 2^bits - 1`) and its modulation
/// `C = sqrt(v_2^2 + v_3^2)` is at least `min_modulation` (DN).
pub fn run(stack: &Stack, min_modulation: f64) -> Result<(StackPhase, PhaseReport)> {
    let n = stack.images.len();
    let saturation: u16 = if stack.bit_depth == 8 { 255 } else { 65535 };
    // Fixed path: integer window from the steps as binary angles.
    let shifts: Vec<u32> = stack
        .steps_rad
        .iter()
        .map(|&s| phase::from_rad(s))
        .collect();
    let win = Window::solve(&shifts, U8F8::from_num(8)).map_err(|e| {
        SimError::Core(format!(
            "the phase steps give no usable solution ({e:?}): noise gain above 8"
        ))
    })?;
    let scale = Scale::from_parts(
        U16F16::ONE,
        U20F12::from_bits((min_modulation * 4096.0).round() as u32),
    );
    // The pipeline's kernel: 16-bit coefficients, 32-bit sums, the folded modulation gate.
    let coef = bench::Coef::of(&win, saturation).ok_or_else(|| {
        SimError::Core("the phase steps give coefficients too large for the kernel".into())
    })?;
    let gate = scale.gate(coef.frac);
    // f64 path: P = (M^T M)^-1 M^T with rows [1, cos s, -sin s].
    let m = DMatrix::from_fn(n, 3, |j, k| match k {
        0 => 1.0,
        1 => stack.steps_rad[j].cos(),
        _ => -stack.steps_rad[j].sin(),
    });
    let mtm = m.transpose() * &m;
    let inv = mtm
        .try_inverse()
        .ok_or_else(|| SimError::Refused("the phase steps are singular".into()))?;
    let p = inv * m.transpose();
    // Noise gain from the centred 2x2 block, for the report.
    let g = crate::reference::noise_gain(&stack.steps_rad);
    let pixels = stack.width * stack.height;
    let mut fixed = Vec::with_capacity(pixels);
    let mut reference = Vec::with_capacity(pixels);
    let mut samples = [0u16; 8];
    let mut iv = DVector::zeros(n);
    for i in 0..pixels {
        let mut sat = false;
        for j in 0..n {
            samples[j] = stack.images[j][i];
            iv[j] = samples[j] as f64;
            sat |= samples[j] >= saturation;
        }
        let v = bench::pixel_v(&coef, &samples[..n], saturation);
        fixed.push(scale.phase_v(&gate, v).ok().map(phase::to_rad));
        let v = &p * &iv;
        let c = v[1].hypot(v[2]);
        reference.push((!sat && c >= min_modulation && c > 0.0).then(|| v[2].atan2(v[1])));
    }
    let mut valid = 0;
    let mut mismatch = 0;
    let (mut sum2, mut max) = (0f64, 0f64);
    for (f, r) in fixed.iter().zip(&reference) {
        match (f, r) {
            (Some(f), Some(r)) => {
                let d = wrap_phase(f - r);
                sum2 += d * d;
                max = max.max(d.abs());
                valid += 1;
            }
            (None, None) => {}
            _ => mismatch += 1,
        }
    }
    let report = PhaseReport {
        width: stack.width,
        height: stack.height,
        total_pixels: pixels,
        valid_pixels: valid,
        valid_mismatch: mismatch,
        fixed_vs_ref_rms_rad: if valid > 0 {
            (sum2 / valid as f64).sqrt()
        } else {
            0.0
        },
        fixed_vs_ref_max_rad: max,
        min_modulation,
        noise_gain: g,
    };
    Ok((StackPhase { fixed, reference }, report))
}
