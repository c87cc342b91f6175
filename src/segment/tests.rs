use super::*;

fn scene(w: usize, h: usize) -> Vec<u8> {
    scene_on(w, h, DEFAULT_KEY_RGB)
}

/// A screen of colour `screen` darkening to the right (shading), a grey square in the
/// middle (columns 10–29, rows 8–23).
fn scene_on(w: usize, h: usize, screen: [u8; 3]) -> Vec<u8> {
    let mut img = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let shade = 1.0 - 0.5 * x as f32 / w as f32;
            let inside = (10..30).contains(&x) && (8..24).contains(&y);
            let px = if inside { [150, 140, 130] } else { screen };
            img.extend(px.iter().map(|&v| (v as f32 * shade) as u8));
        }
    }
    img
}

/// `auto` keys a screen of any saturated colour as the given colour would, and says it
/// found it: a chromaticity within a hundredth of the screen's, over the whole border.
#[test]
fn auto_finds_a_screen_of_any_colour() {
    let (w, h) = (48, 32);
    // The simulated lab's blue, chroma-key blue, a purer blue, green.
    for screen in [DEFAULT_KEY_RGB, [0, 71, 187], [10, 30, 230], [0, 177, 64]] {
        let img = scene_on(w, h, screen);
        let (mask, used) = ChromaKey::default().segment_keyed(&img, w, h, None).unwrap();
        let given = ChromaKey { key: KeyColour::Rgb(screen), ..ChromaKey::default() }.segment(&img, w, h, None).unwrap();
        assert_eq!(mask, given, "screen {screen:?}");
        assert_eq!(mask.iter().filter(|&&m| m == 255).count(), 20 * 16, "screen {screen:?}");
        let want = chromaticity(&screen).unwrap();
        assert!((used.chroma.0 - want.0).abs() < 0.01 && (used.chroma.1 - want.1).abs() < 0.01, "screen {screen:?}: {used:?}");
        assert!(matches!(used.source, KeySource::Found { border_share } if border_share > 0.99), "screen {screen:?}: {used:?}");
    }
    // A turntable of another colour along the bottom: the screen is still the most common.
    let mut img = scene_on(w, h, [0, 71, 187]);
    for px in img[(h - 2) * w * 3..].chunks_exact_mut(3) {
        px.copy_from_slice(&[90, 90, 90]);
    }
    let used = ChromaKey::default().key_of(&img, w, h);
    assert!(matches!(used.source, KeySource::Found { .. }) && (used.chroma.1 - 0.275).abs() < 0.01, "{used:?}");
}

/// The edge share counts each outermost pixel once, corners included, on masks of one
/// row or column too.
#[test]
fn the_edge_share_counts_the_outermost_pixels() {
    let (w, h) = (10, 6);
    let mut mask = vec![0u8; w * h];
    assert_eq!(edge_share(&mask, w, h), 0.0);
    // An object inside the view: nothing on the edge.
    for y in 2..4 {
        mask[y * w + 3..y * w + 7].fill(255);
    }
    assert_eq!(edge_share(&mask, w, h), 0.0);
    // A floor along the bottom row: 10 of the 28 edge pixels; then the left column's
    // inner pixels too.
    mask[(h - 1) * w..].fill(255);
    assert_eq!(edge_share(&mask, w, h), 10.0 / 28.0);
    for y in 1..h - 1 {
        mask[y * w] = 255;
    }
    assert_eq!(edge_share(&mask, w, h), 14.0 / 28.0);
    assert_eq!(edge_share(&[255; 7], 7, 1), 1.0);
    assert_eq!(edge_share(&[0, 255, 0], 1, 3), 1.0 / 3.0);
    assert_eq!(edge_share(&[255; 12], 4, 3), 1.0);
    assert!(object_on_edge(0.44).starts_with("44 % of the left image's edge"), "{}", object_on_edge(0.44));
}

/// Where the border shows no coloured screen — grey frames, or an object over most of
/// it — `auto` keys by the default colour and says so; a given colour is used as given.
#[test]
fn auto_falls_back_where_the_border_shows_no_screen() {
    let (w, h) = (48, 32);
    let default = chromaticity(&DEFAULT_KEY_RGB).unwrap();
    // Grey: one chromaticity everywhere, but grey.
    let grey: Vec<u8> = scene(w, h).chunks_exact(3).flat_map(|p| [((p[0] as u16 + p[1] as u16 + p[2] as u16) / 3) as u8; 3]).collect();
    assert_eq!(ChromaKey::default().key_of(&grey, w, h), KeyUsed { chroma: default, source: KeySource::NotFound, plain_edge: None });
    // A brown object over all but the first four columns, the blue screen there (a
    // quarter of the border): brown is no screen colour, and the screen keys out too
    // little of the border.
    let brown = |cols: usize| {
        let mut img = scene(w, h);
        for (i, px) in img.chunks_exact_mut(3).enumerate() {
            if i % w >= w - cols {
                px.copy_from_slice(&[120, 80, 40]);
            }
        }
        img
    };
    let img = brown(w - 4);
    assert_eq!(ChromaKey::default().key_of(&img, w, h).source, KeySource::NotFound);
    // Over three fifths of the columns (more of the border than the screen, which keys out
    // 43 % of it): the screen is found, not the brown.
    let used = ChromaKey::default().key_of(&brown(w * 3 / 5), w, h);
    assert!(matches!(used.source, KeySource::Found { .. }) && (used.chroma.0 - default.0).abs() < 0.01, "{used:?}");
    let given = ChromaKey { key: KeyColour::Rgb([120, 80, 40]), ..ChromaKey::default() };
    assert_eq!(given.key_of(&img, w, h), KeyUsed { chroma: chromaticity(&[120, 80, 40]).unwrap(), source: KeySource::Given, plain_edge: None });
}

/// A grey floor along the bottom that the blue key leaves reaches the image's edge: its
/// plain pixels are keyed out by texture too, the textured object kept, and the key says
/// so. A colour mask clear of the edge is left as the colour made it.
#[test]
fn a_grey_floor_the_colour_leaves_is_keyed_by_texture() {
    let (w, h) = (96, 72);
    let mut next = crate::testing::xorshift(0xf100_4);
    let object = |x: usize, y: usize| (30..62).contains(&x) && (16..44).contains(&y);
    let mut img = Vec::with_capacity(3 * w * h);
    for y in 0..h {
        for x in 0..w {
            let px = if object(x, y) {
                let v = 60 + (next() % 150) as u8;
                [v, v - 20, v / 2]
            } else if y >= 52 {
                let v = 100 + (next() % 3) as u8;
                [v, v, v]
            } else {
                DEFAULT_KEY_RGB
            };
            img.extend(px);
        }
    }
    let (mask, used) = ChromaKey::default().segment_keyed(&img, w, h, None).unwrap();
    assert!(matches!(used.source, KeySource::Found { .. }) && used.plain_edge.is_some(), "{used:?}");
    assert_eq!(edge_share(&mask, w, h), 0.0);
    for y in 0..h {
        for x in 0..w {
            let inner = (32..60).contains(&x) && (18..42).contains(&y);
            let near = (27..65).contains(&x) && (13..47).contains(&y);
            assert!(if inner { mask[y * w + x] != 0 } else { near || mask[y * w + x] == 0 }, "({x}, {y})");
        }
    }
    // The scene without the floor: the colour's mask as it was.
    let (_, used) = ChromaKey::default().segment_keyed(&scene(w, h), w, h, None).unwrap();
    assert_eq!(used.plain_edge, None);
}

#[test]
fn the_no_screen_message_names_the_share_and_the_colour() {
    assert_eq!(no_screen(), "no coloured screen or plain backdrop in the border of the left image (an object or a textured background over more than 70 % of the border): keyed by the default colour 40,70,190");
}

#[test]
fn key_colours_parse_as_written() {
    assert_eq!("auto".parse(), Ok(KeyColour::Auto));
    assert_eq!(" AUTO ".parse(), Ok(KeyColour::Auto));
    assert_eq!("0, 71 ,187".parse(), Ok(KeyColour::Rgb([0, 71, 187])));
    for bad in ["", "blue", "1,2", "1,2,3,4", "0,0,256", "-1,0,0"] {
        let e = bad.parse::<KeyColour>().unwrap_err().to_string();
        assert!(e.contains("expected `auto` or R,G,B"), "{bad}: {e}");
    }
    for k in [KeyColour::Auto, KeyColour::Rgb([40, 70, 190])] {
        assert_eq!(k.to_string().parse(), Ok(k));
    }
}

#[test]
fn keys_out_a_shaded_screen() {
    let (w, h) = (48, 32);
    let mask = ChromaKey::default().segment(&scene(w, h), w, h, None).unwrap();
    assert_eq!(mask[16 * w + 20], 255);
    assert_eq!(mask[2 * w + 45], 0, "the darker screen is still background");
    let fg = mask.iter().filter(|&&m| m == 255).count();
    assert_eq!(fg, 20 * 16);
}

#[test]
fn opening_removes_a_speck() {
    let (w, h) = (48, 32);
    let mut img = scene(w, h);
    let i = (3 * w + 3) * 3;
    img[i..i + 3].copy_from_slice(&[200, 200, 200]);
    let mask = ChromaKey::default().segment(&img, w, h, None).unwrap();
    assert_eq!(mask[3 * w + 3], 0);
}

#[test]
fn plate_keys_dark_background() {
    let (w, h) = (16, 8);
    let plate = vec![5u8; w * h * 3];
    let mut img = plate.clone();
    for x in 4..12 {
        for y in 2..6 {
            img[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[120, 100, 90]);
        }
    }
    // The blue screen's key given (`auto` would key this plain black as a backdrop).
    let key = ChromaKey { key: KeyColour::Rgb(DEFAULT_KEY_RGB), open_radius: 0, close_radius: 0, ..Default::default() };
    let without = key.segment(&img, w, h, None).unwrap();
    assert_eq!(without[0], 255, "too dark to key by colour");
    let with = key.segment(&img, w, h, Some(&plate)).unwrap();
    assert_eq!(with[0], 0);
    assert_eq!(with[3 * w + 5], 255);
}

/// A rectified image zoomed out (a toed-in rig's alpha) is black wherever it maps outside
/// the camera: here over the left 40 % and the bottom quarter, most of the border. The
/// screen is still found from the rest of the border (all of it keyed), and the black
/// margins are background, not a dark object to search.
#[test]
fn black_margins_of_a_rectified_image_are_neither_screen_nor_object() {
    let (w, h) = (64, 48);
    let mut img = scene_on(w, h, DEFAULT_KEY_RGB);
    for (i, px) in img.chunks_exact_mut(3).enumerate() {
        if i % w < 26 || i / w >= 36 {
            px.copy_from_slice(&[0, 0, 0]);
        }
    }
    let (mask, used) = ChromaKey::default().segment_keyed(&img, w, h, None).unwrap();
    assert!(matches!(used.source, KeySource::Found { border_share } if border_share > 0.99), "{used:?}");
    let object: Vec<usize> = (0..w * h).filter(|&i| mask[i] == 255).collect();
    // The grey square's part right of the margin: columns 26–29, rows 8–23.
    assert_eq!(object.len(), 4 * 16, "{object:?}");
    assert!(object.iter().all(|&i| (26..30).contains(&(i % w)) && (8..24).contains(&(i / w))), "{object:?}");
    // All black: nothing to find a key from, and nothing kept.
    let black = vec![0u8; w * h * 3];
    let (mask, used) = ChromaKey::default().segment_keyed(&black, w, h, None).unwrap();
    assert_eq!((used.source, mask.iter().filter(|&&m| m != 0).count()), (KeySource::NotFound, 0));
}

/// The colour test in AVX2 gives the portable mask: random pixels (dark ones, black
/// ones, and ones on either side of the tolerance around the key), lengths that end in a
/// partial group of eight.
#[test]
fn the_avx2_key_is_the_portable_one() {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        let mut next = crate::testing::xorshift(0x5e9_7e47);
        for (n, tolerance, dark_level) in [(1, 0.12, 60), (37, 0.12, 60), (1000, 0.05, 0), (4099, 0.3, 200)] {
            let key = Key { chroma: chromaticity(&DEFAULT_KEY_RGB).unwrap(), tol2: tolerance * tolerance, dark_level };
            let rgb: Vec<u8> = (0..n)
                .flat_map(|_| match next() % 4 {
                    // Near the key, scaled and jittered: both sides of the tolerance.
                    0 | 1 => {
                        let scale = 0.2 + (next() % 100) as f32 / 60.0;
                        DEFAULT_KEY_RGB.map(|v| ((v as f32 * scale) as i32 + (next() % 31) as i32 - 15).clamp(0, 255) as u8)
                    }
                    2 => [(next() % 8) as u8, (next() % 8) as u8, (next() % 8) as u8],
                    _ => [next() as u8, next() as u8, next() as u8],
                })
                .collect();
            let mut want = vec![0; n];
            key_portable(&key, &rgb, &mut want);
            let mut got = vec![0; n];
            // SAFETY: the CPU has AVX2 (checked above); 3 bytes per pixel.
            let done = unsafe { key_avx2(&key, &rgb, &mut got) };
            key_portable(&key, &rgb[3 * done..], &mut got[done..]);
            assert!(n < 16 || done >= n - 16, "{done} of {n} in the lanes");
            assert_eq!(got, want, "{n} pixels, tolerance {tolerance}, dark level {dark_level}");
            assert!(want.contains(&0) && want.contains(&255) || n < 40, "both outcomes among {n} pixels");
        }
    }
}

/// Dilation and erosion against the rule written out: a pixel of the result is set when
/// any (dilation) or every (erosion) pixel of the square window around it, clipped to the
/// image, is set — on random masks, radii 0–3, sizes down to one pixel.
#[test]
fn morph_is_the_square_window_rule() {
    let mut next = crate::testing::xorshift(0x9e37_79b9_7f4a_7c15);
    for (w, h) in [(1, 1), (1, 7), (9, 1), (13, 11), (40, 23)] {
        for radius in 0..4 {
            for dilate in [false, true] {
                let mask: Vec<u8> = (0..w * h).map(|_| if next() % 3 != 0 { 255 } else { 0 }).collect();
                let mut got = mask.clone();
                morph(&mut got, w, h, radius, dilate);
                for y in 0..h {
                    for x in 0..w {
                        let mut window = (y.saturating_sub(radius)..(y + radius + 1).min(h)).flat_map(|yy| (x.saturating_sub(radius)..(x + radius + 1).min(w)).map(move |xx| (xx, yy)));
                        let on = if dilate { window.any(|(xx, yy)| mask[yy * w + xx] != 0) } else { window.all(|(xx, yy)| mask[yy * w + xx] != 0) };
                        assert_eq!(got[y * w + x], if on { 255 } else { 0 }, "{w}×{h}, radius {radius}, dilate {dilate}, at ({x}, {y})");
                    }
                }
            }
        }
    }
}

/// The rim is taken from the mask's edge, not the image's: a block cut by the image's left
/// edge loses `px` pixels on its three other sides only, and a bar 2 px + 1 wide keeps its
/// middle line at `px` and goes entirely at `px + 1`.
#[test]
fn the_rim_is_the_silhouette_s_not_the_image_edge_s() {
    let (w, h) = (40, 30);
    let mut mask = vec![0u8; w * h];
    let set = |mask: &mut Vec<u8>, xs: std::ops::Range<usize>, ys: std::ops::Range<usize>| {
        for y in ys {
            mask[y * w + xs.start..y * w + xs.end].fill(255);
        }
    };
    set(&mut mask, 0..20, 5..25); // the block, cut by the left edge
    set(&mut mask, 30..35, 2..28); // the bar, 5 px wide
    let inner = inside_rim(&mask, w, h, 2);
    let kept = |m: &[u8], x: usize, y: usize| m[y * w + x] == 255;
    assert!(kept(&inner, 0, 7) && kept(&inner, 17, 22) && !kept(&inner, 18, 10) && !kept(&inner, 5, 6) && !kept(&inner, 5, 23));
    assert_eq!(inner.iter().filter(|&&v| v == 255).count(), 18 * 16 + 22, "the block less 2 px on three sides, the bar's middle column");
    assert!((4..26).all(|y| kept(&inner, 32, y)) && !kept(&inner, 31, 10) && !kept(&inner, 33, 10));
    let inner = inside_rim(&mask, w, h, 3);
    assert!((0..h).all(|y| !kept(&inner, 32, y)), "a bar 5 px wide goes at 3");
    assert_eq!(inside_rim(&mask, w, h, 0), mask);
}

/// The distance map is the erosion's: a pixel survives `inside_rim(k)` exactly where its
/// distance is over `k`, on random blobs that touch every edge of the image and on the
/// block and bar above; an image of object alone is all 255, and the background 0.
#[test]
fn the_rim_distance_is_what_the_erosions_leave() {
    let (w, h) = (53, 41);
    let mut seed = 0x2545_f491_4f6c_dd1d_u64;
    let mut rnd = move |n: usize| {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 33) as usize % n
    };
    for round in 0..40 {
        let mut mask = vec![0u8; w * h];
        for _ in 0..1 + round % 6 {
            let (cx, cy, r) = (rnd(w) as isize, rnd(h) as isize, 2 + rnd(14) as isize);
            for y in 0..h as isize {
                for x in 0..w as isize {
                    if (x - cx).pow(2) + 2 * (y - cy).pow(2) <= r * r {
                        mask[y as usize * w + x as usize] = 255;
                    }
                }
            }
        }
        let d = rim_distance(&mask, w, h);
        for (i, (&m, &v)) in mask.iter().zip(&d).enumerate() {
            assert_eq!(m == 0, v == 0, "round {round}: pixel {i} is background exactly where its distance is 0");
        }
        for k in 0..12 {
            let inner = inside_rim(&mask, w, h, k);
            for (i, (&e, &v)) in inner.iter().zip(&d).enumerate() {
                assert_eq!(e != 0, v as usize > k, "round {round}, erosion {k}: pixel {i} (distance {v})");
            }
        }
    }
    assert!(rim_distance(&vec![255u8; w * h], w, h).iter().all(|&v| v == 255), "no silhouette: nothing is near one");
    assert!(rim_distance(&vec![0u8; w * h], w, h).iter().all(|&v| v == 0));
    // A block cut by the image's left edge: measured from its other three sides only.
    let mut mask = vec![0u8; w * h];
    for y in 5..25 {
        mask[y * w..y * w + 20].fill(255);
    }
    let d = rim_distance(&mask, w, h);
    assert_eq!((d[15 * w], d[15 * w + 19], d[5 * w + 3], d[15 * w + 10]), (10, 1, 1, 10));
}
