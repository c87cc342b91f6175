//! The capture task: the turntable's moves (step-and-shoot or one continuous turn) and the
//! pairs, each sent to the recorder, announced to registration, and queued for the matchers
//! (step mode waits for room; continuous mode drops the oldest waiting pair).

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, TrySendError};

use super::state::{Devices, Job, Note, PipelineSettings, ScanError, ScanMode, ScanShared};
use crate::hw::{PairStats, StereoFrame, TurntableError};

/// Takes the first pair: one captured after the scan started (free-running cameras have
/// been streaming since the daemon started; what waits in their buffers is stale), with the
/// table's angle at its exposure.
pub(super) fn capture_first(devices: &mut Devices, shared: &ScanShared) -> Result<Option<StereoFrame>, ScanError> {
    let mut f = devices.source.fresh_frame()?;
    if let (Some(t), Some(f)) = (devices.turntable.as_mut(), f.as_mut()) {
        if f.table_deg.is_none() {
            f.table_deg = Some(t.angle_at(f.t_left_ns)?);
        }
        shared.counters.table_deg_bits.store(f.table_deg.unwrap_or(0.0).to_bits(), Ordering::Relaxed);
    }
    Ok(f)
}

#[allow(clippy::too_many_arguments)]
pub(super) fn capture(
    devices: &mut Devices,
    shared: &ScanShared,
    first: StereoFrame,
    jobs: &Sender<Job>,
    jobs_rx: &Receiver<Job>,
    notes: &Sender<Note>,
    recorder: &Sender<StereoFrame>,
    settings: &PipelineSettings,
) -> Result<(), ScanError> {
    let spec = &shared.spec;
    let c = &shared.counters;
    let t0 = Instant::now();
    let mut sent = 0usize;
    let mut last_seq: Option<u64> = None;
    let mut first_at = Instant::now();
    let mut deliver = |mut frame: StereoFrame, pairing: Option<PairStats>| -> Result<(), ScanError> {
        if last_seq.is_some_and(|p| frame.seq <= p) {
            // A source restarted its numbering: keep seq strictly increasing.
            frame.seq = last_seq.unwrap() + 1;
        }
        last_seq = Some(frame.seq);
        if let Some(deg) = frame.table_deg {
            c.table_deg_bits.store(deg.to_bits(), Ordering::Relaxed);
        }
        if let Some(p) = pairing {
            c.unpaired.store(p.unpaired_left + p.unpaired_right, Ordering::Relaxed);
            c.max_skew_us.store(p.max_abs_skew_ns / 1000, Ordering::Relaxed);
        } else {
            let skew = (frame.t_right_ns as i64 - frame.t_left_ns as i64).unsigned_abs() / 1000;
            c.max_skew_us.fetch_max(skew, Ordering::Relaxed);
        }
        if c.captured.fetch_add(1, Ordering::Relaxed) == 0 {
            first_at = Instant::now();
        }
        c.capture_us.store(first_at.elapsed().as_micros() as u64, Ordering::Relaxed);
        shared.pulse();
        if settings.record {
            c.recorder_backlog.fetch_add(1, Ordering::Relaxed);
            recorder.send(frame.clone()).map_err(|_| ScanError::Stopped("recorder"))?;
        }
        let seq = frame.seq;
        notes.send(Note::Announce(seq)).map_err(|_| ScanError::Stopped("registration thread"))?;
        let mut job = Job { frame, captured: Instant::now() };
        match spec.mode {
            ScanMode::Step => {
                c.queued.fetch_add(1, Ordering::Relaxed);
                jobs.send(job).map_err(|_| ScanError::Stopped("matcher pool"))?;
            }
            ScanMode::Continuous => loop {
                match jobs.try_send(job) {
                    Ok(()) => {
                        c.queued.fetch_add(1, Ordering::Relaxed);
                        break;
                    }
                    Err(TrySendError::Full(j)) => {
                        job = j;
                        // Capture never waits: the oldest waiting pair makes room.
                        if let Ok(old) = jobs_rx.try_recv() {
                            c.queued.fetch_sub(1, Ordering::Relaxed);
                            c.dropped.fetch_add(1, Ordering::Relaxed);
                            let _ = notes.send(Note::Skipped { seq: old.frame.seq, why: "dropped: the matcher pool was behind".into() });
                        }
                    }
                    Err(TrySendError::Disconnected(_)) => return Err(ScanError::Stopped("matcher pool")),
                }
            },
        }
        sent += 1;
        if let Some(hz) = settings.pace_hz {
            let due = t0 + Duration::from_secs_f64(sent as f64 / hz);
            if let Some(wait) = due.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
        }
        Ok(())
    };

    if let Some(t) = devices.turntable.as_mut() {
        // A stop request ends any wait for the table (bounded stop, whatever it does).
        t.watch_stop(shared.stop_signal());
    }
    let start_deg = first.table_deg;
    deliver(first, devices.source.pairing())?;
    let limit = spec.max_views.unwrap_or(usize::MAX);
    match (spec.mode, devices.turntable.is_some()) {
        (ScanMode::Step, true) => {
            let start = start_deg.unwrap_or(0.0);
            for i in 1..spec.step_views() {
                if shared.stop_requested() {
                    break;
                }
                let target = start + i as f64 * spec.step_deg;
                let table = devices.turntable.as_mut().unwrap();
                // The angle read back: the table stops on a whole motor step, not on `target`.
                let arrived = match table.move_to(target) {
                    Ok(a) => a,
                    Err(TurntableError::Aborted { .. }) if shared.stop_requested() => {
                        // Stopped mid-move: bring the table to rest the safe way, and end.
                        if let Err(e) = table.halt() {
                            tracing::warn!("stopping the table after a stop request: {e}");
                        }
                        break;
                    }
                    Err(e) => return Err(e.into()),
                };
                let mut frame = match devices.source.fresh_frame()? {
                    Some(f) => f,
                    None => break,
                };
                frame.table_deg.get_or_insert(arrived);
                deliver(frame, devices.source.pairing())?;
            }
        }
        (ScanMode::Continuous, true) => {
            let table = devices.turntable.as_mut().unwrap();
            let start = table.angle()?;
            let end = start + spec.total_deg;
            table.start_move(end, spec.speed_deg_s)?;
            // A table that stops short (stalled, unplugged mid-move) must not keep a scan
            // capturing forever.
            let allowed = Duration::from_secs_f64(spec.total_deg / spec.speed_deg_s * 1.5 + 10.0);
            let deadline = Instant::now() + allowed;
            let (mut last_t_ns, mut frame_period_s) = (None::<u64>, 1.0 / 15.0);
            let outcome = (|| -> Result<(), ScanError> {
                let mut n = 1;
                while n < limit && !shared.stop_requested() {
                    let Some(mut frame) = devices.source.next_frame()? else { break };
                    if let Some(prev) = last_t_ns.replace(frame.t_left_ns) {
                        if frame.t_left_ns > prev {
                            frame_period_s = (frame.t_left_ns - prev) as f64 / 1e9;
                        }
                    }
                    let table = devices.turntable.as_mut().unwrap();
                    let deg = match frame.table_deg {
                        Some(d) => d,
                        None => {
                            // The angle at the pair's exposure, not at its dequeue.
                            let d = table.angle_at(frame.t_left_ns)?;
                            frame.table_deg = Some(d);
                            d
                        }
                    };
                    if Instant::now() > deadline {
                        return Err(ScanError::TableShort { total_deg: spec.total_deg, allowed_s: allowed.as_secs_f64(), speed_deg_s: spec.speed_deg_s, at_deg: deg, start_deg: start });
                    }
                    // A full turn's last pair would repeat the first view.
                    // Within half a pair's turn of the end (the cameras' rate from the pairs'
                    // timestamps; 15 fps until two are known).
                    // The table itself stops on a whole motor step, up to half a step short.
                    let half_step = 0.5 * spec.speed_deg_s * frame_period_s;
                    let table_tolerance = (0.5 * table.resolution_deg()).max(1e-6);
                    let done = deg >= end - table_tolerance || (spec.total_deg >= 360.0 && deg >= end - half_step);
                    if done && spec.total_deg >= 360.0 {
                        break;
                    }
                    deliver(frame, devices.source.pairing())?;
                    n += 1;
                    if done {
                        break;
                    }
                }
                Ok(())
            })();
            // Stop the table whatever happened (it may be mid-move after a stop request).
            let halted = devices.turntable.as_mut().unwrap().halt();
            outcome?;
            halted.map_err(ScanError::Halt)?;
        }
        (_, false) => {
            // No turntable (a replay): every pair of the source.
            let mut n = 1;
            while n < limit && !shared.stop_requested() {
                let Some(frame) = devices.source.next_frame()? else { break };
                deliver(frame, devices.source.pairing())?;
                n += 1;
            }
        }
    }
    // The scan is over: the motor need not hold the table (a Horus board keeps it energised).
    if let Some(t) = devices.turntable.as_mut() {
        if let Err(e) = t.release() {
            tracing::warn!("cannot switch the turntable's motor off: {e}");
        }
    }
    Ok(())
}
