//! The core's integer configuration from the camera, calibration and processing blocks: of a
//! recording's manifest ([`config`]) or of a calibration file's camera ([`of_calibration`],
//! the blocks of [`CalFile::core_blocks`]), through one function ([`core_config`]). A frame
//! grabber configured with a calibration file and the host checking its stream's configuration
//! hash compute the same integers.

use dpsa_core::fixed::types::{U16F16, U20F12, U8F8};
use dpsa_core::height::ColumnScale;
use dpsa_core::{phase, Config};
use dpsa_formats::calibration::CalFile;
use dpsa_formats::recording::checks::column_scale_table;
use dpsa_formats::recording::{Calibration, Camera, Manifest, Processing};
use std::fmt;

/// A value the fixed-point core cannot take (one sentence naming it).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConfigError(pub String);

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ConfigError {}

type Result<T> = std::result::Result<T, ConfigError>;

/// What the core runs on, from a manifest: the integer configuration, the reference-phase
/// table and the optional per-column height-scale table.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CoreConfig {
    /// The core's configuration.
    pub cfg: Config,
    /// `phi_0(c)` as binary angles.
    pub ref_phase: Vec<u32>,
    /// Per-column height scale: exponent and `W` mantissas ([`ColumnScale`]); `None` when the
    /// manifest has no `height_per_turn_um_per_column` (every column at `cfg.lsb_per_turn`).
    pub column_scale: Option<(u8, Vec<u16>)>,
}

impl CoreConfig {
    /// The per-column table as the core takes it.
    pub fn columns(&self) -> Option<ColumnScale<'_>> {
        self.column_scale
            .as_ref()
            .map(|(s, m)| ColumnScale::new(*s, m))
    }

    /// The pipeline's state layout, the table counted.
    pub fn layout(&self) -> dpsa_core::Layout {
        dpsa_core::Layout::of(&self.cfg).with_column_scale(self.column_scale.is_some())
    }
}

/// Integer core configuration, reference-phase table and per-column height scale from a
/// manifest: [`core_config`] of its blocks.
pub fn config(m: &Manifest) -> Result<CoreConfig> {
    core_config(&m.camera, &m.calibration, &m.processing)
}

/// Camera `i`'s configuration of the core from a calibration file: [`core_config`] of
/// [`CalFile::core_blocks`].
pub fn of_calibration(cal: &CalFile, i: usize) -> Result<CoreConfig> {
    let (camera, calibration, processing) = cal
        .core_blocks(i)
        .ok_or_else(|| ConfigError(format!("the calibration has no camera {i}")))?;
    core_config(&camera, &calibration, &processing)
}

/// Integer core configuration, reference-phase table and per-column height scale from the
/// camera, calibration and processing blocks.
///
/// This is the one place where calibration floats become the integers both the host and the
/// firmware run on: `cpp` as `U16F16`, `2 pi f_x` and `phi_0(c)` as binary angles (`u32`), LSB
/// per turn as `U16F16`, the modulation threshold as `U20F12`, the noise-gain limit as `U8F8`.
/// Each fixed-point value is `from_bits(round(x * 2^frac))` (round half away from zero, range
/// checked): `fixed`'s `from_num` truncates, so it is not used here. Column `c`'s LSB per
/// turn `T_z(c) / lsb` (with `height_per_turn_um_per_column`) is rounded the same way, then
/// to the table's 16-bit mantissas
/// ([`column_scale_table`]).
pub fn core_config(camera: &Camera, cal: &Calibration, p: &Processing) -> Result<CoreConfig> {
    let to_u32 = |x: f64, what: &str| -> Result<u32> {
        let r = x.round();
        if r.is_finite() && (0.0..=u32::MAX as f64).contains(&r) {
            Ok(r as u32)
        } else {
            Err(ConfigError(format!(
                "{what} = {x} is out of range for the fixed-point core"
            )))
        }
    };
    let narrow = |x: u32, what: &str| -> Result<u16> {
        u16::try_from(x).map_err(|_| ConfigError(format!("{what} = {x} exceeds 65535")))
    };
    let cfg = Config {
        width: narrow(camera.width, "camera.width")?,
        rows: narrow(camera.rows, "camera.rows")?,
        n: p.n,
        camera: camera.id,
        counts_per_pixel: U16F16::from_bits(to_u32(
            cal.counts_per_pixel * 65536.0,
            "counts_per_pixel",
        )?),
        fx: (4_294_967_296.0 / cal.fringe_period_px).round() as u64 as u32,
        lsb_per_turn: U16F16::from_bits(to_u32(
            cal.height_per_turn_um / cal.height_lsb_um * 65536.0,
            "lsb per turn",
        )?),
        saturation: camera.saturation,
        min_modulation: U20F12::from_bits(to_u32(p.min_modulation * 4096.0, "min_modulation")?),
        max_noise_gain: U8F8::from_bits(narrow(
            to_u32(p.max_noise_gain * 256.0, "max_noise_gain")?,
            "max_noise_gain",
        )?),
        max_step_rows: narrow(p.max_step_rows, "max_step_rows")?,
    };
    cfg.validate().map_err(|e| {
        ConfigError(format!(
            "calibration/processing out of range for the core: {e}"
        ))
    })?;
    let ref_phase = cal
        .reference_phase_rad
        .iter()
        .map(|&r| phase::from_rad(r))
        .collect();
    let column_scale = column_scale_table(cal, camera.width)
        .map_err(|e| ConfigError(format!("{}: {}", e.field, e.message)))?;
    if let Some((shift, mantissa)) = &column_scale {
        ColumnScale::new(*shift, mantissa)
            .check(&cfg)
            .map_err(|e| {
                ConfigError(format!(
                    "per-column height scale out of range for the core: {e}"
                ))
            })?;
    }
    Ok(CoreConfig {
        cfg,
        ref_phase,
        column_scale,
    })
}
