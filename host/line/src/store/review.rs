//! What the operator's pages need beyond the measurements (schema version 4): a pad's heights
//! around a call ([`PadImage`], table `pad_images`) and the operator's decision on the call
//! ([`Review`], table `reviews`).

use dpsa_inspect::crop::PadCrop;

/// The height step of `pad_images.heights`, um: each sample is a little-endian `i16` of this
/// many um (+-3.2 mm, far beyond any paste), [`INVALID_SAMPLE`] where the map had no height.
pub const IMAGE_LSB_UM: f64 = 0.1;

/// The `i16` of a sample with no height (NaN), and of one beyond the range.
pub const INVALID_SAMPLE: i16 = i16::MIN;

/// A pad's heights above its local surface as the line keeps them for a pad that warned or
/// failed (table `pad_images`): what an operator looks at to review the call.
#[derive(Debug, Clone, PartialEq)]
pub struct PadImage {
    /// Index of the pad in the paste layer.
    pub pad: u32,
    /// Its package family (the program's), if known.
    pub family: Option<String>,
    /// The heights (read back, quantised to [`IMAGE_LSB_UM`]) and the opening.
    pub crop: PadCrop,
}

/// The columns of a `pad_images` row, encoded.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ImageValues {
    pub(crate) pad: u32,
    pub(crate) family: Option<String>,
    pub(crate) x0_mm: f64,
    pub(crate) y0_mm: f64,
    pub(crate) pitch_mm: f64,
    pub(crate) nx: u32,
    pub(crate) ny: u32,
    pub(crate) lsb_um: f64,
    pub(crate) heights: Vec<u8>,
    pub(crate) outline: String,
}

/// The samples as stored: [`IMAGE_LSB_UM`] steps, little-endian `i16`.
pub(crate) fn encode(heights_um: &[f32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(2 * heights_um.len());
    for &h in heights_um {
        let q = f64::from(h) / IMAGE_LSB_UM;
        let v = if q.is_finite() && q.abs() <= f64::from(i16::MAX) {
            q.round() as i16
        } else {
            INVALID_SAMPLE
        };
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// The samples of `bytes` (whole `i16`s: the caller checked the length) in um, NaN for
/// [`INVALID_SAMPLE`].
pub(crate) fn decode(bytes: &[u8], lsb_um: f64) -> Vec<f32> {
    bytes
        .chunks_exact(2)
        .map(|b| match i16::from_le_bytes([b[0], b[1]]) {
            INVALID_SAMPLE => f32::NAN,
            v => (f64::from(v) * lsb_um) as f32,
        })
        .collect()
}

impl ImageValues {
    /// The row of `image`, or why it cannot be stored.
    pub(crate) fn of(image: &PadImage) -> Result<ImageValues, String> {
        let c = &image.crop;
        let side = 1..=dpsa_inspect::crop::MAX_SIDE;
        if !side.contains(&c.nx) || !side.contains(&c.ny) || c.heights_um.len() != c.nx * c.ny {
            return Err(format!(
                "pad {}: an image of {} x {} samples with {} heights",
                image.pad,
                c.nx,
                c.ny,
                c.heights_um.len()
            ));
        }
        if ![c.x0_mm, c.y0_mm, c.pitch_mm].iter().all(|v| v.is_finite()) || c.pitch_mm <= 0.0 {
            return Err(format!(
                "pad {}: an image at ({}, {}) mm of pitch {} mm",
                image.pad, c.x0_mm, c.y0_mm, c.pitch_mm
            ));
        }
        let outline = serde_json::to_string(&c.outline).map_err(|e| e.to_string())?;
        Ok(ImageValues {
            pad: image.pad,
            family: image.family.clone(),
            x0_mm: c.x0_mm,
            y0_mm: c.y0_mm,
            pitch_mm: c.pitch_mm,
            nx: c.nx as u32,
            ny: c.ny as u32,
            lsb_um: IMAGE_LSB_UM,
            heights: encode(&c.heights_um),
            outline,
        })
    }

    /// The image of a stored row, or why the row is damaged.
    pub(crate) fn image(self) -> Result<PadImage, String> {
        let (nx, ny) = (self.nx as usize, self.ny as usize);
        if self.heights.len() != 2 * nx * ny || self.lsb_um.is_nan() || self.lsb_um <= 0.0 {
            return Err(format!(
                "pad {}'s image: {} bytes for {nx} x {ny} samples of {} um",
                self.pad,
                self.heights.len(),
                self.lsb_um
            ));
        }
        let outline = serde_json::from_str(&self.outline)
            .map_err(|e| format!("pad {}'s image: its outline: {e}", self.pad))?;
        Ok(PadImage {
            pad: self.pad,
            family: self.family,
            crop: PadCrop {
                x0_mm: self.x0_mm,
                y0_mm: self.y0_mm,
                pitch_mm: self.pitch_mm,
                nx,
                ny,
                heights_um: decode(&self.heights, self.lsb_um),
                outline,
            },
        })
    }
}

/// An operator's decision on a pad's call.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Decision {
    /// The defect is real.
    Confirmed,
    /// The machine called a good deposit bad.
    FalseCall,
}

impl Decision {
    /// As stored: `confirmed` or `false_call`.
    pub fn name(self) -> &'static str {
        match self {
            Decision::Confirmed => "confirmed",
            Decision::FalseCall => "false_call",
        }
    }

    /// From its stored name.
    pub fn from_name(s: &str) -> Option<Decision> {
        match s {
            "confirmed" => Some(Decision::Confirmed),
            "false_call" => Some(Decision::FalseCall),
            _ => None,
        }
    }
}

/// One review of a pad's call (table `reviews`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Review {
    /// The review's id (grows with every review).
    pub id: i64,
    /// The board.
    pub board_id: i64,
    /// The pad's index in the paste layer.
    pub pad: u32,
    /// The pad's package family when it was reviewed, if known.
    pub family: Option<String>,
    /// What the operator decided.
    pub decision: Decision,
    /// Who.
    pub reviewer: String,
    /// When, Unix s.
    pub reviewed_unix_s: f64,
    /// What the operator wrote, if anything.
    pub note: Option<String>,
}

/// The reviewed calls of a package family on a line: each pad's newest decision counted once.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FamilyReviews {
    /// The family (`None`: pads of no known family).
    pub family: Option<String>,
    /// Calls confirmed.
    pub confirmed: u64,
    /// False calls.
    pub false_calls: u64,
}

impl FamilyReviews {
    /// False calls over the reviewed calls, 0..=1 (`None` before any review).
    pub fn false_call_rate(&self) -> Option<f64> {
        let n = self.confirmed + self.false_calls;
        (n > 0).then(|| self.false_calls as f64 / n as f64)
    }
}

/// The per-family counts from `(family, decision, count)` rows.
pub(crate) fn family_reviews(rows: Vec<(Option<String>, String, i64)>) -> Vec<FamilyReviews> {
    let mut out: Vec<FamilyReviews> = Vec::new();
    for (family, decision, n) in rows {
        let k = match out.iter().position(|f| f.family == family) {
            Some(k) => k,
            None => {
                out.push(FamilyReviews {
                    family,
                    confirmed: 0,
                    false_calls: 0,
                });
                out.len() - 1
            }
        };
        let n = u64::try_from(n).unwrap_or(0);
        match Decision::from_name(&decision) {
            Some(Decision::Confirmed) => out[k].confirmed += n,
            Some(Decision::FalseCall) => out[k].false_calls += n,
            None => {}
        }
    }
    out.sort_by(|a, b| a.family.cmp(&b.family));
    out
}

/// The newest decision on each pad of this line's boards, counted per family and decision
/// (`?1` the line; PostgreSQL's spelling takes `$1`).
pub(crate) const FAMILY_REVIEWS_SQL: &str =
    "SELECT r.family, r.decision, count(*) FROM reviews AS r JOIN boards AS b ON b.id = r.board_id
     WHERE b.line = ?1 AND r.id = (SELECT max(q.id) FROM reviews AS q
         WHERE q.board_id = r.board_id AND q.pad = r.pad)
     GROUP BY r.family, r.decision";

/// A review of a pad that warned or failed on one of this line's inspected boards, with the
/// family from the pad's image (`?1` board, `?2` pad, `?3` decision, `?4` reviewer, `?5`
/// time, `?6` note, `?7` line): inserts nothing when there is no such call.
pub(crate) const INSERT_REVIEW_SQL: &str =
    "INSERT INTO reviews (board_id, pad, family, decision, reviewer, reviewed_unix_s, note)
     SELECT d.board_id, d.pad, i.family, ?3, ?4, ?5, ?6
     FROM defects AS d JOIN boards AS b ON b.id = d.board_id
     LEFT JOIN pad_images AS i ON i.board_id = d.board_id AND i.pad = d.pad
     WHERE d.board_id = ?1 AND d.pad = ?2 AND b.line = ?7 AND b.state = 'inspected'";

/// The columns of [`Review`] in order, for a `SELECT`.
pub(crate) const REVIEW_COLUMNS: &str =
    "id, board_id, pad, family, decision, reviewer, reviewed_unix_s, note";

/// The columns of [`ImageValues`] after `pad`, in order, for a `SELECT` or an `INSERT`.
pub(crate) const IMAGE_COLUMNS: &str =
    "family, x0_mm, y0_mm, pitch_mm, nx, ny, lsb_um, heights, outline";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_round_trip_within_half_a_step_and_invalid_stays_invalid() {
        let h = [
            0.0,
            0.04,
            0.06,
            -12.34,
            250.0,
            f32::NAN,
            4000.0,
            -4000.0,
            f32::INFINITY,
        ];
        let back = decode(&encode(&h), IMAGE_LSB_UM);
        assert_eq!(back.len(), h.len());
        for (a, b) in h.iter().zip(&back).take(5) {
            assert!((a - b).abs() <= 0.05 + 1e-6, "{a} {b}");
        }
        assert!(back[5..].iter().all(|v| v.is_nan()), "{back:?}");
        assert_eq!(back[2], 0.1);
    }

    #[test]
    fn families_count_each_decision() {
        let f = family_reviews(vec![
            (Some("bga".into()), "false_call".into(), 3),
            (None, "confirmed".into(), 1),
            (Some("bga".into()), "confirmed".into(), 1),
        ]);
        assert_eq!(f.len(), 2);
        assert_eq!(f[0].family, None);
        assert_eq!((f[1].confirmed, f[1].false_calls), (1, 3));
        assert_eq!(f[1].false_call_rate(), Some(0.75));
        assert_eq!(f[0].false_call_rate(), Some(0.0));
    }
}
