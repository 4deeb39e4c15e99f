//! A board's top paste layer (Gerber RS-274X / X2) as pads (`dpsa pads`, `docs/inspection.md`).
//!
//! The file is read in four steps:
//!
//! | file | step |
//! | --- | --- |
//! | `lex` | size and character checks; one statement per line with its original line number; deprecated words translated |
//! | `gerber_parser` (crate) | statements -> `gerber-types` commands |
//! | `interp` | the graphics state: apertures, macros, flashes, strokes, regions, step and repeat, polarity, X2 object attributes -> objects in mm (`object`) |
//! | `merge` | objects -> pads: connected openings (union; clear objects cut), exact outlines for plain flashes |
//!
//! The first three run a chunk of [`CHUNK_STATEMENTS`] statements at a time, so the file is
//! never held as statements or commands whole: what grows with the file is the objects
//! (compact: a flash is its aperture and place, `object`) and then the pads.
//!
//! `shapes` holds the geometry (polygons within 1 um of the curves, macro expressions, the
//! recognition of rounded rectangles built from macro primitives).
//!
//! Coordinates stay in the file's own frame, converted to mm. Bad input is a [`GerberError`]
//! with the line it was found on, never a panic; memory and time are bounded by
//! [`MAX_FILE_BYTES`], [`MAX_OBJECTS`], [`MAX_VERTICES`] and [`MAX_STROKE_VERTICES`]: within them
//! a layer is read in at most 512 MB (`docs/inspection.md`, "At scale").

mod interp;
mod lex;
mod merge;
mod object;
mod overlay;
mod shapes;

pub mod pads;

use pads::Pad;
use serde::Serialize;
use std::io::Read;
use std::path::Path;

/// Largest file read, bytes (64 MiB).
pub const MAX_FILE_BYTES: u64 = 64 << 20;
/// Most objects (flashes, strokes, region contours, after step and repeat) in one layer.
pub const MAX_OBJECTS: usize = 1_000_000;
/// Most polygon vertices the layer holds: those of its strokes, regions, aperture macros and
/// flashes of apertures that are not a plain circle or rounded rectangle (step-and-repeat
/// copies each count), and then those of its merged pads' outlines (128 MB of coordinates
/// each). A plain flash counts none: its pad is its exact outline.
pub const MAX_VERTICES: usize = 8_000_000;
/// Most vertices of the pieces of one stroke before their union (an aperture swept along the
/// chords of an arc).
pub const MAX_STROKE_VERTICES: usize = 200_000;
/// Most work of the exact tests between objects whose bounding boxes meet: the sum over the
/// tested pairs of pieces of their two vertex counts and of the product of their edges near
/// each other (about 2 ns each on this project's machine, so at most about 0.4 s; the largest
/// real layer of `tests/data/gerber` needs 1.6 x 10^6, 1/125 of it).
pub const MAX_PAIR_WORK: u64 = 200_000_000;
/// How much one layer may hold: what [`read_bytes_with`] refuses beyond. The reader's own
/// are [`Limits::READER`] (the constants above); smaller ones run the same checks sooner (the
/// fuzz target reads with [`Limits::FUZZ`], so that each input takes milliseconds, not the
/// second a layer at the reader's limits may take).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Most objects ([`MAX_OBJECTS`] for the reader).
    pub objects: usize,
    /// Most polygon vertices held ([`MAX_VERTICES`]).
    pub vertices: usize,
    /// Most vertices of one stroke's pieces ([`MAX_STROKE_VERTICES`]).
    pub stroke_vertices: usize,
    /// Most work of the merging's exact tests ([`MAX_PAIR_WORK`]).
    pub pair_work: u64,
}

impl Limits {
    /// The reader's limits: those of [`read_file`], [`read_bytes`] and [`read_str`].
    pub const READER: Limits = Limits {
        objects: MAX_OBJECTS,
        vertices: MAX_VERTICES,
        stroke_vertices: MAX_STROKE_VERTICES,
        pair_work: MAX_PAIR_WORK,
    };
    /// For fuzzing: a few thousand objects and vertices, so that the reader's every path is
    /// met within milliseconds (instrumented), the overlays included.
    pub const FUZZ: Limits = Limits {
        objects: 2_000,
        vertices: 10_000,
        stroke_vertices: 2_000,
        pair_work: 100_000,
    };
}

impl Default for Limits {
    fn default() -> Limits {
        Limits::READER
    }
}

/// Statements pre-processed, parsed and interpreted at a time.
pub const CHUNK_STATEMENTS: usize = 16_384;
/// Largest coordinate or size, mm (10 m): beyond it a file is corrupt, not a board.
pub const MAX_COORD_MM: f64 = 10_000.0;

/// Why a paste layer could not be read. `line` is the 1-based line of the file (0 when the
/// problem has no single line, e.g. an empty file).
#[derive(Debug, thiserror::Error)]
pub enum GerberError {
    /// The file could not be opened or read (missing, not a regular file, unreadable). The
    /// message names the file and holds the I/O error's (not a `source()` as well: a chain
    /// printed in full would say it twice).
    #[error("{path}: {error}")]
    Io {
        /// The file, as given.
        path: String,
        /// The I/O error.
        error: std::io::Error,
    },
    /// The file is larger than [`MAX_FILE_BYTES`].
    #[error("the file is {bytes} bytes, more than the {limit} bytes a paste layer may have")]
    TooLarge {
        /// The file's size (or the bytes read before giving up), bytes.
        bytes: u64,
        /// The limit, bytes ([`MAX_FILE_BYTES`]).
        limit: u64,
    },
    /// A control character (other than tab and line ends) or, in a file that is not UTF-8, a
    /// non-ASCII byte outside comments and attributes.
    #[error("line {line}: binary data, not Gerber text")]
    Binary {
        /// 1-based line of the file.
        line: usize,
    },
    /// A statement that does not parse, or that the parser refused.
    #[error("line {line}: {message}")]
    Syntax {
        /// 1-based line of the file (0: the parser did not say).
        line: usize,
        /// What is wrong, with the start of the statement when known.
        message: String,
    },
    /// A length is used before the file set its units (`%MOMM*%` or `%MOIN*%`).
    #[error("line {line}: no units: the file has no %MOMM*% or %MOIN*% before its first use of a length")]
    NoUnits {
        /// 1-based line of the first use.
        line: usize,
    },
    /// A coordinate comes before the coordinate format (`%FS...*%`).
    #[error("line {line}: no coordinate format (%FS...*%) before the first coordinate")]
    NoFormat {
        /// 1-based line of the first coordinate.
        line: usize,
    },
    /// A flash or stroke selects an aperture the file never defined.
    #[error("line {line}: aperture D{code} is used but never defined")]
    UndefinedAperture {
        /// 1-based line of the use.
        line: usize,
        /// The aperture's D code.
        code: i32,
    },
    /// An aperture macro definition runs to the end of the file.
    #[error("line {line}: aperture macro (%AM) is never closed by '%'")]
    UnterminatedMacro {
        /// 1-based line where the macro starts.
        line: usize,
    },
    /// A region (`G36`) runs to the end of the file.
    #[error("line {line}: region (G36) is never closed by G37")]
    UnclosedRegion {
        /// 1-based line of the `G36`.
        line: usize,
    },
    /// A number beyond [`MAX_COORD_MM`], not finite, or negative where a size must not be.
    #[error("line {line}: {what} is out of range (|value| <= 10 m, finite)")]
    OutOfRange {
        /// 1-based line of the number.
        line: usize,
        /// The quantity and its value, e.g. `coordinate 12000.000 mm`.
        what: String,
    },
    /// More than [`MAX_OBJECTS`] objects.
    #[error("line {line}: more than {limit} objects (step and repeat included)")]
    TooManyObjects {
        /// 1-based line where the count went over.
        line: usize,
        /// The limit ([`MAX_OBJECTS`]).
        limit: usize,
    },
    /// More than [`MAX_VERTICES`] polygon vertices.
    #[error("line {line}: more than {limit} polygon vertices in the layer")]
    TooComplex {
        /// 1-based line where the count went over (0: in the merged pads).
        line: usize,
        /// The limit ([`MAX_VERTICES`]).
        limit: usize,
    },
    /// The merging's exact tests would exceed [`MAX_PAIR_WORK`].
    #[error(
        "the layer's objects overlap too densely to merge in bounded time: the exact tests \
         of the objects whose boxes meet would compare more than {limit} pairs of edges"
    )]
    TooEntangled {
        /// The limit ([`MAX_PAIR_WORK`]).
        limit: u64,
    },
    /// One stroke would need more than [`MAX_STROKE_VERTICES`] vertices.
    #[error(
        "line {line}: this stroke of aperture {aperture} needs {vertices} polygon vertices, more \
         than the {limit} one stroke may have (an aperture far too large for its path)"
    )]
    StrokeTooComplex {
        /// 1-based line of the stroke.
        line: usize,
        /// The aperture's class, e.g. `C 0.25` or `R 0.60x0.30`.
        aperture: String,
        /// Vertices the stroke's pieces would have.
        vertices: usize,
        /// The limit ([`MAX_STROKE_VERTICES`]).
        limit: usize,
    },
    /// A valid Gerber feature this reader does not handle.
    #[error("line {line}: not supported: {what}")]
    Unsupported {
        /// 1-based line of the statement.
        line: usize,
        /// The feature.
        what: String,
    },
    /// The file ends inside something it opened (e.g. a step and repeat).
    #[error("line {line}: the file ends early: {what}")]
    Truncated {
        /// 1-based line where the unclosed thing starts.
        line: usize,
        /// What was left open.
        what: String,
    },
}

impl GerberError {
    /// The message as said of the file at `path`: the file's name first, once (an I/O error
    /// names it already).
    pub fn in_file(&self, path: &Path) -> String {
        match self {
            GerberError::Io { .. } => self.to_string(),
            _ => format!("{}: {self}", path.display()),
        }
    }

    /// The 1-based line of the file the error was found on (0: none).
    pub fn line(&self) -> usize {
        match self {
            GerberError::Io { .. }
            | GerberError::TooLarge { .. }
            | GerberError::TooEntangled { .. } => 0,
            GerberError::Binary { line }
            | GerberError::Syntax { line, .. }
            | GerberError::NoUnits { line }
            | GerberError::NoFormat { line }
            | GerberError::UndefinedAperture { line, .. }
            | GerberError::UnterminatedMacro { line }
            | GerberError::UnclosedRegion { line }
            | GerberError::OutOfRange { line, .. }
            | GerberError::TooManyObjects { line, .. }
            | GerberError::TooComplex { line, .. }
            | GerberError::StrokeTooComplex { line, .. }
            | GerberError::Unsupported { line, .. }
            | GerberError::Truncated { line, .. } => *line,
        }
    }
}

/// The pads of one paste layer.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PasteLayer {
    /// One per connected paste opening, in the order of the file.
    pub pads: Vec<Pad>,
    /// The file's units as it said: `"mm"` or `"inch"` (the pads are in mm either way).
    pub units: &'static str,
    /// `[xmin, ymin, xmax, ymax]` of all pads, mm, in the file's frame (zeros when no pads).
    pub bbox_mm: [f64; 4],
    /// `%TF.GenerationSoftware` (vendor,application,version) when the file has it.
    pub generator: Option<String>,
    /// What was odd but did not stop the reading (no M02, unclosed contours, ...).
    pub warnings: Vec<String>,
    /// Whether the file ends with its end-of-file statement (`M02`). A file without it may
    /// be cut short: the inspection refuses it unless the program allows it
    /// (`allow_truncated_layer`).
    pub complete: bool,
}

/// Reads a paste layer file (at most [`MAX_FILE_BYTES`]).
pub fn read_file(path: &Path) -> Result<PasteLayer, GerberError> {
    let io = |error| GerberError::Io {
        path: path.display().to_string(),
        error,
    };
    // A FIFO or device is refused before it is opened (opening a FIFO waits for a writer).
    let file = dpsa_formats::files::check_regular(path)
        .and_then(|_| std::fs::File::open(path))
        .map_err(io)?;
    let len = file.metadata().map_err(io)?.len();
    if len > MAX_FILE_BYTES {
        return Err(GerberError::TooLarge {
            bytes: len,
            limit: MAX_FILE_BYTES,
        });
    }
    let mut bytes = Vec::with_capacity(len as usize);
    // `take` bounds what a growing file (or a device) can hand us.
    file.take(MAX_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(GerberError::TooLarge {
            bytes: bytes.len() as u64,
            limit: MAX_FILE_BYTES,
        });
    }
    read_bytes(bytes)
}

/// Reads a paste layer from the bytes of its file: UTF-8, or else Latin-1 (old exporters'
/// comments), where non-ASCII characters outside comments and attributes are binary data.
pub fn read_bytes(bytes: Vec<u8>) -> Result<PasteLayer, GerberError> {
    read_bytes_with(bytes, &Limits::READER)
}

/// [`read_bytes`] within `limits`.
pub fn read_bytes_with(bytes: Vec<u8>, limits: &Limits) -> Result<PasteLayer, GerberError> {
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(GerberError::TooLarge {
            bytes: bytes.len() as u64,
            limit: MAX_FILE_BYTES,
        });
    }
    match String::from_utf8(bytes) {
        Ok(text) => read_text(text, false, limits),
        Err(e) => {
            // Not UTF-8: Latin-1 (every byte one character), as old exporters wrote their
            // comments; the pre-pass refuses non-ASCII outside comments as binary data.
            let text: String = e.into_bytes().into_iter().map(char::from).collect();
            read_text(text, true, limits)
        }
    }
}

/// Reads a paste layer from its text.
pub fn read_str(text: &str) -> Result<PasteLayer, GerberError> {
    if text.len() as u64 > MAX_FILE_BYTES {
        return Err(GerberError::TooLarge {
            bytes: text.len() as u64,
            limit: MAX_FILE_BYTES,
        });
    }
    let mut warnings = Vec::new();
    let interpreted = interpret(text, false, &mut warnings, &Limits::READER)?;
    layer_of(interpreted, warnings, &Limits::READER)
}

/// [`read_str`] of an owned text, dropped before the pads are made.
fn read_text(text: String, latin1: bool, limits: &Limits) -> Result<PasteLayer, GerberError> {
    let mut warnings = Vec::new();
    let interpreted = interpret(&text, latin1, &mut warnings, limits)?;
    drop(text);
    layer_of(interpreted, warnings, limits)
}

/// Pre-processing, parsing and interpretation, a chunk of statements at a time.
fn interpret(
    text: &str,
    latin1: bool,
    warnings: &mut Vec<String>,
    limits: &Limits,
) -> Result<interp::Interpreted, GerberError> {
    let mut lexer = lex::Lexer::new(text, latin1);
    let mut state = interp::Interpreter::new(*limits);
    while let Some(chunk) = lexer.next_chunk(CHUNK_STATEMENTS)? {
        state.warn(chunk.warnings.iter().cloned());
        let commands = parse(&chunk, warnings)?;
        state.feed(&commands)?;
    }
    state.finish()
}

/// The pads of the interpreted objects.
fn layer_of(
    interpreted: interp::Interpreted,
    mut warnings: Vec<String>,
    limits: &Limits,
) -> Result<PasteLayer, GerberError> {
    let interp::Interpreted {
        layer,
        units,
        generator,
        warnings: w,
        complete,
    } = interpreted;
    warnings.extend(w);
    let pads = merge::pads(layer, &mut warnings, limits)?;
    let bbox_mm = if pads.is_empty() {
        warnings.push("the layer has no pads".into());
        [0.0; 4]
    } else {
        pads.iter().fold(
            [
                f64::INFINITY,
                f64::INFINITY,
                f64::NEG_INFINITY,
                f64::NEG_INFINITY,
            ],
            |b, p| {
                let q = p.outline.bbox();
                [
                    b[0].min(q[0]),
                    b[1].min(q[1]),
                    b[2].max(q[2]),
                    b[3].max(q[3]),
                ]
            },
        )
    };
    Ok(PasteLayer {
        pads,
        units,
        bbox_mm,
        generator,
        warnings,
        complete,
    })
}

/// The parser on the pre-processed text. Its errors are fatal except on attribute lines
/// (whose values it sometimes cannot type, e.g. a date in another format): those are warnings.
fn parse(
    lexed: &lex::Lexed,
    warnings: &mut Vec<String>,
) -> Result<Vec<gerber_types::Command>, GerberError> {
    use gerber_parser::ContentError;
    let reader = std::io::BufReader::new(lexed.text.as_bytes());
    // The pre-processing keeps the parser away from the inputs known to panic it; a panic
    // that is left is still a refusal of the file, not of the program.
    // (The parser's error carries the partial document; boxed, it does not bloat the Result.)
    let doc = std::panic::catch_unwind(move || gerber_parser::parse(reader).map_err(Box::new))
        .map_err(|_| GerberError::Syntax {
            line: 0,
            message: "the Gerber parser failed on this file".into(),
        })?;
    let doc = match doc {
        Ok(doc) => doc,
        Err(boxed) => {
            let (_, e) = *boxed;
            return Err(GerberError::Syntax {
                line: 0,
                message: e.to_string(),
            });
        }
    };
    let mut out = Vec::with_capacity(doc.commands.len());
    let mut commands = doc.commands.into_iter();
    // The chunk's head repeats the format and units of earlier chunks: not the file's.
    for _ in 0..lexed.prelude {
        use gerber_types::{Command, ExtendedCode};
        match commands.next() {
            Some(Ok(Command::ExtendedCode(
                ExtendedCode::CoordinateFormat(_) | ExtendedCode::Unit(_),
            ))) => {}
            _ => {
                return Err(GerberError::Syntax {
                    line: lexed.original_line(1),
                    message: "the parser did not take the format and units again".into(),
                })
            }
        }
    }
    for c in commands {
        match c {
            Ok(cmd) => out.push(cmd),
            Err(e) => {
                if matches!(e.error, ContentError::NoEndOfFile) {
                    continue; // M02 is checked by the interpreter
                }
                let (line, text) = match &e.line {
                    Some((n, t)) => (lexed.original_line(*n), t.as_str()),
                    None => (0, ""),
                };
                let attribute = text.starts_with("%T") || text.starts_with("G04");
                if attribute {
                    warnings.push(format!("line {line}: attribute ignored: {}", e.error));
                } else {
                    let what: String = text.chars().take(60).collect();
                    return Err(GerberError::Syntax {
                        line,
                        message: format!("{} ({what:?})", e.error),
                    });
                }
            }
        }
    }
    Ok(out)
}

/// Edges of the area histogram, mm^2: half decades from 0.001 to 1000 (below and above go to
/// the first and last bin).
pub const AREA_EDGES_MM2: [f64; 13] = [
    0.001, 0.00316, 0.01, 0.0316, 0.1, 0.316, 1.0, 3.16, 10.0, 31.6, 100.0, 316.0, 1000.0,
];

/// One bin of the area histogram: pads with `from_mm2 <= area < to_mm2` (the first bin also
/// takes smaller pads, the last larger ones).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AreaBin {
    /// Lower edge, mm^2 (included).
    pub from_mm2: f64,
    /// Upper edge, mm^2 (excluded).
    pub to_mm2: f64,
    /// Pads in the bin.
    pub count: usize,
}

/// The figures `dpsa pads` prints about a layer.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PadSummary {
    /// Pads in the layer.
    pub count: usize,
    /// `[xmin, ymin, xmax, ymax]`, mm, in the file's frame (zeros when no pads).
    pub bbox_mm: [f64; 4],
    /// Sum of the pads' areas, mm^2.
    pub total_area_mm2: f64,
    /// Pads by area: one bin per pair of neighbouring [`AREA_EDGES_MM2`], in increasing area.
    pub area_histogram: Vec<AreaBin>,
    /// Pads per aperture class, most common first (then by name).
    pub classes: Vec<(String, usize)>,
    /// Pads that carry a component or pin name (X2 `%TO.C` / `%TO.P`).
    pub named: usize,
}

impl PasteLayer {
    /// Count, box, area histogram, classes, named pads.
    pub fn summary(&self) -> PadSummary {
        let n = AREA_EDGES_MM2.len() - 1;
        let mut bins: Vec<AreaBin> = (0..n)
            .map(|i| AreaBin {
                from_mm2: AREA_EDGES_MM2[i],
                to_mm2: AREA_EDGES_MM2[i + 1],
                count: 0,
            })
            .collect();
        let mut total = 0.0;
        let mut classes: std::collections::BTreeMap<String, usize> = Default::default();
        for p in &self.pads {
            let a = p.outline.area();
            total += a;
            let i = AREA_EDGES_MM2[1..n]
                .iter()
                .position(|&e| a < e)
                .unwrap_or(n - 1);
            bins[i].count += 1;
            *classes
                .entry(p.aperture.clone().unwrap_or_else(|| "?".into()))
                .or_default() += 1;
        }
        let mut classes: Vec<(String, usize)> = classes.into_iter().collect();
        classes.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
        PadSummary {
            count: self.pads.len(),
            bbox_mm: self.bbox_mm,
            total_area_mm2: total,
            area_histogram: bins,
            classes,
            named: self
                .pads
                .iter()
                .filter(|p| p.component.is_some() || p.pin.is_some())
                .count(),
        }
    }
}
