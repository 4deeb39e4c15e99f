//! Rendering one camera's frames of a surface carried by the conveyor.
//!
//! Pixel `(r, c)` of a frame taken at conveyor travel `s` sees board point
//! [`CameraModel::board_point`]; its phase is `2 pi f_x(c) r + phi_0(c) + 2 pi h / T_z(c)` and
//! its intensity `ill(c) * a (B + C M cos(phase))` with reflectance `a`. Pixels integrate over
//! their area and a Gaussian blur of `blur_px`: where the surface is smooth (planes, bare
//! warped board) this is exact in closed form for the locally linear phase, `M = sinc(g_r/2)
//! sinc(g_c/2) exp(-sigma^2 |g|^2 / 2)` with the phase gradient `g` (rad/px); pixels near a
//! deposit are averaged over a 3 x 3 grid of sub-pixels (each with its own sub-box sinc and
//! the blur), so steep walls lose modulation and paste/board edges mix as in a real image.
//! Printed target marks are Gaussian reflectance dips, blurred and pixel-integrated in
//! closed form (variances add). Dead pixels see nothing. Noise as in the single-camera
//! simulator (`simulation::simulate`).

use crate::array::print::{paste_height, Deposit, DepositIndex, Material};
use crate::array::scene::{ArrayScene, CalibrationPlan, CameraModel};
use crate::inspection::pads::Outline;
use crate::simulation::simulate::{noisy, rng};
use rand::RngExt;
use std::f64::consts::TAU;

/// A random-box deposit of the scenes without a paste layer, in board millimetres: a rounded
/// box, recorded as such in the array truth. It is printed as a [`Deposit`]
/// ([`MmDeposit::to_deposit`]).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MmDeposit {
    /// Centre along the motion, mm.
    pub x_mm: f64,
    /// Centre across the board, mm.
    pub y_mm: f64,
    /// Footprint along the motion, mm.
    pub length_mm: f64,
    /// Footprint across, mm.
    pub width_mm: f64,
    /// Height above the (warped) board, um.
    pub height_um: f64,
}

impl MmDeposit {
    /// The general deposit of this box: a rounded rectangle with corner radius `corner` and a
    /// wall of `edge` mm (the same heights, bit for bit, as the box always had).
    pub fn to_deposit(&self, corner: f64, edge: f64) -> Deposit {
        Deposit {
            outline: Outline::RoundRect {
                centre: [self.x_mm, self.y_mm],
                size: [self.length_mm, self.width_mm],
                radius: corner,
                rotation_deg: 0.0,
            },
            height_um: self.height_um,
            edge_mm: edge,
            bumps: Vec::new(),
            material: Material::Paste,
            pad: None,
        }
    }

    /// Height at board point `(x, y)`, um.
    pub fn height(&self, x: f64, y: f64, corner: f64, edge: f64) -> f64 {
        self.to_deposit(corner, edge).height([x, y])
    }
}

/// Places `scene.deposits` deposits at random on the board, 4 px apart, 0.5 mm from the edges.
pub fn place_deposits(scene: &ArrayScene, seed: u64) -> Vec<MmDeposit> {
    let mut rng = rng(seed, 1);
    let mut out: Vec<MmDeposit> = Vec::new();
    if scene.deposit_sizes_mm.is_empty() {
        return out;
    }
    let gap = 4.0 * scene.pixel_mm;
    let [lo, hi] = scene.deposit_height_um;
    for _ in 0..scene.deposits {
        for _ in 0..100 {
            let [l, w] = scene.deposit_sizes_mm[rng.random_range(0..scene.deposit_sizes_mm.len())];
            let (ux, uy, uh): (f64, f64, f64) = (rng.random(), rng.random(), rng.random());
            let (x_lo, x_hi) = (0.5 + l / 2.0, scene.board_length_mm - 0.5 - l / 2.0);
            let (y_lo, y_hi) = (0.5 + w / 2.0, scene.board_width_mm - 0.5 - w / 2.0);
            if x_hi < x_lo || y_hi < y_lo {
                continue;
            }
            let d = MmDeposit {
                x_mm: x_lo + ux * (x_hi - x_lo),
                y_mm: y_lo + uy * (y_hi - y_lo),
                length_mm: l,
                width_mm: w,
                height_um: lo + uh * (hi - lo),
            };
            let clash = out.iter().any(|o| {
                (o.x_mm - d.x_mm).abs() < (o.length_mm + d.length_mm) / 2.0 + gap
                    && (o.y_mm - d.y_mm).abs() < (o.width_mm + d.width_mm) / 2.0 + gap
            });
            if !clash {
                out.push(d);
                break;
            }
        }
    }
    out
}

/// What the conveyor carries.
#[derive(Clone, Debug)]
pub enum Surface<'a> {
    /// The board: warp plus deposits (paste, copper), board frame.
    Board {
        /// Everything printed on the board, board frame, mm.
        deposits: &'a [Deposit],
    },
    /// A flat matte plane at a height, um.
    Plane {
        /// Height of the plane, um.
        height_um: f64,
    },
    /// The flat lateral target (height 0) with its printed mark grid.
    Target {
        /// The calibration plan: the grid's pitch and origin and the marks' size and depth.
        plan: &'a CalibrationPlan,
    },
}

impl Surface<'_> {
    /// True height at `(x, y)`, um (every deposit visited: the renderer and the truth raster
    /// use a [`DepositIndex`]).
    pub fn height(&self, scene: &ArrayScene, x: f64, y: f64) -> f64 {
        match self {
            Surface::Board { deposits } => {
                scene.warp(x, y) + deposits.iter().map(|d| d.height([x, y])).sum::<f64>()
            }
            Surface::Plane { height_um } => *height_um,
            Surface::Target { .. } => 0.0,
        }
    }
}

/// Per column of `model`'s camera: the fringe's modulation factor of a pixel on a smooth
/// surface (pixel integration and blur), and the blur's part of it.
fn modulation(scene: &ArrayScene, model: &CameraModel) -> (Vec<f64>, Vec<f64>) {
    let w = model.width as usize;
    let sigma2 = scene.blur_px * scene.blur_px;
    let mut m0 = Vec::with_capacity(w);
    let mut m_blur = Vec::with_capacity(w);
    for c in 0..w {
        let g_r = TAU * model.fringe_frequency[c];
        let g_c = if w > 1 {
            let (a, b) = (c.saturating_sub(1), (c + 1).min(w - 1));
            (model.reference_phase_rad[b] - model.reference_phase_rad[a]) / (b - a) as f64
        } else {
            0.0
        };
        let blur = (-sigma2 * (g_r * g_r + g_c * g_c) / 2.0).exp();
        m_blur.push(blur);
        m0.push(sinc(g_r / 2.0) * sinc(g_c / 2.0) * blur);
    }
    (m0, m_blur)
}

/// The paste's background step over the board's fringe contrast as the cameras of `scene`
/// see them (`(B_paste - B_board) / (C_board M)`, `M` the mean modulation factor over every
/// camera's columns): what a program's `reflectance.background_step` says of this machine.
pub fn paste_background_step(scene: &ArrayScene) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for i in 0..scene.cameras.len() {
        let (m0, _) = modulation(scene, &scene.camera_model(i));
        sum += m0.iter().sum::<f64>();
        n += m0.len();
    }
    let m = sum / n.max(1) as f64;
    (scene.paste_background - scene.background) / (scene.contrast * m)
}

fn sinc(x: f64) -> f64 {
    if x.abs() < 1e-8 {
        1.0
    } else {
        x.sin() / x
    }
}

/// Renders frames of one camera.
pub struct CameraRenderer<'a> {
    /// The scene: board, reflectance, blur and noise settings.
    pub scene: &'a ArrayScene,
    /// The true model of the camera rendered.
    pub model: &'a CameraModel,
    /// What the conveyor carries past it.
    pub surface: Surface<'a>,
    /// Modulation factor of the smooth surface per column (area integration and blur).
    m0: Vec<f64>,
    /// Blur factor alone per column (the 3 x 3 sub-pixel path applies its own sub-box sinc).
    m_blur: Vec<f64>,
    dead: Vec<bool>,
    /// The board's deposits, binned.
    index: DepositIndex,
}

impl<'a> CameraRenderer<'a> {
    /// A renderer of `model`'s frames of `surface`: precomputes the per-column modulation
    /// factors and dead-pixel mask, and bins the board's deposits.
    pub fn new(scene: &'a ArrayScene, model: &'a CameraModel, surface: Surface<'a>) -> Self {
        let w = model.width as usize;
        let (m0, m_blur) = modulation(scene, model);
        let mut dead = vec![false; w * model.rows as usize];
        for &[r, c] in &model.dead_pixels {
            dead[r as usize * w + c as usize] = true;
        }
        let index = match &surface {
            Surface::Board { deposits } => DepositIndex::new(deposits),
            _ => DepositIndex::default(),
        };
        CameraRenderer {
            scene,
            model,
            surface,
            m0,
            m_blur,
            dead,
            index,
        }
    }

    /// Modulation factor of smooth surfaces in column `c` (truth contrast = `ill * C * M`).
    pub fn modulation_factor(&self, c: usize) -> f64 {
        self.m0[c]
    }

    /// Reflectance of the target at `(x, y)` (1 elsewhere), blurred and pixel-integrated.
    fn reflectance(&self, x: f64, y: f64) -> f64 {
        let Surface::Target { plan } = &self.surface else {
            return 1.0;
        };
        let p = plan.target_pitch_mm;
        let [x0, y0] = plan.target_origin_mm;
        let last_x = ((plan.target_length_mm - 2.0 * x0) / p).floor().max(0.0);
        let last_y = ((self.scene.board_width_mm - 2.0 * y0) / p)
            .floor()
            .max(0.0);
        let i = ((x - x0) / p).round().clamp(0.0, last_x);
        let j = ((y - y0) / p).round().clamp(0.0, last_y);
        let (dx, dy) = (x - (x0 + i * p), y - (y0 + j * p));
        let px = self.model.pitch_mm;
        let s2m = plan.target_mark_sigma_mm.powi(2);
        let s2 = s2m + (self.scene.blur_px.powi(2) + 1.0 / 12.0) * px * px;
        1.0 - plan.target_mark_depth * s2m / s2 * (-(dx * dx + dy * dy) / (2.0 * s2)).exp()
    }

    /// True height (um) at board point `(x, y)` and whether it is paste (deposits looked up
    /// in their bins).
    pub fn height_at(&self, x: f64, y: f64) -> (f64, bool) {
        let Surface::Board { deposits } = &self.surface else {
            return (self.surface.height(self.scene, x, y), false);
        };
        let (dh, paste) = paste_height(deposits, &self.index, [x, y]);
        (self.scene.warp(x, y) + dh, paste)
    }

    /// Mean intensity (before noise) of pixel `(r, c)` at conveyor travel `s`, DN.
    pub fn intensity(&self, s: f64, r: usize, c: usize, near_deposit: bool) -> f64 {
        let m = self.model;
        let sc = self.scene;
        if self.dead[r * m.width as usize + c] {
            return 0.0;
        }
        let (f, phi0, tz, ill) = (
            m.fringe_frequency[c],
            m.reference_phase_rad[c],
            m.height_per_turn_um[c],
            m.illumination[c],
        );
        let (rf, cf) = (r as f64, c as f64);
        if !near_deposit {
            let (x, y) = m.board_point(s, rf, cf);
            // Not near a deposit: the bare (warped) board, or the plane / target.
            let h = match self.surface {
                Surface::Board { .. } => sc.warp(x, y),
                _ => self.surface.height(sc, x, y),
            };
            let a = self.reflectance(x, y);
            let phase = TAU * f * rf + phi0 + TAU * h / tz;
            return ill * a * (sc.background + sc.contrast * self.m0[c] * phase.cos());
        }
        let Surface::Board { deposits } = &self.surface else {
            return 0.0;
        };
        // 3 x 3 sub-pixels, each integrating its own third of the pixel (sub-box sinc).
        let g_r = TAU * f;
        let sub = sinc(g_r / 6.0) * self.m_blur[c];
        let mut sum = 0.0;
        for dr in [-1.0 / 3.0, 0.0, 1.0 / 3.0] {
            for dc in [-1.0 / 3.0, 0.0, 1.0 / 3.0] {
                let (x, y) = m.board_point(s, rf + dr, cf + dc);
                let (dh, paste) = paste_height(deposits, &self.index, [x, y]);
                let h = sc.warp(x, y) + dh;
                let (bg, ct) = if paste {
                    (sc.paste_background, sc.paste_contrast)
                } else {
                    (sc.background, sc.contrast)
                };
                let phase = TAU * f * (rf + dr) + phi0 + TAU * h / tz;
                sum += bg + ct * sub * phase.cos();
            }
        }
        ill * sum / 9.0
    }

    /// Renders the frame at conveyor travel `s` with noise stream `stream` (row-major, DN).
    pub fn render(&self, s: f64, seed: u64, stream: u64) -> Vec<u16> {
        let m = self.model;
        let sc = self.scene;
        let (rows, w) = (m.rows as usize, m.width as usize);
        let mut rng = rng(seed, stream);
        let max = f64::from(crate::simulation::recording::max_value(sc.bit_depth));
        let mut out = vec![0u16; rows * w];
        let mut near = vec![false; w];
        let mut cand: Vec<usize> = Vec::new();
        for r in 0..rows {
            near.fill(false);
            if let Surface::Board { deposits } = &self.surface {
                let (xa, ya) = m.board_point(s, r as f64, 0.0);
                let (xb, yb) = m.board_point(s, r as f64, w as f64);
                self.index.in_box(
                    [
                        xa.min(xb) - 0.1,
                        ya.min(yb) - 0.1,
                        xa.max(xb) + 0.1,
                        ya.max(yb) + 0.1,
                    ],
                    &mut cand,
                );
                let (sn, cs) = m.rotation_rad.sin_cos();
                let slack = 2.0 * m.pitch_mm;
                let tilt = w as f64 * m.pitch_mm * sn.abs();
                let col = |y: f64| (y - ya) / (m.pitch_mm * cs);
                for &i in &cand {
                    let b = deposits[i].reach_bbox();
                    let c_lo = col(b[1] - slack - tilt).floor().clamp(0.0, w as f64) as usize;
                    let c_hi = col(b[3] + slack + tilt).ceil().clamp(0.0, w as f64) as usize;
                    for (c, flag) in near.iter_mut().enumerate().take(c_hi).skip(c_lo) {
                        let (x, y) = m.board_point(s, r as f64, c as f64);
                        if x >= b[0] - slack
                            && x <= b[2] + slack
                            && y >= b[1] - slack
                            && y <= b[3] + slack
                        {
                            *flag = true;
                        }
                    }
                }
            }
            for c in 0..w {
                let i = self.intensity(s, r, c, near[c]);
                let dn = noisy(i, sc.gain_e_per_dn, sc.read_noise_dn, &mut rng);
                out[r * w + c] = dn.round().clamp(0.0, max) as u16;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_frames_follow_the_model() {
        // A flat plane: every frame shows the same fringes; the frame mean over many frames
        // matches B + C M cos(2 pi f r + phi0 + 2 pi h / T) written out from the model.
        let scene = ArrayScene::default();
        let model = scene.camera_model(0);
        let r = CameraRenderer::new(&scene, &model, Surface::Plane { height_um: 123.0 });
        let frames: Vec<Vec<u16>> = (0..200).map(|k| r.render(k as f64 * 0.2, 5, k)).collect();
        let w = model.width as usize;
        let dead: Vec<usize> = model
            .dead_pixels
            .iter()
            .map(|&[a, b]| a as usize * w + b as usize)
            .collect();
        let mut worst: f64 = 0.0;
        for (row, col) in [(0usize, 0usize), (13, 77), (39, 159), (20, 80)] {
            let i = row * w + col;
            if dead.contains(&i) {
                continue;
            }
            let mean = frames.iter().map(|f| f64::from(f[i])).sum::<f64>() / 200.0;
            let f = model.fringe_frequency[col];
            let phase = TAU * f * row as f64
                + model.reference_phase_rad[col]
                + TAU * 123.0 / model.height_per_turn_um[col];
            let g = TAU * f;
            let mfac = sinc(g / 2.0) * (-(scene.blur_px * g).powi(2) / 2.0).exp();
            let expect = model.illumination[col] * (1800.0 + 700.0 * mfac * phase.cos());
            let sigma = (expect / 3.0 + 9.0).sqrt() / 200f64.sqrt();
            worst = worst.max(((mean - expect) / sigma).abs());
        }
        assert!(worst < 4.5, "{worst}");
        for &i in &dead {
            assert!(frames[0][i] < 30);
        }
    }

    #[test]
    fn deposits_show_and_edges_blur() {
        let scene = ArrayScene {
            warp_um: 0.0,
            ..ArrayScene::default()
        };
        let deps = place_deposits(&scene, 3);
        assert_eq!(deps.len(), 10);
        let d = &deps[0];
        // On the footprint the height is the deposit's; the wall is smooth.
        assert!((d.height(d.x_mm, d.y_mm, 0.08, 0.06) - d.height_um).abs() < 1e-9);
        assert_eq!(d.height(d.x_mm + d.length_mm, d.y_mm, 0.08, 0.06), 0.0);
        let mid = d.height(d.x_mm + d.length_mm / 2.0 - 0.03, d.y_mm, 0.08, 0.06);
        assert!(mid > 0.0 && mid < d.height_um);
    }
}
