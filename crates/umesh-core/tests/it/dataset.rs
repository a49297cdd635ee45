//! Training data: visibility, probe sampling, force distribution, deterministic shards,
//! merge, resume (and a resumed job's time left), corruption detection.

use nalgebra::Vector3;
use std::path::{Path, PathBuf};
use umesh_core::dataset::{Dataset, DatasetConfig, ShardSelection, run_generate, run_merge, shard_file_name};
use umesh_core::fem::{BoundaryConditions, FixedRegion};
use umesh_core::grid::GridSettings;
use umesh_core::mesh::TriMesh;
use umesh_core::rng::SplitMix64;
use umesh_core::segmentation::{Segmentation, bundled_phantom};
use umesh_core::surface::{SurfaceSettings, extract_surface};
use umesh_core::visible::{Camera, VisibilitySettings, sample_points, visible_surface};
use umesh_core::{Cancel, Eta, Progress};

fn phantom() -> Segmentation {
    let bytes = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/../../assets/phantom.nii.gz")).unwrap();
    bundled_phantom(&bytes).unwrap()
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("umesh-ds-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn visible_area_is_capped_and_front_facing() {
    let seg = phantom();
    let mesh = extract_surface(&seg.organ_mask(), &SurfaceSettings { step: 2, ..Default::default() });
    for fraction in [0.5, 0.3, 1.0] {
        let vis = visible_surface(&mesh, &VisibilitySettings { max_fraction: fraction, ..Default::default() }).unwrap();
        assert!(vis.fraction() <= fraction + 1e-12, "{} > {fraction}", vis.fraction());
        assert!(vis.fraction() > 0.1, "too little visible: {}", vis.fraction());
        let eye = Vector3::from(vis.camera.position_mm);
        for (t, tri) in mesh.triangles.iter().enumerate() {
            if vis.visible[t] {
                let c = tri.iter().map(|&i| mesh.positions[i as usize]).sum::<Vector3<f64>>() / 3.0;
                assert!(
                    mesh.triangle_normal_area(t).0.dot(&(eye - c)) > 0.0,
                    "back-facing triangle {t} marked visible"
                );
            }
        }
    }
    // Without a cap, a camera sees less than the whole closed surface (occlusion + back faces).
    let vis = visible_surface(&mesh, &VisibilitySettings { max_fraction: 1.0, ..Default::default() }).unwrap();
    assert!(vis.fraction() < 0.7, "{}", vis.fraction());
    // A camera behind the organ sees its posterior face instead.
    let (lo, hi) = mesh.bounds().unwrap();
    let c = (lo + hi) / 2.0;
    let back = Camera { position_mm: [c.x, c.y - 500.0, c.z], direction: [0.0, 1.0, 0.0], fov_deg: 50.0 };
    let vb =
        visible_surface(&mesh, &VisibilitySettings { camera: Some(back), max_fraction: 1.0, ..Default::default() })
            .unwrap();
    let both = (0..mesh.triangles.len()).filter(|&t| vb.visible[t] && vis.visible[t]).count();
    assert!(both * 50 < vb.visible.iter().filter(|&&v| v).count(), "front and back views overlap too much");
}

#[test]
fn probe_sampling_is_uniform_by_area() {
    // Two triangles with areas 1 : 3.
    let mesh = TriMesh {
        positions: vec![
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(0.0, 2.0, 0.0),
            Vector3::new(10.0, 0.0, 0.0),
            Vector3::new(13.0, 0.0, 0.0),
            Vector3::new(10.0, 2.0, 0.0),
        ],
        triangles: vec![[0, 1, 2], [3, 4, 5]],
    };
    let n = 20000;
    let pts = sample_points(&mesh, &[true, true], n, &mut SplitMix64(42));
    let first = pts.iter().filter(|(p, _)| p.x < 5.0).count() as f64;
    // Binomial(n, 1/4): expected 5000, standard deviation ~61; allow 4 sigma.
    assert!((first - n as f64 / 4.0).abs() < 4.0 * (n as f64 * 0.25 * 0.75).sqrt(), "{first}");
    // Within a triangle: uniform, so the mean is the centroid.
    let tri2: Vec<Vector3<f64>> = pts.iter().filter(|(p, _)| p.x >= 5.0).map(|(p, _)| *p).collect();
    let mean = tri2.iter().sum::<Vector3<f64>>() / tri2.len() as f64;
    assert!((mean - Vector3::new(11.0, 2.0 / 3.0, 0.0)).norm() < 0.03, "{mean:?}");
    // Invisible triangles get no sample.
    let pts = sample_points(&mesh, &[false, true], 1000, &mut SplitMix64(1));
    assert!(pts.iter().all(|(p, _)| p.x >= 10.0));
}

#[test]
fn barycentric_force_distribution_conserves_force_and_moment() {
    let seg = phantom();
    let grid =
        umesh_core::grid::run_grid(&seg, &GridSettings::default(), &Progress::none(), &Cancel::new()).unwrap().grid;
    let mut rng = SplitMix64(9);
    let mut bc = BoundaryConditions::new(grid.node_count());
    let (mut total, mut moment) = (Vector3::zeros(), Vector3::zeros());
    let mesh = extract_surface(&seg.organ_mask(), &SurfaceSettings { step: 2, ..Default::default() });
    for (p, _) in sample_points(&mesh, &vec![true; mesh.triangles.len()], 200, &mut rng) {
        let f = Vector3::new(rng.next_f64() - 0.5, rng.next_f64() - 0.5, rng.next_f64() - 0.5);
        bc.add_point_force(&grid, &p, &f).unwrap();
        total += f;
        moment += p.cross(&f);
    }
    let nodal: Vector3<f64> = bc.forces_n.iter().sum();
    let nodal_moment: Vector3<f64> = (0..grid.node_count()).map(|n| grid.node_position(n).cross(&bc.forces_n[n])).sum();
    assert!((nodal - total).norm() < 1e-12 * total.norm().max(1.0));
    // Exact for points inside their cells; surface points slightly outside any cell are clamped,
    // which moves their lever arm by at most a fraction of a cell.
    assert!((nodal_moment - moment).norm() < 1e-3 * moment.norm(), "{nodal_moment:?} vs {moment:?}");
}

fn small_config(samples: usize) -> DatasetConfig {
    let mut c = DatasetConfig::paper(FixedRegion::Label { label: umesh_core::phantom::VENA_CAVA, distance_mm: 8.0 });
    c.samples = samples;
    c.seed = 3;
    c.shard_size = 2;
    c.grid.cell_size_mm = 14.0;
    c.forces.probes = 20;
    c.surface_step = 3;
    c
}

fn file_bytes(dir: &Path, name: &str) -> Vec<u8> {
    std::fs::read(dir.join(name)).unwrap_or_else(|e| panic!("{}: {e}", dir.join(name).display()))
}

#[test]
fn shards_merge_into_exactly_the_single_run_dataset_and_resume_completes_it() {
    let seg = phantom();
    let config = small_config(5);
    let single = tmp("single");
    let r = run_generate(&seg, &single, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    assert!(r.complete && r.samples_computed == 5, "{r:?}");
    assert!(r.accepted >= 4, "{r:?}");
    let a = tmp("a");
    let b = tmp("b");
    let ra = run_generate(&seg, &a, &config, ShardSelection::parse("0/2").unwrap(), &Progress::none(), &Cancel::new())
        .unwrap();
    let rb = run_generate(&seg, &b, &config, ShardSelection::parse("1/2").unwrap(), &Progress::none(), &Cancel::new())
        .unwrap();
    assert!(!ra.complete && !rb.complete);
    let merged = tmp("merged");
    let m = run_merge(&[a.clone(), b.clone()], &merged).unwrap();
    assert!(m.complete);
    for shard in 0..config.shard_count() {
        let name = shard_file_name(shard);
        assert_eq!(file_bytes(&single, &name), file_bytes(&merged, &name), "{name} differs");
    }
    assert_eq!(file_bytes(&single, "grid.npz"), file_bytes(&merged, "grid.npz"));
    let ds = Dataset::open(&merged).unwrap();
    assert_eq!(ds.manifest.samples.len(), 5);
    let (idx, u_s, u_v) = ds.load_shard(&ds.manifest.shards[0]).unwrap();
    let [x, y, z] = ds.manifest.padded_shape;
    assert_eq!(u_v.len(), idx.len() * 3 * x * y * z);
    // u_s is u_v on the visible nodes and zero elsewhere.
    let nonzero_s = u_s.iter().filter(|v| **v != 0.0).count();
    let nonzero_v = u_v.iter().filter(|v| **v != 0.0).count();
    assert!(nonzero_s > 0 && nonzero_s < nonzero_v, "{nonzero_s} vs {nonzero_v}");
    for (s, v) in u_s.iter().zip(&u_v) {
        assert!(*s == 0.0 || s == v);
    }

    // Resume: lose a shard, run again, get the same files (shards without their manifest are
    // refused: see shards_without_their_manifest_are_refused_not_adopted).
    let resumed = tmp("resumed");
    run_generate(&seg, &resumed, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    std::fs::remove_file(resumed.join(shard_file_name(1))).unwrap();
    let reports = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let seen = reports.clone();
    let progress = Progress::new(move |done, total, msg| seen.lock().unwrap().push((done, total, msg.to_string())));
    let r2 = run_generate(&seg, &resumed, &config, ShardSelection::all(), &progress, &Cancel::new()).unwrap();
    assert_eq!(r2.samples_computed, 2, "{r2:?}");
    assert_eq!(r2.samples_reused, 3);
    // The resumed run counts over the whole dataset: it starts at the 3 samples kept and
    // reaches 5 of 5 (a job's progress and time left are read from these; two workers may
    // report out of order, so no order is asserted after the first).
    let reports = reports.lock().unwrap().clone();
    assert_eq!(reports.first().map(|r| (r.0, r.1)), Some((3, 5)), "{reports:?}");
    assert!(reports.iter().all(|r| (3..=5).contains(&r.0) && r.1 == 5), "{reports:?}");
    assert!(reports.iter().any(|r| r.0 == 5), "{reports:?}");
    for shard in 0..config.shard_count() {
        let name = shard_file_name(shard);
        assert_eq!(file_bytes(&single, &name), file_bytes(&resumed, &name), "{name} differs after resume");
    }

    // A different configuration in the same folder is refused.
    let mut other = config.clone();
    other.seed = 99;
    let e = run_generate(&seg, &resumed, &other, ShardSelection::all(), &Progress::none(), &Cancel::new())
        .unwrap_err()
        .to_string();
    assert!(e.contains("another configuration"), "{e}");
}

#[test]
fn corrupted_or_truncated_shards_are_detected_on_load() {
    let seg = phantom();
    let config = small_config(2);
    let dir = tmp("corrupt");
    run_generate(&seg, &dir, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    assert!(Dataset::open(&dir).is_ok());
    let shard = dir.join(shard_file_name(0));
    let mut bytes = std::fs::read(&shard).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xff;
    std::fs::write(&shard, &bytes).unwrap();
    let e = Dataset::open(&dir).unwrap_err().to_string();
    assert!(e.contains("shard_000000.npz") && e.contains("corrupted"), "{e}");
    std::fs::write(&shard, &bytes[..mid]).unwrap();
    let e = Dataset::open(&dir).unwrap_err().to_string();
    assert!(e.contains("truncated"), "{e}");
    // Regenerating replaces the damaged shard (it fails validation and is recomputed).
    let r = run_generate(&seg, &dir, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    assert_eq!(r.samples_computed, 2);
    assert!(Dataset::open(&dir).is_ok());
    std::fs::write(dir.join("manifest.json"), "{").unwrap();
    assert!(Dataset::open(&dir).unwrap_err().to_string().contains("manifest.json"));
}

#[test]
fn a_manifest_whose_sample_list_lies_or_holds_nan_is_refused_naming_it() {
    let seg = phantom();
    let config = small_config(2);
    let dir = tmp("lying-manifest");
    run_generate(&seg, &dir, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let path = dir.join("manifest.json");
    let good: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    assert!(Dataset::open(&dir).is_ok());
    let edits: [(&str, fn(&mut serde_json::Value)); 5] = [
        ("listed twice", |m| {
            let first = m["samples"][0].clone();
            m["samples"].as_array_mut().unwrap().push(first);
        }),
        ("does not list", |m| m["samples"][0]["shard"] = "shard_000099.npz".into()),
        ("outside its shard", |m| m["samples"][0]["index"] = 1000.into()),
        ("sample list gives it", |m| {
            let accepted = m["shards"][0]["accepted"].as_u64().unwrap();
            m["shards"][0]["accepted"] = (accepted + 1).into();
        }),
        ("not finite", |m| {
            // serde_json writes NaN as null, which the reader takes for a missing number:
            // the hostile file's text carries it instead (below).
            let k = m["samples"].as_array().unwrap().iter().position(|s| s["accepted"] == true).unwrap();
            m["samples"][k]["max_displacement_mm"] = (-1.0).into();
        }),
    ];
    for (says, edit) in edits {
        let mut m = good.clone();
        edit(&mut m);
        std::fs::write(&path, serde_json::to_string(&m).unwrap()).unwrap();
        let e = Dataset::open(&dir).unwrap_err().to_string();
        assert!(e.contains("manifest.json") && e.contains(says), "{says}: {e}");
    }
    // A NaN or an infinity written into the file's text is refused as well.
    let text = serde_json::to_string(&good).unwrap();
    let key = "\"max_displacement_mm\":";
    let at = text.find(key).unwrap() + key.len();
    let end = at + text[at..].find([',', '}']).unwrap();
    for bad in ["NaN", "1e999"] {
        std::fs::write(&path, format!("{}{bad}{}", &text[..at], &text[end..])).unwrap();
        let e = Dataset::open(&dir).unwrap_err().to_string();
        assert!(e.contains("manifest.json"), "{bad}: {e}");
    }
    std::fs::write(&path, serde_json::to_string_pretty(&good).unwrap()).unwrap();
    assert!(Dataset::open(&dir).is_ok());
}

#[test]
fn calibrated_loads_land_within_a_quarter_of_each_samples_target() {
    let seg = phantom();
    let mut config = small_config(6);
    config.grid.cell_size_mm = 10.0;
    config.forces.probes = 40;
    config.forces.target_displacement_mm = 8.0;
    let dir = tmp("calibrated");
    let r = run_generate(&seg, &dir, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    assert_eq!(r.accepted, 6, "{r:?}");
    let m = umesh_core::dataset::Manifest::read(&dir).unwrap();
    for s in &m.samples {
        let t = s.target_displacement_mm.expect("target recorded");
        // The spread: target x U[0.5, 1.5], times the family's share (an instrument: half).
        let f = s.family.map_or(1.0, |f| f.target_factor());
        assert!((4.0 * f..=12.0 * f).contains(&t), "sample {}: target {t} ({:?})", s.index, s.family);
        let ratio = s.mean_displacement_mm / t;
        assert!(
            (0.75..=1.25).contains(&ratio),
            "sample {}: {:.2} mm for a {t:.2} mm target",
            s.index,
            s.mean_displacement_mm
        );
    }
    let st = umesh_core::dataset::run_stats(&dir).unwrap();
    let a = st.achieved_over_target.unwrap();
    assert!(a.min >= 0.75 && a.max <= 1.25, "{a:?}");
    assert_eq!(st.target_displacement_mm, 8.0);
}

#[test]
fn default_fixed_region_is_the_vena_cava_by_name_or_number_else_a_deep_posterior_slab() {
    use umesh_core::loads::default_fixed;
    let seg = phantom();
    let c = default_fixed(&seg, None, 6.0);
    assert_eq!(c.region, FixedRegion::Label { label: 2, distance_mm: 6.0 }, "{}", c.description);
    assert!(c.description.contains("inferior_vena_cava"), "{}", c.description);
    // TotalSegmentator numbers without names: liver 5, vena cava 63.
    let mut ts = seg.clone();
    ts.volume.label_names.clear();
    for v in &mut ts.volume.data {
        *v = match *v as i64 {
            1 => 5.0,
            2 => 63.0,
            _ => *v,
        };
    }
    ts.organ_labels = vec![5];
    ts.structure_labels = vec![];
    assert_eq!(default_fixed(&ts, None, 6.0).region, FixedRegion::Label { label: 63, distance_mm: 6.0 });
    // No vein: the posterior fifth, deep enough to hold the organ.
    let mut plain = ts.clone();
    for v in &mut plain.volume.data {
        if *v == 63.0 {
            *v = 0.0;
        }
    }
    let c = default_fixed(&plain, None, 6.0);
    let (lo, hi) = plain.organ_mask().world_bounds().unwrap();
    match c.region {
        FixedRegion::Plane { normal, offset_mm, thickness_mm } => {
            assert_eq!(normal, [0.0, 1.0, 0.0]);
            assert!((offset_mm - lo.y).abs() < 1e-9);
            assert!((thickness_mm - 0.2 * (hi.y - lo.y)).abs() < 1e-9, "{thickness_mm}");
        }
        other => panic!("{other:?}"),
    }
    assert!(c.description.contains("no vena cava"), "{}", c.description);
}

#[test]
fn a_camera_inside_the_organ_or_seeing_nothing_and_an_empty_fixed_region_are_refused() {
    use umesh_core::dataset::DatasetContext;
    let seg = phantom();
    let (lo, hi) = seg.organ_mask().world_bounds().unwrap();
    let c = (lo + hi) / 2.0;
    let mut config = small_config(2);
    let mask = seg.organ_mask();
    let [nx, ny, _] = mask.dims;
    let deep = (0..mask.data.len())
        .map(|i| ((i % nx) as i64, ((i / nx) % ny) as i64, (i / (nx * ny)) as i64))
        .find(|&(i, j, k)| (-3..=3).all(|d| mask.get(i + d, j, k) && mask.get(i, j + d, k) && mask.get(i, j, k + d)))
        .unwrap();
    let eye = mask
        .world_from_voxel
        .transform_point(&nalgebra::Point3::new(deep.0 as f64, deep.1 as f64, deep.2 as f64))
        .coords;
    config.visibility.camera = Some(Camera::look_at(&eye, &(eye + Vector3::y()), 50.0));
    let e = DatasetContext::prepare(&seg, &config, &Cancel::new()).unwrap_err().to_string();
    assert!(e.contains("inside the organ"), "{e}");
    // Looking away from the organ.
    config.visibility.camera =
        Some(Camera::look_at(&(c + Vector3::new(0.0, 500.0, 0.0)), &(c + Vector3::new(0.0, 1000.0, 0.0)), 50.0));
    let e = DatasetContext::prepare(&seg, &config, &Cancel::new()).unwrap_err().to_string();
    assert!(e.contains("sees 0.0 %") || e.contains("sees none"), "{e}");
    let mut config = small_config(2);
    config.fixed = FixedRegion::Box { min_mm: [1e5, 1e5, 1e5], max_mm: [1e5 + 1.0, 1e5 + 1.0, 1e5 + 1.0] };
    let e = DatasetContext::prepare(&seg, &config, &Cancel::new()).unwrap_err().to_string();
    assert!(e.contains("holds no grid node"), "{e}");
}

#[test]
fn per_structure_masks_give_the_same_grid_and_structures_as_the_multi_label_file() {
    use umesh_core::nifti_io::{ReadOptions, WriteType, write_volume};
    use umesh_core::segmentation::{MaskFolder, assemble_masks, mask_folder};
    let seg = phantom();
    let dir = tmp("masks");
    std::fs::create_dir_all(&dir).unwrap();
    for (&label, name) in &seg.volume.label_names {
        let mut v = seg.volume.clone();
        v.label_names.clear();
        for x in &mut v.data {
            *x = (x.round() as i64 == label) as u8 as f32;
        }
        write_volume(&dir.join(format!("{name}.nii.gz")), &v, WriteType::U8).unwrap();
    }
    // A file TotalSegmentator also writes, that is no part of the liver model.
    let mut other = seg.volume.clone();
    other.data.iter_mut().for_each(|x| *x = 0.0);
    other.data[0] = 1.0;
    write_volume(&dir.join("spleen.nii.gz"), &other, WriteType::U8).unwrap();
    let MaskFolder { files, ignored } = mask_folder(&dir).unwrap();
    assert_eq!(ignored, vec!["spleen.nii.gz".to_string()]);
    let (folder, notes) = assemble_masks(&files, &ReadOptions::default()).unwrap();
    assert!(notes.resampled.is_empty());
    let settings = GridSettings::default();
    let g1 = umesh_core::grid::run_grid(&seg, &settings, &Progress::none(), &Cancel::new()).unwrap();
    let g2 = umesh_core::grid::run_grid(&folder, &settings, &Progress::none(), &Cancel::new()).unwrap();
    assert_eq!(
        (g1.stats.cells, g1.stats.nodes, g1.stats.padded_shape),
        (g2.stats.cells, g2.stats.nodes, g2.stats.padded_shape)
    );
    assert!((g1.stats.grid_volume_mm3 - g2.stats.grid_volume_mm3).abs() < 1e-6 * g1.stats.grid_volume_mm3);
    let names = |s: &Segmentation| {
        let mut v: Vec<String> = s.structure_labels.iter().map(|&l| s.label_name(l)).collect();
        v.sort();
        v
    };
    assert_eq!(names(&seg), names(&folder));
    // The vena cava anchors the organ in both.
    let a = umesh_core::loads::default_fixed(&folder, None, 6.0);
    assert!(a.description.contains("inferior_vena_cava"), "{}", a.description);
    for s in &folder.structure_labels {
        assert_eq!(
            folder.volume.mask(&[*s]).count(),
            seg.volume
                .mask(&[*seg.volume.label_names.iter().find(|(_, n)| **n == folder.label_name(*s)).unwrap().0])
                .count()
        );
    }
}

#[test]
fn a_vena_cava_drawn_inside_the_liver_mask_still_holds_the_organ() {
    use umesh_core::nifti_io::{ReadOptions, WriteType, write_volume};
    use umesh_core::segmentation::{MaskFile, Role, assemble_masks};
    let seg = phantom();
    let dir = tmp("ivc-inside");
    std::fs::create_dir_all(&dir).unwrap();
    // The liver mask drawn with the vena cava in it (the vena cava's voxels are liver too).
    let ivc_label = umesh_core::phantom::VENA_CAVA;
    let mut liver = seg.volume.clone();
    liver.label_names.clear();
    for x in &mut liver.data {
        let l = x.round() as i64;
        *x = (seg.organ_labels.contains(&l) || l == ivc_label) as u8 as f32;
    }
    write_volume(&dir.join("liver.nii.gz"), &liver, WriteType::U8).unwrap();
    let mut ivc = seg.volume.clone();
    ivc.label_names.clear();
    for x in &mut ivc.data {
        *x = (x.round() as i64 == ivc_label) as u8 as f32;
    }
    let ivc_voxels = ivc.data.iter().filter(|v| **v != 0.0).count();
    write_volume(&dir.join("inferior_vena_cava.nii.gz"), &ivc, WriteType::U8).unwrap();
    let f = |name: &str, role| MaskFile { name: name.into(), path: dir.join(format!("{name}.nii.gz")), role };
    let (s, notes) =
        assemble_masks(&[f("liver", Role::Organ), f("inferior_vena_cava", Role::Anchor)], &ReadOptions::default())
            .unwrap();
    // Was: the vein kept no voxel and the organ fell back to the posterior fifth, silently.
    let a = umesh_core::loads::default_fixed(&s, None, 6.0);
    assert!(a.description.contains("inferior_vena_cava"), "{}", a.description);
    assert_eq!(notes.carved.len(), 1, "{notes:?}");
    assert!(notes.carved[0].contains("inferior_vena_cava.nii.gz"), "{notes:?}");
    // Every vein voxel is the vein's; the organ is the phantom's organ exactly.
    let vein = s.volume.label_names.iter().find(|(_, n)| n.as_str() == "inferior_vena_cava").map(|x| *x.0).unwrap();
    assert_eq!(s.volume.mask(&[vein]).count(), ivc_voxels);
    assert_eq!(s.organ_mask().count(), seg.organ_mask().count());
}

#[test]
fn masks_on_other_lattices_are_resampled_and_disjoint_ones_refused() {
    use umesh_core::nifti_io::{ReadOptions, WriteType, write_volume};
    use umesh_core::segmentation::{MaskFile, Role, assemble_masks};
    let seg = phantom();
    let dir = tmp("lattices");
    std::fs::create_dir_all(&dir).unwrap();
    let mut liver = seg.volume.clone();
    liver.label_names.clear();
    for x in &mut liver.data {
        *x = (seg.organ_labels.contains(&(x.round() as i64))) as u8 as f32;
    }
    write_volume(&dir.join("liver.nii.gz"), &liver, WriteType::U8).unwrap();
    // The portal vein on a lattice shifted by half a voxel.
    let mut pv = seg.volume.clone();
    pv.label_names.clear();
    for x in &mut pv.data {
        *x = (x.round() as i64 == umesh_core::phantom::PORTAL_VEIN) as u8 as f32;
    }
    let mut shifted = pv.clone();
    shifted.world_from_voxel[(0, 3)] += 0.5 * shifted.world_from_voxel[(0, 0)];
    write_volume(&dir.join("pv.nii.gz"), &shifted, WriteType::U8).unwrap();
    let mut far = pv.clone();
    far.world_from_voxel[(2, 3)] += 1e4;
    write_volume(&dir.join("far.nii.gz"), &far, WriteType::U8).unwrap();
    let f = |name: &str, role| MaskFile { name: name.into(), path: dir.join(format!("{name}.nii.gz")), role };
    let (s, notes) =
        assemble_masks(&[f("liver", Role::Organ), f("pv", Role::Structure)], &ReadOptions::default()).unwrap();
    assert_eq!(notes.resampled.len(), 1, "{notes:?}");
    let n = s.volume.mask(&s.structure_labels).count() as f64;
    let n0 = pv.data.iter().filter(|v| **v != 0.0).count() as f64;
    assert!((n - n0).abs() < 0.5 * n0, "{n} vs {n0}");
    let e = assemble_masks(&[f("liver", Role::Organ), f("far", Role::Structure)], &ReadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("far.nii.gz") && e.contains("do not overlap"), "{e}");
}

#[test]
fn samples_carry_a_simulated_camera_view_of_their_deformed_organ() {
    let seg = phantom();
    let config = small_config(4);
    let dir = tmp("views");
    run_generate(&seg, &dir, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let ds = Dataset::open(&dir).unwrap();
    let grid =
        umesh_core::grid::ImmersedGrid::from_npz(&umesh_core::npz::Npz::read(&dir.join("grid.npz")).unwrap()).unwrap();
    let surface =
        extract_surface(&seg.organ_mask(), &SurfaceSettings { step: config.surface_step, ..Default::default() });
    let [_, py, pz] = grid.padded_shape();
    let cells = grid.padded_shape().iter().product::<usize>();
    let mut counts = Vec::new();
    for shard in &ds.manifest.shards {
        let (idx, _, u_v) = ds.load_shard(shard).unwrap();
        let views = ds.load_views(shard).unwrap();
        assert_eq!(views.len(), idx.len());
        for (k, view) in views.iter().enumerate() {
            counts.push(view.len());
            assert!(view.len() > 300 && view.len() <= config.view.points, "sample {}: {} points", idx[k], view.len());
            // The nodal displacement back from the dense field, then the deformed surface.
            let u: Vec<Vector3<f64>> = (0..grid.node_count())
                .map(|n| {
                    let [i, j, l] = grid.node_ijk[n];
                    let d = (i * py + j) * pz + l;
                    let o = k * 3 * cells;
                    Vector3::new(u_v[o + d] as f64, u_v[o + cells + d] as f64, u_v[o + 2 * cells + d] as f64)
                })
                .collect();
            let deformed = umesh_core::loads::deform_mesh(&grid, &surface, &u);
            let mut dist: Vec<f64> = view
                .iter()
                .step_by(10)
                .map(|p| deformed.positions.iter().map(|v| (v - p).norm()).fold(f64::INFINITY, f64::min))
                .collect();
            dist.sort_by(f64::total_cmp);
            // 1 mm depth noise and points inside 3-voxel triangles: the nearest vertex is near.
            let (median, p95) = (dist[dist.len() / 2], dist[dist.len() * 95 / 100]);
            assert!(
                median < 2.5 && p95 < 5.0,
                "sample {}: distance to the deformed surface median {median:.2}, p95 {p95:.2} mm",
                idx[k]
            );
        }
    }
    assert!(
        counts.iter().any(|&c| c != counts[0]),
        "every view holds {} points: dropout and holes do not vary",
        counts[0]
    );
}

#[test]
fn a_dataset_of_the_previous_format_names_the_command_that_regenerates_it() {
    let seg = phantom();
    let dir = tmp("old-format");
    run_generate(&seg, &dir, &small_config(2), ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let path = dir.join("manifest.json");
    let text = std::fs::read_to_string(&path).unwrap().replace("\"format_version\": 2", "\"format_version\": 1");
    std::fs::write(&path, text).unwrap();
    let err = match Dataset::open(&dir) {
        Ok(_) => panic!("an old dataset is refused"),
        Err(e) => e.to_string(),
    };
    assert!(err.contains("v1") && err.contains("umesh dataset generate") && err.contains("manifest.json"), "{err}");
}

fn folder_bytes(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap()))
        .collect();
    v.sort();
    v
}

#[test]
fn shards_without_their_manifest_are_refused_not_adopted() {
    let seg = phantom();
    let dir = tmp("no-manifest");
    run_generate(&seg, &dir, &small_config(2), ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    std::fs::remove_file(dir.join("manifest.json")).unwrap();
    let before = folder_bytes(&dir);
    let mut other = small_config(2);
    other.seed = 99;
    let err = run_generate(&seg, &dir, &other, ShardSelection::all(), &Progress::none(), &Cancel::new())
        .unwrap_err()
        .to_string();
    assert!(err.contains("no manifest.json") && err.contains(&dir.display().to_string()), "{err}");
    assert_eq!(before, folder_bytes(&dir), "the folder was changed");
}

#[test]
fn merge_refuses_another_dataset_in_the_target_and_a_failed_merge_leaves_it_intact() {
    let seg = phantom();
    let a = tmp("merge-a");
    let b = tmp("merge-b");
    run_generate(&seg, &a, &small_config(4), ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let mut cb = small_config(2);
    cb.seed = 11;
    run_generate(&seg, &b, &cb, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let b_before = folder_bytes(&b);
    let err = run_merge(std::slice::from_ref(&a), &b).unwrap_err().to_string();
    assert!(err.contains("another dataset"), "{err}");
    assert_eq!(b_before, folder_bytes(&b));
    // Into a folder of the same dataset: allowed; then a merge whose input is corrupted fails
    // and leaves that target, and its parent, as they were.
    let t = tmp("merge-target");
    run_merge(std::slice::from_ref(&a), &t).unwrap();
    std::fs::write(t.join("notes.txt"), b"kept").unwrap();
    run_merge(std::slice::from_ref(&a), &t).unwrap();
    assert_eq!(std::fs::read(t.join("notes.txt")).unwrap(), b"kept", "other files of the target are kept");
    let t_before = folder_bytes(&t);
    let shard = a.join(shard_file_name(1));
    let mut bytes = std::fs::read(&shard).unwrap();
    bytes.truncate(bytes.len() / 2);
    std::fs::write(&shard, bytes).unwrap();
    let err = run_merge(std::slice::from_ref(&a), &t).unwrap_err().to_string();
    assert!(err.contains("corrupted"), "{err}");
    assert_eq!(t_before, folder_bytes(&t), "the target changed");
    let leftovers: Vec<_> = std::fs::read_dir(t.parent().unwrap())
        .unwrap()
        .flatten()
        .filter(|e| {
            e.file_name().to_string_lossy().starts_with(&format!(".{}", t.file_name().unwrap().to_string_lossy()))
        })
        .collect();
    assert!(leftovers.is_empty(), "staging folders left behind: {leftovers:?}");
}

#[test]
fn a_shard_copied_in_from_another_seed_is_recomputed_not_adopted() {
    let seg = phantom();
    let config = small_config(4);
    let a = tmp("foreign-a");
    let b = tmp("foreign-b");
    run_generate(&seg, &a, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let own = file_bytes(&a, &shard_file_name(1));
    let mut other = config.clone();
    other.seed = 4;
    run_generate(&seg, &b, &other, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let foreign = file_bytes(&b, &shard_file_name(1));
    assert_ne!(own, foreign, "two seeds gave the same shard");
    std::fs::write(a.join(shard_file_name(1)), &foreign).unwrap();
    let r = run_generate(&seg, &a, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    // Shard 0 is the manifest's own; shard 1's bytes are not what the manifest recorded.
    assert_eq!((r.samples_reused, r.samples_computed), (2, 2), "{r:?}");
    assert_eq!(file_bytes(&a, &shard_file_name(1)), own, "the foreign shard survived");
    let m = umesh_core::dataset::Manifest::read(&a).unwrap();
    let rec = m.shards.iter().find(|s| s.file == shard_file_name(1)).unwrap();
    assert_eq!(rec.hash, umesh_core::dataset::fnv_hex(&own));
    Dataset::open(&a).unwrap();
    // A grid.npz from another dataset (another cell size) is refused wherever it is read,
    // naming the file; a truncated one too.
    let mut coarse = config.clone();
    coarse.grid.cell_size_mm = 16.0;
    coarse.samples = 2;
    let c = tmp("foreign-grid");
    run_generate(&seg, &c, &coarse, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let own_grid = file_bytes(&a, "grid.npz");
    for bytes in [file_bytes(&c, "grid.npz"), own_grid[..own_grid.len() / 2].to_vec()] {
        std::fs::write(a.join("grid.npz"), &bytes).unwrap();
        let e = umesh_core::dataset::run_stats(&a).unwrap_err().to_string();
        assert!(e.contains("grid.npz") && e.contains("does not belong to this dataset"), "{e}");
    }
    std::fs::write(a.join("grid.npz"), &own_grid).unwrap();
    umesh_core::dataset::run_stats(&a).unwrap();
}

#[test]
fn a_probes_force_spread_over_its_contact_keeps_the_resultant_and_lands_within_the_radius() {
    use umesh_core::loads::{PointForce, spread_forces};
    let seg = phantom();
    let mesh = extract_surface(&seg.organ_mask(), &SurfaceSettings { step: 2, ..Default::default() });
    let p = mesh.positions[mesh.positions.len() / 3];
    let f = PointForce { point_mm: p.into(), force_n: [0.3, -1.2, 0.5] };
    let spread = spread_forces(&mesh, std::slice::from_ref(&f), 8.0);
    assert!(spread.len() > 5, "{} points", spread.len());
    let total: Vector3<f64> = spread.iter().map(|s| Vector3::from(s.force_n)).sum();
    assert!((total - Vector3::from(f.force_n)).norm() < 1e-12, "{total:?}");
    for s in &spread {
        assert!((Vector3::from(s.point_mm) - p).norm() < 8.0);
    }
    // The moment about the probe point: the patch's weighted centre lies near it (tolerance:
    // a quarter of the radius, the offset on a curved surface).
    let centre: Vector3<f64> = spread
        .iter()
        .map(|s| Vector3::from(s.point_mm) * (Vector3::from(s.force_n).dot(&total) / total.norm_squared()))
        .sum();
    assert!((centre - p).norm() < 2.0, "patch centre {:.2} mm from the probe", (centre - p).norm());
    // Radius 0: the point load as given.
    assert_eq!(spread_forces(&mesh, std::slice::from_ref(&f), 0.0), vec![f]);
}

#[test]
fn a_doomed_set_up_is_refused_by_the_preflight_before_anything_is_written_and_force_goes_on() {
    use umesh_core::dataset::{DatasetError, PreflightCheck, PreflightSettings, run_generate_checked};
    let seg = phantom();
    // Held by a tube through the organ's middle (the portal vein), every pressing pattern
    // squeezes the tissue against it: SVK collapses long before a 10 mm mean displacement
    // when nothing limits the strain (the default limit makes this set-up work: the next test).
    let mut config =
        DatasetConfig::paper(FixedRegion::Label { label: umesh_core::phantom::PORTAL_VEIN, distance_mm: 6.0 });
    config.forces.max_strain = 0.0;
    config.samples = 1000;
    let dir = tmp("doomed");
    let seen = std::sync::Mutex::new(Vec::new());
    // The job is cancelled once the check has reported: a check that let it through fails
    // here at once instead of computing 1000 samples.
    let cancel = Cancel::new();
    let report = |p: &umesh_core::dataset::Preflight| {
        seen.lock().unwrap().push(p.clone());
        cancel.cancel();
    };
    let settings = PreflightSettings { samples: 6, ..Default::default() };
    let check = PreflightCheck { settings: settings.clone(), force: false, report: &report };
    // Bounded work: the grid, eight reference solves and six samples (the time on 2 cores is
    // a README figure, measured by `umesh dataset generate`, not asserted here).
    let e = run_generate_checked(&seg, &dir, &config, ShardSelection::all(), Some(&check), &Progress::none(), &cancel)
        .unwrap_err();
    let DatasetError::Refused { message, preflight } = e else { panic!("not refused: {e}") };
    // Refused on either rule: few accepted, or the accepted far short of their targets (with
    // the floor at a tenth of the target, an organ that collapses keeps its early states).
    assert!(preflight.is_doomed(&settings) && preflight.samples == 6, "{preflight:?}");
    assert!(
        message.contains("Likely cause") && message.contains("--force") && message.contains("--target-displacement-mm"),
        "{message}"
    );
    assert!(message.contains("--max-strain 0.12"), "the limit that makes this set-up work is not named: {message}");
    assert!(!dir.exists(), "a refused job wrote {}", dir.display());
    assert_eq!(seen.lock().unwrap().len(), 1);
    // Forced, the job runs (a short one here, still longer than the check).
    config.samples = 7;
    config.shard_size = 7;
    let report = |p: &umesh_core::dataset::Preflight| seen.lock().unwrap().push(p.clone());
    let forced = PreflightCheck { force: true, report: &report, ..check };
    let r = run_generate_checked(
        &seg,
        &dir,
        &config,
        ShardSelection::all(),
        Some(&forced),
        &Progress::none(),
        &Cancel::new(),
    )
    .unwrap();
    assert!(r.complete && r.samples_computed == 7 && r.preflight.is_some(), "{r:?}");
}

#[test]
fn the_preflight_refuses_only_when_its_samples_rule_out_the_acceptance_needed() {
    use umesh_core::dataset::wilson_upper;
    let z = 1.645;
    // Reference values of the one-sided 95 % Wilson bound (to 1e-3).
    for (k, n, upper) in [(13, 16, 0.922), (12, 16, 0.883), (4, 6, 0.883), (5, 6, 0.962), (4, 16, 0.455)] {
        assert!((wilson_upper(k, n, z) - upper).abs() < 1e-3, "{k}/{n}: {}", wilson_upper(k, n, z));
    }
    assert!((wilson_upper(16, 16, z) - 1.0).abs() < 1e-12);
    assert_eq!(wilson_upper(0, 0, z), 1.0);
    // At 90 % needed, 16 samples refuse at 12 accepted or fewer, 6 at 4 or fewer.
    assert!((0..=16).all(|k| (wilson_upper(k, 16, z) < 0.9) == (k <= 12)));
    assert!((0..=6).all(|k| (wilson_upper(k, 6, z) < 0.9) == (k <= 4)));
}

#[test]
fn a_preflight_whose_samples_stop_far_short_of_their_targets_is_refused_even_when_all_are_accepted() {
    use umesh_core::dataset::{Preflight, PreflightSettings};
    let settings = PreflightSettings::default();
    let p = |accepted: usize, achieved: Option<f64>| Preflight {
        samples: 16,
        accepted,
        below_target: 0,
        strain_limited: 0,
        strain_limited_factor: None,
        rejected: Default::default(),
        acceptance: accepted as f64 / 16.0,
        achieved_over_target: achieved,
        sample_seconds: 1.0,
        threads: 2,
        projected_minutes: 10.0,
        seconds: 30.0,
        visible_fraction: 0.4,
        fixed_fraction: 0.05,
        fixed_nodes: 100,
        nodes: 2000,
        cause: Some("a cause".into()),
    };
    // The sweep's worst configuration averages 0.87 of its target: goes on.
    assert!(p(16, Some(0.87)).refusal(&settings).is_none());
    // 16 of 16 accepted, each at under half its target: refused, and the message says which rule.
    let m = p(16, Some(0.43)).refusal(&settings).expect("not refused");
    assert!(
        m.contains("43 % of their target displacement") && m.contains("Likely cause: a cause") && m.contains("--force"),
        "{m}"
    );
    // No sample accepted: the acceptance rule (no ratio to judge).
    let m = p(0, None).refusal(&settings).expect("not refused");
    assert!(m.contains("store 0 % of its samples"), "{m}");
    assert!(PreflightSettings { min_achieved: 1.5, ..settings }.validate().is_err());
}

#[test]
fn an_organ_held_at_its_core_has_its_targets_lowered_to_the_strain_limit_and_its_samples_converge() {
    use umesh_core::dataset::{DatasetContext, LOCAL_STRAIN_FACTOR, run_stats};
    use umesh_core::fem::solver::FeSolver;
    let seg = phantom();
    let mut config =
        DatasetConfig::paper(FixedRegion::Label { label: umesh_core::phantom::PORTAL_VEIN, distance_mm: 6.0 });
    assert_eq!(config.forces.max_strain, umesh_core::loads::DEFAULT_MAX_STRAIN);
    config.samples = 6;
    config.shard_size = 6;
    // The lowered forces compress the organ as far as the limit allows and no further: the
    // linear solution of a lowered sample sits at the limit (over the organ or at its most
    // compressed cell), to 1e-9.
    let ctx = DatasetContext::prepare(&seg, &config, &Cancel::new()).unwrap();
    let mut solver = FeSolver::new(&ctx.grid, config.material, &ctx.fixed, config.solver.sequential()).unwrap();
    let mut lowered = 0;
    for i in 0..config.samples {
        let (mut forces, target, drawn) = ctx.calibrated_forces(&mut solver, &config, i, 1.0).unwrap();
        let family = ctx.sample_family(&config, i);
        let strain = ctx.calibrate_forces(&mut solver, &config, &mut forces, target, family).unwrap();
        let limit = config.forces.max_strain;
        match drawn {
            Some(d) => {
                lowered += 1;
                assert!(target < d, "sample {i}: lowered {target} from {d}");
                let at_limit = (strain.p95 - limit).abs().min((strain.max - LOCAL_STRAIN_FACTOR * limit).abs());
                assert!(at_limit < 1e-9 && strain.p95 <= limit + 1e-9, "sample {i}: {strain:?}");
            }
            None => assert!(strain.limit_factor(limit) == 1.0, "sample {i}: {strain:?} unlowered"),
        }
    }
    assert!(lowered >= 4, "only {lowered} of 6 lowered on an organ held at its core");
    // A contact alone, on an organ within the limit, is not limited.
    let contact_only = umesh_core::dataset::LinearStrain { p95: 0.05, max: 0.9 };
    assert_eq!(contact_only.limit_factor(0.12), 1.0);
    let both = umesh_core::dataset::LinearStrain { p95: 0.24, max: 0.9 };
    assert!((both.limit_factor(0.12) - 0.3 / 0.9).abs() < 1e-12);
    assert_eq!(both.limit_factor(0.0), 1.0);
    // Generated: every sample converges and the manifest keeps the drawn target beside the one solved.
    let dir = tmp("core_held");
    let r = run_generate(&seg, &dir, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    assert_eq!(r.accepted, 6, "{r:?}");
    let m = umesh_core::dataset::Manifest::read(&dir).unwrap();
    assert_eq!(m.samples.iter().filter(|s| s.drawn_target_mm.is_some()).count(), lowered);
    let st = run_stats(&dir).unwrap();
    assert_eq!(st.strain_limited, lowered);
    assert!(st.strain_limited_factor.as_ref().is_some_and(|f| f.max < 1.0), "{:?}", st.strain_limited_factor);
}

#[test]
fn probes_land_only_where_the_fixed_region_lets_the_surface_move() {
    use umesh_core::dataset::DatasetContext;
    let seg = phantom();
    // The right 30 % of the organ held (the sweep's box-30%): part of what the camera sees is held.
    let (lo, hi) = seg.organ_mask().world_bounds().unwrap();
    let e = hi - lo;
    let region = FixedRegion::Box {
        min_mm: [hi.x - 0.3 * e.x, lo.y - 1.0, lo.z - 1.0],
        max_mm: [hi.x + 1.0, hi.y + 1.0, hi.z + 1.0],
    };
    let mut config = DatasetConfig::paper(region);
    config.samples = 40;
    let ctx = DatasetContext::prepare(&seg, &config, &Cancel::new()).unwrap();
    let seen = ctx.visible.visible.iter().filter(|&&v| v).count();
    let pressable = ctx.pressable.iter().filter(|&&v| v).count();
    assert!(
        ctx.pressable.iter().zip(&ctx.visible.visible).all(|(p, v)| !p || *v),
        "a pressable triangle the camera does not see"
    );
    assert!(pressable < seen && pressable > seen / 4, "{pressable} of {seen} visible triangles pressable");
    // Every probe of every family moves some free node (within 1e-9 of a weight).
    for i in 0..config.samples {
        if ctx.sample_family(&config, i) == umesh_core::loads::LoadFamily::Gravity {
            continue; // a body force on every cell, held ones included
        }
        let (forces, _) = ctx.sample_forces(&config, i);
        for f in &forces {
            let emb = ctx.grid.embed(&Vector3::from(f.point_mm)).expect("a probe off the grid");
            assert!(
                emb.nodes.iter().zip(emb.weights).any(|(n, w)| w > 1e-9 && !ctx.fixed[*n as usize]),
                "sample {i}: a probe at {:?} presses only held nodes",
                f.point_mm
            );
        }
    }
}

#[test]
fn a_mixture_dataset_records_each_samples_family_and_pressing_only_configs_keep_their_hash() {
    use umesh_core::loads::{ForceSettings, LoadFamily};
    // Datasets made before families existed read as pressing only, and such a configuration
    // writes no `families` key (its hash and its shards are what they were).
    let mut old = serde_json::to_value(ForceSettings::energy_scale(100, 3.0)).unwrap();
    assert!(old.get("families").is_none(), "{old}");
    old.as_object_mut().unwrap().remove("families");
    let read: ForceSettings = serde_json::from_value(old).unwrap();
    assert_eq!(read.families, vec![LoadFamily::Pressing]);
    assert_eq!(ForceSettings::default().families, LoadFamily::ALL.to_vec());
    // Bad lists are refused with their reason.
    let mut bad = ForceSettings::default();
    bad.families.clear();
    assert!(bad.validate().unwrap_err().to_string().contains("no load family"));
    bad.families = vec![LoadFamily::Grasp, LoadFamily::Grasp];
    assert!(bad.validate().unwrap_err().to_string().contains("at most once"));
    assert!(ForceSettings::parse_families("pressing,twisting").unwrap_err().to_string().contains("twisting"));
    // A mixture: every sample's family in the manifest, the one `family_of` gives, and the
    // statistics count them.
    let config = small_config(12);
    let d = tmp("families");
    run_generate(&phantom(), &d, &config, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let m = umesh_core::dataset::Manifest::read(&d).unwrap();
    for s in &m.samples {
        assert_eq!(s.family, Some(config.forces.family_of(config.seed, s.index)), "sample {}", s.index);
    }
    let kinds: std::collections::BTreeSet<String> =
        m.samples.iter().map(|s| s.family.unwrap().name().to_string()).collect();
    assert!(kinds.len() >= 3, "12 samples drew only {kinds:?}");
    let st = umesh_core::dataset::run_stats(&d).unwrap();
    assert_eq!(st.families.iter().map(|f| f.1).sum::<usize>(), 12);
    assert_eq!(st.families.iter().map(|f| f.2).sum::<usize>(), st.accepted);
    // A pressing-only dataset records no family.
    let mut pressing = small_config(2);
    pressing.forces.families = vec![LoadFamily::Pressing];
    let d2 = tmp("families_pressing");
    run_generate(&phantom(), &d2, &pressing, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let m2 = umesh_core::dataset::Manifest::read(&d2).unwrap();
    assert!(m2.samples.iter().all(|s| s.family.is_none()));
    assert!(!std::fs::read_to_string(d2.join("manifest.json")).unwrap().contains("families"));
}

#[test]
fn a_sample_is_solved_with_the_material_drawn_for_it_and_the_manifest_records_it() {
    use umesh_core::dataset::{DatasetContext, run_stats};
    use umesh_core::fem::material::MaterialVariation;
    use umesh_core::fem::solver::FeSolver;
    use umesh_core::fem::{MaterialKind, MaterialParams};
    let seg = phantom();
    let svk = small_config(4);
    // Every sample drawn Neo-Hookean at Poisson 0.45: the same physics as a dataset of that material.
    let mut varied = small_config(4);
    varied.material_variation =
        Some(MaterialVariation { poisson_min: 0.45, poisson_max: 0.45, neo_hookean_fraction: 1.0 });
    let mut nh = small_config(4);
    nh.material = MaterialParams { kind: MaterialKind::NeoHookean, poisson: 0.45, ..Default::default() };
    // A configuration without variation serialises as before (its hash unchanged).
    assert!(!serde_json::to_string(&svk).unwrap().contains("material_variation"));
    let ctx = DatasetContext::prepare(&seg, &varied, &Cancel::new()).unwrap();
    let solver_for = |c: &DatasetConfig| FeSolver::new(&ctx.grid, c.material, &ctx.fixed, c.solver.clone()).unwrap();
    // One solver made for the dataset's SVK at 0.49 and reused across materials, as a worker
    // thread does: each sample's material and rest factor must follow it, both ways.
    let mut reused = solver_for(&varied);
    let solve = |solver: &mut FeSolver, c: &DatasetConfig, k: usize| {
        let r = ctx.solve_sample(solver, c, k, 1.0, 0.8, &Cancel::new());
        r.solution.expect("converged").displacement_mm
    };
    for (c, k) in [(&varied, 0usize), (&svk, 1), (&varied, 1), (&svk, 0)] {
        let reference = if c.material_variation.is_some() {
            solve(&mut solver_for(&nh), &nh, k)
        } else {
            solve(&mut solver_for(c), c, k)
        };
        let u = solve(&mut reused, c, k);
        let scale = reference.iter().map(|v| v.norm()).fold(0.0, f64::max);
        let diff = u.iter().zip(&reference).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
        // Tolerance: the Newton tolerance, relative to the largest displacement.
        assert!(scale > 1.0 && diff < 1e-6 * scale, "sample {k}: {diff} mm apart of {scale} mm");
    }
    // The drawn material differs from the dataset's: Neo-Hookean at 0.45 does not move as SVK at 0.49.
    let (a, b) = (solve(&mut solver_for(&nh), &nh, 0), solve(&mut solver_for(&svk), &svk, 0));
    assert!(a.iter().zip(&b).map(|(x, y)| (x - y).norm()).fold(0.0, f64::max) > 1e-3);
    // Recorded per sample, counted by `stats`.
    let dir = tmp("materials");
    run_generate(&seg, &dir, &varied, ShardSelection::all(), &Progress::none(), &Cancel::new()).unwrap();
    let ds = Dataset::open(&dir).unwrap();
    assert!(ds.manifest.samples.iter().all(|s| s.material == Some(nh.material)), "{:?}", ds.manifest.samples);
    let st = run_stats(&dir).unwrap();
    assert_eq!(st.materials.len(), 1);
    let (kind, n, accepted, lo, hi) = st.materials[0];
    assert_eq!((kind, n, lo, hi), (MaterialKind::NeoHookean, 4, 0.45, 0.45));
    assert_eq!(accepted, st.accepted);
}

#[test]
fn a_resumed_jobs_time_left_counts_only_the_work_done_in_this_run() {
    // A job resumed at 500 of 1000 units that then does 10 units a second: 45 s left at 550,
    // to 1e-9 s; counting the 500 earlier units as this run's would say 4.1 s.
    let t0 = std::time::Instant::now();
    let at = |s: f64| t0 + std::time::Duration::from_secs_f64(s);
    let mut eta = Eta::new();
    eta.observe(500, at(0.0));
    assert_eq!(eta.seconds_left(500, 1000, at(0.0)), None, "no rate before this run has done a unit");
    eta.observe(550, at(5.0));
    let rate = eta.rate_per_s(550, at(5.0)).unwrap();
    assert!((rate - 10.0).abs() < 1e-9, "rate {rate} units/s, expected 10");
    let left = eta.seconds_left(550, 1000, at(5.0)).unwrap();
    assert!((left - 45.0).abs() < 1e-9, "{left} s left at 550 of 1000, expected 45");
    assert_eq!(eta.seconds_left(1000, 1000, at(50.0)), None, "a finished job has nothing left");
}
