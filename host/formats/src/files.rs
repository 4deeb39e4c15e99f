//! Files in and out, without surprises.
//!
//! * **Reads are bounded.** [`read_capped`] reads a regular file of at most a given size; a
//!   FIFO, a device or a directory is refused before it is opened (a FIFO would block, a
//!   device such as `/dev/zero` never ends), and a file larger than its format allows is
//!   refused from its length, before anything is read.
//! * **Writes are atomic.** [`AtomicFile`] writes to a temporary file in the destination's
//!   directory and renames it into place in [`AtomicFile::commit`]: an error, a crash or a
//!   SIGINT leaves no complete-looking file at the destination (at most a hidden
//!   `.NAME.XXXXXX` temporary, which an error removes), and two writers of the same path leave
//!   one whole file (the last to finish). An existing destination that is not a regular file
//!   (`/dev/null`, `/dev/full`, a FIFO) is written directly.
//!   A FIFO or socket destination is refused (opening it would wait for a reader).
//! * **Output directories appear whole or not at all.** [`OutputDir`] builds a command's
//!   directory (a board map, an inspection report, a recording) as a hidden `.NAME.XXXXXX`
//!   directory beside the destination and swaps it in whole in [`OutputDir::commit`]. The
//!   destination must be new, empty, or an earlier output of the same kind (recognised by the
//!   hidden [`MARKER`] file or the kind's own manifest); anything else is refused. An error,
//!   a SIGINT/SIGTERM or a crash leaves the earlier directory as it was; two writers of one
//!   destination leave one of them whole; nothing of an earlier run (a stale gallery image)
//!   survives a new one.
//! * **Modes follow the umask.** Files are created `0666 & !umask`, directories
//!   `0777 & !umask` (0644 and 0755 under umask 022), not the 0600/0700 of a bare temporary.
//! * **Outputs never overwrite inputs.** [`refuse_overwrite`] refuses an output that is an
//!   input file (after resolving symlinks), lies inside an input directory, or is a directory
//!   holding an input, before any work.
//! * **Temporary directories go on a signal.** [`TempDir`] is a scratch directory removed
//!   when dropped and by the SIGINT/SIGTERM handler.

use std::ffi::OsString;
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// Why a file or directory could not be read, written or chosen as an output. Its `Display`
/// is one sentence naming the path; an I/O cause is stated in it once, in plain words (see
/// [`io_cause`], [`write_cause`]), and kept as [`FileError::io`] rather than as the error's
/// `source()`, so that a chain printed whole (`{:#}`) does not repeat the OS text.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FileError {
    /// An input (or an output directory being checked) could not be opened or read: missing,
    /// not a regular file, too large, unreadable.
    #[error("{what} {} {}", .path.display(), io_cause(.io))]
    Read {
        /// What the file is for the command, e.g. `recording manifest`.
        what: String,
        /// The file.
        path: PathBuf,
        /// The I/O error (for a file too large or not regular, one made up with kind
        /// `InvalidData` / `InvalidInput` and the reason as its text).
        io: std::io::Error,
    },
    /// Writing an output (or renaming it into place) failed.
    #[error("{} {}", .path.display(), write_cause(.io))]
    Write {
        /// The destination.
        path: PathBuf,
        /// The I/O error.
        io: std::io::Error,
    },
    /// A filler passed to [`write_atomic`] failed with an error that holds no I/O error: its
    /// own message (and `source()` chain), unchanged.
    #[error(transparent)]
    Fill(Box<dyn std::error::Error + Send + Sync + 'static>),
    /// The destination of a file is a directory.
    #[error("cannot write {}: it is a directory", .path.display())]
    IsDirectory {
        /// The destination.
        path: PathBuf,
    },
    /// The output is a FIFO or a socket: writing would wait for a reader.
    #[error(
        "cannot write {what} {}: it is a FIFO or socket (a write would wait for a reader); give a regular file",
        .path.display()
    )]
    Fifo {
        /// The output, for the message (an option such as `--out`, or `the output`).
        what: String,
        /// The FIFO or socket.
        path: PathBuf,
    },
    /// The hidden temporary file or directory beside the destination could not be created.
    #[error(
        "cannot write {}: a temporary {} in {} {}",
        .path.display(),
        file_or_directory(*.directory),
        .dir.display(),
        write_cause(.io)
    )]
    Temporary {
        /// The destination.
        path: PathBuf,
        /// The directory the temporary was to be made in (the destination's).
        dir: PathBuf,
        /// A temporary directory ([`OutputDir`]) rather than a file ([`AtomicFile`]).
        directory: bool,
        /// The I/O error.
        io: std::io::Error,
    },
    /// The parent directory of an output directory could not be created.
    #[error("cannot create {}: it {}", .path.display(), write_cause(.io))]
    CreateDir {
        /// The directory that could not be created.
        path: PathBuf,
        /// The I/O error.
        io: std::io::Error,
    },
    /// A scratch directory ([`TempDir`]) could not be created.
    #[error("cannot create a temporary directory in {}: it {}", .dir.display(), write_cause(.io))]
    TempDir {
        /// The system's temporary directory.
        dir: PathBuf,
        /// The I/O error.
        io: std::io::Error,
    },
    /// A finished output directory could not be swapped in.
    #[error("cannot replace {} with the new {noun}: {}", .path.display(), plain(.io))]
    Replace {
        /// The destination.
        path: PathBuf,
        /// The kind of output ([`DirKind::noun`]).
        noun: &'static str,
        /// The I/O error.
        io: std::io::Error,
    },
    /// The output is one of the command's input files.
    #[error("refusing to write {what} {}: it is the input {}", .path.display(), .input.display())]
    IsInput {
        /// The option naming the output, e.g. `--out`.
        what: String,
        /// The output as given.
        path: PathBuf,
        /// The input as given.
        input: PathBuf,
    },
    /// The output lies inside an input directory.
    #[error(
        "refusing to write {what} {}: it is inside the input directory {} being read",
        .path.display(),
        .input.display()
    )]
    InsideInput {
        /// The option naming the output, e.g. `--out`.
        what: String,
        /// The output as given.
        path: PathBuf,
        /// The input directory as given.
        input: PathBuf,
    },
    /// The output directory holds an input (and would be replaced whole).
    #[error(
        "refusing to write {what} {}: it holds the input {} (it would be replaced)",
        .path.display(),
        .input.display()
    )]
    HoldsInput {
        /// The option naming the output directory, e.g. `--out`.
        what: String,
        /// The output directory as given.
        path: PathBuf,
        /// The input as given.
        input: PathBuf,
    },
    /// Two outputs of one command are the same file.
    #[error("{first_what} {} and {second_what} {} are the same file", .first.display(), .second.display())]
    SameFile {
        /// The first output's option, e.g. `--out`.
        first_what: String,
        /// The first output as given.
        first: PathBuf,
        /// The second output's option.
        second_what: String,
        /// The second output as given.
        second: PathBuf,
    },
    /// A PNG output whose name does not end in `.png`.
    #[error("{what} {}: the file name must end in .png", .path.display())]
    NotPng {
        /// The option naming the output, e.g. `--png`.
        what: String,
        /// The output as given.
        path: PathBuf,
    },
    /// An output directory named `.`, `..` or `/` (it cannot be swapped whole).
    #[error(
        "refusing to write the {noun} into {}: name the directory (it is replaced whole, so `.`, `..` and `/` cannot be)",
        .path.display()
    )]
    UnnamedDir {
        /// The kind of output ([`DirKind::noun`]).
        noun: &'static str,
        /// The destination as given.
        path: PathBuf,
    },
    /// The destination of an output directory exists and is not a directory.
    #[error("refusing to write the {noun} into {}: it exists and is not a directory", .path.display())]
    NotADirectory {
        /// The kind of output ([`DirKind::noun`]).
        noun: &'static str,
        /// The destination.
        path: PathBuf,
    },
    /// The destination holds another kind of dpsa output.
    #[error(
        "refusing to write the {noun} into {}: it holds another dpsa output ({format}); choose another directory",
        .path.display()
    )]
    OtherOutput {
        /// The kind of output ([`DirKind::noun`]).
        noun: &'static str,
        /// The destination.
        path: PathBuf,
        /// The format recorded in the destination's [`MARKER`].
        format: String,
    },
    /// The destination is a directory that is neither empty nor an earlier output of the kind.
    #[error(
        "refusing to write the {noun} into {}: it is not empty and holds no earlier {noun} (it has {:?}); choose a new or empty directory",
        .path.display(),
        .first
    )]
    NotEmpty {
        /// The kind of output ([`DirKind::noun`]).
        noun: &'static str,
        /// The destination.
        path: PathBuf,
        /// The name of one entry found in it.
        first: OsString,
    },
}

fn file_or_directory(directory: bool) -> &'static str {
    if directory {
        "directory"
    } else {
        "file"
    }
}

impl FileError {
    /// The I/O error behind the failure, when there is one.
    pub fn io(&self) -> Option<&std::io::Error> {
        match self {
            FileError::Read { io, .. }
            | FileError::Write { io, .. }
            | FileError::Temporary { io, .. }
            | FileError::CreateDir { io, .. }
            | FileError::TempDir { io, .. }
            | FileError::Replace { io, .. } => Some(io),
            _ => None,
        }
    }
}

/// Largest `manifest.json` read, bytes (64 MiB: a million frame entries).
pub const MAX_MANIFEST_BYTES: u64 = 64 << 20;
/// Largest scene TOML read, bytes.
pub const MAX_SCENE_BYTES: u64 = 16 << 20;

/// Largest frame PNG accepted for a `rows x width` camera: twice the raw 16-bit size plus
/// 1 MiB (filter bytes, zlib and chunk framing, ancillary chunks).
pub fn max_frame_png_bytes(rows: usize, width: usize) -> u64 {
    (rows as u64) * (width as u64) * 4 + (1 << 20)
}

/// Checks that `path` is a regular file (following symlinks) without opening it.
pub fn check_regular(path: &Path) -> std::io::Result<std::fs::Metadata> {
    let meta = std::fs::metadata(path)?;
    if meta.is_file() {
        return Ok(meta);
    }
    let kind = if meta.is_dir() {
        "a directory"
    } else {
        "not a regular file (a FIFO, socket or device)"
    };
    Err(std::io::Error::new(
        std::io::ErrorKind::InvalidInput,
        format!("is {kind}"),
    ))
}

/// Opens a regular file for reading in pieces (a packet stream of any size): a directory, FIFO
/// or device is refused with one sentence naming the file, before anything is read.
pub fn open_regular(path: &Path, what: &str) -> Result<File, FileError> {
    check_regular(path)
        .and_then(|_| File::open(path))
        .map_err(|io| read_error(what, path, io))
}

fn read_error(what: &str, path: &Path, io: std::io::Error) -> FileError {
    FileError::Read {
        what: what.to_string(),
        path: path.to_path_buf(),
        io,
    }
}

/// Reads a regular file of at most `cap` bytes (see the module docs). The error is one
/// sentence naming the file.
pub fn read_capped(path: &Path, cap: u64, what: &str) -> Result<Vec<u8>, FileError> {
    read_capped_io(path, cap).map_err(|io| read_error(what, path, io))
}

/// [`read_capped`] with an `std::io::Error` (kind `NotFound` kept for callers that report a
/// missing file themselves; a size above `cap` is `InvalidData`).
pub fn read_capped_io(path: &Path, cap: u64) -> std::io::Result<Vec<u8>> {
    let meta = check_regular(path)?;
    if meta.len() > cap {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "is {} bytes, more than the {cap} this file can hold",
                meta.len()
            ),
        ));
    }
    let mut buf = Vec::with_capacity(meta.len() as usize);
    File::open(path)?.take(cap + 1).read_to_end(&mut buf)?;
    if buf.len() as u64 > cap {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("grew beyond {cap} bytes while being read"),
        ));
    }
    Ok(buf)
}

/// The cause of an I/O error as a predicate after a path: "is a directory", "does not exist",
/// "cannot be read: permission denied", ... (no repeated OS text).
pub fn io_cause(e: &std::io::Error) -> String {
    use std::io::ErrorKind as K;
    match e.kind() {
        K::NotFound => "does not exist".into(),
        K::PermissionDenied => "cannot be accessed: permission denied".into(),
        K::InvalidInput | K::InvalidData if e.raw_os_error().is_none() => e.to_string(),
        _ => match e.raw_os_error() {
            Some(21) => "is a directory".into(),
            Some(28) => "cannot be written: no space left on the device (disk full)".into(),
            _ => format!("failed: {}", plain(e)),
        },
    }
}

/// The cause of a failed write as a predicate after a path: "cannot be written: no space
/// left on the device (disk full)", "is a directory", ...
pub fn write_cause(e: &std::io::Error) -> String {
    match e.raw_os_error() {
        Some(28) => "cannot be written: no space left on the device (disk full)".into(),
        Some(21) => "is a directory".into(),
        _ if e.kind() == std::io::ErrorKind::PermissionDenied => {
            "cannot be written: permission denied".into()
        }
        _ if e.raw_os_error().is_none() => format!("cannot be written: {e}"),
        _ => format!("cannot be written: {}", plain(e)),
    }
}

/// An I/O error's text without the `(os error N)` suffix.
pub fn plain(e: &std::io::Error) -> String {
    let s = e.to_string();
    match s.find(" (os error ") {
        Some(i) => s[..i].to_string(),
        None => s,
    }
}

/// A file being written: a temporary beside the destination until [`AtomicFile::commit`].
pub struct AtomicFile {
    path: PathBuf,
    inner: Inner,
}

/// Temporary files of unfinished [`AtomicFile`]s, removed by the interrupt handler.
static UNFINISHED: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

fn unfinished() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    UNFINISHED.lock().unwrap_or_else(|p| p.into_inner())
}

/// Removes a file, or a directory with everything in it. A writer thread may still be adding
/// files to the directory while the interrupt handler runs, and could outrun the removal
/// (each round empties it, and a new file keeps the last step from removing it): so the
/// directory is first renamed to a name of its own beside it (`NAME.removing`, hidden as the
/// temporaries' names are), where no writer's path leads, then removed; where the rename
/// fails it is removed where it is, retried.
fn remove_any(p: &Path) {
    match std::fs::symlink_metadata(p) {
        Ok(m) if m.is_dir() => {
            let mut gone = p.as_os_str().to_owned();
            gone.push(".removing");
            let gone = PathBuf::from(gone);
            let target = if std::fs::rename(p, &gone).is_ok() {
                gone
            } else {
                p.to_path_buf()
            };
            for _ in 0..5 {
                if std::fs::remove_dir_all(&target).is_ok() || !target.exists() {
                    break;
                }
            }
        }
        Ok(_) => {
            let _ = std::fs::remove_file(p);
        }
        Err(_) => {}
    }
}

fn register(p: &Path) {
    unfinished().push(p.to_path_buf());
}

fn unregister(p: &Path) {
    unfinished().retain(|q| q != p);
}

/// Mode requested for a new file; the process umask clears bits from it at creation.
fn file_mode() -> std::fs::Permissions {
    mode(0o666)
}

/// Mode requested for a new directory (umask applied at creation).
fn dir_mode() -> std::fs::Permissions {
    mode(0o777)
}

#[cfg(unix)]
fn mode(m: u32) -> std::fs::Permissions {
    use std::os::unix::fs::PermissionsExt;
    std::fs::Permissions::from_mode(m)
}

#[cfg(not(unix))]
fn mode(_: u32) -> std::fs::Permissions {
    std::fs::metadata(".")
        .map(|m| m.permissions())
        .unwrap_or_else(|_| unreachable!("the working directory has metadata"))
}

#[cfg(unix)]
fn is_fifo_or_socket(m: &std::fs::Metadata) -> bool {
    use std::os::unix::fs::FileTypeExt;
    m.file_type().is_fifo() || m.file_type().is_socket()
}

#[cfg(not(unix))]
fn is_fifo_or_socket(_: &std::fs::Metadata) -> bool {
    false
}

/// Makes SIGINT, SIGTERM and SIGHUP remove the temporary files of every unfinished output
/// before the process exits (status 130): an interrupted run leaves neither a partial output
/// nor a hidden temporary behind, and an earlier output at the destination stays as it was.
/// Without it the temporaries of [`AtomicFile`] outlive a signal (they are only removed when
/// dropped). Called once by `main`; a second call is ignored.
pub fn remove_unfinished_on_interrupt() {
    let _ = ctrlc::set_handler(|| {
        // The registry stays locked until the exit: a thread that fails because its
        // temporary vanished blocks on it (in `Drop`) instead of exiting first with status 1.
        let list = unfinished();
        let paths: Vec<PathBuf> = list.clone();
        for p in &paths {
            remove_any(p);
        }
        eprintln!(
            "error: interrupted{}",
            if paths.is_empty() {
                String::new()
            } else {
                format!("; {} unfinished output(s) removed", paths.len())
            }
        );
        std::process::exit(130);
    });
}

enum Inner {
    Temp(tempfile::NamedTempFile),
    /// The destination exists and is not a regular file: written in place.
    Direct(File),
    /// Committed.
    Done,
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        if let Inner::Temp(t) = &self.inner {
            let tmp = t.path().to_path_buf();
            unfinished().retain(|p| *p != tmp);
        }
    }
}

impl AtomicFile {
    /// Starts writing `path`. Refuses a directory; creates the temporary in `path`'s directory.
    pub fn create(path: &Path) -> Result<AtomicFile, FileError> {
        let fail = |io| FileError::Write {
            path: path.to_path_buf(),
            io,
        };
        match std::fs::metadata(path) {
            Ok(m) if m.is_dir() => {
                return Err(FileError::IsDirectory {
                    path: path.to_path_buf(),
                })
            }
            Ok(m) if is_fifo_or_socket(&m) => refuse_fifo_output("the output", path)?,
            Ok(m) if !m.is_file() => {
                let f = std::fs::OpenOptions::new()
                    .write(true)
                    .open(path)
                    .map_err(fail)?;
                return Ok(AtomicFile {
                    path: path.to_path_buf(),
                    inner: Inner::Direct(f),
                });
            }
            _ => {}
        }
        let dir = match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "out".into());
        let tmp = tempfile::Builder::new()
            .prefix(&format!(".{name}."))
            .permissions(file_mode())
            .tempfile_in(&dir)
            .map_err(|io| FileError::Temporary {
                path: path.to_path_buf(),
                dir: dir.clone(),
                directory: false,
                io,
            })?;
        unfinished().push(tmp.path().to_path_buf());
        Ok(AtomicFile {
            path: path.to_path_buf(),
            inner: Inner::Temp(tmp),
        })
    }

    /// The destination path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Flushes and renames the temporary into place (the destination appears whole or not at all).
    pub fn commit(mut self) -> Result<(), FileError> {
        let path = std::mem::take(&mut self.path);
        let fail = |io| FileError::Write {
            path: path.clone(),
            io,
        };
        match std::mem::replace(&mut self.inner, Inner::Done) {
            Inner::Temp(mut t) => {
                t.flush().map_err(fail)?;
                // Hold the registry while renaming, so an interrupt either removes the
                // temporary before the rename or finds it gone after.
                let mut list = unfinished();
                let tmp = t.path().to_path_buf();
                t.persist(&path).map_err(|e| fail(e.error))?;
                list.retain(|p| *p != tmp);
            }
            Inner::Direct(mut f) => f.flush().map_err(fail)?,
            Inner::Done => {}
        }
        Ok(())
    }

    fn file(&mut self) -> std::io::Result<&mut File> {
        match &mut self.inner {
            Inner::Temp(t) => Ok(t.as_file_mut()),
            Inner::Direct(f) => Ok(f),
            Inner::Done => Err(std::io::Error::other("the output was already committed")),
        }
    }
}

impl Write for AtomicFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.file()?.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.file()?.flush()
    }
}

impl Seek for AtomicFile {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.file()?.seek(pos)
    }
}

/// Writes `path` atomically through a buffered writer filled by `fill`. An error of `fill`
/// that is or wraps an I/O error becomes [`FileError::Write`] (see [`write_error`]); any other
/// is kept whole in [`FileError::Fill`].
pub fn write_atomic<E>(
    path: &Path,
    fill: impl FnOnce(&mut BufWriter<AtomicFile>) -> Result<(), E>,
) -> Result<(), FileError>
where
    E: std::error::Error + Send + Sync + 'static,
{
    let mut w = BufWriter::new(AtomicFile::create(path)?);
    fill(&mut w).map_err(|e| write_error(path, e))?;
    let f = w
        .into_inner()
        .map_err(|e| write_error(path, e.into_error()))?;
    f.commit()
}

/// Writes `bytes` to `path` atomically.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<(), FileError> {
    write_atomic(path, |w| w.write_all(bytes))
}

/// One sentence for a failed write to `path`: the first I/O error in `e`'s `source()` chain
/// (`e` itself included) gives [`FileError::Write`], its cause stated once; an error without
/// one is kept whole as [`FileError::Fill`].
pub fn write_error<E>(path: &Path, e: E) -> FileError
where
    E: std::error::Error + Send + Sync + 'static,
{
    let boxed: Box<dyn std::error::Error + Send + Sync + 'static> = Box::new(e);
    let boxed = match boxed.downcast::<std::io::Error>() {
        Ok(io) => {
            return FileError::Write {
                path: path.to_path_buf(),
                io: *io,
            }
        }
        Err(other) => other,
    };
    let mut cause = boxed.source();
    while let Some(c) = cause {
        if let Some(io) = c.downcast_ref::<std::io::Error>() {
            return FileError::Write {
                path: path.to_path_buf(),
                io: copy_io(io),
            };
        }
        cause = c.source();
    }
    FileError::Fill(boxed)
}

/// An owned copy of an I/O error: its OS code, or its kind and text.
fn copy_io(e: &std::io::Error) -> std::io::Error {
    match e.raw_os_error() {
        Some(code) => std::io::Error::from_raw_os_error(code),
        None => std::io::Error::new(e.kind(), e.to_string()),
    }
}

/// A writer that remembers its first I/O error (so a caller can report the file's cause once,
/// e.g. "disk full", instead of the error as wrapped by the layers in between) and optionally
/// keeps a copy of everything written.
pub struct Tee<W: Write> {
    /// The writer written through.
    pub inner: W,
    /// Everything written so far, when asked for (`None`: no copy kept).
    pub copy: Option<Vec<u8>>,
    /// The first I/O error of `inner` (an owned copy: its OS code, or its kind and text).
    pub error: Option<std::io::Error>,
}

impl<W: Write> Tee<W> {
    /// Writes through `inner`, keeping a copy of the bytes when `keep_copy`.
    pub fn new(inner: W, keep_copy: bool) -> Self {
        Tee {
            inner,
            copy: keep_copy.then(Vec::new),
            error: None,
        }
    }

    fn note<T>(&mut self, r: std::io::Result<T>) -> std::io::Result<T> {
        if let Err(e) = &r {
            if self.error.is_none() {
                self.error = Some(copy_io(e));
            }
        }
        r
    }
}

impl<W: Write> Write for Tee<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let r = self.inner.write(buf);
        let n = self.note(r)?;
        if let Some(c) = &mut self.copy {
            c.extend_from_slice(&buf[..n]);
        }
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        let r = self.inner.flush();
        self.note(r)
    }
}

/// Name of the hidden file that marks a directory written by [`OutputDir`]; it holds
/// `{"format": KIND}`.
pub const MARKER: &str = ".dpsa-output";

/// A kind of output directory.
#[derive(Clone, Copy)]
pub struct DirKind {
    /// Recorded in the [`MARKER`], e.g. `dpsa-board-map`.
    pub format: &'static str,
    /// For messages, e.g. `board map`.
    pub noun: &'static str,
    /// Recognises an earlier output of this kind written before the marker existed (by its
    /// own manifest).
    pub ours: fn(&Path) -> bool,
}

/// An output directory under construction: a hidden directory beside the destination until
/// [`OutputDir::commit`] swaps it in (see the module docs).
pub struct OutputDir {
    dest: PathBuf,
    tmp: PathBuf,
    kind: DirKind,
    done: bool,
}

/// The kind recorded in `dir`'s [`MARKER`], if any.
fn marker_kind(dir: &Path) -> Option<String> {
    let b = read_capped_io(&dir.join(MARKER), 4096).ok()?;
    let v: serde_json::Value = serde_json::from_slice(&b).ok()?;
    Some(v.get("format")?.as_str()?.to_string())
}

/// Checks (before any work) that `dest` may be replaced by an output of `kind`: it does not
/// exist, is an empty directory, or holds an earlier output of this kind (its [`MARKER`] or
/// `kind.ours`). A symbolic link is refused (the swap would replace the link).
pub fn check_output_dir(dest: &Path, kind: DirKind) -> Result<(), FileError> {
    let noun = kind.noun;
    let path = dest.to_path_buf();
    if dest.file_name().is_none() {
        return Err(FileError::UnnamedDir { noun, path });
    }
    let meta = match std::fs::symlink_metadata(dest) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(io) => return Err(read_error("output directory", dest, io)),
    };
    if !meta.is_dir() {
        return Err(FileError::NotADirectory { noun, path });
    }
    let first = std::fs::read_dir(dest)
        .and_then(|mut d| d.next().transpose())
        .map_err(|io| read_error("output directory", dest, io))?;
    let Some(first) = first else {
        return Ok(());
    };
    match marker_kind(dest) {
        Some(k) if k == kind.format => Ok(()),
        Some(format) => Err(FileError::OtherOutput { noun, path, format }),
        None if (kind.ours)(dest) => Ok(()),
        None => Err(FileError::NotEmpty {
            noun,
            path,
            first: first.file_name(),
        }),
    }
}

impl OutputDir {
    /// Starts an output directory of `kind` for `dest`: checks the destination (see
    /// [`check_output_dir`]) and creates the hidden directory beside it, removed on an error,
    /// on drop and by the interrupt handler.
    pub fn create(dest: &Path, kind: DirKind) -> Result<OutputDir, FileError> {
        check_output_dir(dest, kind)?;
        let parent = match dest.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent).map_err(|io| FileError::CreateDir {
            path: parent.clone(),
            io,
        })?;
        let name = dest
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "out".into());
        // Registered while the lock is held, so an interrupt cannot miss it.
        let mut list = unfinished();
        let tmp = tempfile::Builder::new()
            .prefix(&format!(".{name}."))
            .permissions(dir_mode())
            .tempdir_in(&parent)
            .map_err(|io| FileError::Temporary {
                path: dest.to_path_buf(),
                dir: parent.clone(),
                directory: true,
                io,
            })?
            .keep();
        list.push(tmp.clone());
        drop(list);
        Ok(OutputDir {
            dest: dest.to_path_buf(),
            tmp,
            kind,
            done: false,
        })
    }

    /// The directory to write into (the hidden one until [`OutputDir::commit`]).
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// The destination.
    pub fn dest(&self) -> &Path {
        &self.dest
    }

    /// Writes the marker and swaps the finished directory in whole; the earlier directory
    /// (if any) is removed.
    pub fn commit(mut self) -> Result<(), FileError> {
        let marker = serde_json::json!({ "format": self.kind.format }).to_string();
        write_bytes(&self.tmp.join(MARKER), marker.as_bytes())?;
        // Re-checked: something else may have appeared at the destination meanwhile.
        check_output_dir(&self.dest, self.kind)?;
        let fail = |io| FileError::Replace {
            path: self.dest.clone(),
            noun: self.kind.noun,
            io,
        };
        {
            // The interrupt handler waits for the swap: it then removes the hidden path,
            // which holds either the new directory (not swapped) or the old one (swapped).
            let _list = unfinished();
            swap_in(&self.tmp, &self.dest).map_err(fail)?;
        }
        remove_any(&self.tmp);
        unregister(&self.tmp);
        self.done = true;
        Ok(())
    }
}

impl Drop for OutputDir {
    fn drop(&mut self) {
        if !self.done {
            remove_any(&self.tmp);
            unregister(&self.tmp);
        }
    }
}

/// Moves the directory `new` to `dest`; an existing `dest` ends up at `new` (to be removed by
/// the caller). On Linux one `renameat2` call: `RENAME_EXCHANGE` when `dest` exists (the
/// destination is a whole directory at every instant, even across a crash), `RENAME_NOREPLACE`
/// when it does not (a concurrent writer that got there first is exchanged with instead of
/// failing). Elsewhere, or on a file system without these flags, the old directory is renamed
/// aside first (a crash between the two renames leaves it under its hidden name).
fn swap_in(new: &Path, dest: &Path) -> std::io::Result<()> {
    for _ in 0..100 {
        let exists = std::fs::symlink_metadata(dest).is_ok();
        match rename2(new, dest, exists) {
            Ok(()) => return Ok(()),
            // Raced: the destination appeared or vanished between the check and the call.
            Err(e)
                if matches!(
                    e.raw_os_error(),
                    Some(libc_errno::EEXIST | libc_errno::ENOENT)
                ) =>
            {
                continue
            }
            Err(e)
                if matches!(
                    e.raw_os_error(),
                    Some(libc_errno::EINVAL | libc_errno::ENOSYS)
                ) =>
            {
                return swap_aside(new, dest)
            }
            Err(e) => return Err(e),
        }
    }
    Err(std::io::Error::other(
        "the destination kept changing while it was being replaced",
    ))
}

mod libc_errno {
    pub const ENOENT: i32 = 2;
    pub const EEXIST: i32 = 17;
    pub const EINVAL: i32 = 22;
    pub const ENOSYS: i32 = 38;
}

#[cfg(target_os = "linux")]
fn rename2(from: &Path, to: &Path, exchange: bool) -> std::io::Result<()> {
    use rustix::fs::{renameat_with, RenameFlags, CWD};
    let flags = if exchange {
        RenameFlags::EXCHANGE
    } else {
        RenameFlags::NOREPLACE
    };
    renameat_with(CWD, from, CWD, to, flags).map_err(std::io::Error::from)
}

#[cfg(not(target_os = "linux"))]
fn rename2(_: &Path, _: &Path, _: bool) -> std::io::Result<()> {
    Err(std::io::Error::from_raw_os_error(libc_errno::ENOSYS))
}

/// [`swap_in`] without `renameat2`: the old directory is renamed to a hidden name beside it,
/// the new one renamed in, and the old one moved to `new` for the caller to remove.
fn swap_aside(new: &Path, dest: &Path) -> std::io::Result<()> {
    let parent = dest.parent().unwrap_or(Path::new("."));
    for _ in 0..100 {
        let aside = tempfile::Builder::new()
            .prefix(".dpsa-old.")
            .tempdir_in(if parent.as_os_str().is_empty() {
                Path::new(".")
            } else {
                parent
            })?
            .keep();
        register(&aside);
        let moved = match std::fs::rename(dest, &aside) {
            Ok(()) => true,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
            Err(e) => {
                remove_any(&aside);
                unregister(&aside);
                return Err(e);
            }
        };
        match std::fs::rename(new, dest) {
            Ok(()) => {
                let _ = std::fs::rename(&aside, new);
                remove_any(&aside);
                unregister(&aside);
                return Ok(());
            }
            // Another writer put its directory in between: try again.
            Err(_) if std::fs::symlink_metadata(dest).is_ok() => {
                let _ = moved;
                remove_any(&aside);
                unregister(&aside);
                continue;
            }
            Err(e) => {
                if moved {
                    let _ = std::fs::rename(&aside, dest);
                }
                remove_any(&aside);
                unregister(&aside);
                return Err(e);
            }
        }
    }
    Err(std::io::Error::other(
        "the destination kept changing while it was being replaced",
    ))
}

/// A scratch directory (in the system temporary directory unless given a parent), removed when
/// dropped and by the SIGINT/SIGTERM handler (see [`remove_unfinished_on_interrupt`]).
pub struct TempDir {
    path: PathBuf,
}

impl TempDir {
    /// A new scratch directory whose name starts with `prefix`.
    pub fn new(prefix: &str) -> Result<TempDir, FileError> {
        let mut list = unfinished();
        let path = tempfile::Builder::new()
            .prefix(prefix)
            .tempdir()
            .map_err(|io| FileError::TempDir {
                dir: std::env::temp_dir(),
                io,
            })?
            .keep();
        list.push(path.clone());
        Ok(TempDir { path })
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        remove_any(&self.path);
        unregister(&self.path);
    }
}

/// An input of a command, for [`refuse_overwrite`].
pub enum Input<'a> {
    /// A file read by the command.
    File(&'a Path),
    /// A directory read by the command (a recording): nothing inside it may be written.
    Dir(&'a Path),
}

/// `path` with symlinks resolved; for a path that does not exist yet, its resolved parent
/// joined with its file name.
fn resolve(path: &Path) -> PathBuf {
    if let Ok(p) = std::fs::canonicalize(path) {
        return p;
    }
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    match (std::fs::canonicalize(parent), path.file_name()) {
        (Ok(p), Some(name)) => p.join(name),
        _ => path.to_path_buf(),
    }
}

/// Refuses (before any work) to write the file `output` when it is one of the `inputs` or lies
/// inside an input directory. `what` names the option, e.g. `--out`.
pub fn refuse_overwrite(what: &str, output: &Path, inputs: &[Input]) -> Result<(), FileError> {
    refuse(what, output, inputs, false)
}

/// [`refuse_overwrite`] for an output directory (replaced whole, see [`OutputDir`]): also
/// refused when it holds an input (a program, a paste layer, a calibration inside it).
pub fn refuse_overwrite_dir(what: &str, output: &Path, inputs: &[Input]) -> Result<(), FileError> {
    refuse(what, output, inputs, true)
}

fn refuse(what: &str, output: &Path, inputs: &[Input], out_is_dir: bool) -> Result<(), FileError> {
    let out = resolve(output);
    for input in inputs {
        let (p, dir) = match input {
            Input::File(p) => (*p, false),
            Input::Dir(d) => (*d, true),
        };
        let inp = resolve(p);
        let (what, path, input) = (what.to_string(), output.to_path_buf(), p.to_path_buf());
        if inp == out {
            return Err(FileError::IsInput { what, path, input });
        }
        if dir && out.starts_with(&inp) {
            return Err(FileError::InsideInput { what, path, input });
        }
        if out_is_dir && inp.starts_with(&out) {
            return Err(FileError::HoldsInput { what, path, input });
        }
    }
    Ok(())
}

/// Refuses (before any work) an output path that is a FIFO or a socket: writing it would wait
/// for a reader. Devices such as `/dev/null` stay allowed.
pub fn refuse_fifo_output(what: &str, path: &Path) -> Result<(), FileError> {
    match std::fs::metadata(path) {
        Ok(m) if is_fifo_or_socket(&m) => Err(FileError::Fifo {
            what: what.to_string(),
            path: path.to_path_buf(),
        }),
        _ => Ok(()),
    }
}

/// Refuses two outputs of one command that are the same file.
pub fn refuse_same(a: (&str, &Path), b: (&str, &Path)) -> Result<(), FileError> {
    if resolve(a.1) == resolve(b.1) {
        return Err(FileError::SameFile {
            first_what: a.0.to_string(),
            first: a.1.to_path_buf(),
            second_what: b.0.to_string(),
            second: b.1.to_path_buf(),
        });
    }
    Ok(())
}

/// Refuses a PNG output path without the `.png` extension.
pub fn require_png(what: &str, path: &Path) -> Result<(), FileError> {
    let ok = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !ok {
        return Err(FileError::NotPng {
            what: what.to_string(),
            path: path.to_path_buf(),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A directory that writer threads keep adding files to (as an output's writers do while
    /// the interrupt handler removes it) is removed whole, and nothing of it is left beside it.
    #[test]
    fn a_directory_still_being_written_is_removed() {
        let parent = tempfile::tempdir().unwrap();
        for round in 0..20 {
            let d = parent.path().join(format!(".out.{round}"));
            std::fs::create_dir(&d).unwrap();
            for i in 0..200 {
                std::fs::write(d.join(format!("old{i}")), b"x").unwrap();
            }
            let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
            let writers: Vec<_> = (0..2)
                .map(|w| {
                    let (d, stop) = (d.clone(), stop.clone());
                    std::thread::spawn(move || {
                        let mut i = 0u64;
                        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                            let _ = std::fs::write(d.join(format!("w{w}-{i}")), b"y");
                            i += 1;
                        }
                    })
                })
                .collect();
            std::thread::sleep(std::time::Duration::from_millis(2));
            remove_any(&d);
            stop.store(true, std::sync::atomic::Ordering::Relaxed);
            for w in writers {
                w.join().unwrap();
            }
            assert!(!d.exists(), "round {round}");
        }
        let left: Vec<_> = std::fs::read_dir(parent.path()).unwrap().collect();
        assert!(left.is_empty(), "{left:?}");
    }

    #[test]
    fn atomic_write_appears_only_on_commit() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.bin");
        std::fs::write(&p, b"old").unwrap();
        let mut f = AtomicFile::create(&p).unwrap();
        f.write_all(b"new contents").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        f.commit().unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new contents");
        // An error leaves the old file and no temporary.
        let err = write_atomic(&p, |w| {
            w.write_all(b"partial")?;
            Err(std::io::Error::other("boom"))
        });
        assert!(err.is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"new contents");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    /// An error whose `source()` is an I/O error (as an encoder's error wrapping its writer's).
    #[derive(Debug)]
    struct Wrapped(std::io::Error);

    impl std::fmt::Display for Wrapped {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str("the encoder failed")
        }
    }

    impl std::error::Error for Wrapped {
        fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
            Some(&self.0)
        }
    }

    /// The typed errors say the sentences the `anyhow` messages said, the I/O cause once and
    /// not again as a `source()` (a chain printed whole, as the CLI does, would repeat it).
    #[test]
    fn file_errors_are_one_sentence() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("none.json");
        let e = read_capped(&missing, 10, "manifest").unwrap_err();
        assert_eq!(
            e.to_string(),
            format!("manifest {} does not exist", missing.display())
        );
        assert!(std::error::Error::source(&e).is_none());
        assert_eq!(
            e.io().map(|io| io.kind()),
            Some(std::io::ErrorKind::NotFound)
        );
        let e = open_regular(dir.path(), "stream").unwrap_err();
        assert_eq!(
            e.to_string(),
            format!("stream {} is a directory", dir.path().display())
        );

        // A filler's I/O error, bare or as the source of its own error: the path and the
        // cause in plain words (ENOSPC is 28 on Linux).
        let out = dir.path().join("out.bin");
        let full = || std::io::Error::from_raw_os_error(28);
        let want = format!(
            "{} cannot be written: no space left on the device (disk full)",
            out.display()
        );
        let e = write_atomic(&out, |_| Err(full())).unwrap_err();
        assert_eq!(e.to_string(), want);
        let e = write_atomic(&out, |_| Err(Wrapped(full()))).unwrap_err();
        assert_eq!(e.to_string(), want);
        assert!(std::error::Error::source(&e).is_none());
        // Any other error is kept whole.
        let e = write_atomic(&out, |_| Err(std::fmt::Error)).unwrap_err();
        assert!(matches!(e, FileError::Fill(_)), "{e:?}");
        assert_eq!(e.to_string(), std::fmt::Error.to_string());
        assert!(!out.exists());
        assert_eq!(
            AtomicFile::create(dir.path()).err().map(|e| e.to_string()),
            Some(format!(
                "cannot write {}: it is a directory",
                dir.path().display()
            ))
        );

        let input = dir.path().join("in.txt");
        std::fs::write(&input, b"x").unwrap();
        let e = refuse_overwrite("--out", &input, &[Input::File(&input)]).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!(
                "refusing to write --out {0}: it is the input {0}",
                input.display()
            )
        );
        let e = refuse_same(("--out", &input), ("--png", &input)).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!("--out {0} and --png {0} are the same file", input.display())
        );
        let e = require_png("--png", Path::new("a.tif")).unwrap_err();
        assert_eq!(e.to_string(), "--png a.tif: the file name must end in .png");
        let e = check_output_dir(dir.path(), KIND).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!(
                "refusing to write the test output into {}: it is not empty and holds no \
                 earlier test output (it has \"in.txt\"); choose a new or empty directory",
                dir.path().display()
            )
        );
        let e = check_output_dir(&input, KIND).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!(
                "refusing to write the test output into {}: it exists and is not a directory",
                input.display()
            )
        );
    }

    const KIND: DirKind = DirKind {
        format: "dpsa-test",
        noun: "test output",
        ours: |_| false,
    };

    #[test]
    fn output_dirs_are_swapped_in_whole() {
        let root = tempfile::tempdir().unwrap();
        let dest = root.path().join("out");
        let listing = || -> Vec<String> {
            let mut v: Vec<String> = std::fs::read_dir(root.path())
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            v.sort();
            v
        };
        for run in 0..2 {
            let o = OutputDir::create(&dest, KIND).unwrap();
            std::fs::write(o.path().join(format!("f{run}")), b"x").unwrap();
            // Nothing at the destination changes before the commit.
            assert_eq!(dest.join("f0").exists(), run == 1);
            o.commit().unwrap();
            assert!(dest.join(format!("f{run}")).is_file());
            assert_eq!(dest.join("f0").exists(), run == 0, "stale file of run 0");
            assert_eq!(listing(), ["out"]);
        }
        // Dropped without a commit: the old directory stays, the hidden one goes.
        let o = OutputDir::create(&dest, KIND).unwrap();
        std::fs::write(o.path().join("g"), b"x").unwrap();
        drop(o);
        assert!(dest.join("f1").is_file() && !dest.join("g").exists());
        assert_eq!(listing(), ["out"]);
        // Another kind's directory, an unrelated one and a file are refused.
        let other = DirKind {
            format: "dpsa-other",
            ..KIND
        };
        assert!(OutputDir::create(&dest, other).is_err());
        let mine = root.path().join("mine");
        std::fs::create_dir(&mine).unwrap();
        std::fs::write(mine.join("notes"), b"x").unwrap();
        assert!(OutputDir::create(&mine, KIND).is_err());
        assert!(OutputDir::create(&mine.join("notes"), KIND).is_err());
        // The fallback without renameat2: old renamed aside, new renamed in.
        let new = root.path().join("new");
        std::fs::create_dir(&new).unwrap();
        std::fs::write(new.join("h"), b"x").unwrap();
        swap_aside(&new, &dest).unwrap();
        assert!(dest.join("h").is_file() && new.join("f1").is_file());
    }

    #[test]
    fn capped_reads() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x");
        std::fs::write(&p, [0u8; 100]).unwrap();
        assert_eq!(read_capped_io(&p, 100).unwrap().len(), 100);
        assert!(read_capped_io(&p, 99).is_err());
        let e = read_capped_io(dir.path(), 10).unwrap_err();
        assert!(e.to_string().contains("directory"), "{e}");
        let e = read_capped_io(Path::new("/dev/zero"), 10).unwrap_err();
        assert!(e.to_string().contains("not a regular file"), "{e}");
    }

    #[test]
    fn overwrite_checks() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("in.txt");
        std::fs::write(&f, b"x").unwrap();
        let inside = dir.path().join("new.dpsa");
        assert!(refuse_overwrite("--out", &inside, &[Input::Dir(dir.path())]).is_err());
        assert!(refuse_overwrite("--out", &f, &[Input::File(&f)]).is_err());
        let other = tempfile::tempdir().unwrap();
        assert!(
            refuse_overwrite("--out", &other.path().join("o"), &[Input::Dir(dir.path())]).is_ok()
        );
        // `.` cannot be swapped.
        let kind = DirKind {
            format: "test-kind",
            noun: "test output",
            ours: |_| false,
        };
        assert!(check_output_dir(Path::new("."), kind).is_err());
        // An output directory that holds an input file.
        assert!(refuse_overwrite_dir("--out", dir.path(), &[Input::File(&f)]).is_err());
        assert!(refuse_overwrite("--out", dir.path(), &[Input::File(&f)]).is_ok());
        assert!(require_png("--png", Path::new("a.PNG")).is_ok());
        assert!(require_png("--png", Path::new("a.dpsa")).is_err());
    }
}
