//! FE verification: patch test, frame indifference, tangent vs finite differences,
//! linear limit, cantilever vs Euler-Bernoulli, immersed vs conforming, Newton's rate.

use nalgebra::{Matrix3, Rotation3, Vector3};
use umesh_core::fem::assembly::{Assembler, ElementModel};
use umesh_core::fem::solver::FeSolver;
use umesh_core::fem::{
    BoundaryConditions, FemError, FixedRegion, HyperelasticMaterial, MaterialKind, MaterialParams, SolveMethod,
    SolverSettings, solve,
};
use umesh_core::grid::{self, GridSettings, ImmersedGrid};
use umesh_core::{Cancel, Progress};

fn box_grid(lo: Vector3<f64>, hi: Vector3<f64>, h: f64, sub: u32) -> ImmersedGrid {
    let s = GridSettings { cell_size_mm: h, subdivisions: sub, samples_per_leaf_axis: 2, pooling_steps: 0 };
    let inside = move |p: &nalgebra::Point3<f64>| (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]);
    // Build over exactly the box so cells conform when the box is a multiple of h.
    grid::build(lo, hi, inside, &s, &Progress::none(), &Cancel::new()).unwrap()
}

fn mat(kind: MaterialKind) -> MaterialParams {
    MaterialParams { kind, young_pa: 1.0e6, poisson: 0.3 }
}

fn rand_f(seed: u64) -> Matrix3<f64> {
    let mut r = umesh_core::rng::SplitMix64(seed);
    Matrix3::identity() + Matrix3::from_fn(|_, _| 0.2 * (r.next_f64() - 0.5))
}

#[test]
fn material_tangents_match_finite_differences_of_pk1() {
    for kind in [MaterialKind::StVenantKirchhoff, MaterialKind::NeoHookean, MaterialKind::Linear] {
        let m = mat(kind).material();
        for seed in 0..5 {
            let f = rand_f(seed);
            let (_, a) = m.pk1_and_tangent(&f);
            let eps = 1e-7;
            for k in 0..3 {
                for l in 0..3 {
                    let mut fp = f;
                    fp[(k, l)] += eps;
                    let mut fm = f;
                    fm[(k, l)] -= eps;
                    let d = (m.pk1(&fp) - m.pk1(&fm)) / (2.0 * eps);
                    for i in 0..3 {
                        for j in 0..3 {
                            let err = (a[(3 * i + j, 3 * k + l)] - d[(i, j)]).abs();
                            assert!(
                                err < 1e-6 * (1.0 + d[(i, j)].abs()) * m.lambda.max(1.0),
                                "{kind:?} dP{i}{j}/dF{k}{l}: {err}"
                            );
                        }
                    }
                }
            }
        }
    }
}

#[test]
fn pk1_is_the_derivative_of_the_energy_density() {
    for kind in [MaterialKind::StVenantKirchhoff, MaterialKind::NeoHookean, MaterialKind::Linear] {
        let m = mat(kind).material();
        let f = rand_f(11);
        let p = m.pk1(&f);
        let eps = 1e-7;
        for k in 0..3 {
            for l in 0..3 {
                let mut fp = f;
                fp[(k, l)] += eps;
                let mut fm = f;
                fm[(k, l)] -= eps;
                let d = (m.energy_density(&fp) - m.energy_density(&fm)) / (2.0 * eps);
                assert!((d - p[(k, l)]).abs() < 1e-6 * m.lambda, "{kind:?} P{k}{l}: {d} vs {}", p[(k, l)]);
            }
        }
        // S is consistent with P = F S.
        assert!((f * m.pk2(&f) - p).norm() < 1e-9 * m.lambda, "{kind:?}");
    }
}

#[test]
fn svk_and_neo_hookean_give_zero_stress_under_rigid_rotation() {
    for kind in [MaterialKind::StVenantKirchhoff, MaterialKind::NeoHookean] {
        let m = mat(kind).material();
        let r = Rotation3::from_euler_angles(0.7, -1.1, 2.3).into_inner();
        assert!(m.pk2(&r).norm() < 1e-12, "{kind:?}: S = {}", m.pk2(&r));
        assert!(m.energy_density(&r).abs() < 1e-12);
    }
}

#[test]
fn assembled_tangent_matches_finite_differences_of_internal_forces() {
    // A box with a partial boundary layer so both regular and sub-cell quadrature are checked.
    let g = box_grid(Vector3::zeros(), Vector3::new(10.0, 7.0, 6.5), 2.5, 1);
    let n = g.node_count();
    let mut constrained = vec![false; 3 * n];
    for c in 0..3 {
        constrained[c] = true;
    }
    for kind in [MaterialKind::StVenantKirchhoff, MaterialKind::NeoHookean] {
        let m = mat(kind).material();
        let lin = mat(MaterialKind::Linear).material();
        let mut asm = Assembler::new(&g, &constrained, lin, 1e-4);
        let mut r = umesh_core::rng::SplitMix64(3);
        let u: Vec<Vector3<f64>> =
            (0..n).map(|_| Vector3::new(r.next_f64() - 0.5, r.next_f64() - 0.5, r.next_f64() - 0.5) * 0.3).collect();
        asm.assemble(ElementModel::Hyperelastic(m), &u, true);
        let k = asm.matrix().to_dense();
        let eps = 1e-6;
        let mut max_err: f64 = 0.0;
        let mut max_k: f64 = 0.0;
        for dof in [3usize, 7, 20, 3 * n - 1] {
            let (nd, c) = (dof / 3, dof % 3);
            let mut up = u.clone();
            up[nd][c] += eps;
            let mut um = u.clone();
            um[nd][c] -= eps;
            let fp = asm.assemble(ElementModel::Hyperelastic(m), &up, false).f_int;
            let fm = asm.assemble(ElementModel::Hyperelastic(m), &um, false).f_int;
            let col = asm.dofs.free_of[dof] as usize;
            for row_dof in 3..3 * n {
                let row = asm.dofs.free_of[row_dof] as usize;
                let fd = (fp[row_dof / 3][row_dof % 3] - fm[row_dof / 3][row_dof % 3]) / (2.0 * eps);
                max_err = max_err.max((k[(row, col)] - fd).abs());
                max_k = max_k.max(k[(row, col)].abs());
            }
        }
        assert!(max_err < 1e-6 * max_k, "{kind:?}: tangent error {max_err:e} vs scale {max_k:e}");
    }
}

/// Nodes on the face x = x0 of a grid.
fn face_nodes(g: &ImmersedGrid, axis: usize, value: f64) -> Vec<usize> {
    (0..g.node_count()).filter(|&n| (g.node_position(n)[axis] - value).abs() < 1e-9).collect()
}

#[test]
fn patch_test_reproduces_a_linear_displacement_field_exactly() {
    let g = box_grid(Vector3::zeros(), Vector3::new(10.0, 10.0, 10.0), 2.5, 1);
    let grad = Matrix3::new(1e-3, 2e-4, -3e-4, 5e-4, -2e-3, 1e-4, 0.0, 3e-4, 1.5e-3);
    let mut bc = BoundaryConditions::new(g.node_count());
    // Prescribe the field on the boundary; interior nodes must follow it exactly.
    for n in 0..g.node_count() {
        let p = g.node_position(n);
        if (0..3).any(|a| p[a].abs() < 1e-9 || (p[a] - 10.0).abs() < 1e-9) {
            bc.prescribed_mm.push((n, grad * p));
        }
    }
    let sol = solve(
        &g,
        &mat(MaterialKind::Linear),
        &bc,
        SolveMethod::Linear,
        &SolverSettings::default(),
        &Progress::none(),
        &Cancel::new(),
    )
    .unwrap();
    let err =
        (0..g.node_count()).map(|n| (sol.displacement_mm[n] - grad * g.node_position(n)).norm()).fold(0.0, f64::max);
    assert!(err < 1e-10, "patch test error {err:e} mm");
}

fn cantilever(
    h: f64,
    method: SolveMethod,
    kind: MaterialKind,
    tip_force_n: f64,
) -> (f64, ImmersedGrid, Vec<Vector3<f64>>) {
    let (l, b) = (100.0, 10.0);
    let g = box_grid(Vector3::zeros(), Vector3::new(l, b, b), h, 1);
    let mut bc = BoundaryConditions::new(g.node_count());
    bc.fix_region(&g, &FixedRegion::Nodes { nodes: face_nodes(&g, 0, 0.0) }, None).unwrap();
    let tip = face_nodes(&g, 0, l);
    // Consistent nodal loads of a uniform traction on the tip face (bilinear face elements).
    let per_axis = (b / h).round() as usize;
    let mut total = 0.0;
    for &n in &tip {
        let p = g.node_position(n);
        let wy = if p.y.abs() < 1e-9 || (p.y - b).abs() < 1e-9 { 0.5 } else { 1.0 };
        let wz = if p.z.abs() < 1e-9 || (p.z - b).abs() < 1e-9 { 0.5 } else { 1.0 };
        total += wy * wz;
        bc.forces_n[n] = Vector3::new(0.0, 0.0, -wy * wz);
    }
    assert_eq!(total, (per_axis * per_axis) as f64);
    for f in &mut bc.forces_n {
        *f *= tip_force_n / total;
    }
    let sol =
        solve(&g, &mat(kind), &bc, method, &SolverSettings::default(), &Progress::none(), &Cancel::new()).unwrap();
    let defl = tip.iter().map(|&n| -sol.displacement_mm[n].z).sum::<f64>() / tip.len() as f64;
    (defl, g, sol.displacement_mm)
}

#[test]
fn cantilever_converges_to_euler_bernoulli_under_refinement() {
    // L = 100 mm, 10 x 10 mm section, E = 1 MPa, nu = 0.3, tip load 0.01 N (linear regime).
    let p = 0.01;
    let e = 1.0; // N/mm^2
    let i = 10.0f64.powi(4) / 12.0;
    let exact = p * 100.0f64.powi(3) / (3.0 * e * i);
    let mut errs = Vec::new();
    for h in [5.0, 2.5, 1.25] {
        let (d, _, _) = cantilever(h, SolveMethod::Linear, MaterialKind::Linear, p);
        errs.push((d - exact).abs() / exact);
    }
    // Full-integration trilinear hexes lock in bending: the error falls with h.
    eprintln!("cantilever vs Euler-Bernoulli, relative errors at h = 5, 2.5, 1.25 mm: {errs:?}");
    assert!(errs[0] > errs[1] && errs[1] > errs[2], "errors {errs:?}");
    assert!(errs[2] < 0.05, "relative error at h = 1.25 mm: {:.3} (errors {errs:?})", errs[2]);
}

#[test]
fn svk_and_linear_agree_to_first_order_for_a_small_load() {
    let (dl, _, _) = cantilever(2.5, SolveMethod::Linear, MaterialKind::Linear, 1e-4);
    let (dn, _, _) = cantilever(2.5, SolveMethod::Newton, MaterialKind::StVenantKirchhoff, 1e-4);
    assert!((dl - dn).abs() / dl < 1e-3, "linear {dl} vs SVK {dn}");
    // And the difference shrinks with the load (second order).
    let (dl2, _, _) = cantilever(2.5, SolveMethod::Linear, MaterialKind::Linear, 1e-3);
    let (dn2, _, _) = cantilever(2.5, SolveMethod::Newton, MaterialKind::StVenantKirchhoff, 1e-3);
    let rel_small = (dl - dn).abs() / dl;
    let rel_big = (dl2 - dn2).abs() / dl2;
    assert!(rel_big > 5.0 * rel_small, "{rel_small:e} vs {rel_big:e}");
}

#[test]
fn newton_converges_quadratically_near_the_solution() {
    let (l, b, h) = (60.0, 10.0, 2.5);
    let g = box_grid(Vector3::zeros(), Vector3::new(l, b, b), h, 1);
    let mut bc = BoundaryConditions::new(g.node_count());
    bc.fix_region(&g, &FixedRegion::Nodes { nodes: face_nodes(&g, 0, 0.0) }, None).unwrap();
    let tip = face_nodes(&g, 0, l);
    for &n in &tip {
        bc.forces_n[n] = Vector3::new(0.0, 0.0, -0.3 / tip.len() as f64);
    }
    let settings = SolverSettings { residual_tol: 1e-12, correction_tol: 1e-12, ..Default::default() };
    let sol = solve(
        &g,
        &mat(MaterialKind::StVenantKirchhoff),
        &bc,
        SolveMethod::Newton,
        &settings,
        &Progress::none(),
        &Cancel::new(),
    )
    .unwrap();
    let last = sol.history.last().unwrap().increment;
    let res: Vec<f64> = sol.history.iter().filter(|r| r.increment == last).map(|r| r.residual).collect();
    assert!(
        sol.max_displacement_mm() > 5.0,
        "the load should be in the nonlinear regime: {}",
        sol.max_displacement_mm()
    );
    // Near the solution r_{k+1} <= C r_k^2: the log-ratio approaches 2.
    let tail: Vec<f64> = res.iter().copied().filter(|&r| r < 1e-2 && r > 1e-13).collect();
    assert!(tail.len() >= 2, "residuals {res:?}");
    let rate = tail[tail.len() - 1].ln() / tail[tail.len() - 2].ln();
    assert!(rate > 1.7, "observed order {rate:.2}, residuals {res:?}");
}

#[test]
fn large_load_is_reached_by_increments_and_impossible_load_is_reported() {
    let (l, b, h) = (60.0, 10.0, 2.5);
    let g = box_grid(Vector3::zeros(), Vector3::new(l, b, b), h, 1);
    let mut bc = BoundaryConditions::new(g.node_count());
    bc.fix_region(&g, &FixedRegion::Nodes { nodes: face_nodes(&g, 0, 0.0) }, None).unwrap();
    let tip = face_nodes(&g, 0, l);
    for &n in &tip {
        bc.forces_n[n] = Vector3::new(0.0, 0.0, -1.5 / tip.len() as f64);
    }
    let settings = SolverSettings { max_iterations: 8, line_search: false, ..Default::default() };
    let sol = solve(
        &g,
        &mat(MaterialKind::StVenantKirchhoff),
        &bc,
        SolveMethod::Newton,
        &settings,
        &Progress::none(),
        &Cancel::new(),
    )
    .unwrap();
    assert!(sol.increments > 1, "expected several increments, got {}", sol.increments);
    assert!(sol.displacement_mm.iter().all(|u| u.iter().all(|v| v.is_finite())));
    // Compressing the bar to nothing cannot converge: a clear error, never a result.
    let mut crush = BoundaryConditions::new(g.node_count());
    crush.fix_region(&g, &FixedRegion::Nodes { nodes: face_nodes(&g, 0, 0.0) }, None).unwrap();
    for &n in &tip {
        crush.prescribed_mm.push((n, Vector3::new(-70.0, 0.0, 0.0)));
    }
    let settings = SolverSettings { max_iterations: 6, max_halvings: 3, ..Default::default() };
    match solve(
        &g,
        &mat(MaterialKind::NeoHookean),
        &crush,
        SolveMethod::Newton,
        &settings,
        &Progress::none(),
        &Cancel::new(),
    ) {
        Err(FemError::NotConverged { history, reason }) => {
            assert!(!reason.is_empty());
            assert!(history.iter().all(|r| r.residual.is_finite()));
        }
        other => panic!("expected NotConverged, got {:?}", other.map(|s| s.max_displacement_mm())),
    }
}

/// Deflection at (0.9 L, b/2, b/2) of a cantilever (L = 100, b = 10 mm) built on a lattice
/// of cell size `h` shifted by `shift` cells (0: conforming), clamped at x <= 0, with the
/// tip load spread over an 11 x 11 lattice of points on the end face.
fn beam_deflection(h: f64, shift: f64, sub: u32) -> f64 {
    let (l, b, p) = (100.0, 10.0, 0.01);
    let pad = shift * h;
    let lo = Vector3::new(-pad, -pad, -pad);
    let hi = Vector3::new(l + if shift > 0.0 { 0.5 * h } else { 0.0 }, b + pad, b + pad);
    let s = GridSettings { cell_size_mm: h, subdivisions: sub, samples_per_leaf_axis: 2, pooling_steps: 0 };
    let inside =
        move |q: &nalgebra::Point3<f64>| q.x >= 0.0 && q.x <= l && q.y >= 0.0 && q.y <= b && q.z >= 0.0 && q.z <= b;
    let g = grid::build(lo, hi, inside, &s, &Progress::none(), &Cancel::new()).unwrap();
    let mut bc = BoundaryConditions::new(g.node_count());
    bc.fix_region(&g, &FixedRegion::Plane { normal: [1.0, 0.0, 0.0], offset_mm: 0.0, thickness_mm: 1e-9 }, None)
        .unwrap();
    for i in 0..11 {
        for j in 0..11 {
            let q = Vector3::new(l, b * i as f64 / 10.0, b * j as f64 / 10.0);
            bc.add_point_force(&g, &q, &Vector3::new(0.0, 0.0, -p / 121.0)).unwrap();
        }
    }
    let sol = solve(
        &g,
        &mat(MaterialKind::Linear),
        &bc,
        SolveMethod::Linear,
        &SolverSettings::default(),
        &Progress::none(),
        &Cancel::new(),
    )
    .unwrap();
    let e = g.embed(&Vector3::new(0.9 * l, b / 2.0, b / 2.0)).unwrap();
    e.nodes.iter().zip(e.weights).map(|(&n, w)| -sol.displacement_mm[n as usize].z * w).sum()
}

#[test]
fn immersed_beam_converges_to_the_conforming_beam() {
    // The same beam on lattices that do not conform (shifted by 0.37 cell) and that do:
    // the relative difference falls as cells shrink (5, 2.5, 1.25 mm).
    let mut diffs = Vec::new();
    for h in [5.0, 2.5, 1.25] {
        let conforming = beam_deflection(h, 0.0, 1);
        let immersed = beam_deflection(h, 0.37, 2);
        diffs.push((immersed - conforming).abs() / conforming);
    }
    eprintln!("immersed vs conforming, relative differences at h = 5, 2.5, 1.25 mm: {diffs:?}");
    assert!(diffs[2] < diffs[0], "relative differences {diffs:?}");
    assert!(diffs[2] < 0.05, "relative differences {diffs:?}");
}

#[test]
fn fe_solver_reuses_its_pattern_for_new_loads() {
    let g = box_grid(Vector3::zeros(), Vector3::new(40.0, 10.0, 10.0), 2.5, 1);
    let fixed: Vec<bool> = (0..g.node_count()).map(|n| g.node_position(n).x < 1e-9).collect();
    let mut solver =
        FeSolver::new(&g, mat(MaterialKind::StVenantKirchhoff), &fixed, SolverSettings::default()).unwrap();
    let mut bc = BoundaryConditions::new(g.node_count());
    bc.fixed = fixed;
    let tip = face_nodes(&g, 0, 40.0);
    let mut last = 0.0;
    for load in [0.01, 0.02] {
        for &n in &tip {
            bc.forces_n[n] = Vector3::new(0.0, -load / tip.len() as f64, 0.0);
        }
        let s = solver.solve(&bc, SolveMethod::Newton, &Progress::none(), &Cancel::new()).unwrap();
        assert!(s.max_displacement_mm() > last);
        last = s.max_displacement_mm();
    }
    // Co-rotational agrees with SVK for a moderate load within a few percent.
    let cr = solver.solve(&bc, SolveMethod::Corotational, &Progress::none(), &Cancel::new()).unwrap();
    assert!(
        (cr.max_displacement_mm() - last).abs() / last < 0.05,
        "corotational {} vs svk {last}",
        cr.max_displacement_mm()
    );
}

#[test]
fn an_exported_problem_carries_its_stabilisation_and_solves_the_same_only_with_it() {
    use umesh_core::fem::problem_io::{read_problem, write_problem};
    // A bar not aligned with its 6 mm cells: its end cells are partly outside, so stabilised.
    let grid = box_grid(Vector3::zeros(), Vector3::new(40.0, 10.0, 10.0), 6.0, 1);
    let m = mat(MaterialKind::Linear);
    let mut bc = BoundaryConditions::new(grid.node_count());
    bc.fix_region(&grid, &FixedRegion::Plane { normal: [1.0, 0.0, 0.0], offset_mm: 0.0, thickness_mm: 0.5 }, None)
        .unwrap();
    bc.add_point_force(&grid, &Vector3::new(39.0, 5.0, 5.0), &Vector3::new(0.0, 0.0, -2.0)).unwrap();
    let settings = SolverSettings::default();
    let alpha = settings.stabilization;
    let u0 = solve(&grid, &m, &bc, SolveMethod::Linear, &settings, &Progress::none(), &Cancel::new())
        .unwrap()
        .displacement_mm;
    let path = std::env::temp_dir().join(format!("umesh-stab-{}.npz", std::process::id()));
    write_problem(&path, &grid, &m, &bc, alpha).unwrap();
    let solve_file = |p: &umesh_core::fem::problem_io::LoadedProblem, stab: f64| -> Vec<Vector3<f64>> {
        let s = SolverSettings { stabilization: stab, ..SolverSettings::default() };
        let u = solve(&p.grid, &p.material, &p.bc, SolveMethod::Linear, &s, &Progress::none(), &Cancel::new())
            .unwrap()
            .displacement_mm;
        p.node_map.iter().map(|&g| u[g]).collect()
    };
    let max_diff =
        |a: &[Vector3<f64>], b: &[Vector3<f64>]| a.iter().zip(b).map(|(x, y)| (x - y).norm()).fold(0.0, f64::max);
    let p = read_problem(&path).unwrap();
    assert!((p.stabilization - alpha).abs() < 1e-12, "the file says alpha = {}", p.stabilization);
    let with = solve_file(&p, p.stabilization);
    assert!(max_diff(&with, &u0) < 1e-9, "the exported problem solves differently: {} mm", max_diff(&with, &u0));
    // Without the arrays the file has no stabilisation: another answer, and adding alpha back
    // (what the arrays said) gives the original one.
    let mut npz = umesh_core::npz::Npz::read(&path).unwrap();
    npz.arrays.remove("stab_cell");
    npz.arrays.remove("stab_scale");
    let arrays: Vec<(&str, umesh_core::npz::Array)> = npz.arrays.iter().map(|(k, v)| (k.as_str(), v.clone())).collect();
    let bare = std::env::temp_dir().join(format!("umesh-stab-bare-{}.npz", std::process::id()));
    umesh_core::npz::write_npz(&bare, &arrays).unwrap();
    let p2 = read_problem(&bare).unwrap();
    assert_eq!(p2.stabilization, 0.0);
    let without = solve_file(&p2, p2.stabilization);
    let scale = u0.iter().map(|v| v.norm()).fold(0.0, f64::max);
    assert!(
        max_diff(&without, &u0) > 1e-4 * scale,
        "the stabilisation made no difference: {}",
        max_diff(&without, &u0)
    );
    assert!(max_diff(&solve_file(&p2, alpha), &u0) < 1e-9);
}

#[test]
fn a_problem_file_with_bad_quadrature_data_is_refused_with_the_array_named() {
    use umesh_core::fem::problem_io::{read_problem, write_problem};
    let grid = box_grid(Vector3::zeros(), Vector3::new(20.0, 10.0, 10.0), 5.0, 1);
    let m = mat(MaterialKind::Linear);
    let mut bc = BoundaryConditions::new(grid.node_count());
    bc.fix_region(&grid, &FixedRegion::Plane { normal: [1.0, 0.0, 0.0], offset_mm: 0.0, thickness_mm: 0.5 }, None)
        .unwrap();
    let path = std::env::temp_dir().join(format!("umesh-quad-{}.npz", std::process::id()));
    write_problem(&path, &grid, &m, &bc, 0.01).unwrap();
    assert!(read_problem(&path).is_ok());
    let base = umesh_core::npz::Npz::read(&path).unwrap();
    let cases: [(&str, &dyn Fn(&mut Vec<f64>), &str); 4] = [
        ("qp_cell", &|v| v[3] = -1.0, "qp_cell[3]"),
        ("qp_cell", &|v| v[0] = 1e6, "qp_cell[0]"),
        ("qp_xi", &|v| v[4] = 1.5, "qp_xi[1]"),
        ("qp_w", &|v| v[2] = -v[2], "qp_w[2]"),
    ];
    for (name, edit, expect) in cases {
        let mut npz = base.clone();
        let a = npz.arrays.get_mut(name).unwrap();
        let mut v: Vec<f64> = match &a.data {
            umesh_core::npz::ArrayData::F64(v) => v.clone(),
            umesh_core::npz::ArrayData::I64(v) => v.iter().map(|&x| x as f64).collect(),
            other => panic!("{name}: {other:?}"),
        };
        edit(&mut v);
        a.data = umesh_core::npz::ArrayData::F64(v);
        let arrays: Vec<(&str, umesh_core::npz::Array)> =
            npz.arrays.iter().map(|(k, v)| (k.as_str(), v.clone())).collect();
        let bad = std::env::temp_dir().join(format!("umesh-quad-bad-{}.npz", std::process::id()));
        umesh_core::npz::write_npz(&bad, &arrays).unwrap();
        let e = read_problem(&bad).unwrap_err().to_string();
        assert!(e.contains(expect) && e.contains("umesh-quad-bad"), "{name}: {e}");
    }
    // Weights that sum to more than a cell's volume.
    let mut npz = base.clone();
    if let umesh_core::npz::ArrayData::F64(v) = &mut npz.arrays.get_mut("qp_w").unwrap().data {
        v.iter_mut().for_each(|w| *w *= 3.0);
    }
    let arrays: Vec<(&str, umesh_core::npz::Array)> = npz.arrays.iter().map(|(k, v)| (k.as_str(), v.clone())).collect();
    umesh_core::npz::write_npz(&path, &arrays).unwrap();
    let e = read_problem(&path).unwrap_err().to_string();
    assert!(e.contains("more than the cell's volume"), "{e}");
}

#[test]
fn compression_quantile_reads_a_uniform_strain_exactly_and_a_translation_or_a_stretch_as_zero() {
    let g = box_grid(Vector3::zeros(), Vector3::new(40.0, 30.0, 20.0), 5.0, 1);
    let pos = g.node_positions();
    let q_of = |u: &[Vector3<f64>], q: f64| umesh_core::fem::element::compression_quantile(&g, u, q);
    // u = diag(0.03, -0.01, 0.005) x: every cell is compressed by 0.01 (along y).
    let mixed: Vec<Vector3<f64>> = pos.iter().map(|p| Vector3::new(0.03 * p.x, -0.01 * p.y, 0.005 * p.z)).collect();
    for q in [0.05, 0.5, 0.95, 1.0] {
        assert!((q_of(&mixed, q) - 0.01).abs() < 1e-12, "q {q}: {}", q_of(&mixed, q));
    }
    let shift = vec![Vector3::new(4.0, -2.0, 7.0); pos.len()];
    assert!(q_of(&shift, 0.95).abs() < 1e-12);
    let stretch: Vec<Vector3<f64>> = pos.iter().map(|p| Vector3::new(0.05 * p.x, 0.0, 0.0)).collect();
    assert!(q_of(&stretch, 1.0).abs() < 1e-12);
    // Half the box squeezed by 0.08 along z, the other half at rest: the median is at the
    // boundary, the 95th percentile and the maximum read the squeeze.
    let half: Vec<Vector3<f64>> = pos.iter().map(|p| Vector3::new(0.0, 0.0, -0.08 * (p.z - 10.0).max(0.0))).collect();
    assert!((q_of(&half, 0.95) - 0.08).abs() < 1e-12 && (q_of(&half, 1.0) - 0.08).abs() < 1e-12);
    assert!(q_of(&half, 0.25).abs() < 1e-12);
}

/// A cube held at its base and pushed down on its top face: SVK collapses in compression, so a
/// target beyond the collapse has no equilibrium. The calibrated solve
/// keeps its converged state nearest the target when that moves at least a tenth of it (and
/// flags it as not reached), and reports an error, never a state, when nothing got that far.
#[test]
fn an_unreachable_target_keeps_the_largest_converged_state_of_at_least_a_tenth_of_it() {
    use umesh_core::fem::solver::{MIN_REACHED_FRACTION, MeanOver};
    let side = 20.0;
    let g = box_grid(Vector3::zeros(), Vector3::new(side, side, side), 5.0, 1);
    let fixed: Vec<bool> = (0..g.node_count()).map(|n| g.node_position(n).z < 1e-9).collect();
    let settings = SolverSettings {
        max_total_iterations: Some(40),
        max_halvings: 3,
        reject_indefinite: true,
        ..SolverSettings::default()
    };
    let material = MaterialParams { kind: MaterialKind::StVenantKirchhoff, young_pa: 4500.0, poisson: 0.45 };
    let mut bc = BoundaryConditions::new(g.node_count());
    bc.fixed = fixed.clone();
    let top = face_nodes(&g, 2, side);
    for &n in &top {
        bc.forces_n[n] = Vector3::new(0.0, 0.0, -0.01 / top.len() as f64);
    }
    let cancel = Cancel::new();
    // Reachable: met to the tolerance asked (5 %).
    let mut solver = FeSolver::new(&g, material, &fixed, settings.clone()).unwrap();
    let ok = solver.solve_to_mean_displacement(&bc, 1.0, 0.05, 0.1, MeanOver::Free, &cancel).unwrap();
    assert!(ok.reached && (ok.mean_mm - 1.0).abs() <= 0.05, "reachable target: mean {} mm", ok.mean_mm);
    // The cube bulges and collapses at a mean displacement of its free nodes near 1.8 mm: 5 mm
    // is out of reach, yet the states converged on the way there move more than a tenth of it.
    let mut solver = FeSolver::new(&g, material, &fixed, settings.clone()).unwrap();
    let kept = solver.solve_to_mean_displacement(&bc, 5.0, 0.05, 0.1, MeanOver::Free, &cancel).unwrap();
    assert!(!kept.reached, "5 mm should be out of reach, got {} mm", kept.mean_mm);
    assert!(
        kept.mean_mm >= MIN_REACHED_FRACTION * 5.0 && kept.mean_mm < 5.0 * 0.95,
        "kept state moves {} mm",
        kept.mean_mm
    );
    assert!(kept.solution.displacement_mm.iter().flat_map(|u| u.iter()).all(|v| v.is_finite()));
    // Its forces are in equilibrium with it: a plain Newton solve of lambda x forces from rest
    // lands on the same state (to 1 % of its mean displacement).
    let mut scaled = bc.clone();
    for f in &mut scaled.forces_n {
        *f *= kept.lambda;
    }
    let direct =
        solve(&g, &material, &scaled, SolveMethod::Newton, &SolverSettings::default(), &Progress::none(), &cancel)
            .unwrap();
    let diff = direct
        .displacement_mm
        .iter()
        .zip(&kept.solution.displacement_mm)
        .map(|(a, b)| (a - b).norm())
        .fold(0.0, f64::max);
    assert!(diff <= 0.01 * kept.mean_mm, "kept state differs from the direct solve by {diff} mm");
    // Four times what a tenth of it reaches: nothing converged that far, so no state.
    let far = 4.0 * kept.mean_mm / MIN_REACHED_FRACTION;
    let mut solver = FeSolver::new(&g, material, &fixed, settings).unwrap();
    match solver.solve_to_mean_displacement(&bc, far, 0.05, 0.1, MeanOver::Free, &cancel) {
        Err(FemError::NotConverged { reason, .. }) => assert!(reason.contains("mm"), "{reason}"),
        other => panic!("expected NotConverged for {far} mm, got {:?}", other.map(|m| m.mean_mm)),
    }
}

#[test]
fn the_corotational_product_is_its_assembled_tangent_and_at_rest_the_small_strain_stiffness_within_1e12() {
    // Whole cells (sharing one stiffness) and cut cells with their stabilisation.
    let g = box_grid(Vector3::zeros(), Vector3::new(10.0, 7.0, 6.5), 2.5, 1);
    let n = g.node_count();
    let constrained: Vec<bool> = (0..3 * n).map(|d| d < 3).collect();
    let lin = mat(MaterialKind::Linear).material();
    let mut asm = Assembler::new(&g, &constrained, lin, 1e-2);
    let nf = asm.dofs.n_free;
    let mut r = umesh_core::rng::SplitMix64(5);
    let x: Vec<f64> = (0..nf).map(|_| r.next_f64() - 0.5).collect();
    let product =
        |k: &faer::Mat<f64>| -> Vec<f64> { (0..nf).map(|i| (0..nf).map(|j| k[(i, j)] * x[j]).sum()).collect() };
    let max_abs = |a: &[f64]| a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let close = |a: &[f64], b: &[f64], what: &str| {
        let err = a.iter().zip(b).fold(0.0f64, |m, (p, q)| m.max((p - q).abs()));
        assert!(err <= 1e-12 * max_abs(b), "{what}: {err:e} against {:e}", max_abs(b));
    };
    // At rest: the small-strain stiffness, as the linear material assembles it cell by cell.
    let zero = vec![Vector3::zeros(); n];
    asm.assemble(ElementModel::Hyperelastic(lin), &zero, true);
    let k_linear = asm.matrix().to_dense();
    asm.assemble(ElementModel::Corotational, &zero, true);
    let mut y = vec![0.0; nf];
    asm.corotational_matvec(&x, &mut y);
    close(&y, &product(&k_linear), "at rest");
    // Rotated and stretched: the product with the cells' rotations is the assembled tangent.
    let rot = Rotation3::from_euler_angles(0.3, -0.2, 0.5);
    let u: Vec<Vector3<f64>> = g.node_positions().iter().map(|p| rot * (1.05 * p) - p).collect();
    asm.assemble(ElementModel::Corotational, &u, true);
    asm.corotational_matvec(&x, &mut y);
    close(&y, &product(&asm.matrix().to_dense()), "rotated");
}
