//! One set of range checks for the camera, calibration and processing blocks, shared by scene
//! files (the simulator's `Scene::validate`), manifests ([`Manifest::validate`](super::Manifest::validate))
//! and calibration files ([`CalFile::validate`](crate::calibration::CalFile::validate)).
//!
//! The ranges are exactly what the fixed-point core accepts (`dpsa_stream::config::core_config` and
//! `dpsa_core::Config::validate`), so a scene or manifest that loads never fails later in the
//! core. [`warnings`] lists settings that are legal but make the result useless.

use super::{max_value, Calibration, Camera, Processing, MAX_ROWS, MAX_WIDTH};

/// Largest number of raw lines in the core's line pool (`max_step_rows * n (n-1) / 2`): slot
/// indices are `u16`.
pub const MAX_POOL_LINES: u64 = u16::MAX as u64;

/// A value out of range: the manifest field (`block.name`) and a sentence.
#[derive(Clone, Debug, PartialEq)]
pub struct Invalid {
    /// The field, as the manifest spells it (`calibration.fringe_period_px`).
    pub field: String,
    /// What is wrong with it, one sentence.
    pub message: String,
}

fn check(ok: bool, field: &str, message: impl FnOnce() -> String) -> Result<(), Invalid> {
    if ok {
        Ok(())
    } else {
        Err(Invalid {
            field: field.into(),
            message: message(),
        })
    }
}

/// Checks the camera, calibration and processing blocks (manifest field names).
pub fn check_blocks(cam: &Camera, cal: &Calibration, p: &Processing) -> Result<(), Invalid> {
    check((1..=MAX_WIDTH).contains(&cam.width), "camera.width", || {
        format!("{} px, expected 1..={MAX_WIDTH}", cam.width)
    })?;
    check((1..=MAX_ROWS).contains(&cam.rows), "camera.rows", || {
        format!("{} px, expected 1..={MAX_ROWS}", cam.rows)
    })?;
    check(
        (8..=16).contains(&cam.bit_depth),
        "camera.bit_depth",
        || format!("{} bits, expected 8..=16", cam.bit_depth),
    )?;
    let max = max_value(cam.bit_depth);
    check(
        (1..=max).contains(&cam.saturation),
        "camera.saturation",
        || {
            format!(
                "{} DN, expected 1..={max} (2^bit_depth - 1 for bit_depth {}): a higher threshold lets clipped samples pass as valid",
                cam.saturation, cam.bit_depth
            )
        },
    )?;

    check_calibration(cal, cam.width)?;

    check((3..=8).contains(&p.n), "processing.n", || {
        format!("{}, expected 3..=8", p.n)
    })?;
    check(
        (1..=cam.rows).contains(&p.max_step_rows),
        "processing.max_step_rows",
        || {
            format!(
                "{} rows, expected 1..={} (camera.rows)",
                p.max_step_rows, cam.rows
            )
        },
    )?;
    let per_row = u64::from(p.n) * u64::from(p.n.saturating_sub(1)) / 2;
    let lines = u64::from(p.max_step_rows) * per_row;
    check(lines <= MAX_POOL_LINES, "processing.max_step_rows", || {
        format!(
            "{} rows need a line pool of {lines} lines (max_step_rows * n (n-1) / 2 with n = {}), the core holds at most {MAX_POOL_LINES} (max_step_rows <= {})",
            p.max_step_rows,
            p.n,
            MAX_POOL_LINES / per_row.max(1)
        )
    })?;
    check(
        p.min_modulation.is_finite() && p.min_modulation >= 0.0,
        "processing.min_modulation",
        || format!("{} DN, expected a finite value >= 0", p.min_modulation),
    )?;
    check(
        (p.min_modulation * 4096.0).round() <= f64::from(u32::MAX),
        "processing.min_modulation",
        || {
            format!(
                "{} DN, expected below 1048576 (the core's Q20.12 threshold)",
                p.min_modulation
            )
        },
    )?;
    check(
        (1.0..=8.0).contains(&p.max_noise_gain),
        "processing.max_noise_gain",
        || format!("{}, expected 1..=8", p.max_noise_gain),
    )?;
    Ok(())
}

/// Checks a calibration block for frames `width` px wide: what the core takes (the encoder
/// step, fringe period, reference-phase table, height scale and its per-column table). Also
/// used on every camera of an array calibration file (`calibration::file`).
pub fn check_calibration(cal: &Calibration, width: u32) -> Result<(), Invalid> {
    let cpp = cal.counts_per_pixel;
    let q16 = cpp * 65536.0;
    check(
        cpp.is_finite() && cpp > 0.0,
        "calibration.counts_per_pixel",
        || format!("{cpp} counts/px, expected a finite value > 0"),
    )?;
    check(
        q16.fract() == 0.0 && (1.0..4_294_967_296.0).contains(&q16),
        "calibration.counts_per_pixel",
        || {
            format!("{cpp} counts/px is not a multiple of 2^-16 in 2^-16 ..< 65536 (counts_per_pixel * 65536 = {q16} must be an integer in 1 ..< 2^32)")
        },
    )?;
    check(
        cal.fringe_period_px.is_finite() && cal.fringe_period_px >= 2.0,
        "calibration.fringe_period_px",
        || format!("{} px, expected a finite value >= 2", cal.fringe_period_px),
    )?;
    check(
        cal.reference_phase_rad.len() == width as usize,
        "calibration.reference_phase_rad",
        || {
            format!(
                "{} values, expected one per column ({})",
                cal.reference_phase_rad.len(),
                width
            )
        },
    )?;
    if let Some(c) = cal.reference_phase_rad.iter().position(|p| !p.is_finite()) {
        check(
            false,
            &format!("calibration.reference_phase_rad[{c}]"),
            || {
                format!(
                    "{}, expected a finite phase (rad)",
                    cal.reference_phase_rad[c]
                )
            },
        )?;
    }
    for (v, field) in [
        (cal.height_per_turn_um, "calibration.height_per_turn_um"),
        (cal.height_lsb_um, "calibration.height_lsb_um"),
    ] {
        check(v.is_finite() && v > 0.0, field, || {
            format!("{v} um, expected a finite value > 0")
        })?;
    }
    let turn_lsb = cal.height_per_turn_um / cal.height_lsb_um;
    check(turn_lsb < 32768.0, "calibration.height_per_turn_um", || {
        format!(
            "one fringe turn is {turn_lsb} LSB (height_per_turn_um {} / height_lsb_um {}), expected < 32768 so it fits the i16 output",
            cal.height_per_turn_um, cal.height_lsb_um
        )
    })?;
    let turn_q16 = (turn_lsb * 65536.0).round();
    check(
        (1.0..2_147_483_648.0).contains(&turn_q16),
        "calibration.height_per_turn_um",
        || {
            format!(
                "one fringe turn is {turn_lsb:e} LSB (height_per_turn_um {:e} / height_lsb_um {}), which the core's Q16.16 LSB-per-turn cannot hold (expected 2^-16 ..< 32768 LSB)",
                cal.height_per_turn_um, cal.height_lsb_um
            )
        },
    )?;
    column_scale_table(cal, width)?;
    Ok(())
}

/// The core's per-column height-scale table of a calibration block: `None` without
/// `height_per_turn_um_per_column`, else the exponent and `W` mantissas
/// ([`dpsa_core::height::ColumnScale`]): column `c`'s LSB per turn
/// `T_z(c) / height_lsb_um` rounded to Q16.16, then to the table's 16-bit mantissas, checked by
/// the core's own [`ColumnScale::check`](dpsa_core::height::ColumnScale::check) against the
/// uniform `lsb_per_turn` (`height_per_turn_um / height_lsb_um`; this block's other checks
/// come first). One function for the manifest check and the core's configuration (`dpsa_stream::config`), so a table that
/// loads is one the core takes.
pub fn column_scale_table(
    cal: &Calibration,
    width: u32,
) -> Result<Option<(u8, Vec<u16>)>, Invalid> {
    use dpsa_core::fixed::types::U16F16;
    use dpsa_core::height::{ColumnScale, ColumnScaleError};
    const FIELD: &str = "calibration.height_per_turn_um_per_column";
    let Some(t) = &cal.height_per_turn_um_per_column else {
        return Ok(None);
    };
    check(t.len() == width as usize, FIELD, || {
        format!("{} values, expected one per column ({width})", t.len())
    })?;
    let lsb = cal.height_lsb_um;
    let mut k = Vec::with_capacity(t.len());
    for (c, &tz) in t.iter().enumerate() {
        let q16 = (tz / lsb * 65536.0).round();
        check(
            tz.is_finite() && tz > 0.0 && (1.0..2_147_483_648.0).contains(&q16),
            &format!("{FIELD}[{c}]"),
            || {
                format!(
                    "{tz} um, expected a finite value > 0 whose turn is 2^-16 ..< 32768 LSB of height_lsb_um {lsb}"
                )
            },
        )?;
        k.push(U16F16::from_bits(q16 as u32));
    }
    let mut m = vec![0u16; t.len()];
    let shift = ColumnScale::encode(&k, &mut m).map_err(|e| Invalid {
        field: FIELD.into(),
        message: format!("not representable in the core's table: {e}"),
    })?;
    let uniform = U16F16::from_bits((cal.height_per_turn_um / lsb * 65536.0).round() as u32);
    let w = u16::try_from(width).unwrap_or(u16::MAX);
    match ColumnScale::new(shift, &m).check_parts(w, uniform) {
        Ok(()) => Ok(Some((shift, m))),
        Err(ColumnScaleError::Range { column }) => {
            let c = usize::from(column);
            Err(Invalid {
                field: format!("{FIELD}[{c}]"),
                message: format!(
                    "{} um is more than a factor of 2 from height_per_turn_um {} um (the core's uniform scale, which a per-column value must stay within)",
                    t[c], cal.height_per_turn_um
                ),
            })
        }
        Err(e) => Err(Invalid {
            field: FIELD.into(),
            message: format!("not representable in the core's table: {e}"),
        }),
    }
}

/// Legal settings that make the result useless, one sentence each (printed as `warning: ...`).
pub fn warnings(cam: &Camera, cal: &Calibration, p: &Processing) -> Vec<String> {
    let mut w = Vec::new();
    let fx = (4_294_967_296.0 / cal.fringe_period_px).round();
    if fx >= 2_147_483_648.0 {
        w.push(format!(
            "fringe_period_px = {}: every phase shift between frames is a multiple of 180 degrees, so every window is ILL_CONDITIONED and no pixel is valid",
            cal.fringe_period_px
        ));
    } else if fx < 1.0 {
        w.push(format!(
            "fringe_period_px = {}: the fringe does not move measurably between frames, so every window is ILL_CONDITIONED",
            cal.fringe_period_px
        ));
    }
    let max_mod = f64::from(max_value(cam.bit_depth)) / 2.0;
    if p.min_modulation > max_mod {
        w.push(format!(
            "min_modulation = {} DN is above {max_mod} DN, the largest modulation a {}-bit camera can show: every pixel is LOW_MODULATION",
            p.min_modulation, cam.bit_depth
        ));
    }
    w
}
