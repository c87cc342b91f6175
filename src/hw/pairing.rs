//! Pairing two free-running cameras by their timestamps: a pure struct on plain frames,
//! usable by any camera backend (V4L2 today), testable without devices or threads.

use std::collections::VecDeque;

use serde::Serialize;

use super::frame::{Picture, StereoFrame};

/// Which camera of the rig.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    Left,
    Right,
}

impl Side {
    pub fn name(self) -> &'static str {
        match self {
            Side::Left => "left",
            Side::Right => "right",
        }
    }
}

/// One camera's frame with the kernel's facts.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraFrame {
    pub side: Side,
    /// Kernel timestamp, ns (CLOCK_MONOTONIC).
    pub t_ns: u64,
    /// Kernel frame counter (gaps: frames the driver dropped).
    pub sequence: u32,
    pub picture: Picture,
}

/// Pairing statistics.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct PairStats {
    pub pairs: u64,
    pub unpaired_left: u64,
    pub unpaired_right: u64,
    /// |t_right − t_left| of the last pair and the largest so far, ns.
    pub last_skew_ns: i64,
    pub max_abs_skew_ns: u64,
}

/// Pairs left and right frames whose timestamps are within `tolerance_ns`. A frame that
/// cannot be paired (its partner never came, or came too far off) is counted, never
/// silently lost; when one camera stops, the other's frames are counted as they age out.
#[derive(Debug)]
pub struct Pairer {
    tolerance_ns: u64,
    left: VecDeque<CameraFrame>,
    right: VecDeque<CameraFrame>,
    /// Most frames waiting on one side before the oldest counts as unpaired.
    backlog: usize,
    next_seq: u64,
    last_left_sequence: Option<u32>,
    pub stats: PairStats,
}

impl Pairer {
    pub fn new(tolerance_ns: u64) -> Pairer {
        Pairer { tolerance_ns, left: VecDeque::new(), right: VecDeque::new(), backlog: 8, next_seq: 0, last_left_sequence: None, stats: PairStats::default() }
    }

    /// Takes one frame; returns the pairs it completes, in order. `seq` follows the left
    /// camera's kernel counter, so frames the driver dropped leave gaps.
    pub fn push(&mut self, frame: CameraFrame, table_deg: Option<f64>) -> Vec<StereoFrame> {
        match frame.side {
            Side::Left => self.left.push_back(frame),
            Side::Right => self.right.push_back(frame),
        }
        let mut out = Vec::new();
        while let (Some(l), Some(r)) = (self.left.front(), self.right.front()) {
            let skew = r.t_ns as i64 - l.t_ns as i64;
            if skew.unsigned_abs() <= self.tolerance_ns {
                // The other side's next frame may be closer still (a late frame): pair the
                // closest.
                let closer_right = self.right.get(1).is_some_and(|r2| (r2.t_ns as i64 - l.t_ns as i64).unsigned_abs() < skew.unsigned_abs());
                let closer_left = self.left.get(1).is_some_and(|l2| (r.t_ns as i64 - l2.t_ns as i64).unsigned_abs() < skew.unsigned_abs());
                if closer_right {
                    self.right.pop_front();
                    self.stats.unpaired_right += 1;
                    continue;
                }
                if closer_left {
                    self.left.pop_front();
                    self.stats.unpaired_left += 1;
                    continue;
                }
                let (l, r) = (self.left.pop_front().unwrap(), self.right.pop_front().unwrap());
                let seq = match self.last_left_sequence {
                    Some(prev) if l.sequence > prev => self.next_seq + (l.sequence - prev) as u64 - 1,
                    _ => self.next_seq,
                };
                self.last_left_sequence = Some(l.sequence);
                self.next_seq = seq + 1;
                self.stats.pairs += 1;
                self.stats.last_skew_ns = skew;
                self.stats.max_abs_skew_ns = self.stats.max_abs_skew_ns.max(skew.unsigned_abs());
                out.push(StereoFrame { seq, t_left_ns: l.t_ns, t_right_ns: r.t_ns, table_deg, left: l.picture, right: r.picture });
            } else if skew > 0 {
                // The left frame is older than any right frame can match.
                self.left.pop_front();
                self.stats.unpaired_left += 1;
            } else {
                self.right.pop_front();
                self.stats.unpaired_right += 1;
            }
        }
        while self.left.len() > self.backlog {
            self.left.pop_front();
            self.stats.unpaired_left += 1;
        }
        while self.right.len() > self.backlog {
            self.right.pop_front();
            self.stats.unpaired_right += 1;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(side: Side, t_ms: u64, sequence: u32) -> CameraFrame {
        CameraFrame { side, t_ns: t_ms * 1_000_000, sequence, picture: Picture::Raw { width: 1, height: 1, channels: 1, data: vec![sequence as u8] } }
    }

    #[test]
    fn pairs_follow_timestamps_and_count_the_unpaired() {
        let mut p = Pairer::new(33_000_000);
        // Interleaved arrival, right 3 ms after left.
        let mut pairs = Vec::new();
        for i in 0..3u32 {
            pairs.extend(p.push(frame(Side::Left, 1000 + 67 * i as u64, i), None));
            pairs.extend(p.push(frame(Side::Right, 1003 + 67 * i as u64, i + 10), None));
        }
        assert_eq!(pairs.iter().map(|f| f.seq).collect::<Vec<_>>(), vec![0, 1, 2]);
        assert!(pairs.iter().all(|f| f.t_right_ns - f.t_left_ns == 3_000_000));
        assert_eq!(p.stats.max_abs_skew_ns, 3_000_000);
        // The driver dropped left frames 3 and 4: seq jumps with the kernel counter; the
        // right frames of those periods find no partner and are counted.
        for i in 3..5u32 {
            assert!(p.push(frame(Side::Right, 1003 + 67 * i as u64, i + 10), None).is_empty());
        }
        let out = p.push(frame(Side::Left, 1000 + 67 * 5, 5), None);
        assert!(out.is_empty());
        let out = p.push(frame(Side::Right, 1003 + 67 * 5, 15), None);
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].seq, 5);
        assert_eq!(p.stats.unpaired_right, 2);
        assert_eq!(p.stats.pairs, 4);
    }

    #[test]
    fn a_late_frame_pairs_with_the_closest_and_a_stopped_camera_ages_out() {
        let mut p = Pairer::new(33_000_000);
        // Left at 1000 and 1066; right frames at 1030 (within tolerance of both) then 1064:
        // the right 1030 goes with left 1000.
        assert!(p.push(frame(Side::Left, 1000, 0), None).is_empty());
        assert!(p.push(frame(Side::Left, 1066, 1), None).is_empty());
        let out = p.push(frame(Side::Right, 1030, 0), None);
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].t_left_ns, 1_000_000_000);
        let out = p.push(frame(Side::Right, 1064, 1), None);
        assert_eq!(out[0].t_left_ns, 1_066_000_000);
        // The right camera stops: left frames pile up to the backlog, then count as unpaired.
        for i in 0..20u32 {
            assert!(p.push(frame(Side::Left, 2000 + 67 * i as u64, 2 + i), None).is_empty());
        }
        assert_eq!(p.stats.unpaired_left, 12);
        // Two frames too far apart never pair.
        let mut q = Pairer::new(10_000_000);
        q.push(frame(Side::Left, 1000, 0), None);
        assert!(q.push(frame(Side::Right, 1050, 0), None).is_empty());
        assert_eq!(q.stats.unpaired_left, 1);
    }
}
