//! The line: boards one after another, live from the frame grabbers, into a store
//! (`docs/line.md`).
//!
//! The data flow, one module each:
//! - [`config`]: `LINE.toml`, checked whole before anything starts; `dpsa line init`.
//! - [`link`]: one thread per frame-grabber connection (TCP): the packet stream decoded as it
//!   arrives (`dpsa_stream::Live`), checked against the calibration, its rows placed by the
//!   registration replayed on its own trigger log and handed on 128 rows at a time.
//! - [`boards`]: the open boards by run id, each camera's rows stitched band by band into the
//!   board map as they arrive (`dpsa_board::assemble::Stitcher`); a board ends when every
//!   camera's end packet came, or is incomplete (a camera cut off or silent, a board too long).
//! - [`keeper`]: the finished map inspected against the product's program, the board and
//!   every pad stored ([`store`]), the CFX message spooled ([`cfx`]); the print's placement
//!   fed to the loop back to the printer ([`printer`]), its proposal stored and spooled; the
//!   measured map kept for the pages by a thread of its own ([`maps`]).
//! - [`service`]: `dpsa line run`: the listeners, the threads, the signals; [`memory`]: the
//!   allocator told to keep the service's memory flat.
//! - [`send`]: `dpsa line send`: simulated frame grabbers replaying recorded streams;
//!   [`link_bench`]: TCP against UDP on loopback, behind the link's choice of TCP.

pub mod boards;
pub mod cfx;
pub mod config;
pub mod keeper;
pub mod link;
pub mod link_bench;
pub mod maps;
pub mod memory;
pub mod printer;
pub mod priority;
pub mod send;
pub mod service;
pub mod store;

use std::path::PathBuf;

/// What stops the line (or one of its commands) before it runs.
#[derive(Debug, thiserror::Error)]
pub enum LineError {
    /// The configuration is wrong: which key, and why.
    #[error("{}: {why}", .path.display())]
    Config {
        /// The configuration file.
        path: PathBuf,
        /// The key and what is wrong with it.
        why: String,
    },
    /// A file could not be read or written.
    #[error(transparent)]
    File(#[from] dpsa_formats::files::FileError),
    /// The store.
    #[error(transparent)]
    Store(#[from] store::StoreError),
    /// A socket, a thread or another operating-system failure.
    #[error("{0}")]
    Io(String),
    /// Refused, with a sentence.
    #[error("{0}")]
    Refused(String),
}
