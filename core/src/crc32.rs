//! CRC-32/ISO-HDLC (the zlib and Ethernet CRC: reflected, polynomial `0xEDB88320`, initial
//! value and final XOR `0xFFFFFFFF`), the checksum of the packets and the feed.
//!
//! One 256-entry table (1 KiB), four bytes per step: one word load, then four table lookups
//! (about 3 instructions per byte on a Cortex-M7, against 8 for a byte loop). The tests check it
//! against the `crc` crate.

/// Reflected polynomial.
const POLY: u32 = 0xEDB8_8320;

/// `TABLE[b]`: the CRC register after shifting the byte `b` through it.
static TABLE: [u32; 256] = table();

const fn table() -> [u32; 256] {
    let mut t = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u32;
        let mut j = 0;
        while j < 8 {
            c = if c & 1 != 0 { (c >> 1) ^ POLY } else { c >> 1 };
            j += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
}

/// One byte through the register.
#[inline(always)]
fn step(crc: u32) -> u32 {
    TABLE[(crc & 0xFF) as usize] ^ (crc >> 8)
}

/// The CRC-32 of `data`.
#[inline(never)]
pub fn checksum(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    let mut words = data.chunks_exact(4);
    for w in &mut words {
        crc ^= u32::from_le_bytes([w[0], w[1], w[2], w[3]]);
        crc = step(step(step(step(crc))));
    }
    for &b in words.remainder() {
        crc = step(crc ^ u32::from(b));
    }
    !crc
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crc::{Crc, CRC_32_ISO_HDLC};
    use proptest::prelude::*;

    const REFERENCE: Crc<u32> = Crc::<u32>::new(&CRC_32_ISO_HDLC);

    #[test]
    fn check_value_and_edges() {
        assert_eq!(checksum(b"123456789"), 0xCBF4_3926);
        assert_eq!(checksum(&[]), 0);
        // Every length and start up to a few words, so every remainder and alignment.
        let data: std::vec::Vec<u8> = (0u32..64).map(|i| (i * 37 + 11) as u8).collect();
        for s in 0..8 {
            for e in s..data.len() {
                assert_eq!(checksum(&data[s..e]), REFERENCE.checksum(&data[s..e]));
            }
        }
    }

    proptest! {
        #[test]
        fn equals_the_crc_crate(data in proptest::collection::vec(any::<u8>(), 0..5000), start in 0usize..4) {
            let d = &data[start.min(data.len())..];
            prop_assert_eq!(checksum(d), REFERENCE.checksum(d));
        }
    }
}
