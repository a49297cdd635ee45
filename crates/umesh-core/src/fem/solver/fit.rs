//! Co-rotational FE registration to an observed point cloud, the FE baseline of the
//! registration: each observed point pulls its nearest deformed surface sample by a soft
//! spring along the sample's (turned) normal, and the correspondences are found again a
//! fixed number of times per frame. Point-to-plane, because a depth camera sees where the
//! surface is, not which material point is there: with point-to-point springs a converged fit
//! matched the points to 1.1 mm RMS and still left 7.8 of the phantom's 17.3 mm of marker
//! motion undone (each sample dragged sideways toward one noisy point), and stiffer springs
//! made it worse (13.6 mm).
//! Every update is a Newton-like step on the co-rotational energy plus the springs: the
//! cells' rest stiffness turned by their current rotations (applied matrix-free), solved by
//! conjugate gradients preconditioned by one matrix factorised once when the fit is built
//! (the rest stiffness plus a spring on every eligible sample, in single precision) and
//! turned by the nodal rotations (stiffness warping). A frame costs a bounded number of
//! triangular solves and assemblies, never a factorisation. Without the rotations, a step
//! from the rest stiffness overshot so far under large deformation (15 mm mean on the
//! phantom) that the line search rejected every update and the frame did nothing.

use super::{FeSolver, FemError, SolverSettings, norm};
use crate::fem::MaterialParams;
use crate::fem::assembly::{ElementModel, NONE};
use crate::grid::{Embedding, ImmersedGrid, interpolate_nodes};
use crate::nn::PointIndex;
use faer::Mat;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use std::time::Instant;

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PointFitSettings {
    /// Correspondence updates per frame (each one assembly of the co-rotational forces).
    pub iterations: usize,
    /// Conjugate-gradient iterations per update at most (each one triangular solve).
    pub cg_iterations: usize,
    /// An observed point farther than this from the current surface pulls nothing (mm).
    pub band_mm: f64,
    /// Total stiffness of the springs over the eligible samples, relative to E·L (L the cube
    /// root of the organ's volume): large enough that the surface follows the points (on the
    /// phantom at 3.5 mm of motion, 50 left 1.6 times the last-frame TRE of 500, 2000 no
    /// better than 500).
    pub spring_scale: f64,
    /// Stiffness of a spring across its sample's normal relative to along it: 1 is a
    /// point-to-point spring, 0 pure point-to-plane (which leaves sliding unresisted by the
    /// data; a little keeps each step well posed).
    #[serde(default = "default_tangential_weight")]
    pub tangential_weight: f64,
}

/// On the phantom's seed-1 recording (17.3 mm of motion, the fit's fixed work) the last-frame
/// TRE was 1.88 mm at 0.005, 2.17 at 0.02, 6.08 at 0.2 and 5.63 at 1 (point-to-point).
fn default_tangential_weight() -> f64 {
    0.005
}

impl Default for PointFitSettings {
    fn default() -> Self {
        Self {
            iterations: 4,
            cg_iterations: 10,
            band_mm: 10.0,
            spring_scale: 500.0,
            tangential_weight: default_tangential_weight(),
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct PointFitReport {
    /// Observed points within the band of the surface, in the last update.
    pub points_matched: usize,
    /// Surface samples pulled by at least one point, in the last update.
    pub samples_matched: usize,
    pub cg_iterations: usize,
    /// Updates that moved the nodes (an update whose step the line search cut below a tenth
    /// changes nothing).
    pub updates: usize,
    /// RMS distance of the matched points to their samples after the last update (mm).
    pub rms_mm: f64,
    /// Where the frame went (ms): closest-point search, co-rotational assemblies (forces and
    /// the line search's energies), conjugate gradients (triangular solves and products).
    pub search_ms: f64,
    pub assembly_ms: f64,
    pub solve_ms: f64,
}

/// How much work a fit does.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitWork {
    pub updates: usize,
    /// CG iterations per update at most, and the relative residual that ends them earlier.
    pub cg_iterations: usize,
    pub cg_tol: f64,
    /// Stop once an update moves the nodes by at most this (mm, RMS); closest-point
    /// correspondences keep switching by a sample, so a max-norm test would never settle.
    pub stop_mm: Option<f64>,
    /// Measure the elastic energy from the starting displacement instead of from rest: the
    /// physics correction, whose start is a network's prediction of an organ under loads the
    /// model does not know. From rest, the step also pulls the prediction back toward the
    /// unloaded shape (those loads' stress read as error); from the start, it adds the least
    /// elastic deformation that brings the surface onto the points. On the phantom's four
    /// 20-frame recordings of 10-17 mm (seed 1) the last frame's TRE fell from 3.36, 0.98, 0.76,
    /// 2.05 mm (pressing, instrument, grasp, gravity) to 2.93, 0.82, 0.90, 1.86 with the same CG
    /// work, and to 2.36, 0.84, 0.84, 1.69 in the 64-patch subspace.
    pub from_start: bool,
    /// With the energy from rest (`from_start` false), solve each update in the subspace when
    /// one is set (`PointFit::use_subspace`), as the correction from the start always does.
    pub rest_in_subspace: bool,
}

impl FitWork {
    /// The registration's per-frame work.
    pub fn fixed(settings: &PointFitSettings) -> Self {
        Self {
            updates: settings.iterations,
            cg_iterations: settings.cg_iterations,
            cg_tol: 1e-3,
            stop_mm: None,
            from_start: false,
            rest_in_subspace: false,
        }
    }

    /// Tight inner solves until an update moves the nodes by at most `tol_mm` RMS (at most
    /// `max_updates`).
    pub fn converged(tol_mm: f64, max_updates: usize) -> Self {
        Self {
            updates: max_updates,
            cg_iterations: 300,
            cg_tol: 1e-6,
            stop_mm: Some(tol_mm),
            from_start: false,
            rest_in_subspace: false,
        }
    }
}

pub struct PointFit<'g> {
    solver: FeSolver<'g>,
    samples: Vec<Embedding>,
    rest_mm: Vec<Vector3<f64>>,
    /// Each sample's outward rest normal.
    normals: Vec<Vector3<f64>>,
    /// Stiffness of one sample's spring (N/mm).
    k_n_per_mm: f64,
    pub settings: PointFitSettings,
    buckets: PointIndex,
    /// When set, each update solves in this basis instead of by conjugate gradients.
    subspace: Option<Subspace>,
    /// The free dofs of the nodes the samples hang on (node, axis, free index): all an update
    /// between two searches needs to move.
    sample_dofs: Vec<(u32, u8, u32)>,
    /// Per free dof: its place in `sample_dofs` (NONE: not a sample's).
    sample_slot: Vec<u32>,
    /// The basis's columns of `sample_dofs` (m x sample dofs), gathered once.
    sample_basis: Option<Mat<f32>>,
}

/// A basis of the displacements an update may make: the organ's response to smooth loads on
/// patches of the surface the springs act on (the rest stiffness with every spring, solved
/// once per patch and axis), orthonormalised. A correction's springs pull only that surface,
/// and an elastic body's response to surface loads is dominated by its smooth part, so the
/// update's system projected on the basis is small and dense: one m x m solve a frame instead
/// of one pair of triangular solves of the whole grid per CG iteration.
#[derive(Clone, Debug)]
pub struct Subspace {
    /// The basis transposed (m x free dofs): column j holds dof j's coefficients. Single
    /// precision: each frame reads it from memory (26 MB in double precision on the phantom),
    /// and its 1e-7 relative rounding is far below the correction's millimetres.
    phit: Mat<f32>,
    /// The rest stiffness projected on the basis (m x m).
    k_r: Mat<f64>,
    /// (K Phi)^T (m x free dofs), K the rest stiffness: an update measured from rest needs the
    /// starting displacement's elastic force in the basis, Phi^T K u, one product.
    kphit: Mat<f32>,
}

impl<'g> PointFit<'g> {
    /// `samples_mm`: rest-surface points with their outward normals that observed points may
    /// pull (the part of the surface the camera can see); `fixed`: the nodes held.
    pub fn new(
        grid: &'g ImmersedGrid,
        material: MaterialParams,
        fixed: &[bool],
        samples_mm: &[(Vector3<f64>, Vector3<f64>)],
        settings: PointFitSettings,
    ) -> Result<Self, FemError> {
        let bad = |r: String| FemError::InvalidInput(r);
        if settings.iterations == 0
            || settings.iterations > 100
            || settings.cg_iterations == 0
            || settings.cg_iterations > 1000
        {
            return Err(bad(format!(
                "point fit: {} updates of {} CG iterations",
                settings.iterations, settings.cg_iterations
            )));
        }
        if !(settings.band_mm > 0.0
            && settings.band_mm.is_finite()
            && settings.spring_scale > 0.0
            && settings.spring_scale.is_finite())
        {
            return Err(bad(format!(
                "point fit: band {} mm, spring scale {}",
                settings.band_mm, settings.spring_scale
            )));
        }
        if !(0.0..=1.0).contains(&settings.tangential_weight) {
            return Err(bad(format!("point fit: tangential weight {} (between 0 and 1)", settings.tangential_weight)));
        }
        let mut solver = FeSolver::new(grid, material, fixed, SolverSettings::default())?;
        let mut samples = Vec::with_capacity(samples_mm.len());
        let mut rest_mm = Vec::with_capacity(samples_mm.len());
        let mut normals = Vec::with_capacity(samples_mm.len());
        for (p, n) in samples_mm {
            let n = n.normalize();
            if !(p.iter().all(|v| v.is_finite()) && n.iter().all(|v| v.is_finite())) {
                continue;
            }
            if let Some(e) = grid.embed(p) {
                samples.push(e);
                rest_mm.push(*p);
                normals.push(n);
            }
        }
        if samples.is_empty() {
            return Err(bad("point fit: no surface sample lies on the grid".into()));
        }
        let h3 = grid.cell_size_mm.powi(3);
        let volume_mm3: f64 = grid.cells.iter().map(|c| c.volume_fraction * h3).sum();
        let e_n_per_mm2 = material.young_pa * 1e-6;
        let k_n_per_mm = settings.spring_scale * e_n_per_mm2 * volume_mm3.cbrt() / samples.len() as f64;
        // The preconditioner: the co-rotational stiffness at rest plus every spring with its
        // rest metric (turned by the nodal rotations in each solve, as the springs turn with
        // their cells).
        let zeros = vec![Vector3::zeros(); grid.node_count()];
        solver.asm.assemble(ElementModel::Corotational, &zeros, true);
        let w = settings.tangential_weight;
        for (e, n) in samples.iter().zip(&normals) {
            debug_assert_eq!(e.nodes, grid.cells[e.cell as usize].nodes);
            let nn = n * n.transpose();
            let m = nn + (Matrix3::identity() - nn) * w;
            for a in 0..8 {
                for b in 0..8 {
                    let v = k_n_per_mm * e.weights[a] * e.weights[b];
                    if v != 0.0 {
                        for c in 0..3 {
                            for d in 0..3 {
                                solver.asm.add_to_cell_entry(e.cell as usize, 3 * a + c, 3 * b + d, v * m[(c, d)]);
                            }
                        }
                    }
                }
            }
        }
        solver.fact.factorize(&solver.asm, false, solver.settings.parallelism.par())?;
        // Only ever a preconditioner: single precision halves every triangular solve.
        solver.fact.factorize32(&solver.asm, solver.settings.parallelism.par());
        let free = &solver.asm.dofs.free_of;
        let mut on_sample = vec![false; grid.node_count()];
        samples.iter().flat_map(|e| e.nodes).for_each(|n| on_sample[n as usize] = true);
        let mut sample_slot = vec![NONE; solver.asm.dofs.n_free];
        let mut sample_dofs = Vec::new();
        for (n, _) in on_sample.iter().enumerate().filter(|(_, on)| **on) {
            for c in 0..3 {
                let f = free[3 * n + c];
                if f != NONE {
                    sample_slot[f as usize] = sample_dofs.len() as u32;
                    sample_dofs.push((n as u32, c as u8, f));
                }
            }
        }
        Ok(Self {
            solver,
            samples,
            rest_mm,
            normals,
            k_n_per_mm,
            settings,
            buckets: PointIndex::default(),
            subspace: None,
            sample_dofs,
            sample_slot,
            sample_basis: None,
        })
    }

    pub fn samples(&self) -> usize {
        self.samples.len()
    }

    /// Energy of the springs toward `targets` (N mm), each with its metric (`spring_metric`).
    fn spring_energy(&self, u: &[Vector3<f64>], targets: &[Option<(Vector3<f64>, Matrix3<f64>)>]) -> f64 {
        self.samples
            .iter()
            .zip(&self.rest_mm)
            .zip(targets)
            .filter_map(|((e, x), t)| {
                t.map(|(t, m)| {
                    let d = x + interpolate_nodes(e, u) - t;
                    0.5 * self.k_n_per_mm * d.dot(&(m * d))
                })
            })
            .sum()
    }

    /// A spring's metric for sample `s`: n n^T + w (I - n n^T), n its rest normal turned by
    /// its cell's rotation at the last assembly.
    fn spring_metric(&self, s: usize) -> Matrix3<f64> {
        let w = self.settings.tangential_weight;
        let n = (self.solver.asm.cell_rotation(self.samples[s].cell as usize) * self.normals[s]).normalize();
        let nn = n * n.transpose();
        nn + (Matrix3::identity() - nn) * w
    }

    fn deformed(&self, u: &[Vector3<f64>]) -> Vec<Vector3<f64>> {
        self.samples.par_iter().zip(&self.rest_mm).map(|(e, x)| x + interpolate_nodes(e, u)).collect()
    }

    /// Move `u` (the previous frame's displacement in, this frame's out) toward `points_mm`:
    /// the settings' fixed number of updates, the registration's per-frame work.
    pub fn fit(&mut self, points_mm: &[Vector3<f64>], u: &mut [Vector3<f64>]) -> Result<PointFitReport, FemError> {
        self.fit_updates(points_mm, u, FitWork::fixed(&self.settings), false)
    }

    /// As `fit` with the given work, the correspondences searched again at every update.
    pub fn fit_with(
        &mut self,
        points_mm: &[Vector3<f64>],
        u: &mut [Vector3<f64>],
        work: FitWork,
    ) -> Result<PointFitReport, FemError> {
        self.fit_updates(points_mm, u, work, false)
    }

    /// As `fit`, but the correspondences of `u`'s surface to `points_mm` found once and held:
    /// with `FitWork::converged`, the solve a frame's fixed work approximates.
    pub fn fit_held(
        &mut self,
        points_mm: &[Vector3<f64>],
        u: &mut [Vector3<f64>],
        work: FitWork,
    ) -> Result<PointFitReport, FemError> {
        self.fit_updates(points_mm, u, work, true)
    }

    /// The Newton-like step `du` from the rest stiffness can overshoot under large rotations:
    /// halved (at most four times) until the energy, elastic plus the matched springs,
    /// decreases. The elastic energy is `e_elastic` at `u`, and along the step either the
    /// quadratic (slope, curvature) of the from-the-start form or a co-rotational assembly.
    #[allow(clippy::type_complexity)]
    fn halving_step(
        &mut self,
        u: &[Vector3<f64>],
        du: &[f64],
        free: &[u32],
        (e_elastic, quad): (f64, Option<(f64, f64)>),
        targets: &[Option<(Vector3<f64>, Matrix3<f64>)>],
    ) -> (Vec<Vector3<f64>>, f64) {
        let e0 = e_elastic + self.spring_energy(u, targets);
        let mut step = 1.0;
        let mut trial = u.to_vec();
        for _ in 0..4 {
            for (n, (tn, un)) in trial.iter_mut().zip(u.iter()).enumerate() {
                for c in 0..3 {
                    let f = free[3 * n + c];
                    tn[c] = un[c] + if f != NONE { step * du[f as usize] } else { 0.0 };
                }
            }
            let el = match quad {
                Some((slope, curvature)) => e_elastic + step * slope + 0.5 * step * step * curvature,
                None => self.solver.asm.assemble(ElementModel::Corotational, &trial, false).energy,
            };
            let e1 = el + self.spring_energy(&trial, targets);
            if e1 <= e0 {
                break;
            }
            step *= 0.5;
        }
        (trial, step)
    }

    /// From the start: the co-rotational stiffness (this assembly's rotations) times the
    /// displacement since `u0` as the elastic force on every node, its energy, and the product
    /// on the free dofs.
    fn elastic_since(
        &mut self,
        u: &[Vector3<f64>],
        u0: &[Vector3<f64>],
        free: &[u32],
        nf: usize,
    ) -> (Vec<Vector3<f64>>, f64, Vec<f64>) {
        let mut d = vec![0.0; nf];
        for (n, (a, b)) in u.iter().zip(u0).enumerate() {
            for c in 0..3 {
                let f = free[3 * n + c];
                if f != NONE {
                    d[f as usize] = a[c] - b[c];
                }
            }
        }
        let mut kd = vec![0.0; nf];
        // The first update starts where it measures from: nothing to multiply.
        if d.iter().any(|&v| v != 0.0) {
            self.solver.asm.corotational_matvec(&d, &mut kd);
        }
        let e = 0.5 * d.iter().zip(&kd).map(|(a, b)| a * b).sum::<f64>();
        let mut g = vec![Vector3::zeros(); u.len()];
        for (n, gn) in g.iter_mut().enumerate() {
            for c in 0..3 {
                let f = free[3 * n + c];
                if f != NONE {
                    gn[c] = kd[f as usize];
                }
            }
        }
        (g, e, kd)
    }

    fn fit_updates(
        &mut self,
        points_mm: &[Vector3<f64>],
        u: &mut [Vector3<f64>],
        work: FitWork,
        freeze: bool,
    ) -> Result<PointFitReport, FemError> {
        let FitWork { updates: iterations, cg_iterations, cg_tol, stop_mm, from_start, rest_in_subspace } = work;
        let grid = self.solver.grid;
        if u.len() != grid.node_count() {
            return Err(FemError::InvalidInput(format!(
                "point fit: {} displacements for {} nodes",
                u.len(),
                grid.node_count()
            )));
        }
        if (from_start || rest_in_subspace)
            && let Some(sub) = self.subspace.take()
        {
            let r = self.subspace_updates(&sub, points_mm, u, iterations, freeze, !from_start);
            self.subspace = Some(sub);
            return Ok(r);
        }
        let band = self.settings.band_mm;
        let ns = self.samples.len();
        let free = self.solver.asm.dofs.free_of.clone();
        let nf = self.solver.asm.dofs.n_free;
        let mut report = PointFitReport::default();
        let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
        // The sample each observed point pulls in the last update (u32::MAX: none).
        let mut nearest: Vec<u32> = Vec::new();
        let u0 = if from_start { u.to_vec() } else { Vec::new() };
        for it in 0..iterations {
            let t = Instant::now();
            let pos = self.deformed(u);
            if it == 0 || !freeze {
                nearest = nearest_samples(&mut self.buckets, grid, &pos, points_mm, band);
            }
            let (acc, count) = pulls(ns, points_mm, &nearest);
            let matched_points = nearest.iter().filter(|&&s| s != u32::MAX).count();
            let matched: Vec<bool> = count.iter().map(|&c| c > 0).collect();
            report.points_matched = matched_points;
            report.samples_matched = matched.iter().filter(|&&m| m).count();
            report.search_ms += ms(t);
            if matched_points == 0 {
                return Ok(report);
            }
            // Gradient of the co-rotational energy plus the matched springs.
            let t = Instant::now();
            let a = self.solver.asm.assemble(ElementModel::Corotational, u, false);
            // The elastic part: the co-rotational forces from rest, or, from the start, the
            // co-rotational stiffness (rotations of this assembly) times the displacement since.
            let (mut g, e_elastic, kd) = if from_start {
                let (g, e, kd) = self.elastic_since(u, &u0, &free, nf);
                (g, e, Some(kd))
            } else {
                (a.f_int, a.energy, None)
            };
            report.assembly_ms += ms(t);
            let metrics: Vec<Option<Matrix3<f64>>> =
                (0..ns).map(|s| matched[s].then(|| self.spring_metric(s))).collect();
            for s in 0..ns {
                if let Some(m) = metrics[s] {
                    let r = m * (pos[s] - acc[s] / count[s] as f64);
                    let e = &self.samples[s];
                    for k in 0..8 {
                        g[e.nodes[k] as usize] += r * (self.k_n_per_mm * e.weights[k]);
                    }
                }
            }
            let b = minus_on_free(&g, &free, nf);
            let t = Instant::now();
            let (du, iters) = self.pcg(&b, &metrics, &free, cg_iterations, cg_tol);
            report.solve_ms += ms(t);
            report.cg_iterations += iters;
            // The step comes from the rest stiffness: under large rotations it can overshoot,
            // so it is halved until the energy (elastic plus the matched springs) decreases.
            let targets: Vec<Option<(Vector3<f64>, Matrix3<f64>)>> =
                (0..ns).map(|s| metrics[s].map(|m| (acc[s] / count[s] as f64, m))).collect();
            // From the start the elastic energy along the step is a quadratic: its slope and
            // curvature (one more product), no assembly per trial.
            let t = Instant::now();
            let quad = kd.as_ref().map(|kd| {
                let mut kdu = vec![0.0; nf];
                self.solver.asm.corotational_matvec(&du, &mut kdu);
                let slope: f64 = du.iter().zip(kd).map(|(a, b)| a * b).sum();
                let curvature: f64 = du.iter().zip(&kdu).map(|(a, b)| a * b).sum();
                (slope, curvature)
            });
            let (trial, step) = self.halving_step(u, &du, &free, (e_elastic, quad), &targets);
            report.assembly_ms += ms(t);
            if step < 0.1 {
                // No decrease even at a sixteenth of the step: this update changes nothing (and,
                // converging, the next one would find the same correspondences).
                if stop_mm.is_some() {
                    break;
                }
                continue;
            }
            let moved_mm = (trial.iter().zip(u.iter()).map(|(a, b)| (a - b).norm_squared()).sum::<f64>()
                / u.len().max(1) as f64)
                .sqrt();
            u.copy_from_slice(&trial);
            report.updates += 1;
            if stop_mm.is_some_and(|tol| moved_mm <= tol) {
                break;
            }
        }
        // The distance left between each matched point and its sample after the update (the
        // last update's correspondences: a fresh search would cost another bucket fill).
        let t = Instant::now();
        report.rms_mm = matched_rms(|s| self.rest_mm[s] + interpolate_nodes(&self.samples[s], u), points_mm, &nearest);
        report.search_ms += ms(t);
        Ok(report)
    }

    /// Solve each update in a basis of the responses to `patches` x 3 smooth surface loads
    /// (see `Subspace`); 0 goes back to conjugate gradients. Costs one triangular-solve pair
    /// and one stiffness product per basis vector, once.
    pub fn use_subspace(&mut self, patches: usize, free_body: bool) -> Result<(), FemError> {
        if patches == 0 {
            self.set_basis(None);
            return Ok(());
        }
        if patches > 1000 {
            return Err(FemError::InvalidInput(format!("point fit: {patches} subspace patches (at most 1000)")));
        }
        let free = self.solver.asm.dofs.free_of.clone();
        let nf = self.solver.asm.dofs.n_free;
        let par = self.solver.settings.parallelism.par();
        // Patch centres spread over the samples by farthest-point sampling, from the sample
        // nearest their centroid (deterministic).
        let ns = self.samples.len();
        let centroid = self.rest_mm.iter().sum::<Vector3<f64>>() / ns as f64;
        let first = (0..ns)
            .min_by(|&a, &b| (self.rest_mm[a] - centroid).norm().total_cmp(&(self.rest_mm[b] - centroid).norm()))
            .unwrap_or(0);
        let mut centres = vec![first];
        let mut dist: Vec<f64> = self.rest_mm.iter().map(|x| (x - self.rest_mm[first]).norm()).collect();
        while centres.len() < patches.min(ns) {
            let (far, d) =
                dist.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map(|(i, d)| (i, *d)).unwrap_or((0, 0.0));
            if d <= 0.0 {
                break;
            }
            centres.push(far);
            for (dj, x) in dist.iter_mut().zip(&self.rest_mm) {
                *dj = dj.min((x - self.rest_mm[far]).norm());
            }
        }
        // The covering radius: every sample lies within it of a centre.
        let cover = dist.iter().copied().fold(0.0, f64::max).max(self.solver.grid.cell_size_mm);
        let sigma2 = cover * cover;
        let mut columns: Vec<Vec<f64>> = Vec::with_capacity(3 * centres.len());
        // Free-body responses (the rest stiffness alone) for a fit whose state lives in the
        // basis: with the springs on every sample each response stays near its patch, and the
        // fit from rest could not move a lobe as a whole (CT check recording: 5.8 mm against
        // 1.2 with free-body responses).
        let mut free_body = if free_body {
            let mut s = FeSolver::new(
                self.solver.grid,
                self.solver.material,
                &self.solver.constrained_nodes,
                SolverSettings::default(),
            )?;
            s.asm.assemble(ElementModel::Corotational, &vec![Vector3::zeros(); self.solver.grid.node_count()], true);
            s.fact.factorize(&s.asm, false, par)?;
            Some(s)
        } else {
            None
        };
        for &c in &centres {
            for axis in 0..3 {
                let mut rhs = Mat::<f64>::zeros(nf, 1);
                for (e, x) in self.samples.iter().zip(&self.rest_mm) {
                    let w = (-(x - self.rest_mm[c]).norm_squared() / (2.0 * sigma2)).exp();
                    if w < 1e-3 {
                        continue;
                    }
                    for k in 0..8 {
                        let f = free[3 * e.nodes[k] as usize + axis];
                        if f != NONE {
                            rhs[(f as usize, 0)] += w * e.weights[k];
                        }
                    }
                }
                match free_body.as_mut() {
                    Some(s) => s.fact.solve(&mut rhs, par),
                    None => self.solver.fact.solve(&mut rhs, par),
                }
                let mut v: Vec<f64> = (0..nf).map(|i| rhs[(i, 0)]).collect();
                // Modified Gram-Schmidt, twice; a vector the others already span is dropped.
                let before = norm(&v);
                for _ in 0..2 {
                    for q in &columns {
                        let d: f64 = q.iter().zip(&v).map(|(a, b)| a * b).sum();
                        v.iter_mut().zip(q).for_each(|(a, b)| *a -= d * b);
                    }
                }
                let after = norm(&v);
                if after.is_finite() && after > 1e-6 * before {
                    v.iter_mut().for_each(|a| *a /= after);
                    columns.push(v);
                }
            }
        }
        let m = columns.len();
        if m == 0 {
            return Err(FemError::InvalidInput("point fit: the subspace has no vector".into()));
        }
        // The rest stiffness (the co-rotational operator at rest) projected on the basis.
        self.solver.asm.assemble(
            ElementModel::Corotational,
            &vec![Vector3::zeros(); self.solver.grid.node_count()],
            false,
        );
        let mut k_r = Mat::<f64>::zeros(m, m);
        let mut kphit = Mat::<f32>::zeros(m, nf);
        let mut kv = vec![0.0; nf];
        for j in 0..m {
            self.solver.asm.corotational_matvec(&columns[j], &mut kv);
            for i in 0..m {
                k_r[(i, j)] = columns[i].iter().zip(&kv).map(|(a, b)| a * b).sum();
            }
            kv.iter().enumerate().for_each(|(f, v)| kphit[(j, f)] = *v as f32);
        }
        for i in 0..m {
            for j in 0..i {
                let v = 0.5 * (k_r[(i, j)] + k_r[(j, i)]);
                k_r[(i, j)] = v;
                k_r[(j, i)] = v;
            }
        }
        let phit = Mat::from_fn(m, nf, |i, j| columns[i][j] as f32);
        self.set_basis(Some(Subspace { phit, k_r, kphit }));
        Ok(())
    }

    fn set_basis(&mut self, subspace: Option<Subspace>) {
        self.sample_basis = subspace.as_ref().map(|sub| {
            Mat::from_fn(sub.phit.nrows(), self.sample_dofs.len(), |i, k| sub.phit[(i, self.sample_dofs[k].2 as usize)])
        });
        self.subspace = subspace;
    }

    /// The subspace in use, to hand to another fit of the same grid, samples and material.
    pub fn subspace(&self) -> Option<&Subspace> {
        self.subspace.as_ref()
    }

    /// Use a subspace built by `use_subspace` on another fit of the same grid and samples.
    pub fn set_subspace(&mut self, subspace: Subspace) -> Result<(), FemError> {
        if subspace.phit.ncols() != self.solver.asm.dofs.n_free {
            return Err(FemError::InvalidInput(format!(
                "point fit: a subspace of {} dofs for {}",
                subspace.phit.ncols(),
                self.solver.asm.dofs.n_free
            )));
        }
        self.set_basis(Some(subspace));
        Ok(())
    }

    /// The basis vectors in use (0: conjugate gradients).
    pub fn subspace_size(&self) -> usize {
        self.subspace.as_ref().map_or(0, |s| s.k_r.nrows())
    }

    /// G (m x matched, column-major: one sample's column after another, built in parallel):
    /// each matched sample's spring along its normal, in the basis.
    fn sample_jacobian(&self, basis_s: &Mat<f32>, matched: &[usize], normals: &[Vector3<f64>], m: usize) -> Vec<f32> {
        let free = &self.solver.asm.dofs.free_of;
        let sk = self.k_n_per_mm.sqrt();
        let mut g_data = vec![0.0f32; m * matched.len()];
        g_data.par_chunks_mut(m).zip(matched.par_iter().zip(normals)).for_each(|(col, (&s, n))| {
            let e = &self.samples[s];
            for k in 0..8 {
                for c in 0..3 {
                    let f = free[3 * e.nodes[k] as usize + c];
                    let coef = (sk * e.weights[k] * n[c]) as f32;
                    if f != NONE
                        && coef != 0.0
                        && let Some(basis) = basis_s.col(self.sample_slot[f as usize] as usize).try_as_col_major()
                    {
                        for (o, b) in col.iter_mut().zip(basis.as_slice()) {
                            *o += coef * *b;
                        }
                    }
                }
            }
        });
        g_data
    }

    /// Each matched sample's normal, turned by its cell's rotation in `u` (one polar
    /// decomposition per cell: neighbouring samples share cells).
    fn turned_normals(&self, matched: &[usize], u: &[Vector3<f64>], g0: &[Vector3<f64>; 8]) -> Vec<Vector3<f64>> {
        let grid = self.solver.grid;
        let mut cells: Vec<u32> = matched.iter().map(|&s| self.samples[s].cell).collect();
        cells.sort_unstable();
        cells.dedup();
        let rotations: Vec<Matrix3<f64>> = cells
            .par_iter()
            .map(|&c| {
                let ue: [Vector3<f64>; 8] = grid.cells[c as usize].nodes.map(|n| u[n as usize]);
                crate::fem::assembly::rotation_of(&crate::fem::element::deformation_gradient(&ue, g0))
            })
            .collect();
        matched
            .iter()
            .map(|&s| {
                let c = cells.binary_search(&self.samples[s].cell).unwrap_or(0);
                (rotations[c] * self.normals[s]).normalize()
            })
            .collect()
    }

    /// The correction's updates in the subspace, the elastic energy measured from the start
    /// (see `FitWork::from_start`) and linearised there: the increment's stiffness is the
    /// projected rest stiffness (the increment is a fraction of the prediction; the prediction
    /// keeps its rotations), the springs point-to-plane along the sample normals turned by
    /// their cells' rotations. The model is then quadratic in the step, so each update is one
    /// m x m solve, exact for its correspondences, with no assembly of the grid and no line
    /// search: (K_r + G G^T) q = -G rho - K_r q_sum, du = Phi q, where G's column of a matched
    /// sample is sqrt(k) (n^T W Phi)^T and rho its distance to its points along n.
    /// `from_rest`: the elastic energy measured from rest instead (the tracking correction),
    /// linear in the rest stiffness: the right side gains -Phi^T K u_start, and the part of
    /// u_start outside the basis's span stays as it is (no surface load the springs can apply
    /// reaches it).
    fn subspace_updates(
        &mut self,
        sub: &Subspace,
        points_mm: &[Vector3<f64>],
        u: &mut [Vector3<f64>],
        updates: usize,
        freeze: bool,
        from_rest: bool,
    ) -> PointFitReport {
        use faer::linalg::solvers::Solve;
        let Some(basis_s) = self.sample_basis.take() else { return PointFitReport::default() };
        let grid = self.solver.grid;
        let band = self.settings.band_mm;
        let ns = self.samples.len();
        let free = &self.solver.asm.dofs.free_of;
        let nf = self.solver.asm.dofs.n_free;
        let m = sub.k_r.nrows();
        let par = self.solver.settings.parallelism.par();
        let sk = self.k_n_per_mm.sqrt();
        let g0 = crate::fem::element::gradients([0.0; 3], grid.cell_size_mm);
        let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
        let mut report = PointFitReport::default();
        let mut q_sum = Mat::<f64>::zeros(m, 1);
        let mut nearest: Vec<u32> = Vec::new();
        // Between updates only the samples' nodes move (the basis's sample rows); the whole
        // grid takes the sum of the steps once, at the end.
        let mut filled = Vec::new();
        let k_start = if from_rest { Some(start_in_basis(sub, u, (free, nf), par)) } else { None };
        let u_start = u.to_vec();
        for it in 0..updates {
            let t = Instant::now();
            if it == 0 {
                filled = self.deformed(u);
                nearest = nearest_samples(&mut self.buckets, grid, &filled, points_mm, band);
            } else if !freeze {
                let now = self.deformed(u);
                nearest = self.nearest_moved(points_mm, &nearest, &filled, &now);
            }
            let (acc, count) = pulls(ns, points_mm, &nearest);
            let matched: Vec<usize> = (0..ns).filter(|&s| count[s] > 0).collect();
            report.points_matched = nearest.iter().filter(|&&s| s != u32::MAX).count();
            report.samples_matched = matched.len();
            report.search_ms += ms(t);
            if matched.is_empty() {
                break;
            }
            let t = Instant::now();
            let normals = self.turned_normals(&matched, u, &g0);
            report.assembly_ms += ms(t);
            let t = Instant::now();
            // G (m x matched, column-major: one sample's column after another, built in
            // parallel) and the distances along the normals.
            // Single precision, as the basis: G G^T is the update's largest product.
            let g_data = self.sample_jacobian(&basis_s, &matched, &normals, m);
            let g = faer::MatRef::from_column_major_slice(&g_data, m, matched.len());
            let rho = Mat::<f32>::from_fn(matched.len(), 1, |j, _| {
                let s = matched[j];
                let x = self.rest_mm[s] + interpolate_nodes(&self.samples[s], u);
                (sk * normals[j].dot(&(x - acc[s] / count[s] as f64))) as f32
            });
            // The lower triangle only: the Cholesky factorisation reads no more.
            let mut ggt = Mat::<f32>::zeros(m, m);
            {
                use faer::linalg::matmul::triangular::{BlockStructure, matmul};
                let rect = BlockStructure::Rectangular;
                matmul(
                    ggt.as_mut(),
                    BlockStructure::TriangularLower,
                    faer::Accum::Replace,
                    g,
                    rect,
                    g.transpose(),
                    rect,
                    1.0,
                    par,
                );
            }
            let a_r = Mat::<f64>::from_fn(m, m, |i, j| if i >= j { sub.k_r[(i, j)] + ggt[(i, j)] as f64 } else { 0.0 });
            let mut grho = Mat::<f32>::zeros(m, 1);
            faer::linalg::matmul::matmul(grho.as_mut(), faer::Accum::Replace, g, rho.as_ref(), -1.0, par);
            let mut b_r = Mat::<f64>::from_fn(m, 1, |i, _| grho[(i, 0)] as f64);
            faer::linalg::matmul::matmul(b_r.as_mut(), faer::Accum::Add, sub.k_r.as_ref(), q_sum.as_ref(), -1.0, par);
            if let Some(k) = &k_start {
                b_r -= k;
            }
            let Ok(llt) = a_r.llt(faer::Side::Lower) else { break };
            let q = llt.solve(&b_r);
            q_sum += &q;
            report.updates += 1;
            if it + 1 < updates {
                let mut du = Mat::<f32>::zeros(self.sample_dofs.len(), 1);
                let q32 = Mat::<f32>::from_fn(m, 1, |i, _| q[(i, 0)] as f32);
                faer::linalg::matmul::matmul(
                    du.as_mut(),
                    faer::Accum::Replace,
                    basis_s.transpose(),
                    q32.as_ref(),
                    1.0,
                    par,
                );
                for (k, &(n, c, _)) in self.sample_dofs.iter().enumerate() {
                    u[n as usize][c as usize] += du[(k, 0)] as f64;
                }
            }
            report.solve_ms += ms(t);
        }
        let t = Instant::now();
        if report.updates > 0 {
            expand_into(u, &u_start, sub, &q_sum, (free, nf), par);
        }
        report.solve_ms += ms(t);
        report.rms_mm = matched_rms(|s| self.rest_mm[s] + interpolate_nodes(&self.samples[s], u), points_mm, &nearest);
        self.sample_basis = Some(basis_s);
        report
    }

    /// The nearest sample within the band of each point after the samples moved from where the
    /// buckets hold them (`filled`) to `now`, searched from each point's previous nearest
    /// (`PointIndex::nearest_moved`): the same samples as a search of freshly filled buckets.
    fn nearest_moved(
        &self,
        points_mm: &[Vector3<f64>],
        previous: &[u32],
        filled: &[Vector3<f64>],
        now: &[Vector3<f64>],
    ) -> Vec<u32> {
        let band = self.settings.band_mm;
        let moved = filled.iter().zip(now).map(|(a, b)| (a - b).norm_squared()).fold(0.0, f64::max).sqrt();
        points_mm
            .par_iter()
            .zip(previous)
            .map(|(p, &s0)| {
                let reach = match now.get(s0 as usize) {
                    Some(x) if self.buckets.holds(x) => (x - p).norm(),
                    _ => band,
                };
                self.buckets.nearest_moved(p, now, reach, moved, band).map_or(u32::MAX, |s| s as u32)
            })
            .collect()
    }

    /// CG on A = K_corot + k sum over matched samples of W^T M W (M the spring's metric), with K_corot the cells' rest
    /// stiffness turned by their rotations at the last assembly (applied without forming it),
    /// preconditioned by stiffness warping: M^-1 = R_N (K_rest + k sum over all samples of
    /// W^T W)^-1 R_N^T, R_N the nodal rotations, the rest factor computed once.
    fn pcg(
        &mut self,
        b: &[f64],
        metrics: &[Option<Matrix3<f64>>],
        free: &[u32],
        max_iter: usize,
        tol: f64,
    ) -> (Vec<f64>, usize) {
        let n = b.len();
        let bnorm = norm(b);
        let mut x = vec![0.0; n];
        if bnorm == 0.0 {
            return (x, 0);
        }
        let rot = self.solver.asm.nodal_rotations();
        // v <- R_N^T v (transpose) or R_N v, node by node over the free components.
        let turn = |v: &mut [f64], transpose: bool| {
            for (nd, r) in rot.iter().enumerate() {
                let idx: [u32; 3] = std::array::from_fn(|c| free[3 * nd + c]);
                if idx.iter().all(|&f| f == NONE) {
                    continue;
                }
                let w = Vector3::from_fn(|c, _| if idx[c] != NONE { v[idx[c] as usize] } else { 0.0 });
                let w = if transpose { r.transpose() * w } else { r * w };
                for c in 0..3 {
                    if idx[c] != NONE {
                        v[idx[c] as usize] = w[c];
                    }
                }
            }
        };
        let precondition = |fit: &mut Self, r: &[f64]| -> Vec<f64> {
            let mut v = r.to_vec();
            turn(&mut v, true);
            let mut z = Mat::from_fn(n, 1, |i, _| v[i]);
            fit.solver.fact.solve(&mut z, fit.solver.settings.parallelism.par());
            let mut z: Vec<f64> = (0..n).map(|i| z[(i, 0)]).collect();
            turn(&mut z, false);
            z
        };
        // The matched springs gathered once: the loop below runs every iteration, and walking
        // all the samples (most unmatched) for them cost a third of an iteration's time.
        let springs: Vec<([u32; 24], [f64; 8], Matrix3<f64>)> = self
            .samples
            .iter()
            .zip(metrics)
            .filter_map(|(e, m)| {
                let m = (*m)?;
                Some((std::array::from_fn(|i| free[3 * e.nodes[i / 3] as usize + i % 3]), e.weights, m))
            })
            .collect();
        let mut r = b.to_vec();
        let mut z = precondition(self, &r);
        let mut p = z.clone();
        let mut rz: f64 = r.iter().zip(&z).map(|(a, b)| a * b).sum();
        let mut ap = vec![0.0; n];
        for k in 1..=max_iter {
            self.solver.asm.corotational_matvec(&p, &mut ap);
            for (dofs, weights, m) in &springs {
                // The matched spring: ap += k W^T M (W p).
                let mut wp = Vector3::<f64>::zeros();
                for a in 0..8 {
                    for c in 0..3 {
                        let f = dofs[3 * a + c];
                        if f != NONE {
                            wp[c] += weights[a] * p[f as usize];
                        }
                    }
                }
                let wp = m * wp;
                for a in 0..8 {
                    for c in 0..3 {
                        let f = dofs[3 * a + c];
                        if f != NONE {
                            ap[f as usize] += self.k_n_per_mm * weights[a] * wp[c];
                        }
                    }
                }
            }
            let pap: f64 = p.iter().zip(&ap).map(|(a, b)| a * b).sum();
            if !(pap > 0.0) {
                return (x, k);
            }
            let alpha = rz / pap;
            for i in 0..n {
                x[i] += alpha * p[i];
                r[i] -= alpha * ap[i];
            }
            if norm(&r) <= tol * bnorm {
                return (x, k);
            }
            z = precondition(self, &r);
            let rz_new: f64 = r.iter().zip(&z).map(|(a, b)| a * b).sum();
            let beta = rz_new / rz;
            rz = rz_new;
            for i in 0..n {
                p[i] = z[i] + beta * p[i];
            }
        }
        (x, max_iter)
    }
}

/// One registration frame of the fit measured against the converged solve.
#[derive(Clone, Debug, serde::Serialize)]
pub struct FrameCheck {
    /// The registration's frame (`PointFit::fit`, correspondences searched at every update),
    /// warm-started from the previous frame's fit.
    pub frame_ms: f64,
    pub frame: PointFitReport,
    /// Node displacement difference (mm) between the fixed work and the converged solve on
    /// the same held correspondences: what stopping early costs.
    pub error_rms_mm: f64,
    pub error_max_mm: f64,
    /// How far the converged solve moved the nodes from the previous frame's (mm, RMS): the
    /// error a frame that did nothing would have.
    pub motion_rms_mm: f64,
    pub converged_updates: usize,
}

/// Fit `previous_mm` from rest (the previous frame, settled by 4 fixed-work frames), then
/// from there: the registration frame on `points_mm`, timed; and the held-correspondence
/// problem solved with the fixed work and to convergence.
pub fn check_frame(
    fit: &mut PointFit<'_>,
    previous_mm: &[Vector3<f64>],
    points_mm: &[Vector3<f64>],
) -> Result<FrameCheck, FemError> {
    let n = fit.solver.grid.node_count();
    let mut u_prev = vec![Vector3::zeros(); n];
    for _ in 0..4 {
        fit.fit(previous_mm, &mut u_prev)?;
    }
    let mut u_frame = u_prev.clone();
    let t = Instant::now();
    let frame = fit.fit(points_mm, &mut u_frame)?;
    let frame_ms = t.elapsed().as_secs_f64() * 1e3;
    let mut u_fast = u_prev.clone();
    fit.fit_held(points_mm, &mut u_fast, FitWork::fixed(&fit.settings))?;
    let mut u_conv = u_prev.clone();
    let conv = fit.fit_held(points_mm, &mut u_conv, FitWork::converged(1e-3, 50))?;
    let rms = |a: &[Vector3<f64>], b: &[Vector3<f64>]| {
        (a.iter().zip(b).map(|(x, y)| (x - y).norm_squared()).sum::<f64>() / n as f64).sqrt()
    };
    Ok(FrameCheck {
        frame_ms,
        frame,
        error_rms_mm: rms(&u_fast, &u_conv),
        error_max_mm: u_fast.iter().zip(&u_conv).map(|(x, y)| (x - y).norm()).fold(0.0, f64::max),
        motion_rms_mm: rms(&u_prev, &u_conv),
        converged_updates: conv.updates,
    })
}

/// The free dofs' entries of minus the nodal vector `g` (the right-hand side of a step).
fn minus_on_free(g: &[Vector3<f64>], free: &[u32], nf: usize) -> Vec<f64> {
    let mut b = vec![0.0; nf];
    for (n, gn) in g.iter().enumerate() {
        for c in 0..3 {
            let f = free[3 * n + c];
            if f != NONE {
                b[f as usize] = -gn[c];
            }
        }
    }
    b
}

/// From rest: Phi^T K u_start (m x 1), the starting elastic force in the basis, with `u`
/// replaced by its energy projection onto the basis (K_r q0 = Phi^T K u_start).
fn start_in_basis(sub: &Subspace, u: &mut [Vector3<f64>], (free, nf): (&[u32], usize), par: faer::Par) -> Mat<f64> {
    let m = sub.k_r.nrows();
    // Phi^T K u_start (m x 1), the starting elastic force in the basis.
    let k_start = {
        let mut v = Mat::<f32>::zeros(nf, 1);
        for (nd, un) in u.iter().enumerate() {
            for c in 0..3 {
                let f = free[3 * nd + c];
                if f != NONE {
                    v[(f as usize, 0)] = un[c] as f32;
                }
            }
        }
        let mut k = Mat::<f32>::zeros(m, 1);
        faer::linalg::matmul::matmul(k.as_mut(), faer::Accum::Replace, sub.kphit.as_ref(), v.as_ref(), 1.0, par);
        Mat::<f64>::from_fn(m, 1, |i, _| k[(i, 0)] as f64)
    };
    // From rest the state lies in the basis: the start is replaced by its energy projection
    // (K_r q0 = Phi^T K u_start). What the basis cannot hold of a prediction is not
    // supported by any load on the seen surface, and kept it pulled the fit away from the
    // points (CT patient's check recording: last frame 1.96 mm kept, 1.17 projected).
    if let Ok(llt) = sub.k_r.llt(faer::Side::Lower) {
        use faer::linalg::solvers::Solve;
        let q0 = llt.solve(&k_start);
        let q32 = Mat::<f32>::from_fn(m, 1, |i, _| q0[(i, 0)] as f32);
        let mut v = Mat::<f32>::zeros(nf, 1);
        faer::linalg::matmul::matmul(v.as_mut(), faer::Accum::Replace, sub.phit.transpose(), q32.as_ref(), 1.0, par);
        for (nd, un) in u.iter_mut().enumerate() {
            for c in 0..3 {
                let f = free[3 * nd + c];
                if f != NONE {
                    un[c] = v[(f as usize, 0)] as f64;
                }
            }
        }
    }
    k_start
}

/// The whole grid's displacement: the start plus the basis's sum of the steps, `q_sum`.
fn expand_into(
    u: &mut [Vector3<f64>],
    u_start: &[Vector3<f64>],
    sub: &Subspace,
    q_sum: &Mat<f64>,
    (free, nf): (&[u32], usize),
    par: faer::Par,
) {
    let m = sub.k_r.nrows();
    let mut du = Mat::<f32>::zeros(nf, 1);
    let q32 = Mat::<f32>::from_fn(m, 1, |i, _| q_sum[(i, 0)] as f32);
    faer::linalg::matmul::matmul(du.as_mut(), faer::Accum::Replace, sub.phit.transpose(), q32.as_ref(), 1.0, par);
    for (nd, (un, u0)) in u.iter_mut().zip(u_start).enumerate() {
        for c in 0..3 {
            let f = free[3 * nd + c];
            if f != NONE {
                un[c] = u0[c] + du[(f as usize, 0)] as f64;
            }
        }
    }
}

/// For each observed point, the index of the sample nearest it within `band` (u32::MAX: none),
/// searched among the deformed samples `pos`.
fn nearest_samples(
    buckets: &mut PointIndex,
    grid: &ImmersedGrid,
    pos: &[Vector3<f64>],
    points_mm: &[Vector3<f64>],
    band: f64,
) -> Vec<u32> {
    buckets.fill(pos, grid.origin_mm, band, grid.padded_shape(), grid.cell_size_mm);
    let buckets = &*buckets;
    points_mm.par_iter().map(|p| buckets.nearest(p, band).map_or(u32::MAX, |(s, _)| s as u32)).collect()
}

/// Per sample: the sum of the points that chose it and how many did.
fn pulls(ns: usize, points_mm: &[Vector3<f64>], nearest: &[u32]) -> (Vec<Vector3<f64>>, Vec<u32>) {
    let mut acc = vec![Vector3::zeros(); ns];
    let mut count = vec![0u32; ns];
    for (p, &s) in points_mm.iter().zip(nearest) {
        if s != u32::MAX {
            acc[s as usize] += p;
            count[s as usize] += 1;
        }
    }
    (acc, count)
}

/// RMS distance of the matched points to their samples (mm).
fn matched_rms(position: impl Fn(usize) -> Vector3<f64>, points_mm: &[Vector3<f64>], nearest: &[u32]) -> f64 {
    let (mut sq, mut n) = (0.0, 0usize);
    for (p, &s) in points_mm.iter().zip(nearest) {
        if s != u32::MAX {
            sq += (position(s as usize) - p).norm_squared();
            n += 1;
        }
    }
    if n > 0 { (sq / n as f64).sqrt() } else { 0.0 }
}
