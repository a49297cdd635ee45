//! Datasets from `umesh dataset generate`, in memory, with the 80/20 split and normalisation.

use umesh_core::dataset::{Dataset, DatasetError};
use umesh_core::grid::ImmersedGrid;
use umesh_core::npz::Npz;

/// All accepted, unflagged samples of a dataset: u_s and u_v as [3, X, Y, Z] f32 each.
#[derive(Debug)]
pub struct SampleSet {
    pub shape: [usize; 3],
    pub indices: Vec<usize>,
    pub u_s: Vec<Vec<f32>>,
    pub u_v: Vec<Vec<f32>>,
    pub grid: ImmersedGrid,
}

impl SampleSet {
    pub fn load(dir: &std::path::Path) -> Result<Self, DatasetError> {
        let ds = Dataset::open(dir)?;
        let flagged: std::collections::BTreeSet<usize> = ds.manifest.samples.iter().filter(|s| s.flagged).map(|s| s.index).collect();
        let grid = ImmersedGrid::from_npz(&Npz::read(&dir.join("grid.npz"))?)?;
        let shape = ds.manifest.padded_shape;
        let n = 3 * shape[0] * shape[1] * shape[2];
        let (mut indices, mut u_s, mut u_v) = (Vec::new(), Vec::new(), Vec::new());
        for shard in &ds.manifest.shards {
            let (idx, s, v) = ds.load_shard(shard)?;
            for (k, i) in idx.into_iter().enumerate() {
                if flagged.contains(&i) {
                    continue;
                }
                indices.push(i);
                u_s.push(s[k * n..(k + 1) * n].to_vec());
                u_v.push(v[k * n..(k + 1) * n].to_vec());
            }
        }
        Ok(Self { shape, indices, u_s, u_v, grid })
    }

    pub fn len(&self) -> usize {
        self.indices.len()
    }

    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// The paper's split: sample indices with i mod 5 == 4 validate (20 %), the rest train.
    pub fn split(&self) -> (Vec<usize>, Vec<usize>) {
        let (mut train, mut val) = (Vec::new(), Vec::new());
        for (k, &i) in self.indices.iter().enumerate() {
            if i % 5 == 4 { val.push(k) } else { train.push(k) }
        }
        (train, val)
    }
}

/// Scale factors (mm per network unit) for inputs and outputs: the RMS of the non-zero values
/// of the training samples.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normalization {
    pub input_scale_mm: f32,
    pub output_scale_mm: f32,
}

impl Normalization {
    pub fn fit(set: &SampleSet, train: &[usize]) -> Self {
        let rms = |v: &[Vec<f32>]| {
            let (mut s, mut n) = (0f64, 0usize);
            for &k in train {
                for &x in &v[k] {
                    if x != 0.0 {
                        s += (x as f64) * (x as f64);
                        n += 1;
                    }
                }
            }
            if n == 0 { 1.0 } else { ((s / n as f64).sqrt() as f32).max(1e-6) }
        };
        Self { input_scale_mm: rms(&set.u_s), output_scale_mm: rms(&set.u_v) }
    }
}
