//! [`RegistrationParams`]: every setting of sequence registration and its default.

use nalgebra::Vector3;

use crate::register::bundle::BundleParams;
use crate::register::icp::IcpParams;
use crate::register::refine::RefineParams;
use crate::register::tracks::{TrackCamera, TrackParams};

/// Settings of sequence registration; distances in the clouds' units (mm for views).
#[derive(Debug, Clone)]
pub struct RegistrationParams {
    pub icp: IcpParams,
    /// m of Algorithm 1: views per block registered to the model (0 = no block step).
    pub block: usize,
    /// At most this many points of each view kept as an ICP target.
    pub max_target_points: usize,
    /// Voxel of the running model used by the block step.
    pub model_voxel: f64,
    /// Close the loop when the views complete a turn.
    pub close_loop: bool,
    /// Views on each side of the closing edge.
    pub loop_views: usize,
    /// Replace the poses with the turntable's predictions when they all agree (see the
    /// module docs).
    pub turntable_poses: bool,
    /// Largest disagreement, degrees, of a pairwise registration with the turntable's
    /// predicted step beyond the typical step's (a slip), and of the typical step itself
    /// unless the turntable's poses fit the views better, for which the predictions are used.
    pub max_turntable_deviation_deg: f64,
    /// ICP results below this fitness are not trusted: the seed is kept and a warning given.
    pub min_fitness: f64,
    /// Estimate the axis once the poses span this much rotation, degrees.
    pub axis_min_span_deg: f64,
    /// Every `axis_long_step_every`-th view is also registered to the earlier view about this
    /// many degrees before it (at most 32 views back), and the axis is estimated from those
    /// long steps (0 = off: the axis comes from the chained poses).
    pub axis_baseline_deg: f64,
    pub axis_long_step_every: usize,
    /// A calibrated axis (point, unit up), when the recording has one.
    pub calibrated_axis: Option<(Vector3<f64>, Vector3<f64>)>,
    /// The turntable refinement at the end of a scan without a calibrated axis
    /// (`register::refine`): the axis fitted to every view at once.
    pub refine: RefineParams,
    /// Points of each view kept for the refinement.
    pub refine_points: usize,
    /// A refined axis whose direction is known to this many degrees (one standard deviation)
    /// or better gives turntable poses; a less certain one only when its poses put the views
    /// onto each other as well as the registered ones, within 1 % (see the module docs).
    pub max_axis_sigma_deg: f64,
    /// Per-view targets (the chain, the long steps, the block step) are range grids paired
    /// by projection ([`super::grid`]): a few distance computations per query and no tree to
    /// build per view. False: exact nearest neighbours on a cell grid (loop closure and the
    /// symmetry test always use those, the refinement a k-d tree).
    pub projective: bool,
    /// The rectified left camera of the views: with it (and table angles, and no calibrated
    /// axis) the object's texture is tracked from view to view (`register::tracks`) and the
    /// axis fitted to the tracks at the end of the scan (`register::bundle`). The pipeline
    /// sets it from the rig's rectification.
    pub track_camera: Option<TrackCamera>,
    /// Tracking settings; None: no tracks, the axis from the views' points alone.
    pub tracks: Option<TrackParams>,
    pub bundle: BundleParams,
}

impl Default for RegistrationParams {
    /// For spinscan's millimetre views: point-to-plane ICP with pairs up to 8 mm apart,
    /// 4000 source points per view and at most 12 iterations, 40 000 target points, Huber weights beyond 1 mm; blocks of
    /// m = 5; a 2 mm running model; loop closure on, one view a side; turntable poses when every step agrees to 1.5°; fitness below 0.3 distrusted; the axis
    /// estimated after 9° of turn.
    fn default() -> Self {
        let mut icp = IcpParams::new(8.0);
        icp.max_source_points = 4000;
        icp.kernel = crate::register::Kernel::Huber(1.0);
        // A smooth, nearly symmetric object (the egg) never converges: its clouds' camera-fixed
        // errors drag the turn towards "no motion" a little every iteration. 12 iterations
        // bound that drift and the time; well-shaped views converge in 8–11 (the torus).
        // Measured on 120-view rings: the final poses as good or better than with 20 or 50.
        icp.max_iterations = 12;
        // Converged once a step moves less than 0.006° and 1e-4 of the view's size (≈ 4 µm):
        // the live poses are refined at the end of the scan anyway.
        icp.min_step_rad = 1e-4;
        icp.min_step_rel = 1e-4;

        RegistrationParams {
            icp,
            block: 5,
            max_target_points: 40_000,
            model_voxel: 2.0,
            close_loop: true,
            loop_views: 1,
            turntable_poses: true,
            max_turntable_deviation_deg: 1.5,
            min_fitness: 0.3,
            axis_min_span_deg: 9.0,
            axis_baseline_deg: 24.0,
            axis_long_step_every: 4,
            calibrated_axis: None,
            refine: RefineParams::default(),
            refine_points: 1500,
            max_axis_sigma_deg: 0.05,
            projective: true,
            track_camera: None,
            tracks: Some(TrackParams::default()),
            bundle: BundleParams::default(),
        }
    }
}

