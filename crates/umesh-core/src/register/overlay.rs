//! CPU rasterisation of the augmented-reality overlay: deformed internal structures, filled
//! and shaded, blended over the camera image, and the organ's outline.

use crate::mesh::TriMesh;
use crate::rgbd::{ColorImage, DepthImage, Intrinsics, blend_pixel, transform_point};
use nalgebra::{Matrix4, Vector3};

/// Rasterise `mesh` (world) seen by a camera; calls `shade(pixel, depth, normal_camera)` for
/// every covered pixel that passes the z-buffer `zbuf` (camera depth, mm).
pub fn rasterize(
    mesh: &TriMesh,
    camera_from_world: &Matrix4<f64>,
    k: &Intrinsics,
    zbuf: &mut [f32],
    mut shade: impl FnMut(usize, f32, Vector3<f64>),
) {
    let (cam, proj) = to_camera(mesh, camera_from_world, k);
    scan(&mesh.triangles, &cam, &proj, k, Some(zbuf), &mut shade);
}

/// Mark in `inside` every pixel that `mesh` covers (no depth test: a silhouette). A union,
/// so the triangles are split over two tasks, each marking its own mask.
pub fn rasterize_silhouette(mesh: &TriMesh, camera_from_world: &Matrix4<f64>, k: &Intrinsics, inside: &mut [bool]) {
    let (cam, proj) = to_camera(mesh, camera_from_world, k);
    let (first, second) = mesh.triangles.split_at(mesh.triangles.len() / 2);
    let mut other = vec![false; inside.len()];
    rayon::join(
        || scan(first, &cam, &proj, k, None, &mut |i, _, _| inside[i] = true),
        || scan(second, &cam, &proj, k, None, &mut |i, _, _| other[i] = true),
    );
    inside.iter_mut().zip(&other).for_each(|(a, b)| *a |= *b);
}

/// Camera-space positions and their projections (None behind the camera).
#[allow(clippy::type_complexity)]
fn to_camera(
    mesh: &TriMesh,
    camera_from_world: &Matrix4<f64>,
    k: &Intrinsics,
) -> (Vec<Vector3<f64>>, Vec<Option<(f64, f64, f64)>>) {
    let cam: Vec<Vector3<f64>> = mesh.positions.iter().map(|p| transform_point(camera_from_world, p)).collect();
    let proj = cam.iter().map(|p| k.project(p)).collect();
    (cam, proj)
}

/// The scan conversion behind both: edge functions stepped along each row (one addition per
/// pixel and edge) and 1/z interpolated linearly in the image (perspective-correct depth),
/// evaluated only for covered pixels.
fn scan(
    triangles: &[[u32; 3]],
    cam: &[Vector3<f64>],
    proj: &[Option<(f64, f64, f64)>],
    k: &Intrinsics,
    mut zbuf: Option<&mut [f32]>,
    shade: &mut dyn FnMut(usize, f32, Vector3<f64>),
) {
    let (w, h) = (k.width, k.height);
    for t in triangles {
        // Closed surfaces are oriented outward: a triangle facing away from the camera is behind
        // a front-facing one of the same surface on every pixel it covers (for the depth test
        // and the silhouette alike), so it is skipped: about half the work.
        let (p0, p1, p2) = (cam[t[0] as usize], cam[t[1] as usize], cam[t[2] as usize]);
        if (p1 - p0).cross(&(p2 - p0)).dot(&p0) > 0.0 {
            continue;
        }
        let (Some(a), Some(b), Some(c)) = (proj[t[0] as usize], proj[t[1] as usize], proj[t[2] as usize]) else {
            continue;
        };
        let area = (b.0 - a.0) * (c.1 - a.1) - (c.0 - a.0) * (b.1 - a.1);
        if area.abs() < 1e-12 {
            continue;
        }
        let x0 = a.0.min(b.0).min(c.0).floor().max(0.0);
        let y0 = a.1.min(b.1).min(c.1).floor().max(0.0);
        let x1 = a.0.max(b.0).max(c.0).ceil().min(w as f64 - 1.0);
        let y1 = a.1.max(b.1).max(c.1).ceil().min(h as f64 - 1.0);
        if x0 > x1 || y0 > y1 {
            continue;
        }
        // The normal shades; a silhouette does not need it.
        let n = if zbuf.is_some() { (p1 - p0).cross(&(p2 - p0)).normalize() } else { Vector3::z() };
        // Barycentric weights as linear functions of the pixel: w = A qx + B qy + C.
        let inv = 1.0 / area;
        let (a0, b0, c0) = ((b.1 - c.1) * inv, (c.0 - b.0) * inv, (b.0 * c.1 - c.0 * b.1) * inv);
        let (a1, b1, c1) = ((c.1 - a.1) * inv, (a.0 - c.0) * inv, (c.0 * a.1 - a.0 * c.1) * inv);
        let (iza, izb, izc) = (1.0 / a.2, 1.0 / b.2, 1.0 / c.2);
        let (xs, xe) = (x0 as usize, x1 as usize);
        for py in y0 as usize..=y1 as usize {
            let qy = py as f64;
            let mut w0 = a0 * x0 + b0 * qy + c0;
            let mut w1 = a1 * x0 + b1 * qy + c1;
            let row = py * w;
            for px in xs..=xe {
                let w2 = 1.0 - w0 - w1;
                if w0 >= 0.0 && w1 >= 0.0 && w2 >= 0.0 {
                    let i = row + px;
                    match zbuf.as_deref_mut() {
                        Some(zb) => {
                            let z = (1.0 / (w0 * iza + w1 * izb + w2 * izc)) as f32;
                            if z < zb[i] {
                                zb[i] = z;
                                shade(i, z, n);
                            }
                        }
                        None => shade(i, 0.0, n),
                    }
                }
                w0 += a0;
                w1 += a1;
            }
        }
    }
}

/// A grey image of the depth (near bright), for recordings without colour.
pub fn depth_preview(depth: &DepthImage) -> ColorImage {
    let valid: Vec<f32> = depth.depth_mm.iter().copied().filter(|&d| d > 0.0).collect();
    let lo = valid.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = valid.iter().copied().fold(0.0, f32::max);
    let span = (hi - lo).max(1.0);
    let mut img = ColorImage::new(depth.width, depth.height, [0, 0, 0]);
    for (i, &d) in depth.depth_mm.iter().enumerate() {
        if d > 0.0 {
            let g = (230.0 - 180.0 * (d - lo) / span) as u8;
            img.rgb[3 * i..3 * i + 3].copy_from_slice(&[g, g, g]);
        }
    }
    img
}

/// Blend the structures (filled, shaded by their normal) and the organ outline over `base`.
pub fn draw_overlay(
    base: &mut ColorImage,
    organ: &TriMesh,
    structures: &[(TriMesh, [u8; 3])],
    camera_from_world: &Matrix4<f64>,
    k: &Intrinsics,
    alpha: f32,
) {
    // The organ's silhouette (the larger job: it covers most of the image) beside the
    // structures; composed afterwards in the same order, so the image does not change.
    let (layer, inside) = rayon::join(
        || structure_layer(structures, camera_from_world, k),
        || {
            let mut inside = vec![false; k.width * k.height];
            rasterize_silhouette(organ, camera_from_world, k, &mut inside);
            inside
        },
    );
    compose_overlay(base, &layer, &inside, k.width, alpha);
}

/// Each pixel's nearest structure, its colour shaded by the surface normal (None: no structure).
pub fn structure_layer(
    structures: &[(TriMesh, [u8; 3])],
    camera_from_world: &Matrix4<f64>,
    k: &Intrinsics,
) -> Vec<Option<[u8; 3]>> {
    let n = k.width * k.height;
    let mut zbuf = vec![f32::INFINITY; n];
    let mut color = vec![None; n];
    for (mesh, rgb) in structures {
        rasterize(mesh, camera_from_world, k, &mut zbuf, |i, _, nrm| {
            let s = (0.45 + 0.55 * nrm.z.abs()) as f32;
            color[i] = Some(rgb.map(|c| (c as f32 * s).min(255.0) as u8));
        });
    }
    color
}

/// The structures' layer blended over `base`, then the outline of the organ's silhouette
/// `inside` (both `width` pixels a row, as `base`). Row by row in parallel: each pixel reads
/// only its own layer entry and its neighbours in `inside`.
pub fn compose_overlay(base: &mut ColorImage, layer: &[Option<[u8; 3]>], inside: &[bool], width: usize, alpha: f32) {
    use rayon::prelude::*;
    if width == 0 {
        return;
    }
    let height = inside.len() / width;
    base.rgb.par_chunks_mut(3 * width).enumerate().for_each(|(v, row)| {
        for (u, px) in row.chunks_exact_mut(3).enumerate() {
            if let Some(Some(c)) = layer.get(v * width + u) {
                blend_pixel(px, *c, alpha);
            }
        }
        if v == 0 || v + 1 >= height {
            return;
        }
        for u in 1..width - 1 {
            let i = v * width + u;
            if inside[i] && (!inside[i - 1] || !inside[i + 1] || !inside[i - width] || !inside[i + width]) {
                blend_pixel(&mut row[3 * u..3 * u + 3], [255, 255, 255], 0.9);
            }
        }
    });
}
