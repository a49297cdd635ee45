//! The patient folder: `patient.json` (inputs and their hashes, every setting, stage status and
//! timings) and the figures read back from a finished folder.

use std::path::{Path, PathBuf};
use umesh_core::dataset::{DatasetConfig, DatasetStats, fnv_hex, run_stats};
use umesh_core::register::correction::CorrectionChoice;
use umesh_core::register::pipeline::Summary;
use umesh_core::segmentation::Segmentation;
use umesh_core::synth::{SynthReport, SynthSettings};
use umesh_net::TrainSettings;
use umesh_net::training::EpochMetrics;
use umesh_net::{NetError, eval};

pub const FORMAT: &str = "umesh-patient";
pub const FORMAT_VERSION: u32 = 1;

/// Everything `prepare` does, chosen before it starts (the CLI and the app build this).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PrepareSettings {
    pub dataset: DatasetConfig,
    /// How the fixed region was chosen, in words.
    pub fixed_description: String,
    pub train: TrainSettings,
    /// Markers per validation sample for the TRE.
    pub eval_markers: usize,
    /// The registration check's synthetic recording.
    pub check: SynthSettings,
    /// The whole job's time budget (s; 0: none): training stops before an epoch that would
    /// leave too little of it for the stages after it.
    #[serde(default)]
    pub time_budget_s: f64,
    /// The most grid nodes the job trains (0: the cell size as asked): a larger organ's cells
    /// grow until its grid fits (`grid_budget`).
    #[serde(default)]
    pub max_grid_nodes: usize,
    /// The cell size the job uses and why, in words.
    #[serde(default)]
    pub grid_description: String,
    /// The most triangles of the organ surface registration judges and draws every frame (0:
    /// the surface step as asked): a larger surface is marched at a coarser step
    /// (`surface_budget`).
    #[serde(default)]
    pub max_surface_triangles: usize,
    /// The surface step the job uses and why, in words.
    #[serde(default)]
    pub surface_description: String,
    /// Where the network's training starts (`prior`): resolved into `train.prior` when the job
    /// starts.
    #[serde(default)]
    pub prior: Prior,
    /// The training's starting weights and why, in words.
    #[serde(default)]
    pub prior_description: String,
}

impl PrepareSettings {
    /// The paper's protocol with the `cpu` network: 1000 samples, 20 epochs, a 20-frame check.
    pub fn paper(dataset: DatasetConfig, fixed_description: String) -> Self {
        Self {
            dataset,
            fixed_description,
            train: TrainSettings { epochs: 20, ..TrainSettings::default() },
            eval_markers: 10,
            check: SynthSettings::default(),
            time_budget_s: 0.0,
            max_grid_nodes: MAX_GRID_NODES,
            grid_description: String::new(),
            max_surface_triangles: MAX_SURFACE_TRIANGLES,
            surface_description: String::new(),
            prior: Prior::Bundled,
            prior_description: String::new(),
        }
    }
}

/// Where a patient's training starts (`resolve_prior` makes it the training's weights).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Prior {
    /// The bundled model when its network and input are the job's (else random weights).
    Bundled,
    /// Random weights (and folders from before priors).
    #[default]
    None,
    /// A model folder of another organ.
    Model(PathBuf),
}

impl Prior {
    /// `bundled`, `none` or a model folder.
    pub fn parse(s: &str) -> Self {
        match s {
            "bundled" => Self::Bundled,
            "none" => Self::None,
            p => Self::Model(PathBuf::from(p)),
        }
    }
}

/// The most grid nodes a patient's default job affords in its hour on 2 cores. Measured (Intel
/// Xeon, 2 cores): the CT liver's 4983 nodes (padded grid 32 x 24 x 24) train an epoch in about
/// 100 s, all 20 within the hour; the 2.15 l SOFA liver at 7 mm (9414 nodes, 40 x 32 x 32)
/// takes about 300 s an epoch, five or six of the 20 in what its dataset leaves. The bundled
/// phantom (5932) stays at its 7 mm. The paper's padded grid was 32 x 40 x 16.
pub const MAX_GRID_NODES: usize = 6000;

/// The most organ-surface triangles a patient's default job keeps. A frame's confidence and
/// overlay work on the whole surface. Measured (Intel Xeon, 2 cores): the CT liver's 20624
/// triangles cost 4.8 ms of confidence and 2.4 ms of overlay a frame; the 2.15 l SOFA liver
/// voxelised at 1 mm and marched every 2 voxels (242984 triangles) 24.5 and 13.2 ms, and its
/// undoubted frames took 50-60 ms. The bundled phantom's model keeps its own surface (68136).
pub const MAX_SURFACE_TRIANGLES: usize = 50_000;

/// One input file and the hash of its bytes.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InputFile {
    pub path: String,
    pub bytes: u64,
    pub hash: String,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    Dataset,
    Train,
    Eval,
    Recording,
    Register,
    Report,
}

impl Stage {
    pub const ALL: [Stage; 6] =
        [Stage::Dataset, Stage::Train, Stage::Eval, Stage::Recording, Stage::Register, Stage::Report];
    pub fn name(self) -> &'static str {
        match self {
            Stage::Dataset => "dataset",
            Stage::Train => "training",
            Stage::Eval => "evaluation",
            Stage::Recording => "check recording",
            Stage::Register => "registration check",
            Stage::Report => "report",
        }
    }
}

#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StageRecord {
    pub done: bool,
    /// Wall time spent in this stage, summed over runs (s).
    pub seconds: f64,
    /// What the stage says of how it ended (training stopped early by its time budget).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// `patient.json`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Patient {
    pub format: String,
    pub format_version: u32,
    pub program_version: String,
    pub inputs: Vec<InputFile>,
    pub segmentation_hash: String,
    pub organ_labels: Vec<String>,
    pub structures: Vec<String>,
    /// The hash of `segmentation.nii.gz` as read back with these names (the file keeps its
    /// affine in single precision, so it is not `segmentation_hash`); absent in older folders.
    #[serde(default)]
    pub stored_segmentation_hash: Option<String>,
    pub settings: PrepareSettings,
    pub stages: std::collections::BTreeMap<Stage, StageRecord>,
}

impl Patient {
    pub fn read(dir: &Path) -> Result<Self, NetError> {
        let p = dir.join("patient.json");
        let text = std::fs::read_to_string(&p).map_err(|e| NetError::Io { path: p.to_path_buf(), source: e })?;
        let v: Patient = serde_json::from_str(&text)
            .map_err(|e| NetError::Invalid(format!("{}: not a umesh patient folder: {e}", p.display())))?;
        if v.format != FORMAT || v.format_version != FORMAT_VERSION {
            return Err(NetError::Invalid(format!(
                "{}: format {} v{} is not {FORMAT} v{FORMAT_VERSION}",
                p.display(),
                v.format,
                v.format_version
            )));
        }
        Ok(v)
    }
    pub(super) fn write(&self, dir: &Path) -> Result<(), NetError> {
        let p = dir.join("patient.json");
        let text = serde_json::to_string_pretty(self).map_err(|e| NetError::Invalid(e.to_string()))?;
        umesh_core::write_atomic(&p, text.as_bytes()).map_err(|e| NetError::Io { path: p.to_path_buf(), source: e })
    }
    pub fn done(&self, s: Stage) -> bool {
        self.stages.get(&s).is_some_and(|r| r.done)
    }
    /// The segmentation the job used, with its organ and structure labels.
    pub fn segmentation(&self, dir: &Path) -> Result<Segmentation, NetError> {
        let seg = self.read_segmentation(dir)?;
        // Labels swapped between names, or voxels edited: not the segmentation the model learnt.
        let hash = umesh_core::dataset::segmentation_hash(&seg);
        if let Some(stored) = &self.stored_segmentation_hash
            && hash != *stored
        {
            return Err(NetError::Invalid(format!(
                "{}: not the segmentation this patient was prepared from (hash {hash}, patient.json says {stored}); prepare the patient again",
                seg.source.display()
            )));
        }
        Ok(seg)
    }

    /// `segmentation.nii.gz` with the labels named in `patient.json`, unchecked against its hash.
    pub(super) fn read_segmentation(&self, dir: &Path) -> Result<Segmentation, NetError> {
        let path = dir.join("segmentation.nii.gz");
        let volume = umesh_core::nifti_io::read_volume(&path, &Default::default())
            .map_err(|e| NetError::Invalid(e.to_string()))?;
        // A name the segmentation does not have (renamed in patient.json or in the file) would
        // drop that structure from every overlay without a word.
        let missing: Vec<&String> = self
            .organ_labels
            .iter()
            .chain(&self.structures)
            .filter(|n| !volume.label_names.iter().any(|(_, v)| v == *n))
            .collect();
        if !missing.is_empty() {
            return Err(NetError::Invalid(format!(
                "{}: names {missing:?} in patient.json are not labels of {} (renamed?); prepare the patient again",
                dir.display(),
                path.display()
            )));
        }
        let by_name = |names: &[String]| -> Vec<i64> {
            names.iter().filter_map(|n| volume.label_names.iter().find(|(_, v)| *v == n).map(|(l, _)| *l)).collect()
        };
        let seg = Segmentation {
            source: path.clone(),
            organ_labels: by_name(&self.organ_labels),
            structure_labels: by_name(&self.structures),
            volume,
        };
        seg.validate().map_err(|e| NetError::Invalid(e.to_string()))?;
        Ok(seg)
    }
}

pub fn model_dir(patient: &Path) -> PathBuf {
    patient.join("model")
}

/// The scan the segmentation was made from, when `umesh prepare --ct` was given one (the app
/// shows it under the model).
pub fn ct_path(patient: &Path) -> PathBuf {
    patient.join("ct.nii.gz")
}

/// What a finished (or resumed) job reports.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PrepareReport {
    pub out: PathBuf,
    /// The cell size the job used and why (`PrepareSettings::grid_description`).
    pub grid: String,
    /// The surface step the job used and why (`PrepareSettings::surface_description`).
    pub surface: String,
    /// Where training started and why (`PrepareSettings::prior_description`).
    pub prior: String,
    pub stages: Vec<(Stage, f64, bool)>,
    pub dataset: DatasetStats,
    pub dataset_samples_per_minute: Option<f64>,
    pub final_epoch: Option<EpochMetrics>,
    /// Why training ended before its epochs (the time budget), if it did.
    pub training_stopped_early: Option<String>,
    pub eval: eval::EvalReport,
    pub check_recording: Option<SynthReport>,
    pub check: CheckReport,
    /// Ready for the operating room, or what is wrong and what to do.
    pub verdict: Verdict,
    pub seconds: f64,
}

/// The verdict on a prepared patient (`patient::judge`).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Verdict {
    pub ready: bool,
    /// One sentence each: what is wrong and what to do.
    pub problems: Vec<String>,
    /// Things to know that do not stop the patient being ready.
    pub notes: Vec<String>,
}

impl Verdict {
    /// "ready" or "not ready: ..." in one line.
    pub fn line(&self) -> String {
        if self.ready { "ready".into() } else { format!("not ready: {}", self.problems.join(" ")) }
    }
}

/// The registration check on the synthetic recording (last frame and mean over frames).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CheckReport {
    pub summary: SummaryRecord,
    pub last_frame_tre_mm: Option<f64>,
    pub last_frame_tre_rigid_mm: Option<f64>,
    pub last_frame_marker_displacement_mm: Option<f64>,
    pub log: Vec<String>,
    /// Why the check could not be made or registered: the job still ends with its model, and
    /// the report and the command say this instead of the check's figures.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
    /// The correction form chosen on the check (the figures above are that form's); None in
    /// folders from before and when the recording has too few frames with truth.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub correction: Option<CorrectionChoice>,
}

impl CheckReport {
    /// A check that did not run, with the reason.
    pub fn not_run(reason: String) -> Self {
        Self {
            summary: SummaryRecord::default(),
            last_frame_tre_mm: None,
            last_frame_tre_rigid_mm: None,
            last_frame_marker_displacement_mm: None,
            log: Vec::new(),
            warning: Some(reason),
            correction: None,
        }
    }
}

/// `Summary` in a form that can be read back.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SummaryRecord {
    pub frames: usize,
    pub skipped: usize,
    pub frame_ms_median: f64,
    pub tre_mean_mm: Option<f64>,
    pub tre_rigid_mean_mm: Option<f64>,
    pub marker_displacement_mean_mm: Option<f64>,
}

impl From<&Summary> for SummaryRecord {
    fn from(s: &Summary) -> Self {
        Self {
            frames: s.frames,
            skipped: s.skipped,
            frame_ms_median: s.frame_ms_median,
            tre_mean_mm: s.tre_mean_mm,
            tre_rigid_mean_mm: s.tre_rigid_mean_mm,
            marker_displacement_mean_mm: s.marker_displacement_mean_mm,
        }
    }
}

/// Hash of each input file (a folder: each file in it that the segmentation used).
pub fn hash_inputs(files: &[PathBuf]) -> Result<Vec<InputFile>, NetError> {
    files
        .iter()
        .map(|p| {
            let bytes = std::fs::read(p).map_err(|e| NetError::Io { path: p.to_path_buf(), source: e })?;
            Ok(InputFile { path: p.display().to_string(), bytes: bytes.len() as u64, hash: fnv_hex(&bytes) })
        })
        .collect()
}

/// Whether `settings` are the `stored` ones read back from `patient.json`: compared as stored,
/// since JSON's float parsing is not always exact (a camera coordinate with decimals came back
/// one ulp off, and a folder refused to resume with two identical hashes in its message).
/// The time budget is not compared: a resumed job may be given another; nor the prior.
pub fn same_as_stored(stored: &PrepareSettings, settings: &PrepareSettings) -> Result<bool, NetError> {
    let text = serde_json::to_string(settings).map_err(|e| NetError::Invalid(e.to_string()))?;
    let now: PrepareSettings = serde_json::from_str(&text).map_err(|e| NetError::Invalid(e.to_string()))?;
    // The grid's and the surface's limits and descriptions say how the cell size and the
    // surface step were chosen; those themselves are compared (a folder from before the
    // limits has none of these).
    Ok(PrepareSettings {
        time_budget_s: now.time_budget_s,
        max_grid_nodes: now.max_grid_nodes,
        grid_description: now.grid_description.clone(),
        max_surface_triangles: now.max_surface_triangles,
        surface_description: now.surface_description.clone(),
        // Where training starts matters only before its first epoch (a resumed training
        // continues from its own last weights), and its path depends on the working directory.
        prior: now.prior.clone(),
        prior_description: now.prior_description.clone(),
        train: TrainSettings { prior: now.train.prior.clone(), ..stored.train.clone() },
        ..stored.clone()
    } == now)
}

/// The settings that differ, as `path: stored -> now` (at most 6), for a refusal that names them.
pub fn settings_differences(stored: &PrepareSettings, now: &PrepareSettings) -> Vec<String> {
    fn walk(path: &str, a: &serde_json::Value, b: &serde_json::Value, out: &mut Vec<String>) {
        match (a, b) {
            (serde_json::Value::Object(x), serde_json::Value::Object(y)) => {
                let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
                for k in keys {
                    let null = serde_json::Value::Null;
                    walk(
                        &format!("{path}{}{k}", if path.is_empty() { "" } else { "." }),
                        x.get(k).unwrap_or(&null),
                        y.get(k).unwrap_or(&null),
                        out,
                    );
                }
            }
            _ if a != b => out.push(format!("{path}: {a} -> {b}")),
            _ => {}
        }
    }
    let (Ok(a), Ok(b)) = (serde_json::to_value(stored), serde_json::to_value(now)) else { return Vec::new() };
    let mut out = Vec::new();
    walk("", &a, &b, &mut out);
    out.truncate(6);
    out
}

pub fn read_metrics(model: &Path) -> Vec<EpochMetrics> {
    std::fs::read_to_string(model.join("metrics.jsonl"))
        .map(|t| t.lines().filter_map(|l| serde_json::from_str(l).ok()).collect())
        .unwrap_or_default()
}

pub(super) fn write_json<T: serde::Serialize>(path: &Path, v: &T) -> Result<(), NetError> {
    let text = serde_json::to_string_pretty(v).map_err(|e| NetError::Invalid(e.to_string()))?;
    umesh_core::write_atomic(path, text.as_bytes()).map_err(|e| NetError::Io { path: path.to_path_buf(), source: e })
}

pub(super) fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, NetError> {
    let text = std::fs::read_to_string(path).map_err(|e| NetError::Io { path: path.to_path_buf(), source: e })?;
    serde_json::from_str(&text).map_err(|e| NetError::Invalid(format!("{}: {e}", path.display())))
}

/// What a patient folder holds so far, for the app's jobs view (the report's figures): every
/// part after patient.json is optional, as an interrupted job has written only some.
#[derive(Clone, Debug)]
pub struct PatientFigures {
    pub dir: PathBuf,
    pub patient: Patient,
    pub dataset: Option<DatasetStats>,
    /// Per accepted sample: (achieved mean nodal displacement, its target) in mm; no target
    /// for uncalibrated datasets.
    pub mean_vs_target_mm: Vec<(f64, Option<f64>)>,
    pub metrics: Vec<EpochMetrics>,
    pub eval: Option<eval::EvalReport>,
    pub check: Option<CheckReport>,
    pub has_model: bool,
}

pub fn read_figures(dir: &Path) -> Result<PatientFigures, NetError> {
    let patient = Patient::read(dir)?;
    let ds = dir.join("dataset");
    let dataset = run_stats(&ds).ok();
    let mean_vs_target_mm = umesh_core::dataset::Manifest::read(&ds)
        .map(|m| m.accepted().map(|s| (s.mean_displacement_mm, s.target_displacement_mm)).collect())
        .unwrap_or_default();
    let model = model_dir(dir);
    Ok(PatientFigures {
        dir: dir.to_path_buf(),
        dataset,
        mean_vs_target_mm,
        metrics: read_metrics(&model),
        eval: read_json(&dir.join("eval.json")).ok(),
        check: read_json(&dir.join("check").join("register.json")).ok(),
        has_model: model.join("model.json").exists() && model.join("model.safetensors").exists(),
        patient,
    })
}

/// A model folder inside a patient folder is that patient's: only its own dataset trains it
/// (another dataset's model there would be registered as the patient's). Err names both paths.
pub fn check_model_out(out: &Path, dataset: &Path) -> Result<(), NetError> {
    let Some(patient) = out.parent().filter(|p| p.join("patient.json").is_file()) else { return Ok(()) };
    let own = patient.join("dataset");
    let same = matches!((dataset.canonicalize(), own.canonicalize()), (Ok(x), Ok(y)) if x == y);
    if same {
        return Ok(());
    }
    Err(NetError::Invalid(format!(
        "{}: the model of the patient {}, trained only on its own dataset ({}), not on {}; choose another output folder",
        out.display(),
        patient.display(),
        own.display(),
        dataset.display()
    )))
}
