//! Images out: 16-bit height PNGs, false-colour PNGs and wrapped-phase PNGs.

use image::{GrayImage, ImageBuffer, Luma, Rgb, RgbImage};
use std::path::Path;

use crate::files::FileError;
use crate::heightmap::HeightMap;

/// Why an image was not written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PngError {
    /// The map's rows leave more than [`MAX_HOLE_ROWS`] board rows without a row (the image
    /// would be mostly holes, and could be as tall as the `i64` rows allow).
    #[error(
        "the rows span {span} board rows ({first} to {last}) but only {present} are present: more than {MAX_HOLE_ROWS} missing rows (an encoder-fault gap?) cannot be drawn"
    )]
    TooManyMissingRows {
        /// Board rows from the first to the last row present, both included.
        span: u64,
        /// The first board row present.
        first: i64,
        /// The last board row present.
        last: i64,
        /// Rows present.
        present: usize,
    },
    /// The file could not be written.
    #[error(transparent)]
    File(#[from] FileError),
}

/// Largest number of board rows without a row (lost packets, encoder-fault gaps) an image
/// may span beyond the rows it has.
pub const MAX_HOLE_ROWS: u64 = 1 << 16;

/// Image rows of a map placed by board row: `(first board row, image height)`. Rows sit at
/// their board row, so a missing row is an invalid image row, not a shift of the rows after
/// it. Refuses a span of more than [`MAX_HOLE_ROWS`] board rows beyond the rows present.
fn span(map: &HeightMap) -> Result<(i64, u32), PngError> {
    let (Some(first), Some(last)) = (map.first_row(), map.last_row()) else {
        return Ok((0, 0));
    };
    let span = (last as i128 - first as i128 + 1) as u64;
    if span > map.rows.len() as u64 + MAX_HOLE_ROWS || span > u32::MAX as u64 {
        return Err(PngError::TooManyMissingRows {
            span,
            first,
            last,
            present: map.rows.len(),
        });
    }
    Ok((first, span as u32))
}

/// Writes the height map as a 16-bit greyscale PNG: value `h + 32768` (h in LSB) for valid
/// pixels, 0 for invalid ones. Image row `i` is board row `first_row + i` (missing rows are
/// invalid).
pub fn write_height_png(map: &HeightMap, path: &Path) -> Result<(), PngError> {
    let (first, h) = span(map)?;
    let w = map.width as u32;
    let img: ImageBuffer<Luma<u16>, Vec<u16>> = ImageBuffer::from_fn(w, h, |x, y| {
        let Some(row) = map.get(first + y as i64) else {
            return Luma([0]);
        };
        let c = x as usize;
        if row.pixel_valid(c) {
            Luma([(row.heights[c] as i32 + 32768).clamp(1, 65535) as u16])
        } else {
            Luma([0])
        }
    });
    Ok(save_png(&img, path)?)
}

/// Writes a false-colour PNG of the heights over `[lo_um, hi_um]`; invalid pixels are dark grey.
pub fn write_false_colour_png(
    map: &HeightMap,
    lo_um: f64,
    hi_um: f64,
    path: &Path,
) -> Result<(), PngError> {
    let (first, h) = span(map)?;
    let w = map.width as u32;
    let span = (hi_um - lo_um).max(1e-9);
    let img: RgbImage = ImageBuffer::from_fn(w, h, |x, y| {
        let Some(row) = map.get(first + y as i64) else {
            return Rgb([40, 40, 40]);
        };
        let c = x as usize;
        if row.pixel_valid(c) {
            let t = ((row.heights[c] as f64 * map.lsb_um - lo_um) / span).clamp(0.0, 1.0);
            Rgb(colour(t))
        } else {
            Rgb([40, 40, 40])
        }
    });
    Ok(save_png(&img, path)?)
}

/// Writes a wrapped phase map (`[-pi, pi)` -> 1..=255) as 8-bit grey; `None` (invalid) is 0.
pub fn write_phase_png(phase: &[Option<f64>], width: usize, path: &Path) -> Result<(), FileError> {
    let h = phase.len() / width.max(1);
    let img: GrayImage = ImageBuffer::from_fn(width as u32, h as u32, |x, y| {
        match phase[y as usize * width + x as usize] {
            Some(p) => {
                let t = (p + std::f64::consts::PI) / (2.0 * std::f64::consts::PI);
                Luma([(1.0 + t.clamp(0.0, 1.0) * 254.0).round() as u8])
            }
            None => Luma([0]),
        }
    });
    save_png(&img, path)
}

/// Writes an image as PNG atomically (temporary file renamed into place when complete).
pub fn save_png<P, C>(img: &ImageBuffer<P, C>, path: &Path) -> Result<(), FileError>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    crate::files::write_atomic(path, |w| img.write_to(w, image::ImageFormat::Png))
}

/// Writes a 16-bit grey PNG of `width x rows` atomically, row by row: `row(i, out)` fills
/// row `i`. Nothing image-sized is held (the `image` crate's encoder holds the image and a
/// big-endian copy of it: 190 MB on a paper board's map); the `png` crate's encoder with
/// its fast compression and each row filtered against the row above (`Up`), not the adaptive
/// filter, which tries five filters on every row and keeps the best: on the paper board's 47.8
/// Mpx map 45.6 MB against 44.7 MB, the same samples, written faster (`docs/board.md`,
/// thirteenth part), and undone on reading with one addition per byte (the line's pages read
/// kept maps).
pub fn save_png16_rows(
    path: &Path,
    width: usize,
    rows: usize,
    mut row: impl FnMut(usize, &mut [u16]),
) -> Result<(), FileError> {
    crate::files::write_atomic(path, |w| {
        let mut enc = png::Encoder::new(w, width as u32, rows as u32);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        enc.set_compression(png::Compression::Fast);
        enc.set_filter(png::Filter::Up);
        let mut writer = enc.write_header()?;
        let mut stream = writer.stream_writer()?;
        let (mut values, mut bytes) = (vec![0u16; width], vec![0u8; 2 * width]);
        for i in 0..rows {
            row(i, &mut values);
            for (b, v) in bytes.chunks_exact_mut(2).zip(&values) {
                b.copy_from_slice(&v.to_be_bytes());
            }
            std::io::Write::write_all(&mut stream, &bytes)?;
        }
        stream.finish()?;
        Ok::<(), png::EncodingError>(())
    })
}

/// Writes an 8-bit indexed PNG of `width x rows` atomically: `values` row-major, drawn
/// through `palette` (one colour per value; a value past its end is the last colour). A reader
/// that decodes to colours sees the palette's; one that reads the samples ([`read_png_indexed`],
/// or `PIL.Image.open(f)` without `convert`) gets the values.
pub fn save_png_indexed(
    path: &Path,
    width: u32,
    rows: u32,
    values: &[u8],
    palette: &[[u8; 3]],
) -> Result<(), FileError> {
    let flat: Vec<u8> = palette.iter().flatten().copied().collect();
    crate::files::write_atomic(path, |w| {
        let mut enc = png::Encoder::new(w, width, rows);
        enc.set_color(png::ColorType::Indexed);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_palette(flat);
        enc.set_compression(png::Compression::Fast);
        let mut writer = enc.write_header()?;
        writer.write_image_data(values)?;
        writer.finish()?;
        Ok::<(), png::EncodingError>(())
    })
}

/// The samples and palette of an 8-bit indexed PNG ([`save_png_indexed`]).
pub fn read_png_indexed(path: &Path) -> Result<(Vec<u8>, Vec<[u8; 3]>), png::DecodingError> {
    let file = std::io::BufReader::new(std::fs::File::open(path)?);
    let mut decoder = png::Decoder::new(file);
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info()?;
    let info = reader.info();
    if info.color_type != png::ColorType::Indexed || info.bit_depth != png::BitDepth::Eight {
        return Err(png::DecodingError::IoError(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "not an 8-bit indexed PNG",
        )));
    }
    let palette = info
        .palette
        .as_deref()
        .unwrap_or(&[])
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    let size = reader
        .output_buffer_size()
        .ok_or(png::DecodingError::LimitsExceeded)?;
    let mut buf = vec![0; size];
    let frame = reader.next_frame(&mut buf)?;
    buf.truncate(frame.buffer_size());
    Ok((buf, palette))
}

/// A perceptually ordered blue -> cyan -> green -> yellow -> red ramp, `t` in `[0, 1]`.
pub fn colour(t: f64) -> [u8; 3] {
    const STOPS: [[f64; 3]; 5] = [
        [0.19, 0.07, 0.60],
        [0.10, 0.60, 0.90],
        [0.30, 0.85, 0.35],
        [0.98, 0.85, 0.15],
        [0.85, 0.10, 0.10],
    ];
    let x = t * (STOPS.len() - 1) as f64;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f64;
    let mut out = [0u8; 3];
    for k in 0..3 {
        let v = STOPS[i][k] * (1.0 - f) + STOPS[i + 1][k] * f;
        out[k] = (v * 255.0).round() as u8;
    }
    out
}

/// The false-colour companion of a height PNG: `x.png` -> `x.colour.png`.
pub fn colour_path(png: &Path) -> std::path::PathBuf {
    png.with_extension("colour.png")
}

/// Writes `png` (16-bit heights) and `png` with `.colour.png` (false colour, -20..230 um).
pub fn write_pngs(map: &HeightMap, png: &Path) -> Result<std::path::PathBuf, PngError> {
    write_height_png(map, png)?;
    let colour = colour_path(png);
    write_false_colour_png(map, -20.0, 230.0, &colour)?;
    Ok(colour)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::heightmap::HeightRow;

    fn row(row: i64) -> HeightRow {
        HeightRow {
            row,
            latch: 0,
            flags: 0,
            heights: vec![10, 20],
            valid: vec![true, false],
        }
    }

    #[test]
    fn a_map_of_mostly_holes_is_refused_in_one_sentence() {
        let dir = tempfile::tempdir().unwrap();
        let png = dir.path().join("h.png");
        let mut map = HeightMap::new(2, 1.0);
        map.rows = vec![row(0), row(MAX_HOLE_ROWS as i64 + 2)];
        let e = write_pngs(&map, &png).unwrap_err();
        assert!(matches!(e, PngError::TooManyMissingRows { .. }), "{e:?}");
        assert_eq!(
            e.to_string(),
            "the rows span 65539 board rows (0 to 65538) but only 2 are present: more than \
             65536 missing rows (an encoder-fault gap?) cannot be drawn"
        );
        assert!(std::fs::read_dir(dir.path()).unwrap().next().is_none());
        // One hole fewer is drawn, the missing rows invalid (0).
        map.rows[1].row -= 1;
        write_pngs(&map, &png).unwrap();
        let img = image::open(&png).unwrap().into_luma16();
        assert_eq!(img.dimensions(), (2, MAX_HOLE_ROWS as u32 + 2));
        assert_eq!(img.get_pixel(0, 0).0, [10 + 32768]);
        assert_eq!(img.get_pixel(1, 0).0, [0]);
        assert_eq!(img.get_pixel(0, 1).0, [0]);
        // A file error passes through with its own sentence.
        let e = write_pngs(&map, dir.path()).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!("cannot write {}: it is a directory", dir.path().display())
        );
    }
}
