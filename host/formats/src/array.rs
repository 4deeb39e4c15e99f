//! The array recording's manifest, `array.json` (`docs/recording.md`, "A camera array"):
//! the array's design (cameras, pixel pitch, encoder scale), the board's size and identity.
//! A board map is laid out from it; the cameras' own recordings (`camI/`) are read by the
//! simulator crate's `ArrayRecording`, and a production `board --streams` needs none of them.

use crate::BoardId;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Name of the array manifest.
pub const ARRAY_FILE: &str = crate::kind::markers::ARRAY_FILE;
/// Format tag of `array.json`.
pub const ARRAY_FORMAT: &str = crate::kind::markers::ARRAY_FORMAT;
/// Version of `array.json` this build reads and writes.
pub const ARRAY_VERSION: u32 = 1;
/// Largest number of cameras in an array.
pub const MAX_CAMERAS: usize = 8;

/// Board recording or calibration recording.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    /// A printed board, once through the cameras.
    Board,
    /// The calibration passes (planes, held-out plane, lateral target).
    Calibration,
}

/// What a calibration pass carried through the cameras.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum PassKind {
    /// A flat matte plane at a known height, used for fitting.
    Plane,
    /// A flat plane at a known height not used for fitting (checks the calibration).
    Holdout,
    /// The lateral target: a flat printed grid of marks.
    Target,
}

/// One calibration pass; camera `i`'s recording of it is `cam{i}/{name}`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Pass {
    /// The pass's directory name under each camera's directory.
    pub name: String,
    /// What the pass carried.
    pub kind: PassKind,
    /// Known height of the plane (0 for the target), um: an input of calibration.
    pub height_um: f64,
}

/// The design position of a camera (what calibration starts from).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DesignCamera {
    /// The camera's place, `0..cameras`.
    pub id: u8,
    /// Frame columns `W`.
    pub width: u32,
    /// Frame rows `H`.
    pub rows: u32,
    /// Design position along the motion of image row 0, mm.
    pub x_mm: f64,
    /// Design position across the board of column 0, mm.
    pub y_mm: f64,
}

/// The lateral target as printed: inputs of calibration.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TargetInfo {
    /// Mark pitch, both directions, mm.
    pub pitch_mm: f64,
    /// Board coordinates of the first mark `[along, across]`, mm (the target's leading edge
    /// resets the encoder, as a board's does).
    pub origin_mm: [f64; 2],
    /// Target length along the motion, mm.
    pub length_mm: f64,
}

/// Contents of `array.json`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ArrayManifest {
    /// [`ARRAY_FORMAT`].
    pub format: String,
    /// [`ARRAY_VERSION`].
    pub version: u32,
    /// A board or a calibration recording.
    pub kind: Kind,
    /// The cameras' design, camera `i` at index `i`.
    pub cameras: Vec<DesignCamera>,
    /// Nominal pixel pitch on the board, mm.
    pub pixel_mm: f64,
    /// Encoder scale typed before calibration, counts/mm.
    pub nominal_counts_per_mm: f64,
    /// The board's length along the motion, mm: the board map's rows.
    pub board_length_mm: f64,
    /// The board's width across the motion, mm: the board map's columns.
    pub board_width_mm: f64,
    /// Calibration passes (calibration recordings only).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub passes: Vec<Pass>,
    /// The lateral target (calibration recordings only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<TargetInfo>,
    /// Board recordings: the board's identity, also in every camera's manifest (`board_id`)
    /// and so the run id of every camera's packet stream (the simulator's `board_identity`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub board_id: Option<BoardId>,
    /// Board recordings of a scene with a paste layer: the layer printed ((`paste.gbr`)).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub paste_layer: Option<String>,
    /// Simulated board recordings with a paste layer: the print ((`print.json`)).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub print: Option<String>,
}

/// `array.json` missing, unreadable or out of range: one sentence naming the file.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct ArrayError(pub String);

impl ArrayManifest {
    /// Reads and checks `dir/array.json` (format, version, cameras in their places with
    /// finite design positions, pitch, encoder scale and board size in range); the error says
    /// what is wrong in one sentence naming the file.
    pub fn load(dir: &Path) -> Result<ArrayManifest, ArrayError> {
        let path = dir.join(ARRAY_FILE);
        let bytes =
            crate::files::read_capped_io(&path, crate::files::MAX_MANIFEST_BYTES).map_err(|e| {
                if e.kind() == std::io::ErrorKind::NotFound {
                    ArrayError(format!(
                        "{}: no {ARRAY_FILE} (is this an array recording? docs/recording.md)",
                        dir.display()
                    ))
                } else {
                    ArrayError(format!("{} {}", path.display(), crate::files::io_cause(&e)))
                }
            })?;
        let manifest: ArrayManifest = serde_json::from_slice(&bytes).map_err(|e| {
            ArrayError(format!(
                "{}: not a valid array manifest: {e}",
                path.display()
            ))
        })?;
        if manifest.format != ARRAY_FORMAT || manifest.version != ARRAY_VERSION {
            return Err(ArrayError(format!(
                "{}: format {:?} version {}, this build reads {ARRAY_FORMAT:?} version {ARRAY_VERSION}",
                path.display(),
                manifest.format,
                manifest.version
            )));
        }
        if manifest.cameras.is_empty() || manifest.cameras.len() > MAX_CAMERAS {
            return Err(ArrayError(format!(
                "{}: {} cameras, expected 1..=8",
                path.display(),
                manifest.cameras.len()
            )));
        }
        for (i, c) in manifest.cameras.iter().enumerate() {
            if usize::from(c.id) != i {
                return Err(ArrayError(format!(
                    "{}: camera {i} has id {}, expected {i}",
                    path.display(),
                    c.id
                )));
            }
            if !(c.x_mm.is_finite() && c.y_mm.is_finite()) {
                return Err(ArrayError(format!(
                    "{}: camera {i}'s design position (x_mm {}, y_mm {}) is not finite",
                    path.display(),
                    c.x_mm,
                    c.y_mm
                )));
            }
        }
        // The same ranges as the scene's keys: a 0 here would size a board map from a
        // division by zero (or a map of no rows).
        let m = &manifest;
        for (key, v, lo, hi, unit) in [
            ("pixel_mm", m.pixel_mm, 1e-4, 10.0, "mm"),
            (
                "nominal_counts_per_mm",
                m.nominal_counts_per_mm,
                1e-3,
                1e6,
                "counts/mm",
            ),
            ("board_length_mm", m.board_length_mm, 1.0, 2000.0, "mm"),
            ("board_width_mm", m.board_width_mm, 1.0, 2000.0, "mm"),
        ] {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return Err(ArrayError(format!(
                    "{}: `{key}` is {v}, expected a finite value in {lo}..={hi} ({unit})",
                    path.display()
                )));
            }
        }
        Ok(manifest)
    }
}
