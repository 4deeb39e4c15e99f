//! CRC-32/ISO-HDLC (the zlib and Ethernet CRC: reflected, polynomial `0xEDB88320`, initial
//! value and final XOR `0xFFFFFFFF`), the checksum of the packets and the feed.
//!
//! A word at a time, 6 bits a step (a 64-entry and a 4-entry table, 272 bytes of flash): one
//! word load, then five 6-bit steps and one 2-bit step of three instructions each, about 5.5
//! instructions per byte on a Cortex-M7. A 16-entry table would take 7 per byte, a 256-entry
//! one 3.75 for 1 KiB of flash (the firmware's packets are about 0.7 bytes per output pixel,
//! so each instruction per byte is about 0.7 per pixel of the packet encode). The tests check
//! it against the `crc` crate.

/// Reflected polynomial.
const POLY: u32 = 0xEDB8_8320;

/// `T6[n]`: the CRC register after shifting the 6 bits `n` through it.
static T6: [u32; 64] = table::<64>(6);
/// `T2[n]`: the same for 2 bits.
static T2: [u32; 4] = table::<4>(2);

const fn table<const N: usize>(bits: u32) -> [u32; N] {
    let mut t = [0u32; N];
    let mut i = 0;
    while i < N {
        let mut c = i as u32;
        let mut j = 0;
        while j < bits {
            c = if c & 1 != 0 { (c >> 1) ^ POLY } else { c >> 1 };
            j += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
}

/// 6 bits, then 2 bits through the register.
#[inline(always)]
fn step6(crc: u32) -> u32 {
    T6[(crc & 63) as usize] ^ (crc >> 6)
}

#[inline(always)]
fn step2(crc: u32) -> u32 {
    T2[(crc & 3) as usize] ^ (crc >> 2)
}

/// The CRC-32 of `data`.
#[inline(never)]
pub fn checksum(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    let mut words = data.chunks_exact(4);
    for w in &mut words {
        crc ^= u32::from_le_bytes([w[0], w[1], w[2], w[3]]);
        // 32 bits: 5 x 6 + 2.
        crc = step2(step6(step6(step6(step6(step6(crc))))));
    }
    for &b in words.remainder() {
        crc = step2(step6(crc ^ u32::from(b)));
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
