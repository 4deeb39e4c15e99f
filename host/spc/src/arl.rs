//! How often each rule fires on a process in control: its in-control average run length
//! (ARL), the mean number of points up to and including its first firing, for independent
//! normal points with the centre and sigma known. `1000 / ARL` is the false alarms a chart
//! raises over 1,000 boards, so this is what an alarm policy is set from.
//!
//! Computed exactly, independently of [`crate::rules`] (which tests compare with it by
//! simulating the rules' own code):
//!
//! - a point rule (WE1, N1): `1 / p`, `p = P(|z| > 3)`;
//! - a run of `w` points all in a set of probability `p` (N7: `|z| < 1`):
//!   `(1 - p^w) / ((1 - p) p^w)`;
//! - `w` in a row on one side (WE4, N2), either side with probability one half: `2^w - 1`;
//! - the zone-count rules (WE2, N5: 2 of 3 beyond 2 sigma; WE3, N6: 4 of 5 beyond 1 sigma) and
//!   N8 (8 beyond 1 sigma on both sides): an absorbing Markov chain over the categories of the
//!   last points (`t = (I - Q)^-1 1` from the chain's start, where no point has been seen);
//! - the trend and alternation rules (N3, N4) read the points' order, not their zones: no
//!   closed form here, `None` (the tests state their simulated value).

use crate::rules::Rule;
use nalgebra::{DMatrix, DVector};

/// `P(Z > x)` for a standard normal `Z`.
fn upper_tail(x: f64) -> f64 {
    0.5 * libm::erfc(x / std::f64::consts::SQRT_2)
}

/// The expected steps to absorption from state 0 of a chain with `n` transient states whose
/// transitions from a state are `next(state)` as `(probability, Some(state) | None)` (`None`:
/// absorbed, the rule fired).
fn chain(n: usize, next: impl Fn(usize) -> Vec<(f64, Option<usize>)>) -> Option<f64> {
    let mut a = DMatrix::<f64>::identity(n, n);
    for s in 0..n {
        for (p, t) in next(s) {
            if let Some(t) = t {
                a[(s, t)] -= p;
            }
        }
    }
    let t = a.lu().solve(&DVector::from_element(n, 1.0))?;
    Some(t[0])
}

/// A rule that fires when a window of `w` categories (of probabilities `probs`) satisfies
/// `fires`: the chain over the last `w - 1` categories, a window not yet full holding the
/// category `probs.len()` ("not seen"), which no pattern may contain.
fn window_chain(w: usize, probs: &[f64], fires: impl Fn(&[usize]) -> bool) -> Option<f64> {
    let k = probs.len() + 1;
    let n = k.pow(w as u32 - 1);
    // State: the last w - 1 categories, oldest first, as base-k digits; state 0 must be "all
    // not seen", so the digit `probs.len()` is stored as 0 and the categories shifted by one.
    let digits = |mut s: usize| -> Vec<usize> {
        let mut d = vec![0; w - 1];
        for slot in d.iter_mut().rev() {
            *slot = s % k;
            s /= k;
        }
        d
    };
    let encode = |d: &[usize]| d.iter().fold(0, |s, &x| s * k + x);
    chain(n, |s| {
        let hist = digits(s);
        (0..probs.len())
            .map(|c| {
                let mut win: Vec<usize> = hist.clone();
                win.push(c + 1);
                let full = win.iter().all(|&x| x != 0);
                let cats: Vec<usize> = win.iter().map(|&x| x.wrapping_sub(1)).collect();
                if full && fires(&cats) {
                    (probs[c], None)
                } else {
                    (probs[c], Some(encode(&win[1..])))
                }
            })
            .collect()
    })
}

/// N8 (the last 8 points all beyond 1 sigma, on both sides) by the chain over `(r, s)`: the
/// run of points beyond 1 sigma (`r`, up to 7) and the same-side streak that ends it (`s`, up
/// to `r`), either side alike; state 0 is "no run". `q` is `P(z > 1)`.
fn mixture_chain(q: f64) -> Option<f64> {
    const W: usize = 8;
    let index = |r: usize, s: usize| {
        if r == 0 {
            0
        } else {
            1 + (r - 1) * r / 2 + (s - 1)
        }
    };
    let n = index(W - 1, W - 1) + 1;
    let state = |i: usize| -> (usize, usize) {
        if i == 0 {
            return (0, 0);
        }
        let mut r = 1;
        while index(r + 1, 1) <= i && r < W - 1 {
            r += 1;
        }
        (r, i - index(r, 1) + 1)
    };
    chain(n, |i| {
        let (r, s) = state(i);
        let within = (1.0 - 2.0 * q, Some(0));
        let r1 = r + 1;
        // The same side (the streak grows) and the other (it starts again at 1).
        let same = if r1 >= W && s + 1 < W {
            (q, None)
        } else {
            (q, Some(index(r1.min(W - 1), (s + 1).min(r1.min(W - 1)))))
        };
        let other = if r == 0 {
            (q, Some(index(1, 1)))
        } else if r1 >= W {
            (q, None)
        } else {
            (q, Some(index(r1, 1)))
        };
        let same = if r == 0 { (q, Some(index(1, 1))) } else { same };
        vec![within, same, other]
    })
}

/// The in-control ARL of `rule` (see the module docs); `None` for N3 and N4.
pub fn in_control_arl(rule: Rule) -> Option<f64> {
    let beyond = |x: f64| upper_tail(x);
    match rule {
        Rule::We1 | Rule::N1 => Some(1.0 / (2.0 * beyond(3.0))),
        Rule::We4 => Some(2f64.powi(8) - 1.0),
        Rule::N2 => Some(2f64.powi(9) - 1.0),
        Rule::N7 => {
            let p = 1.0 - 2.0 * beyond(1.0);
            let pw = p.powi(15);
            Some((1.0 - pw) / ((1.0 - p) * pw))
        }
        Rule::We2 | Rule::N5 | Rule::We3 | Rule::N6 => {
            let (w, k, x) = match rule {
                Rule::We2 | Rule::N5 => (3, 2, 2.0),
                _ => (5, 4, 1.0),
            };
            // Categories: above x, below -x, between.
            let probs = [beyond(x), beyond(x), 1.0 - 2.0 * beyond(x)];
            window_chain(w, &probs, |win| {
                win.iter().filter(|&&c| c == 0).count() >= k
                    || win.iter().filter(|&&c| c == 1).count() >= k
            })
        }
        Rule::N8 => mixture_chain(beyond(1.0)),
        Rule::N3 | Rule::N4 => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rules::fires;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    /// Published values: 370.4 for a point beyond 3 sigma, 255 for 8 in a row on one side.
    #[test]
    fn the_published_values() {
        assert!((in_control_arl(Rule::We1).unwrap() - 370.4).abs() < 0.05);
        assert_eq!(in_control_arl(Rule::We4), Some(255.0));
        // The chain gives the closed form where there is one: a run of 8 on one side as a
        // window rule over (above, below) halves.
        let by_chain = window_chain(8, &[0.5, 0.5], |w| {
            w.iter().all(|&c| c == 0) || w.iter().all(|&c| c == 1)
        })
        .unwrap();
        assert!((by_chain - 255.0).abs() < 1e-6, "{by_chain}");
        // And the point rule: a window of one.
        let p = 2.0 * upper_tail(3.0);
        let one = window_chain(1, &[p, 1.0 - p], |w| w[0] == 0).unwrap();
        assert!((one - 1.0 / p).abs() < 1e-6);
    }

    /// The rules' own code on simulated in-control points: the mean index of the first
    /// firing (plus one) over many runs agrees with the exact ARL within 4 standard errors.
    #[test]
    fn the_rules_fire_as_often_as_their_arl_says() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for rule in Rule::ALL {
            let runs = 1500;
            let mut lengths = Vec::with_capacity(runs);
            for _ in 0..runs {
                // Points in blocks until the rule fires (each block carries the last window
                // over, so no firing is lost at a seam).
                let mut x: Vec<f64> = Vec::new();
                let first = loop {
                    let more: Vec<f64> =
                        (0..2048).map(|_| StandardNormal.sample(&mut rng)).collect();
                    x.extend(more);
                    let z: Vec<Option<f64>> = x.iter().map(|&v| Some(v)).collect();
                    if let Some(&i) = fires(rule, &x, &z).first() {
                        break i;
                    }
                };
                lengths.push((first + 1) as f64);
            }
            let n = lengths.len() as f64;
            let mean = lengths.iter().sum::<f64>() / n;
            let sd = (lengths.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
            let se = sd / n.sqrt();
            match in_control_arl(rule) {
                Some(arl) => {
                    eprintln!("{rule}: exact {arl:.1}, simulated {mean:.1} +- {se:.1}");
                    assert!(
                        (mean - arl).abs() < 4.0 * se,
                        "{rule}: exact {arl}, simulated {mean} +- {se}"
                    );
                }
                None => eprintln!("{rule}: simulated {mean:.1} +- {se:.1} (no closed form)"),
            }
        }
    }
}
