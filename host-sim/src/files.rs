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
//! * **Outputs never overwrite inputs.** [`refuse_overwrite`] refuses an output that is an
//!   input file (after resolving symlinks) or lies inside an input directory, before any work.

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

/// Makes SIGINT, SIGTERM and SIGHUP remove the temporary files of every unfinished output
/// before the process exits (status 130): an interrupted run leaves neither a partial output
/// nor a hidden temporary behind, and an earlier output at the destination stays as it was.
/// Without it the temporaries of [`AtomicFile`] outlive a signal (they are only removed when
/// dropped). Called once by `main`; a second call is ignored.
pub fn remove_unfinished_on_interrupt() {
    let _ = ctrlc::set_handler(|| {
        let paths = std::mem::take(&mut *unfinished());
        for p in &paths {
            let _ = std::fs::remove_file(p);
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

/// Refuses (before any work) to write `output` when it is one of the `inputs` or lies inside
/// an input directory. `what` names the option, e.g. `--out`.
pub fn refuse_overwrite(what: &str, output: &Path, inputs: &[Input]) -> Result<()> {
    let out = resolve(output);
    for input in inputs {
        match input {
            Input::File(p) => {
                if resolve(p) == out {
                    bail!(
                        "refusing to write {what} {}: it is the input {}",
                        output.display(),
                        p.display()
                    );
                }
            }
            Input::Dir(d) => {
                if out.starts_with(resolve(d)) {
                    bail!(
                        "refusing to write {what} {}: it is inside the recording {} being read",
                        output.display(),
                        d.display()
                    );
                }
            }
        }
    }
    Ok(())
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
        assert!(require_png("--png", Path::new("a.PNG")).is_ok());
        assert!(require_png("--png", Path::new("a.dpsa")).is_err());
    }
}
