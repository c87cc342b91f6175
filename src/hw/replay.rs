//! A recording replayed through the camera seam, frame by frame (no turntable: the angles
//! are the recorded ones).

use super::{CaptureError, StereoFrame, StereoSource};
use crate::calib::StereoCalib;
use crate::recording::Recording;

/// Replays a recording through the camera seam, frame by frame.
pub struct ReplaySource {
    recording: Recording,
    next: usize,
}

impl ReplaySource {
    pub fn new(recording: Recording) -> ReplaySource {
        ReplaySource { recording, next: 0 }
    }

    pub fn recording(&self) -> &Recording {
        &self.recording
    }
}

impl StereoSource for ReplaySource {
    fn describe(&self) -> String {
        format!("recording {}", self.recording.dir.display())
    }

    fn calibration(&self) -> &StereoCalib {
        &self.recording.calib
    }

    fn next_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
        if self.next >= self.recording.frames.len() {
            return Ok(None);
        }
        let frame = self.recording.load_frame(self.next)?;
        self.next += 1;
        Ok(Some(frame))
    }
}
