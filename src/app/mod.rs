//! The desktop app (Bevy + egui): one folder per view (`model/`, `jobs/`, `qa/`, `ar/`), each
//! with its state, systems and panel; the shell (`shell/`: the view registry, 3-D view, camera,
//! core <-> Bevy conversions, background tasks) apart and knowing no view; the window's frame
//! (`frame.rs`: menus, status bar, dialogs) and the headless scenes (`screenshot.rs`) over them;
//! the state the views share in `state.rs`. Heavy work runs in background tasks.

pub mod ar;
pub mod ct;
pub mod frame;
pub mod jobs;
pub mod model;
pub mod qa;
pub mod screenshot;
pub mod setup;
pub mod shell;
pub mod state;
pub mod views;

use bevy::prelude::*;
use bevy::render::error_handler::{RenderError, RenderErrorHandler, RenderErrorPolicy};
use bevy_egui::{EguiPlugin, EguiPrimaryContextPass};

/// The plugins that hold state and logic, with no window or renderer (headless tests use
/// these with `MinimalPlugins`).
pub struct CorePlugins;

impl Plugin for CorePlugins {
    fn build(&self, app: &mut App) {
        app.add_plugins((
            shell::tasks::JobsPlugin,
            model::probes::ProbesPlugin,
            jobs::queue::WorkflowPlugin,
            qa::QaPlugin,
            ar::ArPlugin,
            setup::SetupPlugin,
            model::session::SessionPlugin,
        ))
        // The session's state: held here so that headless tests can save and reopen one.
        .init_resource::<ct::CtView>()
        .init_resource::<shell::camera::OrbitCamera>()
        .init_resource::<state::OpenPatient>()
        .init_resource::<state::ActiveModel>();
        if !app.is_plugin_added::<bevy::state::app::StatesPlugin>() {
            app.add_plugins(bevy::state::app::StatesPlugin);
        }
        app.init_state::<state::Mode>();
    }
}

/// Everything interactive: scene, camera, grid preview, probes input, panels.
pub struct ViewPlugins;

impl Plugin for ViewPlugins {
    fn build(&self, app: &mut App) {
        views::register_default_views(app);
        app.add_plugins(EguiPlugin::default())
            .add_plugins((
                CorePlugins,
                model::scene::ScenePlugin,
                ct::CtPlugin,
                shell::camera::OrbitCameraPlugin,
                model::grid_preview::GridPreviewPlugin,
                model::probes::ProbeInputPlugin,
                shell::view3d::View3dPlugin,
                qa::scene::QaViewPlugin,
                setup::SetupViewPlugin,
            ))
            .init_resource::<frame::UiState>()
            .init_resource::<jobs::panel::JobsUi>()
            .add_systems(EguiPrimaryContextPass, frame::ui_system)
            .insert_resource(ClearColor(Color::srgb(0.11, 0.12, 0.14)))
            .insert_resource(RenderErrorHandler(render_error_policy));
    }
}

/// The renderer, without bevy_pbr's screen-space ambient occlusion (unused here; its compute
/// shader does not compile on Mesa's GL, logged an error on every start and preceded the
/// occasional heap-corruption abort): the SSAO plugin skips itself on devices with fewer than 5
/// storage textures per shader stage, so the device is asked for 4.
pub fn render_plugin(synchronous_pipeline_compilation: bool) -> bevy::render::RenderPlugin {
    use bevy::render::settings::{RenderCreation, WgpuLimits, WgpuSettings};
    let limits = WgpuLimits { max_storage_textures_per_shader_stage: 4, ..WgpuLimits::default() };
    bevy::render::RenderPlugin {
        render_creation: RenderCreation::Automatic(Box::new(WgpuSettings {
            constrained_limits: Some(limits),
            ..Default::default()
        })),
        synchronous_pipeline_compilation,
        ..Default::default()
    }
}

/// bevy_pbr's SSAO compute pipeline (left out, see `render_plugin`) failed to compile on Mesa's
/// GL; should it come back, it is ignored. Every other render error stops the app as bevy's
/// default handler does.
fn render_error_policy(error: &RenderError, main_world: &mut World, _render: &mut World) -> RenderErrorPolicy {
    let d = error.description.to_lowercase();
    if d.contains("ssao") || d.contains("screen_space_ambient_occlusion") {
        warn!(
            "ignoring a render error of the unused SSAO pipeline: {}",
            error.description.lines().next().unwrap_or("")
        );
        return RenderErrorPolicy::Ignore;
    }
    error!("render error, quitting: {}", error.description);
    main_world.write_message(AppExit::error());
    RenderErrorPolicy::StopRendering
}

/// The 3-D camera, rendering into the [`shell::view3d::View3d`] image, and the camera egui renders
/// with into `target` (the window when None); the UI shows the 3-D image between its panels.
pub fn spawn_cameras(world: &mut World, target: Option<bevy::camera::RenderTarget>) {
    use bevy::camera::{RenderTarget, visibility::RenderLayers};
    let t = world.get_resource::<shell::camera::OrbitCamera>().cloned().unwrap_or_default().transform();
    let image = world.resource::<shell::view3d::View3d>().image.clone();
    // No MSAA: with software rendering (llvmpipe) it costs more than the whole scene.
    world.spawn((Camera3d::default(), t, shell::camera::MainCamera, Msaa::Off, RenderTarget::Image(image.into())));
    let mut ui = world.spawn((
        bevy_egui::PrimaryEguiContext,
        Camera2d,
        RenderLayers::none(),
        Msaa::Off,
        Camera { order: 1, ..default() },
    ));
    if let Some(tg) = target {
        ui.insert(tg);
    }
}

fn spawn_window_cameras(world: &mut World) {
    spawn_cameras(world, None);
}

/// What the window opens on: a patient folder (`umesh gui PATIENT/`), a segmentation with
/// its scan (`umesh gui --ct CT SEG`) or the bundled phantom.
#[derive(Resource, Clone, Default)]
pub enum StartWith {
    #[default]
    Phantom,
    Patient(std::path::PathBuf),
    Open(state::OpenRequest),
    /// A session file: opened when it exists, else the phantom with this file to save to.
    Session(std::path::PathBuf),
}

fn load_at_start(
    mut jobs: ResMut<shell::tasks::Jobs>,
    start: Res<StartWith>,
    mut file: ResMut<model::session::SessionFile>,
) {
    match &*start {
        StartWith::Session(path) => {
            file.0 = Some(path.clone());
            if path.exists() {
                jobs.spawn("open session", model::session::open_job(path.clone()));
            } else {
                jobs.spawn("load phantom", model::compute::load_job(state::OpenRequest::default()));
            }
        }
        StartWith::Patient(dir) => {
            jobs.spawn("open patient", model::compute::open_patient_job(dir.clone()));
        }
        StartWith::Open(req) => {
            jobs.spawn("load", model::compute::load_job(req.clone()));
        }
        StartWith::Phantom => {
            jobs.spawn("load phantom", model::compute::load_job(state::OpenRequest::default()));
        }
    }
}

/// Build a grid once an organ is loaded and none exists.
fn auto_grid(
    organ: Res<state::Organ>,
    grid: Res<state::GridState>,
    mut jobs: ResMut<shell::tasks::Jobs>,
    mut done: Local<u64>,
) {
    if let Some(d) = &organ.data
        && grid.grid.is_none()
        && *done != organ.generation
        && !jobs.is_running("grid")
    {
        *done = organ.generation;
        jobs.spawn("grid", model::compute::grid_job(d.seg.clone(), grid.settings.clone()));
    }
}

/// Ask for another frame right away when shown state changed (a job finished, a sample or an
/// AR frame arrived, the rehearsal deformed the organ), or while a probe is dragged.
fn request_redraws(
    organ: Res<state::Organ>,
    sim: Res<state::Simulation>,
    grid: Res<state::GridState>,
    probes: Res<state::Probes>,
    qa: Res<qa::Qa>,
    ar: Res<ar::Ar>,
    jobs: Res<shell::tasks::Jobs>,
    setup: Res<setup::ObservationSetup>,
    mut last: Local<[u64; 8]>,
    mut redraw: MessageWriter<bevy::window::RequestRedraw>,
) {
    let now = [
        organ.generation,
        sim.generation,
        grid.generation,
        probes.generation,
        qa.generation,
        ar.generation,
        jobs.finished.len() as u64,
        setup.generation,
    ];
    if now != *last || probes.dragging.is_some() {
        *last = now;
        redraw.write(bevy::window::RequestRedraw);
    }
}

/// Open the app window on a patient folder, or on the bundled phantom.
pub fn run_gui(start: StartWith) -> AppExit {
    App::new()
        .add_plugins(
            DefaultPlugins
                .set(WindowPlugin {
                    primary_window: Some(Window {
                        title: "umesh".into(),
                        resolution: (1400u32, 900u32).into(),
                        ..default()
                    }),
                    ..default()
                })
                .set(render_plugin(false)),
        )
        .add_plugins(ViewPlugins)
        .insert_resource(bevy_egui::EguiGlobalSettings { auto_create_primary_context: false, ..default() })
        .insert_resource(start)
        .add_systems(Startup, (spawn_window_cameras, load_at_start))
        .add_systems(Update, (auto_grid.after(model::session::apply_pending), request_redraws))
        // Update on input, on a wake-up (AR frames) and on state changes; otherwise 10 times a
        // second for progress bars. A software-rendered frame costs a core: drawing only when
        // something changed leaves the CPU to solves, training and registration.
        .insert_resource(bevy::winit::WinitSettings {
            focused_mode: bevy::winit::UpdateMode::reactive(std::time::Duration::from_millis(100)),
            unfocused_mode: bevy::winit::UpdateMode::reactive_low_power(std::time::Duration::from_millis(500)),
        })
        .run()
}
