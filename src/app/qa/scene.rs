//! The QA browser's 3-D scene: the sample's FE displacement as a colour map on the organ,
//! the structures following, the probes and forces and the input u_s as arrows; with a
//! model, the prediction beside it, coloured by its error.

use crate::app::qa::Qa;
use crate::app::shell::convert::{
    UNITS_PER_MM, bevy_dir_from_world, bevy_from_world, color_u8, displacement_colors, mesh_from_trimesh,
};
use crate::app::state::Mode;
use bevy::prelude::*;
use nalgebra::Vector3;

#[derive(Component)]
struct QaMesh;

/// Sideways offset of the prediction (mm): the organ's width and a margin.
fn prediction_offset_mm(qa: &Qa) -> Vector3<f64> {
    let w = qa.sample.as_ref().and_then(|s| s.truth_surface.bounds()).map(|(lo, hi)| hi.x - lo.x).unwrap_or(200.0);
    Vector3::new(-(w * 1.15), 0.0, 0.0)
}

fn sync(
    mut commands: Commands,
    qa: Res<Qa>,
    mode: Res<State<Mode>>,
    mut shown: Local<(u64, bool, bool)>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
    old: Query<Entity, With<QaMesh>>,
) {
    let want = (qa.generation, *mode.get() == Mode::Qa, qa.show_prediction);
    if *shown == want {
        return;
    }
    *shown = want;
    for e in &old {
        commands.entity(e).despawn();
    }
    let (Some(s), true) = (&qa.sample, want.1) else { return };
    let organ_mat = || StandardMaterial {
        base_color: Color::WHITE.with_alpha(0.55),
        alpha_mode: AlphaMode::Blend,
        perceptual_roughness: 0.7,
        ..default()
    };
    let mut add = |mesh: Mesh, mat: StandardMaterial, commands: &mut Commands| {
        commands.spawn((Mesh3d(meshes.add(mesh)), MeshMaterial3d(materials.add(mat)), QaMesh));
    };
    let max = s.max_mm.max(1e-3);
    add(
        mesh_from_trimesh(&s.truth_surface, Some(displacement_colors(&s.truth_magnitude_mm, max))),
        organ_mat(),
        &mut commands,
    );
    for (m, c) in &s.truth_structures {
        add(
            mesh_from_trimesh(m, None),
            StandardMaterial { base_color: color_u8(*c), perceptual_roughness: 0.5, ..default() },
            &mut commands,
        );
    }
    if let (Some((surface, err, structures)), true) = (&s.predicted, qa.show_prediction) {
        let off = prediction_offset_mm(&qa);
        let shift = |m: &umesh_core::mesh::TriMesh| {
            let mut m = m.clone();
            m.positions.iter_mut().for_each(|p| *p += off);
            m
        };
        // Error on the same colour scale as the displacement: comparable at a glance.
        add(mesh_from_trimesh(&shift(surface), Some(displacement_colors(err, max))), organ_mat(), &mut commands);
        for (m, c) in structures {
            add(
                mesh_from_trimesh(&shift(m), None),
                StandardMaterial { base_color: color_u8(*c), perceptual_roughness: 0.5, ..default() },
                &mut commands,
            );
        }
    }
}

fn draw(qa: Res<Qa>, mut gizmos: Gizmos) {
    let Some(s) = &qa.sample else { return };
    // Forces: 10 mm of arrow per newton, at least 4 mm.
    for (p, f) in s.probes_mm.iter().zip(&s.forces_n) {
        let a = bevy_from_world(p);
        let len = (f.norm() * 10.0).max(4.0) as f32 * UNITS_PER_MM;
        if f.norm() > 0.0 {
            gizmos.arrow(a - bevy_dir_from_world(&f.normalize()) * len, a, Color::srgb(0.1, 0.9, 1.0));
        }
    }
    if qa.show_u_s {
        // One node in twelve, as lines fading from dark (rest) to white (moved): arrows at
        // every node hide the organ.
        for (p, u) in s.u_s_arrows.iter().step_by(12) {
            let a = bevy_from_world(p);
            // True length: the line ends where the FE moved the node.
            gizmos.line_gradient(
                a,
                a + bevy_dir_from_world(u) * UNITS_PER_MM,
                Color::srgb(0.2, 0.2, 0.2),
                Color::WHITE,
            );
        }
    }
}

pub struct QaViewPlugin;

impl Plugin for QaViewPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(PostUpdate, sync).add_systems(Update, draw.run_if(in_state(Mode::Qa)));
    }
}
