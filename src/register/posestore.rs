//! The shared pose store: one registration thread publishes, many matcher threads read.
//!
//! The writer builds a new immutable [`PoseSnapshot`] outside any lock and swaps an `Arc` in;
//! a reader clones the `Arc` under the same mutex. The lock is held for a pointer copy on
//! either side, so neither can keep the other waiting for longer than that, and a reader
//! always sees one consistent snapshot (all poses of the same generation).

use std::sync::{Arc, Mutex};

use nalgebra::Isometry3;

/// The registered pose of one view.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewPose {
    pub seq: u64,
    /// Maps the view's points into the first view's frame.
    pub first_from_view: Isometry3<f64>,
    /// Turntable angle of the view, when recorded.
    pub table_deg: Option<f64>,
}

/// Everything published at once.
#[derive(Debug, Clone, Default)]
pub struct PoseSnapshot {
    /// Bumped on every publication.
    pub generation: u64,
    /// Registered views in order of `seq`.
    pub views: Vec<ViewPose>,
}

impl PoseSnapshot {
    /// The latest registered view.
    pub fn latest(&self) -> Option<&ViewPose> {
        self.views.last()
    }

    /// The pose of view `seq`, if registered.
    pub fn get(&self, seq: u64) -> Option<&ViewPose> {
        self.views.binary_search_by_key(&seq, |v| v.seq).ok().map(|i| &self.views[i])
    }

    /// Motion between the last two registered views, `prev_from_latest`.
    pub fn last_motion(&self) -> Option<Isometry3<f64>> {
        let n = self.views.len();
        (n >= 2).then(|| self.views[n - 2].first_from_view.inverse() * self.views[n - 1].first_from_view)
    }
}

/// See the module docs.
#[derive(Debug, Default)]
pub struct PoseStore {
    current: Mutex<Arc<PoseSnapshot>>,
}

impl PoseStore {
    pub fn new() -> PoseStore {
        PoseStore::default()
    }

    /// The current snapshot (cheap: an `Arc` clone).
    pub fn snapshot(&self) -> Arc<PoseSnapshot> {
        self.current.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Publishes `views` as the next generation.
    pub fn publish(&self, views: Vec<ViewPose>) {
        let generation = self.snapshot().generation + 1;
        let next = Arc::new(PoseSnapshot { generation, views });
        *self.current.lock().unwrap_or_else(|e| e.into_inner()) = next;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readers_always_see_whole_generations() {
        let store = Arc::new(PoseStore::new());
        let writer = {
            let store = store.clone();
            std::thread::spawn(move || {
                for g in 1..=300u64 {
                    // Every view of generation g carries translation x = g.
                    let views = (0..g).map(|seq| ViewPose { seq, first_from_view: Isometry3::translation(g as f64, 0.0, 0.0), table_deg: None }).collect();
                    store.publish(views);
                }
            })
        };
        let readers: Vec<_> = (0..4)
            .map(|_| {
                let store = store.clone();
                std::thread::spawn(move || {
                    let mut last = 0;
                    for _ in 0..2000 {
                        let s = store.snapshot();
                        assert!(s.generation >= last, "generations never go back");
                        last = s.generation;
                        assert_eq!(s.views.len() as u64, s.generation);
                        assert!(s.views.iter().all(|v| v.first_from_view.translation.x == s.generation as f64));
                    }
                })
            })
            .collect();
        writer.join().unwrap();
        for r in readers {
            r.join().unwrap();
        }
        let s = store.snapshot();
        assert_eq!(s.generation, 300);
        assert_eq!(s.get(7).unwrap().seq, 7);
        assert_eq!(s.last_motion().unwrap(), Isometry3::identity());
    }
}
