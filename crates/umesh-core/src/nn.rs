//! Nearest neighbours in 3-D: one index for the observation operator, the physics correction's
//! closest samples, ICP, the coverage gate and the confidence rule. Points on a surface are
//! evenly spread, so a uniform grid of cells about the search radius beats a tree and builds in
//! one pass.

use nalgebra::Vector3;

const MAX_BUCKETS: f64 = (1 << 20) as f64;

/// Points bucketed on a uniform grid of cells over a box, for nearest-point queries searched in
/// shells of growing distance (a query near a point stops after 27 cells). Filled by a counting
/// sort, refilled without allocating; ties go to the smaller coordinates, then the smaller index,
/// so an answer never depends on the order of the search.
#[derive(Default)]
pub struct PointIndex {
    origin: Vector3<f64>,
    size: f64,
    dims: [usize; 3],
    start: Vec<u32>,
    points: Vec<Vector3<f64>>,
    /// Index of each bucketed point in the filled slice.
    index: Vec<u32>,
    /// The points of the filled slice the box left out (non-finite or beyond the band).
    outside: Vec<u32>,
}

impl std::fmt::Debug for PointIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PointIndex")
            .field("cell_mm", &self.size)
            .field("dims", &self.dims)
            .field("points", &self.points.len())
            .finish()
    }
}

impl PointIndex {
    /// The points near a lattice (`shape` cells of `h` from `lattice_origin`): its box grown
    /// by `band` (points beyond cannot be nearest to a node), cells half the band wide. Returns
    /// the number of points bucketed.
    pub fn fill(
        &mut self,
        points: &[Vector3<f64>],
        lattice_origin: Vector3<f64>,
        band: f64,
        shape: [usize; 3],
        h: f64,
    ) -> usize {
        let extent = Vector3::new(shape[0] as f64, shape[1] as f64, shape[2] as f64) * h + Vector3::repeat(2.0 * band);
        self.fill_box(points, lattice_origin - Vector3::repeat(band), extent, 0.5 * band)
    }

    /// Every finite point of `points` in cells of about `cell_mm` over their bounding box.
    pub fn new(points: &[Vector3<f64>], cell_mm: f64) -> Self {
        let finite = points.iter().filter(|p| p.iter().all(|v| v.is_finite()));
        let (lo, hi) = finite
            .fold((Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY)), |(lo, hi), p| {
                (lo.inf(p), hi.sup(p))
            });
        let mut index = Self::default();
        if lo.x <= hi.x {
            let cell_mm = cell_mm.max(1e-3);
            // One cell more than the extent, so the largest coordinates fall inside.
            index.fill_box(points, lo, hi - lo + Vector3::repeat(cell_mm), cell_mm);
        }
        index
    }

    /// The points inside the box from `origin` spanning `extent`, in cells of `cell_mm` or, for a
    /// box that would need more than about MAX_BUCKETS of them, larger (the shell search finds
    /// the same nearest point with any cell size). The others are kept aside (`nearest_moved`).
    pub fn fill_box(
        &mut self,
        points: &[Vector3<f64>],
        origin: Vector3<f64>,
        extent: Vector3<f64>,
        cell_mm: f64,
    ) -> usize {
        self.origin = origin;
        self.size = cell_mm.max((extent.x * extent.y * extent.z / MAX_BUCKETS).cbrt());
        self.dims = [0, 1, 2].map(|a| ((extent[a] / self.size).ceil() as usize).max(1));
        let n = self.dims.iter().product::<usize>();
        // A counting sort: counts, their running sums as each cell's end, then each point
        // placed by counting down from its cell's end, which leaves the starts.
        let keys: Vec<u32> = points.iter().map(|p| self.cell_of(p).map_or(u32::MAX, |b| b as u32)).collect();
        let mut start = std::mem::take(&mut self.start);
        start.clear();
        start.resize(n + 1, 0);
        for &b in keys.iter().filter(|&&b| b != u32::MAX) {
            start[b as usize + 1] += 1;
        }
        for b in 0..n {
            start[b + 1] += start[b];
        }
        let used = start[n] as usize;
        self.outside.clear();
        self.outside.extend(keys.iter().enumerate().filter(|(_, b)| **b == u32::MAX).map(|(i, _)| i as u32));
        self.points.clear();
        self.points.resize(used, Vector3::zeros());
        self.index.clear();
        self.index.resize(used, 0);
        for (i, (p, &b)) in points.iter().zip(&keys).enumerate().rev() {
            if b != u32::MAX {
                let end = &mut start[b as usize + 1];
                *end -= 1;
                self.points[*end as usize] = *p;
                self.index[*end as usize] = i as u32;
            }
        }
        // Each cell's end counted down to its start; shift back so start[b]..start[b + 1] is b.
        for b in 0..n {
            start[b] = start[b + 1];
        }
        start[n] = used as u32;
        self.start = start;
        used
    }

    /// The bucket of `p`; None outside the grown lattice's box or not finite.
    fn cell_of(&self, p: &Vector3<f64>) -> Option<usize> {
        let l = (p - self.origin) / self.size;
        if !(l.iter().all(|v| v.is_finite() && *v >= 0.0)) {
            return None;
        }
        let (i, j, k) = (l.x as usize, l.y as usize, l.z as usize);
        (i < self.dims[0] && j < self.dims[1] && k < self.dims[2]).then(|| (i * self.dims[1] + j) * self.dims[2] + k)
    }

    /// Whether a fill would bucket `p`.
    pub fn holds(&self, p: &Vector3<f64>) -> bool {
        self.cell_of(p).is_some()
    }

    /// The nearest point within `band` of `x` once the bucketed points have moved to `now`
    /// (indexed as filled) by at most `moved` each, given that one of them is now within
    /// `reach` of `x` and inside the box (`band` when none is known): the same point as
    /// `nearest` on buckets filled with `now`, without the fill. The nearest is now within
    /// `reach`, so it was within `reach + moved` when filled: only the buckets that far are
    /// looked at.
    pub fn nearest_moved(
        &self,
        x: &Vector3<f64>,
        now: &[Vector3<f64>],
        reach: f64,
        moved: f64,
        band: f64,
    ) -> Option<usize> {
        // A micrometre's slack for the rounding of the positions keeps every candidate.
        let r = reach.min(band) + moved + 1e-3;
        if !(self.size > 0.0 && r.is_finite() && x.iter().all(|v| v.is_finite())) {
            return None;
        }
        let range = |a: usize| {
            let lo = ((x[a] - r - self.origin[a]) / self.size).floor().max(0.0) as usize;
            let hi = ((x[a] + r - self.origin[a]) / self.size).floor();
            (lo, if hi < 0.0 { None } else { Some((hi as usize).min(self.dims[a] - 1)) })
        };
        let mut best: Option<(f64, usize, Vector3<f64>)> = None;
        let mut consider = |idx: usize| {
            let q = now[idx];
            let d2 = (q - x).norm_squared();
            // A fresh fill would not hold a point moved out of the box.
            if d2 > band * band || !self.holds(&q) {
                return;
            }
            // `nearest`'s order: distance, then coordinates, then index.
            let better = match best {
                None => true,
                Some((bd, bi, bq)) => d2 < bd || (d2 == bd && (q.x, q.y, q.z, idx) < (bq.x, bq.y, bq.z, bi)),
            };
            if better {
                best = Some((d2, idx, q));
            }
        };
        if let [(i0, Some(i1)), (j0, Some(j1)), (k0, Some(k1))] = [range(0), range(1), range(2)] {
            for i in i0..=i1 {
                for j in j0..=j1 {
                    let row = (i * self.dims[1] + j) * self.dims[2];
                    for b in row + k0..=row + k1 {
                        for s in self.start[b] as usize..self.start[b + 1] as usize {
                            if (self.points[s] - x).norm_squared() <= r * r {
                                consider(self.index[s] as usize);
                            }
                        }
                    }
                }
            }
        }
        // Those the box left out may have moved in.
        for &idx in &self.outside {
            consider(idx as usize);
        }
        best.map(|(_, i, _)| i)
    }

    /// The nearest bucketed point within `band` of `x`: its index in the filled slice and
    /// position. Ties go to the smaller coordinates, then the smaller index, so the result does
    /// not depend on the order of the search.
    pub fn nearest(&self, x: &Vector3<f64>, band: f64) -> Option<(usize, Vector3<f64>)> {
        self.nearest_except(x, band, usize::MAX)
    }

    /// As `nearest`, leaving out point `skip` (a point's nearest other point).
    pub fn nearest_except(&self, x: &Vector3<f64>, band: f64, skip: usize) -> Option<(usize, Vector3<f64>)> {
        if self.size <= 0.0 {
            return None;
        }
        let l = (x - self.origin) / self.size;
        let c = [l.x.floor() as i64, l.y.floor() as i64, l.z.floor() as i64];
        // Queries use the band the buckets were filled with (2 shells) or less; 64 bounds a
        // query's work should one ask for far more.
        let reach = (band / self.size).ceil().clamp(1.0, 64.0) as i64;
        let mut best: Option<(f64, usize, Vector3<f64>)> = None;
        let visit = |i: i64, j: i64, k: i64, best: &mut Option<(f64, usize, Vector3<f64>)>| {
            if i < 0
                || j < 0
                || k < 0
                || i >= self.dims[0] as i64
                || j >= self.dims[1] as i64
                || k >= self.dims[2] as i64
            {
                return;
            }
            let b = (i as usize * self.dims[1] + j as usize) * self.dims[2] + k as usize;
            for s in self.start[b] as usize..self.start[b + 1] as usize {
                let (q, idx) = (&self.points[s], self.index[s] as usize);
                if idx == skip {
                    continue;
                }
                let d2 = (q - x).norm_squared();
                let better = match *best {
                    None => true,
                    Some((bd, bi, bq)) => d2 < bd || (d2 == bd && (q.x, q.y, q.z, idx) < (bq.x, bq.y, bq.z, bi)),
                };
                if better {
                    *best = Some((d2, idx, *q));
                }
            }
        };
        for shell in 0..=reach {
            for di in -shell..=shell {
                for dj in -shell..=shell {
                    // Inside the shell's cube only its two k faces are new.
                    let stride = if di.abs() == shell || dj.abs() == shell { 1 } else { 2 * shell as usize };
                    for dk in (-shell..=shell).step_by(stride.max(1)) {
                        visit(c[0] + di, c[1] + dj, c[2] + dk, &mut best);
                    }
                }
            }
            // Every point of the next shell is at least `shell` whole cells away: a nearer one
            // (or a tie) cannot be there.
            let r = shell as f64 * self.size;
            if best.is_some_and(|(d2, _, _)| d2 < r * r) {
                break;
            }
        }
        best.filter(|(d2, _, _)| *d2 <= band * band).map(|(_, i, q)| (i, q))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sphere's surface (radius 30 mm about (40, 40, 40)) sampled about every 1-2 mm, with
    /// exact duplicates of the first 50 at the end (ties by index).
    fn sphere_points(r: &mut impl FnMut(f64) -> f64) -> Vec<Vector3<f64>> {
        let mut points: Vec<Vector3<f64>> = (0..4000)
            .map(|_| {
                let (z, a) = (r(2.0) - 1.0, r(std::f64::consts::TAU));
                let s = (1.0 - z * z).sqrt();
                Vector3::new(40.0 + 30.0 * s * a.cos(), 40.0 + 30.0 * s * a.sin(), 40.0 + 30.0 * z)
            })
            .collect();
        points.extend(points[..50].to_vec());
        points
    }

    #[test]
    fn the_index_finds_the_same_nearest_point_within_the_band_as_a_brute_force_search() {
        let mut rng = crate::rng::SplitMix64(7);
        let mut r = |s: f64| s * rng.next_f64();
        let points = sphere_points(&mut r);
        // 0.05 mm on an 80 mm lattice: cells far larger than half the band (about 2^20 of them at most).
        for (band, h) in [(2.0, 4.0), (5.0, 4.0), (10.0, 4.0), (0.05, 4.0)] {
            let mut b = PointIndex::default();
            assert_eq!(b.fill(&points, Vector3::zeros(), band, [20, 20, 20], h), points.len());
            // Each axis rounds its count up: a few per cent over.
            assert!(b.start.len() <= (1 << 20) * 11 / 10, "{} cells for a {band} mm band", b.start.len());
            for k in 0..2000 {
                // Anywhere in the box, or near a point (within the band).
                let q = if k % 2 == 0 {
                    Vector3::new(r(90.0) - 5.0, r(90.0) - 5.0, r(90.0) - 5.0)
                } else {
                    let p = points[(r(1.0) * points.len() as f64) as usize % points.len()];
                    p + Vector3::new(r(band) - 0.5 * band, r(band) - 0.5 * band, r(band) - 0.5 * band) * 0.5
                };
                let brute = points
                    .iter()
                    .enumerate()
                    .map(|(i, p)| ((p - q).norm_squared(), i))
                    .filter(|(d2, _)| *d2 <= band * band)
                    .min_by(|a, b| {
                        a.0.total_cmp(&b.0).then_with(|| {
                            (points[a.1].x, points[a.1].y, points[a.1].z, a.1)
                                .partial_cmp(&(points[b.1].x, points[b.1].y, points[b.1].z, b.1))
                                .unwrap()
                        })
                    });
                let got = b.nearest(&q, band).map(|(i, _)| i);
                assert_eq!(got, brute.map(|(_, i)| i), "band {band} mm, query {q:?}");
            }
        }
    }

    #[test]
    fn the_index_finds_after_a_move_the_same_nearest_point_as_buckets_filled_anew() {
        let mut rng = crate::rng::SplitMix64(11);
        let mut r = |s: f64| s * rng.next_f64();
        let filled = sphere_points(&mut r);
        let band = 10.0;
        // Moves small and large against the band, some points crossing the box's side.
        for moved in [0.3, 2.0, 8.0] {
            let mut now: Vec<Vector3<f64>> = filled
                .iter()
                .map(|p| p + Vector3::new(r(2.0) - 1.0, r(2.0) - 1.0, r(2.0) - 1.0).normalize() * r(moved))
                .collect();
            // The duplicates moved alike (ties by index after the move).
            for i in 0..50 {
                now[4000 + i] = now[i];
            }
            // The box ends at x = 50 + 10 mm: the sphere (x up to 70) reaches beyond it.
            let shape = [10, 20, 20];
            let mut old = PointIndex::default();
            old.fill(&filled, Vector3::zeros(), band, shape, 4.0);
            let mut fresh = PointIndex::default();
            fresh.fill(&now, Vector3::zeros(), band, shape, 4.0);
            let left = now.iter().zip(&filled).filter(|(n, f)| old.holds(f) != old.holds(n)).count();
            assert!(moved < 1.0 || left > 0, "no point crossed the box's side at {moved} mm");
            for k in 0..2000 {
                let q = if k % 2 == 0 {
                    Vector3::new(r(90.0) - 5.0, r(90.0) - 5.0, r(90.0) - 5.0)
                } else {
                    now[(r(1.0) * now.len() as f64) as usize % now.len()]
                        + Vector3::new(r(4.0) - 2.0, r(4.0) - 2.0, r(4.0) - 2.0)
                };
                // A known point's distance bounds the nearest's, as the previous match does.
                let known = now[(r(1.0) * now.len() as f64) as usize % now.len()];
                let reach = if k % 3 == 0 || !fresh.holds(&known) { band } else { (known - q).norm() };
                let expect = fresh.nearest(&q, band).map(|(i, _)| i);
                assert_eq!(old.nearest_moved(&q, &now, reach, moved, band), expect, "moved {moved} mm, query {q:?}");
            }
        }
    }
}
