//! The compressed binary frame format (`.zfr`), beside 16-bit PNG.
//!
//! A `.zfr` file is `b"DPSAZFR1"`, then `rows` and `width` as little-endian u32, then one zstd
//! frame (level 1) holding the frame's samples as horizontal differences: for every row, the
//! first sample and then `v[c] - v[c-1]` (wrapping 16-bit), each zigzag-coded (small signed
//! differences become small unsigned values) and stored little-endian. It is lossless; a
//! recording's manifest names each frame file, and `Recording::frame` picks the decoder by the
//! file's extension, so every tool reads both formats.

use serde::{Deserialize, Serialize};

/// Magic bytes at the start of every `.zfr` frame.
pub const MAGIC: &[u8; 8] = b"DPSAZFR1";
/// Extension of the binary frame files.
pub const EXTENSION: &str = "zfr";

/// How `dpsa simulate` writes frames.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
#[serde(rename_all = "lowercase")]
pub enum FrameFormat {
    /// 16-bit greyscale PNG (fast compression): readable by any image tool.
    Png,
    /// zstd-compressed horizontal differences (this module): smaller and faster.
    #[default]
    Zfr,
}

impl FrameFormat {
    /// File extension of the format.
    pub fn extension(self) -> &'static str {
        match self {
            FrameFormat::Png => "png",
            FrameFormat::Zfr => EXTENSION,
        }
    }
}

fn zigzag(d: i16) -> u16 {
    ((d << 1) ^ (d >> 15)) as u16
}

fn unzigzag(z: u16) -> i16 {
    ((z >> 1) as i16) ^ -((z & 1) as i16)
}

/// Encodes a `rows x width` frame (row-major). `data.len()` must be `rows * width`.
pub fn encode(rows: usize, width: usize, data: &[u16]) -> std::io::Result<Vec<u8>> {
    if rows.checked_mul(width) != Some(data.len())
        || rows > u32::MAX as usize
        || width > u32::MAX as usize
    {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{} samples for a {rows} x {width} frame", data.len()),
        ));
    }
    let mut raw = Vec::with_capacity(data.len() * 2);
    for row in data.chunks_exact(width.max(1)) {
        let mut prev = 0u16;
        for &v in row {
            let d = v.wrapping_sub(prev) as i16;
            raw.extend_from_slice(&zigzag(d).to_le_bytes());
            prev = v;
        }
    }
    let body = zstd::bulk::compress(&raw, 1)?;
    let mut out = Vec::with_capacity(body.len() + 16);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(rows as u32).to_le_bytes());
    out.extend_from_slice(&(width as u32).to_le_bytes());
    out.extend_from_slice(&body);
    Ok(out)
}

/// Header of a `.zfr` file: `(rows, width)`, or a sentence saying why it is not one.
pub fn header(bytes: &[u8]) -> Result<(usize, usize), String> {
    if bytes.len() < 16 || &bytes[..8] != MAGIC {
        return Err("not a dpsa .zfr frame (bad magic bytes or truncated header)".into());
    }
    let rows = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize;
    let width = u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]) as usize;
    Ok((rows, width))
}

/// Decodes the samples of a `.zfr` file whose header says `rows x width` (check the header
/// against the camera first: the decoder allocates exactly `rows * width` samples).
pub fn decode_body(bytes: &[u8], rows: usize, width: usize) -> Result<Vec<u16>, String> {
    let n = rows
        .checked_mul(width)
        .and_then(|n| n.checked_mul(2))
        .ok_or("frame size overflows")?;
    let raw = zstd::bulk::decompress(bytes.get(16..).unwrap_or(&[]), n)
        .map_err(|e| format!("corrupt zstd data: {e}"))?;
    if raw.len() != n {
        return Err(format!(
            "{} bytes of samples, expected {n} ({rows} x {width} x 2)",
            raw.len()
        ));
    }
    let mut out = Vec::with_capacity(rows * width);
    for row in raw.chunks_exact((2 * width).max(2)) {
        let mut prev = 0u16;
        for b in row.chunks_exact(2) {
            let v = prev.wrapping_add(unzigzag(u16::from_le_bytes([b[0], b[1]])) as u16);
            out.push(v);
            prev = v;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_corruption() {
        let (rows, width) = (7, 33);
        let data: Vec<u16> = (0..rows * width)
            .map(|i| ((i * 7919) % 4096) as u16 ^ if i % 5 == 0 { 0xFFFF } else { 0 })
            .collect();
        let bytes = encode(rows, width, &data).unwrap();
        assert_eq!(header(&bytes), Ok((rows, width)));
        assert_eq!(decode_body(&bytes, rows, width).unwrap(), data);
        assert!(header(&bytes[..10]).is_err());
        assert!(decode_body(&bytes[..bytes.len() - 3], rows, width).is_err());
        assert!(decode_body(&bytes, rows, width + 1).is_err());
        for d in [i16::MIN, -1, 0, 1, i16::MAX] {
            assert_eq!(unzigzag(zigzag(d)), d);
        }
        assert!(encode(2, 2, &[1, 2, 3]).is_err());
    }
}
