//! CRC-32/ISO-HDLC (the zlib and Ethernet CRC: reflected, polynomial `0xEDB88320`, initial
//! value and final XOR `0xFFFFFFFF`), the checksum of the packets and the feed.
//!
//! On the target: one 256-entry table (1 KiB), four bytes per step: one word load, then four
//! table lookups (about 3 instructions per byte on a Cortex-M7, against 8 for a byte loop). A
//! faster table method (slicing by 8 or 16) wants 8 or 16 KiB of tables in the DTCM beside
//! the pipeline's line pool (`memory.x`), or read from flash.
//!
//! On a host (the `std` feature): the `crc32fast` crate, which folds 64 bytes at a time with
//! carry-less multiplication where the processor has it (x86-64's PCLMULQDQ, detected at run
//! time). The host checks the CRC of every packet it decodes: the table's byte-serial chain was
//! 15 % of `dpsa decode`'s time (`perf record`), 2 % of the line service's. Both give the same
//! value for every input (tested; the `crc` crate is the reference of both).

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

/// The CRC-32 of `data`: crc32fast's on a host (`std`), [`by_table`] on the target.
#[cfg(feature = "std")]
#[inline]
pub fn checksum(data: &[u8]) -> u32 {
    crc32fast::hash(data)
}

/// The CRC-32 of `data`: crc32fast's on a host (`std`), [`by_table`] on the target.
#[cfg(not(feature = "std"))]
#[inline(never)]
pub fn checksum(data: &[u8]) -> u32 {
    by_table(data)
}

/// The CRC-32 of `data` through the 1 KiB table, four bytes per step (the target's).
#[inline(always)]
pub fn by_table(data: &[u8]) -> u32 {
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
        for f in [checksum, by_table] {
            assert_eq!(f(b"123456789"), 0xCBF4_3926);
            assert_eq!(f(&[]), 0);
            // Every length and start up to a few words (and past crc32fast's 64-byte folds),
            // so every remainder and alignment.
            let data: std::vec::Vec<u8> = (0u32..300).map(|i| (i * 37 + 11) as u8).collect();
            for s in 0..8 {
                for e in s..data.len() {
                    assert_eq!(f(&data[s..e]), REFERENCE.checksum(&data[s..e]));
                }
            }
        }
    }

    proptest! {
        /// The host's and the target's CRC against the `crc` crate (the tests build the core
        /// with `std`, so `checksum` is crc32fast's here and `by_table` the target's).
        #[test]
        fn equals_the_crc_crate(data in proptest::collection::vec(any::<u8>(), 0..5000), start in 0usize..4) {
            let d = &data[start.min(data.len())..];
            prop_assert_eq!(checksum(d), REFERENCE.checksum(d));
            prop_assert_eq!(by_table(d), REFERENCE.checksum(d));
        }
    }
}
