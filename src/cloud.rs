//! Point clouds and meshes in memory.

/// Coloured points, optionally with normals. Units and frame are the producer's; spinscan's
/// own clouds are millimetres in a LEFT raw camera frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    pub points: Vec<[f32; 3]>,
    /// One per point, RGB (same length as `points`).
    pub colors: Vec<[u8; 3]>,
    /// One per point when present.
    pub normals: Option<Vec<[f32; 3]>>,
    /// One per point when present: how far inside the object's silhouette the point's pixel
    /// lay in the view it was matched in, pixels (a square neighbourhood; capped at 255:
    /// [`crate::segment::rim_distance`]). The fusion weighs points near the silhouette down
    /// (`FuseParams::rim_weight_px`). PLY: `property uchar rim_px`.
    pub rim_px: Option<Vec<u8>>,
}

impl PointCloud {
    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
}

/// A cloud with triangles (polygons of a PLY file are fanned into triangles).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub cloud: PointCloud,
    pub triangles: Vec<[u32; 3]>,
}
