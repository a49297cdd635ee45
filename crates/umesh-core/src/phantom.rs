//! A deterministic procedural liver phantom: a lobed liver about 20 x 14 x 12 cm,
//! the inferior vena cava in a posterior groove, a branching portal vein tree and three
//! tumours, on a 1.5 mm isotropic lattice in RAS millimetres.

use crate::rng::SplitMix64;
use crate::volume::Volume;
use nalgebra::{Matrix4, Vector3};
use rayon::prelude::*;

pub const LIVER: i64 = 1;
pub const VENA_CAVA: i64 = 2;
pub const PORTAL_VEIN: i64 = 3;
pub const TUMOURS: [i64; 3] = [4, 5, 6];
/// Labels that together make the organ volume (the liver with what it contains).
pub const ORGAN_LABELS: [i64; 5] = [LIVER, PORTAL_VEIN, TUMOURS[0], TUMOURS[1], TUMOURS[2]];
/// Labels drawn as internal structures.
pub const STRUCTURE_LABELS: [i64; 4] = [PORTAL_VEIN, TUMOURS[0], TUMOURS[1], TUMOURS[2]];

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct PhantomSettings {
    pub spacing_mm: f64,
    pub seed: u64,
}

impl Default for PhantomSettings {
    fn default() -> Self {
        Self { spacing_mm: 1.5, seed: 7 }
    }
}

fn ellipsoid(p: Vector3<f64>, c: Vector3<f64>, r: Vector3<f64>) -> f64 {
    let q = (p - c).component_div(&r);
    (q.norm() - 1.0) * r.min()
}

fn smin(a: f64, b: f64, k: f64) -> f64 {
    let h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0);
    b + (a - b) * h - k * h * (1.0 - h)
}

/// Signed distance (approximate, mm; negative inside) of the liver's outer shape.
pub fn liver_sdf(p: Vector3<f64>) -> f64 {
    let right = ellipsoid(p, Vector3::new(30.0, 0.0, 0.0), Vector3::new(72.0, 68.0, 58.0));
    let left = ellipsoid(p, Vector3::new(-45.0, 12.0, 14.0), Vector3::new(62.0, 44.0, 28.0));
    let mut d = smin(right, left, 18.0);
    // Visceral (inferior) concavity.
    let cav = -ellipsoid(p, Vector3::new(5.0, -20.0, -78.0), Vector3::new(60.0, 50.0, 40.0));
    d = -smin(-d, -cav, 10.0);
    d + 2.5 * (p.x / 23.0).sin() * (p.y / 19.0).sin() * (p.z / 17.0).cos()
}

#[derive(Clone, Debug)]
struct Segment {
    a: Vector3<f64>,
    b: Vector3<f64>,
    radius_mm: f64,
}

impl Segment {
    fn dist(&self, p: Vector3<f64>) -> f64 {
        let ab = self.b - self.a;
        let t = ((p - self.a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0);
        (p - (self.a + ab * t)).norm() - self.radius_mm
    }
}

fn portal_tree(rng: &mut SplitMix64) -> Vec<Segment> {
    let mut segs = Vec::new();
    let mut stack = vec![(Vector3::new(5.0, -35.0, -55.0), Vector3::new(0.25, 0.35, 1.0).normalize(), 38.0, 6.0, 0u32)];
    while let Some((start, dir, len, r, depth)) = stack.pop() {
        let end = start + dir * len;
        segs.push(Segment { a: start, b: end, radius_mm: r });
        if depth >= 4 {
            continue;
        }
        // A random axis perpendicular to the branch; children turn +-(25..45) degrees about it.
        let any = if dir.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let u = dir.cross(&any).normalize();
        let v = dir.cross(&u);
        let phi = rng.next_f64() * std::f64::consts::TAU;
        let axis = u * phi.cos() + v * phi.sin();
        for sign in [-1.0, 1.0] {
            let ang = sign * (25.0 + 20.0 * rng.next_f64()).to_radians();
            let rot = nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), ang);
            let ndir = rot * dir;
            stack.push((end, ndir, len * (0.7 + 0.1 * rng.next_f64()), r * 0.72, depth + 1));
        }
    }
    segs
}

/// Generate the phantom label volume (uint8 labels, RAS mm).
pub fn generate(settings: &PhantomSettings) -> Volume {
    let h = settings.spacing_mm;
    let extent = Vector3::new(250.0, 190.0, 160.0);
    let origin = Vector3::new(-125.0, -95.0, -80.0);
    let dims = [(extent.x / h).ceil() as usize, (extent.y / h).ceil() as usize, (extent.z / h).ceil() as usize];
    let mut world_from_voxel = Matrix4::new_scaling(h);
    world_from_voxel[(3, 3)] = 1.0;
    for i in 0..3 {
        world_from_voxel[(i, 3)] = origin[i];
    }
    let mut rng = SplitMix64(settings.seed);
    let tree = portal_tree(&mut rng);
    let tumours = [
        (Vector3::new(55.0, 10.0, 12.0), 14.0),
        (Vector3::new(-48.0, 18.0, 16.0), 10.0),
        (Vector3::new(20.0, 28.0, -22.0), 12.0),
    ];
    let ivc = Segment { a: Vector3::new(12.0, -58.0, -90.0), b: Vector3::new(12.0, -58.0, 90.0), radius_mm: 11.0 };
    let [nx, ny, _] = dims;
    let mut vol = Volume::new(dims, world_from_voxel);
    vol.data.par_chunks_mut(nx * ny).enumerate().for_each(|(k, slab)| {
        for j in 0..ny {
            for i in 0..nx {
                let p = origin + Vector3::new(i as f64, j as f64, k as f64) * h;
                let d = liver_sdf(p);
                let mut label = 0;
                if d < 0.0 {
                    label = LIVER;
                    if d < -1.5 && tree.iter().any(|s| s.dist(p) < 0.0) {
                        label = PORTAL_VEIN;
                    }
                    for (t, (c, r)) in tumours.iter().enumerate() {
                        // Lobulated tumour surface.
                        let q = p - c;
                        let wobble = 1.0 + 0.12 * (3.0 * q.x / r).sin() * (2.0 * q.y / r).cos();
                        if q.norm() < r * wobble {
                            label = TUMOURS[t];
                        }
                    }
                }
                if ivc.dist(p) < 0.0 {
                    label = VENA_CAVA;
                }
                slab[i + nx * j] = label as f32;
            }
        }
    });
    for (l, n) in [
        (LIVER, "liver"),
        (VENA_CAVA, "inferior_vena_cava"),
        (PORTAL_VEIN, "portal_vein"),
        (TUMOURS[0], "tumour_1"),
        (TUMOURS[1], "tumour_2"),
        (TUMOURS[2], "tumour_3"),
    ] {
        vol.label_names.insert(l, n.to_string());
    }
    vol
}
