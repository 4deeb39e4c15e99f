//! The tests' small deterministic generator (a 64-bit linear congruential one, Knuth's MMIX
//! constants): the same numbers on every machine, so a test's inputs are the same each run.

/// Uniform numbers in `[0, 1)` from seed `.0`.
pub(crate) struct Lcg(pub(crate) u64);

impl Lcg {
    /// The next number: the state's top 53 bits over `2^53`.
    pub(crate) fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}
