//! The errors of the simulator crate's API: one [`SimError`] for every module, since the
//! simulator's modules call one another (a board run renders, records, calibrates and
//! compares). The production crates' own errors pass through unchanged (`transparent`); what
//! is the simulator's own is one sentence per variant. [`At::at`] puts where it happened
//! ("camera 2", "frame 17") in front of an error as the error's first line, the cause kept as
//! its `source()`, so the binary's `{:#}` prints `camera 2: <cause>` as before.

use dpsa_board::BoardError;
use dpsa_formats::array::ArrayError;
use dpsa_formats::calibration::CalError;
use dpsa_formats::files::FileError;
use dpsa_formats::images::PngError;
use dpsa_formats::recording::RecordingError;
use dpsa_gerber::GerberError;
use dpsa_inspect::InspectError;

/// Why a simulator, reference, calibration, bench or target call failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    /// A file could not be read, written or created (the sentence names it and the cause).
    #[error(transparent)]
    File(#[from] FileError),
    /// A camera recording's manifest or frames refused.
    #[error(transparent)]
    Recording(#[from] RecordingError),
    /// The calibration file refused.
    #[error(transparent)]
    Calibration(#[from] CalError),
    /// `array.json` missing or out of range.
    #[error(transparent)]
    Array(#[from] ArrayError),
    /// A configuration the fixed-point core cannot take.
    #[error(transparent)]
    Config(#[from] dpsa_stream::config::ConfigError),
    /// The board map could not be built or written.
    #[error(transparent)]
    Board(#[from] BoardError),
    /// The line's store refused or failed (`dpsa print-process`).
    #[error(transparent)]
    Store(#[from] dpsa_line::store::StoreError),
    /// The inspection failed (program, paste layer, registration, report).
    #[error(transparent)]
    Inspect(#[from] InspectError),
    /// A Gerber layer could not be read.
    #[error(transparent)]
    Gerber(#[from] GerberError),
    /// A PNG could not be read or written.
    #[error(transparent)]
    Png(#[from] PngError),
    /// A file the simulator wrote or reads back (a truth, a report) is not the JSON it should
    /// be.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// An I/O error on a file the simulator made itself (a temporary file): the caller puts
    /// which one in front with [`At::at`].
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// A single-camera scene refused (`dpsa simulate`).
    #[error(transparent)]
    Scene(#[from] crate::simulation::scene::SceneError),
    /// An array scene refused (`dpsa simulate-array`, `dpsa grr`).
    #[error(transparent)]
    ArrayScene(#[from] crate::array::scene::ArraySceneError),
    /// The paste layer cannot be printed with the scene's print parameters.
    #[error(transparent)]
    Print(#[from] crate::array::print::PrintError),
    /// A scene, an option or an input file the simulator refuses: one sentence that says which
    /// and why, with the values found.
    #[error("{0}")]
    Refused(String),
    /// The fixed-point core refused its configuration, a frame or a line (which, and the
    /// core's reason).
    #[error("{0}")]
    Core(String),
    /// An external program (QEMU, the firmware build, Python with numpy) is missing or failed:
    /// which, and what it said.
    #[error("{0}")]
    Tool(String),
    /// A bench's codec or compressor did not give back what it was given (a bug in it or in
    /// the bench, never a figure to print).
    #[error("{0}")]
    RoundTrip(String),
    /// A thread panicked or an invariant broke (a bug: please report it).
    #[error("internal error: {0}")]
    Internal(String),
    /// Where an error happened, in front of it ("camera 2", "frame 17 line 3").
    #[error("{at}")]
    At {
        /// Where, as the first words of the message.
        at: String,
        /// What went wrong there.
        #[source]
        error: Box<SimError>,
    },
}

/// `Result` with [`SimError`].
pub type Result<T, E = SimError> = std::result::Result<T, E>;

impl SimError {
    /// A refusal, as one sentence.
    pub fn refused(why: impl Into<String>) -> SimError {
        SimError::Refused(why.into())
    }
}

/// `e` and its whole `source()` chain in one line, `: `-separated, as the binary prints an
/// error with `{:#}`: for a message that must carry its cause as text (a hook's error, a
/// stream link's failure).
pub fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cause = c.source();
    }
    s
}

/// Puts where an error happened in front of it (as `anyhow`'s `context` did, typed).
pub trait At<T> {
    /// `Err(e)` becomes [`SimError::At`] with `at()` in front of `e`.
    fn at<S: Into<String>>(self, at: impl FnOnce() -> S) -> Result<T>;
}

impl<T, E: Into<SimError>> At<T> for std::result::Result<T, E> {
    fn at<S: Into<String>>(self, at: impl FnOnce() -> S) -> Result<T> {
        self.map_err(|e| SimError::At {
            at: at().into(),
            error: Box::new(e.into()),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The chain prints as `anyhow`'s context did: where, then the cause, each once.
    #[test]
    fn at_puts_where_in_front_and_keeps_the_cause_once() {
        let r: std::result::Result<(), SimError> =
            Err(SimError::refused("the scene has no cameras"));
        let e = r.at(|| "camera 2").unwrap_err();
        assert_eq!(e.to_string(), "camera 2");
        assert_eq!(chain(&e), "camera 2: the scene has no cameras");
        let inner = std::error::Error::source(&e).map(ToString::to_string);
        assert_eq!(inner.as_deref(), Some("the scene has no cameras"));
    }
}
