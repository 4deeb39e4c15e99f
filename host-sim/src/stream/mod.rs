//! Packet streams: decoding a stream of row packets back into a height map, with the
//! damage report (good, corrupt and resynchronised packets).

use crate::heightmap::{HeightMap, HeightRow};
use dpsa_core::packets::{codec, Item, PacketError, Stream};
use serde::Serialize;

/// A packet that could not be decoded, and where.
#[derive(Clone, Debug, Serialize)]
pub struct Damage {
    /// Byte offset of the damaged packet (or of the garbage) in the stream.
    pub offset: usize,
    pub error: String,
}

/// Counts of a decoded stream.
#[derive(Clone, Debug, Default, Serialize)]
pub struct DecodeReport {
    /// Packets whose CRC and layout checked out.
    pub ok: usize,
    /// Damaged packets (each reported once in `damage`).
    pub corrupt: usize,
    /// Times the decoder had to search for the next sync word.
    pub resynced: usize,
    pub damage: Vec<Damage>,
}

/// Decodes a whole packet stream. Damage never stops the decoder: it reports the packet and
/// resynchronises on the next sync word. `lsb_um` labels the heights (the stream carries LSBs).
pub fn decode_stream(bytes: &[u8], lsb_um: f64) -> (HeightMap, DecodeReport) {
    let mut map = HeightMap::new(0, lsb_um);
    let mut rep = DecodeReport::default();
    // Codec reference state, sized by the first packet whose framing checks out; packets of
    // another width are reported as damage (a stream has one width). One decoder serves the
    // whole stream so that predicted rows (intra period > 1) find their reference.
    let width = first_width(bytes).unwrap_or(1);
    let mut reference = codec::ReferenceRow::new(width);
    let mut dec = reference.decoder();
    for item in Stream::new(bytes) {
        match item {
            Item::Packet { offset, packet: p } => {
                let w = p.header.width as usize;
                let mut heights = vec![0i16; w];
                let mut bits = vec![0u8; w.div_ceil(8)];
                let res = match dec.as_mut() {
                    Some(d) if d.width() == w => p.unpack(d, &mut heights, &mut bits),
                    _ => Err(PacketError::BadLength),
                };
                match res {
                    Ok(()) => {
                        if map.width == 0 {
                            map.width = w;
                        }
                        let valid = (0..w).map(|c| bits[c / 8] & (1 << (c % 8)) != 0).collect();
                        map.rows.push(HeightRow {
                            row: p.header.row,
                            latch: p.header.latch,
                            flags: p.header.flags,
                            heights,
                            valid,
                        });
                        rep.ok += 1;
                    }
                    Err(e) => damage(&mut rep, offset, e),
                }
            }
            Item::Damage { offset, error } => {
                damage(&mut rep, offset, error);
                rep.resynced += 1;
            }
        }
    }
    map.sort();
    (map, rep)
}

/// Width of the first packet in `bytes` whose framing and CRC check out.
fn first_width(bytes: &[u8]) -> Option<usize> {
    Stream::new(bytes).find_map(|item| match item {
        Item::Packet { packet, .. } => Some(packet.header.width as usize),
        Item::Damage { .. } => None,
    })
}

fn damage(rep: &mut DecodeReport, offset: usize, e: PacketError) {
    rep.corrupt += 1;
    rep.damage.push(Damage {
        offset,
        error: e.to_string(),
    });
}
