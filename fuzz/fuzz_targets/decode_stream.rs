//! Arbitrary bytes as a packet stream (docs/stream.md): the core's stream walk
//! (`packets::Stream`, what the host's decoder runs on), the packet parser at every sync word,
//! and the row codec's decoder, directly.
//!
//! Oracles besides "no panic, no hang, no overflow": the stream walk is self-consistent, a
//! parsed packet lies inside the input, and every row the codec decodes is well formed (heights
//! 0 where invalid, padding bits 0) and survives a re-encode / decode round trip unchanged.

#![no_main]

use dpsa_core::packets::{self, codec};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    whole_stream(data);
    packets_at_syncs(data);
    codec_payloads(data);
});

/// `packets::Stream`: never panics; items in stream order at increasing offsets inside the
/// input; a packet starts with the sync word and ends inside the input, the next item starts
/// right after it; damage is followed by the next sync word after it (or the end); every byte
/// of the input is covered by a packet or skipped after damage.
fn whole_stream(data: &[u8]) {
    let mut next_at = 0usize;
    let (mut ok, mut damage) = (0usize, 0usize);
    let mut walk = packets::Stream::new(data);
    let mut tracker = packets::Tracker::new();
    while let Some(item) = walk.next() {
        match item {
            packets::Item::Packet { offset, packet } => {
                assert_eq!(offset, next_at, "a packet where the walk did not stand");
                assert_eq!(data[offset..offset + 4], packets::SYNC);
                let len = header_len(packet.version) + packet.payload.len() + packets::TRAILER_LEN;
                assert!(offset + len <= data.len());
                // The packet re-parses alone to itself.
                let (again, l2) = packets::decode(&data[offset..offset + len]).unwrap();
                assert_eq!(
                    (again.header, again.seq, l2),
                    (packet.header, packet.seq, len)
                );
                next_at = offset + len;
                ok += 1;
                tracker.packet(&packet);
            }
            packets::Item::Damage { offset, error } => {
                assert_eq!(offset, next_at, "damage where the walk did not stand");
                assert!(offset < data.len());
                assert!(packets::decode(&data[offset..]).err() == Some(error));
                // Resynchronised on the next sync word, or (a version 2 packet whose header
                // checked out, payload CRC bad) skipped whole.
                let resync = packets::find_sync(data, offset + 1).unwrap_or(data.len());
                let at = walk.position();
                if error == packets::PacketError::BadCrc && data[offset + 4] == packets::VERSION {
                    assert!(at > offset + packets::HEADER_LEN && at <= data.len());
                    next_at = at;
                } else {
                    assert!(at == offset + 1 || at == resync);
                    next_at = resync;
                }
                damage += 1;
                tracker.damage();
            }
        }
    }
    assert_eq!(
        next_at.max(walk.position()),
        data.len(),
        "the walk stopped early"
    );
    assert!(ok + damage <= data.len());
    let s = tracker.summary();
    assert_eq!(s.damage as usize, damage);
    assert!(s.packets as usize <= ok);
}

fn header_len(version: u8) -> usize {
    if version == packets::VERSION {
        packets::HEADER_LEN
    } else {
        packets::HEADER_LEN_V1
    }
}

/// Well-framed packets at or after every sync word (`packets::decode` tried at each).
fn framed(data: &[u8]) -> impl Iterator<Item = packets::Packet<'_>> {
    let mut from = 0;
    std::iter::from_fn(move || loop {
        let p = packets::find_sync(data, from)?;
        from = p + 1;
        if let Ok((pkt, len)) = packets::decode(&data[p..]) {
            assert!(len <= data.len() - p);
            assert_eq!(
                len,
                header_len(pkt.version) + pkt.payload.len() + packets::TRAILER_LEN
            );
            return Some(pkt);
        }
    })
}

/// `packets::decode` at every sync word; the compressed payloads of well-framed packets go
/// through a codec decoder (one kept across the packets of the first width seen, so that
/// predicted rows can decode; a fresh one for other widths).
fn packets_at_syncs(data: &[u8]) {
    let usable = |p: &packets::Packet<'_>| {
        p.kind == packets::Kind::Row
            && p.codec == packets::CODEC_COMPRESSED
            && (1..=codec::MAX_WIDTH).contains(&(p.header.width as usize))
    };
    let Some(w0) = framed(data).find(usable).map(|p| p.header.width as usize) else {
        return;
    };
    let (mut rh, mut rv) = (vec![0i16; w0], vec![0u8; w0.div_ceil(8)]);
    let mut dec = codec::Decoder::new(&mut rh, &mut rv, w0).unwrap();
    for pkt in framed(data).filter(usable) {
        let w = pkt.header.width as usize;
        let (mut h, mut v) = (vec![0i16; w], vec![0u8; w.div_ceil(8)]);
        let ok = if w == w0 {
            dec.decode(pkt.payload, &mut h, &mut v).is_ok()
        } else {
            let (mut fh, mut fv) = (vec![0i16; w], vec![0u8; w.div_ceil(8)]);
            let mut d = codec::Decoder::new(&mut fh, &mut fv, w).unwrap();
            d.decode(pkt.payload, &mut h, &mut v).is_ok()
        };
        if ok {
            check_row(w, &h, &v);
        }
    }
}

/// The input after its first byte as payloads of a row of `1 + data[0]` pixels, each prefixed
/// by its length (u16 little-endian, cut to what is left), through one codec decoder.
fn codec_payloads(data: &[u8]) {
    let Some((&w0, mut rest)) = data.split_first() else {
        return;
    };
    let w = 1 + usize::from(w0);
    let nb = w.div_ceil(8);
    let (mut rh, mut rv) = (vec![0i16; w], vec![0u8; nb]);
    let mut dec = codec::Decoder::new(&mut rh, &mut rv, w).unwrap();
    let (mut h, mut v) = (vec![0i16; w], vec![0u8; nb]);
    while rest.len() >= 2 {
        let n = usize::from(u16::from_le_bytes([rest[0], rest[1]])).min(rest.len() - 2);
        let payload = &rest[2..2 + n];
        rest = &rest[2 + n..];
        if dec.decode(payload, &mut h, &mut v).is_ok() {
            check_row(w, &h, &v);
        }
    }
}

/// A decoded row is well formed and codes back to itself.
fn check_row(w: usize, h: &[i16], v: &[u8]) {
    let nb = w.div_ceil(8);
    let valid = |c: usize| v[c / 8] >> (c % 8) & 1 != 0;
    for (c, &x) in h.iter().enumerate().take(w) {
        assert!(valid(c) || x == 0, "invalid pixel {c} has height {x}");
    }
    if !w.is_multiple_of(8) {
        assert_eq!(v[nb - 1] >> (w % 8), 0, "padding bits set");
    }
    let (mut eh, mut ev, mut dh, mut dv) =
        (vec![0i16; w], vec![0u8; nb], vec![0i16; w], vec![0u8; nb]);
    let mut enc = codec::Encoder::new(&mut eh, &mut ev, w, packets::STREAM_INTRA_PERIOD).unwrap();
    let mut buf = vec![0u8; codec::max_len(w)];
    let n = enc.encode(h, v, &mut buf).unwrap();
    assert!(n <= codec::max_len(w));
    let mut dec = codec::Decoder::new(&mut dh, &mut dv, w).unwrap();
    let (mut h2, mut v2) = (vec![0i16; w], vec![0u8; nb]);
    dec.decode(&buf[..n], &mut h2, &mut v2).unwrap();
    assert_eq!(&h2[..], &h[..w]);
    assert_eq!(&v2[..], &v[..nb]);
}
