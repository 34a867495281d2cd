//! Validation of uploaded images before they enter the queue: the format
//! from the bytes' signature (PNG or JPEG), the size from the header (an
//! oversized image is refused before anything is allocated for its pixels),
//! then the decode with allocation limits, off the async runtime.

use std::io::Cursor;

use image::{ImageFormat, ImageReader, Limits};

use super::error::ApiError;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;

/// Limits on an uploaded image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageLimits {
    /// Most pixels (width times height).
    pub max_pixels: usize,
    /// Longest side.
    pub max_side: u32,
}

impl Default for ImageLimits {
    fn default() -> Self {
        Self {
            max_pixels: 16_000_000,
            max_side: 16_384,
        }
    }
}

/// The media types an image may be sent as.
pub const IMAGE_TYPES: [&str; 2] = ["image/jpeg", "image/png"];

/// The size of an uploaded PNG or JPEG from its header alone (nothing is
/// allocated for its pixels), refusing it with the right error: 400 when
/// empty, 415 when neither PNG nor JPEG, 413 when the header declares more
/// pixels than allowed, 422 when the header cannot be read.
pub fn image_size(bytes: &[u8], limits: &ImageLimits) -> Result<(usize, usize), ApiError> {
    let format = image_format(bytes)?;
    header_size(bytes, format, limits)
}

/// PNG or JPEG, from the bytes' signature.
fn image_format(bytes: &[u8]) -> Result<ImageFormat, ApiError> {
    if bytes.is_empty() {
        return Err(ApiError::BadRequest("the request has no image".into()));
    }
    let format = image::guess_format(bytes)
        .map_err(|_| ApiError::Unprocessable("the body is not a PNG or JPEG image".into()))?;
    if !matches!(format, ImageFormat::Png | ImageFormat::Jpeg) {
        let name = format
            .extensions_str()
            .first()
            .map_or_else(|| "another format".to_string(), |e| e.to_uppercase());
        return Err(ApiError::UnsupportedMediaType(format!(
            "images must be PNG or JPEG; this one is {name}"
        )));
    }
    Ok(format)
}

/// The size the header declares, checked against `limits`.
fn header_size(
    bytes: &[u8],
    format: ImageFormat,
    limits: &ImageLimits,
) -> Result<(usize, usize), ApiError> {
    let (w, h) = ImageReader::with_format(Cursor::new(bytes), format)
        .into_dimensions()
        .map_err(|e| ApiError::Unprocessable(format!("cannot read the image header: {e}")))?;
    if w == 0 || h == 0 {
        return Err(ApiError::Unprocessable(format!(
            "the image is empty ({w}x{h})"
        )));
    }
    if w > limits.max_side
        || h > limits.max_side
        || (w as u64) * (h as u64) > limits.max_pixels as u64
    {
        return Err(ApiError::PayloadTooLarge(format!(
            "the image is {w}x{h}; at most {} pixels and {} per side are accepted",
            limits.max_pixels, limits.max_side
        )));
    }
    Ok((w as usize, h as usize))
}

/// Decodes an uploaded PNG or JPEG into an RGB image, refusing it with the
/// right error: 400 when empty, 415 when neither PNG nor JPEG, 413 when the
/// header declares more pixels than allowed, 422 when it cannot be decoded.
/// The pixels are taken as stored: an EXIF orientation is not applied.
pub fn decode(bytes: &[u8], limits: &ImageLimits) -> Result<ColorImage, ApiError> {
    let format = image_format(bytes)?;
    let reader = |bytes| {
        let mut r = ImageReader::with_format(Cursor::new(bytes), format);
        let mut l = Limits::default();
        l.max_image_width = Some(limits.max_side);
        l.max_image_height = Some(limits.max_side);
        // Room for the decoded RGBA buffer of the largest allowed image.
        l.max_alloc = Some((limits.max_pixels as u64).saturating_mul(4) + (1 << 20));
        r.limits(l);
        r
    };
    // The header alone first: nothing is allocated for pixels.
    header_size(bytes, format, limits)?;
    if format == ImageFormat::Jpeg && !jpeg_is_complete(bytes) {
        // The decoder fills a truncated scan with grey; refuse it instead.
        return Err(ApiError::Unprocessable(
            "the JPEG is truncated (no end-of-image marker after its last scan)".into(),
        ));
    }
    let img = reader(bytes).decode().map_err(|e| match e {
        image::ImageError::Limits(_) => {
            ApiError::PayloadTooLarge(format!("the image needs too much memory: {e}"))
        }
        _ => ApiError::Unprocessable(format!("cannot decode the image: {e}")),
    })?;
    ColorImage::from_rgb8(&img.to_rgb8()).map_err(|e| ApiError::Unprocessable(e.to_string()))
}

/// The PNG signature.
const PNG_SIGNATURE: &[u8] = b"\x89PNG\r\n\x1a\n";

fn mask_error(e: impl std::fmt::Display) -> ApiError {
    ApiError::Unprocessable(format!("mask: cannot read the PNG: {e}"))
}

/// The size of a visibility mask from its PNG header alone: 422 when it
/// is not a PNG, 413 when it declares more pixels than allowed.
pub fn mask_size(bytes: &[u8], limits: &ImageLimits) -> Result<(usize, usize), ApiError> {
    if !bytes.starts_with(PNG_SIGNATURE) {
        return Err(ApiError::Unprocessable("the mask must be a PNG".into()));
    }
    header_size(bytes, ImageFormat::Png, limits).map_err(|e| match e {
        ApiError::PayloadTooLarge(m) => ApiError::PayloadTooLarge(format!("mask: {m}")),
        other => ApiError::Unprocessable(format!("mask: {other}")),
    })
}

/// Decodes a visibility mask of `expected` size (checked from the header,
/// before any pixel is decoded): a PNG whose pixels are visible where a
/// stored value is non-zero: the grey level or any colour channel at its
/// own depth (a 16-bit 1 counts), the index of a palette PNG (whatever
/// colour the palette gives it); a fully transparent pixel (alpha 0) is
/// hidden. Anything that is not a decodable PNG is 422 (413 when its
/// header declares too many pixels).
pub fn decode_mask(
    bytes: &[u8],
    limits: &ImageLimits,
    expected: Option<(usize, usize)>,
) -> Result<Mask, ApiError> {
    let (w, h) = mask_size(bytes, limits)?;
    if let Some((ew, eh)) = expected {
        if (w, h) != (ew, eh) {
            return Err(ApiError::Unprocessable(format!(
                "the mask is {w}x{h}, the image {ew}x{eh}: send a mask of the image's size"
            )));
        }
    }
    let mut decoder = png::Decoder::new(Cursor::new(bytes));
    // The stored values: no palette expansion, no scaling of bit depths.
    decoder.set_transformations(png::Transformations::IDENTITY);
    decoder.set_limits(png::Limits {
        bytes: limits.max_pixels.saturating_mul(8) + (1 << 20),
    });
    let mut reader = decoder.read_info().map_err(mask_error)?;
    let (colour, depth) = reader.output_color_type();
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| mask_error("the image is too large"))?;
    let mut buf = vec![0u8; size];
    let frame = reader.next_frame(&mut buf).map_err(mask_error)?;
    let line = frame.line_size;
    let bits = depth as usize;
    let (channels, alpha) = match colour {
        png::ColorType::Grayscale | png::ColorType::Indexed => (1, false),
        png::ColorType::GrayscaleAlpha => (2, true),
        png::ColorType::Rgb => (3, false),
        png::ColorType::Rgba => (4, true),
    };
    // Sample `k` of a row, at its own depth.
    let sample = |row: &[u8], k: usize| -> u16 {
        match bits {
            16 => u16::from_be_bytes([row[2 * k], row[2 * k + 1]]),
            8 => u16::from(row[k]),
            b => {
                let bit = k * b;
                let byte = row[bit / 8];
                let shift = 8 - b - bit % 8;
                u16::from((byte >> shift) & ((1u8 << b) - 1))
            }
        }
    };
    // A tRNS chunk makes pixels transparent without an alpha channel: a
    // palette index whose alpha is 0, or the one grey level or colour it
    // names (stored values at the image's depth; the decoder keeps one
    // byte per channel below 16 bits, two big-endian at 16).
    let trns = reader.info().trns.as_deref().map(<[u8]>::to_vec);
    let keyed = |t: &[u8], c: usize| -> Option<u16> {
        if bits == 16 {
            t.get(2 * c..2 * c + 2)
                .map(|b| u16::from_be_bytes([b[0], b[1]]))
        } else {
            t.get(c).map(|&b| u16::from(b))
        }
    };
    let transparent = |row: &[u8], first: usize| -> bool {
        let Some(t) = trns.as_deref() else {
            return false;
        };
        match colour {
            png::ColorType::Indexed => t.get(usize::from(sample(row, first))) == Some(&0),
            png::ColorType::Grayscale => keyed(t, 0) == Some(sample(row, first)),
            png::ColorType::Rgb => (0..3).all(|c| keyed(t, c) == Some(sample(row, first + c))),
            _ => false,
        }
    };
    let mut mask = Mask::new(w, h);
    for y in 0..h {
        let row = &buf[y * line..(y + 1) * line];
        for x in 0..w {
            let first = x * channels;
            let colours = if alpha { channels - 1 } else { channels };
            let opaque = if alpha {
                sample(row, first + channels - 1) != 0
            } else {
                !transparent(row, first)
            };
            if opaque && (0..colours).any(|c| sample(row, first + c) != 0) {
                mask.set(x, y, true);
            }
        }
    }
    Ok(mask)
}

/// Whether a JPEG has an end-of-image marker (`FF D9`) after the start of
/// its last scan (`FF DA`): a file cut in its entropy-coded data has not.
/// Data after the end-of-image marker (as some cameras append) is allowed.
fn jpeg_is_complete(bytes: &[u8]) -> bool {
    let last = |m: u8| bytes.windows(2).rposition(|w| w == [0xFF, m]);
    match (last(0xDA), last(0xD9)) {
        (Some(sos), Some(eoi)) => eoi > sos,
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png(w: u32, h: u32) -> Vec<u8> {
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([x as u8, y as u8, 7]));
        let mut out = Vec::new();
        img.write_to(&mut Cursor::new(&mut out), ImageFormat::Png)
            .unwrap();
        out
    }

    #[test]
    fn decodes_png_and_jpeg() {
        let p = png(20, 10);
        let img = decode(&p, &ImageLimits::default()).unwrap();
        assert_eq!((img.width(), img.height()), (20, 10));
        let rgb = image::RgbImage::from_fn(16, 8, |x, _| image::Rgb([x as u8 * 10, 0, 0]));
        let mut j = Vec::new();
        rgb.write_to(&mut Cursor::new(&mut j), ImageFormat::Jpeg)
            .unwrap();
        let img = decode(&j, &ImageLimits::default()).unwrap();
        assert_eq!((img.width(), img.height()), (16, 8));
    }

    #[test]
    fn refuses_bad_input_with_the_right_error() {
        let limits = ImageLimits {
            max_pixels: 100,
            max_side: 50,
        };
        assert!(matches!(decode(&[], &limits), Err(ApiError::BadRequest(_))));
        assert!(matches!(
            decode(b"definitely not an image", &limits),
            Err(ApiError::Unprocessable(_))
        ));
        assert!(matches!(
            decode(&png(20, 10), &limits),
            Err(ApiError::PayloadTooLarge(_))
        ));
        let mut gif = b"GIF89a".to_vec();
        gif.extend([0u8; 20]);
        assert!(matches!(
            decode(&gif, &limits),
            Err(ApiError::UnsupportedMediaType(_))
        ));
        let p = png(8, 8);
        assert!(matches!(
            decode(&p[..p.len() / 2], &ImageLimits::default()),
            Err(ApiError::Unprocessable(_))
        ));
        let rgb = image::RgbImage::from_fn(64, 64, |x, y| image::Rgb([x as u8 * 3, y as u8, 9]));
        let mut j = Vec::new();
        rgb.write_to(&mut Cursor::new(&mut j), ImageFormat::Jpeg)
            .unwrap();
        assert!(decode(&j, &ImageLimits::default()).is_ok());
        let mut trailing = j.clone();
        trailing.extend_from_slice(b"appended by a camera");
        assert!(decode(&trailing, &ImageLimits::default()).is_ok());
        assert!(matches!(
            decode(&j[..j.len() * 2 / 3], &ImageLimits::default()),
            Err(ApiError::Unprocessable(_))
        ));
    }

    #[test]
    fn masks_are_non_zero_pixels_of_a_png() {
        let img = image::GrayImage::from_fn(6, 4, |x, y| image::Luma([u8::from(x > y) * 255]));
        let mut p = Vec::new();
        img.write_to(&mut Cursor::new(&mut p), ImageFormat::Png)
            .unwrap();
        let m = decode_mask(&p, &ImageLimits::default(), Some((6, 4))).unwrap();
        assert_eq!((m.width, m.height), (6, 4));
        for y in 0..4 {
            for x in 0..6 {
                assert_eq!(m.get(x, y), x > y, "({x}, {y})");
            }
        }
        let rgb = image::RgbImage::from_fn(8, 8, |_, _| image::Rgb([9, 9, 9]));
        let mut j = Vec::new();
        rgb.write_to(&mut Cursor::new(&mut j), ImageFormat::Jpeg)
            .unwrap();
        for bad in [&j[..], &p[..p.len() / 2], b"not a mask"] {
            assert!(matches!(
                decode_mask(bad, &ImageLimits::default(), None),
                Err(ApiError::Unprocessable(_))
            ));
        }
    }

    /// An 8x1 PNG of `colour` with stored `data`, a palette and a tRNS
    /// chunk when given.
    fn keyed_png(
        colour: png::ColorType,
        data: &[u8],
        palette: Option<Vec<u8>>,
        trns: &[u8],
    ) -> Vec<u8> {
        let mut out = Vec::new();
        let mut e = png::Encoder::new(&mut out, 8, 1);
        e.set_color(colour);
        e.set_depth(png::BitDepth::Eight);
        if let Some(p) = palette {
            e.set_palette(p);
        }
        e.set_trns(trns.to_vec());
        let mut w = e.write_header().unwrap();
        w.write_image_data(data).unwrap();
        w.finish().unwrap();
        out
    }

    #[test]
    fn a_trns_chunk_hides_what_it_makes_transparent() {
        let limits = ImageLimits::default();
        let row = |m: &Mask| (0..8).map(|x| m.get(x, 0)).collect::<Vec<_>>();
        // Palette: index 2 fully transparent, index 1 half.
        let palette = keyed_png(
            png::ColorType::Indexed,
            &[0, 1, 2, 1, 2, 0, 1, 2],
            Some(vec![0; 9]),
            &[255, 128, 0],
        );
        // Grey: level 7 is transparent.
        let grey = keyed_png(
            png::ColorType::Grayscale,
            &[0, 1, 7, 1, 7, 0, 1, 7],
            None,
            &[0, 7],
        );
        // RGB: (0, 7, 0) is transparent; (0, 7, 1) is not.
        let rgb_data: Vec<u8> = [0u8, 1, 2, 1, 2, 0, 1, 2]
            .iter()
            .flat_map(|&k| match k {
                0 => [0, 0, 0],
                1 => [0, 7, 1],
                _ => [0, 7, 0],
            })
            .collect();
        let rgb = keyed_png(png::ColorType::Rgb, &rgb_data, None, &[0, 0, 0, 7, 0, 0]);
        let want = vec![false, true, false, true, false, false, true, false];
        for (what, bytes) in [("palette", palette), ("grey", grey), ("rgb", rgb)] {
            let m = decode_mask(&bytes, &limits, Some((8, 1))).unwrap();
            assert_eq!(row(&m), want, "{what}");
        }
    }
}
