//! The registration thread: takes finished views in `seq` order (a reorder buffer fed by the
//! capture task's announcements), writes each to the results folder, registers it (or only
//! the newest when behind), publishes poses to the shared [`PoseStore`], and at the end
//! closes the loop and merges the model. It runs at a lower priority than the matchers.

use std::collections::BTreeMap;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender};
use serde_json::json;

use super::fusion::{announce_mesh, LiveFusion};
use super::state::{lower_priority, ms_since, Note, PipelineSettings, ScanError, ScanMode, ScanShared, Stage};
use crate::pipeline::registered::{finish_registration, register_view, ModelOptions};
use crate::pipeline::results::ResultsWriter;
use crate::register::posestore::PoseStore;

#[allow(clippy::too_many_arguments)]
pub(super) fn register_loop(
    mut results: ResultsWriter,
    notes: Receiver<Note>,
    views: Receiver<Note>,
    observers: Vec<Sender<(u64, f64, f64)>>,
    store: Arc<PoseStore>,
    shared: Arc<ScanShared>,
    settings: PipelineSettings,
) -> (ResultsWriter, Result<(), ScanError>) {
    // Registration yields the cores to the matchers: its thread and its own worker pool run
    // at a lower priority (nice +REGISTER_NICE), so a busy registration delays poses, not
    // views.
    lower_priority(REGISTER_NICE);
    let pool = rayon::ThreadPoolBuilder::new().thread_name(|i| format!("register-{i}")).start_handler(|_| lower_priority(REGISTER_NICE)).build();
    let outcome = match pool {
        Ok(pool) => pool.install(|| register_all(&mut results, notes, views, observers, store, &shared, &settings)),
        Err(_) => register_all(&mut results, notes, views, observers, store, &shared, &settings),
    };
    (results, outcome)
}

#[allow(clippy::too_many_arguments)]
fn register_all(
    results: &mut ResultsWriter,
    notes: Receiver<Note>,
    views: Receiver<Note>,
    observers: Vec<Sender<(u64, f64, f64)>>,
    store: Arc<PoseStore>,
    shared: &Arc<ScanShared>,
    settings: &PipelineSettings,
) -> Result<(), ScanError> {
    let mut registrar = settings.registration.clone().map(|p| crate::pipeline::registrar(p, settings.calibrated_axis.as_ref(), None, store.clone()));
    // The live surface (fusion.rs): registered views, fused as their poses are published.
    let live = match (&registrar, ModelOptions::default().mesh) {
        (Some(_), Some(params)) => Some(LiveFusion::start(shared.clone(), params, REGISTER_NICE + 2)),
        _ => None,
    };
    let mut expected = std::collections::VecDeque::new();
    let mut done: BTreeMap<u64, Note> = BTreeMap::new();
    let c = &shared.counters;
    let mut last_progress = Instant::now() - Duration::from_secs(1);
    let newest_only = shared.spec.mode == ScanMode::Continuous || settings.register_newest_when_behind;
    let mut process = |note: Note, results: &mut ResultsWriter, behind: bool| -> Result<(), ScanError> {
        match note {
            Note::View { frame_meta, view, captured } => {
                let t_write = Instant::now();
                let mut entry = results.write_view(&frame_meta, &view, settings.assist.as_ref())?;
                let mut write_ms = ms_since(t_write);
                if registrar.is_some() && newest_only && behind && captured.elapsed() > SKIP_AFTER {
                    // A continuous scan sees the object at 15 fps: when newer views wait and
                    // this one is already late, it is kept (views/, disparity/) but not
                    // registered, so that the poses stay fresh. A short backlog (a block
                    // step's longer view) is worked off instead.
                    entry["registered"] = json!(false);
                    entry["register_skipped"] = json!(format!("newer views were waiting and this one was captured more than {} ms ago (registration is behind; the newest view is registered)", SKIP_AFTER.as_millis()));
                    c.register_skipped.fetch_add(1, Ordering::Relaxed);
                } else if let Some(reg) = registrar.as_mut() {
                    let t_register = Instant::now();
                    let registered = register_view(reg, &frame_meta, &view, &mut entry);
                    c.add_stage(Stage::Register, ms_since(t_register));
                    if let Some((fitness, rmse)) = registered {
                        for o in &observers {
                            let _ = o.send((frame_meta.seq, fitness, rmse));
                        }
                    }
                    // The poses as the view's registration just published them (the
                    // turntable's, once an axis fitted to the views so far passes its tests;
                    // register::ring::live).
                    let published = store.snapshot();
                    if let (Some(live), Some(p)) = (&live, published.views.iter().rev().find(|p| p.seq == frame_meta.seq)) {
                        live.add(&view.cloud, &p.first_from_view);
                    }
                    results.write_poses(&published.views)?;
                    if let Some(p) = reg.poses().last() {
                        c.pose_deg_bits.store(reg.turned_deg().to_bits(), Ordering::Relaxed);
                        c.pose_seq.store(p.seq + 1, Ordering::Relaxed);
                    }
                }
                if entry.get("registered").is_none() {
                    // Capture → the pose published (before the long and block steps ran on).
                    let after_publish = entry["register_ms"].as_f64().zip(entry["publish_ms"].as_f64()).map_or(0.0, |(r, p)| (r - p).max(0.0));
                    let lag = (captured.elapsed().as_micros() as u64).saturating_sub((after_publish * 1e3) as u64);
                    entry["registration_lag_ms"] = json!(lag as f64 / 1e3);
                    c.lag_sum_us.fetch_add(lag, Ordering::Relaxed);
                    c.lag_max_us.fetch_max(lag, Ordering::Relaxed);
                    c.registered.fetch_add(1, Ordering::Relaxed);
                }
                let t_push = Instant::now();
                results.push_frame(entry)?;
                write_ms += ms_since(t_push);
                c.add_stage(Stage::Write, write_ms);
            }
            Note::Skipped { seq, why } => results.note_skipped(seq, &why),
            Note::Announce(_) => unreachable!("announcements are not queued"),
        }
        shared.pulse();
        if last_progress.elapsed() >= Duration::from_millis(200) {
            last_progress = Instant::now();
            shared.emit("scan.progress", shared.progress());
        }
        Ok(())
    };
    let (mut notes_open, mut views_open) = (true, true);
    while notes_open || views_open {
        let note = crossbeam_channel::select! {
            recv(if notes_open { Some(&notes) } else { None }.unwrap_or(&crossbeam_channel::never())) -> n => match n {
                Ok(n) => n,
                Err(_) => { notes_open = false; continue; }
            },
            recv(if views_open { Some(&views) } else { None }.unwrap_or(&crossbeam_channel::never())) -> n => match n {
                Ok(n) => n,
                Err(_) => { views_open = false; continue; }
            },
        };
        let seq = match &note {
            Note::Announce(seq) => {
                expected.push_back(*seq);
                continue;
            }
            Note::View { frame_meta, .. } => frame_meta.seq,
            Note::Skipped { seq, .. } => *seq,
        };
        done.insert(seq, note);
        while let Some(next) = expected.front() {
            let Some(note) = done.remove(next) else { break };
            expected.pop_front();
            // Behind: a newer view is finished already, or waits in the channel.
            let behind = done.values().any(|n| matches!(n, Note::View { .. })) || !views.is_empty();
            process(note, results, behind)?;
        }
    }
    // Whatever is left (announced pairs whose matcher never reported: a panic) is skipped.
    for seq in expected {
        match done.remove(&seq) {
            Some(note) => process(note, results, false)?,
            None => results.note_skipped(seq, "never matched"),
        }
    }
    shared.emit("scan.progress", shared.progress());
    // (A mesh asked for now is answered from the live field before it goes.)
    drop(live);
    if let Some(reg) = registrar.as_mut() {
        if reg.poses().len() >= 2 {
            let section = finish_registration(reg, results, &ModelOptions::default(), &Default::default()).map_err(ScanError::Model)?;
            // A mesh asked for after the live field went is answered by the scan's own.
            if shared.take_mesh_request() {
                announce_mesh(shared, &shared.dir.join("mesh.ply"), &section["mesh"], None);
            }
        }
    }
    Ok(())
}

/// Finished views waiting for the registration thread before the matchers wait (a view is
/// about 4 MB at 640×480).
pub(super) const VIEW_BACKLOG: usize = 4;

/// When registering only the newest view when behind (continuous scans), a view waits at most
/// this long after its capture before newer views make it skip registration: longer than a
/// frame period, so that one slow view does not cost the next its pose, and well inside the
/// 200 ms the matchers can wait for a fresh pose.
const SKIP_AFTER: Duration = Duration::from_millis(120);

/// Nice value of the registration threads, above the matchers' (capture and the control
/// socket stay at the process's).
const REGISTER_NICE: i32 = super::pool::MATCHER_NICE + 5;
