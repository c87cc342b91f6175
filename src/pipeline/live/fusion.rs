//! The scan's live surface: every view integrated into a fused field as soon as its pose is
//! published, on a thread of its own below registration's priority, and a mesh of what is
//! fused so far written to `mesh_live.ply` when a client asks (`scan.mesh`). The scan's
//! final `mesh.ply` is fused again from every view with the refined poses at its end
//! (`finish_registration`); the live field is the preview.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::path::Path;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender, TrySendError};
use nalgebra::Isometry3;
use serde_json::{json, Value};

use super::state::{lower_priority, ScanShared};
use crate::cloud::PointCloud;
use crate::fuse::{FuseParams, Tsdf};

/// Views waiting for the fusion thread; when it falls further behind, a view is left out of
/// the preview (never out of `mesh.ply`) rather than slow registration down.
const BACKLOG: usize = 8;

/// How often the fusion thread looks for a mesh request while no view comes.
const POLL: Duration = Duration::from_millis(100);

/// The live field's thread; dropping it ends the thread (answering a pending request first).
pub(super) struct LiveFusion {
    tx: Option<Sender<(PointCloud, Isometry3<f64>)>>,
    handle: Option<JoinHandle<()>>,
    shared: Arc<ScanShared>,
}

impl LiveFusion {
    pub(super) fn start(shared: Arc<ScanShared>, params: FuseParams, nice: i32) -> LiveFusion {
        let (tx, rx) = crossbeam_channel::bounded(BACKLOG);
        let sh = shared.clone();
        let handle = std::thread::Builder::new()
            .name("fuse".into())
            .spawn(move || {
                lower_priority(nice);
                run(rx, &sh, params)
            })
            .ok();
        LiveFusion { tx: handle.as_ref().map(|_| tx), handle, shared }
    }

    /// Hands a registered view to the fusion thread (left out of the preview, and counted,
    /// when the thread is `BACKLOG` views behind).
    pub(super) fn add(&self, cloud: &PointCloud, first_from_view: &Isometry3<f64>) {
        let Some(tx) = &self.tx else { return };
        if let Err(TrySendError::Full(_)) = tx.try_send((cloud.clone(), *first_from_view)) {
            self.shared.counters.live_fusion_skipped.fetch_add(1, Ordering::Relaxed);
        }
    }
}

impl Drop for LiveFusion {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

fn run(rx: Receiver<(PointCloud, Isometry3<f64>)>, shared: &ScanShared, params: FuseParams) {
    let Ok(mut tsdf) = Tsdf::new(params) else { return };
    loop {
        let open = match rx.recv_timeout(POLL) {
            Ok((cloud, pose)) => {
                tsdf.integrate(&cloud, &pose);
                true
            }
            Err(RecvTimeoutError::Timeout) => true,
            Err(RecvTimeoutError::Disconnected) => false,
        };
        if shared.take_mesh_request() {
            // The preview holds every view registered before the request: those still
            // waiting (a loaded machine starves this thread, which runs below registration's
            // priority) are fused first. A single view at a coarse sampling can leave no cube
            // of the field seen at all eight corners, so a preview of fewer views than the
            // client saw registered can come out empty.
            for _ in 0..rx.len() {
                let Ok((cloud, pose)) = rx.try_recv() else { break };
                tsdf.integrate(&cloud, &pose);
            }
            write_preview(&tsdf, shared);
        }
        if !open {
            return;
        }
    }
}

/// `mesh_live.ply` from the views fused so far, announced by a `scan.mesh` event (with the
/// reason when it could not be written).
fn write_preview(tsdf: &Tsdf, shared: &ScanShared) {
    let path = shared.dir.join("mesh_live.ply");
    let start = Instant::now();
    let (mesh, stats) = tsdf.mesh();
    let figures = crate::pipeline::mesh::mesh_json(tsdf, &stats, start.elapsed().as_secs_f64() * 1e3);
    let error = crate::io::mesh::write_mesh(&path, &mesh).err().map(|e| e.to_string());
    announce_mesh(shared, &path, &figures, error);
}

/// The `scan.mesh` event for a mesh written to `file`, from its figures (`mesh_json`'s).
pub(super) fn announce_mesh(shared: &ScanShared, file: &Path, figures: &Value, error: Option<String>) {
    let mut about = json!({"name": shared.spec.name, "file": file.display().to_string()});
    for key in ["views", "vertices", "triangles", "holes_filled"] {
        about[key] = figures[key].clone();
    }
    if let Some(e) = error {
        about["error"] = json!(e);
    }
    shared.emit("scan.mesh", about);
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use super::*;
    use crate::pipeline::live::{ScanMode, ScanSpec};

    /// A flat 20 × 20 mm patch 300 mm ahead, sampled every 0.5 mm.
    fn patch() -> PointCloud {
        let mut cloud = PointCloud::default();
        for i in 0..40 {
            for j in 0..40 {
                cloud.points.push([i as f32 * 0.5 - 10.0, j as f32 * 0.5 - 10.0, 300.0]);
                cloud.colors.push([200, 200, 200]);
            }
        }
        cloud
    }

    /// A request that finds views still waiting (the thread was starved) is answered with
    /// all of them fused, not with the first alone: the client saw them registered.
    #[test]
    fn a_preview_fuses_every_view_waiting_when_it_is_asked_for() {
        let dir = std::env::temp_dir().join(format!("spinscan-live-fusion-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let events: Arc<Mutex<Vec<Value>>> = Arc::default();
        let sink = events.clone();
        let spec = ScanSpec { name: "starved".into(), mode: ScanMode::Step, step_deg: 45.0, total_deg: 360.0, speed_deg_s: 6.0, max_views: None };
        let shared = ScanShared::new(spec, dir.clone(), Box::new(move |m, v| sink.lock().unwrap().push(json!({"method": m, "params": v}))));
        let (tx, rx) = crossbeam_channel::bounded(BACKLOG);
        for k in 0..3 {
            tx.send((patch(), Isometry3::translation(0.1 * k as f64, 0.0, 0.0))).unwrap();
        }
        shared.request_mesh();
        drop(tx);
        run(rx, &shared, FuseParams::default());
        let events = events.lock().unwrap();
        let meshes: Vec<&Value> = events.iter().filter(|e| e["method"] == "scan.mesh").collect();
        assert_eq!(meshes.len(), 1, "{events:?}");
        let about = &meshes[0]["params"];
        assert_eq!(about["views"], 3, "{about}");
        assert!(about["triangles"].as_u64().unwrap() > 0 && about.get("error").is_none(), "{about}");
        assert!(dir.join("mesh_live.ply").is_file());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
