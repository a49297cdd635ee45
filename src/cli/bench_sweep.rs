//! `umesh bench dataset --sweep`: dataset generation with the defaults over organs of other
//! sizes and shapes, other attachments and other cameras, one axis varied at a time. Each
//! configuration reports its acceptance, achieved / target mean displacement and throughput,
//! so that a change tuned on one organ shows on the others.

use super::input::PHANTOM_BYTES;
use anyhow::{Context, Result};
use nalgebra::{Matrix4, Vector3};
use std::path::{Path, PathBuf};
use std::time::Instant;
use umesh_core::dataset::{DatasetConfig, ShardSelection, run_generate, run_stats};
use umesh_core::fem::FixedRegion;
use umesh_core::grid::ImmersedGrid;
use umesh_core::rng::SplitMix64;
use umesh_core::segmentation::{self, Segmentation};
use umesh_core::visible::Camera;
use umesh_core::{Cancel, Progress};

/// The shared real data, when it sits beside the checkout (as in CI).
fn shared_data() -> Option<PathBuf> {
    [PathBuf::from("../shared/data"), PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data")]
        .into_iter()
        .find(|p| p.is_dir())
}

/// The segmentation with its world frame stretched by `s` per axis about the organ's centre.
fn stretched(seg: &Segmentation, s: [f64; 3]) -> Result<Segmentation> {
    let (lo, hi) = seg.organ_mask().world_bounds().context("the organ mask is empty")?;
    let c = (lo + hi) / 2.0;
    let mut m = Matrix4::identity();
    for a in 0..3 {
        m[(a, a)] = s[a];
        m[(a, 3)] = c[a] * (1.0 - s[a]);
    }
    let mut out = seg.clone();
    out.volume.world_from_voxel = m * seg.volume.world_from_voxel;
    Ok(out)
}

struct Organ {
    name: &'static str,
    seg: Segmentation,
    /// A label other than the default anchor, for the "label" attachment.
    other_label: Option<i64>,
}

fn organs() -> Result<Vec<Organ>> {
    let phantom = segmentation::bundled_phantom(PHANTOM_BYTES)?;
    let mut v = vec![
        Organ { name: "phantom", seg: phantom.clone(), other_label: Some(umesh_core::phantom::PORTAL_VEIN) },
        Organ {
            name: "phantom-0.6x",
            seg: stretched(&phantom, [0.6; 3])?,
            other_label: Some(umesh_core::phantom::PORTAL_VEIN),
        },
        Organ {
            name: "phantom-1.6x",
            seg: stretched(&phantom, [1.6; 3])?,
            other_label: Some(umesh_core::phantom::PORTAL_VEIN),
        },
        Organ {
            name: "phantom-squashed",
            seg: stretched(&phantom, [1.25, 1.0, 0.6])?,
            other_label: Some(umesh_core::phantom::PORTAL_VEIN),
        },
    ];
    if let Some(d) = shared_data() {
        let ts = d.join("totalsegmentator");
        let opts = umesh_core::nifti_io::ReadOptions::default();
        v.push(Organ {
            name: "ct",
            seg: segmentation::load_nifti_labels(&ts.join("example_seg.nii.gz"), &[5], &[64], &opts)?,
            other_label: Some(64),
        });
        v.push(Organ {
            name: "mr",
            seg: segmentation::load_nifti_labels(&ts.join("example_seg_mr.nii.gz"), &[5], &[], &opts)?,
            other_label: None,
        });
        // SOFA's liver (6.4 x 4.9 x 4.4 units) scaled to an adult liver: 30 mm a unit, 1.05 l.
        v.push(Organ {
            name: "sofa",
            seg: segmentation::load_meshes(&d.join("sofa/liver-smooth.obj"), &[], 1.0, 30.0)?,
            other_label: None,
        });
    } else {
        eprintln!("../shared/data absent: the sweep covers the phantom family only");
    }
    Ok(v)
}

/// Attachments other than the default, from the organ's bounds (and grid, for the patch).
fn attachments(organ: &Organ, config: &DatasetConfig) -> Result<Vec<(&'static str, FixedRegion)>> {
    let (lo, hi) = organ.seg.organ_mask().world_bounds().context("the organ mask is empty")?;
    let e = hi - lo;
    let c = (lo + hi) / 2.0;
    let mut v = Vec::new();
    if let Some(l) = organ.other_label {
        v.push(("label", FixedRegion::Label { label: l, distance_mm: 6.0 }));
    }
    // A box holding about a third of the organ: the right lobe.
    v.push((
        "box-30%",
        FixedRegion::Box {
            min_mm: [hi.x - 0.3 * e.x, lo.y - 1.0, lo.z - 1.0],
            max_mm: [hi.x + 1.0, hi.y + 1.0, hi.z + 1.0],
        },
    ));
    // The inferior plane instead of the posterior one.
    v.push(("plane", FixedRegion::Plane { normal: [0.0, 0.0, 1.0], offset_mm: lo.z, thickness_mm: 0.15 * e.z }));
    // A patch of the surface: the grid nodes within 15 mm of the posterior surface point
    // nearest the organ's centre line.
    let grid = ImmersedGrid::from_mask(&organ.seg.organ_mask(), &config.grid, &Progress::none(), &Cancel::new())?;
    let positions = grid.node_positions();
    let anchor = positions
        .iter()
        .min_by(|a, b| {
            let key = |p: &Vector3<f64>| p.y - lo.y + 0.5 * ((p.x - c.x).abs() + (p.z - c.z).abs());
            key(a).total_cmp(&key(b))
        })
        .copied()
        .context("the grid has no node")?;
    let nodes: Vec<usize> = (0..positions.len()).filter(|&n| (positions[n] - anchor).norm() <= 15.0).collect();
    v.push(("surface-patch", FixedRegion::Nodes { nodes }));
    // The same attachment given as a small box around it (a ligament's surface points boxed).
    let (a, r) = (anchor, 12.0);
    v.push((
        "small-box",
        FixedRegion::Box { min_mm: [a.x - r, a.y - r, a.z - r], max_mm: [a.x + r, a.y + r, a.z + r] },
    ));
    Ok(v)
}

/// The six named views and three random directions (seeded), 2.5 organ sizes away.
fn cameras(seg: &Segmentation) -> Result<Vec<(String, Camera)>> {
    let (lo, hi) = seg.organ_mask().world_bounds().context("the organ mask is empty")?;
    let mut v = Vec::new();
    for name in ["anterior", "posterior", "right", "left", "superior", "inferior"] {
        v.push((name.to_string(), Camera::named(name, &lo, &hi)?));
    }
    let c = (lo + hi) / 2.0;
    let r = 2.5 * (hi - lo).norm();
    let mut rng = SplitMix64(7);
    for k in 0..3 {
        let d = loop {
            let d = Vector3::new(rng.next_f64(), rng.next_f64(), rng.next_f64()) * 2.0 - Vector3::repeat(1.0);
            if d.norm() > 0.2 && d.norm() <= 1.0 {
                break d.normalize();
            }
        };
        v.push((format!("random-{k}"), Camera::look_at(&(c + d * r), &c, 50.0)));
    }
    Ok(v)
}

fn measure(name: &str, seg: &Segmentation, config: &DatasetConfig, dir: &Path) -> Result<serde_json::Value> {
    let _ = std::fs::remove_dir_all(dir);
    let t = Instant::now();
    let r = run_generate(seg, dir, config, ShardSelection::all(), &Progress::none(), &Cancel::new());
    let secs = t.elapsed().as_secs_f64();
    let r = match r {
        Ok(r) => r,
        // A set-up the dataset refuses (camera inside the organ, nothing fixed) is a result too.
        Err(e) => return Ok(serde_json::json!({ "config": name, "error": format!("{e:#}") })),
    };
    let st = run_stats(dir)?;
    // One reason per kind of rejection, so that a row that fails says why.
    let mut reasons = serde_json::Map::new();
    for s in umesh_core::dataset::Manifest::read(dir)?.samples.iter().filter(|s| !s.accepted) {
        let kind = s.rejection.map(|r| format!("{r:?}").to_lowercase()).unwrap_or_default();
        reasons.entry(kind).or_insert_with(|| {
            serde_json::json!(format!("sample {}: {}", s.index, s.reason.clone().unwrap_or_default()))
        });
    }
    let ctx = umesh_core::dataset::DatasetContext::prepare(seg, config, &Cancel::new())?;
    let _ = std::fs::remove_dir_all(dir);
    let fixed = ctx.fixed.iter().filter(|&&f| f).count();
    Ok(serde_json::json!({
        "config": name,
        "nodes": ctx.grid.node_count(),
        "volume_ml": ctx.grid.volume_mm3() / 1e3,
        "visible_fraction": ctx.visible.fraction(),
        "fixed_fraction": fixed as f64 / ctx.grid.node_count().max(1) as f64,
        "samples": r.samples_computed,
        "accepted": r.accepted,
        "acceptance": r.accepted as f64 / r.samples_computed.max(1) as f64,
        "rejected": r.rejected,
        "rejection_reasons": reasons,
        "below_target": st.below_target,
        "strain_limited": st.strain_limited,
        "strain_limited_factor_median": st.strain_limited_factor.as_ref().map(|d| d.median),
        "achieved_over_target_mean": st.achieved_over_target.as_ref().map(|d| d.mean),
        "achieved_over_target_min": st.achieved_over_target.as_ref().map(|d| d.min),
        "samples_per_minute": r.samples_computed as f64 * 60.0 / secs,
        "solve_s_median": st.solve_ms.as_ref().map(|d| d.median / 1e3),
        "solve_s_max": st.solve_ms.as_ref().map(|d| d.max / 1e3),
        "rejected_solve_s_max": st.rejected_solve_ms.as_ref().map(|d| d.max / 1e3),
    }))
}

pub fn run(samples: usize, only: Option<&str>, json: bool) -> Result<serde_json::Value> {
    let dir = std::env::temp_dir().join(format!("umesh-bench-sweep-{}", std::process::id()));
    let mut rows = Vec::new();
    let wanted = |name: &str| only.is_none_or(|o| name.contains(o));
    let mut run_one = |name: String, seg: &Segmentation, config: &DatasetConfig| -> Result<()> {
        if !wanted(&name) {
            return Ok(());
        }
        let row = measure(&name, seg, config, &dir)?;
        if !json {
            eprintln!("{row}");
        }
        rows.push(row);
        Ok(())
    };
    for organ in organs()? {
        let fixed = umesh_core::loads::default_fixed(&organ.seg, None, 6.0).region;
        let mut base = DatasetConfig::paper(fixed);
        base.samples = samples.max(2);
        base.shard_size = base.samples;
        run_one(format!("{} default", organ.name), &organ.seg, &base)?;
        // Attachments on the phantom, the CT and the mesh organ; cameras on the phantom and the CT.
        if matches!(organ.name, "phantom" | "ct" | "sofa") {
            for (a, region) in attachments(&organ, &base)? {
                let mut c = base.clone();
                c.fixed = region;
                run_one(format!("{} fixed {a}", organ.name), &organ.seg, &c)?;
            }
        }
        if matches!(organ.name, "phantom" | "ct") {
            for (v, cam) in cameras(&organ.seg)? {
                let mut c = base.clone();
                c.visibility.camera = Some(cam);
                run_one(format!("{} camera {v}", organ.name), &organ.seg, &c)?;
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(
        serde_json::json!({ "samples_per_config": samples.max(2), "threads": rayon::current_num_threads(), "configs": rows }),
    )
}
