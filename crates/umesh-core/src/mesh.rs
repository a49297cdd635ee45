//! Triangle meshes in world millimetres: topology checks, normals, measures, voxelisation.

use crate::volume::Mask;
use nalgebra::{Matrix4, Point3, Vector3};
use std::collections::HashMap;

#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriMesh {
    pub positions: Vec<Vector3<f64>>,
    pub triangles: Vec<[u32; 3]>,
}

/// How a mesh fails to be a closed, consistently oriented surface.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TopologyReport {
    pub triangles: usize,
    pub boundary_edges: usize,
    pub non_manifold_edges: usize,
    pub inconsistent_edges: usize,
}

impl TopologyReport {
    pub fn is_watertight(&self) -> bool {
        // A surface with no triangle encloses nothing.
        self.triangles > 0 && self.boundary_edges == 0 && self.non_manifold_edges == 0 && self.inconsistent_edges == 0
    }
}

impl TriMesh {
    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    pub fn topology(&self) -> TopologyReport {
        // Count each directed edge; a closed oriented 2-manifold uses every edge once in each direction.
        let mut directed: HashMap<(u32, u32), u32> = HashMap::with_capacity(self.triangles.len() * 3);
        for t in &self.triangles {
            for e in 0..3 {
                *directed.entry((t[e], t[(e + 1) % 3])).or_insert(0) += 1;
            }
        }
        let mut report = TopologyReport {
            triangles: self.triangles.len(),
            boundary_edges: 0,
            non_manifold_edges: 0,
            inconsistent_edges: 0,
        };
        for (&(a, b), &n_ab) in &directed {
            let n_ba = directed.get(&(b, a)).copied().unwrap_or(0);
            if n_ba > 0 && a > b {
                continue; // counted from the other direction
            }
            match n_ab + n_ba {
                1 => report.boundary_edges += 1,
                2 if n_ba == 0 => report.inconsistent_edges += 1,
                2 => {}
                _ => report.non_manifold_edges += 1,
            }
        }
        report
    }

    pub fn triangle_normal_area(&self, t: usize) -> (Vector3<f64>, f64) {
        let [a, b, c] = self.triangles[t].map(|i| self.positions[i as usize]);
        let n = (b - a).cross(&(c - a));
        let len = n.norm();
        (if len > 0.0 { n / len } else { Vector3::zeros() }, 0.5 * len)
    }

    pub fn area_mm2(&self) -> f64 {
        (0..self.triangles.len()).map(|t| self.triangle_normal_area(t).1).sum()
    }

    /// Signed enclosed volume (positive when normals point outward).
    pub fn signed_volume_mm3(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.positions[i as usize]);
                a.dot(&b.cross(&c)) / 6.0
            })
            .sum()
    }

    /// Area-weighted vertex normals.
    pub fn vertex_normals(&self) -> Vec<Vector3<f64>> {
        let mut n = vec![Vector3::zeros(); self.positions.len()];
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| self.positions[i as usize]);
            let fnrm = (b - a).cross(&(c - a));
            for &i in t {
                n[i as usize] += fnrm;
            }
        }
        for v in &mut n {
            let l = v.norm();
            if l > 0.0 {
                *v /= l;
            }
        }
        n
    }

    pub fn bounds(&self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let first = *self.positions.first()?;
        Some(self.positions.iter().fold((first, first), |(lo, hi), p| (lo.inf(p), hi.sup(p))))
    }

    pub fn transform(&mut self, m: &Matrix4<f64>) {
        for p in &mut self.positions {
            *p = m.transform_point(&Point3::from(*p)).coords;
        }
        if m.fixed_view::<3, 3>(0, 0).determinant() < 0.0 {
            for t in &mut self.triangles {
                t.swap(1, 2);
            }
        }
    }

    /// Taubin smoothing (lambda/mu), which smooths without the shrinkage of plain Laplacian.
    pub fn taubin_smooth(&mut self, iterations: usize) {
        let n = self.positions.len();
        let mut nbrs: Vec<Vec<u32>> = vec![Vec::new(); n];
        for t in &self.triangles {
            for e in 0..3 {
                let (a, b) = (t[e], t[(e + 1) % 3]);
                if !nbrs[a as usize].contains(&b) {
                    nbrs[a as usize].push(b);
                }
                if !nbrs[b as usize].contains(&a) {
                    nbrs[b as usize].push(a);
                }
            }
        }
        let mut tmp = self.positions.clone();
        for _ in 0..iterations {
            for factor in [0.5, -0.53] {
                for (i, nb) in nbrs.iter().enumerate() {
                    if nb.is_empty() {
                        continue;
                    }
                    let avg = nb.iter().map(|&j| self.positions[j as usize]).sum::<Vector3<f64>>() / nb.len() as f64;
                    tmp[i] = self.positions[i] + (avg - self.positions[i]) * factor;
                }
                std::mem::swap(&mut self.positions, &mut tmp);
            }
        }
    }

    /// Voxelise a closed mesh by ray parity along z on an axis-aligned lattice of `spacing_mm`.
    pub fn voxelize(&self, spacing_mm: f64) -> Option<Mask> {
        let (lo, hi) = self.bounds()?;
        // NIfTI keeps the lattice in single precision: an origin and spacing exact in f32 read
        // back as this very lattice, so a segmentation saved from a mesh gives the same grid
        // (and grid hash) as the mesh did (a patient prepared from a mesh accepts its model).
        let spacing_mm = spacing_mm as f32 as f64;
        let pad = 2.0 * spacing_mm;
        let origin = (lo - Vector3::repeat(pad)).map(|v| v as f32 as f64);
        let dims = [0, 1, 2].map(|a| (((hi[a] - lo[a]) + 2.0 * pad) / spacing_mm).ceil() as usize + 1);
        let [nx, ny, nz] = dims;
        if nx.saturating_mul(ny).saturating_mul(nz) > crate::nifti_io::DEFAULT_MAX_VOXELS as usize {
            return None;
        }
        let mut data = vec![false; nx * ny * nz];
        // Bucket triangles by the lattice columns their xy-bounding box covers.
        let mut columns: HashMap<(usize, usize), Vec<usize>> = HashMap::new();
        for (t, tri) in self.triangles.iter().enumerate() {
            let p = tri.map(|i| self.positions[i as usize]);
            let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
            for q in &p {
                x0 = x0.min(q.x);
                x1 = x1.max(q.x);
                y0 = y0.min(q.y);
                y1 = y1.max(q.y);
            }
            let i0 = ((x0 - origin.x) / spacing_mm).floor().max(0.0) as usize;
            let i1 = (((x1 - origin.x) / spacing_mm).ceil() as usize).min(nx - 1);
            let j0 = ((y0 - origin.y) / spacing_mm).floor().max(0.0) as usize;
            let j1 = (((y1 - origin.y) / spacing_mm).ceil() as usize).min(ny - 1);
            for i in i0..=i1 {
                for j in j0..=j1 {
                    columns.entry((i, j)).or_default().push(t);
                }
            }
        }
        for ((i, j), tris) in columns {
            // Slightly perturbed ray position avoids hitting edges and vertices exactly.
            let x = origin.x + i as f64 * spacing_mm + 1.234e-7;
            let y = origin.y + j as f64 * spacing_mm + 2.345e-7;
            let mut hits: Vec<f64> = Vec::new();
            for t in tris {
                let [a, b, c] = self.triangles[t].map(|v| self.positions[v as usize]);
                let d = (b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y);
                if d.abs() < 1e-18 {
                    continue;
                }
                let u = ((x - a.x) * (c.y - a.y) - (c.x - a.x) * (y - a.y)) / d;
                let v = ((b.x - a.x) * (y - a.y) - (x - a.x) * (b.y - a.y)) / d;
                if u >= 0.0 && v >= 0.0 && u + v <= 1.0 {
                    hits.push(a.z + u * (b.z - a.z) + v * (c.z - a.z));
                }
            }
            hits.sort_by(f64::total_cmp);
            for pair in hits.chunks_exact(2) {
                let k0 = ((pair[0] - origin.z) / spacing_mm).ceil().max(0.0) as usize;
                let k1 = ((pair[1] - origin.z) / spacing_mm).floor();
                if k1 < 0.0 {
                    continue;
                }
                for k in k0..=(k1 as usize).min(nz - 1) {
                    data[i + nx * (j + ny * k)] = true;
                }
            }
        }
        let mut world_from_voxel = Matrix4::new_scaling(spacing_mm);
        world_from_voxel[(3, 3)] = 1.0;
        for a in 0..3 {
            world_from_voxel[(a, 3)] = origin[a];
        }
        Some(Mask { dims, data, world_from_voxel })
    }
}

/// Where a ray meets a mesh.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayHit {
    /// Distance along the (unit) ray direction (mm).
    pub distance_mm: f64,
    pub triangle: usize,
    pub point: Vector3<f64>,
    /// Unit normal of the hit triangle (outward for outward-oriented meshes).
    pub normal: Vector3<f64>,
}

impl TriMesh {
    /// The nearest intersection of the ray `origin + t * direction` (t > 0) with the mesh
    /// (Moller-Trumbore, both faces), e.g. to place a force probe under the mouse.
    pub fn ray_cast(&self, origin: &Vector3<f64>, direction: &Vector3<f64>) -> Option<RayHit> {
        let d = direction.try_normalize(1e-12)?;
        let mut best: Option<RayHit> = None;
        for (ti, t) in self.triangles.iter().enumerate() {
            let [a, b, c] = t.map(|i| self.positions[i as usize]);
            let (e1, e2) = (b - a, c - a);
            let p = d.cross(&e2);
            let det = e1.dot(&p);
            if det.abs() < 1e-12 {
                continue;
            }
            let inv = 1.0 / det;
            let s = origin - a;
            let u = s.dot(&p) * inv;
            if !(0.0..=1.0).contains(&u) {
                continue;
            }
            let q = s.cross(&e1);
            let v = d.dot(&q) * inv;
            if v < 0.0 || u + v > 1.0 {
                continue;
            }
            let dist = e2.dot(&q) * inv;
            if dist > 1e-9 && best.is_none_or(|h| dist < h.distance_mm) {
                best = Some(RayHit {
                    distance_mm: dist,
                    triangle: ti,
                    point: origin + d * dist,
                    normal: e1.cross(&e2).normalize(),
                });
            }
        }
        best
    }
}
