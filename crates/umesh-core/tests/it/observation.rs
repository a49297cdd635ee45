//! The observation operator: correspondence-free (order and density), close to the surface
//! motion it encodes, zero where nothing moved.

use nalgebra::Vector3;
use umesh_core::grid::{GridSettings, ImmersedGrid};
use umesh_core::mesh::TriMesh;
use umesh_core::observation::{CHANNELS, Encoding, ObservationSettings, Observer};
use umesh_core::rng::SplitMix64;
use umesh_core::segmentation::{Segmentation, bundled_phantom};
use umesh_core::surface::{SurfaceSettings, extract_surface};
use umesh_core::visible::{VisibilitySettings, sample_points, visible_surface};
use umesh_core::{Cancel, Progress};

fn phantom() -> Segmentation {
    let bytes = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/../../assets/phantom.nii.gz")).unwrap();
    bundled_phantom(&bytes).unwrap()
}

struct Case {
    grid: ImmersedGrid,
    surface: TriMesh,
    visible: Vec<bool>,
}

fn case() -> Case {
    let seg = phantom();
    let mask = seg.organ_mask();
    let grid = ImmersedGrid::from_mask(&mask, &GridSettings::default(), &Progress::none(), &Cancel::new()).unwrap();
    let surface = extract_surface(&mask, &SurfaceSettings { step: 2, ..Default::default() });
    let visible = visible_surface(&surface, &VisibilitySettings::default()).unwrap().visible;
    Case { grid, surface, visible }
}

fn points(c: &Case, n: usize, seed: u64, shift: Vector3<f64>) -> Vec<Vector3<f64>> {
    sample_points(&c.surface, &c.visible, n, &mut SplitMix64(seed)).into_iter().map(|(p, _)| p + shift).collect()
}

/// Mean |a - b| over the offset channels of nodes observed in both, and how many there are.
fn offset_difference(a: &[f32], b: &[f32]) -> (f64, usize) {
    let cells = a.len() / CHANNELS;
    let (mut s, mut n) = (0.0, 0);
    for d in 0..cells {
        if a[3 * cells + d] > 0.0 && b[3 * cells + d] > 0.0 {
            s += (0..3).map(|c| (a[c * cells + d] - b[c * cells + d]) as f64).map(|v| v * v).sum::<f64>().sqrt();
            n += 1;
        }
    }
    (s / n.max(1) as f64, n)
}

fn mean_offset(a: &[f32]) -> (Vector3<f64>, usize) {
    let cells = a.len() / CHANNELS;
    let (mut s, mut n) = (Vector3::zeros(), 0);
    for d in 0..cells {
        if a[3 * cells + d] > 0.0 {
            s += Vector3::new(a[d] as f64, a[cells + d] as f64, a[2 * cells + d] as f64);
            n += 1;
        }
    }
    (s / n.max(1) as f64, n)
}

fn observer(c: &Case, encoding: Encoding) -> Observer {
    Observer::new(&c.grid, &c.surface, ObservationSettings { encoding, ..Default::default() }).unwrap()
}

#[test]
fn shuffled_or_duplicated_points_give_the_same_encoding() {
    let c = case();
    for encoding in [Encoding::Corner, Encoding::Nearest] {
        let mut obs = observer(&c, encoding);
        let pts = points(&c, 4000, 1, Vector3::new(0.0, 2.0, 0.0));
        let mut a = Vec::new();
        obs.encode(&pts, &mut a);
        let mut shuffled = pts.clone();
        let mut rng = SplitMix64(9);
        for i in (1..shuffled.len()).rev() {
            shuffled.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
        }
        let mut b = Vec::new();
        obs.encode(&shuffled, &mut b);
        let doubled: Vec<_> = pts.iter().chain(&pts).copied().collect();
        let mut d = Vec::new();
        obs.encode(&doubled, &mut d);
        // Sums in another order differ by rounding only: 1e-4 mm.
        for other in [&b, &d] {
            let max = a.iter().zip(other.iter()).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
            assert!(max < 1e-4, "{encoding:?}: the encoding moved by {max} mm with the points' order or density");
        }
    }
}

#[test]
fn an_unmoved_surface_encodes_to_nearly_zero_and_a_resampled_one_nearly_the_same() {
    let c = case();
    // Tolerances (mean over observed nodes): the corner means depend on which part of each cell
    // the seen patch covers (measured 1.0 and 1.3 mm); the normal projection does not (0.07, 0.06).
    for (encoding, rest_tol, resample_tol) in [(Encoding::Corner, 1.5, 2.0), (Encoding::Nearest, 0.3, 0.3)] {
        let mut obs = observer(&c, encoding);
        let mut a = Vec::new();
        let stats = obs.encode(&points(&c, 4000, 2, Vector3::zeros()), &mut a);
        assert_eq!(stats.points_used, 4000);
        assert!(stats.nodes_observed > 200, "{encoding:?}: {} nodes observed", stats.nodes_observed);
        let (m, n) = mean_offset(&a);
        let cells = a.len() / CHANNELS;
        let mean_abs = (0..cells)
            .filter(|&d| a[3 * cells + d] > 0.0)
            .map(|d| Vector3::new(a[d] as f64, a[cells + d] as f64, a[2 * cells + d] as f64).norm())
            .sum::<f64>()
            / n as f64;
        eprintln!("{encoding:?}: rest {mean_abs:.3} mm over {n} nodes");
        assert!(
            mean_abs < rest_tol,
            "{encoding:?}: the rest surface encodes to {mean_abs:.2} mm on average (mean vector {m:?})"
        );
        // Another random sample of the same surface, half as dense.
        let mut b = Vec::new();
        obs.encode(&points(&c, 2000, 3, Vector3::zeros()), &mut b);
        let (diff, common) = offset_difference(&a, &b);
        assert!(common > n / 2, "{encoding:?}: {common} of {n} nodes observed in both samples");
        eprintln!("{encoding:?}: resampled {diff:.3} mm over {common} nodes");
        assert!(diff < resample_tol, "{encoding:?}: resampling changed the encoding by {diff:.2} mm");
    }
}

#[test]
fn a_translated_surface_encodes_its_motion() {
    // 6 mm toward the camera (anterior, +y): both encodings see most of it along y.
    let c = case();
    let t = Vector3::new(0.0, 6.0, 0.0);
    // Each seen point measures the normal part of the motion, 6 n_y^2 along y (measured 2.6 and 2.1 mm on average).
    for (encoding, lo, hi) in [(Encoding::Corner, 1.5, 6.0), (Encoding::Nearest, 1.5, 6.0)] {
        let mut obs = observer(&c, encoding);
        let mut a = Vec::new();
        obs.encode(&points(&c, 4000, 4, t), &mut a);
        let (m, n) = mean_offset(&a);
        assert!(n > 200, "{encoding:?}: {n} nodes observed");
        eprintln!("{encoding:?}: mean encoded motion {m:?} over {n} nodes for a {t:?} mm shift");
        assert!(m.y > lo && m.y < hi, "{encoding:?}: mean encoded motion {m:?} for a {t:?} mm shift");
    }
}

#[test]
fn points_outside_the_grid_or_not_finite_are_ignored() {
    let c = case();
    let mut obs = observer(&c, Encoding::Nearest);
    let mut out = Vec::new();
    let far =
        vec![Vector3::new(1e6, 0.0, 0.0), Vector3::new(f64::NAN, 0.0, 0.0), Vector3::new(0.0, f64::INFINITY, 0.0)];
    let s = obs.encode(&far, &mut out);
    assert_eq!((s.points_used, s.nodes_observed), (0, 0));
    assert!(out.iter().all(|v| *v == 0.0));
    let s = observer(&c, Encoding::Corner).encode(&far, &mut out);
    assert_eq!((s.points_used, s.nodes_observed), (0, 0));
    let s = obs.encode(&[], &mut out);
    assert_eq!(s.nodes_observed, 0);
}
