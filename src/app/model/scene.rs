//! The 3-D scene: the organ (semi-transparent, or coloured by displacement once deformed)
//! and its internal structures in distinct colours; rebuilt when the state changes.

use crate::app::shell::convert::{color_u8, displacement_colors, mesh_from_trimesh};
use crate::app::state::{Organ, Simulation};
use bevy::prelude::*;

#[derive(Component)]
pub struct OrganMesh;

#[derive(Component)]
pub struct StructureMesh;

#[derive(Resource, Default, PartialEq)]
struct Shown {
    organ: u64,
    sim: u64,
    deformed: bool,
    setup: u64,
    ghost: bool,
}

fn setup(mut commands: Commands) {
    // A directional light with shadows: it shades on GL as well as on Vulkan.
    commands.spawn((
        // Shadows follow the view quality (view3d).
        DirectionalLight { illuminance: 9000.0, shadow_maps_enabled: true, ..default() },
        Transform::from_xyz(2.0, 6.0, -5.0).looking_at(Vec3::ZERO, Vec3::Y),
    ));
    commands.insert_resource(GlobalAmbientLight { brightness: 600.0, ..default() });
    commands.insert_resource(bevy::light::DirectionalLightShadowMap { size: 1024 });
}

fn sync(
    mut commands: Commands,
    organ: Res<Organ>,
    sim: Res<Simulation>,
    setup: Res<crate::app::setup::ObservationSetup>,
    mut shown: ResMut<Shown>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
    old: Query<Entity, Or<(With<OrganMesh>, With<StructureMesh>)>>,
) {
    let deformed = sim.show_deformed && sim.result.is_some();
    // The seen-surface tint follows the camera preview (shown on the rest shape only).
    let setup_key = if deformed { 0 } else { setup.generation * 2 + setup.show as u64 };
    let ghost = deformed && sim.show_ghost;
    let now = Shown { organ: organ.generation, sim: sim.generation, deformed, setup: setup_key, ghost };
    if *shown == now {
        return;
    }
    *shown = now;
    for e in &old {
        commands.entity(e).despawn();
    }
    let Some(data) = &organ.data else { return };
    let def = sim.result.as_ref().filter(|_| deformed);
    let (surface, colors, seen) = match def {
        Some(d) => (
            d.surface.as_ref(),
            Some(displacement_colors(&d.surface_displacement_mm, d.max_mm.max(1e-3) as f32)),
            false,
        ),
        None => {
            let seen = crate::app::setup::seen_colors(&setup, data, organ.generation);
            let tinted = seen.is_some();
            (data.surface.as_ref(), seen, tinted)
        }
    };
    let organ_mat = if seen {
        // Vertex colours carry the organ's and the seen part's colour and opacity.
        StandardMaterial {
            base_color: Color::WHITE,
            alpha_mode: AlphaMode::Blend,
            perceptual_roughness: 0.6,
            double_sided: true,
            cull_mode: None,
            ..default()
        }
    } else if colors.is_some() {
        StandardMaterial {
            base_color: Color::WHITE.with_alpha(0.55),
            alpha_mode: AlphaMode::Blend,
            perceptual_roughness: 0.7,
            ..default()
        }
    } else {
        StandardMaterial {
            base_color: Color::srgba(0.62, 0.25, 0.2, 0.35),
            alpha_mode: AlphaMode::Blend,
            perceptual_roughness: 0.6,
            double_sided: true,
            cull_mode: None,
            ..default()
        }
    };
    commands.spawn((
        Mesh3d(meshes.add(mesh_from_trimesh(surface, colors))),
        MeshMaterial3d(materials.add(organ_mat)),
        OrganMesh,
    ));
    if ghost {
        // The rest shape, faint and unlit: where the organ was, without hiding where it is.
        let mat = StandardMaterial {
            base_color: Color::srgba(0.85, 0.85, 0.9, 0.12),
            alpha_mode: AlphaMode::Blend,
            unlit: true,
            double_sided: true,
            cull_mode: None,
            ..default()
        };
        commands.spawn((
            Mesh3d(meshes.add(mesh_from_trimesh(&data.surface, None))),
            MeshMaterial3d(materials.add(mat)),
            OrganMesh,
        ));
    }
    for (i, s) in data.structures.iter().enumerate() {
        let m = def.and_then(|d| d.structures.get(i)).map(|m| m.as_ref()).unwrap_or(s.mesh.as_ref());
        commands.spawn((
            Mesh3d(meshes.add(mesh_from_trimesh(m, None))),
            MeshMaterial3d(materials.add(StandardMaterial {
                base_color: color_u8(s.color),
                perceptual_roughness: 0.5,
                ..default()
            })),
            StructureMesh,
        ));
    }
}

/// The organ and its structures show in the model view only (the QA view has its own).
fn visibility(
    mode: Res<State<crate::app::state::Mode>>,
    mut q: Query<&mut Visibility, Or<(With<OrganMesh>, With<StructureMesh>)>>,
) {
    let want = if *mode.get() == crate::app::state::Mode::Model { Visibility::Inherited } else { Visibility::Hidden };
    for mut v in &mut q {
        if *v != want {
            *v = want;
        }
    }
}

pub struct ScenePlugin;

impl Plugin for ScenePlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<Shown>().add_systems(Startup, setup).add_systems(PostUpdate, (sync, visibility).chain());
    }
}
