//! Labels beside marks in a picture, none over another: the overview image of `dpsa inspect`
//! and the board drawing of the operator's pages name every call this way.

/// Where labels may go, px: `[left, top, right, bottom]`.
pub type Bounds = [f64; 4];

/// Labels already placed: their boxes, `[left, top, right, bottom]` px.
#[derive(Clone, Debug, Default)]
pub struct Placed(pub Vec<[f64; 4]>);

impl Placed {
    /// Where a label `w x h` px for the mark at `(x, y)` goes: the first of eight places
    /// around the mark, then three rings further out, whose box overlaps no label placed
    /// and stays inside `bounds`; crowded past all of them, the first place moved inside
    /// `bounds`. Returns the text's baseline start (the box's left and its bottom less a
    /// fifth of `h`) and keeps the box.
    pub fn place(&mut self, x: f64, y: f64, w: f64, h: f64, bounds: Bounds) -> (f64, f64) {
        let descent = h / 5.0;
        let boxed = |tx: f64, ty: f64| [tx, ty - h + descent, tx + w, ty + descent];
        let fits = |b: &[f64; 4]| {
            b[0] >= bounds[0]
                && b[2] <= bounds[2]
                && b[1] >= bounds[1]
                && b[3] <= bounds[3]
                && self
                    .0
                    .iter()
                    .all(|p| b[2] <= p[0] || b[0] >= p[2] || b[3] <= p[1] || b[1] >= p[3])
        };
        let mut first = None;
        for ring in 0..4 {
            let d = 0.8 * h + 1.15 * h * ring as f64;
            for (dx, dy) in [
                (d, -d + 0.3 * h),
                (d, d + 0.6 * h),
                (-d - w, -d + 0.3 * h),
                (-d - w, d + 0.6 * h),
                (-w / 2.0, -d - 0.15 * h),
                (-w / 2.0, d + h),
                (d + 2.0, 0.3 * h),
                (-d - w - 2.0, 0.3 * h),
            ] {
                let b = boxed(x + dx, y + dy);
                first.get_or_insert((x + dx, y + dy));
                if fits(&b) {
                    self.0.push(b);
                    return (x + dx, y + dy);
                }
            }
        }
        let (tx, ty) = first.unwrap_or((x, y));
        let tx = tx.clamp(bounds[0], (bounds[2] - w).max(bounds[0]));
        let ty = ty.clamp(
            bounds[1] + h - descent,
            (bounds[3] - descent).max(bounds[1] + h - descent),
        );
        self.0.push(boxed(tx, ty));
        (tx, ty)
    }
}

/// A scale bar's length: the largest 1, 2 or 5 x 10^k not above `max` (1 for no length).
pub fn scale_bar_mm(max: f64) -> f64 {
    if !(max.is_finite() && max > 0.0) {
        return 1.0;
    }
    let mag = 10f64.powf(max.log10().floor());
    [5.0, 2.0, 1.0]
        .into_iter()
        .map(|m| m * mag)
        .find(|&s| s <= max)
        .unwrap_or(mag)
}

/// Round steps between `lo` and `hi`: multiples of 1, 2 or 5 x 10^k, about `n` of them.
pub fn ticks(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    if !(lo.is_finite() && hi.is_finite()) || hi <= lo || n == 0 {
        return Vec::new();
    }
    let raw = (hi - lo) / n as f64;
    let e = raw.log10().floor() as i32;
    // A tick is k m 10^e, computed as (k m) / 10^-e below 1 so that 1.2 is 1.2.
    let at = |k: i64, m: f64| {
        if e >= 0 {
            k as f64 * m * 10f64.powi(e)
        } else {
            k as f64 * m / 10f64.powi(-e)
        }
    };
    let m = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .find(|&m| at(1, m) >= raw)
        .unwrap_or(10.0);
    let step = at(1, m);
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    (first..=last).map(|k| at(k, m)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const B: Bounds = [2.0, 2.0, 998.0, 676.0];

    #[test]
    fn ticks_are_round_and_inside() {
        assert_eq!(ticks(0.0, 192.0, 4), [0.0, 50.0, 100.0, 150.0]);
        assert_eq!(ticks(0.98, 2.03, 4), [1.0, 1.5, 2.0]);
        assert_eq!(ticks(0.98, 2.03, 8), [1.0, 1.2, 1.4, 1.6, 1.8, 2.0]);
        assert!(ticks(1.0, 1.0, 4).is_empty());
        assert!(ticks(f64::NAN, 1.0, 4).is_empty());
    }

    #[test]
    fn scale_bars_are_round_and_not_longer() {
        assert_eq!(scale_bar_mm(4.6), 2.0);
        assert_eq!(scale_bar_mm(5.0), 5.0);
        assert_eq!(scale_bar_mm(47.0), 20.0);
        assert_eq!(scale_bar_mm(0.9), 0.5);
        assert_eq!(scale_bar_mm(f64::NAN), 1.0);
    }

    /// Nine marks close together, one at the edge: no two labels overlap and all stay inside.
    #[test]
    fn labels_do_not_overlap_and_stay_inside() {
        let mut p = Placed::default();
        for k in 0..8 {
            p.place(500.0 + 4.0 * k as f64, 300.0, 98.0, 14.0, B);
        }
        p.place(997.0, 300.0, 140.0, 14.0, B);
        for (i, a) in p.0.iter().enumerate() {
            assert!(
                a[0] >= B[0] && a[2] <= B[2] && a[1] >= B[1] && a[3] <= B[3],
                "{a:?}"
            );
            for b in &p.0[i + 1..] {
                let apart = a[2] <= b[0] || a[0] >= b[2] || a[3] <= b[1] || a[1] >= b[3];
                assert!(apart, "{a:?} {b:?}");
            }
        }
    }

    /// Crowded past every place: the label still stays inside.
    #[test]
    fn a_crowded_label_stays_inside() {
        let mut p = Placed(vec![[0.0, 0.0, 1000.0, 700.0]]);
        p.place(995.0, 690.0, 140.0, 14.0, B);
        let b = p.0[1];
        assert!(
            b[0] >= B[0] && b[2] <= B[2] && b[1] >= B[1] && b[3] <= B[3],
            "{b:?}"
        );
    }
}
