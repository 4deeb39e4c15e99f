//! The errors of the inspection's API: one [`InspectError`] for reading the map, the program
//! and its paste layer, registering, evaluating and writing the report. Each message is one
//! sentence naming the file (and the key or field) it is about.

use crate::program::ProgramError;
use crate::register::RegisterError;
use crate::teach::TeachError;
use dpsa_formats::files::FileError;
use dpsa_gerber::GerberError;
use std::path::PathBuf;

/// Why an inspection (or reading its map) failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum InspectError {
    /// The program could not be read or is refused.
    #[error(transparent)]
    Program(#[from] ProgramError),
    /// The pads could not be named from the program's placement file (`[components]`).
    #[error(transparent)]
    Teach(#[from] TeachError),
    /// The design could not be registered on the map.
    #[error(transparent)]
    Register(#[from] RegisterError),
    /// An input could not be read or an output written (or `--out` would replace an input).
    #[error(transparent)]
    File(#[from] FileError),
    /// The report could not be put into JSON.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// The evaluation ([`crate::run::Evaluate`]) failed, with its own error.
    #[error(transparent)]
    Evaluation(Box<dyn std::error::Error + Send + Sync + 'static>),
    /// The program's paste layer could not be read. The reader's error is part of the
    /// message, not a `source()`.
    #[error("paste layer {}", .error.in_file(.path))]
    PasteLayer {
        /// The layer's file.
        path: PathBuf,
        /// The reader's error.
        error: GerberError,
    },
    /// The paste layer has no end (`M02`) and the program does not allow that.
    #[error(
        "paste layer {}: the file has no end (M02) and may be truncated; set \
         allow_truncated_layer = true in {} to inspect the {pads} pads it has",
        .path.display(),
        .program.display()
    )]
    TruncatedLayer {
        /// The layer's file.
        path: PathBuf,
        /// The program file, where the key would go.
        program: PathBuf,
        /// Pads read before the file ended.
        pads: usize,
    },
    /// The paste layer has no pads.
    #[error("paste layer {}: no pads", .path.display())]
    NoPads {
        /// The layer's file.
        path: PathBuf,
    },
    /// A map's `board.json` is not JSON of the board map's shape.
    #[error("{} is not a board map's board.json", .path.display())]
    MapJson {
        /// The `board.json`.
        path: PathBuf,
        /// The parser's error.
        #[source]
        source: serde_json::Error,
    },
    /// A board map's file does not hold what this build reads (format, version, units, grid,
    /// image size or sample type), as one sentence after the file's name.
    #[error("{}: {why}", .path.display())]
    Map {
        /// The `board.json` or `heights_um.tiff`.
        path: PathBuf,
        /// What is wrong, with the values found.
        why: String,
    },
    /// A map's heights file is not a TIFF.
    #[error("{} is not a TIFF", .path.display())]
    NotTiff {
        /// The `heights_um.tiff`.
        path: PathBuf,
        /// The decoder's error.
        #[source]
        source: tiff::TiffError,
    },
    /// The TIFF decoder could not read the heights' size or pixels.
    #[error("{}: {what}", .path.display())]
    Tiff {
        /// The `heights_um.tiff`.
        path: PathBuf,
        /// `no image size` or `cannot decode`.
        what: &'static str,
        /// The decoder's error.
        #[source]
        source: tiff::TiffError,
    },
    /// The report's gallery directory could not be made. The I/O error is part of the
    /// message, not a `source()`.
    #[error("cannot create {}: {error}", .path.display())]
    CreateDir {
        /// The directory.
        path: PathBuf,
        /// The I/O error.
        error: std::io::Error,
    },
    /// `repeat` ran no inspection (not reached: at least one always runs).
    #[error("no inspection ran")]
    NoInspection,
}
