//! Foreground segmentation against a uniform (blue) background, as in the paper's set-up.
//!
//! The key test works in normalised chromaticity `(r, g) = (R, G) / (R + G + B)`: shading and
//! exposure scale all three channels alike and leave chromaticity unchanged, so a shadowed
//! part of the screen is still the screen. Pixels too dark for a stable chromaticity are
//! decided by the optional background plate (an image of the empty scene), else kept as
//! foreground (losing object pixels is worse than keeping a little screen). The mask is then
//! cleaned by a morphological opening (removes specks) and closing (fills pinholes).
//!
//! The screen's colour is found in each frame by default ([`KeyColour::Auto`]): the most
//! common chromaticity of the image's border, where a turntable scene shows the screen, so
//! that a lab's own blue (or green) screen is keyed without being measured first. Where the
//! border shows no coloured screen — grey cameras, a white, grey or black backdrop — a plain
//! backdrop is keyed by its lack of texture instead ([`backdrop`]); where the border is not
//! plain either (an object filling the view, a cluttered room) the default key colour is
//! used. Where a colour's mask reaches the image's edge (a grey floor or turntable the colour
//! leaves), its plain regions are keyed out by texture too. [`KeyUsed`] says which a frame got.

pub mod backdrop;

/// Which colour the screen is keyed by.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum KeyColour {
    /// Found in each frame ([`ChromaKey::key_of`]); where the frame's border shows no
    /// coloured screen, a plain backdrop keyed by texture ([`backdrop`]), else
    /// [`DEFAULT_KEY_RGB`].
    Auto,
    /// This colour, RGB.
    Rgb([u8; 3]),
}

impl std::fmt::Display for KeyColour {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            KeyColour::Auto => f.write_str("auto"),
            KeyColour::Rgb([r, g, b]) => write!(f, "{r},{g},{b}"),
        }
    }
}

/// A key colour that is not `auto` or `R,G,B`.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("`{0}` is not a key colour: expected `auto` or R,G,B with three numbers 0…255, e.g. 40,70,190")]
pub struct BadKeyColour(String);

impl std::str::FromStr for KeyColour {
    type Err = BadKeyColour;

    fn from_str(s: &str) -> Result<KeyColour, BadKeyColour> {
        if s.trim().eq_ignore_ascii_case("auto") {
            return Ok(KeyColour::Auto);
        }
        let err = || BadKeyColour(s.to_string());
        let parts: Vec<&str> = s.split(',').map(str::trim).collect();
        if parts.len() != 3 {
            return Err(err());
        }
        let mut rgb = [0u8; 3];
        for (c, p) in rgb.iter_mut().zip(parts) {
            *c = p.parse().map_err(|_| err())?;
        }
        Ok(KeyColour::Rgb(rgb))
    }
}

/// The simulated lab's screen colour, and the key where [`KeyColour::Auto`] finds neither a
/// coloured screen nor a plain backdrop.
pub const DEFAULT_KEY_RGB: [u8; 3] = [40, 70, 190];

/// What a frame whose border showed neither a coloured screen nor a plain backdrop is
/// segmented by, in words (from [`AUTO_MIN_SHARE`] and [`DEFAULT_KEY_RGB`]).
pub fn no_screen() -> String {
    format!("no coloured screen or plain backdrop in the border of the left image (an object or a textured background over more than {:.0} % of the border): keyed by the default colour {}", (1.0 - AUTO_MIN_SHARE) * 100.0, KeyColour::Rgb(DEFAULT_KEY_RGB))
}

/// What a frame whose border showed no coloured screen but a plain backdrop is segmented by,
/// in words, with its texture threshold (grey levels).
pub fn plain_backdrop(threshold: f32) -> String {
    format!("no coloured screen in the border of the left image: keyed as a plain backdrop, the untextured regions (standard deviation under {threshold:.1} grey levels over 5 × 5 pixels) that reach the image's edge or cover {:.1} % of it; where a coloured screen is in view, give its colour (`--key-color R,G,B`), or give a background plate (`--plate`) if the views lose plain parts of the object", backdrop::LARGE_SHARE * 100.0)
}

/// Share of a frame's border pixels that the colour [`KeyColour::Auto`] found must key out
/// for it to be taken as the screen's.
pub const AUTO_MIN_SHARE: f32 = 0.3;

/// Share of a mask's edge (its outermost pixels) kept as object from which a frame is said to
/// hold more than the object ([`object_on_edge`]). An object scanned whole stays inside the
/// view: its mask leaves the edge clear (0 on the simulated lab's recordings); a grey floor
/// or turntable the key leaves covered 44 % of it.
pub const EDGE_WARN_SHARE: f32 = 0.05;

/// The share (0…1) of the outermost pixels of a `w` × `h` mask (255 = object) that are object.
pub fn edge_share(mask: &[u8], w: usize, h: usize) -> f32 {
    if w == 0 || h == 0 || mask.len() != w * h {
        return 0.0;
    }
    let (mut object, mut n) = (0, 0);
    for (y, row) in mask.chunks_exact(w).enumerate() {
        if y == 0 || y == h - 1 {
            object += row.iter().filter(|&&m| m != 0).count();
            n += w;
        } else {
            object += (row[0] != 0) as usize + (w > 1 && row[w - 1] != 0) as usize;
            n += 1 + (w > 1) as usize;
        }
    }
    object as f32 / n as f32
}

/// What a frame whose mask covers `share` of the image's edge holds, in words.
pub fn object_on_edge(share: f32) -> String {
    format!("{:.0} % of the left image's edge is kept as object (at most {:.0} % expected of an object in full view): part of the scene the key leaves — a turntable or floor not in the screen's colour — is matched and enters the views, or the object leaves the view", share * 100.0, EDGE_WARN_SHARE * 100.0)
}

/// The key a frame is segmented with, and where it came from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyUsed {
    /// Its chromaticity `(R, G) / (R + G + B)`.
    pub chroma: (f32, f32),
    pub source: KeySource,
    /// Where the colour's mask reached the image's edge ([`EDGE_WARN_SHARE`]: a grey floor or
    /// turntable the colour leaves), the plain regions were keyed out too
    /// ([`backdrop::key_within`]), by texture under this threshold (grey levels).
    pub plain_edge: Option<f32>,
}

/// Where a frame's key colour came from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum KeySource {
    /// The colour given ([`KeyColour::Rgb`]).
    Given,
    /// Found in the frame's border, which it keys out to this share (0…1).
    Found { border_share: f32 },
    /// [`KeyColour::Auto`] found no coloured screen in the border, but a plain backdrop
    /// over this share (0…1) of it, keyed by texture below `threshold` grey levels
    /// ([`backdrop`]).
    Backdrop { border_share: f32, threshold: f32 },
    /// [`KeyColour::Auto`] found neither a coloured screen nor a plain backdrop in the
    /// border: [`DEFAULT_KEY_RGB`].
    NotFound,
}

/// Chroma-key settings.
#[derive(Debug, Clone, PartialEq)]
pub struct ChromaKey {
    /// The background colour.
    pub key: KeyColour,
    /// Largest chromaticity distance from the key still counted as background (0…1).
    pub tolerance: f32,
    /// Pixels whose R + G + B is below this are too dark to key by colour.
    pub dark_level: u16,
    /// With a plate: a pixel within this many grey levels (every channel) of the plate is
    /// background.
    pub plate_tolerance: u8,
    /// Radius in pixels of the square opening (0 disables).
    pub open_radius: usize,
    /// Radius in pixels of the square closing (0 disables).
    pub close_radius: usize,
    /// The points of the pixels within this many pixels of the mask's edge (the object's
    /// silhouette; the image's edge does not count) are left out of what a scan fuses, and
    /// kept for its registration ([`inside_rim`]; 0 fuses them). Applied after matching, by
    /// the pipeline: the search itself covers the mask.
    pub rim_px: usize,
}

impl Default for ChromaKey {
    fn default() -> Self {
        ChromaKey { key: KeyColour::Auto, tolerance: 0.12, dark_level: 60, plate_tolerance: 20, open_radius: 1, close_radius: 2, rim_px: DEFAULT_RIM_PX }
    }
}

/// Why segmentation could not run.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SegmentError {
    #[error("background plate is {0}×{1} but the image is {2}×{3}")]
    PlateSize(usize, usize, usize, usize),
    #[error("image buffer holds {0} bytes, expected {1} (width × height × 3)")]
    Buffer(usize, usize),
    #[error("chroma-key tolerance must be within 0…1, got {0}")]
    Tolerance(f32),
}

/// The colour test's terms: the key's chromaticity, the squared tolerance, the dark level.
struct Key {
    chroma: (f32, f32),
    tol2: f32,
    dark_level: u16,
}

/// The colour test, pixel by pixel: 0 where a pixel is bright enough and its chromaticity
/// lies within the tolerance of the key's, or where it is black (0, 0, 0: no light, as a
/// rectified image is where it maps outside the camera's; nothing there to match), 255
/// elsewhere. Branch-free per pixel: a pixel of sum 0 has no chromaticity (its ratios are
/// NaN, which fails the colour test).
fn key_portable(key: &Key, rgb: &[u8], mask: &mut [u8]) {
    for (m, px) in mask.iter_mut().zip(rgb.chunks_exact(3)) {
        let (r, g, b) = (px[0] as f32, px[1] as f32, px[2] as f32);
        let s = r + g + b;
        let bright = px[0] as u16 + px[1] as u16 + px[2] as u16 >= key.dark_level;
        let (dr, dg) = (r / s - key.chroma.0, g / s - key.chroma.1);
        let keyed = (bright & (s > 0.0) & (dr * dr + dg * dg <= key.tol2)) | (s == 0.0);
        *m = if keyed { 0 } else { 255 };
    }
}

/// [`key_portable`] eight pixels at a time: the 24 bytes split into their channels by one
/// permute and three shuffles, then the same float operations in the same order (no fused
/// multiply-add), so the same mask. Returns the pixels it did: it stops where its 32-byte
/// loads would run past `rgb`.
///
/// # Safety
/// The CPU has AVX2; `rgb` holds at least `3 · mask.len()` bytes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn key_avx2(key: &Key, rgb: &[u8], mask: &mut [u8]) -> usize {
    use std::arch::x86_64::*;
    assert!(rgb.len() >= 3 * mask.len());
    // Pixels 0–3 (bytes 0–11) into the low lane, 4–7 (bytes 12–23) into the high one, then
    // each channel's byte of the lane's four pixels into 32-bit lanes.
    let halves = _mm256_setr_epi32(0, 1, 2, 0, 3, 4, 5, 0);
    let channel = |c: i8| _mm256_setr_epi8(c, -1, -1, -1, c + 3, -1, -1, -1, c + 6, -1, -1, -1, c + 9, -1, -1, -1, c, -1, -1, -1, c + 3, -1, -1, -1, c + 6, -1, -1, -1, c + 9, -1, -1, -1);
    let (red, green, blue) = (channel(0), channel(1), channel(2));
    let (k0, k1, tol2) = (_mm256_set1_ps(key.chroma.0), _mm256_set1_ps(key.chroma.1), _mm256_set1_ps(key.tol2));
    let dark = _mm256_set1_epi32(key.dark_level as i32 - 1);
    let zero = _mm256_setzero_ps();
    // 32 bytes read from 3i: the last group of eight ends 8 bytes before `rgb` does.
    let groups = (rgb.len().saturating_sub(8) / 3).min(mask.len()) / 8;
    for k in 0..groups {
        let i = 8 * k;
        // SAFETY: 3i + 32 ≤ 3 · 8 · groups + 8 ≤ rgb.len().
        let bytes = _mm256_permutevar8x32_epi32(unsafe { _mm256_loadu_si256(rgb.as_ptr().add(3 * i) as *const __m256i) }, halves);
        let (ri, gi, bi) = (_mm256_shuffle_epi8(bytes, red), _mm256_shuffle_epi8(bytes, green), _mm256_shuffle_epi8(bytes, blue));
        let bright = _mm256_cmpgt_epi32(_mm256_add_epi32(_mm256_add_epi32(ri, gi), bi), dark);
        let (r, g, b) = (_mm256_cvtepi32_ps(ri), _mm256_cvtepi32_ps(gi), _mm256_cvtepi32_ps(bi));
        let s = _mm256_add_ps(_mm256_add_ps(r, g), b);
        let dr = _mm256_sub_ps(_mm256_div_ps(r, s), k0);
        let dg = _mm256_sub_ps(_mm256_div_ps(g, s), k1);
        let near = _mm256_cmp_ps::<_CMP_LE_OQ>(_mm256_add_ps(_mm256_mul_ps(dr, dr), _mm256_mul_ps(dg, dg)), tol2);
        let lit = _mm256_cmp_ps::<_CMP_GT_OQ>(s, zero);
        let black = _mm256_cmp_ps::<_CMP_EQ_OQ>(s, zero);
        let keyed = _mm256_or_si256(_mm256_and_si256(bright, _mm256_castps_si256(_mm256_and_ps(near, lit))), _mm256_castps_si256(black));
        // 255 where not keyed: the lanes' 32-bit masks narrowed to bytes.
        let m = _mm256_andnot_si256(keyed, _mm256_set1_epi32(-1));
        let m = _mm256_packs_epi16(_mm256_packs_epi32(m, m), _mm256_setzero_si256());
        let (lo, hi) = (_mm_cvtsi128_si32(_mm256_castsi256_si128(m)), _mm_cvtsi128_si32(_mm256_extracti128_si256::<1>(m)));
        mask[i..i + 4].copy_from_slice(&lo.to_le_bytes());
        mask[i + 4..i + 8].copy_from_slice(&hi.to_le_bytes());
    }
    8 * groups
}

fn chromaticity(p: &[u8]) -> Option<(f32, f32)> {
    let s = p[0] as f32 + p[1] as f32 + p[2] as f32;
    (s > 0.0).then(|| (p[0] as f32 / s, p[1] as f32 / s))
}

/// The pixels of an RGB image's border that hold the scene ([`backdrop::lit_border`]): how
/// many there are, and the chromaticities of the bright ones. None where too few do.
fn border_chromaticities(rgb: &[u8], w: usize, h: usize, dark_level: u16) -> Option<(usize, Vec<(f32, f32)>)> {
    let at = backdrop::lit_border(rgb, w, h)?;
    let bright = |px: &&[u8]| px[0] as u16 + px[1] as u16 + px[2] as u16 >= dark_level;
    let chroma = at.iter().map(|&i| &rgb[3 * i..3 * i + 3]).filter(bright).filter_map(chromaticity).collect();
    Some((at.len(), chroma))
}

/// The screen's chromaticity in an RGB image, and the share of the border's pixels within
/// `tolerance` of it: the most common chromaticity (bins of 1/32) among the bright pixels of
/// the border — a ring of a sixteenth of the smaller side, on a grid of an eighth of that,
/// its black pixels (outside a rectified image) left out — refined to the mean of those
/// within half the tolerance of it. Only blue or green colours away from grey count (red not
/// the strongest channel; farther than the tolerance from grey), as screens are: keying a
/// grey or brown border would take out an object of that colour. None where no such colour
/// keys out [`AUTO_MIN_SHARE`] of the border, or where too little of the border is lit.
fn find_screen(rgb: &[u8], w: usize, h: usize, dark_level: u16, tolerance: f32) -> Option<((f32, f32), f32)> {
    const BINS: usize = 32;
    // (About 7 000 pixels of a 640 × 480 frame's border: plenty for the histogram.)
    let (all, chroma) = border_chromaticities(rgb, w, h, dark_level)?;
    let bin = |(r, g): (f32, f32)| ((r * BINS as f32) as usize).min(BINS - 1) * BINS + ((g * BINS as f32) as usize).min(BINS - 1);
    let mut hist = vec![(0u32, 0.0f64, 0.0f64); BINS * BINS];
    for &c in &chroma {
        let e = &mut hist[bin(c)];
        *e = (e.0 + 1, e.1 + c.0 as f64, e.2 + c.1 as f64);
    }
    let within = |centre: (f32, f32), tol: f32| {
        move |&&(r, g): &&(f32, f32)| {
            let (dr, dg) = (r - centre.0, g - centre.1);
            dr * dr + dg * dg <= tol * tol
        }
    };
    // A screen is blue or green (red is not its strongest channel) and not grey: keying a
    // grey, brown or skin-coloured border would key out an object of that colour.
    let grey = (1.0 / 3.0, 1.0 / 3.0);
    let screen_like = |c: (f32, f32)| c.0 < c.1.max(1.0 - c.0 - c.1) && !within(grey, tolerance)(&&c);
    let mean = |e: (u32, f64, f64)| ((e.1 / e.0 as f64) as f32, (e.2 / e.0 as f64) as f32);
    // The fullest such bin (the first of equals).
    let peak = hist.iter().filter(|e| e.0 > 0 && screen_like(mean(**e))).fold((0u32, 0.0, 0.0), |best, &e| if e.0 > best.0 { e } else { best });
    if peak.0 == 0 {
        return None;
    }
    let peak = mean(peak);
    let near: Vec<&(f32, f32)> = chroma.iter().filter(within(peak, tolerance / 2.0)).collect();
    let centre = if near.is_empty() { peak } else { (near.iter().map(|c| c.0).sum::<f32>() / near.len() as f32, near.iter().map(|c| c.1).sum::<f32>() / near.len() as f32) };
    let share = chroma.iter().filter(within(centre, tolerance)).count() as f32 / all as f32;
    (share >= AUTO_MIN_SHARE && screen_like(centre)).then_some((centre, share))
}

impl KeyUsed {
    /// A frame's `segmentation` entry in `report.json`: which key it was keyed by (the colour
    /// `given`, one `found` in the frame's border, a plain `backdrop` keyed by texture where
    /// no coloured screen was found, or the `default` colour where neither was), its
    /// chromaticity, the share of the border it keyed out where it was found, the texture
    /// threshold of a backdrop or of the plain regions keyed beyond a colour
    /// (`plain_edge_keyed`), and `edge`, the share of the image's edge the mask kept as
    /// object ([`edge_share`]).
    pub fn report_entry(&self, edge: f32) -> serde_json::Value {
        let (key, share, threshold) = match self.source {
            KeySource::Given => ("given", None, self.plain_edge),
            KeySource::Found { border_share } => ("found", Some(border_share), self.plain_edge),
            KeySource::Backdrop { border_share, threshold } => ("backdrop", Some(border_share), Some(threshold)),
            KeySource::NotFound => ("default", None, None),
        };
        serde_json::json!({"key": key, "chromaticity": [self.chroma.0, self.chroma.1], "border_share": share, "texture_threshold": threshold, "plain_edge_keyed": self.plain_edge.is_some(), "edge_object_share": edge})
    }
}

impl ChromaKey {
    /// The colour key an interleaved RGB image is segmented with: the colour given, or the
    /// one [`KeyColour::Auto`] finds in the image's border (else [`KeySource::NotFound`],
    /// where [`ChromaKey::segment_keyed`] looks for a plain backdrop).
    pub fn key_of(&self, rgb: &[u8], width: usize, height: usize) -> KeyUsed {
        match self.key {
            KeyColour::Rgb(c) => KeyUsed { chroma: chromaticity(&c).unwrap_or((0.0, 0.0)), source: KeySource::Given, plain_edge: None },
            KeyColour::Auto => match find_screen(rgb, width, height, self.dark_level, self.tolerance) {
                Some((chroma, border_share)) => KeyUsed { chroma, source: KeySource::Found { border_share }, plain_edge: None },
                None => KeyUsed { chroma: chromaticity(&DEFAULT_KEY_RGB).expect("a colour, not black"), source: KeySource::NotFound, plain_edge: None },
            },
        }
    }

    /// Segments an interleaved RGB image: 255 = object, 0 = background.
    pub fn segment(&self, rgb: &[u8], width: usize, height: usize, plate: Option<&[u8]>) -> Result<Vec<u8>, SegmentError> {
        self.segment_keyed(rgb, width, height, plate).map(|(mask, _)| mask)
    }

    /// [`ChromaKey::segment`], with the key it used: [`ChromaKey::key_of`]'s colour, or, where
    /// [`KeyColour::Auto`] found no coloured screen, a plain backdrop ([`backdrop::key`]).
    pub fn segment_keyed(&self, rgb: &[u8], width: usize, height: usize, plate: Option<&[u8]>) -> Result<(Vec<u8>, KeyUsed), SegmentError> {
        if rgb.len() != width * height * 3 {
            return Err(SegmentError::Buffer(rgb.len(), width * height * 3));
        }
        if !(0.0..=1.0).contains(&self.tolerance) {
            return Err(SegmentError::Tolerance(self.tolerance));
        }
        if let Some(p) = plate {
            if p.len() != rgb.len() {
                let n = p.len() / 3;
                return Err(SegmentError::PlateSize(n / height.max(1), height, width, height));
            }
        }
        let mut used = self.key_of(rgb, width, height);
        let backdrop = if used.source == KeySource::NotFound { backdrop::key(rgb, width, height) } else { None };
        let mut mask = match backdrop {
            Some((mask, b)) => {
                used = KeyUsed { chroma: b.chroma, source: KeySource::Backdrop { border_share: b.border_share, threshold: b.threshold }, plain_edge: None };
                mask
            }
            None => {
                let key = Key { chroma: used.chroma, tol2: self.tolerance * self.tolerance, dark_level: self.dark_level };
                let mut mask = vec![0u8; width * height];
                let mut done = 0;
                #[cfg(target_arch = "x86_64")]
                if std::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2 (checked just above); `rgb` holds 3 bytes per
                    // mask pixel (checked at the top).
                    done = unsafe { key_avx2(&key, rgb, &mut mask) };
                }
                key_portable(&key, &rgb[3 * done..], &mut mask[done..]);
                mask
            }
        };
        if let Some(p) = plate {
            for ((m, px), pl) in mask.iter_mut().zip(rgb.chunks_exact(3)).zip(p.chunks_exact(3)) {
                let plated = px.iter().zip(pl).all(|(&a, &b)| a.abs_diff(b) <= self.plate_tolerance);
                *m = if plated { 0 } else { *m };
            }
        }
        if self.open_radius > 0 {
            morph(&mut mask, width, height, self.open_radius, false);
            morph(&mut mask, width, height, self.open_radius, true);
        }
        if self.close_radius > 0 {
            morph(&mut mask, width, height, self.close_radius, true);
            morph(&mut mask, width, height, self.close_radius, false);
        }
        // A colour key that leaves part of the scene reaching the image's edge (a grey floor
        // or turntable): its plain regions go too.
        if matches!(used.source, KeySource::Given | KeySource::Found { .. }) && edge_share(&mask, width, height) >= EDGE_WARN_SHARE {
            used.plain_edge = backdrop::key_within(rgb, width, height, &mut mask).map(|b| b.threshold);
        }
        Ok((mask, used))
    }
}

/// [`ChromaKey::rim_px`]'s default: every point fused. A correlation window (9 × 9 by
/// default) that reaches across the silhouette matches the outline, and each camera sees a
/// rounded object's outline at a different place on it: such matches are the least accurate a
/// view has. Leaving 3 pixels out brings the fused mesh's vertices 4–16 % closer to the true
/// surface, but the mesh then covers up to 2.6 % less of the surface the views saw
/// (docs/segmentation.md, "The silhouette's rim"): a choice for the user, not a default.
pub const DEFAULT_RIM_PX: usize = 0;

/// The widest rim the commands and the daemon's config accept, pixels.
pub const MAX_RIM_PX: usize = 32;

/// A mask (255 = object) less its rim: the pixels at least `px` pixels (a square window) inside
/// the object's silhouette stay 255. The image's edge is not a silhouette: an object cut by it
/// keeps its pixels there. Parts narrower than `2 px + 1` pixels go entirely.
pub fn inside_rim(mask: &[u8], w: usize, h: usize, px: usize) -> Vec<u8> {
    let mut inner = mask.to_vec();
    morph(&mut inner, w, h, px, false);
    inner
}

/// The bounding box of the non-zero bytes of a row-major `w`-wide mask: its columns and rows
/// (half-open), `None` where every byte is 0.
pub fn mask_bounds(mask: &[u8], w: usize) -> Option<(std::ops::Range<usize>, std::ops::Range<usize>)> {
    // Tested CHUNK bytes at a time, each chunk a fixed-size array folded branch-free (a few
    // vector instructions): from each end of a row to its first chunk holding a set byte, so
    // that a row of the object costs its background alone, and an empty row one scan.
    const CHUNK: usize = 32;
    let any = |c: &[u8]| <&[u8; CHUNK]>::try_from(c).expect("a whole chunk").iter().fold(0u8, |a, &v| a | v) != 0;
    let mut r: Option<(std::ops::Range<usize>, std::ops::Range<usize>)> = None;
    for (y, row) in mask.chunks_exact(w).enumerate() {
        let whole = w / CHUNK * CHUNK;
        let first = match row[..whole].chunks_exact(CHUNK).position(any) {
            Some(c) => c * CHUNK + row[c * CHUNK..].iter().position(|&v| v != 0).expect("one in the chunk"),
            None => match row[whole..].iter().position(|&v| v != 0) {
                Some(k) => whole + k,
                // An empty row.
                None => continue,
            },
        };
        // From the right end: the columns past the whole chunks, then whole chunks down to
        // `first`'s (which holds a set byte).
        let last = match row[whole..].iter().rposition(|&v| v != 0) {
            Some(k) => whole + k,
            None => {
                let c = row[..whole].rchunks_exact(CHUNK).position(any).expect("first's chunk holds one");
                let end = whole - c * CHUNK;
                row[..end].iter().rposition(|&v| v != 0).expect("one in the chunk")
            }
        } + 1;
        // Grown row by row, top to bottom.
        r = Some(match r {
            None => (first..last, y..y + 1),
            Some((xs, ys)) => (xs.start.min(first)..xs.end.max(last), ys.start..y + 1),
        });
    }
    r
}

/// How far inside the object's silhouette each pixel of a mask (255 = object) lies, pixels:
/// the Chebyshev distance (a square neighbourhood, as [`inside_rim`] erodes) to the nearest
/// background pixel inside the image, capped at 255; 0 on the background. So a pixel
/// survives `inside_rim(mask, w, h, k)` exactly where its distance is over `k`. The image's
/// edge is not a silhouette: an object cut by it is measured from its background only (all
/// 255 without any). The fusion weighs a view's points by it (`FuseParams::rim_weight_px`).
///
/// Two passes of the 8-neighbour chamfer with unit steps (exact for this distance), over the
/// mask's bounding box and the ring of background around it, where that ring is inside
/// the image; everything outside is background or beyond the image. 0.19 ms a 640 × 480
/// frame (`cargo bench --bench matcher -- segment`; 0.09 for `inside_rim` at 3).
pub fn rim_distance(mask: &[u8], w: usize, h: usize) -> Vec<u8> {
    let mut d = vec![0u8; w * h];
    // The bounding box of the object, grown by the ring of background around it.
    let Some((xs, ys)) = mask_bounds(&mask[..w * h], w.max(1)) else { return d };
    let (x0, x1, y0, y1) = (xs.start.saturating_sub(1), xs.end.min(w - 1), ys.start.saturating_sub(1), ys.end.min(h - 1));
    // The box in a buffer with a frame of 255 around it: a neighbour beyond the box is
    // beyond the image (never background) or background of the box's ring, which is nearer.
    let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
    let stride = bw + 2;
    let mut b = vec![u8::MAX; stride * (bh + 2)];
    for y in 0..bh {
        let src = &mask[(y0 + y) * w + x0..][..bw];
        for (v, &m) in b[(y + 1) * stride + 1..][..bw].iter_mut().zip(src) {
            *v = if m != 0 { u8::MAX } else { 0 };
        }
    }
    chamfer_passes(&mut b, bw, bh, 1, 1);
    for y in 0..bh {
        d[(y0 + y) * w + x0..][..bw].copy_from_slice(&b[(y + 1) * stride + 1..][..bw]);
    }
    d
}

/// A step of a chamfer distance: added without overflowing (a sum past the type's top
/// stays there).
pub(crate) trait ChamferStep: Copy + Ord {
    /// The type's top: not reached.
    const TOP: Self;
    fn plus(self, step: Self) -> Self;
}

impl ChamferStep for u8 {
    const TOP: u8 = u8::MAX;
    fn plus(self, step: u8) -> u8 {
        self.saturating_add(step)
    }
}

impl ChamferStep for u32 {
    const TOP: u32 = u32::MAX;
    fn plus(self, step: u32) -> u32 {
        self.saturating_add(step)
    }
}

/// The two passes of an 8-neighbour chamfer distance over a `bw × bh` box held in `b` with a
/// frame of one pixel around it (rows of `bw + 2`): 0 on the background, [`ChamferStep::TOP`]
/// elsewhere before; each pixel's least sum of `axial` and `diagonal` steps to the
/// background after. The frame is never written: it holds what lies beyond the box.
/// Each pass takes the three neighbours of the row before for the whole row at once
/// (element-wise, so that it vectorises), then the one before along the row.
pub(crate) fn chamfer_passes<T: ChamferStep>(b: &mut [T], bw: usize, bh: usize, axial: T, diagonal: T) {
    let stride = bw + 2;
    let top = T::TOP;
    let mut above = vec![top; bw];
    for y in 1..=bh {
        let (prev, row) = b.split_at_mut(y * stride);
        let prev = &prev[(y - 1) * stride..];
        for (i, a) in above.iter_mut().enumerate() {
            *a = prev[i].plus(diagonal).min(prev[i + 1].plus(axial)).min(prev[i + 2].plus(diagonal));
        }
        let mut left = top;
        for (v, &a) in row[1..=bw].iter_mut().zip(&above) {
            left = (*v).min(a).min(left.plus(axial));
            *v = left;
        }
    }
    for y in (1..=bh).rev() {
        let (row, next) = b.split_at_mut((y + 1) * stride);
        let next = &next[..stride];
        for (i, a) in above.iter_mut().enumerate() {
            *a = next[i].plus(diagonal).min(next[i + 1].plus(axial)).min(next[i + 2].plus(diagonal));
        }
        let mut right = top;
        for (v, &a) in row[y * stride + 1..][..bw].iter_mut().zip(&above).rev() {
            right = (*v).min(a).min(right.plus(axial));
            *v = right;
        }
    }
}

/// Square dilation (`dilate = true`) or erosion of a 0/255 mask, separable: the OR (AND) of
/// the 2·radius + 1 pixels along each row, then down each column. Only pixels inside the image
/// count, so an object touching the border is not eaten by the erosion. Each step combines
/// whole shifted rows element-wise — 32 pixels per AVX2 instruction, O(radius) per pixel,
/// which for the radii used here (1–2) beats a running count, whose loop does not vectorise.
fn morph(mask: &mut [u8], w: usize, h: usize, radius: usize, dilate: bool) {
    if w == 0 || h == 0 {
        return;
    }
    // Outside the image: unset for a dilation, set for an erosion (neither changes the result).
    let neutral = if dilate { 0u8 } else { 255 };
    let combine = |acc: &mut [u8], other: &[u8]| {
        if dilate {
            acc.iter_mut().zip(other).for_each(|(a, &b)| *a |= b);
        } else {
            acc.iter_mut().zip(other).for_each(|(a, &b)| *a &= b);
        }
    };
    debug_assert!(mask.iter().all(|&v| v == 0 || v == 255), "morph takes a 0/255 mask");
    let mut tmp = vec![0u8; w * h];
    let mut padded = vec![neutral; w + 2 * radius];
    for (src, dst) in mask.chunks_exact(w).zip(tmp.chunks_exact_mut(w)) {
        padded[radius..radius + w].copy_from_slice(src);
        dst.copy_from_slice(&padded[..w]);
        for k in 1..=2 * radius {
            combine(dst, &padded[k..k + w]);
        }
    }
    for y in 0..h {
        let rows = y.saturating_sub(radius)..(y + radius + 1).min(h);
        let out = &mut mask[y * w..(y + 1) * w];
        out.copy_from_slice(&tmp[rows.start * w..(rows.start + 1) * w]);
        for yy in rows.start + 1..rows.end {
            combine(out, &tmp[yy * w..(yy + 1) * w]);
        }
    }
}

#[cfg(test)]
mod tests;
