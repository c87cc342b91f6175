//! MJPEG frames as UVC cameras send them, made into standard JPEG files.
//!
//! A UVC camera may leave out the Huffman tables (the UVC spec makes DHT optional: decoders
//! are to assume the standard tables of ISO 10918-1 Annex K.3, as the OpenDML AVI spec says).
//! Many decoders only assume them when an `AVI1` APP0 marks the frame, and a recording of
//! such frames is no standard JPEG. [`standardize`] inserts the standard DHT before the scan
//! when a frame has none, before decoding and before recording. A frame cut short (the
//! driver handed over an incomplete buffer) lacks its end-of-image marker and is refused.

use std::borrow::Cow;

/// Why an MJPEG buffer is not a usable JPEG.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MjpegError {
    #[error("MJPG frame of {0} bytes does not start with a JPEG marker (FF D8)")]
    NotJpeg(usize),
    #[error("MJPG frame of {0} bytes has no end-of-image marker (FF D9): the frame is incomplete")]
    Truncated(usize),
    #[error("MJPG frame: a marker segment runs past the end of the frame at byte {0}")]
    BadSegment(usize),
}

/// Number of codes of each length 1…16, then the symbols: Annex K.3, tables K.3–K.6.
const DC_LUMA_BITS: [u8; 16] = [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0];
const DC_CHROMA_BITS: [u8; 16] = [0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0];
const DC_SYMBOLS: [u8; 12] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11];
const AC_LUMA_BITS: [u8; 16] = [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7D];
const AC_LUMA_SYMBOLS: [u8; 162] = [
    0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13, 0x51, 0x61, 0x07, 0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xA1, 0x08, 0x23, 0x42, 0xB1,
    0xC1, 0x15, 0x52, 0xD1, 0xF0, 0x24, 0x33, 0x62, 0x72, 0x82, 0x09, 0x0A, 0x16, 0x17, 0x18, 0x19, 0x1A, 0x25, 0x26, 0x27, 0x28, 0x29, 0x2A, 0x34, 0x35, 0x36, 0x37,
    0x38, 0x39, 0x3A, 0x43, 0x44, 0x45, 0x46, 0x47, 0x48, 0x49, 0x4A, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5A, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0x6A,
    0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7A, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8A, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9A, 0xA2, 0xA3,
    0xA4, 0xA5, 0xA6, 0xA7, 0xA8, 0xA9, 0xAA, 0xB2, 0xB3, 0xB4, 0xB5, 0xB6, 0xB7, 0xB8, 0xB9, 0xBA, 0xC2, 0xC3, 0xC4, 0xC5, 0xC6, 0xC7, 0xC8, 0xC9, 0xCA, 0xD2, 0xD3,
    0xD4, 0xD5, 0xD6, 0xD7, 0xD8, 0xD9, 0xDA, 0xE1, 0xE2, 0xE3, 0xE4, 0xE5, 0xE6, 0xE7, 0xE8, 0xE9, 0xEA, 0xF1, 0xF2, 0xF3, 0xF4, 0xF5, 0xF6, 0xF7, 0xF8, 0xF9, 0xFA,
];
const AC_CHROMA_BITS: [u8; 16] = [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77];
const AC_CHROMA_SYMBOLS: [u8; 162] = [
    0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51, 0x07, 0x61, 0x71, 0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xA1, 0xB1, 0xC1,
    0x09, 0x23, 0x33, 0x52, 0xF0, 0x15, 0x62, 0x72, 0xD1, 0x0A, 0x16, 0x24, 0x34, 0xE1, 0x25, 0xF1, 0x17, 0x18, 0x19, 0x1A, 0x26, 0x27, 0x28, 0x29, 0x2A, 0x35, 0x36,
    0x37, 0x38, 0x39, 0x3A, 0x43, 0x44, 0x45, 0x46, 0x47, 0x48, 0x49, 0x4A, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5A, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68, 0x69,
    0x6A, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7A, 0x82, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8A, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9A,
    0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7, 0xA8, 0xA9, 0xAA, 0xB2, 0xB3, 0xB4, 0xB5, 0xB6, 0xB7, 0xB8, 0xB9, 0xBA, 0xC2, 0xC3, 0xC4, 0xC5, 0xC6, 0xC7, 0xC8, 0xC9, 0xCA,
    0xD2, 0xD3, 0xD4, 0xD5, 0xD6, 0xD7, 0xD8, 0xD9, 0xDA, 0xE2, 0xE3, 0xE4, 0xE5, 0xE6, 0xE7, 0xE8, 0xE9, 0xEA, 0xF2, 0xF3, 0xF4, 0xF5, 0xF6, 0xF7, 0xF8, 0xF9, 0xFA,
];

/// The DHT segment of the four standard tables.
fn standard_dht() -> Vec<u8> {
    let tables: [(u8, &[u8], &[u8]); 4] =
        [(0x00, &DC_LUMA_BITS, &DC_SYMBOLS), (0x10, &AC_LUMA_BITS, &AC_LUMA_SYMBOLS), (0x01, &DC_CHROMA_BITS, &DC_SYMBOLS), (0x11, &AC_CHROMA_BITS, &AC_CHROMA_SYMBOLS)];
    let mut body = Vec::new();
    for (class_id, bits, symbols) in tables {
        debug_assert_eq!(bits.iter().map(|&b| b as usize).sum::<usize>(), symbols.len());
        body.push(class_id);
        body.extend_from_slice(bits);
        body.extend_from_slice(symbols);
    }
    let mut seg = vec![0xFF, 0xC4];
    seg.extend_from_slice(&((body.len() + 2) as u16).to_be_bytes());
    seg.extend(body);
    seg
}

/// The frame through its end-of-image marker (a camera may pad the buffer after it), or
/// why it is not a whole JPEG.
pub fn complete(bytes: &[u8]) -> Result<&[u8], MjpegError> {
    if bytes.len() < 4 || bytes[0] != 0xFF || bytes[1] != 0xD8 {
        return Err(MjpegError::NotJpeg(bytes.len()));
    }
    // Padding after EOI is zeros (or stale bytes); look from the end for the marker.
    match bytes.windows(2).rposition(|w| w == [0xFF, 0xD9]) {
        Some(i) if i >= 2 => Ok(&bytes[..i + 2]),
        _ => Err(MjpegError::Truncated(bytes.len())),
    }
}

/// `jpeg` with the standard Huffman tables inserted before its scan when it defines none.
pub fn standardize(jpeg: &[u8]) -> Result<Cow<'_, [u8]>, MjpegError> {
    let mut pos = 2;
    loop {
        // Markers may be padded with fill bytes (FF FF … FF xx).
        if pos + 1 >= jpeg.len() || jpeg[pos] != 0xFF {
            return Err(MjpegError::BadSegment(pos));
        }
        while pos + 1 < jpeg.len() && jpeg[pos + 1] == 0xFF {
            pos += 1;
        }
        let marker = jpeg.get(pos + 1).copied().ok_or(MjpegError::BadSegment(pos))?;
        match marker {
            0xC4 => return Ok(Cow::Borrowed(jpeg)),
            0xDA => {
                let mut out = Vec::with_capacity(jpeg.len() + 420);
                out.extend_from_slice(&jpeg[..pos]);
                out.extend(standard_dht());
                out.extend_from_slice(&jpeg[pos..]);
                return Ok(Cow::Owned(out));
            }
            0x01 | 0xD0..=0xD7 => pos += 2,
            _ => {
                let len = jpeg.get(pos + 2..pos + 4).map(|b| u16::from_be_bytes([b[0], b[1]]) as usize).ok_or(MjpegError::BadSegment(pos))?;
                if len < 2 || pos + 2 + len > jpeg.len() {
                    return Err(MjpegError::BadSegment(pos));
                }
                pos += 2 + len;
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A JPEG of a gradient, and the same with its DHT segments cut out (what a UVC camera
    /// may send).
    fn jpeg_and_stripped() -> (Vec<u8>, Vec<u8>) {
        let img = image::RgbImage::from_fn(32, 16, |x, y| image::Rgb([(x * 8) as u8, (y * 16) as u8, 90]));
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 85).encode_image(&img).unwrap();
        let stripped = without_dht(&jpeg);
        (jpeg, stripped)
    }

    /// `jpeg` with its DHT segments cut out.
    pub(crate) fn without_dht(jpeg: &[u8]) -> Vec<u8> {
        let mut stripped = jpeg[..2].to_vec();
        let mut pos = 2;
        loop {
            let marker = jpeg[pos + 1];
            if marker == 0xDA {
                stripped.extend_from_slice(&jpeg[pos..]);
                break;
            }
            let len = u16::from_be_bytes([jpeg[pos + 2], jpeg[pos + 3]]) as usize;
            if marker != 0xC4 {
                stripped.extend_from_slice(&jpeg[pos..pos + 2 + len]);
            }
            pos += 2 + len;
        }
        stripped
    }

    fn decode(bytes: &[u8]) -> Option<Vec<u8>> {
        image::load_from_memory_with_format(bytes, image::ImageFormat::Jpeg).ok().map(|i| i.to_rgb8().into_raw())
    }

    #[test]
    fn a_frame_without_huffman_tables_gets_the_standard_ones() {
        let (jpeg, stripped) = jpeg_and_stripped();
        assert!(stripped.len() < jpeg.len(), "the encoder wrote DHT segments");
        assert_ne!(decode(&stripped), decode(&jpeg), "without tables the frame does not decode as it should");
        let fixed = standardize(&stripped).unwrap();
        assert!(matches!(fixed, Cow::Owned(_)));
        // The encoder uses the standard tables, so the repaired frame decodes to the same pixels.
        assert_eq!(decode(&fixed), decode(&jpeg));
        assert!(decode(&jpeg).is_some());
        // A frame with its tables is left alone.
        assert!(matches!(standardize(&jpeg).unwrap(), Cow::Borrowed(_)));
    }

    #[test]
    fn an_incomplete_frame_is_refused_and_padding_is_trimmed() {
        let (jpeg, _) = jpeg_and_stripped();
        let mut padded = jpeg.clone();
        padded.extend_from_slice(&[0; 100]);
        assert_eq!(complete(&padded).unwrap(), &jpeg[..]);
        let cut = &jpeg[..jpeg.len() * 2 / 3];
        assert_eq!(complete(cut), Err(MjpegError::Truncated(cut.len())));
        assert_eq!(complete(&[0u8; 64]), Err(MjpegError::NotJpeg(64)));
    }
}
