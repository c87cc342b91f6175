use super::*;
use crate::register::posestore::ViewPose;
use nalgebra::{Point3, Translation3, Vector3};

/// A sphere turning about a vertical axis that does not pass through its centre, seen by an
/// ideal 320×240 rig: true disparity per pixel for each frame.
struct Scene {
    rect: Rectification,
    cam: RectCamera,
    axis_point: Vector3<f64>,
    step_deg: f64,
}

impl Scene {
    fn new() -> Scene {
        let rect = Rectification::compute(&crate::hw::sim::ideal_calib(320, 240, 300.0, 60.0), (320, 240), 0.0).unwrap();
        let cam = RectCamera::new(&rect);
        Scene { rect, cam, axis_point: Vector3::new(0.0, 0.0, 420.0), step_deg: 2.0 }
    }

    /// `view_from_first`: the object turned by `k` steps.
    fn turn(&self, k: f64) -> Isometry3<f64> {
        let a = Translation3::from(self.axis_point);
        a * UnitQuaternion::from_scaled_axis(Vector3::y() * (k * self.step_deg).to_radians()) * a.inverse()
    }

    fn disparity(&self, k: f64) -> DisparityMap {
        let centre = self.turn(k) * Point3::new(30.0, 0.0, 420.0);
        let radius = 70.0;
        let (w, h) = (320, 240);
        let mut d = DisparityMap::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let dir = Vector3::new((x as f64 - self.cam.cx) / self.cam.fx, (y as f64 - self.cam.cy) / self.cam.fy, 1.0);
                // |s·dir − c|² = R²: the nearer root.
                let (a, b, c) = (dir.norm_squared(), -2.0 * dir.dot(&centre.coords), centre.coords.norm_squared() - radius * radius);
                let disc = b * b - 4.0 * a * c;
                if disc < 0.0 {
                    continue;
                }
                let s = (-b - disc.sqrt()) / (2.0 * a);
                let p = dir * s;
                d.set(x, y, Some(self.cam.project(&p).unwrap().2 as f32));
            }
        }
        d
    }

    fn mask(d: &DisparityMap) -> Vec<u8> {
        d.values().iter().map(|v| if v.is_finite() { 255 } else { 0 }).collect()
    }

    fn poses(&self, views: std::ops::Range<u64>) -> PoseSnapshot {
        let views = views.map(|k| ViewPose { seq: k, first_from_view: self.turn(k as f64).inverse(), table_deg: Some(k as f64 * self.step_deg) }).collect();
        PoseSnapshot { generation: 1, views }
    }
}

fn stats(valid: f64) -> MatchStats {
    MatchStats { searched: 1000, matched: (1000.0 * valid) as usize, ..Default::default() }
}

/// Share of foreground pixels whose interval holds the true disparity, and the mean width.
fn containment(plan: &Plan, truth: &DisparityMap) -> (f64, f64, usize) {
    let (mut n, mut inside, mut width) = (0usize, 0usize, 0f64);
    for y in 0..truth.height {
        for x in 0..truth.width {
            let Some(t) = truth.get(x, y) else { continue };
            n += 1;
            if let Some((lo, hi)) = plan.intervals.get(x, y) {
                inside += (lo as f32 <= t && t <= hi as f32) as usize;
                width += (hi - lo + 1) as f64;
            }
        }
    }
    (inside as f64 / n as f64, width / n as f64, n)
}

/// An assistant at the pixel granularity (the rules as written) that has seen `frames` frames.
fn assistant(scene: &Scene, mode: AssistMode, frames: u64) -> Assistant {
    assistant_at(scene, mode, Granularity::Pixel, frames)
}

fn assistant_at(scene: &Scene, mode: AssistMode, granularity: Granularity, frames: u64) -> Assistant {
    let mut a = Assistant::new(AssistParams { mode, granularity, ..Default::default() }, &scene.rect, (0, 127));
    for k in 0..frames {
        let d = scene.disparity(k as f64);
        let plan = a.plan(k, Some(&Scene::mask(&d)), &scene.poses(0..k));
        assert!(a.accept(k, &plan, &d, Some(&Scene::mask(&d)), &stats(0.9)).is_none());
    }
    a
}

#[test]
fn the_first_frames_and_no_assistance_search_the_full_range() {
    let scene = Scene::new();
    let mut a = Assistant::new(AssistParams { mode: AssistMode::Paper { w: 0.8 }, ..Default::default() }, &scene.rect, (0, 127));
    let d = scene.disparity(0.0);
    let mask = Scene::mask(&d);
    let plan = a.plan(0, Some(&mask), &scene.poses(0..0));
    assert_eq!(plan.full_range.as_deref(), Some("no previous frame"));
    a.accept(0, &plan, &d, Some(&mask), &stats(0.9));
    let plan = a.plan(1, Some(&mask), &scene.poses(0..1));
    assert_eq!(plan.full_range.as_deref(), Some("no registered motion yet"));
    assert_eq!(plan.intervals.get(160, 120), Some((0, 127)));
    assert_eq!(plan.intervals.get(0, 0), None, "background is not searched");
    let mut none = assistant(&scene, AssistMode::None, 3);
    assert_eq!(none.plan(3, Some(&mask), &scene.poses(0..3)).full_range.as_deref(), Some("assistance off"));
    // With assistance off the accepted frames are not kept: no plan reads them, and a
    // frame without assistance costs no copy (`bench table1`'s row without assistance times it).
    assert!(none.prev.is_none() && none.recent_valid.is_empty(), "assistance off keeps no previous frame");
}

#[test]
fn paper_intervals_hold_the_true_disparity_and_are_narrow() {
    let scene = Scene::new();
    for w in [0.6, 0.8, 1.0, 2.0] {
        let mut a = assistant(&scene, AssistMode::Paper { w }, 3);
        let truth = scene.disparity(3.0);
        let plan = a.plan(3, Some(&Scene::mask(&truth)), &scene.poses(0..3));
        assert!(plan.assisted(), "{:?}", plan.full_range);
        let (inside, width, n) = containment(&plan, &truth);
        assert!(inside > 0.99, "w = {w}: {inside}");
        assert!(width < 16.0, "w = {w}: {width}");
        // The single circle covers most of the object; the rest came from the union.
        assert!(plan.single_px as f64 > 0.8 * n as f64, "w = {w}: {} of {n}", plan.single_px);
        assert!(plan.union_px > 0, "w = {w}");
        assert_eq!(plan.lag, 0);
    }
    // A larger w searches more.
    let width = |w| {
        let mut a = assistant(&scene, AssistMode::Paper { w }, 3);
        let truth = scene.disparity(3.0);
        containment(&a.plan(3, Some(&Scene::mask(&truth)), &scene.poses(0..3)), &truth).1
    };
    assert!(width(2.0) > width(0.6));
}

#[test]
fn paper_intervals_are_the_rule_itself() {
    // Every foreground pixel's interval, as the plan builds it (single circle, union gathered
    // within a reach and splatted beyond it), against the paper's two cases written out
    // directly: the single circle d_prev ± ρ, and the hull of the chords of *every* previous
    // sphere whose left projection holds the pixel — rounded outwards and clipped as the plan
    // does. Pixels no sphere reaches are the hole fill's, checked elsewhere.
    let scene = Scene::new();
    for w in [0.8, 2.0] {
        let mut a = assistant(&scene, AssistMode::Paper { w }, 3);
        let truth = scene.disparity(3.0);
        let mask = Scene::mask(&truth);
        let plan = a.plan(3, Some(&mask), &scene.poses(0..3));
        assert!(plan.assisted());
        let prev = a.prev.as_ref().unwrap();
        let (width, height) = (truth.width, truth.height);
        let rho = |x: usize, y: usize| a.rho[y * width + x];
        let points: Vec<(usize, usize, f32, f32)> = (0..height).flat_map(|y| (0..width).map(move |x| (x, y))).filter(|&(x, y)| a.region.xs().contains(&x) && a.region.ys().contains(&y) && rho(x, y).is_finite()).map(|(x, y)| (x, y, prev.disparity.get(x, y).unwrap(), rho(x, y))).collect();
        assert!(points.len() > 1000);
        let round = |lo: f32, hi: f32| interval((0, 127), lo, hi);
        let (mut singles, mut unions) = (0, 0);
        for y in 0..height {
            for x in 0..width {
                if mask[y * width + x] == 0 {
                    continue;
                }
                let single = prev.disparity.get(x, y).is_some() && rho(x, y).is_finite() && prev.mask.as_ref().unwrap()[y * width + x] != 0;
                let expected = if single {
                    singles += 1;
                    let (d, r) = (prev.disparity.get(x, y).unwrap(), rho(x, y));
                    round(d - r, d + r)
                } else {
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for &(sx, sy, d, r) in &points {
                        let dy = y as f32 - sy as f32;
                        let c2 = r * r - dy * dy;
                        let dx = x as f32 - sx as f32;
                        if c2 >= 0.0 && dx.abs() <= c2.sqrt() {
                            lo = lo.min(d + dx - c2.sqrt());
                            hi = hi.max(d + dx + c2.sqrt());
                        }
                    }
                    if lo > hi {
                        continue; // a hole: filled from its neighbours
                    }
                    unions += 1;
                    round(lo, hi)
                };
                assert_eq!(plan.intervals.get(x, y), expected, "w = {w}, pixel ({x}, {y}), single: {single}");
            }
        }
        assert_eq!((singles, unions), (plan.single_px, plan.union_px), "w = {w}");
        assert!(unions > 0, "w = {w}");
    }
}

#[test]
fn predicted_intervals_hold_the_true_disparity_and_are_narrow() {
    let scene = Scene::new();
    let truth = scene.disparity(4.0);
    let mask = Scene::mask(&truth);
    // ±(3 × 0.5 px) around the prediction, rounded outwards, hull of 2 × 2 splats; per tile,
    // the hull over 16 × 8 pixels of the sphere's slanting surface (7.4 disparities a
    // pixel); per sloped tile, the hull about the plane the previous frame's disparities give
    // the tile (5.6, against the pixels' own 5.3).
    for (granularity, narrow) in [(Granularity::Pixel, 7.0), (Granularity::Tile, 12.0), (Granularity::Plane, 6.0)] {
        let mut p = assistant_at(&scene, AssistMode::Predicted, granularity, 4);
        let plan = p.plan(4, Some(&mask), &scene.poses(0..4));
        assert!(plan.assisted());
        let (inside, width, _) = containment(&plan, &truth);
        assert!(inside > 0.99, "{granularity:?}: {inside}");
        assert!(width < narrow, "{granularity:?}: {width}");
        assert!(plan.single_px > 0 && plan.uncovered_px * 50 < plan.single_px, "{granularity:?}: {} single, {} uncovered", plan.single_px, plan.uncovered_px);
    }
}

#[test]
fn a_lagging_registration_is_extrapolated_and_widened() {
    let scene = Scene::new();
    let truth = scene.disparity(5.0);
    let mask = Scene::mask(&truth);
    for mode in [AssistMode::Paper { w: 0.8 }, AssistMode::Predicted] {
        // Frames 0–4 matched, but only views 0–2 registered: two frames of lag.
        let mut lagging = Assistant::new(AssistParams { mode, ..Default::default() }, &scene.rect, (0, 127));
        let mut current = Assistant::new(AssistParams { mode, ..Default::default() }, &scene.rect, (0, 127));
        for k in 0..5u64 {
            let d = scene.disparity(k as f64);
            let m = Scene::mask(&d);
            let pl = lagging.plan(k, Some(&m), &scene.poses(0..k.min(3)));
            lagging.accept(k, &pl, &d, Some(&m), &stats(0.9));
            let pc = current.plan(k, Some(&m), &scene.poses(0..k));
            current.accept(k, &pc, &d, Some(&m), &stats(0.9));
        }
        let late = lagging.plan(5, Some(&mask), &scene.poses(0..3));
        let on_time = current.plan(5, Some(&mask), &scene.poses(0..5));
        assert_eq!((late.lag, on_time.lag), (2, 0));
        let (inside, late_width, _) = containment(&late, &truth);
        let (_, width, _) = containment(&on_time, &truth);
        assert!(inside > 0.99, "{mode:?}: {inside}");
        assert!(late_width >= width, "{mode:?}: {late_width} < {width}");
    }
}

#[test]
fn a_frame_that_looks_wrong_is_sent_back_and_a_bad_registration_is_not_trusted() {
    let scene = Scene::new();
    let mut a = assistant(&scene, AssistMode::Paper { w: 0.8 }, 3);
    let truth = scene.disparity(3.0);
    let mask = Scene::mask(&truth);
    let plan = a.plan(3, Some(&mask), &scene.poses(0..3));
    let why = a.accept(3, &plan, &truth, Some(&mask), &stats(0.4)).expect("a collapse of the valid fraction is caught");
    assert!(why.contains("valid fraction 0.400"), "{why}");
    // The full-range redo is accepted.
    let full = Plan { full_range: Some("fallback".into()), ..plan.clone() };
    assert!(a.accept(3, &full, &truth, Some(&mask), &stats(0.4)).is_none());
    a.observe_registration(3, 0.1, 0.5);
    let next = a.plan(4, Some(&mask), &scene.poses(0..4));
    assert!(next.full_range.as_deref().is_some_and(|r| r.contains("fitness 0.10")), "{:?}", next.full_range);
    // A residual jumping over 3 × the recent median is not trusted either.
    for (s, r) in [(4, 0.5), (5, 0.6), (6, 0.5)] {
        a.observe_registration(s, 0.9, r);
    }
    assert!(a.plan(4, Some(&mask), &scene.poses(0..4)).assisted());
    a.observe_registration(7, 0.9, 2.0);
    let next = a.plan(4, Some(&mask), &scene.poses(0..4));
    assert!(next.full_range.as_deref().is_some_and(|r| r.contains("RMSE 2.00 mm")), "{:?}", next.full_range);
}

#[test]
fn rect_camera_inverts_its_projection_and_agrees_with_triangulation() {
    let scene = Scene::new();
    let p = Vector3::new(12.0, -30.0, 450.0);
    let (x, y, d) = scene.cam.project(&p).unwrap();
    let back = scene.cam.point(x, y, d).unwrap();
    assert!((back - p).norm() < 1e-9);
    let mut map = DisparityMap::new(320, 240);
    map.set(100, 50, Some(40.0));
    let (cloud, _) = crate::stereo::triangulate::triangulate(&map, &scene.rect, &vec![0u8; 320 * 240 * 3], None);
    let q = scene.cam.point(100.0, 50.0, 40.0).unwrap();
    let t = cloud.points[0];
    assert!((Vector3::new(t[0] as f64, t[1] as f64, t[2] as f64) - q).norm() < 1e-3, "{t:?} vs {q}");
}

#[test]
fn fast_rounding_matches_the_standard_library() {
    for x in [-3.5f32, -3.0, -0.2, -0.0, 0.0, 0.2, 2.0, 2.7, 127.49, 1e6, f32::INFINITY, f32::NEG_INFINITY] {
        assert_eq!(super::region::floor(x), x.floor(), "{x}");
        assert_eq!(super::region::ceil(x), x.ceil(), "{x}");
    }
}

#[test]
fn set_flags_are_found_in_order_whatever_the_length() {
    // Lengths around the eight-byte words, flags of every density, any non-zero value.
    let mut state = 0x2545_f491_4f6c_dd1du64;
    for len in [0usize, 1, 7, 8, 9, 15, 16, 17, 64, 203] {
        for density in [0u64, 1, 8, 64] {
            let flags: Vec<u8> = (0..len)
                .map(|_| {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    if state % 64 < density { (state >> 32) as u8 | 1 } else { 0 }
                })
                .collect();
            let mut found = Vec::new();
            super::region::for_each_set(&flags, |k| found.push(k));
            let expected: Vec<usize> = (0..len).filter(|&k| flags[k] != 0).collect();
            assert_eq!(found, expected, "len {len}, density {density}/64");
        }
    }
}

#[test]
fn the_working_region_follows_the_object_and_does_not_creep() {
    // The region of a plan is this frame's foreground and the previous frame's disparities,
    // grown by the fill distance: over many frames of an object that stays put in the image,
    // it stays as large as that (it once grew by the fill distance at every frame).
    let scene = Scene::new();
    // (Tiles keep one pixel of room, for splats straddling the foreground's edge.)
    for (mode, granularity, room) in [(AssistMode::Paper { w: 0.8 }, Granularity::Pixel, FILL + 1), (AssistMode::Predicted, Granularity::Pixel, FILL + 1), (AssistMode::Predicted, Granularity::Tile, 1), (AssistMode::Predicted, Granularity::Plane, 1)] {
        let mut a = assistant_at(&scene, mode, granularity, 3);
        for k in 3..20u64 {
            let d = scene.disparity(k as f64);
            let mask = Scene::mask(&d);
            let prev = a.prev.as_ref().expect("a previous frame").disparity.clone();
            let plan = a.plan(k, Some(&mask), &scene.poses(0..k));
            assert!(plan.assisted(), "{mode:?} frame {k}: {:?}", plan.full_range);
            let (w, h) = (d.width, d.height);
            let full = Region { x0: 0, x1: w, y0: 0, y1: h };
            let bound = Region::of(Some(&mask), w, h).unwrap().union(&Region::of_disparity(&prev, full)).grow(room, w, h);
            assert_eq!(a.region, bound, "{mode:?} frame {k}");
            assert!(a.accept(k, &plan, &d, Some(&mask), &stats(0.9)).is_none());
            a.recycle(plan);
        }
    }
}

#[test]
fn the_kept_frame_is_the_accepted_map_wherever_the_object_moves() {
    // Only the hull of the old and new disparities' boxes is copied into the kept frame: it
    // must still equal the accepted map everywhere, as the object jumps around the image and
    // a frame comes out empty.
    let scene = Scene::new();
    let mut a = assistant(&scene, AssistMode::Paper { w: 0.8 }, 3);
    let base = scene.disparity(3.0);
    let (w, h) = (base.width, base.height);
    for (k, shift) in [(3u64, 0isize), (4, 40), (5, -60), (6, 0), (7, 25)] {
        let mut d = DisparityMap::new(w, h);
        if k != 6 {
            for y in 0..h {
                for x in 0..w {
                    let xs = x as isize - shift;
                    if (0..w as isize).contains(&xs) {
                        d.values_mut()[y * w + x] = base.values()[y * w + xs as usize];
                    }
                }
            }
        }
        let plan = a.plan(k, None, &scene.poses(0..k));
        assert!(a.accept(k, &plan, &d, None, &stats(0.9)).is_none());
        let kept = &a.prev.as_ref().expect("a kept frame").disparity;
        assert!(kept.values().iter().zip(d.values()).all(|(a, b)| a.to_bits() == b.to_bits()), "frame {k}");
        a.recycle(plan);
    }
}

#[test]
fn a_recycled_interval_buffer_gives_the_plan_a_new_one_gives() {
    // A recycled buffer is cleared only where its old region lies outside the new one (each
    // plan writes all of its own). The matched maps hold part of the object — the part away
    // from where it goes next — so a region built from them and the next mask leaves old
    // foreground behind, on the left, on the right and in whole rows: as the object jumps
    // around the image and a frame comes out empty, every plan must equal the plan built in a
    // fresh buffer.
    let scene = Scene::new();
    let modes = [(AssistMode::Paper { w: 0.8 }, Granularity::Pixel), (AssistMode::Predicted, Granularity::Pixel), (AssistMode::Predicted, Granularity::Tile), (AssistMode::Paper { w: 0.8 }, Granularity::Tile), (AssistMode::Predicted, Granularity::Plane), (AssistMode::Paper { w: 0.8 }, Granularity::Plane)];
    for (mode, granularity) in modes {
        let (mut recycling, mut fresh) = (assistant_at(&scene, mode, granularity, 3), assistant_at(&scene, mode, granularity, 3));
        let base = scene.disparity(3.0);
        let (w, h) = (base.width, base.height);
        // Frame, shift, and the part of the object (in its unshifted pixels) the match keeps.
        let all = |_: isize, _: isize| true;
        let frames: [(u64, isize, isize, &dyn Fn(isize, isize) -> bool); 7] = [
            (3, 0, 0, &|xs, _| xs >= 180),
            (4, 60, 0, &|xs, _| xs < 180),
            (5, -60, 0, &|_, ys| ys >= 140),
            (6, -60, 60, &all),
            (7, 0, 0, &all),
            (8, 60, 0, &all),
            (9, 60, 0, &all),
        ];
        for (k, dx, dy, keep) in frames {
            let (mut d, mut part) = (DisparityMap::new(w, h), DisparityMap::new(w, h));
            if k != 7 {
                for y in 0..h {
                    for x in 0..w {
                        let (xs, ys) = (x as isize - dx, y as isize - dy);
                        if (0..w as isize).contains(&xs) && (0..h as isize).contains(&ys) {
                            let v = base.values()[ys as usize * w + xs as usize];
                            d.values_mut()[y * w + x] = v;
                            part.values_mut()[y * w + x] = if keep(xs, ys) { v } else { f32::NAN };
                        }
                    }
                }
            }
            let mask = Scene::mask(&d);
            let (a, b) = (recycling.plan(k, Some(&mask), &scene.poses(0..k)), fresh.plan(k, Some(&mask), &scene.poses(0..k)));
            assert!(a.assisted(), "{mode:?} frame {k}");
            assert!(a.intervals == b.intervals, "{mode:?} {granularity:?} frame {k}");
            // Each plan records where it searches (the matcher's crop is found inside it), and
            // the record holds every searched pixel, recycled buffer or not.
            for plan in [&a, &b] {
                let (xs, ys) = plan.intervals.searched_rect().expect("a plan records where it searches");
                assert!(xs.len() < w && ys.len() < h, "{mode:?} {granularity:?} frame {k}: {xs:?} × {ys:?}");
                for y in 0..h {
                    for x in 0..w {
                        assert!(plan.intervals.get(x, y).is_none() || (xs.contains(&x) && ys.contains(&y)), "{mode:?} {granularity:?} frame {k}: ({x}, {y}) outside {xs:?} × {ys:?}");
                    }
                }
            }
            assert!(recycling.accept(k, &a, &part, Some(&mask), &stats(0.9)).is_none());
            assert!(fresh.accept(k, &b, &part, Some(&mask), &stats(0.9)).is_none());
            recycling.recycle(a);
        }
    }
}

#[test]
fn holes_take_the_hull_of_the_bounds_around_them() {
    // Foreground pixels no splat reached (the predicted mode's forward warp leaves many):
    // each takes the hull of the bounds within FILL pixels, widened by 2 px, rounded outwards
    // and clipped — or the full range where there are none. Written out directly here, over
    // the 13 × 13 window of every hole, against what the plan built.
    let scene = Scene::new();
    let truth = scene.disparity(4.0);
    let (w, h) = (truth.width, truth.height);
    // The object's mask grown by 4 px on both sides (new foreground beside it: filled), and
    // patches far from it (nothing around: the full range), one on rows of the object.
    let mut mask = Scene::mask(&truth);
    for y in 0..h {
        if let (Some(first), Some(last)) = ((0..w).find(|&x| mask[y * w + x] != 0), (0..w).rev().find(|&x| mask[y * w + x] != 0)) {
            for x in first.saturating_sub(4)..first {
                mask[y * w + x] = 255;
            }
            for x in last + 1..(last + 5).min(w) {
                mask[y * w + x] = 255;
            }
        }
    }
    for y in 2..5 {
        for x in 2..5 {
            mask[y * w + x] = 255;
        }
    }
    let middle = (0..h).filter(|&y| truth.values()[y * w..(y + 1) * w].iter().any(|d| d.is_finite())).nth(10).expect("object rows");
    for y in middle..middle + 3 {
        for x in w - 5..w - 2 {
            mask[y * w + x] = 255;
        }
    }
    let mut a = assistant(&scene, AssistMode::Predicted, 4);
    let plan = a.plan(4, Some(&mask), &scene.poses(0..4));
    assert!(plan.assisted());
    let (r0, r1) = (0.0f32, 127.0f32);
    let region = a.region;
    let (mut filled, mut uncovered) = (0, 0);
    for y in region.ys() {
        for x in region.xs() {
            let (l, u) = (a.lo[y * w + x].max(r0), a.hi[y * w + x].min(r1));
            if mask[y * w + x] == 0 || l <= u {
                continue;
            }
            let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
            for yy in y.saturating_sub(FILL).max(region.y0)..(y + FILL + 1).min(region.y1) {
                for xx in x.saturating_sub(FILL).max(region.x0)..(x + FILL + 1).min(region.x1) {
                    lo = lo.min(a.lo[yy * w + xx]);
                    hi = hi.max(a.hi[yy * w + xx]);
                }
            }
            let expected = match (lo <= hi).then(|| interval((0, 127), lo - 2.0, hi + 2.0)).flatten() {
                Some(r) => {
                    filled += 1;
                    r
                }
                None => {
                    uncovered += 1;
                    (0, 127)
                }
            };
            assert_eq!(plan.intervals.get(x, y), Some(expected), "hole ({x}, {y})");
        }
    }
    assert!(filled > 20 && uncovered > 0, "{filled} holes filled, {uncovered} uncovered");
    assert_eq!((filled, uncovered), (plan.filled_px, plan.uncovered_px));
}

/// Pixel and tile granularity on the same frames: the tile's interval is the hull of the
/// pixel rule's bounds over the tile — exactly over its foreground pixels (`paper`, reduced
/// from the per-pixel bounds), or between that and the hull over all its pixels
/// (`predicted`, whose splats go straight into the tiles, foreground or not).
#[test]
fn tile_intervals_are_the_hull_of_the_pixel_rule_over_each_tile() {
    use super::tiles::{TH, TW};
    let scene = Scene::new();
    let truth = scene.disparity(4.0);
    let mask = Scene::mask(&truth);
    let (w, h) = (truth.width, truth.height);
    for mode in [AssistMode::Predicted, AssistMode::Paper { w: 0.8 }] {
        let with = |granularity| {
            let mut a = Assistant::new(AssistParams { mode, granularity, ..Default::default() }, &scene.rect, (0, 127));
            for k in 0..4 {
                let d = scene.disparity(k as f64);
                let plan = a.plan(k, Some(&Scene::mask(&d)), &scene.poses(0..k));
                assert!(a.accept(k, &plan, &d, Some(&Scene::mask(&d)), &stats(0.9)).is_none());
            }
            let plan = a.plan(4, Some(&mask), &scene.poses(0..4));
            assert!(plan.assisted());
            (a, plan)
        };
        let (px, _) = with(Granularity::Pixel);
        let (_, tiled) = with(Granularity::Tile);
        let (mut checked, mut fg_px) = (0, 0);
        for ty in 0..h.div_ceil(TH) {
            for tx in 0..w.div_ceil(TW) {
                let pixels: Vec<(usize, usize)> = (ty * TH..((ty + 1) * TH).min(h)).flat_map(|y| (tx * TW..((tx + 1) * TW).min(w)).map(move |x| (x, y))).collect();
                let hull = |only_fg: bool| {
                    let inside = |&&(x, y): &&(usize, usize)| (!only_fg || mask[y * w + x] != 0) && px.region.xs().contains(&x) && px.region.ys().contains(&y);
                    let a = pixels.iter().filter(inside).map(|&(x, y)| px.lo[y * w + x]).fold(f32::INFINITY, f32::min);
                    let b = pixels.iter().filter(inside).map(|&(x, y)| px.hi[y * w + x]).fold(f32::NEG_INFINITY, f32::max);
                    interval((0, 127), a, b)
                };
                let fg: Vec<_> = pixels.iter().filter(|&&(x, y)| mask[y * w + x] != 0).collect();
                let Some(&&(x0, y0)) = fg.first() else {
                    assert!(pixels.iter().all(|&(x, y)| tiled.intervals.get(x, y).is_none()), "{mode:?}: background searched in tile ({tx}, {ty})");
                    continue;
                };
                let band = tiled.intervals.get(x0, y0);
                assert!(fg.iter().all(|&&(x, y)| tiled.intervals.get(x, y) == band), "{mode:?}: tile ({tx}, {ty}) is not one interval");
                fg_px += fg.len();
                let Some(exact) = hull(true) else { continue };
                let band = band.expect("a tile with bounds is searched");
                match mode {
                    AssistMode::Paper { .. } => assert_eq!(band, exact, "{mode:?}: tile ({tx}, {ty})"),
                    _ => {
                        let all = hull(false).expect("holds the foreground's");
                        assert!(all.0 <= band.0 && band.0 <= exact.0 && exact.1 <= band.1 && band.1 <= all.1, "{mode:?}: tile ({tx}, {ty}): {band:?} not between {exact:?} and {all:?}");
                    }
                }
                checked += 1;
            }
        }
        assert!(checked > 20 && fg_px == mask.iter().filter(|&&m| m != 0).count(), "{mode:?}: {checked} tiles");
    }
}

/// At tile granularity, flat or sloped, the plan's counts still add up to the foreground:
/// every foreground pixel is counted once, as predicted (or single, or union), filled or
/// full range.
#[test]
fn tile_plans_count_every_foreground_pixel_once() {
    let scene = Scene::new();
    let truth = scene.disparity(4.0);
    let mask = Scene::mask(&truth);
    let fg = mask.iter().filter(|&&m| m != 0).count();
    for (mode, granularity) in [AssistMode::Predicted, AssistMode::Paper { w: 0.8 }].into_iter().flat_map(|m| [(m, Granularity::Tile), (m, Granularity::Plane)]) {
        let mut a = assistant_at(&scene, mode, granularity, 4);
        let plan = a.plan(4, Some(&mask), &scene.poses(0..4));
        assert!(plan.assisted());
        assert_eq!(plan.single_px + plan.union_px + plan.filled_px + plan.uncovered_px, fg, "{mode:?}: {} + {} + {} + {}", plan.single_px, plan.union_px, plan.filled_px, plan.uncovered_px);
        assert!(plan.single_px > fg / 2, "{mode:?}");
    }
}
