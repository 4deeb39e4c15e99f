//! What kind of file (or directory) a path is, told from its first bytes or its marker file,
//! so that a file given in the wrong place is named for what it is ("this is a Gerber paste
//! layer; `--program` takes the program.toml that `dpsa simulate` writes") instead of failing
//! in the parser of the expected kind.
//!
//! [`sniff`] reads at most [`SNIFF_BYTES`] of a regular file (or of a directory's marker file)
//! and never follows anything else (a FIFO or a device is [`Kind::Other`] unread).
//! [`expect`] is what the commands call before loading an input: an input of another
//! *known* kind is refused with one sentence; an unknown one is left to the loader, whose
//! error then names what is wrong inside it.

use std::io::Read;
use std::path::{Path, PathBuf};

/// The marker names and format strings by which files and directories are told apart, each
/// defined once here and used by the crates that write them.
pub mod markers {
    /// The `format` of an array calibration file.
    pub const CALIBRATION_FORMAT: &str = "dpsa-calibration";
    /// The marker file of an array recording directory.
    pub const ARRAY_FILE: &str = "array.json";
    /// The `format` in an array recording's marker file.
    pub const ARRAY_FORMAT: &str = "dpsa-array-recording";
    /// The manifest of a single-camera recording directory.
    pub const RECORDING_MANIFEST: &str = "manifest.json";
    /// The `format` in a single-camera recording's manifest.
    pub const RECORDING_FORMAT: &str = "dpsa-recording";
}

/// Most bytes read from a file to tell its kind.
pub const SNIFF_BYTES: usize = 64 * 1024;

/// The kinds of input `dpsa` reads or writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A Gerber RS-274X / X2 file (a paste layer).
    Gerber,
    /// An inspection program (`program.toml`).
    Program,
    /// An array calibration file (`format = "dpsa-calibration"`).
    Calibration,
    /// A single-camera scene file.
    Scene,
    /// An array scene file (`[[cameras]]`).
    ArrayScene,
    /// A single-camera recording directory (`manifest.json`, `dpsa-recording`).
    Recording,
    /// An array board recording directory (`array.json`, kind board).
    ArrayBoardRecording,
    /// An array calibration recording directory (`array.json`, kind calibration).
    ArrayCalibrationRecording,
    /// A board map directory (`board.json`, `dpsa-board-map`).
    BoardMap,
    /// An inspection output directory (`pads.csv` and `report.json`).
    InspectionOutput,
    /// A packet stream (starts with the sync word `DPSA`).
    Stream,
    /// A frame-grabber feed (`DPSR`).
    Feed,
    /// A compressed frame (`DPSAZFR1`).
    Frame,
    /// A PNG image.
    Png,
    /// A TIFF image.
    Tiff,
    /// A JPEG image.
    Jpeg,
    /// An ELF executable (the firmware).
    Elf,
    /// A simulator print truth (`print.json`).
    PrintTruth,
    /// Something else (or unreadable): left to the loader.
    Other,
}

impl Kind {
    /// What it is, as the object of "this is ...".
    pub fn describe(self) -> &'static str {
        match self {
            Kind::Gerber => "a Gerber file (a paste layer)",
            Kind::Program => "an inspection program (program.toml)",
            Kind::Calibration => "an array calibration file (dpsa-calibration TOML)",
            Kind::Scene => "a single-camera scene file",
            Kind::ArrayScene => "an array scene file (with [[cameras]])",
            Kind::Recording => "a single-camera recording (manifest.json)",
            Kind::ArrayBoardRecording => "an array board recording (array.json of a board)",
            Kind::ArrayCalibrationRecording => {
                "an array calibration recording (array.json of calibration planes and the target)"
            }
            Kind::BoardMap => "a board map directory (board.json)",
            Kind::InspectionOutput => "an inspection output directory (pads.csv, report.json)",
            Kind::Stream => "a packet stream (sync word DPSA)",
            Kind::Feed => "a frame-grabber feed (DPSR)",
            Kind::Frame => "a compressed frame (.zfr)",
            Kind::Png => "a PNG image",
            Kind::Tiff => "a TIFF image",
            Kind::Jpeg => "a JPEG image",
            Kind::Elf => "an ELF executable",
            Kind::PrintTruth => "a simulator print truth (print.json)",
            Kind::Other => "a file of unknown kind",
        }
    }

    /// The command that makes one.
    pub fn made_by(self) -> &'static str {
        match self {
            Kind::Gerber => "your CAD tool's top paste layer, or `dpsa layout`",
            Kind::Program => "the program.toml that `dpsa simulate` writes into a board recording of an array scene with a paste layer",
            Kind::Calibration => "the file `dpsa calibrate CALREC --out CAL.toml` writes",
            Kind::Scene | Kind::ArrayScene => "a scene TOML such as scenes/*.toml",
            Kind::Recording => "`dpsa simulate --scene default --out DIR`",
            Kind::ArrayBoardRecording => "`dpsa simulate --scene ARRAY.toml --out DIR`",
            Kind::ArrayCalibrationRecording => {
                "`dpsa simulate --scene ARRAY.toml --calibration --out DIR`"
            }
            Kind::BoardMap => "`dpsa board BOARDREC --cal CAL.toml --out MAPDIR`",
            Kind::InspectionOutput => "`dpsa inspect MAPDIR --program PROG --out DIR`",
            Kind::Stream => "`dpsa reconstruct DIR --out FILE` or `dpsa target-run`",
            Kind::Feed => "`dpsa target-run`",
            Kind::Frame => "`dpsa simulate`",
            Kind::Png | Kind::Tiff | Kind::Jpeg => "a camera or image tool",
            Kind::Elf => "the firmware build",
            Kind::PrintTruth => "`dpsa simulate` of an array scene with a paste layer (print.json)",
            Kind::Other => "",
        }
    }
}

/// An input of the wrong kind.
#[derive(Debug)]
pub struct WrongKind {
    /// The input.
    pub path: PathBuf,
    /// The option or argument it was given as (`--program`, `MAPDIR`).
    pub given_as: String,
    /// What it is.
    pub found: Kind,
    /// What the command takes there.
    pub wanted: Kind,
}

impl std::fmt::Display for WrongKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} is {}; {} takes {}: {}",
            self.path.display(),
            self.found.describe(),
            self.given_as,
            self.wanted.describe(),
            self.wanted.made_by()
        )
    }
}

impl std::error::Error for WrongKind {}

/// The first bytes of a regular file (at most [`SNIFF_BYTES`]); `None` for anything else.
fn head(path: &Path) -> Option<Vec<u8>> {
    let meta = std::fs::metadata(path).ok()?;
    if !meta.is_file() {
        return None;
    }
    let mut buf = Vec::new();
    std::fs::File::open(path)
        .ok()?
        .take(SNIFF_BYTES as u64)
        .read_to_end(&mut buf)
        .ok()?;
    Some(buf)
}

/// The `"format"` string of a JSON file's first bytes (a plain scan, no parse: the head may
/// be cut).
fn json_format(bytes: &[u8]) -> Option<String> {
    let text = String::from_utf8_lossy(bytes);
    let at = text.find("\"format\"")?;
    let rest = text[at + 8..].trim_start().strip_prefix(':')?.trim_start();
    let rest = rest.strip_prefix('"')?;
    Some(rest[..rest.find('"')?].to_string())
}

/// A line of TOML that sets `key` at the top level (before any table).
fn toml_has(text: &str, key: &str) -> bool {
    for line in text.lines() {
        let l = line.trim_start();
        if l.starts_with('[') {
            return false;
        }
        if let Some(rest) = l.strip_prefix(key) {
            if rest.trim_start().starts_with('=') {
                return true;
            }
        }
    }
    false
}

/// A line that is exactly `line` (surrounding blanks aside): a TOML table header.
fn has_line(text: &str, line: &str) -> bool {
    text.lines().any(|l| l.trim() == line)
}

/// The kind of `bytes`, the head of a file.
pub fn sniff_bytes(bytes: &[u8]) -> Kind {
    if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        return Kind::Png;
    }
    if bytes.starts_with(b"II*\0") || bytes.starts_with(b"MM\0*") {
        return Kind::Tiff;
    }
    if bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
        return Kind::Jpeg;
    }
    if bytes.starts_with(b"\x7fELF") {
        return Kind::Elf;
    }
    if bytes.starts_with(b"DPSAZFR1") {
        return Kind::Frame;
    }
    if bytes.starts_with(&dpsa_core::packets::SYNC) {
        return Kind::Stream;
    }
    if bytes.starts_with(&dpsa_core::frames::feed::MAGIC) {
        return Kind::Feed;
    }
    let text = String::from_utf8_lossy(bytes);
    let t = text.trim_start_matches('\u{feff}').trim_start();
    // Gerber: a comment (G04), or an extended command block first, and Gerber words soon.
    let gerber_words = ["%FS", "%MO", "%TF.", "%ADD", "G04"];
    if (t.starts_with("G04") || t.starts_with('%'))
        && gerber_words.iter().filter(|w| t.contains(*w)).count() >= 2
    {
        return Kind::Gerber;
    }
    if t.starts_with('{') {
        return if t.contains("\"design_to_board\"") && t.contains("\"print_offset_mm\"") {
            Kind::PrintTruth
        } else {
            Kind::Other
        };
    }
    let cal_format = format!("\"{}\"", markers::CALIBRATION_FORMAT);
    let is_cal = t.lines().any(|l| {
        l.trim_start()
            .strip_prefix("format")
            .and_then(|r| r.trim_start().strip_prefix('='))
            .is_some_and(|v| v.trim() == cal_format)
    });
    if is_cal {
        return Kind::Calibration;
    }
    if toml_has(t, "paste_layer") {
        // A program names its layer at the top; so does an array scene, which has cameras.
        if has_line(t, "[[cameras]]") {
            return Kind::ArrayScene;
        }
        return Kind::Program;
    }
    if has_line(t, "[[cameras]]") {
        return Kind::ArrayScene;
    }
    if toml_has(t, "width") && toml_has(t, "fringe_period_px") {
        return Kind::Scene;
    }
    Kind::Other
}

/// The kind of `path`: a directory by its marker file, a file by its first bytes.
pub fn sniff(path: &Path) -> Kind {
    let Ok(meta) = std::fs::metadata(path) else {
        return Kind::Other;
    };
    if meta.is_dir() {
        let format = |name: &str| head(&path.join(name)).and_then(|b| json_format(&b));
        if let Some(f) = format(markers::ARRAY_FILE) {
            if f == markers::ARRAY_FORMAT {
                let b = head(&path.join(markers::ARRAY_FILE)).unwrap_or_default();
                let text = String::from_utf8_lossy(&b);
                return if text.contains("\"kind\": \"calibration\"")
                    || text.contains("\"kind\":\"calibration\"")
                {
                    Kind::ArrayCalibrationRecording
                } else {
                    Kind::ArrayBoardRecording
                };
            }
        }
        if format(markers::RECORDING_MANIFEST).as_deref() == Some(markers::RECORDING_FORMAT) {
            return Kind::Recording;
        }
        if format("board.json").as_deref() == Some(crate::board_map::FORMAT) {
            return Kind::BoardMap;
        }
        if path.join("pads.csv").is_file() && path.join("report.json").is_file() {
            return Kind::InspectionOutput;
        }
        return Kind::Other;
    }
    match head(path) {
        Some(b) => sniff_bytes(&b),
        None => Kind::Other,
    }
}

/// Refuses `path` (given as `given_as`) when it is of a known kind other than `wanted` (or
/// than any of `also`, kinds the input may equally be).
pub fn expect(path: &Path, given_as: &str, wanted: Kind, also: &[Kind]) -> Result<(), WrongKind> {
    let found = sniff(path);
    if found == Kind::Other || found == wanted || also.contains(&found) {
        return Ok(());
    }
    Err(WrongKind {
        path: path.to_path_buf(),
        given_as: given_as.to_string(),
        found,
        wanted,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tells_the_shipped_files_apart() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let k = |p: &str| sniff(&root.join(p));
        assert_eq!(k("scenes/array-small.paste.gbr"), Kind::Gerber);
        assert_eq!(k("scenes/array-small.toml"), Kind::ArrayScene);
        assert_eq!(k("scenes/array-paste.toml"), Kind::ArrayScene);
        // A single-camera scene may set any few keys: not told, left to its loader.
        assert_eq!(k("scenes/noisy.toml"), Kind::Other);
        assert_eq!(k("README.md"), Kind::Other);
        assert_eq!(k("scenes"), Kind::Other);
    }

    #[test]
    fn tells_formats_by_their_first_bytes() {
        assert_eq!(sniff_bytes(b"DPSA\x02\x00rest"), Kind::Stream);
        assert_eq!(sniff_bytes(b"\x89PNG\r\n\x1a\n...."), Kind::Png);
        assert_eq!(
            sniff_bytes(b"format = \"dpsa-calibration\"\nversion = 1\n"),
            Kind::Calibration
        );
        assert_eq!(
            sniff_bytes(b"paste_layer = \"paste.gbr\"\nstencil_um = 100.0\n[placement]\n"),
            Kind::Program
        );
        assert_eq!(
            sniff_bytes(b"G04 a comment*\n%FSLAX46Y46*%\n%MOMM*%\n"),
            Kind::Gerber
        );
        assert_eq!(sniff_bytes(b"hello"), Kind::Other);
    }
}
