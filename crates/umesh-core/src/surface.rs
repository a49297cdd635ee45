//! Surface extraction: marching tetrahedra on a smoothed mask. The Kuhn (Freudenthal)
//! split of every cube into six tetrahedra is consistent between neighbours, so the
//! result is a closed 2-manifold; triangles are oriented from inside to outside.

use crate::mesh::TriMesh;
use crate::volume::Mask;
use nalgebra::{Point3, Vector3};
use std::collections::HashMap;

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SurfaceSettings {
    /// Gaussian smoothing of the mask before extraction, in voxels.
    pub sigma_voxels: f64,
    /// Sample every `step`-th voxel (coarser, lighter meshes).
    pub step: usize,
    /// Taubin smoothing passes after extraction.
    pub smooth_iterations: usize,
}

impl Default for SurfaceSettings {
    fn default() -> Self {
        Self { sigma_voxels: 1.0, step: 1, smooth_iterations: 3 }
    }
}

/// Separable Gaussian blur of a mask into a field in [0, 1] on the mask's lattice,
/// cropped to the mask's bounding box plus a margin. Returns (field, dims, offset).
fn blurred_field(mask: &Mask, sigma: f64, margin: usize) -> Option<(Vec<f32>, [usize; 3], [i64; 3])> {
    let (lo, hi) = mask.voxel_bounds()?;
    let off = [0, 1, 2].map(|a| lo[a] as i64 - margin as i64);
    let dims = [0, 1, 2].map(|a| hi[a] - lo[a] + 1 + 2 * margin);
    let [nx, ny, nz] = dims;
    let mut f = vec![0f32; nx * ny * nz];
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                if mask.get(i as i64 + off[0], j as i64 + off[1], k as i64 + off[2]) {
                    f[i + nx * (j + ny * k)] = 1.0;
                }
            }
        }
    }
    if sigma > 0.0 {
        let r = (3.0 * sigma).ceil() as i64;
        let w: Vec<f32> = (-r..=r).map(|x| (-(x * x) as f64 / (2.0 * sigma * sigma)).exp() as f32).collect();
        let s: f32 = w.iter().sum();
        let w: Vec<f32> = w.iter().map(|v| v / s).collect();
        let strides = [1, nx, nx * ny];
        for a in 0..3 {
            let mut out = vec![0f32; f.len()];
            for idx in 0..f.len() {
                let c = [idx % nx, (idx / nx) % ny, idx / (nx * ny)];
                let mut acc = 0f32;
                for (t, wt) in w.iter().enumerate() {
                    let p = c[a] as i64 + t as i64 - r;
                    if p >= 0 && (p as usize) < dims[a] {
                        acc += wt * f[(idx as i64 + (p - c[a] as i64) * strides[a] as i64) as usize];
                    }
                }
                out[idx] = acc;
            }
            f = out;
        }
    }
    Some((f, dims, off))
}

/// The six tetrahedra of a cube sharing the diagonal 0-7 (corner bits: x=1, y=2, z=4).
const KUHN: [[usize; 4]; 6] = [[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]];

/// Extract the boundary surface of a mask in world millimetres.
pub fn extract_surface(mask: &Mask, settings: &SurfaceSettings) -> TriMesh {
    let step = settings.step.max(1);
    let margin = ((3.0 * settings.sigma_voxels).ceil() as usize + 1).max(step + 1);
    let Some((field, dims, off)) = blurred_field(mask, settings.sigma_voxels, margin) else {
        return TriMesh::default();
    };
    let [nx, ny, nz] = dims;
    let iso = 0.5f32;
    let sx = (nx - 1) / step + 1;
    let sy = (ny - 1) / step + 1;
    let sz = (nz - 1) / step + 1;
    let lattice = |i: usize, j: usize, k: usize| (i * step) + nx * ((j * step) + ny * (k * step));
    let key = |i: usize, j: usize, k: usize| (i + sx * (j + sy * k)) as u64;
    let mut mesh = TriMesh::default();
    let mut edge_vertex: HashMap<(u64, u64), u32> = HashMap::new();
    let pos = |i: usize, j: usize, k: usize| Vector3::new((i * step) as f64, (j * step) as f64, (k * step) as f64);
    for k in 0..sz.saturating_sub(1) {
        for j in 0..sy.saturating_sub(1) {
            for i in 0..sx.saturating_sub(1) {
                let corner = |c: usize| (i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1));
                let vals: [f32; 8] = std::array::from_fn(|c| {
                    let (a, b, d) = corner(c);
                    field[lattice(a, b, d)]
                });
                let ins = vals.iter().filter(|&&v| v > iso).count();
                if ins == 0 || ins == 8 {
                    continue;
                }
                for tet in KUHN {
                    let inside: Vec<usize> = tet.iter().copied().filter(|&c| vals[c] > iso).collect();
                    let outside: Vec<usize> = tet.iter().copied().filter(|&c| vals[c] <= iso).collect();
                    if inside.is_empty() || outside.is_empty() {
                        continue;
                    }
                    let mut vert = |a: usize, b: usize| -> u32 {
                        let (ca, cb) = (corner(a), corner(b));
                        let (ka, kb) = (key(ca.0, ca.1, ca.2), key(cb.0, cb.1, cb.2));
                        let ek = (ka.min(kb), ka.max(kb));
                        *edge_vertex.entry(ek).or_insert_with(|| {
                            let t = ((iso - vals[a]) / (vals[b] - vals[a])).clamp(0.01, 0.99) as f64;
                            let p = pos(ca.0, ca.1, ca.2) * (1.0 - t) + pos(cb.0, cb.1, cb.2) * t;
                            mesh.positions.push(p);
                            (mesh.positions.len() - 1) as u32
                        })
                    };
                    // Direction from inside to outside, to orient triangles.
                    let centroid = |cs: &[usize]| {
                        cs.iter()
                            .map(|&c| {
                                let (a, b, d) = corner(c);
                                pos(a, b, d)
                            })
                            .sum::<Vector3<f64>>()
                            / cs.len() as f64
                    };
                    let outward = centroid(&outside) - centroid(&inside);
                    let mut tris: Vec<[u32; 3]> = Vec::new();
                    match (inside.len(), outside.len()) {
                        (1, 3) => tris.push([
                            vert(inside[0], outside[0]),
                            vert(inside[0], outside[1]),
                            vert(inside[0], outside[2]),
                        ]),
                        (3, 1) => tris.push([
                            vert(inside[0], outside[0]),
                            vert(inside[1], outside[0]),
                            vert(inside[2], outside[0]),
                        ]),
                        _ => {
                            let a = vert(inside[0], outside[0]);
                            let b = vert(inside[0], outside[1]);
                            let c = vert(inside[1], outside[1]);
                            let d = vert(inside[1], outside[0]);
                            tris.push([a, b, c]);
                            tris.push([a, c, d]);
                        }
                    }
                    for mut t in tris {
                        let [p0, p1, p2] = t.map(|v| mesh.positions[v as usize]);
                        if (p1 - p0).cross(&(p2 - p0)).dot(&outward) < 0.0 {
                            t.swap(1, 2);
                        }
                        mesh.triangles.push(t);
                    }
                }
            }
        }
    }
    mesh.taubin_smooth(settings.smooth_iterations);
    // Lattice -> voxel -> world.
    let m = mask.world_from_voxel;
    for p in &mut mesh.positions {
        let v = *p + Vector3::new(off[0] as f64, off[1] as f64, off[2] as f64);
        *p = m.transform_point(&Point3::from(v)).coords;
    }
    if m.fixed_view::<3, 3>(0, 0).determinant() < 0.0 {
        for t in &mut mesh.triangles {
            t.swap(1, 2);
        }
    }
    mesh
}
