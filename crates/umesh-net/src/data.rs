//! Datasets from `umesh dataset generate`, in memory, with the 80/20 split and normalisation.

use umesh_core::dataset::{Dataset, DatasetError};
use umesh_core::grid::ImmersedGrid;
use umesh_core::mesh::TriMesh;
use umesh_core::npz::{ArrayData, Npz};
use umesh_core::observation::{ObservationSettings, Observer};

/// The rest surface stored in a dataset's or model's `grid.npz` (the one the camera views
/// were sampled on).
pub fn rest_surface(npz: &Npz) -> Result<TriMesh, umesh_core::Invalid> {
    let v = match &npz.get("surface_vertices").map_err(|e| e.to_string())?.data {
        ArrayData::F32(v) if v.len() % 3 == 0 => v.clone(),
        _ => return Err(umesh_core::Invalid::from("'surface_vertices' is not float32 [N, 3]")),
    };
    let t = match &npz.get("surface_triangles").map_err(|e| e.to_string())?.data {
        ArrayData::I64(t) if t.len() % 3 == 0 => t.clone(),
        _ => return Err(umesh_core::Invalid::from("'surface_triangles' is not int64 [M, 3]")),
    };
    let n = v.len() / 3;
    if t.iter().any(|&i| i < 0 || i as usize >= n) {
        return Err(umesh_core::Invalid::from("'surface_triangles' indexes a vertex that does not exist"));
    }
    Ok(TriMesh {
        positions: v.chunks_exact(3).map(|p| nalgebra::Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)).collect(),
        triangles: t.chunks_exact(3).map(|c| [c[0] as u32, c[1] as u32, c[2] as u32]).collect(),
    })
}

/// All accepted, unflagged samples of a dataset: the network input ([C, X, Y, Z]: u_s, or the
/// encoded camera view) and u_v ([3, X, Y, Z]), f32.
#[derive(Debug)]
pub struct SampleSet {
    pub shape: [usize; 3],
    /// Input channels C.
    pub channels: usize,
    pub indices: Vec<usize>,
    pub u_s: Vec<Vec<f32>>,
    pub u_v: Vec<Vec<f32>>,
    pub grid: ImmersedGrid,
}

impl SampleSet {
    /// With the exact surface displacement u_s as input.
    pub fn load(dir: &std::path::Path) -> Result<Self, DatasetError> {
        Self::load_inputs(dir, None)
    }

    /// With u_s, or with each sample's simulated camera view encoded by `observation`.
    pub fn load_inputs(dir: &std::path::Path, observation: Option<&ObservationSettings>) -> Result<Self, DatasetError> {
        let ds = Dataset::open(dir)?;
        let flagged: std::collections::BTreeSet<usize> =
            ds.manifest.samples.iter().filter(|s| s.flagged).map(|s| s.index).collect();
        let npz = umesh_core::dataset::read_grid_npz(dir, &ds.manifest)?;
        let grid = ImmersedGrid::from_npz(&npz)?;
        let shape = ds.manifest.padded_shape;
        let n = 3 * shape[0] * shape[1] * shape[2];
        let mut observer = match observation {
            Some(o) => {
                let surface = rest_surface(&npz)
                    .map_err(|e| DatasetError::Invalid { path: dir.join("grid.npz"), reason: e.into() })?;
                Some(
                    Observer::new(&grid, &surface, o.clone())
                        .map_err(|e| DatasetError::Invalid { path: dir.join("grid.npz"), reason: e.into() })?,
                )
            }
            None => None,
        };
        let (mut indices, mut u_s, mut u_v) = (Vec::new(), Vec::new(), Vec::new());
        for shard in &ds.manifest.shards {
            let (idx, s, v) = ds.load_shard(shard)?;
            let views = if observer.is_some() { ds.load_views(shard)? } else { Vec::new() };
            for (k, i) in idx.into_iter().enumerate() {
                if flagged.contains(&i) {
                    continue;
                }
                indices.push(i);
                match &mut observer {
                    Some(obs) => {
                        let mut x = Vec::new();
                        obs.encode(&views[k], &mut x);
                        u_s.push(x);
                    }
                    None => u_s.push(s[k * n..(k + 1) * n].to_vec()),
                }
                u_v.push(v[k * n..(k + 1) * n].to_vec());
            }
        }
        let channels = if observer.is_some() { umesh_core::observation::CHANNELS } else { 3 };
        Ok(Self { shape, channels, indices, u_s, u_v, grid })
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

/// The displacement of each grid node from a dense [3, X, Y, Z] field.
pub fn node_displacements(grid: &ImmersedGrid, field: &[f32]) -> Vec<nalgebra::Vector3<f64>> {
    let [x, y, z] = grid.padded_shape();
    let cells = x * y * z;
    (0..grid.node_count())
        .map(|n| {
            let d = grid.dense_index(n);
            nalgebra::Vector3::new(field[d] as f64, field[cells + d] as f64, field[2 * cells + d] as f64)
        })
        .collect()
}

/// Fresh simulated camera views of the training samples, one per epoch and sample: the
/// rest surface deformed by the sample's u_v, seen as the dataset's generation saw it (the
/// dataset's camera and view settings, a new random stream), encoded by the observation
/// operator. One SVK solve then gives many camera views, as a moving laparoscope would.
pub struct ViewRefresher {
    surface: TriMesh,
    camera: umesh_core::visible::Camera,
    view: umesh_core::observation::ViewSettings,
    observation: ObservationSettings,
    seed: u64,
}

impl ViewRefresher {
    /// For the dataset in `dir` (its manifest's camera and view settings).
    pub fn new(dir: &std::path::Path, observation: &ObservationSettings) -> Result<Self, DatasetError> {
        let manifest = umesh_core::dataset::Manifest::read(dir)?;
        let npz = umesh_core::dataset::read_grid_npz(dir, &manifest)?;
        let surface =
            rest_surface(&npz).map_err(|e| DatasetError::Invalid { path: dir.join("grid.npz"), reason: e.into() })?;
        let camera = manifest
            .config
            .visibility
            .camera
            .clone()
            .unwrap_or_else(|| umesh_core::visible::Camera::anterior(&surface));
        Ok(Self {
            surface,
            camera,
            view: manifest.config.view.clone(),
            observation: observation.clone(),
            seed: manifest.config.seed,
        })
    }

    /// Replace the inputs of samples `ids` (positions in `set`) by new views for `epoch`.
    /// Deterministic for (dataset seed, epoch, sample index); a sample whose view fails keeps
    /// its input. About `rest_fraction` of them get a view of the undeformed organ instead,
    /// whose target is zero (`rest[k]` true): every SVK sample moves 5-15 mm, and without rest
    /// views the network predicts millimetres of deformation for an organ that has not moved.
    /// Returns the number of new views.
    pub fn refresh(
        &self,
        set: &mut SampleSet,
        ids: &[usize],
        epoch: usize,
        rest_fraction: f64,
        rest: &mut [bool],
    ) -> Result<usize, umesh_core::Invalid> {
        use rayon::prelude::*;
        use umesh_core::rng::SplitMix64;
        let grid = &set.grid;
        Observer::new(grid, &self.surface, self.observation.clone())?;
        let fresh: Vec<(usize, bool, Option<Vec<f32>>)> = ids
            .par_iter()
            .map_init(
                || Observer::new(grid, &self.surface, self.observation.clone()),
                |obs, &k| {
                    let i = set.indices[k] as u64;
                    let mut rng = SplitMix64(
                        self.seed
                            ^ i.wrapping_mul(0x9E37_79B9_7F4A_7C15)
                            ^ (epoch as u64).wrapping_mul(0xD1B5_4A32_D192_ED03),
                    );
                    let at_rest = rng.next_f64() < rest_fraction;
                    let Ok(obs) = obs else { return (k, false, None) };
                    let deformed = if at_rest {
                        self.surface.clone()
                    } else {
                        umesh_core::loads::deform_mesh(grid, &self.surface, &node_displacements(grid, &set.u_v[k]))
                    };
                    match umesh_core::observation::simulated_view(&deformed, &self.camera, &self.view, &mut rng) {
                        Ok(points) if points.len() >= 10 => {
                            let mut out = Vec::new();
                            obs.encode(&points, &mut out);
                            (k, at_rest, Some(out))
                        }
                        _ => (k, false, None),
                    }
                },
            )
            .collect();
        let mut n = 0;
        for (k, at_rest, x) in fresh {
            rest[k] = false;
            if let Some(x) = x {
                set.u_s[k] = x;
                rest[k] = at_rest;
                n += 1;
            }
        }
        Ok(n)
    }
}
