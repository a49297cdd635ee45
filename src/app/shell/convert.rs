//! Core <-> Bevy conversions. Core works in world RAS millimetres (z up); Bevy is y-up. One
//! Bevy unit is 10 cm, so organs are a few units across and the default clip planes fit.

use bevy::asset::RenderAssetUsages;
use bevy::mesh::{Indices, PrimitiveTopology};
use bevy::prelude::*;
use nalgebra::Vector3;
use umesh_core::mesh::TriMesh;

pub const UNITS_PER_MM: f32 = 0.01;

/// World RAS (mm) -> Bevy.
pub fn bevy_from_world(p: &Vector3<f64>) -> Vec3 {
    Vec3::new(p.x as f32, p.z as f32, -p.y as f32) * UNITS_PER_MM
}

/// Bevy -> world RAS (mm).
pub fn world_from_bevy(v: Vec3) -> Vector3<f64> {
    let v = v / UNITS_PER_MM;
    Vector3::new(v.x as f64, -v.z as f64, v.y as f64)
}

/// A direction (no scaling).
pub fn bevy_dir_from_world(d: &Vector3<f64>) -> Vec3 {
    Vec3::new(d.x as f32, d.z as f32, -d.y as f32)
}

pub fn world_dir_from_bevy(v: Vec3) -> Vector3<f64> {
    Vector3::new(v.x as f64, -v.z as f64, v.y as f64)
}

/// A triangle mesh with smooth normals and optional per-vertex colours.
pub fn mesh_from_trimesh(m: &TriMesh, colors: Option<Vec<[f32; 4]>>) -> Mesh {
    let positions: Vec<[f32; 3]> = m.positions.iter().map(|p| bevy_from_world(p).to_array()).collect();
    let normals: Vec<[f32; 3]> =
        m.vertex_normals().iter().map(|n| bevy_dir_from_world(n).normalize_or_zero().to_array()).collect();
    let indices: Vec<u32> = m.triangles.iter().flat_map(|t| *t).collect();
    let mut mesh = Mesh::new(PrimitiveTopology::TriangleList, RenderAssetUsages::default());
    mesh.insert_attribute(Mesh::ATTRIBUTE_POSITION, positions);
    mesh.insert_attribute(Mesh::ATTRIBUTE_NORMAL, normals);
    if let Some(c) = colors {
        mesh.insert_attribute(Mesh::ATTRIBUTE_COLOR, c);
    }
    mesh.insert_indices(Indices::U32(indices));
    mesh
}

/// The displacement colour map at `t` in [0, 1] (blue -> cyan -> yellow -> red), sRGB.
pub fn colormap_srgb(t: f32) -> [f32; 3] {
    let t = t.clamp(0.0, 1.0);
    if t < 0.33 {
        let s = t / 0.33;
        [0.1, 0.3 + 0.6 * s, 1.0 - 0.2 * s]
    } else if t < 0.66 {
        let s = (t - 0.33) / 0.33;
        [0.1 + 0.85 * s, 0.9, 0.8 - 0.7 * s]
    } else {
        let s = (t - 0.66) / 0.34;
        [0.95, 0.9 - 0.75 * s, 0.1]
    }
}

/// Colour map for displacement magnitudes (0 -> blue, max -> red), linear RGBA.
pub fn displacement_colors(values: &[f32], max: f32) -> Vec<[f32; 4]> {
    let max = max.max(1e-6);
    values
        .iter()
        .map(|&v| {
            let c = colormap_srgb(v / max);
            let l = Color::srgb(c[0], c[1], c[2]).to_linear();
            [l.red, l.green, l.blue, 1.0]
        })
        .collect()
}

pub fn color_u8(c: [u8; 3]) -> Color {
    Color::srgb_u8(c[0], c[1], c[2])
}
