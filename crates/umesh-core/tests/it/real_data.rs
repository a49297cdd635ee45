//! Opt-in checks on the real data in `../shared/data` (skipped, with a message, when the
//! folder is not beside the checkout).

use std::path::PathBuf;
use umesh_core::grid::{GridSettings, run_grid};
use umesh_core::nifti_io::ReadOptions;
use umesh_core::segmentation::{load_meshes, load_nifti};
use umesh_core::{Cancel, Progress};

fn data_dir() -> Option<PathBuf> {
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data");
    if d.is_dir() {
        Some(d)
    } else {
        eprintln!("SKIPPED: {} not found; the real-data checks did not run", d.display());
        None
    }
}

#[test]
fn totalsegmentator_liver_grid_volume_matches_the_voxel_volume() {
    let Some(d) = data_dir() else { return };
    let path = d.join("totalsegmentator/example_seg.nii.gz");
    let seg = load_nifti(&path, &[5], &[63, 64], &ReadOptions::default()).unwrap();
    assert_eq!(seg.volume.dims, [122, 101, 30]);
    assert_eq!(seg.label_name(5), "liver");
    assert_eq!(seg.label_name(63), "inferior_vena_cava");
    let voxel_volume = seg.organ_mask().volume_mm3();
    for h in [7.0, 5.0] {
        let out =
            run_grid(&seg, &GridSettings { cell_size_mm: h, ..Default::default() }, &Progress::none(), &Cancel::new())
                .unwrap();
        let err = (out.stats.grid_volume_mm3 - voxel_volume) / voxel_volume;
        eprintln!(
            "real liver, h = {h} mm: grid {:.0} mm^3 vs voxels {voxel_volume:.0} mm^3 ({:+.2} %), {} cells, {} nodes, padded {:?}",
            out.stats.grid_volume_mm3,
            100.0 * err,
            out.stats.cells,
            out.stats.nodes,
            out.stats.padded_shape
        );
        assert!(err.abs() < 0.02, "h = {h}: {err}");
    }
    // TotalSegmentator's own statistics give about 1 062 450 mm^3 for the liver.
    assert!((voxel_volume - 1_062_450.0).abs() / 1_062_450.0 < 0.02, "{voxel_volume}");
    // A missing label is a clear error.
    let e = load_nifti(&path, &[200], &[], &ReadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("label 200") && e.contains("example_seg.nii.gz"), "{e}");
}

#[test]
fn mr_segmentation_with_lps_affine_loads_in_ras() {
    let Some(d) = data_dir() else { return };
    let seg =
        load_nifti(&d.join("totalsegmentator/example_seg_mr.nii.gz"), &[5], &[], &ReadOptions::default()).unwrap();
    let m = seg.volume.world_from_voxel;
    // LPS storage: the affine's x and y columns point to -x and -y of RAS or are diagonal-free;
    // either way the volume is positive and finite.
    assert!(m.iter().all(|v| v.is_finite()));
    assert!(seg.organ_mask().volume_mm3() > 100_000.0);
    let out = run_grid(&seg, &GridSettings::default(), &Progress::none(), &Cancel::new()).unwrap();
    let err = (out.stats.grid_volume_mm3 - seg.organ_mask().volume_mm3()) / seg.organ_mask().volume_mm3();
    assert!(err.abs() < 0.03, "{err}");
}

#[test]
fn sofa_liver_meshes_are_closed_and_voxelise() {
    let Some(d) = data_dir() else { return };
    for name in ["liver.obj", "liver-smooth.obj"] {
        // Scene units taken as centimetres.
        let path = d.join("sofa").join(name);
        let mesh = umesh_core::mesh_io::read_closed_mesh(&path).unwrap();
        let mesh_volume = mesh.signed_volume_mm3() * 1000.0;
        let seg = load_meshes(&path, &[], 1.0, 10.0).unwrap();
        let vol = seg.organ_mask().volume_mm3();
        eprintln!("{name}: mesh volume {mesh_volume:.0} mm^3, voxelised {vol:.0} mm^3");
        assert!((vol - mesh_volume).abs() / mesh_volume < 0.05, "{name}: {vol} vs {mesh_volume}");
        let out = run_grid(
            &seg,
            &GridSettings { cell_size_mm: 3.0, ..Default::default() },
            &Progress::none(),
            &Cancel::new(),
        )
        .unwrap();
        assert!(out.stats.cells > 100);
    }
}
