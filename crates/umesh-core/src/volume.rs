//! Scalar volumes on a voxel lattice with their voxel -> world (RAS mm) affine.

use nalgebra::{Matrix4, Point3, Vector3};

/// A 3-D scalar volume. Voxel (i, j, k) is stored at `i + nx * (j + ny * k)`
/// (NIfTI order, x fastest). Values are the scaled values (`scl_slope`/`scl_inter` applied).
#[derive(Clone, Debug)]
pub struct Volume {
    pub dims: [usize; 3],
    pub data: Vec<f32>,
    /// Maps voxel indices (homogeneous) to world RAS millimetres.
    pub world_from_voxel: Matrix4<f64>,
    /// Label number -> name, when the file or a sidecar names them.
    pub label_names: std::collections::BTreeMap<i64, String>,
}

impl Volume {
    pub fn new(dims: [usize; 3], world_from_voxel: Matrix4<f64>) -> Self {
        Self { dims, data: vec![0.0; dims[0] * dims[1] * dims[2]], world_from_voxel, label_names: Default::default() }
    }

    #[inline]
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }

    pub fn voxel_count(&self) -> usize {
        self.data.len()
    }

    /// Volume of one voxel in mm^3 (|det| of the linear part of the affine).
    pub fn voxel_volume_mm3(&self) -> f64 {
        self.world_from_voxel.fixed_view::<3, 3>(0, 0).determinant().abs()
    }

    /// The smallest voxel edge (mm) of the three axes.
    pub fn min_spacing_mm(&self) -> f64 {
        (0..3).map(|c| self.world_from_voxel.fixed_view::<3, 1>(0, c).norm()).fold(f64::INFINITY, f64::min)
    }

    pub fn voxel_from_world(&self) -> Matrix4<f64> {
        self.world_from_voxel.try_inverse().unwrap_or_else(Matrix4::identity)
    }

    pub fn world_point(&self, voxel: Vector3<f64>) -> Point3<f64> {
        self.world_from_voxel.transform_point(&Point3::from(voxel))
    }

    /// Distinct non-zero labels (values rounded to integers) with their voxel counts.
    pub fn label_counts(&self) -> std::collections::BTreeMap<i64, usize> {
        let mut counts = std::collections::BTreeMap::new();
        for &v in &self.data {
            let l = v.round() as i64;
            if l != 0 {
                *counts.entry(l).or_insert(0) += 1;
            }
        }
        counts
    }

    /// Binary mask of the voxels whose rounded value is one of `labels`.
    pub fn mask(&self, labels: &[i64]) -> Mask {
        let data = self.data.iter().map(|&v| labels.contains(&(v.round() as i64))).collect();
        Mask { dims: self.dims, data, world_from_voxel: self.world_from_voxel }
    }
}

/// A binary mask on a voxel lattice.
#[derive(Clone, Debug)]
pub struct Mask {
    pub dims: [usize; 3],
    pub data: Vec<bool>,
    pub world_from_voxel: Matrix4<f64>,
}

impl Mask {
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&b| b).count()
    }

    pub fn voxel_volume_mm3(&self) -> f64 {
        self.world_from_voxel.fixed_view::<3, 3>(0, 0).determinant().abs()
    }

    pub fn volume_mm3(&self) -> f64 {
        self.count() as f64 * self.voxel_volume_mm3()
    }

    #[inline]
    pub fn get(&self, i: i64, j: i64, k: i64) -> bool {
        if i < 0 || j < 0 || k < 0 {
            return false;
        }
        let (i, j, k) = (i as usize, j as usize, k as usize);
        if i >= self.dims[0] || j >= self.dims[1] || k >= self.dims[2] {
            return false;
        }
        self.data[i + self.dims[0] * (j + self.dims[1] * k)]
    }

    /// Inclusive voxel bounding box of the set voxels, or None when empty.
    pub fn voxel_bounds(&self) -> Option<([usize; 3], [usize; 3])> {
        let [nx, ny, _] = self.dims;
        let mut lo = [usize::MAX; 3];
        let mut hi = [0usize; 3];
        let mut any = false;
        for (idx, &b) in self.data.iter().enumerate() {
            if b {
                any = true;
                let c = [idx % nx, (idx / nx) % ny, idx / (nx * ny)];
                for a in 0..3 {
                    lo[a] = lo[a].min(c[a]);
                    hi[a] = hi[a].max(c[a]);
                }
            }
        }
        any.then_some((lo, hi))
    }

    /// World-space axis-aligned bounds (mm) of the set voxels (voxel cubes included).
    pub fn world_bounds(&self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let (lo, hi) = self.voxel_bounds()?;
        let mut min = Vector3::repeat(f64::INFINITY);
        let mut max = Vector3::repeat(f64::NEG_INFINITY);
        for c in 0..8 {
            let v = Vector3::new(
                if c & 1 == 0 { lo[0] as f64 - 0.5 } else { hi[0] as f64 + 0.5 },
                if c & 2 == 0 { lo[1] as f64 - 0.5 } else { hi[1] as f64 + 0.5 },
                if c & 4 == 0 { lo[2] as f64 - 0.5 } else { hi[2] as f64 + 0.5 },
            );
            let p = self.world_from_voxel.transform_point(&Point3::from(v));
            min = min.inf(&p.coords);
            max = max.sup(&p.coords);
        }
        Some((min, max))
    }

    /// An inside test in world coordinates (nearest voxel).
    pub fn world_sampler(&self) -> MaskSampler<'_> {
        MaskSampler {
            mask: self,
            voxel_from_world: self.world_from_voxel.try_inverse().unwrap_or_else(Matrix4::identity),
        }
    }
}

/// Nearest-voxel inside test of a mask at world points.
#[derive(Debug)]
pub struct MaskSampler<'a> {
    mask: &'a Mask,
    voxel_from_world: Matrix4<f64>,
}

impl MaskSampler<'_> {
    #[inline]
    pub fn inside(&self, p: &Point3<f64>) -> bool {
        let v = self.voxel_from_world.transform_point(p);
        self.mask.get(v.x.round() as i64, v.y.round() as i64, v.z.round() as i64)
    }
}
