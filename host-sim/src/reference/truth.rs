//! Ground-truth lookups: heights and illumination at a board row, and the flat-pixel mask.

use crate::simulation::recording::{
    CameraTruth, Recording, RecordingError, TRUTH_BACKGROUND_FILE, TRUTH_CONTRAST_FILE,
    TRUTH_HEIGHT_FILE,
};

/// Index of board row `b` in the truth arrays.
pub(crate) fn truth_row_index(truth: &CameraTruth, b: i64) -> Option<usize> {
    let i = b.checked_sub(truth.first_row)?;
    (i >= 0 && (i as u64) < truth.rows as u64).then_some(i as usize)
}

/// `(height um, background DN, contrast DN)` of truth row index `ti`, column `c`.
pub(crate) fn truth_at(truth: &CameraTruth, ti: usize, c: usize) -> Option<(f64, f64, f64)> {
    if c >= truth.width {
        return None;
    }
    let idx = ti.checked_mul(truth.width)?.checked_add(c)?;
    Some((
        f64::from(*truth.height_um.get(idx)?),
        f64::from(*truth.background.get(idx)?),
        f64::from(*truth.contrast.get(idx)?),
    ))
}

/// True height of board row `b`, column `c`, um, when inside the truth.
pub fn truth_height(truth: &CameraTruth, b: i64, c: usize) -> Option<f64> {
    let ti = truth_row_index(truth, b)?;
    if c >= truth.width {
        return None;
    }
    truth
        .height_um
        .get(ti * truth.width + c)
        .map(|&h| f64::from(h))
}

/// Flat-pixel mask of the truth, row-major `truth.rows x truth.width`.
///
/// A pixel is flat when it and its 8 neighbours (board rows `b-1..=b+1`, columns
/// `c-1..=c+1`) have exactly the same truth height; border pixels are never flat. Errors
/// against truth are measured only on flat pixels: registration rounds each frame's offset to
/// a whole pixel, so a sample can come from up to half a pixel away along the motion, and on
/// deposit walls the error would measure that lateral sampling rather than the phase
/// algorithm.
pub fn flat_mask(truth: &CameraTruth) -> Vec<bool> {
    let (rows, w) = (truth.rows, truth.width);
    let mut mask = vec![false; rows.saturating_mul(w)];
    if truth.height_um.len() < rows.saturating_mul(w) {
        return mask;
    }
    let h = &truth.height_um;
    let line = |r: usize| &h[r * w..(r + 1) * w];
    for r in 1..rows.saturating_sub(1) {
        let flat = flat_row(line(r - 1), line(r), line(r + 1));
        mask[r * w..(r + 1) * w].copy_from_slice(&flat);
    }
    mask
}

/// The [`flat_mask`] of one truth row from its heights and those of its neighbours (board
/// rows `b - 1`, `b`, `b + 1`, all of one width): a pixel is flat when it and its 8 neighbours
/// have exactly the same height; the first and last columns never are.
pub fn flat_row(prev: &[f32], cur: &[f32], next: &[f32]) -> Vec<bool> {
    let w = cur.len();
    let mut flat = vec![false; w];
    if w < 3 || prev.len() != w || next.len() != w {
        return flat;
    }
    for c in 1..w - 1 {
        let v = cur[c];
        flat[c] = [prev, cur, next]
            .iter()
            .all(|line| line[c - 1..=c + 1].iter().all(|&x| x == v));
    }
    flat
}

/// One board row of the ground truth: heights um, background and contrast DN, and its
/// [`flat_row`] (all false for the first and last truth rows).
#[derive(Clone, Debug)]
pub struct CameraTruthRow<'a> {
    /// True height per column, um.
    pub height_um: &'a [f32],
    /// Background `B` per column, DN.
    pub background: &'a [f32],
    /// Contrast `C` per column, DN.
    pub contrast: &'a [f32],
    /// Per column: flat in the truth ([`flat_row`]).
    pub flat: Vec<bool>,
}

impl CameraTruthRow<'_> {
    /// `(height um, background DN, contrast DN)` of column `c`.
    pub fn at(&self, c: usize) -> Option<(f64, f64, f64)> {
        Some((
            f64::from(*self.height_um.get(c)?),
            f64::from(*self.background.get(c)?),
            f64::from(*self.contrast.get(c)?),
        ))
    }

    /// True when column `c` is flat.
    pub fn is_flat(&self, c: usize) -> bool {
        self.flat.get(c).copied().unwrap_or(false)
    }
}

/// The truth row of board row `b`, from a truth held in memory.
pub fn truth_row(truth: &CameraTruth, b: i64) -> Option<CameraTruthRow<'_>> {
    let ti = truth_row_index(truth, b)?;
    let w = truth.width;
    fn line(v: &[f32], r: usize, w: usize) -> Option<&[f32]> {
        v.get(r * w..(r + 1) * w)
    }
    let (h, bg, ct) = (
        line(&truth.height_um, ti, w)?,
        line(&truth.background, ti, w)?,
        line(&truth.contrast, ti, w)?,
    );
    let flat = match (
        ti.checked_sub(1).and_then(|p| line(&truth.height_um, p, w)),
        line(&truth.height_um, ti + 1, w).filter(|_| ti + 1 < truth.rows),
    ) {
        (Some(prev), Some(next)) => flat_row(prev, h, next),
        _ => vec![false; w],
    };
    Some(CameraTruthRow {
        height_um: h,
        background: bg,
        contrast: ct,
        flat,
    })
}

/// The ground truth of a recording read forward, row by row: at most three rows of each file
/// are held, so a comparison of any board length stays within a constant memory. The files
/// are checked for their exact size (`rows x width x 4` bytes) when opened.
pub struct CameraTruthReader {
    first_row: i64,
    rows: usize,
    width: usize,
    files: [std::io::BufReader<std::fs::File>; 3],
    /// Consecutive truth rows `(index, [height, background, contrast])`, oldest first.
    lines: std::collections::VecDeque<(usize, [Vec<f32>; 3])>,
    /// Rows read so far.
    read: usize,
    /// Flat pixels of the rows whose neighbours have been read.
    flat_pixels: u64,
}

impl CameraTruthReader {
    /// Opens the truth of `rec`; `Ok(None)` when the manifest has no truth block.
    pub fn open(rec: &Recording) -> Result<Option<CameraTruthReader>, RecordingError> {
        let Some(info) = &rec.manifest.truth else {
            return Ok(None);
        };
        let (rows, width) = (info.rows as usize, rec.width());
        let expected = rows as u64 * width as u64 * 4;
        let open = |name: &str| -> Result<_, RecordingError> {
            let path = rec.dir.join(name);
            let io = |cause| RecordingError::Io {
                path: path.clone(),
                cause,
            };
            let meta = crate::files::check_regular(&path).map_err(io)?;
            if meta.len() != expected {
                return Err(RecordingError::TruthLength {
                    path: path.clone(),
                    expected,
                    actual: meta.len(),
                });
            }
            let f = std::fs::File::open(&path).map_err(io)?;
            Ok(std::io::BufReader::with_capacity(1 << 16, f))
        };
        Ok(Some(CameraTruthReader {
            first_row: info.first_row,
            rows,
            width,
            files: [
                open(TRUTH_HEIGHT_FILE)?,
                open(TRUTH_BACKGROUND_FILE)?,
                open(TRUTH_CONTRAST_FILE)?,
            ],
            lines: std::collections::VecDeque::new(),
            read: 0,
            flat_pixels: 0,
        }))
    }

    fn read_line(&mut self) -> std::io::Result<[Vec<f32>; 3]> {
        let mut bytes = vec![0u8; self.width * 4];
        let mut out: [Vec<f32>; 3] = Default::default();
        for (f, o) in self.files.iter_mut().zip(out.iter_mut()) {
            std::io::Read::read_exact(f, &mut bytes)?;
            *o = bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
        }
        Ok(out)
    }

    /// Reads rows until row `upto` (inclusive, clamped to the last) is held, counting the
    /// flat pixels of every row whose both neighbours have arrived; keeps `keep_from..`.
    fn advance(&mut self, upto: usize, keep_from: usize) -> std::io::Result<()> {
        let upto = upto.min(self.rows.saturating_sub(1));
        while self.read <= upto && self.read < self.rows {
            let line = self.read_line()?;
            self.lines.push_back((self.read, line));
            self.read += 1;
            let n = self.lines.len();
            if n >= 3 {
                let (p, c, x) = (
                    &self.lines[n - 3].1,
                    &self.lines[n - 2].1,
                    &self.lines[n - 1].1,
                );
                let flat = flat_row(&p[0], &c[0], &x[0]);
                self.flat_pixels += flat.iter().filter(|&&f| f).count() as u64;
            }
            while self.lines.len() > 3 {
                self.lines.pop_front();
            }
        }
        while self.lines.len() > 1 && self.lines.front().is_some_and(|(i, _)| *i < keep_from) {
            self.lines.pop_front();
        }
        Ok(())
    }

    /// The truth row of board row `b`. Board rows must be asked in nondecreasing order; a row
    /// before one already passed, or outside the truth, gives `None`.
    pub fn row(&mut self, b: i64) -> std::io::Result<Option<CameraTruthRow<'_>>> {
        let Some(ti) = b
            .checked_sub(self.first_row)
            .filter(|&i| i >= 0 && (i as u64) < self.rows as u64)
            .map(|i| i as usize)
        else {
            return Ok(None);
        };
        self.advance(ti + 1, ti.saturating_sub(1))?;
        let find = |i: usize| self.lines.iter().find(|(j, _)| *j == i).map(|(_, l)| l);
        let Some(cur) = find(ti) else {
            return Ok(None);
        };
        let flat = match (ti.checked_sub(1).and_then(find), find(ti + 1)) {
            (Some(p), Some(x)) => flat_row(&p[0], &cur[0], &x[0]),
            _ => vec![false; self.width],
        };
        Ok(Some(CameraTruthRow {
            height_um: &cur[0],
            background: &cur[1],
            contrast: &cur[2],
            flat,
        }))
    }

    /// Reads the rest of the truth and returns its flat-pixel count (the whole truth's, as
    /// [`flat_mask`] counts it).
    pub fn finish(mut self) -> std::io::Result<u64> {
        let last = self.rows.saturating_sub(1);
        self.advance(last, last)?;
        Ok(self.flat_pixels)
    }
}
