use std::time::Instant;
use umesh_core::fem::assembly::{Assembler, ElementModel};
use umesh_core::fem::{MaterialParams, MaterialKind};
use faer::sparse::linalg::cholesky::{factorize_symbolic_cholesky, SymmetricOrdering};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::dyn_stack::{MemBuffer, MemStack};

fn nd(nodes: &mut Vec<usize>, ijk: &[[usize; 3]], out: &mut Vec<usize>) {
    if nodes.len() <= 48 { out.extend(nodes.iter()); return; }
    let mut lo = [usize::MAX; 3]; let mut hi = [0; 3];
    for &n in nodes.iter() { for a in 0..3 { lo[a] = lo[a].min(ijk[n][a]); hi[a] = hi[a].max(ijk[n][a]); } }
    let ax = (0..3).max_by_key(|&a| hi[a] - lo[a]).unwrap();
    if hi[ax] - lo[ax] < 2 { out.extend(nodes.iter()); return; }
    let mid = (lo[ax] + hi[ax]) / 2;
    let mut l: Vec<usize> = nodes.iter().copied().filter(|&n| ijk[n][ax] < mid).collect();
    let mut r: Vec<usize> = nodes.iter().copied().filter(|&n| ijk[n][ax] > mid).collect();
    let s: Vec<usize> = nodes.iter().copied().filter(|&n| ijk[n][ax] == mid).collect();
    nd(&mut l, ijk, out); nd(&mut r, ijk, out); out.extend(s);
}

fn main() {
    let seg = umesh_core::segmentation::bundled_phantom(&std::fs::read("assets/phantom.nii.gz").unwrap()).unwrap();
    let g = umesh_core::grid::run_grid(&seg, &Default::default(), &Default::default(), &Default::default()).unwrap().grid;
    let fixed: Vec<bool> = (0..g.node_count()).flat_map(|n| [g.node_position(n).y < -50.0; 3]).collect();
    let lin = MaterialParams { kind: MaterialKind::Linear, ..Default::default() }.material();
    let mut asm = Assembler::new(&g, &fixed, lin, 1e-2);
    let u = vec![nalgebra::Vector3::zeros(); g.node_count()];
    asm.assemble(ElementModel::Hyperelastic(lin), &u, true);
    let n = asm.dofs.n_free;
    println!("n {} nnz {}", n, asm.nnz());
    let mut all: Vec<usize> = (0..g.node_count()).collect();
    let mut order = Vec::new();
    nd(&mut all, &g.node_ijk, &mut order);
    let mut fwd = Vec::new();
    for &nd_ in &order { for c in 0..3 { let f = asm.dofs.free_of[3*nd_+c]; if f != u32::MAX { fwd.push(f as usize); } } }
    let mut inv = vec![0usize; n]; for (i, &f) in fwd.iter().enumerate() { inv[f] = i; }
    let perm = faer::perm::PermRef::new_checked(&fwd, &inv, n);
    for par in [faer::Par::Seq, faer::Par::rayon(2)] {
    for (name, ord) in [("amd", SymmetricOrdering::Amd), ("nd", SymmetricOrdering::Custom(perm))] {
        let t = Instant::now();
        let sym = factorize_symbolic_cholesky(asm.matrix().symbolic(), faer::Side::Lower, ord, Default::default()).unwrap();
        let ts = t.elapsed();
        let mut vals = vec![0.0f64; sym.len_val()];
        let mut mem = MemBuffer::new(sym.factorize_numeric_llt_scratch::<f64>(par, Default::default()));
        for _ in 0..2 {
        let t = Instant::now();
        sym.factorize_numeric_llt(&mut vals, asm.matrix(), faer::Side::Lower, LltRegularization::default(), par, MemStack::new(&mut mem), Default::default()).unwrap();
        println!("{par:?} {name}: symbolic {ts:?}, nnz(L) {}, numeric {:?}", sym.len_val(), t.elapsed());
        }
    }
    }
}
