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
