//! Grid, surfaces and phantom: analytic volumes, embedding, padding, watertight surfaces,
//! determinism of the phantom.

use nalgebra::{Matrix4, Point3, Vector3};
use umesh_core::grid::{self, CellKind, GridSettings, ImmersedGrid};
use umesh_core::npz::Npz;
use umesh_core::phantom::{self, PhantomSettings};
use umesh_core::surface::{SurfaceSettings, extract_surface};
use umesh_core::volume::Mask;
use umesh_core::{Cancel, Progress};

fn ellipsoid_grid(r: Vector3<f64>, h: f64, levels: u32) -> ImmersedGrid {
    let s = GridSettings { cell_size_mm: h, subdivisions: levels, samples_per_leaf_axis: 2, pooling_steps: 3 };
    let inside = move |p: &Point3<f64>| (p.coords.component_div(&r)).norm_squared() <= 1.0;
    // An off-centre box so the lattice is not symmetric about the shape.
    grid::build(
        -r - Vector3::new(0.3, 0.1, 0.7),
        r + Vector3::new(0.2, 0.5, 0.1),
        inside,
        &s,
        &Progress::none(),
        &Cancel::new(),
    )
    .unwrap()
}

fn rel_err(g: &ImmersedGrid, r: Vector3<f64>) -> f64 {
    let exact = 4.0 / 3.0 * std::f64::consts::PI * r.x * r.y * r.z;
    (g.volume_mm3() - exact).abs() / exact
}

#[test]
fn sphere_and_ellipsoid_volumes_converge_with_cell_size() {
    for r in [Vector3::repeat(50.0), Vector3::new(60.0, 40.0, 25.0)] {
        let errs: Vec<f64> = [10.0, 5.0, 2.5].iter().map(|&h| rel_err(&ellipsoid_grid(r, h, 1), r)).collect();
        eprintln!("radii {r:?}: volume errors at h = 10, 5, 2.5 mm (1 level): {errs:?}");
        assert!(errs[2] < errs[0], "{errs:?}");
        assert!(errs[2] < 0.01, "{errs:?}");
    }
}

#[test]
fn volume_error_decreases_with_subdivision_levels() {
    let r = Vector3::new(60.0, 40.0, 25.0);
    let errs: Vec<f64> = (0..4).map(|l| rel_err(&ellipsoid_grid(r, 10.0, l), r)).collect();
    eprintln!("ellipsoid volume errors at h = 10 mm, levels 0..3: {errs:?}");
    assert!(errs[3] < errs[1] && errs[1] < errs[0], "{errs:?}");
    assert!(errs[3] < 0.01, "{errs:?}");
}

#[test]
fn cells_are_classified_and_quadrature_weights_match_fractions() {
    let g = ellipsoid_grid(Vector3::repeat(30.0), 6.0, 1);
    let vol = g.cell_volume_mm3();
    for (c, cell) in g.cells.iter().enumerate() {
        let w: f64 = g.quadrature[g.qp_offsets[c]..g.qp_offsets[c + 1]].iter().map(|q| q.weight_mm3).sum();
        assert!((w - cell.volume_fraction * vol).abs() < 1e-9 * vol);
        match cell.kind {
            CellKind::Inside => assert_eq!(cell.volume_fraction, 1.0),
            CellKind::Boundary => assert!(cell.volume_fraction > 0.0 && cell.volume_fraction < 1.0),
        }
        for q in &g.quadrature[g.qp_offsets[c]..g.qp_offsets[c + 1]] {
            assert!(q.xi.iter().all(|x| x.abs() <= 1.0));
        }
    }
    assert!(g.cells.iter().any(|c| c.kind == CellKind::Boundary));
    assert!(g.cells.iter().any(|c| c.kind == CellKind::Inside));
}

#[test]
fn a_coarsened_grid_holds_the_same_volume_and_quadrature_on_the_same_lattice_within_1e9() {
    let g = ellipsoid_grid(Vector3::new(60.0, 40.0, 25.0), 5.0, 1);
    for factor in [2, 3] {
        let c = g.coarsened(factor);
        // The same integration points, moved into larger cells: the same volume and first moment.
        let moment = |g: &ImmersedGrid| -> Vector3<f64> {
            g.quadrature
                .iter()
                .map(|q| {
                    let cell = &g.cells[q.cell as usize];
                    let lattice =
                        Vector3::from(cell.ijk.map(|v| v as f64)) + Vector3::from(q.xi.map(|x| 0.5 * (x + 1.0)));
                    (g.origin_mm + lattice * g.cell_size_mm) * q.weight_mm3
                })
                .sum()
        };
        assert!((c.volume_mm3() - g.volume_mm3()).abs() < 1e-9 * g.volume_mm3(), "factor {factor}");
        assert!((moment(&c) - moment(&g)).norm() < 1e-9 * g.volume_mm3() * 60.0, "factor {factor}");
        assert_eq!(c.cell_size_mm, factor as f64 * g.cell_size_mm);
        assert!(c.node_count() * 3 < g.node_count(), "factor {factor}: {} of {} nodes", c.node_count(), g.node_count());
        let vol = c.cell_volume_mm3();
        for (k, cell) in c.cells.iter().enumerate() {
            let w: f64 = c.quadrature[c.qp_offsets[k]..c.qp_offsets[k + 1]].iter().map(|q| q.weight_mm3).sum();
            assert!((w - cell.volume_fraction * vol).abs() < 1e-9 * vol, "factor {factor}, cell {k}");
            assert!(
                c.quadrature[c.qp_offsets[k]..c.qp_offsets[k + 1]].iter().all(|q| q.xi.iter().all(|x| x.abs() <= 1.0))
            );
        }
        // Every coarse node lies on a fine node's place; every fine node sits in the coarse grid.
        for n in 0..c.node_count() {
            let p = c.node_position(n);
            let lattice = (p - g.origin_mm) / g.cell_size_mm;
            assert!(lattice.iter().all(|v| (v - v.round()).abs() < 1e-9), "factor {factor}, node {n}");
        }
        for p in g.node_positions() {
            let e = c.embed(&p).expect("embedded");
            let q: Vector3<f64> = e.nodes.iter().zip(e.weights).map(|(&n, w)| c.node_position(n as usize) * w).sum();
            assert!((q - p).norm() < 1e-9, "factor {factor}: {p:?} -> {q:?}");
        }
    }
}

#[test]
fn embedding_weights_sum_to_one_and_reproduce_positions() {
    let g = ellipsoid_grid(Vector3::new(40.0, 30.0, 20.0), 5.0, 1);
    let mut rng = umesh_core::rng::SplitMix64(5);
    let mut checked = 0;
    for _ in 0..2000 {
        let p = Vector3::new(rng.next_f64() - 0.5, rng.next_f64() - 0.5, rng.next_f64() - 0.5)
            .component_mul(&Vector3::new(80.0, 60.0, 40.0));
        if (p.component_div(&Vector3::new(40.0, 30.0, 20.0))).norm() > 1.0 {
            continue;
        }
        let e = g.embed(&p).unwrap();
        let sum: f64 = e.weights.iter().sum();
        assert!((sum - 1.0).abs() < 1e-12);
        assert!(e.weights.iter().all(|&w| (-1e-12..=1.0 + 1e-12).contains(&w)));
        let q: Vector3<f64> = e.nodes.iter().zip(e.weights).map(|(&n, w)| g.node_position(n as usize) * w).sum();
        assert!((q - p).norm() < 1e-9, "{p:?} -> {q:?}");
        checked += 1;
    }
    assert!(checked > 500);
    // Nodes embed onto themselves.
    for n in (0..g.node_count()).step_by(7) {
        let e = g.embed(&g.node_position(n)).unwrap();
        let q: Vector3<f64> = e.nodes.iter().zip(e.weights).map(|(&m, w)| g.node_position(m as usize) * w).sum();
        assert!((q - g.node_position(n)).norm() < 1e-9);
    }
}

#[test]
fn padded_shape_is_a_multiple_of_two_to_the_pooling_steps() {
    for k in 0..5 {
        let s = GridSettings { cell_size_mm: 7.0, pooling_steps: k, ..Default::default() };
        let r = Vector3::new(70.0, 50.0, 40.0);
        let g = grid::build(
            -r,
            r,
            move |p: &Point3<f64>| p.coords.component_div(&r).norm() <= 1.0,
            &s,
            &Progress::none(),
            &Cancel::new(),
        )
        .unwrap();
        let p = g.padded_shape();
        for a in 0..3 {
            assert_eq!(p[a] % (1 << k), 0);
            assert!(p[a] >= g.node_dims()[a] && p[a] < g.node_dims()[a] + (1 << k));
        }
        // Dense indices are distinct and in range.
        let mut seen = std::collections::HashSet::new();
        for n in 0..g.node_count() {
            let d = g.dense_index(n);
            assert!(d < p[0] * p[1] * p[2]);
            assert!(seen.insert(d));
        }
    }
}

#[test]
fn grid_npz_round_trip_preserves_everything() {
    let g = ellipsoid_grid(Vector3::new(30.0, 20.0, 15.0), 5.0, 1);
    let bytes = umesh_core::npz::encode_npz(&g.to_npz_arrays()).unwrap();
    let npz = Npz::from_bytes(std::path::Path::new("mem.npz"), &bytes).unwrap();
    let back = ImmersedGrid::from_npz(&npz).unwrap();
    assert_eq!(back.cells.len(), g.cells.len());
    assert_eq!(back.node_ijk, g.node_ijk);
    assert_eq!(back.quadrature, g.quadrature);
    assert_eq!(back.padded_shape(), g.padded_shape());
    assert!((back.origin_mm - g.origin_mm).norm() < 1e-12);
}

fn sphere_mask(radius_mm: f64, spacing_mm: f64) -> Mask {
    let n = (2.0 * radius_mm / spacing_mm).ceil() as usize + 6;
    let mut m = Matrix4::new_scaling(spacing_mm);
    m[(3, 3)] = 1.0;
    let c = n as f64 * spacing_mm / 2.0;
    for i in 0..3 {
        m[(i, 3)] = -c;
    }
    let mut data = vec![false; n * n * n];
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let p = m.transform_point(&Point3::new(i as f64, j as f64, k as f64));
                data[i + n * (j + n * k)] = p.coords.norm() <= radius_mm;
            }
        }
    }
    Mask { dims: [n, n, n], data, world_from_voxel: m }
}

#[test]
fn surfaces_are_watertight_with_outward_normals() {
    let mask = sphere_mask(20.0, 1.0);
    for step in [1, 2] {
        let mesh = extract_surface(&mask, &SurfaceSettings { step, ..Default::default() });
        let t = mesh.topology();
        assert!(t.is_watertight(), "step {step}: {t:?}");
        let exact = 4.0 / 3.0 * std::f64::consts::PI * 20f64.powi(3);
        let v = mesh.signed_volume_mm3();
        assert!(v > 0.0, "normals point inward");
        assert!((v - exact).abs() / exact < 0.06, "volume {v} vs {exact}");
        let normals = mesh.vertex_normals();
        let outward = mesh.positions.iter().zip(&normals).filter(|(p, n)| p.dot(n) > 0.0).count();
        assert_eq!(outward, mesh.positions.len());
    }
    // The phantom's labels too.
    let vol = phantom::generate(&PhantomSettings { spacing_mm: 3.0, seed: 7 });
    for labels in [phantom::ORGAN_LABELS.to_vec(), vec![phantom::PORTAL_VEIN], vec![phantom::TUMOURS[0]]] {
        let mesh = extract_surface(&vol.mask(&labels), &SurfaceSettings::default());
        assert!(mesh.topology().is_watertight(), "labels {labels:?}");
        assert!(mesh.signed_volume_mm3() > 0.0);
    }
}

#[test]
fn phantom_generation_is_deterministic_and_matches_the_bundled_asset() {
    let a = phantom::generate(&PhantomSettings { spacing_mm: 3.0, seed: 7 });
    let b = phantom::generate(&PhantomSettings { spacing_mm: 3.0, seed: 7 });
    assert_eq!(a.data, b.data);
    let ea = umesh_core::nifti_io::encode_nifti1(&a, umesh_core::nifti_io::WriteType::U8);
    let eb = umesh_core::nifti_io::encode_nifti1(&b, umesh_core::nifti_io::WriteType::U8);
    assert_eq!(ea, eb);
    // Different seeds give different vessel trees.
    let c = phantom::generate(&PhantomSettings { spacing_mm: 3.0, seed: 8 });
    assert_ne!(a.data, c.data);
    // The committed asset is exactly what `umesh phantom` writes.
    let asset = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/../../assets/phantom.nii.gz")).unwrap();
    let bundled =
        umesh_core::nifti_io::read_volume_bytes(std::path::Path::new("phantom"), &asset, &Default::default()).unwrap();
    let fresh = phantom::generate(&PhantomSettings::default());
    assert_eq!(bundled.dims, fresh.dims);
    assert_eq!(bundled.data, fresh.data);
    // Liver-like size: about 20 x 14 x 12 cm.
    let (lo, hi) = fresh.mask(&phantom::ORGAN_LABELS).world_bounds().unwrap();
    let ext = hi - lo;
    assert!(
        ext.x > 180.0 && ext.x < 240.0 && ext.y > 110.0 && ext.y < 170.0 && ext.z > 90.0 && ext.z < 150.0,
        "{ext:?}"
    );
    let counts = fresh.label_counts();
    for l in [
        phantom::LIVER,
        phantom::VENA_CAVA,
        phantom::PORTAL_VEIN,
        phantom::TUMOURS[0],
        phantom::TUMOURS[1],
        phantom::TUMOURS[2],
    ] {
        assert!(counts.get(&l).copied().unwrap_or(0) > 100, "label {l} missing");
    }
}

#[test]
fn grid_build_is_cancellable_and_rejects_bad_settings() {
    let r = Vector3::repeat(30.0);
    let inside = move |p: &Point3<f64>| p.coords.norm() <= 30.0;
    let cancel = Cancel::new();
    cancel.cancel();
    assert!(matches!(
        grid::build(-r, r, inside, &GridSettings::default(), &Progress::none(), &cancel),
        Err(grid::GridError::Cancelled(_))
    ));
    for bad in [
        GridSettings { cell_size_mm: 0.0, ..Default::default() },
        GridSettings { cell_size_mm: f64::NAN, ..Default::default() },
        GridSettings { subdivisions: 9, ..Default::default() },
    ] {
        assert!(matches!(
            grid::build(-r, r, inside, &bad, &Progress::none(), &Cancel::new()),
            Err(grid::GridError::Settings(_))
        ));
    }
    let tiny = GridSettings { cell_size_mm: 0.001, ..Default::default() };
    assert!(matches!(
        grid::build(-r, r, inside, &tiny, &Progress::none(), &Cancel::new()),
        Err(grid::GridError::TooLarge { .. })
    ));
    // 0.5 mm cells: 1.7 M box cells pass the box limit, and with 4 subdivisions (32^3 inside
    // tests each) would classify for hours: refused before any work, naming the options.
    let fine = GridSettings { cell_size_mm: 0.5, subdivisions: 4, ..Default::default() };
    let e = grid::build(-r, r, inside, &fine, &Progress::none(), &Cancel::new()).unwrap_err();
    assert!(matches!(e, grid::GridError::TooMuchWork { .. }) && e.to_string().contains("--subdivisions"), "{e}");
    let empty = Mask { dims: [4, 4, 4], data: vec![false; 64], world_from_voxel: Matrix4::identity() };
    assert!(matches!(
        ImmersedGrid::from_mask(&empty, &GridSettings::default(), &Progress::none(), &Cancel::new()),
        Err(grid::GridError::EmptyMask)
    ));
}

#[test]
fn ray_cast_finds_the_nearest_surface_point_of_a_sphere() {
    // A sphere of radius 40 mm from the marching-tetrahedra surface of a voxel ball.
    let mut w = Matrix4::new_scaling(2.0);
    w[(3, 3)] = 1.0;
    let c = Vector3::new(60.0, 60.0, 60.0);
    let mut data = Vec::with_capacity(61 * 61 * 61);
    for k in 0..61 {
        for j in 0..61 {
            for i in 0..61 {
                data.push((Vector3::new(i as f64, j as f64, k as f64) * 2.0 - c).norm() <= 40.0);
            }
        }
    }
    let mask = Mask { dims: [61, 61, 61], data, world_from_voxel: w };
    let s = extract_surface(&mask, &SurfaceSettings::default());
    for dir in [Vector3::new(1.0, 0.0, 0.0), Vector3::new(-0.3, 0.5, 0.8)] {
        let origin = c - dir.normalize() * 200.0;
        let hit = s.ray_cast(&origin, &dir).expect("the ray hits the sphere");
        // The nearest hit is the near side: 200 - 40 mm away, within the surface's accuracy.
        assert!((hit.distance_mm - 160.0).abs() < 1.5, "{}", hit.distance_mm);
        assert!(hit.normal.dot(&dir.normalize()) < -0.9, "outward normal faces the ray");
    }
    assert!(s.ray_cast(&(c + Vector3::new(0.0, 0.0, 100.0)), &Vector3::z()).is_none(), "a ray pointing away misses");
}
