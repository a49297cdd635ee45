//! The per-frame registration pipeline and its latency breakdown.

use super::confidence::{Confidence, ConfidenceReference, frame_confidence};
use super::correction::{CoarseCarried, CoarseFit, CorrectionReport, CorrectionSettings, FormFigures, SurfaceFit};
use super::icp::{IcpReport, IcpSettings, icp_point_to_plane};
use super::overlay::{compose_overlay, depth_preview, rasterize_silhouette, structure_layer};
use super::{RegistrationContext, displacement_at};
use crate::fem::MaterialParams;
use crate::fem::solver::fit::{FitWork, PointFitReport, PointFitSettings};
use crate::progress::{Cancel, Progress};
use crate::rgbd::segment::{SegmentSettings, segment_frame};
use crate::rgbd::stream::{FrameSource, Poll};
use crate::rgbd::{ColorImage, DepthImage, Frame, Intrinsics, rigid_inverse, transform_point};
use nalgebra::{Matrix4, Vector3};
use std::path::Path;
use std::time::{Duration, Instant};

/// Why a frame was skipped: its input (no organ pixel, a bad frame, a fit that failed), or the
/// model's prediction, with the model's own error as the source.
#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    #[error(transparent)]
    Invalid(#[from] crate::Invalid),
    #[error("frame {frame}: {model}: {source}")]
    Model {
        frame: usize,
        model: String,
        #[source]
        source: crate::ModelError,
    },
}

/// Volume displacement from surface displacement: the network, or the FE model.
pub trait DisplacementModel: Send {
    fn name(&self) -> String;
    /// u_s [3, X, Y, Z] (mm), or the encoded observation when `observation` is Some ->
    /// u_v [3, X, Y, Z] (mm), written into `out`.
    fn predict(&mut self, u_s: &[f32], out: &mut Vec<f32>) -> Result<(), crate::ModelError>;
    /// The observation encoding the model takes; None: the surface displacement u_s.
    fn observation(&self) -> Option<crate::observation::ObservationSettings> {
        None
    }
    /// Fit the frame's organ points (world, mm) directly, for models that do (the FE
    /// baseline): Some(surface samples matched) with the field in `out`.
    fn fit_points(
        &mut self,
        _points_world_mm: &[Vector3<f64>],
        _out: &mut Vec<f32>,
    ) -> Option<Result<usize, crate::Invalid>> {
        None
    }
    /// The range of the confidence figures on the model's validation views, if measured.
    fn confidence_reference(&self) -> Option<ConfidenceReference> {
        None
    }
    /// Whether the physics correction follows the model's prediction: not after the FE fit,
    /// which is that fit already.
    fn takes_correction(&self) -> bool {
        true
    }
    /// The caller reads each channel of `predict`'s output only at these dense indices (the
    /// grid's nodes): a model may skip the work for the rest and leave them 0.
    fn read_only_at(&mut self, _voxels: &[usize]) {}
}

/// The FE registration alone: the rest grid's co-rotational model pulled onto the frame's
/// organ points (`correction::SurfaceFit`), warm-started from the previous frame; no network,
/// no encoding. `work`: per frame, the fixed work of the registration frame or a converged fit.
pub struct FeDisplacementModel<'g> {
    fit: SurfaceFit<'g>,
    pub last: PointFitReport,
    pub work: FitWork,
}

impl<'g> FeDisplacementModel<'g> {
    pub fn new(ctx: &'g RegistrationContext, material: MaterialParams) -> Result<Self, crate::Invalid> {
        Self::with_settings(ctx, material, PointFitSettings::default())
    }

    pub fn with_settings(
        ctx: &'g RegistrationContext,
        material: MaterialParams,
        settings: PointFitSettings,
    ) -> Result<Self, crate::Invalid> {
        let work = FitWork::fixed(&settings);
        Ok(Self { fit: SurfaceFit::new(ctx, material, settings)?, last: PointFitReport::default(), work })
    }

    /// Each frame's fit run until an update moves the nodes by at most `tol_mm` RMS (at most
    /// `max_updates` updates of tight inner solves).
    pub fn converged(mut self, tol_mm: f64, max_updates: usize) -> Self {
        self.work = FitWork::converged(tol_mm, max_updates);
        self
    }
}

impl DisplacementModel for FeDisplacementModel<'_> {
    fn name(&self) -> String {
        match self.work.stop_mm {
            Some(_) => "co-rotational FE fit (point-to-plane, converged)".into(),
            None => "co-rotational FE fit (point-to-plane)".into(),
        }
    }
    fn predict(&mut self, _u_s: &[f32], _out: &mut Vec<f32>) -> Result<(), crate::ModelError> {
        Err("the FE registration takes the observed points".into())
    }
    fn fit_points(
        &mut self,
        points_world_mm: &[Vector3<f64>],
        out: &mut Vec<f32>,
    ) -> Option<Result<usize, crate::Invalid>> {
        let r = match self.fit.fit(points_world_mm, self.work) {
            Ok(r) => r,
            Err(e) => return Some(Err(e)),
        };
        self.last = r;
        out.clear();
        self.fit.write_field(out);
        Some(Ok(r.samples_matched))
    }
    fn takes_correction(&self) -> bool {
        false
    }
}

/// Where each frame's camera pose comes from. The tracked pose is the frame's own (a
/// recording's `trajectory.log`, the stream's `world_from_camera`), else the initial pose.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PosePolicy {
    /// Keep the tracked pose; on the first frame a trimmed ICP (the best-fitting half of the
    /// cloud) refines it by at most `pose_bound_mm`, and later frames carry that refinement.
    /// For a tracked camera with a network that reproduces the organ's motion, and for
    /// sequences that start deformed where the first-frame ICP slides.
    Tracked,
    /// Full ICP on the first frame from the tracked or initial pose; later frames carry it
    /// (the organ deforms after the first frame).
    #[default]
    IcpFirst,
    /// Full ICP on every frame (a camera whose pose is unknown and moves).
    IcpEveryFrame,
}

impl PosePolicy {
    pub const ALL: [PosePolicy; 3] = [PosePolicy::Tracked, PosePolicy::IcpFirst, PosePolicy::IcpEveryFrame];

    pub fn name(self) -> &'static str {
        match self {
            PosePolicy::Tracked => "tracked",
            PosePolicy::IcpFirst => "icp-first",
            PosePolicy::IcpEveryFrame => "icp-every-frame",
        }
    }

    pub fn parse(s: &str) -> Result<Self, crate::Invalid> {
        Self::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| crate::Invalid(format!("pose policy {s:?}: one of tracked, icp-first, icp-every-frame")))
    }
}

/// `--pose auto`: the pose follows the source. A source that carries a tracked camera pose
/// for every frame (a trajectory with one pose a frame, a stream whose frames carry
/// `world_from_camera`) is registered with it (`Tracked`: on a sequence that starts deformed
/// the full first-frame ICP slides the organ); any other keeps `IcpFirst`. Returns the policy
/// and the reason, for the report and the AR panel.
pub fn choose_pose(requested: Option<PosePolicy>, source_tracks_every_frame: bool) -> (PosePolicy, String) {
    match requested {
        Some(p) => (p, format!("{p}, as asked")),
        None if source_tracks_every_frame => {
            (PosePolicy::Tracked, "tracked: the source carries a tracked camera pose for every frame".into())
        }
        None => (
            PosePolicy::IcpFirst,
            "icp-first: the source carries no tracked pose for every frame (an initial pose at most)".into(),
        ),
    }
}

impl std::fmt::Display for PosePolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RegisterSettings {
    pub segment: SegmentSettings,
    /// The full ICP of `icp-first` and `icp-every-frame`.
    pub icp: IcpSettings,
    #[serde(default)]
    pub pose: PosePolicy,
    /// With `pose: tracked`: the refinement moves the cloud by at most this much (RMS, mm).
    #[serde(default = "default_pose_bound")]
    pub pose_bound_mm: f64,
    /// Back-project every n-th pixel for ICP.
    pub point_stride: usize,
    /// Search range along each surface normal for the observed surface (mm).
    pub search_mm: f64,
    /// Start each frame's search from the previous frame's prediction (recovers the
    /// tangential motion a depth camera cannot see).
    pub warm_start: bool,
    /// Network evaluations per frame; each further one re-measures from the last prediction.
    pub iterations: usize,
    /// Draw the overlay image.
    pub overlay: bool,
    pub overlay_alpha: f32,
    /// Frames whose organ points cover less of the surface than this are not registered
    /// (`RegistrationContext::gate_coverage`).
    #[serde(default = "default_min_coverage")]
    pub min_coverage: f64,
    /// The physics correction after each network prediction (`correction`).
    #[serde(default)]
    pub correction: CorrectionSettings,
}

/// A frame's organ points beyond this are thinned evenly (a 640 x 480 frame gives at most
/// 19 200 at the default stride).
pub const MAX_FRAME_POINTS: usize = 50_000;

fn default_min_coverage() -> f64 {
    0.05
}

/// About the error of an optically tracked laparoscope after hand-eye calibration: the
/// refinement corrects that much and no more (on a deformed organ a rigid fit would otherwise
/// explain part of the deformation as camera motion: 3.9 mm on a phantom sequence that starts
/// at 3.7 mm of marker motion, from the exact pose).
fn default_pose_bound() -> f64 {
    1.5
}

impl RegisterSettings {
    /// Check the options a user sets (named as the CLI names them).
    pub fn validate(&self) -> Result<(), crate::Invalid> {
        if !(self.pose_bound_mm.is_finite() && (0.0..=100.0).contains(&self.pose_bound_mm)) {
            return Err(crate::Invalid(format!("--pose-bound-mm {}: between 0 and 100 mm", self.pose_bound_mm)));
        }
        if !(self.min_coverage.is_finite() && (0.0..=1.0).contains(&self.min_coverage)) {
            return Err(crate::Invalid(format!("--min-coverage {}: a share between 0 and 1", self.min_coverage)));
        }
        if self.iterations == 0 || self.iterations > 100 {
            return Err(crate::Invalid(format!("--iterations {}: between 1 and 100", self.iterations)));
        }
        let (lo, hi) = (self.segment.depth_min_mm, self.segment.depth_max_mm);
        // A depth camera sees from centimetres to a few metres: a window outside that, or
        // empty, keeps no pixel of any frame.
        if !(lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo < hi && hi <= 100_000.0) {
            return Err(crate::Invalid(format!(
                "--depth-min-mm {lo} / --depth-max-mm {hi}: a window 0 <= min < max <= 100000 mm (the depths a camera measures)"
            )));
        }
        self.icp.validate()?;
        // Its messages name the options.
        self.correction.validate()
    }

    /// The ICP the pose policy runs.
    fn icp_settings(&self) -> IcpSettings {
        match self.pose {
            PosePolicy::Tracked => IcpSettings::tracked(self.pose_bound_mm),
            _ => self.icp.clone(),
        }
    }
}

impl Default for RegisterSettings {
    fn default() -> Self {
        Self {
            segment: SegmentSettings::default(),
            icp: IcpSettings::default(),
            pose: PosePolicy::IcpFirst,
            pose_bound_mm: default_pose_bound(),
            point_stride: 4,
            search_mm: 30.0,
            warm_start: true,
            iterations: 1,
            overlay: true,
            overlay_alpha: 0.6,
            min_coverage: default_min_coverage(),
            correction: CorrectionSettings::default(),
        }
    }
}

/// Ground truth of a synthetic recording (`ground_truth.json`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GroundTruth {
    /// The true camera pose, row-major 4x4 (mm); of the first frame when the camera moves.
    pub world_from_camera: [f64; 16],
    /// The true camera pose of each frame when the camera moves (row-major 4x4, mm).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub world_from_camera_frames: Vec<[f64; 16]>,
    /// Marker positions at rest (world, mm).
    pub markers_rest_mm: Vec<[f64; 3]>,
    /// True marker positions per frame (world, mm).
    pub markers_mm: Vec<Vec<[f64; 3]>>,
    /// The hash of the grid the truth was computed on (absent in older recordings).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grid_hash: Option<String>,
}

/// The farthest a ground-truth position may lie from the world's origin (mm): 10 m.
pub const MAX_COORDINATE_MM: f64 = 1e4;

impl GroundTruth {
    pub fn read(path: &Path) -> Result<Self, crate::Invalid> {
        let t = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        let g: Self =
            serde_json::from_str(&t).map_err(|e| format!("{}: not a ground-truth file: {e}", path.display()))?;
        if !g.world_from_camera_frames.is_empty() && g.world_from_camera_frames.len() != g.markers_mm.len() {
            return Err(crate::Invalid(format!(
                "{}: {} camera poses for {} frames",
                path.display(),
                g.world_from_camera_frames.len(),
                g.markers_mm.len()
            )));
        }
        if g.markers_mm.iter().any(|f| f.len() != g.markers_rest_mm.len()) {
            return Err(crate::Invalid(format!("{}: a frame has a different number of markers", path.display())));
        }
        // Positions and poses a recording can have: a marker within 10 m of the origin, a pose
        // of finite numbers. Huge values gave TREs of 1e300 mm reported as a result.
        let far = |p: &[f64; 3]| !p.iter().all(|v| v.is_finite() && v.abs() <= MAX_COORDINATE_MM);
        if g.markers_rest_mm.iter().chain(g.markers_mm.iter().flatten()).any(far) {
            return Err(crate::Invalid(format!(
                "{}: a marker position is not finite or lies over {MAX_COORDINATE_MM} mm from the origin",
                path.display()
            )));
        }
        if g.world_from_camera
            .iter()
            .chain(g.world_from_camera_frames.iter().flatten())
            .any(|v| !v.is_finite() || v.abs() > MAX_COORDINATE_MM)
        {
            return Err(crate::Invalid(format!(
                "{}: a camera pose holds a value that is not finite or over {MAX_COORDINATE_MM}",
                path.display()
            )));
        }
        Ok(g)
    }
    pub fn pose(&self) -> Matrix4<f64> {
        Matrix4::from_row_slice(&self.world_from_camera)
    }

    /// The truth must be of the organ it is compared with: its markers were drawn inside that
    /// organ at rest, so (nearly) all lie within its bounds (with a 10 mm margin). A recording
    /// of another organ would give TREs of tens of mm that describe nothing.
    pub fn check_fits(&self, ctx: &RegistrationContext) -> Result<(), crate::Invalid> {
        // A synthetic truth knows its organ's grid: another grid is another organ (or the same
        // file made into another organ), whose markers may still lie within these bounds.
        if let Some(h) = &self.grid_hash
            && *h != ctx.grid_hash
        {
            return Err(crate::Invalid(format!(
                "the ground truth was made on another organ's grid (grid hash {h}; this model's grid is {}): register a recording made on this model's organ",
                ctx.grid_hash
            )));
        }
        let m = self.markers_rest_mm.len();
        let Some((lo, hi)) = ctx.surface.bounds() else { return Ok(()) };
        let margin = Vector3::repeat(10.0);
        let (lo, hi) = (lo - margin, hi + margin);
        let inside = self
            .markers_rest_mm
            .iter()
            .filter(|p| (0..3).all(|a| p[a].is_finite() && p[a] >= lo[a] && p[a] <= hi[a]))
            .count();
        if m > 0 && (inside as f64) < 0.8 * m as f64 {
            return Err(crate::Invalid(format!(
                "the ground truth is not of this organ: {} of its {m} markers lie outside the organ's bounds (a recording made on another organ?)",
                m - inside
            )));
        }
        Ok(())
    }
    /// The true camera pose of frame `i`.
    pub fn pose_at(&self, i: usize) -> Matrix4<f64> {
        match self.world_from_camera_frames.get(i) {
            Some(m) => Matrix4::from_row_slice(m),
            None => self.pose(),
        }
    }
}

#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Latency {
    pub points_ms: f64,
    pub icp_ms: f64,
    pub surface_ms: f64,
    pub predict_ms: f64,
    pub overlay_ms: f64,
    pub confidence_ms: f64,
    /// The physics correction (the first frame's includes building its model).
    pub correction_ms: f64,
    pub total_ms: f64,
}

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct FrameReport {
    pub frame: usize,
    pub timestamp_s: f64,
    pub observed_points: usize,
    /// The frame gave this many organ points, thinned to `observed_points` (MAX_FRAME_POINTS).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub points_thinned_from: Option<usize>,
    /// Share of the predicted organ surface the organ points cover (`confidence::frame_coverage`).
    pub surface_coverage: f64,
    /// Visible surface vertices whose displacement was measured.
    pub measured_vertices: usize,
    pub icp: Option<IcpReport>,
    pub latency: Latency,
    pub tre_mean_mm: Option<f64>,
    pub tre_max_mm: Option<f64>,
    /// TRE when the organ is taken as rigid (no deformation predicted): the baseline.
    pub tre_rigid_mean_mm: Option<f64>,
    pub marker_displacement_mean_mm: Option<f64>,
    /// Without ground truth: the fit of the prediction to the observed points and the
    /// warnings when it leaves the range seen in training.
    pub confidence: Confidence,
    /// What the physics correction did (None: off, or the FE registration itself).
    pub correction: Option<CorrectionReport>,
    /// From the camera bridge taking the frame to its overlay (bridge, transport, waiting,
    /// registration), when the source stamps its frames on this machine's clock.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub end_to_end_ms: Option<f64>,
}

/// What one frame produced (for the GUI and the overlay writer).
#[derive(Debug)]
pub struct FrameOutput {
    pub report: FrameReport,
    /// Predicted u_v [3, X, Y, Z].
    pub field: Vec<f32>,
    pub overlay: Option<ColorImage>,
    pub world_from_camera: Matrix4<f64>,
}

/// A frame's organ points (camera, mm), how many there were before thinning, and its depth
/// image with the other pixels cleared.
struct OrganPoints {
    points: Vec<Vector3<f64>>,
    thinned_from: Option<usize>,
    depth: DepthImage,
}

/// What the model's prediction of a frame measured and cost.
struct Prediction {
    /// The model is the FE fit itself (no correction follows it).
    fe_fit: bool,
    measured: usize,
    surface_ms: f64,
    predict_ms: f64,
}

/// The registered markers' error against a synthetic recording's truth (mm).
#[derive(Default)]
struct Tre {
    mean_mm: Option<f64>,
    max_mm: Option<f64>,
    rigid_mean_mm: Option<f64>,
    displacement_mean_mm: Option<f64>,
}

/// Registration state carried from frame to frame.
pub struct Registrar<'c> {
    pub ctx: &'c RegistrationContext,
    pub settings: RegisterSettings,
    pub world_from_camera: Matrix4<f64>,
    posed: bool,
    /// world_from_camera of the last rigid alignment times the inverse of the tracked pose
    /// of that frame: applied to later tracked poses (a tracked, moving laparoscope).
    correction: Option<Matrix4<f64>>,
    prev_field: Vec<f32>,
    u_s: Vec<f32>,
    field: Vec<f32>,
    /// Where the field is read: the grid nodes' dense indices (`DisplacementModel::read_only_at`).
    node_voxels: Vec<usize>,
    /// Built on the first frame of a model that takes observations.
    observer: Option<crate::observation::Observer>,
    /// The organ surface's vertex rings, for the confidence residual.
    rings: super::confidence::VertexRings,
    /// The physics correction's FE model, built on the first frame that needs it.
    corrector: Option<SurfaceFit<'c>>,
    /// The previous frame's correction of its prediction, per node (`CorrectionSettings::carry`).
    carried: Vec<Vector3<f64>>,
    /// The doubted frames' fit on the coarsened organ (`CorrectionSettings::doubted_coarsening`),
    /// and its fit carried over consecutive doubted frames (in the coarse tracking form, over
    /// all), per coarse node.
    coarse_fit: Option<CoarseFit<'c>>,
    coarse_carried: CoarseCarried,
    /// No initial pose was given: a frame must bring its own until one has been aligned.
    needs_frame_pose: bool,
}

impl<'c> Registrar<'c> {
    pub fn new(
        ctx: &'c RegistrationContext,
        settings: RegisterSettings,
        initial_world_from_camera: Matrix4<f64>,
    ) -> Self {
        let [x, y, z] = ctx.padded_shape();
        Self {
            ctx,
            settings,
            world_from_camera: initial_world_from_camera,
            posed: false,
            correction: None,
            prev_field: vec![0.0; 3 * x * y * z],
            u_s: Vec::new(),
            field: Vec::new(),
            node_voxels: (0..ctx.grid.node_count()).map(|n| ctx.grid.dense_index(n)).collect(),
            observer: None,
            rings: super::confidence::VertexRings::new(&ctx.surface),
            corrector: None,
            carried: Vec::new(),
            coarse_fit: None,
            coarse_carried: CoarseCarried::default(),
            needs_frame_pose: false,
        }
    }

    /// Without an initial pose: each frame's own pose (a stream's `world_from_camera`) is used;
    /// a frame without one, before any was aligned, is skipped with that reason.
    pub fn require_frame_pose(&mut self) {
        self.needs_frame_pose = true;
    }

    /// Forget the pose refinement and the previous prediction (a new sequence).
    pub fn reset(&mut self, world_from_camera: Matrix4<f64>) {
        self.world_from_camera = world_from_camera;
        self.posed = false;
        self.correction = None;
        self.prev_field.iter_mut().for_each(|v| *v = 0.0);
        self.carried.clear();
        self.coarse_carried.clear();
    }

    /// Change the physics correction between frames; a carried correction starts again.
    pub fn set_correction(&mut self, correction: CorrectionSettings) {
        if correction != self.settings.correction {
            // Another basis: the fit is built again (the context keeps each basis built).
            if correction.basis() != self.settings.correction.basis() {
                self.corrector = None;
            }
            if correction.doubted_coarsening != self.settings.correction.doubted_coarsening {
                self.coarse_fit = None;
            }
            self.settings.correction = correction;
            self.carried.clear();
            self.coarse_carried.clear();
        }
    }

    /// Build the physics correction's FE model now (its factorisation, about half a second on
    /// a 5000-node liver, and its subspace unless the context holds it): before the first
    /// frame, which would otherwise take that time. Nothing when the correction is off.
    pub fn prepare_correction(&mut self) -> Result<(), crate::Invalid> {
        let c = self.settings.correction;
        if c.updates == 0 {
            return Ok(());
        }
        // The coarse tracking form corrects every frame on the coarse grid: no fine model.
        if self.corrector.is_none() && !c.coarse_tracking {
            let mut fit = SurfaceFit::new(self.ctx, self.ctx.material, PointFitSettings::default())?;
            fit.use_subspace(c.basis())?;
            self.corrector = Some(fit);
        }
        let coarsening = if c.coarse_tracking {
            Some(c.doubted_coarsening)
        } else {
            c.doubted().map(|d| d.doubted_coarsening).filter(|&f| f > 1)
        };
        if let Some(factor) = coarsening
            && self.coarse_fit.is_none()
        {
            self.coarse_fit = Some(CoarseFit::new(self.ctx, factor)?);
        }
        Ok(())
    }

    /// Register one frame. Errors (no organ pixel, ...) mean: skip this frame.
    ///
    /// The frame runs on a thread of rayon's pool: its parallel parts (the network's layers,
    /// the fit beside its judgement, the overlay) then start on the thread that asks for them,
    /// the other joining in, rather than each handed from a caller outside the pool to threads
    /// that may have gone to sleep.
    pub fn process(
        &mut self,
        frame: &Frame,
        model: &mut dyn DisplacementModel,
        truth: Option<&[[f64; 3]]>,
        rest: Option<&[[f64; 3]]>,
        true_pose: Option<&Matrix4<f64>>,
    ) -> Result<FrameOutput, FrameError> {
        rayon::scope(|_| self.process_here(frame, model, truth, rest, true_pose))
    }

    fn process_here(
        &mut self,
        frame: &Frame,
        model: &mut dyn DisplacementModel,
        truth: Option<&[[f64; 3]]>,
        rest: Option<&[[f64; 3]]>,
        true_pose: Option<&Matrix4<f64>>,
    ) -> Result<FrameOutput, FrameError> {
        let t0 = Instant::now();
        frame.validate()?;
        let OrganPoints { points, thinned_from, depth } = self.organ_points(frame)?;
        let points_ms = ms(t0);
        let t1 = Instant::now();
        let icp = self.align(frame, &points)?;
        let icp_ms = ms(t1);
        let camera_from_world = rigid_inverse(&self.world_from_camera);
        let world: Vec<Vector3<f64>> = points.iter().map(|p| transform_point(&self.world_from_camera, p)).collect();
        // Too little of the organ seen (a cloud off the organ, a camera looking away): no
        // deformation can be inferred from it. Each point is taken to the rest surface first,
        // so that a deformed or pushed organ (a first frame already deformed) is not refused.
        let coverage = self.ctx.gate_coverage(&world);
        if coverage < self.settings.min_coverage {
            return Err(FrameError::Invalid(crate::Invalid(format!(
                "frame {}: the organ points cover {:.1} % of the organ's surface (under {:.0} %): not registered, the previous overlay stays",
                frame.index,
                100.0 * coverage,
                100.0 * self.settings.min_coverage
            ))));
        }
        let p = self.predict(frame, model, &world, &depth, &camera_from_world)?;
        // The physics correction: the prediction pulled onto the observed points by the FE model
        // (not after the FE registration, which is that fit already).
        let reference = model.confidence_reference();
        let (correction, correction_ms, judged_confidence) = if self.settings.correction.updates > 0 && !p.fe_fit {
            let t = Instant::now();
            let (c, judged) = self.correct(frame, &world, reference.as_ref())?;
            (Some(c), ms(t), Some(judged))
        } else {
            (None, 0.0, None)
        };
        self.prev_field.clone_from(&self.field);
        let t = Instant::now();
        let (overlay, (confidence, confidence_ms)) =
            self.draw(frame, &world, &camera_from_world, judged_confidence, reference.as_ref());
        let overlay_ms = if self.settings.overlay { ms(t) } else { 0.0 };
        let tre = match (truth, rest, true_pose) {
            (Some(truth), Some(rest), Some(tp)) => self.tre(truth, rest, tp, &camera_from_world),
            _ => Tre::default(),
        };
        let latency = Latency {
            points_ms,
            icp_ms,
            surface_ms: p.surface_ms,
            predict_ms: p.predict_ms,
            overlay_ms,
            confidence_ms,
            correction_ms,
            total_ms: ms(t0),
        };
        Ok(FrameOutput {
            report: FrameReport {
                frame: frame.index,
                timestamp_s: frame.timestamp_s,
                observed_points: points.len(),
                points_thinned_from: thinned_from,
                surface_coverage: confidence.surface_coverage,
                measured_vertices: p.measured,
                icp,
                latency,
                tre_mean_mm: tre.mean_mm,
                tre_max_mm: tre.max_mm,
                tre_rigid_mean_mm: tre.rigid_mean_mm,
                marker_displacement_mean_mm: tre.displacement_mean_mm,
                confidence,
                correction,
                end_to_end_ms: frame.host_time_s.and_then(|t| {
                    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).ok()?.as_secs_f64();
                    let ms = (now - t) * 1e3;
                    // Another machine's clock gives nonsense: no figure rather than a wrong one.
                    (0.0..3.6e6).contains(&ms).then_some(ms)
                }),
            },
            field: self.field.clone(),
            overlay,
            world_from_camera: self.world_from_camera,
        })
    }

    /// The frame's organ points (camera, mm) and its depth image with every other pixel cleared.
    fn organ_points(&self, frame: &Frame) -> Result<OrganPoints, FrameError> {
        let keep = segment_frame(frame, &self.settings.segment)?;
        let mut depth = frame.depth.clone();
        for (d, &kp) in depth.depth_mm.iter_mut().zip(&keep) {
            if !kp {
                *d = 0.0;
            }
        }
        // A cloud from the camera is used whole; a depth image every `point_stride` pixels; and
        // at most MAX_FRAME_POINTS of either, evenly, so that the largest accepted frame (16
        // Mpixel) registers in bounded time.
        let mut points = frame.organ_points(&keep, self.settings.point_stride);
        let thinned_from = (points.len() > MAX_FRAME_POINTS).then_some(points.len());
        if let Some(n) = thinned_from {
            points = (0..MAX_FRAME_POINTS).map(|i| points[i * n / MAX_FRAME_POINTS]).collect();
        }
        if points.is_empty() {
            return Err(FrameError::Invalid(crate::Invalid(format!(
                "frame {}: no organ point in the depth image (the previous overlay stays)",
                frame.index
            ))));
        }
        Ok(OrganPoints { points, thinned_from, depth })
    }

    /// The frame's camera pose: its tracked pose with the last refinement, aligned by ICP as the
    /// pose policy asks (the report of that alignment, when one ran).
    fn align(&mut self, frame: &Frame, points: &[Vector3<f64>]) -> Result<Option<IcpReport>, FrameError> {
        if self.needs_frame_pose && !self.posed && frame.world_from_camera.is_none() {
            return Err(FrameError::Invalid(crate::Invalid(format!(
                "frame {}: no camera pose (the source gives none and no initial pose was given)",
                frame.index
            ))));
        }
        // The frame's tracked pose, with the refinement of the last alignment.
        if let Some(t) = frame.world_from_camera {
            self.world_from_camera = self.correction.map_or(t, |c| c * t);
        }
        let policy = self.settings.pose;
        if self.posed && policy != PosePolicy::IcpEveryFrame {
            return Ok(None);
        }
        let mut r =
            icp_point_to_plane(points, &self.ctx.icp_target, &self.world_from_camera, &self.settings.icp_settings());
        if r.fitness < 0.3 {
            if policy != PosePolicy::Tracked {
                return Err(FrameError::Invalid(crate::Invalid(format!(
                    "frame {}: rigid alignment failed (ICP fitness {:.2}, RMS {:.1} mm)",
                    frame.index, r.fitness, r.rms_mm
                ))));
            }
            // A tracked pose stands on its own: kept as it is when too little fits.
            r.transform = self.world_from_camera;
            r.moved_mm = 0.0;
        }
        self.correction = frame.world_from_camera.map(|t| r.transform * rigid_inverse(&t));
        self.world_from_camera = r.transform;
        self.posed = true;
        Ok(Some(r))
    }

    /// The model's displacement field for the frame, in `self.field`: the FE fit of the points,
    /// the network on their encoding, or the network on the surface displacement measured
    /// along the normals (iterated from the previous frame's field).
    fn predict(
        &mut self,
        frame: &Frame,
        model: &mut dyn DisplacementModel,
        world: &[Vector3<f64>],
        depth: &DepthImage,
        camera_from_world: &Matrix4<f64>,
    ) -> Result<Prediction, FrameError> {
        let (mut surface_ms, mut predict_ms, mut measured) = (0.0, 0.0, 0);
        let observation = model.observation();
        let t = Instant::now();
        let fitted = model.fit_points(world, &mut self.field);
        let fe_fit = fitted.is_some();
        let direct = fe_fit || observation.is_some();
        if let Some(r) = fitted {
            measured = r.map_err(|e| crate::Invalid(format!("frame {}: {}: {e}", frame.index, model.name())))?;
            predict_ms += ms(t);
        } else if let Some(o) = observation {
            // Correspondence-free: the frame's organ points in the world, encoded on the rest
            // grid as the training views were; one prediction, no iteration.
            let t = Instant::now();
            if self.observer.as_ref().is_none_or(|x| x.settings != o) {
                self.observer = Some(crate::observation::Observer::new(&self.ctx.grid, &self.ctx.surface, o)?);
            }
            let stats = self.observer.as_mut().map(|x| x.encode(world, &mut self.u_s)).unwrap_or_default();
            measured = stats.nodes_observed;
            surface_ms += ms(t);
            if measured > 0 {
                predict_ms += self.run_model(frame, model)?;
            }
        }
        if !direct {
            let mut current =
                if self.settings.warm_start { self.prev_field.clone() } else { vec![0.0; self.prev_field.len()] };
            for _ in 0..self.settings.iterations.max(1) {
                let t = Instant::now();
                measured = self.surface_input(depth, &frame.intrinsics, camera_from_world, &current);
                surface_ms += ms(t);
                predict_ms += self.run_model(frame, model)?;
                current.clone_from(&self.field);
            }
        }
        if measured == 0 {
            return Err(FrameError::Invalid(crate::Invalid(format!(
                "frame {}: no visible surface point found in the depth image",
                frame.index
            ))));
        }
        Ok(Prediction { fe_fit, measured, surface_ms, predict_ms })
    }

    /// The model's prediction from `self.u_s` into `self.field`; its time (ms).
    fn run_model(&mut self, frame: &Frame, model: &mut dyn DisplacementModel) -> Result<f64, FrameError> {
        let t = Instant::now();
        model.read_only_at(&self.node_voxels);
        model.predict(&self.u_s, &mut self.field).map_err(|source| FrameError::Model {
            frame: frame.index,
            model: model.name(),
            source,
        })?;
        Ok(ms(t))
    }

    /// The physics correction of `self.field` in place, with the confidence of the prediction it
    /// corrects (and that judgement's time).
    fn correct(
        &mut self,
        frame: &Frame,
        world: &[Vector3<f64>],
        reference: Option<&ConfidenceReference>,
    ) -> Result<(CorrectionReport, (Confidence, f64)), FrameError> {
        self.prepare_correction()?;
        let settings = self.settings.correction;
        let predicted = self.field.clone();
        // The confidence judges the model's own prediction: its reference is the model's residual
        // on its validation views, and the correction shrinks the residual by construction (on
        // eleven phantom recordings the corrected frames' residual hid all five frames above
        // 2 mm; the prediction's flagged four, the fifth at 2.00 mm, and no other frame).
        // It runs beside the correction, on the two cores; a doubted prediction is then
        // corrected again, from itself, as the FE fit. After a doubted frame the next is
        // likely doubted too (runs of 6-13 frames on the CT patient's held-out family): the
        // confidence is judged first and the correction that would be thrown away is skipped.
        let (ctx, rings) = (self.ctx, &self.rings);
        let judge = || {
            let t = Instant::now();
            let predicted_organ = ctx.deformed_surface(&predicted);
            let coverage = super::confidence::frame_coverage(&predicted_organ, world);
            let c = frame_confidence(world, &predicted_organ, &ctx.surface, rings, coverage, reference);
            (c, ms(t))
        };
        let failed = |e: crate::Invalid| crate::Invalid(format!("frame {}: physics correction: {e}", frame.index));
        if settings.coarse_tracking {
            // Every frame is the coarse fit, which follows the prediction's motion. The judgement
            // runs beside it; a doubted prediction may have jumped, and its frame is fitted again
            // from the fit before alone. At the first frame and after a doubted frame the fit
            // follows no prediction, whatever the judgement: it is the doubted frame's fit
            // already, and the judgement decides only whether the next frame follows this one.
            let (coarse, field) = (self.coarse_fit.as_mut().expect("prepared above"), &mut self.field);
            let carried = &mut self.coarse_carried;
            let doubts = settings.doubted_updates > 0;
            let before = (doubts && carried.follows()).then(|| carried.clone());
            let (judged, mut corrected) = rayon::join(judge, || coarse.track(world, field, &settings, carried, true));
            if judged.0.prediction_doubted && doubts {
                match before {
                    Some(before) => {
                        field.clone_from(&predicted);
                        *carried = before;
                        corrected = coarse.track(world, field, &settings, carried, false);
                    }
                    None => {
                        carried.forget_prediction();
                        corrected = corrected.map(|r| CorrectionReport { doubted: true, ..r });
                    }
                }
            }
            return Ok((corrected.map_err(failed)?, judged));
        }
        let (corrector, field) = (self.corrector.as_mut().expect("prepared above"), &mut self.field);
        let carried = settings.carry.then_some(&mut self.carried);
        let in_doubted_run = !self.coarse_carried.is_empty();
        let ((c, conf_ms), mut corrected) = if in_doubted_run {
            let (c, conf_ms) = judge();
            let doubted = c.prediction_doubted;
            ((c, conf_ms), (!doubted).then(|| corrector.correct(world, field, &settings, carried)))
        } else {
            let (judged, corrected) = rayon::join(judge, || corrector.correct(world, field, &settings, carried));
            (judged, Some(corrected))
        };
        match settings.doubted() {
            Some(d) if c.prediction_doubted => {
                // Carried over consecutive doubted frames (in the tracking form, over all).
                *field = predicted;
                corrected = Some(match self.coarse_fit.as_mut() {
                    Some(coarse) if d.doubted_coarsening > 1 => {
                        // After a doubted frame the fit starts from that frame's: fewer updates.
                        let d = if in_doubted_run { d.after_doubted() } else { d };
                        coarse.correct(world, field, &d, &mut self.coarse_carried)
                    }
                    _ => corrector
                        .correct(world, field, &d, Some(&mut self.carried))
                        .map(|r| CorrectionReport { doubted: true, ..r }),
                });
            }
            _ if !settings.carry => {
                self.carried.clear();
                self.coarse_carried.clear();
            }
            _ => {}
        }
        // Skipped only when the frame turned out doubted, and then the fit above ran.
        let corrected = corrected.unwrap_or_else(|| Err(crate::Invalid("no correction ran".into()))).map_err(failed)?;
        Ok((corrected, (c, conf_ms)))
    }

    /// The overlay (when drawn) and the frame's confidence: the one judged beside the
    /// correction, or else judged here on the registered organ. The registered organ (its
    /// silhouette's outline, and without a correction the frame's confidence) on one core, the
    /// deformed structures' layer on the other.
    fn draw(
        &self,
        frame: &Frame,
        world: &[Vector3<f64>],
        camera_from_world: &Matrix4<f64>,
        judged_confidence: Option<(Confidence, f64)>,
        reference: Option<&ConfidenceReference>,
    ) -> (Option<ColorImage>, (Confidence, f64)) {
        let k = frame.intrinsics;
        let (ctx, field, draw) = (self.ctx, &self.field, self.settings.overlay);
        let ((inside, judged), layer) = rayon::join(
            || match judged_confidence {
                // Neither an outline to draw nor a confidence to judge: no organ needed.
                Some(judged) if !draw => (None, judged),
                judged => {
                    let t = Instant::now();
                    let organ = ctx.deformed_surface(field);
                    let organ_ms = ms(t);
                    rayon::join(
                        || {
                            draw.then(|| {
                                let mut inside = vec![false; k.width * k.height];
                                rasterize_silhouette(&organ, camera_from_world, &k, &mut inside);
                                inside
                            })
                        },
                        || {
                            judged.unwrap_or_else(|| {
                                let t = Instant::now();
                                let coverage = super::confidence::frame_coverage(&organ, world);
                                let c = frame_confidence(world, &organ, &ctx.surface, &self.rings, coverage, reference);
                                (c, ms(t) + organ_ms)
                            })
                        },
                    )
                }
            },
            || {
                draw.then(|| {
                    let structures: Vec<_> =
                        ctx.structures.iter().map(|s| (ctx.deformed_structure(s, field), s.color)).collect();
                    structure_layer(&structures, camera_from_world, &k)
                })
            },
        );
        let overlay = match (inside, layer) {
            (Some(inside), Some(layer)) => {
                let mut img = frame.color.clone().unwrap_or_else(|| depth_preview(&frame.depth));
                compose_overlay(&mut img, &layer, &inside, k.width, self.settings.overlay_alpha);
                Some(img)
            }
            _ => None,
        };
        (overlay, judged)
    }

    /// The registered markers against the truth, in the true camera's frame (a pose error counts).
    fn tre(
        &self,
        truth: &[[f64; 3]],
        rest: &[[f64; 3]],
        true_pose: &Matrix4<f64>,
        camera_from_world: &Matrix4<f64>,
    ) -> Tre {
        let true_cam = rigid_inverse(true_pose);
        let (mut e, mut e0, mut d) = (Vec::new(), Vec::new(), Vec::new());
        for (m_true, m_rest) in truth.iter().zip(rest) {
            let (mt, mr) = (Vector3::from(*m_true), Vector3::from(*m_rest));
            let Some(emb) = self.ctx.grid.embed(&mr) else { continue };
            let pred = mr + displacement_at(&self.ctx.grid, &self.field, &emb);
            let truth_cam = transform_point(&true_cam, &mt);
            e.push((transform_point(camera_from_world, &pred) - truth_cam).norm());
            e0.push((transform_point(camera_from_world, &mr) - truth_cam).norm());
            d.push((mt - mr).norm());
        }
        if e.is_empty() {
            return Tre::default();
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        Tre {
            mean_mm: Some(mean(&e)),
            max_mm: Some(e.iter().copied().fold(0.0, f64::max)),
            rigid_mean_mm: Some(mean(&e0)),
            displacement_mean_mm: Some(mean(&d)),
        }
    }

    /// u_s from the observed depth: each visible surface vertex, moved by the `current`
    /// displacement estimate, is pushed along its normal onto the observed surface; the grid's
    /// visible nodes take the embedding-weighted mean of their vertices; nodes that no vertex
    /// informs take the mean of their neighbours. Returns how many vertices were measured.
    fn surface_input(
        &mut self,
        depth: &DepthImage,
        k: &Intrinsics,
        camera_from_world: &Matrix4<f64>,
        current: &[f32],
    ) -> usize {
        let ctx = self.ctx;
        let g = &ctx.grid;
        let [x, y, z] = ctx.padded_shape();
        let cells = x * y * z;
        let nv = ctx.visible_nodes.len();
        let mut slot = std::collections::HashMap::with_capacity(nv);
        for (i, &n) in ctx.visible_nodes.iter().enumerate() {
            slot.insert(n as u32, i);
        }
        let mut acc = vec![Vector3::<f64>::zeros(); nv];
        let mut wsum = vec![0.0f64; nv];
        let rot = camera_from_world.fixed_view::<3, 3>(0, 0).into_owned();
        let step = 0.5;
        let max_steps = (self.settings.search_mm / step).ceil() as i64;
        let mut measured = 0;
        for &v in &ctx.visible_vertices {
            let e = &ctx.surface_embedding[v];
            let u0 = displacement_at(g, current, e);
            let p = ctx.surface.positions[v] + u0;
            let n = ctx.surface_normals[v];
            let pc = transform_point(camera_from_world, &p);
            let nc = rot * n;
            // Grazing normals make the along-normal search ill-conditioned.
            if nc.dot(&pc.normalize()) > -0.2 {
                continue;
            }
            // f(t) = observed depth - point depth along p + t n; its root nearest t = 0.
            let f = |t: f64| -> Option<f64> {
                let q = pc + nc * t;
                let (pu, pv, pz) = k.project(&q)?;
                depth.sample(pu, pv, 15.0).map(|d| d as f64 - pz)
            };
            let f0 = f(0.0);
            let mut found = (f0 == Some(0.0)).then_some(0.0);
            // Walk outwards both ways at once, nearest root first.
            let (mut lo, mut hi) = ((0.0, f0), (0.0, f0));
            for s in 1..=max_steps {
                if found.is_some() {
                    break;
                }
                for dir in [1.0, -1.0] {
                    let t = dir * s as f64 * step;
                    let cur = (t, f(t));
                    let last = if dir > 0.0 { hi } else { lo };
                    if let (Some(a), Some(b)) = (last.1, cur.1)
                        && a * b <= 0.0
                        && a != b
                    {
                        found = Some(last.0 + (cur.0 - last.0) * a / (a - b));
                        break;
                    }
                    if dir > 0.0 {
                        hi = cur;
                    } else {
                        lo = cur;
                    }
                }
            }
            let Some(t) = found else { continue };
            measured += 1;
            let d = u0 + n * t;
            for (node, w) in e.nodes.iter().zip(e.weights) {
                if w > 1e-9
                    && let Some(&s) = slot.get(node)
                {
                    acc[s] += d * w;
                    wsum[s] += w;
                }
            }
        }
        let mut val: Vec<Option<Vector3<f64>>> = (0..nv).map(|i| (wsum[i] > 1e-6).then(|| acc[i] / wsum[i])).collect();
        for _ in 0..8 {
            if val.iter().all(Option::is_some) {
                break;
            }
            let next: Vec<Option<Vector3<f64>>> = (0..nv)
                .map(|i| {
                    val[i].or_else(|| {
                        let nb: Vec<Vector3<f64>> = ctx.node_neighbours[i].iter().filter_map(|&j| val[j]).collect();
                        (!nb.is_empty()).then(|| nb.iter().sum::<Vector3<f64>>() / nb.len() as f64)
                    })
                })
                .collect();
            val = next;
        }
        self.u_s.clear();
        self.u_s.resize(3 * cells, 0.0);
        for (i, &n) in ctx.visible_nodes.iter().enumerate() {
            let d = g.dense_index(n);
            let u = val[i].unwrap_or_else(|| displacement_at_node(current, d, cells));
            for c in 0..3 {
                self.u_s[c * cells + d] = u[c] as f32;
            }
        }
        measured
    }
}

fn displacement_at_node(field: &[f32], d: usize, cells: usize) -> Vector3<f64> {
    Vector3::new(field[d] as f64, field[cells + d] as f64, field[2 * cells + d] as f64)
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Summary {
    pub frames: usize,
    pub skipped: usize,
    pub frame_ms_median: f64,
    pub frame_ms_p95: f64,
    pub tre_mean_mm: Option<f64>,
    pub tre_max_mm: Option<f64>,
    pub tre_rigid_mean_mm: Option<f64>,
    pub marker_displacement_mean_mm: Option<f64>,
    /// The last registered frame's TRE, rigid-only TRE and mean marker motion (the largest
    /// deformation of a ramped recording).
    pub last_tre_mm: Option<f64>,
    pub last_tre_rigid_mm: Option<f64>,
    pub last_marker_displacement_mm: Option<f64>,
    /// Frames whose confidence figures left the range seen in training.
    pub frames_with_warning: usize,
    /// Frames whose prediction was doubted and corrected as the FE fit
    /// (`CorrectionSettings::doubted`).
    pub frames_corrected_as_fe: usize,
    /// The median of the frames' residual 95th percentiles (mm).
    pub residual_p95_median_mm: f64,
    /// The most any frame's ICP moved the cloud from the pose it started from (RMS, mm).
    pub pose_moved_max_mm: Option<f64>,
    /// Frames the source dropped (the camera's gaps, frames the registration was late for);
    /// counted in `skipped` too.
    #[serde(default)]
    pub dropped: usize,
    /// Median end-to-end latency (`FrameReport::end_to_end_ms`) over the frames that have one.
    pub end_to_end_ms_median: Option<f64>,
}

pub fn summarize(frames: &[FrameReport], skipped: usize) -> Summary {
    let mut t: Vec<f64> = frames.iter().map(|f| f.latency.total_ms).collect();
    t.sort_by(f64::total_cmp);
    let pct = |p: f64| if t.is_empty() { 0.0 } else { t[((t.len() - 1) as f64 * p).round() as usize] };
    let mean_of = |g: &dyn Fn(&FrameReport) -> Option<f64>| {
        let v: Vec<f64> = frames.iter().filter_map(g).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    Summary {
        frames: frames.len(),
        skipped,
        frame_ms_median: pct(0.5),
        frame_ms_p95: pct(0.95),
        tre_mean_mm: mean_of(&|f| f.tre_mean_mm),
        tre_max_mm: frames.iter().filter_map(|f| f.tre_max_mm).reduce(f64::max),
        tre_rigid_mean_mm: mean_of(&|f| f.tre_rigid_mean_mm),
        marker_displacement_mean_mm: mean_of(&|f| f.marker_displacement_mean_mm),
        last_tre_mm: frames.last().and_then(|f| f.tre_mean_mm),
        last_tre_rigid_mm: frames.last().and_then(|f| f.tre_rigid_mean_mm),
        last_marker_displacement_mm: frames.last().and_then(|f| f.marker_displacement_mean_mm),
        frames_with_warning: frames.iter().filter(|f| f.confidence.warning()).count(),
        frames_corrected_as_fe: frames.iter().filter(|f| f.correction.is_some_and(|c| c.doubted)).count(),
        residual_p95_median_mm: {
            let mut r: Vec<f64> = frames.iter().map(|f| f.confidence.residual_p95_mm).collect();
            r.sort_by(f64::total_cmp);
            if r.is_empty() { 0.0 } else { r[(r.len() - 1) / 2] }
        },
        pose_moved_max_mm: frames.iter().filter_map(|f| f.icp.as_ref().map(|i| i.moved_mm)).reduce(f64::max),
        dropped: 0,
        end_to_end_ms_median: {
            let mut e: Vec<f64> = frames.iter().filter_map(|f| f.end_to_end_ms).collect();
            e.sort_by(f64::total_cmp);
            (!e.is_empty()).then(|| e[(e.len() - 1) / 2])
        },
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct RegisterReport {
    pub model: String,
    /// The pose policy the frames were registered with.
    pub pose: PosePolicy,
    /// Why that policy (`choose_pose`).
    pub pose_reason: String,
    pub summary: Summary,
    pub frames: Vec<FrameReport>,
    pub log: Vec<String>,
}

impl RegisterReport {
    /// Its figures as a correction form's on a recording with ground truth (`CorrectionChoice`);
    /// None when fewer than two of its frames have a TRE.
    pub fn form_figures(&self) -> Option<FormFigures> {
        let tre: Vec<f64> = self.frames.iter().filter_map(|f| f.tre_mean_mm).filter(|t| t.is_finite()).collect();
        if tre.len() < 2 {
            return None;
        }
        let late = &tre[tre.len() / 2..];
        Some(FormFigures {
            late_tre_mm: late.iter().sum::<f64>() / late.len() as f64,
            last_tre_mm: tre[tre.len() - 1],
            frame_ms_median: self.summary.frame_ms_median,
        })
    }
}

/// Register every frame of `source`; `on_frame` receives each output (to write overlays).
pub fn run_register(
    source: &mut dyn FrameSource,
    ctx: &RegistrationContext,
    model: &mut dyn DisplacementModel,
    initial_world_from_camera: impl Into<Option<Matrix4<f64>>>,
    truth: Option<&GroundTruth>,
    settings: &RegisterSettings,
    on_frame: &mut dyn FnMut(&FrameOutput) -> Result<(), crate::Invalid>,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<RegisterReport, crate::rgbd::RgbdError> {
    if let Some(t) = truth {
        t.check_fits(ctx)?;
    }
    let mut reg = Registrar::new(ctx, settings.clone(), Matrix4::identity());
    if model.takes_correction() {
        reg.prepare_correction()?;
    }
    run_registrar(reg, source, model, initial_world_from_camera, truth, on_frame, progress, cancel)
}

/// `run_register` with a registrar built beforehand (`Registrar::new`, `prepare_correction`):
/// a caller builds its FE models before a live source opens, so that no frame arriving
/// meanwhile is dropped. The registrar starts again from `initial_world_from_camera`
/// (`Registrar::reset`), keeping the models.
#[allow(clippy::too_many_arguments)]
pub fn run_registrar(
    mut reg: Registrar<'_>,
    source: &mut dyn FrameSource,
    model: &mut dyn DisplacementModel,
    initial_world_from_camera: impl Into<Option<Matrix4<f64>>>,
    truth: Option<&GroundTruth>,
    on_frame: &mut dyn FnMut(&FrameOutput) -> Result<(), crate::Invalid>,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<RegisterReport, crate::rgbd::RgbdError> {
    let initial = initial_world_from_camera.into();
    if let Some(t) = truth {
        t.check_fits(reg.ctx)?;
    }
    reg.reset(initial.unwrap_or_else(Matrix4::identity));
    if initial.is_none() {
        reg.require_frame_pose();
    }
    if model.takes_correction() {
        reg.prepare_correction()?;
    }
    let settings = reg.settings.clone();
    let mut frames = Vec::new();
    let mut log = Vec::new();
    let mut skipped = 0;
    let rest = truth.map(|g| g.markers_rest_mm.as_slice());
    let mut n = 0u64;
    loop {
        cancel.check()?;
        let frame = match source.poll(Duration::from_secs(10)) {
            Poll::Frame(f) => f,
            Poll::Pending => {
                log.push("no frame for 10 s: stopping".into());
                break;
            }
            Poll::Ended(reason) => {
                if let Some(r) = reason {
                    log.push(format!("the source ended: {r}"));
                }
                break;
            }
        };
        log.extend(source.take_log());
        n += 1;
        progress.report(n, 0, &format!("frame {}", frame.index));
        let gt = truth.and_then(|g| g.markers_mm.get(frame.index)).map(|v| v.as_slice());
        let true_pose = truth.map(|g| g.pose_at(frame.index));
        match reg.process(&frame, model, gt, rest, true_pose.as_ref()) {
            Ok(out) => {
                on_frame(&out).map_err(|e| crate::rgbd::RgbdError::Stream(e.into()))?;
                frames.push(out.report);
            }
            Err(e) => {
                skipped += 1;
                log.push(format!("frame {} skipped: {e}", frame.index));
            }
        }
    }
    log.extend(source.take_log());
    let dropped = source.dropped() as usize;
    skipped += dropped;
    let summary = Summary { dropped, ..summarize(&frames, skipped) };
    let pose_reason = format!("{}, as set", settings.pose);
    Ok(RegisterReport { model: model.name(), pose: settings.pose, pose_reason, summary, frames, log })
}
