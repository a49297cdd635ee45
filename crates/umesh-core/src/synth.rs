//! Synthetic RGB-D recordings with ground truth: the organ pressed by random probes with a
//! load that ramps up over the sequence (SVK solves), seen by a virtual depth camera with
//! noise and holes, plus the true positions of virtual markers.

use crate::dataset::{DatasetConfig, DatasetContext};
use crate::fem::solver::{FeSolver, SolveMethod, SolverSettings};
use crate::fem::{BoundaryConditions, MaterialParams};
use crate::loads::{LoadFamily, deform_mesh};
use crate::progress::{Cancel, Progress};
use crate::register::overlay::rasterize;
use crate::register::pipeline::GroundTruth;
use crate::register::{RegistrationContext, virtual_markers};
use crate::rgbd::recording::{RecordingMeta, write_frame, write_trajectory_log};
use crate::rgbd::{ColorImage, DepthImage, Frame, Intrinsics, RgbdError, rigid_inverse};
use crate::rng::SplitMix64;
use crate::segmentation::Segmentation;
use crate::visible::Camera;
use nalgebra::{Matrix4, Vector3};
use std::path::{Path, PathBuf};

/// The share of its target a recording's load must reach (a dataset keeps less).
const RECORDING_MIN_REACHED: f64 = 0.5;

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SynthSettings {
    pub frames: usize,
    pub fps: f64,
    pub width: usize,
    pub height: usize,
    pub focal_px: f64,
    /// Standard deviation of the depth noise (mm).
    pub noise_mm: f64,
    /// Holes (no depth) per frame, discs of `hole_radius_px`.
    pub holes: usize,
    pub hole_radius_px: f64,
    /// Markers inside the organ (as many again on the internal structures).
    pub markers: usize,
    pub seed: u64,
    /// Scale of the final load relative to the dataset's random forces.
    pub load_scale: f64,
    /// The camera moves by this much over the sequence (mm, sideways to its view).
    #[serde(default)]
    pub camera_motion_mm: f64,
    /// and turns by this much (degrees, about a random axis through its position).
    #[serde(default)]
    pub camera_motion_deg: f64,
    /// Instrument shafts occluding the organ, sweeping across it over the sequence.
    #[serde(default)]
    pub instruments: usize,
    /// The truth's material, when it differs from the dataset's (a test off the training
    /// distribution); the loads are still the dataset's.
    #[serde(default)]
    pub material: Option<MaterialParams>,
    /// The load family of the truth (`pressing`: one of the dataset's own patterns; the others
    /// drawn from the seed). Calibrated as samples are: the last frame's mean nodal displacement
    /// is the dataset's target times `load_scale` (times the family's `target_factor`).
    #[serde(default = "pressing")]
    pub loads: LoadFamily,
    /// The share of the final load already on at the first frame (0: the sequence starts at
    /// rest; 0.5: half deformed, a recording begun after the instrument touched the organ).
    #[serde(default)]
    pub first_load: f64,
    /// Write each frame as a cloud of this many organ points (`points/*.ply`, camera frame,
    /// with the colour image) instead of a depth image; 0: depth images.
    #[serde(default)]
    pub cloud_points: usize,
    /// The truth's attachment moved by this vector (world mm) from the one the dataset (and so
    /// the model) assumes: a test off the training distribution. Applied on the grid's lattice
    /// (each component rounded to whole cells; the report gives the shift applied).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub attachment_shift_mm: Option<[f64; 3]>,
}

fn pressing() -> LoadFamily {
    LoadFamily::Pressing
}

impl Default for SynthSettings {
    fn default() -> Self {
        Self {
            frames: 20,
            fps: 20.0,
            width: 640,
            height: 480,
            focal_px: 525.0,
            noise_mm: 1.0,
            holes: 6,
            hole_radius_px: 10.0,
            markers: 10,
            seed: 7,
            // Markers inside the organ move less than its mean node (fixed region, structures
            // deep inside): 1.3 brings the default recordings to the dataset's 10 mm scale.
            load_scale: 1.3,
            camera_motion_mm: 0.0,
            camera_motion_deg: 0.0,
            instruments: 0,
            material: None,
            loads: LoadFamily::Pressing,
            first_load: 0.0,
            cloud_points: 0,
            attachment_shift_mm: None,
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SynthReport {
    pub out: PathBuf,
    pub frames: usize,
    pub markers: usize,
    pub max_marker_displacement_mm: f64,
    pub mean_marker_displacement_mm: f64,
    pub solve_ms_total: f64,
    /// The load scale the recording was made at (`SynthSettings::load_scale`).
    #[serde(default)]
    pub load_scale: f64,
    /// The truth's attachment shift as applied on the lattice (mm), and how many nodes it holds
    /// against the dataset's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub attachment_shift_mm: Option<[f64; 3]>,
    /// The share of the final load the truth reached: below 1 when the material could not
    /// take the whole load (the frames from the first that failed hold the largest load that
    /// converged; the markers are that state's).
    #[serde(default = "one")]
    pub load_reached: f64,
    /// The load scale asked for; `load_scale` is the one made (0.7 or 0.5 of it when the
    /// organ could not take the whole load).
    #[serde(default)]
    pub load_scale_asked: f64,
    #[serde(default)]
    pub fixed_nodes: usize,
    #[serde(default)]
    pub dataset_fixed_nodes: usize,
}

fn one() -> f64 {
    1.0
}

/// Bisections of a frame's load when the truth does not converge at it (1/16 of the step),
/// each a solve of at most `BISECTION_ITERATIONS` Newton iterations.
const LOAD_BISECTIONS: usize = 4;
const BISECTION_ITERATIONS: usize = 60;
/// Newton iterations a truth frame may take (a recording's frames take 10-30).
const TRUTH_ITERATIONS: usize = 200;

/// The fixed nodes `fixed` moved by `shift_mm`, rounded to whole cells of the grid's lattice:
/// node n is fixed when the node one rounded shift behind it was. Returns the flags and the
/// shift applied.
pub fn shifted_fixed(grid: &crate::grid::ImmersedGrid, fixed: &[bool], shift_mm: [f64; 3]) -> (Vec<bool>, [f64; 3]) {
    let h = grid.cell_size_mm;
    let cells: [i64; 3] = std::array::from_fn(|a| (shift_mm[a] / h).round() as i64);
    let index: std::collections::HashMap<[i64; 3], usize> =
        grid.node_ijk.iter().enumerate().map(|(n, ijk)| ([ijk[0] as i64, ijk[1] as i64, ijk[2] as i64], n)).collect();
    let moved = (0..grid.node_count())
        .map(|n| {
            let ijk = grid.node_ijk[n];
            let from = [ijk[0] as i64 - cells[0], ijk[1] as i64 - cells[1], ijk[2] as i64 - cells[2]];
            index.get(&from).is_some_and(|&m| fixed[m])
        })
        .collect();
    (moved, std::array::from_fn(|a| cells[a] as f64 * h))
}

/// world_from_camera (OpenCV axes: x right, y down, z forward) of a look-at camera.
pub fn camera_pose(c: &Camera) -> Matrix4<f64> {
    let f = Vector3::from(c.direction).normalize();
    let up0 = if f.z.abs() < 0.9 { Vector3::z() } else { Vector3::y() };
    let r = f.cross(&up0).normalize();
    let u = r.cross(&f);
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 1>(0, 0).copy_from(&r);
    m.fixed_view_mut::<3, 1>(0, 1).copy_from(&(-u));
    m.fixed_view_mut::<3, 1>(0, 2).copy_from(&f);
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&Vector3::from(c.position_mm));
    m
}

fn gaussian(rng: &mut SplitMix64) -> f64 {
    let u1 = rng.next_f64().max(1e-12);
    let u2 = rng.next_f64();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// An instrument shaft in the image: from where it enters the view to its tip, `clearance_mm`
/// in front of the organ's nearest point at the tip.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shaft {
    pub entry_px: [f64; 2],
    pub tip_px: [f64; 2],
    pub radius_px: f64,
    pub clearance_mm: f64,
}

/// Random instrument sweeps: each shaft's start and end of the sequence.
fn instrument_sweeps(n: usize, k: &Intrinsics, rng: &mut SplitMix64) -> Vec<(Shaft, Shaft)> {
    let (w, h) = (k.width as f64, k.height as f64);
    (0..n)
        .map(|_| {
            // Enter from the left or right border; the tip sweeps across the middle of the view.
            let left = rng.next_f64() < 0.5;
            let entry = [if left { -20.0 } else { w + 20.0 }, h * (0.2 + 0.6 * rng.next_f64())];
            let tip = |rng: &mut SplitMix64| [w * (0.3 + 0.4 * rng.next_f64()), h * (0.3 + 0.4 * rng.next_f64())];
            let radius_px = w * (0.025 + 0.02 * rng.next_f64());
            let clearance_mm = 10.0 + 20.0 * rng.next_f64();
            let a = Shaft { entry_px: entry, tip_px: tip(rng), radius_px, clearance_mm };
            let b = Shaft { tip_px: tip(rng), ..a };
            (a, b)
        })
        .collect()
}

/// The camera pose at sequence position `t` in [0, 1]: moved sideways by `t` times the
/// offset and turned by `t` times the angle about `axis` (camera frame).
fn moved_pose(
    pose: &Matrix4<f64>,
    offset_cam_mm: &Vector3<f64>,
    axis_cam: &Vector3<f64>,
    angle_rad: f64,
    t: f64,
) -> Matrix4<f64> {
    let r = nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(*axis_cam), angle_rad * t);
    let mut local = Matrix4::identity();
    local.fixed_view_mut::<3, 3>(0, 0).copy_from(r.matrix());
    local.fixed_view_mut::<3, 1>(0, 3).copy_from(&(offset_cam_mm * t));
    pose * local
}

/// Render depth (mm), colour and the organ mask of `mesh` from `world_from_camera`.
pub fn render_frame(
    mesh: &crate::mesh::TriMesh,
    world_from_camera: &Matrix4<f64>,
    k: &Intrinsics,
    s: &SynthSettings,
    instruments: &[Shaft],
    rng: &mut SplitMix64,
) -> (DepthImage, ColorImage, Vec<bool>) {
    let n = k.width * k.height;
    let cam = rigid_inverse(world_from_camera);
    let mut z = vec![f32::INFINITY; n];
    let mut shade = vec![0f32; n];
    rasterize(mesh, &cam, k, &mut z, |i, _, nrm| shade[i] = nrm.z.abs() as f32);
    let far = z.iter().copied().filter(|d| d.is_finite()).fold(0.0f32, f32::max) + 40.0;
    let near = z.iter().copied().filter(|d| d.is_finite()).fold(f32::INFINITY, f32::min);
    // Instrument shafts between the camera and the organ: not organ pixels.
    let mut tool = vec![false; n];
    for sh in instruments {
        let (dx, dy) = (sh.tip_px[0] - sh.entry_px[0], sh.tip_px[1] - sh.entry_px[1]);
        let len2 = (dx * dx + dy * dy).max(1e-9);
        for v in 0..k.height {
            for u in 0..k.width {
                let t = (((u as f64 - sh.entry_px[0]) * dx + (v as f64 - sh.entry_px[1]) * dy) / len2).clamp(0.0, 1.0);
                let (px, py) = (sh.entry_px[0] + t * dx, sh.entry_px[1] + t * dy);
                if (u as f64 - px).powi(2) + (v as f64 - py).powi(2) <= sh.radius_px * sh.radius_px {
                    let i = v * k.width + u;
                    tool[i] = true;
                    // The shaft rises toward the camera from its tip.
                    z[i] = (near as f64 - sh.clearance_mm - (1.0 - t) * 40.0).max(10.0) as f32;
                    shade[i] = (1.0 - ((u as f64 - px).powi(2) + (v as f64 - py).powi(2)).sqrt() / sh.radius_px) as f32;
                }
            }
        }
    }
    let mask: Vec<bool> = z.iter().zip(&tool).map(|(d, &t)| d.is_finite() && !t).collect();
    let mut depth = vec![0f32; n];
    let mut color = ColorImage::new(k.width, k.height, [0, 0, 0]);
    for i in 0..n {
        let tex = (rng.next_f64() * 12.0) as f32;
        let (d, rgb) = if tool[i] {
            let l = 0.4 + 0.6 * shade[i];
            (z[i], [(150.0 * l + tex) as u8, (155.0 * l + tex) as u8, (165.0 * l + tex) as u8])
        } else if mask[i] {
            let l = 0.3 + 0.7 * shade[i];
            (z[i], [(150.0 * l + tex) as u8, (60.0 * l + tex * 0.5) as u8, (50.0 * l + tex * 0.5) as u8])
        } else {
            // A green drape behind the organ.
            (far, [(35.0 + tex) as u8, (85.0 + tex) as u8, (70.0 + tex) as u8])
        };
        depth[i] = (d as f64 + s.noise_mm * gaussian(rng)).max(0.0) as f32;
        color.rgb[3 * i..3 * i + 3].copy_from_slice(&rgb);
    }
    for _ in 0..s.holes {
        let (cu, cv) = (rng.next_f64() * k.width as f64, rng.next_f64() * k.height as f64);
        let r = s.hole_radius_px * (0.5 + rng.next_f64());
        let (u0, u1) = ((cu - r).max(0.0) as usize, ((cu + r) as usize).min(k.width - 1));
        let (v0, v1) = ((cv - r).max(0.0) as usize, ((cv + r) as usize).min(k.height - 1));
        for v in v0..=v1 {
            for u in u0..=u1 {
                if (u as f64 - cu).powi(2) + (v as f64 - cv).powi(2) <= r * r {
                    depth[v * k.width + u] = 0.0;
                }
            }
        }
    }
    (DepthImage { width: k.width, height: k.height, depth_mm: depth }, color, mask)
}

/// The most markers a recording carries (`--markers`).
pub const MAX_MARKERS: usize = 100_000;

/// Write a synthetic recording of `seg` to `out`.
pub fn run_rgbd_synth(
    seg: &Segmentation,
    config: &DatasetConfig,
    settings: &SynthSettings,
    out: &Path,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<SynthReport, RgbdError> {
    let bad = |r: String| crate::rgbd::invalid(out, r);
    let config = &recording_config(config, settings);
    let k = checked_intrinsics(config, settings, out)?;
    progress.report(0, settings.frames as u64, "preparing the grid");
    let mut ctx = DatasetContext::prepare(seg, config, cancel).map_err(|e| bad(e.to_string()))?;
    // The organ held elsewhere than the model assumes: the load is calibrated and the truth
    // solved with the moved attachment.
    let dataset_fixed_nodes = ctx.fixed.iter().filter(|&&f| f).count();
    let shift_applied = match settings.attachment_shift_mm {
        Some(shift) => {
            let (f, applied) = shifted_fixed(&ctx.grid, &ctx.fixed, shift);
            let held = f.iter().filter(|&&x| x).count();
            // Fewer than a tenth of the nodes the dataset holds: the attachment left the organ.
            if held * 10 < dataset_fixed_nodes {
                return Err(bad(format!(
                    "attachment shift {shift:?} mm: the shifted attachment holds {held} of the organ's nodes (the dataset's holds {dataset_fixed_nodes}); a smaller shift"
                )));
            }
            ctx.fixed = f;
            Some(applied)
        }
        None => None,
    };
    let (forces, load_scale) = recording_load(&ctx, config, settings, out, cancel)?;
    let pose = camera_pose(&ctx.visible.camera);
    let mut full = BoundaryConditions::new(ctx.grid.node_count());
    full.fixed = ctx.fixed.clone();
    ctx.apply_load(&mut full, config, &forces, settings.loads).map_err(|e| bad(e.into()))?;
    let rest_surface = ctx.surface.clone();
    let fixed = ctx.fixed.clone();
    let reg = RegistrationContext::new(ctx, seg).map_err(|e| bad(e.into()))?;
    let markers = virtual_markers(&reg, settings.markers, settings.seed ^ 0xA11CE);
    let grid = &reg.grid;
    let material = settings.material.unwrap_or(config.material);
    let mut truth_solve = TruthRamp::new(grid, material, &fixed, config, full).map_err(|e| bad(e.to_string()))?;
    let fixed_count = fixed.iter().filter(|&&f| f).count();
    let mut rng = SplitMix64(settings.seed);
    let CameraPath { poses, sweeps } = camera_path(settings, &pose, &k);
    let mut truth = GroundTruth {
        world_from_camera: row_major(&pose),
        world_from_camera_frames: if settings.camera_motion_mm > 0.0 || settings.camera_motion_deg > 0.0 {
            poses.iter().map(row_major).collect()
        } else {
            Vec::new()
        },
        markers_rest_mm: markers.iter().map(|m| [m.x, m.y, m.z]).collect(),
        markers_mm: Vec::new(),
        grid_hash: Some(reg.grid_hash.clone()),
    };
    let mut disp = Vec::new();
    for f in 0..settings.frames {
        cancel.check()?;
        progress.report(f as u64, settings.frames as u64, &format!("frame {f}: solving"));
        let t = if settings.frames > 1 { f as f64 / (settings.frames - 1) as f64 } else { 1.0 };
        let ramp = (settings.first_load + (1.0 - settings.first_load) * t).min(truth_solve.load_cap);
        let u = truth_solve.displacement(ramp, cancel).map_err(|e| bad(format!("frame {f}: {e}")))?;
        let surface = deform_mesh(grid, &rest_surface, &u);
        let shafts: Vec<Shaft> = sweeps
            .iter()
            .map(|(a, b)| Shaft {
                tip_px: [
                    a.tip_px[0] + (b.tip_px[0] - a.tip_px[0]) * ramp,
                    a.tip_px[1] + (b.tip_px[1] - a.tip_px[1]) * ramp,
                ],
                ..*a
            })
            .collect();
        let (depth, color, mask) = render_frame(&surface, &poses[f], &k, settings, &shafts, &mut rng);
        truth.markers_mm.push(marker_positions(grid, &markers, &u, &mut disp));
        let frame = Frame {
            index: f,
            timestamp_s: f as f64 / settings.fps,
            intrinsics: k,
            depth,
            color: Some(color),
            mask: Some(mask),
            world_from_camera: Some(poses[f]),
            points: None,
            device_frame: None,
            host_time_s: None,
        };
        if settings.cloud_points > 0 {
            write_cloud_frame(out, &format!("{f:05}"), &frame, settings.cloud_points, &mut rng)?;
        } else {
            write_frame(out, &format!("{f:05}"), &frame, 1000.0)?;
        }
    }
    write_recording_files(out, &k, settings, &poses, &truth)?;
    progress.report(settings.frames as u64, settings.frames as u64, "done");
    let last = &disp[disp.len() - markers.len()..];
    Ok(SynthReport {
        out: out.to_path_buf(),
        frames: settings.frames,
        markers: markers.len(),
        max_marker_displacement_mm: disp.iter().copied().fold(0.0, f64::max),
        mean_marker_displacement_mm: last.iter().sum::<f64>() / last.len().max(1) as f64,
        solve_ms_total: truth_solve.solve_ms,
        load_scale,
        attachment_shift_mm: shift_applied,
        load_reached: truth_solve.load_cap,
        load_scale_asked: settings.load_scale,
        fixed_nodes: fixed_count,
        dataset_fixed_nodes,
    })
}

/// The dataset's configuration as a recording uses it.
fn recording_config(config: &DatasetConfig, settings: &SynthSettings) -> DatasetConfig {
    // A pressing recording is one of the dataset's pressing patterns, whatever families the
    // dataset mixes (its sample index would otherwise draw any of them).
    // A recording presses as hard as it is asked: the strain limit shapes training data only
    // (a check recording at 50x the target would otherwise be lowered and still say 50x).
    // And at the target it is asked for: without this, a pressing recording took its sample's
    // random factor within the dataset's spread (seed 0's drew about 1.5: 1.3 x the target
    // moved the phantom's markers 24 mm; another dataset's seed drew 0.47).
    let mut own = config.clone();
    own.forces.max_strain = 0.0;
    own.forces.target_spread = 0.0;
    if settings.loads == LoadFamily::Pressing {
        own.forces.families = vec![LoadFamily::Pressing];
    }
    own
}

/// The settings checked, each refusal naming the figure and its range; the camera's intrinsics.
fn checked_intrinsics(config: &DatasetConfig, settings: &SynthSettings, out: &Path) -> Result<Intrinsics, RgbdError> {
    let bad = |r: String| crate::rgbd::invalid(out, r);
    if settings.frames == 0 || settings.frames > 100_000 {
        return Err(bad(format!("{} frames: between 1 and 100000", settings.frames)));
    }
    let k = Intrinsics {
        width: settings.width,
        height: settings.height,
        fx: settings.focal_px,
        fy: settings.focal_px,
        cx: (settings.width as f64 - 1.0) / 2.0,
        cy: (settings.height as f64 - 1.0) / 2.0,
    };
    k.validate().map_err(|e| bad(e.into()))?;
    let finite_in = |v: f64, lo: f64, hi: f64| v.is_finite() && v >= lo && v <= hi;
    // A NaN noise made all-zero depth frames that looked like a recording.
    if !finite_in(settings.noise_mm, 0.0, 100.0) {
        return Err(bad(format!("depth noise {} mm: between 0 and 100 mm", settings.noise_mm)));
    }
    if !finite_in(settings.fps, 1e-3, 1e4) {
        return Err(bad(format!("{} frames per second: between 0.001 and 10000", settings.fps)));
    }
    if !finite_in(settings.hole_radius_px, 0.0, 1e4) || settings.holes > 10_000 {
        return Err(bad(format!(
            "{} holes of {} px: at most 10000 holes of 0-10000 px",
            settings.holes, settings.hole_radius_px
        )));
    }
    if !(finite_in(settings.load_scale, 0.0, 100.0) && settings.load_scale > 0.0) {
        return Err(bad(format!("load scale {}: above 0 and at most 100", settings.load_scale)));
    }
    if !finite_in(settings.camera_motion_mm, 0.0, 500.0) || !finite_in(settings.camera_motion_deg, 0.0, 90.0) {
        return Err(bad(format!(
            "camera motion {} mm, {} degrees: between 0 and 500 mm, 0 and 90 degrees",
            settings.camera_motion_mm, settings.camera_motion_deg
        )));
    }
    if settings.loads != LoadFamily::Pressing && config.forces.calibration == crate::loads::LoadCalibration::EnergyScale
    {
        // Checked before the grid is built: only pressing has an uncalibrated scale.
        return Err(bad(format!(
            "--loads {}: needs a dataset with mean-displacement calibration",
            settings.loads.name()
        )));
    }
    if !finite_in(settings.first_load, 0.0, 1.0) {
        return Err(bad(format!(
            "first-frame load {}: between 0 and 1 (a share of the final load)",
            settings.first_load
        )));
    }
    // Markers measure the TRE: none gives a recording whose every figure is empty; each is
    // written to the ground truth of every frame.
    if !(1..=MAX_MARKERS).contains(&settings.markers) {
        return Err(bad(format!("{} markers: between 1 and {MAX_MARKERS}", settings.markers)));
    }
    if settings.cloud_points > crate::rgbd::MAX_POINTS {
        return Err(bad(format!("{} cloud points: at most {}", settings.cloud_points, crate::rgbd::MAX_POINTS)));
    }
    if settings.instruments > 10 {
        return Err(bad(format!("{} instruments: at most 10", settings.instruments)));
    }
    if let Some(m) = &settings.material {
        m.validate().map_err(|e| bad(format!("truth material: {e}")))?;
    }
    Ok(k)
}

/// The recording's last-frame forces, calibrated as the dataset's samples are (its mean nodal
/// displacement is the dataset's target times the load scale), and the scale used: a load the
/// organ cannot take (SVK collapsing under it) is made smaller rather than refused, a test
/// recording at the largest of these scales that converges, reported.
fn recording_load(
    ctx: &DatasetContext,
    config: &DatasetConfig,
    settings: &SynthSettings,
    out: &Path,
    cancel: &Cancel,
) -> Result<(Vec<crate::loads::PointForce>, f64), RgbdError> {
    let mut load_scale = settings.load_scale;
    let mut forces = solve_recording_load(ctx, config, settings, load_scale, out, cancel);
    for factor in [0.7, 0.5] {
        if forces.is_ok() || cancel.is_cancelled() {
            break;
        }
        load_scale = settings.load_scale * factor;
        forces = solve_recording_load(ctx, config, settings, load_scale, out, cancel);
    }
    Ok((forces?, load_scale))
}

/// The forces at one load scale, solved once to check that they converge and press as asked.
fn solve_recording_load(
    ctx: &DatasetContext,
    config: &DatasetConfig,
    settings: &SynthSettings,
    load_scale: f64,
    out: &Path,
    cancel: &Cancel,
) -> Result<Vec<crate::loads::PointForce>, RgbdError> {
    let bad = |r: String| crate::rgbd::invalid(out, r);
    // A recording presses as asked or says it could not: a state the dataset would keep below
    // an unreachable target (down to a tenth of it) is refused under half of it, as it was
    // before, and the load is made smaller by the caller.
    let reached = |sol: &crate::fem::solver::Solution, target_mm: f64| -> Result<(), RgbdError> {
        let m = config.forces.mean_over.mean_mm(&sol.displacement_mm, &ctx.fixed);
        if m < RECORDING_MIN_REACHED * target_mm {
            return Err(bad(format!("the recording's load reached {m:.2} mm of the {target_mm:.2} mm asked")));
        }
        Ok(())
    };
    let budget = SolverSettings { max_total_iterations: Some(120), max_halvings: 8, ..config.solver.clone() };
    if settings.loads != LoadFamily::Pressing {
        // Another family: its own draw from the seed, calibrated and solved as a sample's.
        let mut rng = SplitMix64(settings.seed ^ 0x10AD_FA11);
        let pts = crate::visible::sample_points(
            &ctx.surface,
            &ctx.pressable,
            crate::loads::family_points(settings.loads, &config.forces),
            &mut rng,
        );
        let mut f =
            crate::loads::family_forces(settings.loads, &pts, &ctx.grid, &config.material, &config.forces, &mut rng);
        let mut s0 = FeSolver::new(&ctx.grid, config.material, &ctx.fixed, budget).map_err(|e| bad(e.to_string()))?;
        let target = config.forces.target_displacement_mm * load_scale * settings.loads.target_factor();
        ctx.calibrate_forces(&mut s0, config, &mut f, target, settings.loads)
            .map_err(|e| bad(format!("the recording's load: {e}")))?;
        let r = ctx.solve_calibrated(&mut s0, config, f, target, settings.loads, 0.5, cancel);
        let sol = r.solution.map_err(|e| bad(format!("the recording's {} load: {}", settings.loads.name(), e.1)))?;
        reached(&sol, r.target_mm)?;
        return Ok(r.forces);
    }
    // The dataset's load model for a sample index no dataset draws.
    let index = 10_000_000 + settings.seed as usize;
    if config.forces.calibration == crate::loads::LoadCalibration::EnergyScale {
        let mut f = ctx.sample_forces(config, index).0;
        let _ = crate::loads::scale_forces(&mut f, 1.0, load_scale);
        return Ok(f);
    }
    let mut s0 = FeSolver::new(&ctx.grid, config.material, &ctx.fixed, budget).map_err(|e| bad(e.to_string()))?;
    let r = ctx.solve_sample(&mut s0, config, index, load_scale, 0.5, cancel);
    let sol = r.solution.map_err(|e| bad(format!("the recording's load: {}", e.1)))?;
    reached(&sol, r.target_mm)?;
    Ok(r.forces)
}

/// The truth's solves along the load ramp, frame after frame.
struct TruthRamp<'g> {
    solver: FeSolver<'g>,
    /// The last frame's full load.
    full: BoundaryConditions,
    /// The share of the final load the truth reached (below 1 when it could not converge).
    load_cap: f64,
    last_ramp: f64,
    /// The state at `load_cap`, once capped.
    held: Option<Vec<Vector3<f64>>>,
    solve_ms: f64,
}

impl<'g> TruthRamp<'g> {
    fn new(
        grid: &'g crate::grid::ImmersedGrid,
        material: MaterialParams,
        fixed: &[bool],
        config: &DatasetConfig,
        full: BoundaryConditions,
    ) -> Result<Self, crate::fem::FemError> {
        // The truth is solved with a larger budget than the dataset's (a frame must not be
        // dropped), but a bounded one: a truth collapsing under its load (a softer material than
        // the loads were calibrated on) ran over 6 minutes a frame; it now falls to the bisection.
        let settings = SolverSettings {
            max_total_iterations: Some(TRUTH_ITERATIONS),
            max_halvings: 8,
            reject_indefinite: false,
            ..config.solver.clone()
        };
        let solver = FeSolver::new(grid, material, fixed, settings)?;
        Ok(Self { solver, full, load_cap: 1.0, last_ramp: 0.0, held: None, solve_ms: 0.0 })
    }

    fn scaled(&self, r: f64) -> BoundaryConditions {
        let mut bc = self.full.clone();
        for v in &mut bc.forces_n {
            *v *= r;
        }
        bc
    }

    /// The nodal displacement at `ramp` times the full load (at most `load_cap`).
    fn displacement(&mut self, ramp: f64, cancel: &Cancel) -> Result<Vec<Vector3<f64>>, String> {
        let n = self.full.fixed.len();
        let u = if ramp == 0.0 {
            vec![Vector3::zeros(); n]
        } else if let Some(u) = self.held.as_ref().filter(|_| ramp >= self.load_cap) {
            // Capped at the largest load that converged: that state, not solved again.
            u.clone()
        } else {
            let t = std::time::Instant::now();
            let sol = match self.solver.solve(&self.scaled(ramp), SolveMethod::Newton, &Progress::none(), cancel) {
                Ok(sol) => sol,
                // The truth cannot reach this frame's load (SVK collapsing under it): the
                // largest load between the last converged frame's and this one that converges
                // (bisected), kept for the frames after; the report says how far it got.
                Err(e) if !cancel.is_cancelled() => {
                    let Some((lo, sol)) = self.bisect(ramp, cancel) else { return Err(e.to_string()) };
                    self.load_cap = lo;
                    self.held = Some(sol.displacement_mm.clone());
                    sol
                }
                Err(e) => return Err(e.to_string()),
            };
            self.solve_ms += t.elapsed().as_secs_f64() * 1e3;
            sol.displacement_mm
        };
        self.last_ramp = ramp.min(self.load_cap);
        Ok(u)
    }

    /// The largest load between the last converged frame's and `ramp` that converges, with its
    /// solution; each probe bounded, so a collapsing truth costs a few solves, not hours.
    fn bisect(&mut self, ramp: f64, cancel: &Cancel) -> Option<(f64, crate::fem::solver::Solution)> {
        let (mut lo, mut hi, mut best) = (self.last_ramp, ramp, None);
        let unbounded = self.solver.settings.max_total_iterations;
        self.solver.settings.max_total_iterations = Some(BISECTION_ITERATIONS);
        for _ in 0..LOAD_BISECTIONS {
            let mid = 0.5 * (lo + hi);
            match self.solver.solve(&self.scaled(mid), SolveMethod::Newton, &Progress::none(), cancel) {
                Ok(sol) => {
                    lo = mid;
                    best = Some(sol);
                }
                Err(_) => hi = mid,
            }
        }
        self.solver.settings.max_total_iterations = unbounded;
        best.map(|sol| (lo, sol))
    }
}

/// The camera's pose at each frame and the instruments' sweeps.
struct CameraPath {
    poses: Vec<Matrix4<f64>>,
    sweeps: Vec<(Shaft, Shaft)>,
}

/// Camera motion and instruments from their own stream, so that a recording without them is
/// the one this seed always gave.
fn camera_path(settings: &SynthSettings, pose: &Matrix4<f64>, k: &Intrinsics) -> CameraPath {
    let mut motion_rng = SplitMix64(settings.seed ^ 0x00C0_FFEE);
    let unit = |rng: &mut SplitMix64| loop {
        let v = Vector3::new(rng.next_f64() * 2.0 - 1.0, rng.next_f64() * 2.0 - 1.0, rng.next_f64() * 2.0 - 1.0);
        if v.norm() > 0.1 && v.norm() <= 1.0 {
            break v.normalize();
        }
    };
    let mut side = unit(&mut motion_rng);
    side.z = 0.0;
    let offset_cam = if side.norm() > 1e-6 {
        side.normalize() * settings.camera_motion_mm
    } else {
        Vector3::x() * settings.camera_motion_mm
    };
    let axis_cam = unit(&mut motion_rng);
    let sweeps = instrument_sweeps(settings.instruments, k, &mut motion_rng);
    let poses = (0..settings.frames)
        .map(|f| {
            let t = if settings.frames > 1 { f as f64 / (settings.frames - 1) as f64 } else { 0.0 };
            moved_pose(pose, &offset_cam, &axis_cam, settings.camera_motion_deg.to_radians(), t)
        })
        .collect();
    CameraPath { poses, sweeps }
}

fn row_major(m: &Matrix4<f64>) -> [f64; 16] {
    m.transpose().as_slice().try_into().unwrap_or([0.0; 16])
}

/// The markers moved by the nodal displacement `u` (world, mm); each one's displacement is
/// appended to `disp`.
fn marker_positions(
    grid: &crate::grid::ImmersedGrid,
    markers: &[Vector3<f64>],
    u: &[Vector3<f64>],
    disp: &mut Vec<f64>,
) -> Vec<[f64; 3]> {
    markers
        .iter()
        .map(|p| {
            let d: Vector3<f64> = grid
                .embed(p)
                .map(|e| e.nodes.iter().zip(e.weights).map(|(&n, w)| u[n as usize] * w).sum())
                .unwrap_or_default();
            disp.push(d.norm());
            [p.x + d.x, p.y + d.y, p.z + d.z]
        })
        .collect()
}

/// The recording's files beside its frames: intrinsics, frame rate, poses, truth, settings.
fn write_recording_files(
    out: &Path,
    k: &Intrinsics,
    settings: &SynthSettings,
    poses: &[Matrix4<f64>],
    truth: &GroundTruth,
) -> Result<(), RgbdError> {
    let io = |p: PathBuf| move |e: std::io::Error| RgbdError::Io { path: p, source: e };
    let w = |name: &str, text: String| -> Result<(), RgbdError> {
        let p = out.join(name);
        crate::write_atomic(&p, text.as_bytes()).map_err(io(p.clone()))
    };
    w("intrinsics.json", k.to_open3d_json())?;
    w("recording.json", json(&RecordingMeta { depth_scale: 1000.0, fps: settings.fps }))?;
    w("trajectory.log", write_trajectory_log(poses))?;
    w("ground_truth.json", json(truth))?;
    w("synth.json", json(settings))
}

/// A frame as a camera's sparse cloud: `count` organ pixels with depth drawn at random
/// (fewer when the organ shows fewer), back-projected; the colour image beside it.
fn write_cloud_frame(
    dir: &Path,
    stem: &str,
    frame: &Frame,
    count: usize,
    rng: &mut SplitMix64,
) -> Result<(), RgbdError> {
    let mut organ: Vec<usize> = (0..frame.depth.depth_mm.len())
        .filter(|&i| frame.mask.as_ref().is_none_or(|m| m[i]) && frame.depth.depth_mm[i] > 0.0)
        .collect();
    // A partial Fisher-Yates shuffle: the first `count` are a uniform draw.
    let n = count.min(organ.len());
    for i in 0..n {
        let j = i + (rng.next_u64() % (organ.len() - i) as u64) as usize;
        organ.swap(i, j);
    }
    let k = &frame.intrinsics;
    let points: Vec<Vector3<f64>> = organ[..n]
        .iter()
        .map(|&i| k.unproject((i % k.width) as f64, (i / k.width) as f64, frame.depth.depth_mm[i] as f64))
        .collect();
    let p = dir.join("points").join(format!("{stem}.ply"));
    crate::mesh_io::write_point_cloud(&p, &points, "umesh synthetic cloud, camera frame millimetres")
        .map_err(|e| crate::rgbd::invalid(&p, e.to_string()))?;
    if let Some(c) = &frame.color {
        let p = dir.join("color").join(format!("{stem}.png"));
        let bytes = c.encode_png().map_err(|r| crate::rgbd::invalid(&p, r))?;
        crate::write_atomic(&p, &bytes).map_err(|e| RgbdError::Io { path: p.clone(), source: e })?;
    }
    Ok(())
}

fn json<T: serde::Serialize>(v: &T) -> String {
    serde_json::to_string_pretty(v).unwrap_or_default()
}
