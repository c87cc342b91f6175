//! A matcher of the pool: takes pairs from the bounded channel, plans each with its own
//! [`crate::assist::Assistant`] from the shared [`PoseStore`], runs
//! [`Pipeline::process_frame`], and hands the view to registration.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use crossbeam_channel::{Receiver, Sender};

use super::state::{lower_priority, ms_since, Job, Note, PipelineSettings, ScanShared, Stage};
use crate::pipeline::{Assist, Pipeline};
use crate::register::posestore::PoseStore;

/// Nice value of the matcher threads (and the recorder's): the scan's bulk work yields the
/// cores to capture and to the control socket, which need little CPU but need it at once
/// (`cargo bench --bench daemon -- status`, `docs/daemon.md`). Threads a matcher starts
/// inherit it.
pub(super) const MATCHER_NICE: i32 = 2;

pub(super) fn matcher_loop(mut pipe: Pipeline, jobs: Receiver<Job>, notes: Sender<Note>, observed: Receiver<(u64, f64, f64)>, store: Arc<PoseStore>, shared: Arc<ScanShared>, settings: PipelineSettings) {
    lower_priority(MATCHER_NICE);
    let mut assistant = settings.assist_in_use().map(|a| pipe.assistant(a.clone()));
    let c = &shared.counters;
    let plate = settings.plate.as_ref().map(|p| pipe.rectify_plate(&p.rgb));
    for job in jobs {
        c.queued.fetch_sub(1, Ordering::Relaxed);
        let seq = job.frame.seq;
        if let Some(a) = assistant.as_mut() {
            for (s, fitness, rmse) in observed.try_iter() {
                a.observe_registration(s, fitness, rmse);
            }
        }
        let poses = store.snapshot();
        let assist = assistant.as_mut().map(|assistant| Assist { assistant, poses: &poses });
        // `Pipeline::process_frame`'s three steps, each timed (`scan.progress`'s `stage_ms`).
        let t0 = Instant::now();
        let view = pipe.prepare_frame(&job.frame, settings.segment, plate.as_ref()).and_then(|prepared| {
            c.add_stage(Stage::Prepare, ms_since(t0));
            let m = pipe.match_frame(seq, &prepared, assist)?;
            c.add_stage(Stage::Match, m.outcome.match_ms);
            if m.assisted {
                c.add_stage(Stage::Assist, m.outcome.interval_ms);
            }
            let t1 = Instant::now();
            let view = pipe.finish_view(prepared, m);
            c.add_stage(Stage::Triangulate, ms_since(t1));
            Ok(view)
        });
        let meta = job.frame.meta();
        let note = match view {
            Ok(view) => {
                c.matched.fetch_add(1, Ordering::Relaxed);
                c.matched_us.fetch_max(shared.started.elapsed().as_micros() as u64, Ordering::Relaxed);
                Note::View { frame_meta: meta, view: Box::new(view), captured: job.captured }
            }
            Err(e) => {
                c.failed.fetch_add(1, Ordering::Relaxed);
                tracing::warn!("frame seq {seq}: not matched: {e} (the pair is recorded)");
                Note::Skipped { seq, why: e.to_string() }
            }
        };
        shared.pulse();
        if notes.send(note).is_err() {
            return;
        }
    }
}
