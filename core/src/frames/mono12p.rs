//! Mono12p: 12-bit samples packed two per three bytes, the line format of a 12-bit camera.
//!
//! The GenICam pixel format `Mono12p` (PFNC): samples are packed least significant bit
//! first, so pixels `2i` and `2i + 1` fill bytes `3i .. 3i + 3` as the little-endian 24-bit
//! value `x(2i) | x(2i + 1) << 12`. A line of `W` pixels takes [`packed_len`]`(W) = 3 ceil(W/2)`
//! bytes (an odd `W` pads the last pair with a zero sample). A 12-bit camera sends its lines so,
//! and the feed may carry them so ([`crate::frames::feed`]).
//!
//! The pipeline keeps the raw samples of open rows in this format whenever every sample that
//! matters fits 12 bits, i.e. when `saturation <= 4095` ([`crate::pipeline::Layout`]): three
//! quarters of the line pool's 16-bit size, the difference between the default geometry's
//! state fitting a 256 KiB TCM or not. [`pack`] clamps a sample above 4095 to 4095, which keeps
//! it at or above any such saturation level: the pipeline's output is the same as with 16-bit
//! storage (tested in `pipeline`).
//!
//! The accumulate kernel reads eight pixels of a line as three aligned words
//! ([`crate::accumulate::block_packed`]), so a pool line takes [`stored_len`] bytes: the
//! packed line rounded up to whole words, and every line starts on a word.

/// Largest sample a packed line holds.
pub const MAX: u16 = 0x0FFF;

/// Bytes of a packed line of `width` pixels: `3 ceil(width / 2)`.
pub const fn packed_len(width: usize) -> usize {
    3 * width.div_ceil(2)
}

/// Bytes a line takes in the line pool and in the pipeline's packing buffer: [`packed_len`]
/// rounded up to whole 32-bit words.
pub const fn stored_len(width: usize) -> usize {
    packed_len(width).div_ceil(4) * 4
}

/// Packs `line` into `out` (at least [`packed_len`]`(line.len())` bytes), each sample clamped
/// to [`MAX`]. Bytes of `out` past the packed length are left alone.
pub fn pack(line: &[u16], out: &mut [u8]) {
    let pairs = line.chunks(2);
    for (o, p) in out.chunks_exact_mut(3).zip(pairs) {
        let x0 = p[0].min(MAX) as u32;
        let x1 = p.get(1).map_or(0, |&x| x.min(MAX)) as u32;
        let v = x0 | x1 << 12;
        o.copy_from_slice(&v.to_le_bytes()[..3]);
    }
}

/// Unpacks `b` ([`packed_len`]`(line.len())` bytes or more) into `line`.
pub fn unpack(b: &[u8], line: &mut [u16]) {
    for (c, x) in line.iter_mut().enumerate() {
        *x = sample(b, c);
    }
}

/// Sample `c` of a packed line (`b` holds at least [`packed_len`]`(c + 1)` bytes).
#[inline(always)]
pub fn sample(b: &[u8], c: usize) -> u16 {
    let i = 3 * (c / 2);
    let v = b[i] as u32 | (b[i + 1] as u32) << 8 | (b[i + 2] as u32) << 16;
    ((v >> (12 * (c & 1))) & 0xFFF) as u16
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;

    #[test]
    fn round_trip_and_clamp() {
        for w in [1usize, 2, 3, 7, 64, 2048] {
            let line: vec::Vec<u16> = (0..w).map(|c| ((c * 2654435761) % 5000) as u16).collect();
            let mut b = vec![0xAAu8; packed_len(w) + 1];
            pack(&line, &mut b);
            assert_eq!(b[packed_len(w)], 0xAA, "bytes past the line untouched");
            assert!(stored_len(w) >= packed_len(w) && stored_len(w) % 4 == 0);
            let mut back = vec![0u16; w];
            unpack(&b, &mut back);
            for c in 0..w {
                assert_eq!(back[c], line[c].min(MAX), "w {w} c {c}");
                assert_eq!(sample(&b, c), line[c].min(MAX));
            }
        }
        // The PFNC layout, byte by byte: 0xABC, 0x123 -> BC 3A 12.
        let mut b = [0u8; 4];
        pack(&[0xABC, 0x123], &mut b);
        assert_eq!(b[..3], [0xBC, 0x3A, 0x12]);
        // An odd width pads with a zero sample.
        pack(&[0xFFF], &mut b);
        assert_eq!(b[..3], [0xFF, 0x0F, 0x00]);
    }
}
