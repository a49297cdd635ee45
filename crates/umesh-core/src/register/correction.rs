//! The rest grid's co-rotational FE model pulled onto a frame's organ points (world, after the
//! rigid alignment) by point-to-plane springs on the surface the training camera sees, the
//! fixed region held (`fem::solver::fit`). Two uses, one fit: the physics correction after a
//! network's prediction (a bounded number of updates warm-started from the prediction), and
//! the FE registration alone (`FeDisplacementModel`, warm-started from the previous frame).

use super::RegistrationContext;
use crate::fem::MaterialParams;
use crate::fem::solver::fit::{FitWork, PointFit, PointFitReport, PointFitSettings};
use crate::grid::interpolate_nodes;
use nalgebra::Vector3;
use std::time::Instant;

/// The correction after each prediction.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CorrectionSettings {
    /// FE updates per frame (each one closest-point search and one co-rotational assembly);
    /// 0: no correction.
    pub updates: usize,
    /// Conjugate-gradient iterations per update at most (each one pair of triangular solves).
    pub cg_iterations: usize,
    /// When above 0: each update solved in a basis of the organ's responses to smooth loads on
    /// this many patches of the seen surface (x 3 axes), built once (`PointFit::use_subspace`),
    /// instead of by conjugate gradients.
    #[serde(default)]
    pub subspace_patches: usize,
    /// Start each frame's correction from the prediction plus the previous frame's correction
    /// (what the fit moved then, kept): over a sequence the correction accumulates, as the FE
    /// fit alone does from frame to frame, instead of starting again from each prediction.
    #[serde(default)]
    pub carry: bool,
    /// Measure the elastic energy from rest, as the FE fit alone does (by conjugate gradients,
    /// the subspace unused), instead of from the prediction (`FitWork::from_start`).
    #[serde(default)]
    pub from_rest: bool,
    /// On a frame whose prediction the confidence rule doubts (`Confidence::prediction_doubted`:
    /// the observed points too far from it, or it moves beyond the training deformations), the
    /// correction runs as the FE fit instead: its energy from rest, carried over the doubted
    /// frames, this many updates (0: a doubted frame is corrected as any other).
    #[serde(default = "default_doubted_updates")]
    pub doubted_updates: usize,
    /// Updates of a doubted frame that follows a doubted frame, whose fit on the coarsened
    /// organ starts from the one before (at most `doubted_updates`; a fit on the organ's own
    /// grid, `doubted_coarsening` 1 or the tracking forms, uses `doubted_updates` throughout).
    /// On the CT patient's 14 benchmark draws (grasp held out of training in 6) the last frames
    /// were at 0.71-1.53 mm with 2 against 0.72-1.39 with 4, at half the CG iterations; the
    /// first doubted frame of a run, started from the prediction, needs the 4 (2 left one at
    /// 1.78 mm against 0.87).
    #[serde(default = "default_doubted_carried_updates")]
    pub doubted_carried_updates: usize,
    /// A doubted frame that follows a doubted frame stops taking updates once one moved the
    /// coarse nodes by at most this (mm, RMS; 0: always `doubted_carried_updates`). A first
    /// update leaves about half its move for the next (on the CT patient's 14 benchmark draws
    /// the first moved 0.74-1.38 mm, the second 0.19-0.66), and what one update leaves the next
    /// frame starts from; an organ moving fast (about 4 mm a frame, first updates of 2-6 mm)
    /// gets the second update it needs. On those draws one update instead of two moved the last
    /// frame's error by -0.05 to +0.20 mm and halved the fit's time.
    #[serde(default = "default_doubted_carried_stop_mm")]
    pub doubted_carried_stop_mm: f64,
    /// Conjugate-gradient iterations per update of a doubted frame at most.
    #[serde(default = "default_doubted_cg")]
    pub doubted_cg_iterations: usize,
    /// A doubted frame's fit runs on the organ's cells this many times as large
    /// (`coarse::CoarseModel`; 1: on its own grid). Forms that carry their fit over every
    /// frame (the tracking forms) fit doubted frames on their own grid. Twice as large by
    /// default: on the CT patient's benchmark draws a doubted frame's correction took about
    /// 55-65 ms instead of 260-400, every draw still within 2 mm (0.71-1.55 mm against
    /// 0.41-1.26 on its own grid).
    #[serde(default = "default_doubted_coarsening")]
    pub doubted_coarsening: usize,
    /// Every frame corrected as the FE fit from rest on the organ coarsened
    /// `doubted_coarsening` times (`CoarseFit::track`), carried from frame to frame and moved
    /// by the network's prediction: `updates` updates a frame, `doubted_updates` at the first.
    #[serde(default)]
    pub coarse_tracking: bool,
}

fn default_doubted_coarsening() -> usize {
    CorrectionSettings::default().doubted_coarsening
}

fn default_doubted_updates() -> usize {
    CorrectionSettings::default().doubted_updates
}

fn default_doubted_carried_updates() -> usize {
    CorrectionSettings::default().doubted_carried_updates
}

fn default_doubted_carried_stop_mm() -> f64 {
    CorrectionSettings::default().doubted_carried_stop_mm
}

fn default_doubted_cg() -> usize {
    CorrectionSettings::default().doubted_cg_iterations
}

impl Default for CorrectionSettings {
    fn default() -> Self {
        Self {
            updates: 2,
            cg_iterations: 6,
            subspace_patches: 64,
            carry: false,
            from_rest: false,
            doubted_updates: 4,
            doubted_carried_updates: 2,
            doubted_carried_stop_mm: 2.0,
            doubted_cg_iterations: 10,
            doubted_coarsening: 2,
            coarse_tracking: false,
        }
    }
}

/// The most conjugate-gradient iterations a frame's correction may ask for (updates x
/// iterations; the defaults ask for 20, a doubted frame for 40).
pub const MAX_CG_PER_FRAME: usize = 200;

/// The largest `doubted_carried_stop_mm`: an update that moved the organ's nodes by 50 mm RMS is
/// no small step.
pub const MAX_CARRIED_STOP_MM: f64 = 50.0;

/// The most surface patches of the correction's subspace (3 basis vectors each; 64 by default).
pub const MAX_SUBSPACE_PATCHES: usize = 128;

impl CorrectionSettings {
    pub fn off() -> Self {
        Self { updates: 0, ..Self::default() }
    }

    /// The tracking correction: carried from frame to frame, its energy from rest (by CG), 2
    /// updates of 10 iterations. On the CT patient's eight new draws (`umesh bench register`)
    /// one update of 6 left gravity at 2.10 and 2.40 mm, two of 10 bring them to 0.95 and 1.81
    /// (all eight 0.39-1.81; the hand-made eight 0.52-1.89 -> 0.37-0.97), about twice its time.
    pub fn tracking() -> Self {
        Self { updates: 2, cg_iterations: 10, subspace_patches: 0, carry: true, from_rest: true, ..Self::default() }
    }

    /// The tracking correction solved in the surface-load subspace: carried, its energy from
    /// rest (linear in the rest stiffness), two updates of one m x m solve each.
    pub fn fast_tracking() -> Self {
        Self { updates: 2, carry: true, from_rest: true, ..Self::default() }
    }

    /// The tracking correction on the organ's cells twice as large (`CoarseFit::track`): one
    /// update of 6 CG iterations a frame, started from the fit before moved as the network's
    /// prediction moved, 4 of 10 at the first frame. On the 2.15 l SOFA liver's eight benchmark
    /// draws one update from the fit before alone fell behind the organ (the last frame 3.07 mm
    /// on the grasp draw that moved most), two took 0.33-0.94 mm at twice the fit's time; moved
    /// with the prediction, one of 10 iterations took 0.35-1.02 mm and one of 6 0.38-1.09, the
    /// subspace form's frame (four draws alternated twice: 26.6 ms median against its 27.9;
    /// 29.2 with 10).
    pub fn coarse_tracking() -> Self {
        Self {
            updates: 1,
            cg_iterations: 6,
            subspace_patches: 0,
            carry: false,
            from_rest: true,
            coarse_tracking: true,
            ..Self::default()
        }
    }

    pub fn validate(&self) -> Result<(), crate::Invalid> {
        for (what, updates, cg) in [
            ("--correction-updates / --correction-cg: the correction", self.updates, self.cg_iterations),
            (
                "--doubted-updates / --doubted-cg: the correction of a doubted frame",
                self.doubted_updates,
                self.doubted_cg_iterations,
            ),
        ] {
            // What a frame can afford: about 3 ms a CG iteration on the phantom (20 updates of
            // 200 took 12.7 s a frame), three times that on a 9000-node liver.
            if updates > 0 && (!(1..=MAX_CG_PER_FRAME).contains(&cg) || updates.saturating_mul(cg) > MAX_CG_PER_FRAME) {
                return Err(crate::Invalid(format!(
                    "{what}: {updates} updates of {cg} CG iterations; at most {MAX_CG_PER_FRAME} iterations a frame in all (about 0.6 s on the phantom)"
                )));
            }
        }
        if self.doubted_updates > 0 && !(1..=self.doubted_updates).contains(&self.doubted_carried_updates) {
            return Err(crate::Invalid(format!(
                "--doubted-carried-updates {}: a doubted frame after a doubted frame gets 1 to --doubted-updates ({}) updates",
                self.doubted_carried_updates, self.doubted_updates
            )));
        }
        if !(self.doubted_carried_stop_mm.is_finite()
            && (0.0..=MAX_CARRIED_STOP_MM).contains(&self.doubted_carried_stop_mm))
        {
            return Err(crate::Invalid(format!(
                "--doubted-carried-stop-mm {}: the motion (mm RMS) below which a doubted frame after a doubted frame stops taking updates: 0 (take them all) to {MAX_CARRIED_STOP_MM}",
                self.doubted_carried_stop_mm
            )));
        }
        if !(1..=super::coarse::MAX_COARSENING).contains(&self.doubted_coarsening) {
            return Err(crate::Invalid(format!(
                "--doubted-coarsening {}: a doubted frame's fit runs on cells 1 (the organ's own) to {} times the organ's",
                self.doubted_coarsening,
                super::coarse::MAX_COARSENING
            )));
        }
        if self.coarse_tracking && self.updates > 0 && self.doubted_coarsening < 2 {
            return Err(crate::Invalid(format!(
                "--doubted-coarsening {}: the coarse tracking form fits cells 2 to {} times the organ's (on the organ's own cells it is the tracking form)",
                self.doubted_coarsening,
                super::coarse::MAX_COARSENING
            )));
        }
        if self.subspace_patches > MAX_SUBSPACE_PATCHES {
            return Err(crate::Invalid(format!(
                "--correction-subspace: {} subspace patches; at most {MAX_SUBSPACE_PATCHES} (its basis is built before the first frame: 256 patches took 35 s on the phantom, 1000 did not finish in 5 minutes)",
                self.subspace_patches
            )));
        }
        Ok(())
    }

    /// The basis this correction solves in: (patches, free body); 0 patches when it is off or
    /// solved by CG. The tracking form's state lives in the basis, made of free-body responses
    /// (the rest stiffness alone); the correction from the prediction adds to it responses of a
    /// body held by the springs.
    pub fn basis(&self) -> (usize, bool) {
        if self.updates == 0 || self.coarse_tracking { (0, false) } else { (self.subspace_patches, self.from_rest) }
    }

    /// The correction of a frame whose prediction the confidence rule doubts: the FE fit from
    /// rest, carried (`doubted_updates`); None when it is not asked for or the correction is off.
    pub fn doubted(&self) -> Option<CorrectionSettings> {
        (self.updates > 0 && self.doubted_updates > 0).then_some(Self {
            updates: self.doubted_updates,
            cg_iterations: self.doubted_cg_iterations,
            // The tracking forms are the FE fit already: a doubted frame gets more of the same
            // updates; the correction from the prediction turns to the fit by CG.
            subspace_patches: if self.from_rest { self.subspace_patches } else { 0 },
            carry: true,
            from_rest: true,
            doubted_coarsening: if self.carry { 1 } else { self.doubted_coarsening },
            ..*self
        })
    }

    /// A doubted frame's correction (`doubted`) when the frame before was doubted too and its
    /// fit on the coarsened organ is where this one starts: `doubted_carried_updates`.
    pub fn after_doubted(&self) -> CorrectionSettings {
        Self { updates: self.doubted_carried_updates.clamp(1, self.updates.max(1)), ..*self }
    }

    pub fn work(&self) -> FitWork {
        FitWork {
            updates: self.updates,
            cg_iterations: self.cg_iterations,
            cg_tol: 1e-3,
            stop_mm: None,
            from_start: !self.from_rest,
            rest_in_subspace: self.from_rest && self.subspace_patches > 0,
        }
    }
}

/// What the correction did to one frame's prediction.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct CorrectionReport {
    /// How far it moved the prediction's nodes (mm): RMS over the nodes and the largest.
    pub moved_rms_mm: f64,
    pub moved_max_mm: f64,
    pub fit: PointFitReport,
    pub ms: f64,
    /// The prediction was doubted and corrected as the FE fit (`CorrectionSettings::doubted`).
    pub doubted: bool,
}

/// Build the physics correction's subspace of `patches` on `ctx` (seconds on a large grid)
/// before the frames come: a live stream then loses no frame to it.
pub fn prepare_correction(ctx: &RegistrationContext, basis: (usize, bool)) -> Result<(), crate::Invalid> {
    if basis.0 == 0 {
        return Ok(());
    }
    SurfaceFit::new(ctx, ctx.material, PointFitSettings::default())?.use_subspace(basis)
}

/// Samples every ~4.5 mm on the rest surface where all three corners of a triangle are seen by
/// the training camera, each with its triangle's normal: what the fit's springs pull.
pub(crate) fn seen_samples(ctx: &RegistrationContext) -> Vec<(Vector3<f64>, Vector3<f64>)> {
    let mut seen = vec![false; ctx.surface.positions.len()];
    for &v in &ctx.visible_vertices {
        seen[v] = true;
    }
    let part = crate::mesh::TriMesh {
        positions: ctx.surface.positions.clone(),
        triangles: ctx.surface.triangles.iter().copied().filter(|t| t.iter().all(|&v| seen[v as usize])).collect(),
    };
    crate::observation::dense_surface_points(&part, 0.05)
}

/// The FE model of a registration context with its current nodal displacement.
pub struct SurfaceFit<'c> {
    ctx: &'c RegistrationContext,
    fit: PointFit<'c>,
    pub u: Vec<Vector3<f64>>,
}

impl<'c> SurfaceFit<'c> {
    /// The fit's springs on `seen_samples`.
    pub fn new(
        ctx: &'c RegistrationContext,
        material: MaterialParams,
        settings: PointFitSettings,
    ) -> Result<Self, crate::Invalid> {
        let fit =
            PointFit::new(&ctx.grid, material, &ctx.fixed, &seen_samples(ctx), settings).map_err(|e| e.to_string())?;
        Ok(Self { ctx, fit, u: vec![Vector3::zeros(); ctx.grid.node_count()] })
    }

    /// Start from a dense [3, X, Y, Z] field (mm); the fixed nodes stay at zero.
    pub fn set_field(&mut self, field: &[f32]) {
        let g = &self.ctx.grid;
        let [x, y, z] = g.padded_shape();
        let cells = x * y * z;
        for (n, u) in self.u.iter_mut().enumerate() {
            let d = g.dense_index(n);
            *u = if self.ctx.fixed[n] {
                Vector3::zeros()
            } else {
                Vector3::new(field[d] as f64, field[cells + d] as f64, field[2 * cells + d] as f64)
            };
        }
    }

    /// The current displacement written into a dense [3, X, Y, Z] field (mm) at the grid's
    /// nodes, resized to the grid (entries off the grid are left as they are).
    pub fn write_field(&self, out: &mut Vec<f32>) {
        let g = &self.ctx.grid;
        let [x, y, z] = g.padded_shape();
        let cells = x * y * z;
        out.resize(3 * cells, 0.0);
        for (n, u) in self.u.iter().enumerate() {
            let d = g.dense_index(n);
            for c in 0..3 {
                out[c * cells + d] = u[c] as f32;
            }
        }
    }

    /// Solve the updates in a basis of `patches` x 3 surface-load responses (0: by CG), free
    /// body or held by the springs (`CorrectionSettings::basis`); built once per context.
    pub fn use_subspace(&mut self, basis: (usize, bool)) -> Result<(), crate::Invalid> {
        let ctx = self.ctx;
        let cached = ctx
            .correction_basis
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .find(|(k, _)| *k == basis)
            .map(|(_, s)| s.clone());
        if let Some(sub) = cached {
            return Ok(self.fit.set_subspace(sub).map_err(|e| e.to_string())?);
        }
        self.fit.use_subspace(basis.0, basis.1).map_err(|e| e.to_string())?;
        if let Some(sub) = self.fit.subspace() {
            ctx.correction_basis.lock().unwrap_or_else(|e| e.into_inner()).push((basis, sub.clone()));
        }
        Ok(())
    }

    /// `work` updates toward the points (world, mm), correspondences searched at each.
    pub fn fit(&mut self, points_world_mm: &[Vector3<f64>], work: FitWork) -> Result<PointFitReport, crate::Invalid> {
        Ok(self.fit.fit_with(points_world_mm, &mut self.u, work).map_err(|e| e.to_string())?)
    }

    /// The physics correction of a predicted field in place. With `carried` (one offset per
    /// node, empty at the start of a sequence), the fit starts from the prediction plus that
    /// offset and leaves in it this frame's whole correction of the prediction.
    pub fn correct(
        &mut self,
        points_world_mm: &[Vector3<f64>],
        field: &mut Vec<f32>,
        settings: &CorrectionSettings,
        carried: Option<&mut Vec<Vector3<f64>>>,
    ) -> Result<CorrectionReport, crate::Invalid> {
        let t = Instant::now();
        self.set_field(field);
        let predicted = self.u.clone();
        // The carried offset is zero at the fixed nodes: the fit holds them, as set_field does.
        if let Some(c) = carried.as_deref()
            && c.len() == self.u.len()
        {
            self.u.iter_mut().zip(c).for_each(|(u, d)| *u += d);
        }
        let fit = self.fit(points_world_mm, settings.work())?;
        // Moved: from the prediction, the carried part included.
        let moved: Vec<Vector3<f64>> = self.u.iter().zip(&predicted).map(|(a, b)| a - b).collect();
        let (sq, max) =
            moved.iter().fold((0.0f64, 0.0f64), |(s, m), d| (s + d.norm_squared(), m.max(d.norm_squared())));
        if let Some(c) = carried {
            *c = moved;
        }
        self.write_field(field);
        let n = self.u.len().max(1) as f64;
        Ok(CorrectionReport {
            moved_rms_mm: (sq / n).sqrt(),
            moved_max_mm: max.sqrt(),
            fit,
            ms: t.elapsed().as_secs_f64() * 1e3,
            doubted: false,
        })
    }
}

/// The FE fit of a doubted frame on the context's organ coarsened (`coarse::CoarseModel`), or
/// of every frame in the coarse tracking form. The prediction keeps its detail: only the change
/// the fit makes is carried to the organ's grid, interpolated.
pub struct CoarseFit<'c> {
    ctx: &'c RegistrationContext,
    model: &'c super::coarse::CoarseModel,
    fit: PointFit<'c>,
}

/// What a coarse fit carries from frame to frame: its displacement of the coarse nodes and the
/// prediction it corrected there (empty: a sequence starts, or a run of doubted frames ended).
#[derive(Clone, Debug, Default)]
pub struct CoarseCarried {
    fit: Vec<Vector3<f64>>,
    predicted: Vec<Vector3<f64>>,
}

impl CoarseCarried {
    pub fn is_empty(&self) -> bool {
        self.fit.is_empty()
    }

    pub fn clear(&mut self) {
        self.fit.clear();
        self.predicted.clear();
    }

    /// A fit and the prediction it followed are carried: a trusted frame follows them.
    pub fn follows(&self) -> bool {
        !self.fit.is_empty() && self.predicted.len() == self.fit.len()
    }

    /// The frame just fitted turned out doubted: the next frame does not follow its prediction.
    pub fn forget_prediction(&mut self) {
        self.predicted.clear();
    }
}

impl<'c> CoarseFit<'c> {
    pub fn new(ctx: &'c RegistrationContext, factor: usize) -> Result<Self, crate::Invalid> {
        let model = ctx.coarse_model(factor)?;
        let fit =
            PointFit::new(&model.grid, ctx.material, &model.fixed, &seen_samples(ctx), PointFitSettings::default())
                .map_err(|e| e.to_string())?;
        Ok(Self { ctx, model, fit })
    }

    /// As `SurfaceFit::correct` with the energy from rest: the predicted field is fitted on the
    /// coarse grid, started from `carried` (the coarse fit of the doubted frame before) or, at
    /// the first doubted frame (`carried` empty), from the prediction's restriction; the change
    /// the fit made to the prediction is added to the field interpolated, and `carried` then
    /// holds this frame's fit. The energy is measured from rest, so the start decides only how
    /// much work is left: the fit before is a frame's motion away, while a prediction the rule
    /// doubts may jump (on the CT patient, a pressing draw restarted from prediction plus the
    /// change carried reached 2.93 mm in 2 updates against 1.29 in 4). From the fit before,
    /// the updates stop once one moves little (`doubted_carried_stop_mm`).
    pub fn correct(
        &mut self,
        points_world_mm: &[Vector3<f64>],
        field: &mut [f32],
        settings: &CorrectionSettings,
        carried: &mut CoarseCarried,
    ) -> Result<CorrectionReport, crate::Invalid> {
        let t = Instant::now();
        let predicted = self.predicted(field);
        let from_carried = carried.fit.len() == predicted.len();
        let start = if from_carried { carried.fit.clone() } else { predicted.clone() };
        let mut work = CorrectionSettings { subspace_patches: 0, from_rest: true, ..*settings }.work();
        if from_carried && settings.doubted_carried_stop_mm > 0.0 {
            work.stop_mm = Some(settings.doubted_carried_stop_mm);
        }
        let mut r = self.fit_from(points_world_mm, field, predicted, start, work, carried)?;
        r.ms = t.elapsed().as_secs_f64() * 1e3;
        Ok(r)
    }

    /// The coarse tracking form's correction of every frame (`CorrectionSettings::
    /// coarse_tracking`), the fit from rest carried from frame to frame. With `trusted` (the
    /// confidence rule did not doubt this prediction) it starts from the fit before moved as
    /// the prediction moved at the coarse nodes since the last trusted one, `updates` updates:
    /// the network's motion is the start, the elastic energy from rest the fit, and the
    /// prediction's own error where the surface does not show it stays out. A doubted
    /// prediction may jump (on the CT patient's pressing draw, following it diverged to 6.5 mm
    /// within three frames): it starts from the fit before alone, as a doubted frame after a
    /// doubted frame (`after_doubted`, with the stop), and so does the frame after it. The
    /// first frame starts from the prediction as a first doubted frame (`doubted_updates` of
    /// `doubted_cg_iterations`; with `doubted_updates` 0, as the others).
    pub fn track(
        &mut self,
        points_world_mm: &[Vector3<f64>],
        field: &mut [f32],
        settings: &CorrectionSettings,
        carried: &mut CoarseCarried,
        trusted: bool,
    ) -> Result<CorrectionReport, crate::Invalid> {
        let n = self.model.grid.node_count();
        let following = trusted && carried.fit.len() == n && carried.predicted.len() == n;
        let r = match settings.doubted() {
            // Not following: what a doubted frame's coarse fit does (from the fit before with
            // the stop, or at the first frame from the prediction).
            Some(d) if !following => {
                let d = if carried.fit.len() == n { d.after_doubted() } else { d };
                self.correct(points_world_mm, field, &d, carried)
            }
            _ => {
                let t = Instant::now();
                let predicted = self.predicted(field);
                let work = CorrectionSettings { subspace_patches: 0, from_rest: true, ..*settings }.work();
                let start = if following {
                    carried.fit.iter().zip(&predicted).zip(&carried.predicted).map(|((u, p), q)| u + p - q).collect()
                } else {
                    predicted.clone()
                };
                let mut r = self.fit_from(points_world_mm, field, predicted, start, work, carried)?;
                r.ms = t.elapsed().as_secs_f64() * 1e3;
                Ok(r)
            }
        }?;
        if !trusted {
            carried.forget_prediction();
        }
        Ok(CorrectionReport { doubted: !trusted, ..r })
    }

    /// The field's prediction at the coarse nodes.
    fn predicted(&self, field: &[f32]) -> Vec<Vector3<f64>> {
        let fine = &self.ctx.grid;
        let [x, y, z] = fine.padded_shape();
        let cells = x * y * z;
        let predicted_fine: Vec<Vector3<f64>> = (0..fine.node_count())
            .map(|n| {
                let d = fine.dense_index(n);
                Vector3::new(field[d] as f64, field[cells + d] as f64, field[2 * cells + d] as f64)
            })
            .collect();
        self.model.restrict(&predicted_fine)
    }

    /// Fit from `start`; the change from `predicted` added to the field interpolated; the fit
    /// and the prediction kept in `carried`.
    fn fit_from(
        &mut self,
        points_world_mm: &[Vector3<f64>],
        field: &mut [f32],
        predicted: Vec<Vector3<f64>>,
        mut u: Vec<Vector3<f64>>,
        work: FitWork,
        carried: &mut CoarseCarried,
    ) -> Result<CorrectionReport, crate::Invalid> {
        let fine = &self.ctx.grid;
        let [x, y, z] = fine.padded_shape();
        let cells = x * y * z;
        let fit = self.fit.fit_with(points_world_mm, &mut u, work).map_err(|e| e.to_string())?;
        let change: Vec<Vector3<f64>> = u.iter().zip(&predicted).map(|(a, b)| a - b).collect();
        carried.fit = u;
        carried.predicted = predicted;
        let (mut sq, mut max) = (0.0f64, 0.0f64);
        for (n, e) in self.model.fine_in_coarse.iter().enumerate() {
            if self.ctx.fixed[n] {
                continue;
            }
            let d = interpolate_nodes(e, &change);
            let i = fine.dense_index(n);
            for c in 0..3 {
                field[c * cells + i] += d[c] as f32;
            }
            sq += d.norm_squared();
            max = max.max(d.norm_squared());
        }
        Ok(CorrectionReport {
            moved_rms_mm: (sq / fine.node_count().max(1) as f64).sqrt(),
            moved_max_mm: max.sqrt(),
            fit,
            ms: 0.0,
            doubted: true,
        })
    }
}

/// The correction's forms: the subspace update from each prediction (`CorrectionSettings::
/// default`), the tracking form by CG (`tracking`, 5-10 times the frame; the FE fit itself,
/// best where the network is weak) and, asked for by name, the tracking form in a subspace
/// (`fast_tracking`, about the subspace form's frame; not yet as accurate as either), and the
/// tracking form on cells twice as large (`coarse_tracking`, about the subspace form's frame).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CorrectionForm {
    #[default]
    Subspace,
    Tracking,
    FastTracking,
    CoarseTracking,
}

impl CorrectionForm {
    pub fn settings(self) -> CorrectionSettings {
        match self {
            Self::Subspace => CorrectionSettings::default(),
            Self::Tracking => CorrectionSettings::tracking(),
            Self::FastTracking => CorrectionSettings::fast_tracking(),
            Self::CoarseTracking => CorrectionSettings::coarse_tracking(),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Subspace => "subspace",
            Self::Tracking => "tracking",
            Self::FastTracking => "fast-tracking",
            Self::CoarseTracking => "coarse-tracking",
        }
    }
}

/// A form that costs more than twice the frame of the form it would replace is chosen only
/// when its mean TRE over the second half of the check recording's frames is at most this
/// share of that form's; a form of about the same cost only has to be more accurate.
/// Measured ratios (tracking / subspace): 0.32-0.49 on eight CT recordings, 0.49-0.62 on a
/// model that never saw the family, 0.61-1.21 (median 0.93) on the phantom's seventeen.
pub const TRACKING_CHOSEN_AT_MOST: f64 = 0.75;

/// The frame budget a form is chosen within unless told otherwise (ms): a camera at 30 frames a
/// second.
pub const DEFAULT_FRAME_BUDGET_MS: f64 = 33.0;

/// One correction form's figures on a check recording.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FormFigures {
    /// Mean TRE over the second half of the frames with ground truth (mm).
    pub late_tre_mm: f64,
    pub last_tre_mm: f64,
    pub frame_ms_median: f64,
}

/// The correction forms a model's registration check measured on its organ, kept in the model
/// folder (`CorrectionChoice::FILE`), and the form chosen within the default frame budget:
/// `register` and the AR view choose again for the budget they are given.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CorrectionChoice {
    pub format: String,
    pub format_version: u32,
    pub form: CorrectionForm,
    pub subspace: FormFigures,
    pub tracking: FormFigures,
    /// Measured by checks that know the form (a choice written before does not have it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coarse_tracking: Option<FormFigures>,
    /// The recording the forms were measured on.
    pub recording: String,
}

impl CorrectionChoice {
    pub const FILE: &'static str = "correction.json";
    const FORMAT: &'static str = "umesh-correction-choice";

    pub fn decide(subspace: FormFigures, tracking: FormFigures, recording: &std::path::Path) -> Self {
        Self::decide_among(subspace, None, tracking, recording)
    }

    /// As `decide`, with the coarse tracking form's figures when it was measured.
    pub fn decide_among(
        subspace: FormFigures,
        coarse_tracking: Option<FormFigures>,
        tracking: FormFigures,
        recording: &std::path::Path,
    ) -> Self {
        let mut c = Self {
            format: Self::FORMAT.into(),
            format_version: 1,
            form: CorrectionForm::Subspace,
            subspace,
            tracking,
            coarse_tracking,
            recording: recording.display().to_string(),
        };
        c.form = c.choose(Some(DEFAULT_FRAME_BUDGET_MS)).0;
        c
    }

    /// The measured forms, cheapest first (fast-tracking is asked for by name only: on the CT
    /// patient's benchmark it met the bar on 3 of 8 draws where the subspace form met it on 7).
    fn forms(&self) -> Vec<(CorrectionForm, FormFigures)> {
        let mut forms = vec![(CorrectionForm::Subspace, self.subspace)];
        forms.extend(self.coarse_tracking.map(|f| (CorrectionForm::CoarseTracking, f)));
        forms.push((CorrectionForm::Tracking, self.tracking));
        forms
    }

    /// The form for a frame budget (None: accuracy alone) and why, in one sentence: starting
    /// from the cheapest, a form replaces the one held when its measured frame fits the budget
    /// and it is more accurate (by `TRACKING_CHOSEN_AT_MOST` when it costs more than twice the
    /// frame). When no form fits, the fastest measured, said so.
    pub fn choose(&self, budget_ms: Option<f64>) -> (CorrectionForm, String) {
        let forms = self.forms();
        let within = |f: &FormFigures| budget_ms.is_none_or(|b| f.frame_ms_median <= b);
        let (mut best, mut fig) = forms[0];
        for &(form, f) in &forms[1..] {
            let share = if f.frame_ms_median > 2.0 * fig.frame_ms_median { TRACKING_CHOSEN_AT_MOST } else { 1.0 };
            if within(&f) && f.late_tre_mm <= share * fig.late_tre_mm {
                (best, fig) = (form, f);
            }
        }
        if !within(&fig)
            && let Some(&(form, f)) = forms.iter().min_by(|a, b| a.1.frame_ms_median.total_cmp(&b.1.frame_ms_median))
        {
            (best, fig) = (form, f);
        }
        let measured = forms
            .iter()
            .map(|(form, f)| format!("{} {:.2} mm at {:.0} ms", form.name(), f.late_tre_mm, f.frame_ms_median))
            .collect::<Vec<_>>()
            .join(", ");
        let why = match budget_ms {
            Some(b) if !within(&fig) => format!(
                "{} correction: no form met the {b:.0} ms frame budget on the check recording, this is the fastest (late TRE and frame: {measured})",
                best.name()
            ),
            Some(b) => format!(
                "{} correction: the most accurate within {b:.0} ms a frame on the check recording (late TRE and frame: {measured}; a form over twice the frame must be {:.0} % better)",
                best.name(),
                100.0 * (1.0 - TRACKING_CHOSEN_AT_MOST)
            ),
            None => format!(
                "{} correction: the most accurate on the check recording, the frame time not limited (late TRE and frame: {measured})",
                best.name()
            ),
        };
        (best, why)
    }

    /// One line: the form chosen within the default budget and the figures it was chosen on.
    pub fn describe(&self) -> String {
        self.choose(Some(DEFAULT_FRAME_BUDGET_MS)).1
    }

    /// The model folder's choice; None when it has none (models from before, or not checked).
    pub fn read(model_dir: &std::path::Path) -> Result<Option<Self>, crate::Invalid> {
        let path = model_dir.join(Self::FILE);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(crate::Invalid(format!("{}: {e}", path.display()))),
        };
        let c: Self = serde_json::from_str(&text)
            .map_err(|e| crate::Invalid(format!("{}: not a correction choice: {e}", path.display())))?;
        if c.format != Self::FORMAT || c.format_version != 1 {
            return Err(crate::Invalid(format!(
                "{}: format {} version {} (expected {} 1)",
                path.display(),
                c.format,
                c.format_version,
                Self::FORMAT
            )));
        }
        // A TRE beyond 1000 mm or a frame beyond an hour describes no registration (1e308 mm
        // was printed as it was).
        let ok = |x: &FormFigures| {
            [(x.late_tre_mm, 1000.0), (x.last_tre_mm, 1000.0), (x.frame_ms_median, 3.6e6)]
                .iter()
                .all(|(v, max)| v.is_finite() && *v >= 0.0 && v <= max)
        };
        if !(ok(&c.subspace) && ok(&c.tracking) && c.coarse_tracking.as_ref().is_none_or(ok)) {
            return Err(crate::Invalid(format!(
                "{}: a figure is negative or not finite, or beyond what a registration gives (a TRE over 1000 mm, a frame over an hour)",
                path.display()
            )));
        }
        Ok(Some(c))
    }

    pub fn write(&self, model_dir: &std::path::Path) -> Result<(), crate::Invalid> {
        let path = model_dir.join(Self::FILE);
        let text = serde_json::to_string_pretty(self).map_err(|e| crate::Invalid(e.to_string()))?;
        crate::write_atomic(&path, text.as_bytes()).map_err(|e| crate::Invalid(format!("{}: {e}", path.display())))
    }
}
