//! The instructions the host's inner loops run on: the target's baseline (SSE2 on x86-64),
//! or AVX2 with FMA where run-time detection finds them (x86-64 only). A loop built for both
//! gives the same values on either, to the bit: Rust neither fuses a multiplication and an
//! addition into an FMA nor reorders floating-point operations, whatever the instructions,
//! and the hand-written vector forms do the scalar operations in the scalar order. The
//! choice is one of speed only; the tests that compare the two take [`Instructions::Baseline`]
//! and [`Instructions::best`].

/// An instruction set a loop is built for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Instructions {
    /// The target's baseline instructions (SSE2 on x86-64).
    Baseline,
    /// AVX2 with FMA and the bit instructions of the same processors (x86-64, detected).
    Avx2,
}

impl Instructions {
    /// AVX2 where this processor has it (with FMA), else the baseline.
    pub fn best() -> Instructions {
        if avx2_fma() {
            Instructions::Avx2
        } else {
            Instructions::Baseline
        }
    }

    /// Whether these are AVX2 and this processor runs them: what a caller checks before it
    /// takes an AVX2 build (asked for AVX2 on a processor without it, it takes the
    /// baseline).
    pub fn avx2(self) -> bool {
        self == Instructions::Avx2 && avx2_fma()
    }
}

/// The best this processor runs ([`Instructions::best`]): what a stage takes unless a test
/// asks for another.
impl Default for Instructions {
    fn default() -> Instructions {
        Instructions::best()
    }
}

/// Whether this processor runs AVX2 and FMA (run-time detection on x86-64; the standard
/// library caches it, so a call is a load).
fn avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    return std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The baseline is never taken for AVX2, and AVX2 only where detected.
    #[test]
    fn avx2_only_where_detected() {
        assert!(!Instructions::Baseline.avx2());
        assert_eq!(
            Instructions::Avx2.avx2(),
            Instructions::best() == Instructions::Avx2
        );
        #[cfg(target_arch = "x86_64")]
        assert_eq!(
            Instructions::best() == Instructions::Avx2,
            std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
        );
    }
}
