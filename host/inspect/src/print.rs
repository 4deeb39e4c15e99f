//! The print's placement on one board: where the stencil put the paste against the openings,
//! from every pad's offset.
//!
//! A stencil misaligned on the board shifts, turns and (when stencil and board differ in
//! scale, or the stencil stretches) scales the whole deposit pattern. With `q` a pad's
//! position from the pattern's centre (design frame, mm) and `d` its deposit's offset from its
//! opening (um, design axes, as the inspection measures it), the print is
//!
//! ```text
//! d_x = t_x - theta q_y + s q_x
//! d_y = t_y + theta q_x + s q_y
//! ```
//!
//! with `t` the translation at the centre (um), `theta` the rotation (mrad: 1 mrad over 1 mm is
//! 1 um) and `s` the stretch (per mille: 1 per mille over 1 mm is 1 um). Deposits that are no
//! measure of the print (a bridge pulls the centroid between two pads, a missing deposit has
//! none) are outliers: the fit is Tukey's biweight M-estimate (c = 4.685, 95 % efficient at the
//! normal) by iteratively reweighted least squares from the median translation, its scale
//! 1.4826 times the median absolute residual. Its standard uncertainty is the M-estimator's
//! sandwich covariance `s^2 (A'WA)^-1 (A'W^2A) (A'WA)^-1`, checked against the spread of fits
//! over repeated noisy boards in the tests.
//!
//! The offsets are against the board's registration: by fiducials (copper) they measure the
//! print; registered by the paste pattern itself (a program without fiducials) the pattern's
//! own shift and turn are taken out before the offsets are measured, and the print offset
//! reads near zero whatever the printer did.

use crate::measure::PadMeasurement;
use dpsa_gerber::pads::Pad;
use nalgebra::{Matrix4, Vector4};

/// The print of an inspected board: every pad's opening (its outline's centroid, design mm)
/// with the offset its deposit was measured at (pads without one, not measurable, left out).
pub fn of_board(pads: &[Pad], measurements: &[PadMeasurement]) -> Option<PrintOffset> {
    let offsets: Vec<PadOffset> = pads
        .iter()
        .zip(measurements)
        .map(|(p, m)| PadOffset {
            at_mm: p.outline.centroid(),
            offset_um: m.offset_um,
        })
        .collect();
    fit(&offsets)
}

/// One pad as the fit takes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PadOffset {
    /// The opening's centre, design frame, mm.
    pub at_mm: [f64; 2],
    /// The deposit's offset from it, design axes, um.
    pub offset_um: [f64; 2],
}

/// The print on one board.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct PrintOffset {
    /// Translation along x at the pattern's centre, um.
    pub x_um: f64,
    /// Along y, um.
    pub y_um: f64,
    /// Rotation, counter-clockwise, millidegrees.
    pub rotation_mdeg: f64,
    /// Stretch of the pattern against the openings' (stencil against board scale), ppm.
    pub stretch_ppm: f64,
    /// Standard uncertainties of the four, same units and order.
    pub uncertainty: [f64; 4],
    /// The pattern's centre the translation is given at, design mm.
    pub centre_mm: [f64; 2],
    /// Pads the fit used (weight above 0).
    pub pads: usize,
    /// Pads it set aside as outliers (weight 0).
    pub outliers: usize,
    /// The robust scale of the residuals, um.
    pub scale_um: f64,
}

/// Tukey's biweight constant (95 % efficiency at the normal).
const TUKEY_C: f64 = 4.685;

/// Most reweighting rounds.
const ROUNDS: usize = 100;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// The two rows of a pad (`q` from the centre, mm) in the unknowns `[t_x, t_y, theta, s]`.
fn rows(q: [f64; 2]) -> [[f64; 4]; 2] {
    [[1.0, 0.0, -q[1], q[0]], [0.0, 1.0, q[0], q[1]]]
}

/// The print of `pads` (non-finite entries ignored); `None` with fewer than 3 usable pads or a
/// pattern that cannot show a turn or a stretch (all pads at one place).
pub fn fit(pads: &[PadOffset]) -> Option<PrintOffset> {
    let pads: Vec<&PadOffset> = pads
        .iter()
        .filter(|p| p.at_mm.iter().chain(&p.offset_um).all(|v| v.is_finite()))
        .collect();
    if pads.len() < 3 {
        return None;
    }
    let n = pads.len() as f64;
    let centre = [
        pads.iter().map(|p| p.at_mm[0]).sum::<f64>() / n,
        pads.iter().map(|p| p.at_mm[1]).sum::<f64>() / n,
    ];
    let q: Vec<[f64; 2]> = pads
        .iter()
        .map(|p| [p.at_mm[0] - centre[0], p.at_mm[1] - centre[1]])
        .collect();
    let mut v = Vector4::new(
        median(&mut pads.iter().map(|p| p.offset_um[0]).collect::<Vec<_>>()),
        median(&mut pads.iter().map(|p| p.offset_um[1]).collect::<Vec<_>>()),
        0.0,
        0.0,
    );
    let residuals = |v: &Vector4<f64>| -> Vec<[f64; 2]> {
        pads.iter()
            .zip(&q)
            .map(|(p, &qi)| {
                let r = rows(qi);
                [0, 1].map(|k| p.offset_um[k] - (0..4).map(|j| r[k][j] * v[j]).sum::<f64>())
            })
            .collect()
    };
    let scale_of = |res: &[[f64; 2]]| {
        let mut a: Vec<f64> = res.iter().flat_map(|r| [r[0].abs(), r[1].abs()]).collect();
        1.4826 * median(&mut a)
    };
    let weight = |r: f64, scale: f64| {
        let u = r / (TUKEY_C * scale);
        if u.abs() < 1.0 {
            (1.0 - u * u).powi(2)
        } else {
            0.0
        }
    };
    // The normal matrices for weights `w` (per residual) and their squares.
    let normal = |w: &[[f64; 2]], power: i32| {
        let mut m = Matrix4::<f64>::zeros();
        for (qi, wi) in q.iter().zip(w) {
            let r = rows(*qi);
            for k in 0..2 {
                let wk = wi[k].powi(power);
                for a in 0..4 {
                    for b in 0..4 {
                        m[(a, b)] += wk * r[k][a] * r[k][b];
                    }
                }
            }
        }
        m
    };
    let mut scale = scale_of(&residuals(&v));
    let mut w: Vec<[f64; 2]> = vec![[1.0, 1.0]; pads.len()];
    for _ in 0..ROUNDS {
        let res = residuals(&v);
        scale = scale_of(&res);
        if !(scale > 0.0 && scale.is_finite()) {
            // Every residual zero (a perfect fit): nothing more to weigh.
            break;
        }
        w = res
            .iter()
            .map(|r| [weight(r[0], scale), weight(r[1], scale)])
            .collect();
        let mut rhs = Vector4::<f64>::zeros();
        for ((p, qi), wi) in pads.iter().zip(&q).zip(&w) {
            let r = rows(*qi);
            for k in 0..2 {
                for a in 0..4 {
                    rhs[a] += wi[k] * r[k][a] * p.offset_um[k];
                }
            }
        }
        let next = normal(&w, 1).try_inverse()? * rhs;
        let done = (next - v).abs().max() < 1e-10 * (1.0 + v.abs().max());
        v = next;
        if done {
            break;
        }
    }
    let used = w.iter().filter(|wi| wi[0] > 0.0 && wi[1] > 0.0).count();
    if used < 3 {
        return None;
    }
    // The pattern must span a turn and a stretch: the normal matrix well conditioned.
    let m1 = normal(&w, 1);
    let inv = m1.try_inverse()?;
    let cov = inv * normal(&w, 2) * inv * (scale * scale);
    let sd: [f64; 4] = [0, 1, 2, 3].map(|k| cov[(k, k)].max(0.0).sqrt());
    let (deg, ppm) = (180.0 / std::f64::consts::PI, 1000.0);
    Some(PrintOffset {
        x_um: v[0],
        y_um: v[1],
        rotation_mdeg: v[2] * deg,
        stretch_ppm: v[3] * ppm,
        uncertainty: [sd[0], sd[1], sd[2] * deg, sd[3] * ppm],
        centre_mm: centre,
        pads: used,
        outliers: pads.len() - used,
        scale_um: scale,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// A board of `n x n` pads over 200 x 150 mm printed with translation `t` (um), rotation
    /// `rot` (mrad) and stretch `s` (per mille), with noise `sd` (um) and the `bad` first pads
    /// thrown off by 300 um (bridges, missing deposits).
    fn board(
        t: [f64; 2],
        rot: f64,
        s: f64,
        sd: f64,
        bad: usize,
        rng: &mut rand_chacha::ChaCha8Rng,
    ) -> Vec<PadOffset> {
        let noise = Normal::new(0.0, sd.max(1e-300)).unwrap();
        let mut v = Vec::new();
        for i in 0..20 {
            for j in 0..15 {
                let at = [10.0 + 10.0 * i as f64, 5.0 + 10.0 * j as f64];
                let q = [at[0] - 105.0, at[1] - 75.0];
                let mut d = [t[0] - rot * q[1] + s * q[0], t[1] + rot * q[0] + s * q[1]];
                if sd > 0.0 {
                    d[0] += noise.sample(rng);
                    d[1] += noise.sample(rng);
                }
                if v.len() < bad {
                    d[0] += 300.0;
                    d[1] -= 200.0;
                }
                v.push(PadOffset {
                    at_mm: at,
                    offset_um: d,
                });
            }
        }
        v
    }

    #[test]
    fn an_exact_print_is_recovered_exactly() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let p = fit(&board([30.0, -12.0], 0.2, 0.05, 0.0, 0, &mut rng)).unwrap();
        assert!(
            (p.x_um - 30.0).abs() < 1e-9 && (p.y_um + 12.0).abs() < 1e-9,
            "{p:?}"
        );
        assert!((p.rotation_mdeg - 0.2 * 180.0 / std::f64::consts::PI).abs() < 1e-9);
        assert!((p.stretch_ppm - 50.0).abs() < 1e-9);
        assert_eq!((p.pads, p.outliers), (300, 0));
        assert_eq!(p.centre_mm, [105.0, 75.0]);
    }

    /// A tenth of the pads thrown far off (bridges, missing deposits) moves the fit by less
    /// than its own uncertainty; least squares would follow them by tens of um.
    #[test]
    fn outliers_are_set_aside() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let pads = board([60.0, 0.0], -0.1, 0.0, 5.0, 30, &mut rng);
        let p = fit(&pads).unwrap();
        assert!(p.outliers >= 30, "{p:?}");
        assert!((p.x_um - 60.0).abs() < 3.0 * p.uncertainty[0], "{p:?}");
        assert!(p.y_um.abs() < 3.0 * p.uncertainty[1], "{p:?}");
        let rot = -0.1 * 180.0 / std::f64::consts::PI;
        assert!(
            (p.rotation_mdeg - rot).abs() < 3.0 * p.uncertainty[2],
            "{p:?}"
        );
        let mean_x = pads.iter().map(|p| p.offset_um[0]).sum::<f64>() / pads.len() as f64;
        assert!((mean_x - 60.0).abs() > 25.0);
    }

    /// The stated uncertainty is the spread of the fit over 400 boards printed alike with
    /// fresh noise (and outliers): each within 20 % of the observed standard deviation.
    #[test]
    fn the_uncertainty_is_the_spread_over_repeated_boards() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let fits: Vec<PrintOffset> = (0..400)
            .map(|_| fit(&board([10.0, 5.0], 0.05, -0.02, 8.0, 15, &mut rng)).unwrap())
            .collect();
        let vals = |f: &PrintOffset| [f.x_um, f.y_um, f.rotation_mdeg, f.stretch_ppm];
        for k in 0..4 {
            let v: Vec<f64> = fits.iter().map(|f| vals(f)[k]).collect();
            let m = v.iter().sum::<f64>() / v.len() as f64;
            let sd = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt();
            let said = fits.iter().map(|f| f.uncertainty[k]).sum::<f64>() / fits.len() as f64;
            eprintln!("parameter {k}: stated {said:.5}, observed {sd:.5}");
            assert!(
                (said / sd - 1.0).abs() < 0.2,
                "parameter {k}: stated {said}, observed {sd}"
            );
        }
    }

    #[test]
    fn too_few_or_degenerate_pads_give_none() {
        let p = |x: f64, y: f64| PadOffset {
            at_mm: [x, y],
            offset_um: [1.0, 2.0],
        };
        assert_eq!(fit(&[p(0.0, 0.0), p(1.0, 0.0)]), None);
        assert_eq!(
            fit(&[p(5.0, 5.0), p(5.0, 5.0), p(5.0, 5.0), p(5.0, 5.0)]),
            None
        );
        let nan = PadOffset {
            at_mm: [f64::NAN, 0.0],
            offset_um: [0.0; 2],
        };
        assert_eq!(fit(&[nan, p(0.0, 0.0), p(1.0, 0.0)]), None);
        // Three pads not in a line: a fit.
        assert!(fit(&[p(0.0, 0.0), p(10.0, 0.0), p(0.0, 10.0)]).is_some());
    }
}
