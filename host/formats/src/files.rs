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

use anyhow::{bail, Result};
use std::fs::File;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

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
pub fn open_regular(path: &Path, what: &str) -> Result<File> {
    check_regular(path)
        .and_then(|_| File::open(path))
        .map_err(|e| anyhow::anyhow!("{what} {} {}", path.display(), io_cause(&e)))
}

/// Reads a regular file of at most `cap` bytes (see the module docs). The error is one
/// sentence naming the file.
pub fn read_capped(path: &Path, cap: u64, what: &str) -> Result<Vec<u8>> {
    read_capped_io(path, cap)
        .map_err(|e| anyhow::anyhow!("{what} {} {}", path.display(), io_cause(&e)))
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

/// Removes a file, or a directory with everything in it (retried: a writer thread may still be
/// adding files while the interrupt handler runs).
fn remove_any(p: &Path) {
    match std::fs::symlink_metadata(p) {
        Ok(m) if m.is_dir() => {
            for _ in 0..5 {
                if std::fs::remove_dir_all(p).is_ok() || !p.exists() {
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
    pub fn create(path: &Path) -> Result<AtomicFile> {
        let fail = |e: std::io::Error| anyhow::anyhow!("{} {}", path.display(), write_cause(&e));
        match std::fs::metadata(path) {
            Ok(m) if m.is_dir() => bail!("cannot write {}: it is a directory", path.display()),
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
            .map_err(|e| {
                anyhow::anyhow!(
                    "cannot write {}: a temporary file in {} {}",
                    path.display(),
                    dir.display(),
                    write_cause(&e)
                )
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
    pub fn commit(mut self) -> Result<()> {
        let path = std::mem::take(&mut self.path);
        let fail = |e: std::io::Error| anyhow::anyhow!("{} {}", path.display(), write_cause(&e));
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

/// Writes `path` atomically through a buffered writer filled by `fill`.
pub fn write_atomic(
    path: &Path,
    fill: impl FnOnce(&mut BufWriter<AtomicFile>) -> Result<()>,
) -> Result<()> {
    let mut w = BufWriter::new(AtomicFile::create(path)?);
    fill(&mut w).map_err(|e| write_error(path, e))?;
    let f = w
        .into_inner()
        .map_err(|e| write_error(path, anyhow::Error::new(e.into_error())))?;
    f.commit()
}

/// Writes `bytes` to `path` atomically.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic(path, |w| Ok(w.write_all(bytes)?))
}

/// One sentence for a failed write to `path`: an I/O cause found in the chain is stated once.
pub fn write_error(path: &Path, e: anyhow::Error) -> anyhow::Error {
    match e.chain().find_map(|c| c.downcast_ref::<std::io::Error>()) {
        Some(io) => anyhow::anyhow!("{} {}", path.display(), write_cause(io)),
        None => e,
    }
}

/// A writer that remembers its first I/O error (so a caller can report the file's cause once,
/// e.g. "disk full", instead of the error as wrapped by the layers in between) and optionally
/// keeps a copy of everything written.
pub struct Tee<W: Write> {
    pub inner: W,
    pub copy: Option<Vec<u8>>,
    pub error: Option<std::io::Error>,
}

impl<W: Write> Tee<W> {
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
                self.error = Some(match e.raw_os_error() {
                    Some(code) => std::io::Error::from_raw_os_error(code),
                    None => std::io::Error::new(e.kind(), e.to_string()),
                });
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
pub fn check_output_dir(dest: &Path, kind: DirKind) -> Result<()> {
    let noun = kind.noun;
    if dest.file_name().is_none() {
        bail!(
            "refusing to write the {noun} into {}: name the directory (it is replaced whole, so `.`, `..` and `/` cannot be)",
            dest.display()
        );
    }
    let meta = match std::fs::symlink_metadata(dest) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => bail!("output directory {} {}", dest.display(), io_cause(&e)),
    };
    if !meta.is_dir() {
        bail!(
            "refusing to write the {noun} into {}: it exists and is not a directory",
            dest.display()
        );
    }
    let first = std::fs::read_dir(dest)
        .and_then(|mut d| d.next().transpose())
        .map_err(|e| anyhow::anyhow!("output directory {} {}", dest.display(), io_cause(&e)))?;
    let Some(first) = first else {
        return Ok(());
    };
    match marker_kind(dest) {
        Some(k) if k == kind.format => return Ok(()),
        Some(k) => bail!(
            "refusing to write the {noun} into {}: it holds another dpsa output ({k}); choose another directory",
            dest.display()
        ),
        None if (kind.ours)(dest) => return Ok(()),
        None => {}
    }
    bail!(
        "refusing to write the {noun} into {}: it is not empty and holds no earlier {noun} (it has {:?}); choose a new or empty directory",
        dest.display(),
        first.file_name()
    )
}

impl OutputDir {
    /// Starts an output directory of `kind` for `dest`: checks the destination (see
    /// [`check_output_dir`]) and creates the hidden directory beside it, removed on an error,
    /// on drop and by the interrupt handler.
    pub fn create(dest: &Path, kind: DirKind) -> Result<OutputDir> {
        check_output_dir(dest, kind)?;
        let parent = match dest.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent).map_err(|e| {
            anyhow::anyhow!("cannot create {}: it {}", parent.display(), write_cause(&e))
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
            .map_err(|e| {
                anyhow::anyhow!(
                    "cannot write {}: a temporary directory in {} {}",
                    dest.display(),
                    parent.display(),
                    write_cause(&e)
                )
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
    pub fn commit(mut self) -> Result<()> {
        let marker = serde_json::json!({ "format": self.kind.format }).to_string();
        write_bytes(&self.tmp.join(MARKER), marker.as_bytes())?;
        // Re-checked: something else may have appeared at the destination meanwhile.
        check_output_dir(&self.dest, self.kind)?;
        let fail = |e: std::io::Error| {
            anyhow::anyhow!(
                "cannot replace {} with the new {}: {}",
                self.dest.display(),
                self.kind.noun,
                plain(&e)
            )
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
    pub fn new(prefix: &str) -> Result<TempDir> {
        let mut list = unfinished();
        let path = tempfile::Builder::new()
            .prefix(prefix)
            .tempdir()
            .map_err(|e| {
                anyhow::anyhow!(
                    "cannot create a temporary directory in {}: it {}",
                    std::env::temp_dir().display(),
                    write_cause(&e)
                )
            })?
            .keep();
        list.push(path.clone());
        Ok(TempDir { path })
    }

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
pub fn refuse_overwrite(what: &str, output: &Path, inputs: &[Input]) -> Result<()> {
    refuse(what, output, inputs, false)
}

/// [`refuse_overwrite`] for an output directory (replaced whole, see [`OutputDir`]): also
/// refused when it holds an input (a program, a paste layer, a calibration inside it).
pub fn refuse_overwrite_dir(what: &str, output: &Path, inputs: &[Input]) -> Result<()> {
    refuse(what, output, inputs, true)
}

fn refuse(what: &str, output: &Path, inputs: &[Input], out_is_dir: bool) -> Result<()> {
    let out = resolve(output);
    for input in inputs {
        let (p, dir) = match input {
            Input::File(p) => (*p, false),
            Input::Dir(d) => (*d, true),
        };
        let inp = resolve(p);
        if inp == out {
            bail!(
                "refusing to write {what} {}: it is the input {}",
                output.display(),
                p.display()
            );
        }
        if dir && out.starts_with(&inp) {
            bail!(
                "refusing to write {what} {}: it is inside the input directory {} being read",
                output.display(),
                p.display()
            );
        }
        if out_is_dir && inp.starts_with(&out) {
            bail!(
                "refusing to write {what} {}: it holds the input {} (it would be replaced)",
                output.display(),
                p.display()
            );
        }
    }
    Ok(())
}

/// Refuses (before any work) an output path that is a FIFO or a socket: writing it would wait
/// for a reader. Devices such as `/dev/null` stay allowed.
pub fn refuse_fifo_output(what: &str, path: &Path) -> Result<()> {
    match std::fs::metadata(path) {
        Ok(m) if is_fifo_or_socket(&m) => bail!(
            "cannot write {what} {}: it is a FIFO or socket (a write would wait for a reader); give a regular file",
            path.display()
        ),
        _ => Ok(()),
    }
}

/// Refuses two outputs of one command that are the same file.
pub fn refuse_same(a: (&str, &Path), b: (&str, &Path)) -> Result<()> {
    if resolve(a.1) == resolve(b.1) {
        bail!(
            "{} {} and {} {} are the same file",
            a.0,
            a.1.display(),
            b.0,
            b.1.display()
        );
    }
    Ok(())
}

/// Refuses a PNG output path without the `.png` extension.
pub fn require_png(what: &str, path: &Path) -> Result<()> {
    let ok = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !ok {
        bail!("{what} {}: the file name must end in .png", path.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
            anyhow::bail!("boom")
        });
        assert!(err.is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"new contents");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
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
