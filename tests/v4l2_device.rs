//! Real V4L2 cameras, for the lab: built only with `--features device-tests`, and then the
//! devices are named by environment variables (no camera can exist on CI machines):
//!
//! ```sh
//! SPINSCAN_TEST_LEFT=/dev/spinscan-left SPINSCAN_TEST_RIGHT=/dev/spinscan-right \
//!   [SPINSCAN_TEST_FORMAT=MJPG] [SPINSCAN_TEST_SIZE=640x480] \
//!   cargo test --features device-tests --test v4l2_device
//! ```
#![cfg(feature = "device-tests")]

use std::time::Duration;

use spinscan::hw::StereoSource;
use spinscan::hw::v4l2::{StreamConfig, V4l2Stereo};

fn var(name: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| panic!("--features device-tests needs {name} naming a V4L2 device (see the top of tests/v4l2_device.rs)"))
}

#[test]
fn two_cameras_deliver_paired_frames_on_one_clock() {
    let (left, right) = (var("SPINSCAN_TEST_LEFT"), var("SPINSCAN_TEST_RIGHT"));
    let format = std::env::var("SPINSCAN_TEST_FORMAT").unwrap_or_else(|_| "MJPG".into());
    let size = std::env::var("SPINSCAN_TEST_SIZE").unwrap_or_else(|_| "640x480".into());
    let (w, h) = size.split_once('x').map(|(w, h)| (w.parse().unwrap(), h.parse().unwrap())).expect("SPINSCAN_TEST_SIZE like 640x480");
    let mut fourcc = [b' '; 4];
    fourcc.copy_from_slice(&format.as_bytes()[..4]);
    let cfg = StreamConfig { width: w, height: h, fps: 15, fourcc, buffers: 4, timeout: Duration::from_secs(2), auto_exposure: None, exposure_100us: None, gain: None };
    let calib = spinscan::hw::sim::calib_of(&hw_sim::Rig::ideal(w as usize, h as usize, 700.0, 60.0));
    let mut cams = V4l2Stereo::open(left.as_ref(), right.as_ref(), cfg, None, calib).expect("open both cameras");
    // The pairing tolerance follows the rate the drivers chose: half its period.
    let tolerance_ns = spinscan::hw::v4l2::half_period_ns(cams.fps());
    eprintln!("the cameras run at {:.2} fps (15 asked)", cams.fps());
    let mut last_seq = None;
    for _ in 0..30 {
        let f = cams.next_frame().expect("a pair").expect("cameras never run out");
        assert!((f.t_right_ns as i64 - f.t_left_ns as i64).unsigned_abs() <= tolerance_ns, "skew within the tolerance");
        assert!(last_seq.is_none_or(|s| f.seq > s), "seq increases");
        last_seq = Some(f.seq);
        let (fw, fh, rgb) = f.left.to_rgb().expect("left frame decodes");
        assert_eq!((fw, fh, rgb.len()), (w as usize, h as usize, w as usize * h as usize * 3));
        f.right.to_rgb().expect("right frame decodes");
    }
    let stats = cams.pair_stats();
    assert!(stats.pairs >= 30);
    eprintln!("pairs {}, unpaired left {} right {}, max skew {:.2} ms", stats.pairs, stats.unpaired_left, stats.unpaired_right, stats.max_abs_skew_ns as f64 / 1e6);

    // A captured frame is a standard JPEG: Huffman tables present (the lab check-list's DHT
    // check), whole through its end marker.
    let f = cams.fresh_frame().expect("a pair").expect("cameras never run out");
    if let spinscan::hw::Picture::Jpeg { bytes } = &f.left {
        assert!(bytes.windows(2).any(|w| w == [0xFF, 0xC4]), "a DHT segment");
        assert_eq!(&bytes[bytes.len() - 2..], &[0xFF, 0xD9]);
    }
}
