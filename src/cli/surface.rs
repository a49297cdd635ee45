use super::input::{InputArgs, LoadInput};
use anyhow::{Context, Result};
use std::path::PathBuf;
use umesh_core::mesh_io::write_mesh;
use umesh_core::surface::{SurfaceSettings, extract_surface};

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub input: InputArgs,
    /// Labels to extract (default: the organ labels together, then each structure label).
    #[arg(long, value_delimiter = ',')]
    pub label: Vec<i64>,
    /// Output folder; files are named after the labels.
    #[arg(long, default_value = "out/surfaces")]
    pub out: PathBuf,
    /// Mesh format: obj, ply or stl.
    #[arg(long, default_value = "obj")]
    pub format: String,
    /// Use every n-th voxel (lighter meshes).
    #[arg(long, default_value_t = 1)]
    pub step: usize,
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    anyhow::ensure!(matches!(a.format.as_str(), "obj" | "ply" | "stl"), "--format must be obj, ply or stl");
    let seg = a.input.load()?;
    let mut jobs: Vec<(String, Vec<i64>)> = Vec::new();
    if a.label.is_empty() {
        jobs.push(("organ".into(), seg.organ_labels.clone()));
        for &l in &seg.structure_labels {
            jobs.push((seg.label_name(l), vec![l]));
        }
    } else {
        for &l in &a.label {
            jobs.push((seg.label_name(l), vec![l]));
        }
    }
    // One voxel (every voxel) to 16 (a coarse preview); the same bounds as a model's surface step.
    if !(1..=16).contains(&a.step) {
        anyhow::bail!("--step {}: between 1 (every voxel) and 16 voxels", a.step);
    }
    let settings = SurfaceSettings { step: a.step, ..Default::default() };
    let mut out = Vec::new();
    // Every surface first, then the folder replaced whole: a label that fails leaves the last
    // run's folder as it was, and no mesh of an earlier run survives beside the new ones.
    umesh_core::check_apart(&a.out, &a.input.paths())?;
    let staged =
        umesh_core::StagedDir::new(&a.out, umesh_core::OutputKind::Surfaces, &["organ.obj", "organ.ply", "organ.stl"])
            .with_context(|| format!("--out {}", a.out.display()))?;
    for (name, labels) in jobs {
        let mask = seg.volume.mask(&labels);
        anyhow::ensure!(mask.count() > 0, "{}: labels {labels:?} have no voxel", seg.source.display());
        let mesh = extract_surface(&mask, &settings);
        anyhow::ensure!(
            !mesh.triangles.is_empty(),
            "{}: labels {labels:?} hold {} voxel(s), too few for a surface at this smoothing; nothing written",
            seg.source.display(),
            mask.count()
        );
        let file_name = format!("{}.{}", name.replace([' ', '/'], "_"), a.format);
        let file = a.out.join(&file_name);
        write_mesh(&staged.path().join(&file_name), &mesh)?;
        let t = mesh.topology();
        out.push(serde_json::json!({"name": name, "labels": labels, "file": file, "vertices": mesh.positions.len(),
            "triangles": mesh.triangles.len(), "area_mm2": mesh.area_mm2(), "volume_mm3": mesh.signed_volume_mm3(), "watertight": t.is_watertight()}));
        if !a.json {
            println!(
                "{:24} {:>8} triangles  {:>10.0} mm^3  watertight: {}  -> {}",
                name,
                mesh.triangles.len(),
                mesh.signed_volume_mm3(),
                t.is_watertight(),
                file.display()
            );
        }
    }
    staged.commit().with_context(|| format!("replacing {}", a.out.display()))?;
    if a.json {
        super::output::print_json(&serde_json::json!({"surfaces": out}));
    }
    Ok(())
}
