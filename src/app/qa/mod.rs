//! Dataset QA browser: open a dataset made for the loaded organ, step through its samples,
//! see the probes, the network input u_s and the FE volume displacement, compare with the
//! active model's prediction (per-sample TRE), and flag samples: the flags are written back
//! into the manifest, and training skips flagged samples.

pub mod panel;
pub mod scene;
pub mod view;

use crate::app::state::{ActiveModel, Organ, QaTruth, UiMessages};
use anyhow::Context;
use bevy::prelude::*;
use bevy::tasks::{AsyncComputeTaskPool, Task, futures::check_ready};
use nalgebra::Vector3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use umesh_core::dataset::{DatasetContext, Manifest, SampleRecord};
use umesh_core::mesh::TriMesh;
use umesh_core::npz::{ArrayData, Npz};
use umesh_core::register::{RegistrationContext, displacement_at, virtual_markers};
use umesh_net::inference::Predictor;

/// An opened dataset: its manifest and the registration context of its grid (rebuilt from
/// the loaded organ and checked against the dataset's grid hash).
pub struct QaDataset {
    pub dir: PathBuf,
    pub ctx: RegistrationContext,
    /// Markers for the per-sample TRE (fixed: every sample uses the same ones).
    pub markers: Vec<umesh_core::grid::Embedding>,
}

/// One sample, ready to show.
pub struct QaSample {
    pub index: usize,
    pub probes_mm: Vec<Vector3<f64>>,
    pub forces_n: Vec<Vector3<f64>>,
    /// Visible nodes with a nonzero input displacement: (node position, u_s) in mm.
    pub u_s_arrows: Vec<(Vector3<f64>, Vector3<f64>)>,
    pub truth_surface: Arc<TriMesh>,
    pub truth_magnitude_mm: Vec<f32>,
    pub truth_structures: Vec<(TriMesh, [u8; 3])>,
    pub max_mm: f32,
    /// With a model: the predicted surface, its error per vertex (mm) and the sample's TRE.
    pub predicted: Option<(TriMesh, Vec<f32>, Vec<(TriMesh, [u8; 3])>)>,
    pub tre_mm: Option<f64>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum QaSort {
    #[default]
    Index,
    LargestDisplacement,
    MostIterations,
    LargestError,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum QaFilter {
    #[default]
    Accepted,
    Flagged,
    Rejected,
    All,
}

#[derive(Resource, Default)]
pub struct Qa {
    pub dataset: Option<Arc<QaDataset>>,
    pub manifest: Option<Manifest>,
    pub path_text: String,
    pub sort: QaSort,
    pub filter: QaFilter,
    /// Manifest positions in display order.
    pub order: Vec<usize>,
    pub cursor: usize,
    pub sample: Option<Arc<QaSample>>,
    pub predictor: Option<Arc<Mutex<Predictor>>>,
    /// Per-sample TRE (mm) by sample index, from "evaluate all" or browsing.
    pub tre: BTreeMap<usize, f64>,
    pub generation: u64,
    pub show_u_s: bool,
    pub show_prediction: bool,
    opening: Option<Task<anyhow::Result<(QaDataset, Manifest, Option<Predictor>)>>>,
    loading: Option<(usize, Task<anyhow::Result<QaSample>>)>,
    evaluating: Option<Task<anyhow::Result<BTreeMap<usize, f64>>>>,
    requested: Option<usize>,
}

impl Qa {
    pub fn busy(&self) -> Option<&'static str> {
        if self.opening.is_some() {
            Some("opening the dataset")
        } else if self.evaluating.is_some() {
            Some("evaluating every sample")
        } else if self.loading.is_some() {
            Some("loading the sample")
        } else {
            None
        }
    }

    /// Recompute the display order after a sort, a filter or a flag change.
    pub fn reorder(&mut self) {
        let Some(m) = &self.manifest else { return };
        let current = self.order.get(self.cursor).copied();
        let mut v: Vec<usize> = (0..m.samples.len())
            .filter(|&i| {
                let s = &m.samples[i];
                match self.filter {
                    QaFilter::Accepted => s.accepted && !s.flagged,
                    QaFilter::Flagged => s.flagged,
                    QaFilter::Rejected => !s.accepted,
                    QaFilter::All => true,
                }
            })
            .collect();
        let key = |i: &usize| -> f64 {
            let s = &m.samples[*i];
            match self.sort {
                QaSort::Index => s.index as f64,
                QaSort::LargestDisplacement => -s.max_displacement_mm,
                QaSort::MostIterations => -(s.newton_iterations as f64),
                QaSort::LargestError => -self.tre.get(&s.index).copied().unwrap_or(f64::NEG_INFINITY),
            }
        };
        v.sort_by(|a, b| key(a).total_cmp(&key(b)));
        self.cursor = current.and_then(|c| v.iter().position(|&i| i == c)).unwrap_or(0);
        self.order = v;
        self.request_current();
    }

    pub fn current_record(&self) -> Option<&SampleRecord> {
        self.manifest.as_ref()?.samples.get(*self.order.get(self.cursor)?)
    }

    pub fn step(&mut self, delta: i64) {
        if self.order.is_empty() {
            return;
        }
        self.cursor = (self.cursor as i64 + delta).clamp(0, self.order.len() as i64 - 1) as usize;
        self.request_current();
    }

    fn request_current(&mut self) {
        self.requested = self.current_record().filter(|r| r.accepted).map(|r| r.index);
    }

    /// Flip the flag of the current sample and write the manifest (atomically).
    pub fn toggle_flag(&mut self) -> anyhow::Result<String> {
        let (Some(ds), Some(pos)) = (&self.dataset, self.order.get(self.cursor).copied()) else {
            anyhow::bail!("no sample")
        };
        let dir = ds.dir.clone();
        let m = self.manifest.as_mut().context("no dataset")?;
        // Re-read first: another process (a CLI run) may have changed the manifest since.
        let mut fresh = Manifest::read(&dir)?;
        let index = m.samples[pos].index;
        let s = fresh
            .samples
            .iter_mut()
            .find(|s| s.index == index)
            .with_context(|| format!("sample {index} is no longer in the manifest"))?;
        s.flagged = !s.flagged;
        let flagged = s.flagged;
        fresh.write(&dir)?;
        *m = fresh;
        let msg = format!(
            "sample {index} {} in {}",
            if flagged { "flagged (training skips it)" } else { "unflagged" },
            dir.display()
        );
        self.reorder();
        Ok(msg)
    }

    pub fn open(&mut self, dir: PathBuf, organ: &Organ, model: &ActiveModel) -> anyhow::Result<()> {
        let data = organ.data.clone().context("load the organ the dataset was made from first")?;
        let model = model.clone();
        self.opening =
            Some(AsyncComputeTaskPool::get().spawn(async move { open_dataset(&dir, &data.seg, Some(&model)) }));
        Ok(())
    }

    pub fn evaluate_all(&mut self) {
        let (Some(ds), Some(m), Some(p)) = (self.dataset.clone(), self.manifest.clone(), self.predictor.clone()) else {
            return;
        };
        self.evaluating = Some(AsyncComputeTaskPool::get().spawn(async move { evaluate_dataset(&ds, &m, &p) }));
    }
}

/// Open a dataset for the segmentation `seg`; with `model`, also load the active model,
/// which must fit the dataset's grid.
pub fn open_dataset(
    dir: &Path,
    seg: &umesh_core::segmentation::Segmentation,
    model: Option<&ActiveModel>,
) -> anyhow::Result<(QaDataset, Manifest, Option<Predictor>)> {
    let ds = umesh_core::dataset::Dataset::open(dir)?;
    let m = ds.manifest;
    let seg_hash = umesh_core::dataset::segmentation_hash(seg);
    if m.segmentation_hash != seg_hash {
        anyhow::bail!(
            "{}: made from another segmentation ({}); open that segmentation first (File > Open)",
            dir.display(),
            m.segmentation
        );
    }
    let dctx = DatasetContext::prepare(seg, &m.config, &umesh_core::Cancel::new())?;
    if dctx.grid_hash() != m.grid_hash {
        anyhow::bail!(
            "{}: made on another grid than this program builds from its settings (grid hash differs)",
            dir.display()
        );
    }
    let ctx = RegistrationContext::new(dctx, seg)?;
    let markers = virtual_markers(&ctx, 10, 0).iter().filter_map(|p| ctx.grid.embed(p)).collect();
    let predictor = match model {
        Some(am) => {
            let p =
                Predictor::load_checkpoint(&am.dir, &am.checkpoint).with_context(|| am.dir.display().to_string())?;
            p.info.check_grid(&m.grid_hash, m.padded_shape).with_context(|| format!("model {}", am.dir.display()))?;
            Some(p)
        }
        None => None,
    };
    Ok((QaDataset { dir: dir.into(), ctx, markers }, m, predictor))
}

fn f32s(npz: &Npz, name: &str, path: &Path) -> anyhow::Result<Vec<f32>> {
    match &npz.get(name)?.data {
        ArrayData::F32(v) => Ok(v.clone()),
        _ => Err(anyhow::anyhow!("{}: '{name}' is not float32", path.display())),
    }
}

/// (u_s, u_v, probes, forces) of sample `index` and its position among its shard's samples.
#[allow(clippy::type_complexity)]
fn read_sample(
    ds: &QaDataset,
    m: &Manifest,
    index: usize,
) -> anyhow::Result<(Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>, usize)> {
    let rec = m.samples.iter().find(|s| s.index == index).with_context(|| format!("no sample {index}"))?;
    let path = ds.dir.join(&rec.shard);
    let npz = Npz::read(&path)?;
    let idx: Vec<i64> = match &npz.get("index")?.data {
        ArrayData::I64(v) => v.clone(),
        _ => anyhow::bail!("{}: 'index' is not int64", path.display()),
    };
    let k = idx
        .iter()
        .position(|&i| i as usize == index)
        .with_context(|| format!("{}: sample {index} missing", path.display()))?;
    let a = idx.len();
    let (u_s, u_v, pr, fo) = (
        f32s(&npz, "u_s", &path)?,
        f32s(&npz, "u_v", &path)?,
        f32s(&npz, "probes_mm", &path)?,
        f32s(&npz, "forces_n", &path)?,
    );
    let n = u_s.len() / a.max(1);
    let p = pr.len() / a.max(1);
    Ok((
        u_s[k * n..(k + 1) * n].to_vec(),
        u_v[k * n..(k + 1) * n].to_vec(),
        pr[k * p..(k + 1) * p].to_vec(),
        fo[k * p..(k + 1) * p].to_vec(),
        k,
    ))
}

fn sample_tre(ds: &QaDataset, pred: &[f32], truth: &[f32]) -> f64 {
    let e: Vec<f64> = ds
        .markers
        .iter()
        .map(|e| (displacement_at(&ds.ctx.grid, pred, e) - displacement_at(&ds.ctx.grid, truth, e)).norm())
        .collect();
    e.iter().sum::<f64>() / e.len().max(1) as f64
}

/// The network input of sample `index`, the `k`-th of its shard: its stored camera view
/// encoded, or its u_s.
fn model_input(
    ds: &QaDataset,
    m: &Manifest,
    index: usize,
    k: usize,
    p: &Predictor,
    u_s: &[f32],
) -> anyhow::Result<Vec<f32>> {
    let mut enc = umesh_net::inference::InputEncoder::new(&p.info, &ds.ctx.grid, &ds.ctx.surface)?;
    if !enc.takes_points() {
        return enc.input(None, Some(u_s)).map_err(anyhow::Error::from);
    }
    let rec = m.samples.iter().find(|s| s.index == index).with_context(|| format!("no sample {index}"))?;
    let shard = m.shards.iter().find(|s| s.file == rec.shard).with_context(|| format!("no shard {}", rec.shard))?;
    let data = umesh_core::dataset::Dataset { dir: ds.dir.clone(), manifest: m.clone() };
    // The views come in the order of the shard's sample indices, as read_sample's `k`.
    let views = data.load_views(shard)?;
    let view = views.get(k).with_context(|| format!("{}: no camera view for sample {index}", shard.file))?;
    enc.input(Some(view), None).map_err(anyhow::Error::from)
}

pub fn load_sample(
    ds: &QaDataset,
    m: &Manifest,
    index: usize,
    predictor: Option<&Mutex<Predictor>>,
) -> anyhow::Result<QaSample> {
    let (u_s, u_v, pr, fo, k) = read_sample(ds, m, index)?;
    let ctx = &ds.ctx;
    let g = &ctx.grid;
    let v3 = |v: &[f32]| -> Vec<Vector3<f64>> {
        v.chunks_exact(3).map(|c| Vector3::new(c[0] as f64, c[1] as f64, c[2] as f64)).collect()
    };
    let cells = u_s.len() / 3;
    let u_s_arrows = ctx
        .visible_nodes
        .iter()
        .filter_map(|&n| {
            let d = g.dense_index(n);
            let u = Vector3::new(u_s[d] as f64, u_s[cells + d] as f64, u_s[2 * cells + d] as f64);
            (u.norm() > 1e-3).then(|| (g.node_position(n), u))
        })
        .collect();
    let truth_surface = ctx.deformed_surface(&u_v);
    let truth_magnitude_mm: Vec<f32> =
        truth_surface.positions.iter().zip(&ctx.surface.positions).map(|(a, b)| (a - b).norm() as f32).collect();
    let max_mm = truth_magnitude_mm.iter().copied().fold(0.0, f32::max);
    let truth_structures = ctx.structures.iter().map(|s| (ctx.deformed_structure(s, &u_v), s.color)).collect();
    let (predicted, tre_mm) = match predictor {
        Some(p) => {
            let mut p = p.lock().map_err(|_| anyhow::anyhow!("the model is poisoned"))?;
            let x = model_input(ds, m, index, k, &p, &u_s)?;
            let pred = p.predict(&x, g.padded_shape())?.to_vec();
            let surface = ctx.deformed_surface(&pred);
            let err: Vec<f32> =
                surface.positions.iter().zip(&truth_surface.positions).map(|(a, b)| (a - b).norm() as f32).collect();
            let structures = ctx.structures.iter().map(|s| (ctx.deformed_structure(s, &pred), s.color)).collect();
            let tre = sample_tre(ds, &pred, &u_v);
            (Some((surface, err, structures)), Some(tre))
        }
        None => (None, None),
    };
    Ok(QaSample {
        index,
        probes_mm: v3(&pr),
        forces_n: v3(&fo),
        u_s_arrows,
        truth_surface: Arc::new(truth_surface),
        truth_magnitude_mm,
        truth_structures,
        max_mm,
        predicted,
        tre_mm,
    })
}

/// The network's TRE on every accepted sample (by sample index).
pub fn evaluate_dataset(ds: &QaDataset, m: &Manifest, p: &Mutex<Predictor>) -> anyhow::Result<BTreeMap<usize, f64>> {
    let mut out = BTreeMap::new();
    let mut p = p.lock().map_err(|_| anyhow::anyhow!("the model is poisoned"))?;
    let shape = ds.ctx.grid.padded_shape();
    let data = umesh_core::dataset::Dataset { dir: ds.dir.clone(), manifest: m.clone() };
    let mut enc = umesh_net::inference::InputEncoder::new(&p.info, &ds.ctx.grid, &ds.ctx.surface)?;
    for shard in &m.shards {
        let (idx, u_s, u_v) = data.load_shard(shard)?;
        let views = if enc.takes_points() { data.load_views(shard)? } else { Vec::new() };
        let n = u_s.len() / idx.len().max(1);
        for (k, &i) in idx.iter().enumerate() {
            let x = enc.input(views.get(k).map(|v| v.as_slice()), Some(&u_s[k * n..(k + 1) * n]))?;
            let pred = p.predict(&x, shape)?.to_vec();
            out.insert(i, sample_tre(ds, &pred, &u_v[k * n..(k + 1) * n]));
        }
    }
    Ok(out)
}

/// Poll the QA tasks; start loading the requested sample.
fn poll_qa(mut qa: ResMut<Qa>, mut messages: ResMut<UiMessages>) {
    if let Some(t) = &mut qa.opening
        && let Some(r) = check_ready(t)
    {
        qa.opening = None;
        match r {
            Ok((ds, m, p)) => {
                messages.info(format!(
                    "dataset {}: {} samples, {} accepted, {} flagged{}",
                    ds.dir.display(),
                    m.samples.len(),
                    m.accepted().count(),
                    m.samples.iter().filter(|s| s.flagged).count(),
                    if p.is_some() { "; model loaded for comparison" } else { "" }
                ));
                qa.dataset = Some(Arc::new(ds));
                qa.manifest = Some(m);
                qa.predictor = p.map(|p| Arc::new(Mutex::new(p)));
                qa.tre.clear();
                qa.sample = None;
                qa.generation += 1;
                qa.cursor = 0;
                qa.order.clear();
                qa.reorder();
            }
            Err(e) => messages.error(format!("{e:#}")),
        }
    }
    if let Some(t) = &mut qa.evaluating
        && let Some(r) = check_ready(t)
    {
        qa.evaluating = None;
        match r {
            Ok(tre) => {
                let mean = tre.values().sum::<f64>() / tre.len().max(1) as f64;
                messages.info(format!("evaluated {} samples: TRE {mean:.2} mm mean", tre.len()));
                qa.tre = tre;
                qa.reorder();
            }
            Err(e) => messages.error(format!("evaluation failed: {e:#}")),
        }
    }
    if let Some((_, t)) = &mut qa.loading
        && let Some(r) = check_ready(t)
    {
        qa.loading = None;
        match r {
            Ok(s) => {
                if let Some(t) = s.tre_mm {
                    qa.tre.insert(s.index, t);
                }
                qa.sample = Some(Arc::new(s));
                qa.generation += 1;
            }
            Err(e) => messages.error(format!("sample: {e:#}")),
        }
    }
    if qa.loading.is_none()
        && let Some(index) = qa.requested.take()
        && qa.sample.as_ref().is_none_or(|s| s.index != index)
        && let (Some(ds), Some(m)) = (qa.dataset.clone(), qa.manifest.clone())
    {
        let p = qa.predictor.clone();
        qa.loading =
            Some((index, AsyncComputeTaskPool::get().spawn(async move { load_sample(&ds, &m, index, p.as_deref()) })));
    }
}

pub struct QaPlugin;

impl Plugin for QaPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<Qa>().init_resource::<QaTruth>().add_systems(Update, (poll_qa, publish_truth).chain());
    }
}

/// Shares the shown sample's truth surface with the views that outline it.
fn publish_truth(qa: Res<Qa>, mut truth: ResMut<QaTruth>) {
    if truth.generation != qa.generation {
        truth.surface = qa.sample.as_ref().map(|s| s.truth_surface.clone());
        truth.generation = qa.generation;
    }
}
