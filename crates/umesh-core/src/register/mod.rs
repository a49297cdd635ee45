//! Intraoperative registration: observed RGB-D frame -> rigid pose (ICP) -> surface
//! displacement of the grid's visible nodes (u_s) -> volume displacement (network or FE)
//! -> internal structures deformed through their grid embedding -> overlay on the image.

pub mod coarse;
pub mod confidence;
pub mod correction;
pub mod icp;
pub mod overlay;
pub mod pipeline;

use crate::dataset::DatasetContext;
use crate::grid::{Embedding, ImmersedGrid};
use crate::mesh::TriMesh;
use crate::segmentation::Segmentation;
use crate::surface::{SurfaceSettings, extract_surface};
use icp::IcpTarget;
use nalgebra::Vector3;
use rayon::prelude::*;

/// An internal structure (tumour, vessel) to overlay.
#[derive(Debug)]
pub struct Structure {
    pub label: i64,
    pub name: String,
    pub color: [u8; 3],
    pub mesh: TriMesh,
    embedding: Vec<Embedding>,
}

/// Distinct overlay colours: tumours warm, vessels cool.
pub fn structure_color(name: &str, i: usize) -> [u8; 3] {
    let n = name.to_lowercase();
    if n.contains("tumo") || n.contains("lesion") {
        [[255, 215, 40], [255, 140, 30], [250, 90, 160]][i % 3]
    } else if n.contains("cava") || n.contains("ivc") {
        [60, 120, 255]
    } else if n.contains("portal") || n.contains("vein") {
        [170, 90, 255]
    } else {
        [[80, 230, 120], [60, 220, 230], [230, 230, 230]][i % 3]
    }
}

/// The surfaces of the segmentation's internal structures, with names and overlay colours
/// (labels with no voxel or no surface are left out).
pub fn structure_surfaces(seg: &Segmentation) -> Vec<(i64, String, [u8; 3], TriMesh)> {
    let mut out = Vec::new();
    for (i, &label) in seg.structure_labels.iter().enumerate() {
        let mask = seg.volume.mask(&[label]);
        if mask.count() == 0 {
            continue;
        }
        let mesh = extract_surface(&mask, &SurfaceSettings { sigma_voxels: 0.8, step: 1, smooth_iterations: 10 });
        if !mesh.triangles.is_empty() {
            let name = seg.label_name(label);
            out.push((label, name.clone(), structure_color(&name, i), mesh));
        }
    }
    out
}

/// What registration needs from the preoperative model.
#[derive(Debug)]
pub struct RegistrationContext {
    pub grid: ImmersedGrid,
    /// The hash of the grid (`DatasetContext::grid_hash`): a synthetic recording's ground truth
    /// carries the hash of the grid it was made on.
    pub grid_hash: String,
    /// The rest organ surface (world, mm).
    pub surface: TriMesh,
    pub surface_normals: Vec<Vector3<f64>>,
    surface_embedding: Vec<Embedding>,
    /// Vertices of the surface the training camera sees.
    pub visible_vertices: Vec<usize>,
    /// Grid nodes of the network input (u_s is non-zero there).
    pub visible_nodes: Vec<usize>,
    pub fixed: Vec<bool>,
    /// The dataset's material (the physics correction's model).
    pub material: crate::fem::MaterialParams,
    pub structures: Vec<Structure>,
    /// Visible node -> neighbouring visible nodes (6-connected), to fill unobserved nodes.
    node_neighbours: Vec<Vec<usize>>,
    pub(crate) icp_target: IcpTarget,
    /// The rest surface's vertices in cells as large as the coverage gate's search.
    gate_grid: crate::nn::PointIndex,
    /// The physics correction's subspace (patches, basis), built once (before the frames by
    /// the correction's `prepare_correction`, or at the first corrected frame) and shared by
    /// every registration on this context.
    /// The correction's bases built so far, by (patches, free body): built once per context.
    pub(crate) correction_basis: std::sync::Mutex<Vec<((usize, bool), crate::fem::solver::fit::Subspace)>>,
    /// The organ coarsened 2, 3, ... times for a doubted frame's fit, built once when first
    /// asked for.
    coarse: [std::sync::OnceLock<Result<coarse::CoarseModel, String>>; coarse::MAX_COARSENING - 1],
}

fn embed_all(grid: &ImmersedGrid, pts: &[Vector3<f64>]) -> Result<Vec<Embedding>, crate::Invalid> {
    pts.iter()
        .map(|p| grid.embed(p).ok_or_else(|| crate::Invalid(format!("point {p:?} lies outside the grid"))))
        .collect()
}

/// The triangles of `mesh` whose three vertices lie in or near the grid, with their
/// embeddings; None when no triangle does.
fn clip_to_grid(grid: &ImmersedGrid, mesh: &TriMesh) -> Option<(TriMesh, Vec<Embedding>)> {
    let emb: Vec<Option<Embedding>> = mesh.positions.iter().map(|p| grid.embed(p)).collect();
    if emb.iter().all(|e| e.is_some()) {
        return Some((mesh.clone(), emb.into_iter().flatten().collect()));
    }
    let mut remap = vec![u32::MAX; mesh.positions.len()];
    let mut out = TriMesh { positions: Vec::new(), triangles: Vec::new() };
    let mut embedding = Vec::new();
    for tri in &mesh.triangles {
        let Some(es) = tri.iter().map(|&v| emb[v as usize]).collect::<Option<Vec<Embedding>>>() else { continue };
        let mut t = [0u32; 3];
        for (k, (&v, e)) in tri.iter().zip(es).enumerate() {
            let v = v as usize;
            if remap[v] == u32::MAX {
                remap[v] = out.positions.len() as u32;
                out.positions.push(mesh.positions[v]);
                embedding.push(e);
            }
            t[k] = remap[v];
        }
        out.triangles.push(t);
    }
    (!out.triangles.is_empty()).then_some((out, embedding))
}

impl RegistrationContext {
    /// From the dataset context of the model's grid, with the structures of `seg`.
    pub fn new(ctx: DatasetContext, seg: &Segmentation) -> Result<Self, crate::Invalid> {
        let grid_hash = ctx.grid_hash();
        let mut structures = Vec::new();
        for (label, name, color, mesh) in structure_surfaces(seg) {
            // A structure may leave the organ (TotalSegmentator's portal vein runs on to the
            // spleen): only the part the grid carries is drawn.
            let Some((mesh, embedding)) = clip_to_grid(&ctx.grid, &mesh) else { continue };
            structures.push(Structure { label, name, color, mesh, embedding });
        }
        let surface = ctx.surface;
        let surface_normals = surface.vertex_normals();
        let surface_embedding = embed_all(&ctx.grid, &surface.positions)?;
        let mut vis = vec![false; surface.positions.len()];
        for (t, tri) in surface.triangles.iter().enumerate() {
            if ctx.visible.visible[t] {
                for &v in tri {
                    vis[v as usize] = true;
                }
            }
        }
        let visible_vertices: Vec<usize> = (0..vis.len()).filter(|&v| vis[v]).collect();
        let grid = ctx.grid;
        let mut slot = vec![usize::MAX; grid.node_count()];
        for (k, &n) in ctx.visible_nodes.iter().enumerate() {
            slot[n] = k;
        }
        let node_neighbours = ctx
            .visible_nodes
            .iter()
            .map(|&n| {
                let [i, j, k] = grid.node_ijk[n];
                let mut out = Vec::new();
                for (di, dj, dk) in [(-1i64, 0i64, 0i64), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)] {
                    let q = [i as i64 + di, j as i64 + dj, k as i64 + dk];
                    if q.iter().all(|&v| v >= 0)
                        && let Some(m) = grid.node_at([q[0] as usize, q[1] as usize, q[2] as usize])
                        && slot[m] != usize::MAX
                    {
                        out.push(slot[m]);
                    }
                }
                out
            })
            .collect();
        let spacing = surface.area_mm2().sqrt() / (surface.positions.len().max(1) as f64).sqrt();
        let icp_target = IcpTarget::new(surface.positions.clone(), surface_normals.clone(), spacing);
        // Cells of a few vertex spacings: the shell search stops after a shell or two for a
        // point near the surface (cells of the whole reach held thousands of vertices each).
        let gate_grid = crate::nn::PointIndex::new(&surface.positions, (4.0 * spacing).max(2.0));
        Ok(Self {
            grid,
            surface,
            surface_normals,
            surface_embedding,
            visible_vertices,
            visible_nodes: ctx.visible_nodes,
            fixed: ctx.fixed,
            material: ctx.material,
            structures,
            node_neighbours,
            icp_target,
            gate_grid,
            correction_basis: Default::default(),
            coarse: Default::default(),
            grid_hash,
        })
    }

    /// The share of the organ's surface within `radius_mm` of an observed point (world, mm):
    /// surface vertices, at most about 2000 of them, each counted once.
    pub fn surface_coverage(&self, points_world_mm: &[Vector3<f64>], radius_mm: f64) -> f64 {
        confidence::surface_coverage(&self.surface, points_world_mm, radius_mm)
    }

    /// The coverage gate before a frame is registered: the share of the organ's surface the
    /// points cover once each is taken to its nearest rest-surface point within the coverage
    /// radius plus `DEFORMATION_ALLOWANCE_MM` (a deformed or pushed organ's points lie off the
    /// rest surface; a cloud off the organ covers nothing). At most 500 of the points.
    pub fn gate_coverage(&self, points_world_mm: &[Vector3<f64>]) -> f64 {
        let step = points_world_mm.len().div_ceil(500).max(1);
        let sub: Vec<Vector3<f64>> = points_world_mm.iter().step_by(step).copied().collect();
        let radius = confidence::coverage_radius_mm(&sub);
        let reach = radius + confidence::DEFORMATION_ALLOWANCE_MM;
        let on_surface: Vec<Vector3<f64>> =
            sub.par_iter().filter_map(|p| self.gate_grid.nearest(p, reach).map(|(_, q)| q)).collect();
        self.surface_coverage(&on_surface, radius)
    }

    pub fn padded_shape(&self) -> [usize; 3] {
        self.grid.padded_shape()
    }

    /// The organ on cells `factor` (2 to `coarse::MAX_COARSENING`) times as large, built at the
    /// first call.
    pub fn coarse_model(&self, factor: usize) -> Result<&coarse::CoarseModel, crate::Invalid> {
        let slot = factor.checked_sub(2).and_then(|i| self.coarse.get(i)).ok_or_else(|| {
            crate::Invalid(format!(
                "--doubted-coarsening {factor}: the coarse grid's cells are 2 to {} times the organ's (1: its own grid)",
                coarse::MAX_COARSENING
            ))
        })?;
        slot.get_or_init(|| coarse::CoarseModel::new(&self.grid, &self.fixed, factor).map_err(|e| e.0))
            .as_ref()
            .map_err(|e| crate::Invalid(e.clone()))
    }

    /// The organ surface deformed by a dense [3, X, Y, Z] displacement field.
    pub fn deformed_surface(&self, field: &[f32]) -> TriMesh {
        deform(&self.grid, &self.surface, &self.surface_embedding, field)
    }

    pub fn deformed_structure(&self, s: &Structure, field: &[f32]) -> TriMesh {
        deform(&self.grid, &s.mesh, &s.embedding, field)
    }
}

fn deform(grid: &ImmersedGrid, mesh: &TriMesh, emb: &[Embedding], field: &[f32]) -> TriMesh {
    let mut out = mesh.clone();
    for (p, e) in out.positions.iter_mut().zip(emb) {
        *p += displacement_at(grid, field, e);
    }
    out
}

/// Displacement (mm) at an embedded point from a dense [3, X, Y, Z] field.
pub fn displacement_at(grid: &ImmersedGrid, field: &[f32], e: &Embedding) -> Vector3<f64> {
    let [x, y, z] = grid.padded_shape();
    let cells = x * y * z;
    let mut d = Vector3::zeros();
    for (n, w) in e.nodes.iter().zip(e.weights) {
        if w != 0.0 {
            let idx = grid.dense_index(*n as usize);
            for c in 0..3 {
                d[c] += w * field[c * cells + idx] as f64;
            }
        }
    }
    d
}

/// `count` uniformly random points in the grid's fully inside cells (all cells if none is).
pub fn inside_markers(grid: &ImmersedGrid, count: usize, rng: &mut crate::rng::SplitMix64) -> Vec<Vector3<f64>> {
    let inside: Vec<usize> =
        (0..grid.cells.len()).filter(|&c| grid.cells[c].kind == crate::grid::CellKind::Inside).collect();
    let cells = if inside.is_empty() { (0..grid.cells.len()).collect() } else { inside };
    (0..count)
        .map(|_| {
            let c = cells[(rng.next_u64() % cells.len() as u64) as usize];
            let [i, j, k] = grid.cells[c].ijk;
            let off = Vector3::new(i as f64 + rng.next_f64(), j as f64 + rng.next_f64(), k as f64 + rng.next_f64());
            grid.origin_mm + off * grid.cell_size_mm
        })
        .collect()
}

/// Virtual markers for the TRE: `count` points inside the organ (inside cells) and, when the
/// segmentation has internal structures, as many points on them; fixed by `seed`.
pub fn virtual_markers(ctx: &RegistrationContext, count: usize, seed: u64) -> Vec<Vector3<f64>> {
    let mut rng = crate::rng::SplitMix64(seed);
    let mut out = inside_markers(&ctx.grid, count, &mut rng);
    let verts: Vec<&Vector3<f64>> = ctx.structures.iter().flat_map(|s| s.mesh.positions.iter()).collect();
    if !verts.is_empty() {
        for _ in 0..count {
            out.push(*verts[(rng.next_u64() % verts.len() as u64) as usize]);
        }
    }
    out
}
