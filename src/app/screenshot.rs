//! Headless screenshots of named scenes: no window, no X server. The app renders into an
//! offscreen image (egui included) through whatever adapter wgpu finds: with
//! `WGPU_BACKEND=gl`, EGL surfaceless on Mesa's llvmpipe. Deterministic: fixed camera, fixed
//! state computed before rendering, warm-up frames before the capture.

use crate::app::model::compute;
use crate::app::model::probes::{ProbeRay, ProbeSettings, Rehearsal, RehearsalModel, probe_from_ray};
use crate::app::shell::camera::OrbitCamera;
use crate::app::shell::tasks::{self, JobOutput};
use crate::app::state::*;
use anyhow::Context;
use bevy::asset::RenderAssetUsages;
use bevy::camera::RenderTarget;
use bevy::prelude::*;
use bevy::render::render_resource::TextureFormat;
use bevy::render::view::screenshot::{Screenshot, ScreenshotCaptured};
use bevy::window::ExitCondition;
use bevy::winit::WinitPlugin;
use bevy_egui::EguiGlobalSettings;
use nalgebra::Vector3;
use std::path::Path;
use std::sync::{Arc, Mutex};
use umesh_core::{Cancel, Progress};

pub const SCENES: &[&str] = &["phantom", "grid", "probes", "rehearsal", "camera", "jobs", "qa", "ar", "ar-camera"];
/// Scenes on the real data beside the checkout (`../shared/data`, or `UMESH_SHARED_DATA`):
/// rendered when it exists.
pub const DATA_SCENES: &[&str] = &["ct"];

/// The real-data folder the data scenes read.
pub fn shared_data() -> std::path::PathBuf {
    std::env::var_os("UMESH_SHARED_DATA")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"))
}

fn known(scene: &str) -> bool {
    SCENES.contains(&scene) || DATA_SCENES.contains(&scene)
}

/// A folder for data a scene generates (a small dataset, a short recording), kept between
/// runs: the generation is deterministic and is skipped when the folder is complete.
/// Keyed by the dataset format and by what the data is made from (the configuration, the
/// recording's settings): a cache written by an older umesh, or for another bundled model, is
/// not reused.
fn scene_cache(name: &str, made_from: &impl serde::Serialize) -> std::path::PathBuf {
    let key = umesh_core::dataset::fnv_hex(serde_json::to_string(made_from).unwrap_or_default().as_bytes());
    std::env::temp_dir().join(format!("umesh-scene-{name}-v{}-{key}", umesh_core::dataset::FORMAT_VERSION))
}

/// The dataset configuration of the bundled model (the scenes' data are made with it).
fn bundled_config(organ: &OrganData) -> anyhow::Result<umesh_core::dataset::DatasetConfig> {
    let info = umesh_net::ModelInfo::read(&ActiveModel::default().dir)?;
    Ok(umesh_workflow::input::model_dataset_config(Some(&info), &organ.seg))
}

fn run(job: impl FnOnce(&Progress, &Cancel) -> anyhow::Result<JobOutput>) -> anyhow::Result<JobOutput> {
    job(&Progress::none(), &Cancel::new())
}

/// Rays from the anterior side toward points of the organ: deterministic probe positions.
fn anterior_probes(organ: &OrganData, offsets: &[(f64, f64)]) -> Vec<Probe> {
    let (lo, hi) = organ.surface.bounds().unwrap_or_default();
    let c = (lo + hi) * 0.5;
    let size = hi - lo;
    offsets
        .iter()
        .filter_map(|&(dx, dz)| {
            let origin = Vector3::new(c.x + dx * size.x, hi.y + 100.0, c.z + dz * size.z);
            probe_from_ray(organ, &ProbeRay { origin_mm: origin, direction: -Vector3::y() }, &ProbeSettings::default())
        })
        .collect()
}

/// `samples` samples with the bundled model's configuration, in shards of 4, generated once
/// into the temporary folder `name` (resumed when complete).
fn small_dataset(organ: &OrganData, name: &str, samples: usize) -> anyhow::Result<std::path::PathBuf> {
    let mut config = bundled_config(organ)?;
    config.samples = samples;
    config.shard_size = 4;
    let dir = scene_cache(name, &config);
    let all = umesh_core::dataset::ShardSelection::all();
    umesh_core::dataset::run_generate(&organ.seg, &dir, &config, all, &Progress::none(), &Cancel::new())?;
    Ok(dir)
}

/// The AR view's synthetic recording of `frames` frames with the bundled model's configuration,
/// made once into the temporary folder `name`.
fn synthetic_recording(organ: &OrganData, name: &str, frames: usize) -> anyhow::Result<std::path::PathBuf> {
    let made_from = (bundled_config(organ)?, crate::app::ar::panel::synthetic_settings(frames));
    let dir = scene_cache(name, &made_from);
    if !dir.join("trajectory.log").is_file() {
        run(crate::app::ar::panel::synth_job(organ.clone(), ActiveModel::default().dir, dir.clone(), frames))?;
    }
    Ok(dir)
}

/// Compute the state a scene shows (synchronously: a screenshot waits for nothing).
pub fn prepare_scene(world: &mut World, scene: &str) -> anyhow::Result<()> {
    let req = if scene == "ct" {
        // TotalSegmentator's CT and its segmentation: liver 5, vena cava 63, portal vein 64.
        let d = shared_data().join("totalsegmentator");
        let d = std::fs::canonicalize(&d).unwrap_or(d);
        OpenRequest {
            path: Some(d.join("example_seg.nii.gz")),
            ct: Some(d.join("example_ct_sm.nii.gz")),
            ..Default::default()
        }
    } else {
        OpenRequest::default()
    };
    let JobOutput::Loaded(organ) = run(compute::load_job(req))? else {
        anyhow::bail!("unexpected job output");
    };
    world.resource_mut::<Organ>().set(organ.clone());
    let mut cam = OrbitCamera::default();
    cam.frame(world.resource::<Organ>());
    world.insert_resource(cam);
    let show_grid = scene == "grid";
    if scene != "phantom" {
        let JobOutput::Grid(g, vox) = run(compute::grid_job(organ.seg.clone(), Default::default()))? else {
            anyhow::bail!("grid")
        };
        let mut gs = world.resource_mut::<GridState>();
        gs.stats = Some(g.stats());
        gs.grid = Some(g.clone());
        gs.voxel_volume_mm3 = vox;
        gs.show = show_grid;
        gs.generation += 1;
    }
    world.resource_mut::<GridState>().show = show_grid;
    // The camera preview is computed in the background in the app; only its own scene shows it
    // (computed here, so that the image does not depend on timing).
    world.resource_mut::<crate::app::setup::ObservationSetup>().show = scene == "camera";
    match scene {
        "phantom" | "grid" => {}
        "camera" => camera_scene(world)?,
        "probes" | "ct" => probes_scene(world, &organ, scene)?,
        "rehearsal" => rehearsal_scene(world, &organ)?,
        "jobs" => {
            // The dashboard on the bundled model's training metrics.
            world.resource_mut::<NextState<Mode>>().set(Mode::Jobs);
            let mut j = world.resource_mut::<crate::app::jobs::panel::JobsUi>();
            let dir = umesh_workflow::input::bundled_model();
            j.folder_text = short_path(&dir);
            j.dash = Some(crate::app::jobs::panel::DashSource::Folder(dir));
        }
        "qa" => qa_scene(world, &organ)?,
        "ar" => ar_scene(world, &organ)?,
        "ar-camera" => ar_camera_scene(world, &organ)?,
        other => anyhow::bail!("unknown scene {other:?}; scenes: {}, {}", SCENES.join(", "), DATA_SCENES.join(", ")),
    }
    Ok(())
}

/// The dataset camera's preview, seen from behind the laparoscope.
fn camera_scene(world: &mut World) -> anyhow::Result<()> {
    world.resource_scope(|world, mut setup: Mut<crate::app::setup::ObservationSetup>| {
        setup.camera = crate::app::setup::CameraChoice::Named("anterior-inferior".into());
        setup.compute_now(
            world.resource::<Organ>(),
            world.resource::<GridState>(),
            &world.resource::<Simulation>().fixed,
        )
    })?;
    // From behind the laparoscope and a little aside: the frustum opens toward the
    // organ, whose seen part faces the viewer.
    let eye = world
        .resource::<crate::app::setup::ObservationSetup>()
        .preview
        .as_ref()
        .map(|p| p.camera.position_mm)
        .context("no preview")?;
    let eye = crate::app::shell::convert::bevy_from_world(&Vector3::from(eye));
    let mut cam = world.resource_mut::<OrbitCamera>();
    let v = (eye - cam.focus).normalize();
    cam.pitch = v.y.asin() + 0.15;
    cam.yaw = (-v.x).atan2(-v.z) + 0.35;
    cam.distance = (eye - cam.focus).length() * 1.1;
    Ok(())
}

/// Three probes and their SVK solve (softer on the real liver of the `ct` scene).
fn probes_scene(world: &mut World, organ: &OrganData, scene: &str) -> anyhow::Result<()> {
    let mut probes = anterior_probes(organ, &[(-0.2, 0.1), (0.05, 0.2), (0.2, -0.05)]);
    if scene == "ct" {
        // The real liver is softer under these forces: a deformation of the dataset's
        // scale (about 10 mm), and a view from the front, above and right, where the
        // three slices show.
        probes.iter_mut().for_each(|p| p.force_n *= 0.3);
        let mut cam = world.resource_mut::<OrbitCamera>();
        cam.yaw = 0.75;
        cam.pitch = -0.6;
        cam.distance *= 0.85;
    }
    let grid = world.resource::<GridState>().grid.clone().context("no grid")?;
    let fixed = FixedChoice::default();
    let JobOutput::Simulated(d) = run(compute::simulate_job(organ.clone(), grid, fixed, probes.clone()))? else {
        anyhow::bail!("simulate");
    };
    let mut pr = world.resource_mut::<Probes>();
    for p in probes {
        pr.add(p);
    }
    pr.selected = None;
    world.resource_mut::<Simulation>().set(d);
    Ok(())
}

/// One probe pulled, the bundled network predicting.
fn rehearsal_scene(world: &mut World, organ: &OrganData) -> anyhow::Result<()> {
    let model = RehearsalModel::load(&umesh_workflow::input::bundled_model(), organ)?;
    let mut probes = anterior_probes(organ, &[(0.0, 0.1)]);
    // Pulled 15 mm inward and a little up, as a drag would.
    for p in &mut probes {
        p.force_n = (-p.normal * 15.0 + Vector3::new(0.0, 0.0, 5.0)) * ProbeSettings::default().newtons_per_mm;
    }
    let mut pr = world.resource_mut::<Probes>();
    for p in probes {
        pr.add(p);
    }
    pr.selected = None;
    let mut reh = world.resource_mut::<Rehearsal>();
    reh.model = Some(Arc::new(Mutex::new(model)));
    reh.enabled = true;
    reh.shown_generation = u64::MAX;
    Ok(())
}

/// The dataset browser on four samples made with the bundled model's configuration.
fn qa_scene(world: &mut World, organ: &OrganData) -> anyhow::Result<()> {
    // Four samples made with the bundled model's configuration, the model beside them.
    let model = ActiveModel::default();
    let dir = small_dataset(organ, "qa-dataset", 4)?;
    let (ds, m, p) = crate::app::qa::open_dataset(&dir, &organ.seg, Some(&model))?;
    let p = p.map(|p| Arc::new(Mutex::new(p)));
    let first = m.accepted().next().map(|r| r.index).context("no accepted sample")?;
    let sample = crate::app::qa::load_sample(&ds, &m, first, p.as_deref())?;
    world.resource_mut::<NextState<Mode>>().set(Mode::Qa);
    let mut qa = world.resource_mut::<crate::app::qa::Qa>();
    qa.path_text = dir.display().to_string();
    qa.dataset = Some(Arc::new(ds));
    qa.manifest = Some(m);
    qa.predictor = p;
    if let Some(t) = sample.tre_mm {
        qa.tre.insert(first, t);
    }
    qa.sample = Some(Arc::new(sample));
    qa.show_u_s = true;
    qa.show_prediction = true;
    qa.generation += 1;
    qa.reorder();
    // Frame the truth and the prediction beside it.
    let mut cam = world.resource_mut::<OrbitCamera>();
    cam.focus.x -= cam.distance * 0.18;
    cam.distance *= 1.5;
    Ok(())
}

/// The AR view on a synthetic recording, stepped through its frames.
fn ar_scene(world: &mut World, organ: &OrganData) -> anyhow::Result<()> {
    let model = ActiveModel::default();
    let dir = synthetic_recording(organ, "ar-recording", 4)?;
    world.resource_mut::<NextState<Mode>>().set(Mode::Ar);
    let mut ar = world.resource_mut::<crate::app::ar::Ar>();
    ar.source_text = dir.display().to_string();
    ar.show_points = true;
    let s = crate::app::ar::ArSession::start(crate::app::ar::ArSource::Recording(dir), organ.seg.clone(), model, None);
    s.send(crate::app::ar::ArCommand::ShowPoints(true));
    // Through the frames in order: the rigid alignment is made on the undeformed first
    // frame, as when a recording plays (aligning on a deformed frame absorbs the motion).
    for f in 0..=3 {
        s.send(crate::app::ar::ArCommand::Seek(f));
    }
    ar.session = Some(s);
    Ok(())
}

/// The AR view on a live camera: the synthetic recording served in umesh's stream protocol
/// as `umesh rgbd realsense` serves a RealSense camera (no masks, the tracked pose and the
/// bridge's time stamp in each frame, one every 0.4 s), so the panel shows the live source,
/// the pose it follows and the camera-to-overlay time.
fn ar_camera_scene(world: &mut World, organ: &OrganData) -> anyhow::Result<()> {
    use umesh_core::rgbd::recording::Recording;
    let dir = synthetic_recording(organ, "ar-recording", 4)?;
    let rec = Recording::open(&dir, None)?;
    let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
    let addr = listener.local_addr()?.to_string();
    std::thread::spawn(move || {
        let Ok((mut sock, _)) = listener.accept() else { return };
        for i in 0..rec.len() {
            let Ok(mut f) = rec.read_frame(i) else { continue };
            f.mask = None;
            f.device_frame = Some(i as u64 + 1);
            f.host_time_s =
                std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).ok().map(|d| d.as_secs_f64());
            if umesh_core::rgbd::stream::write_frame(&mut sock, &f, 1000.0).is_err() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(400));
        }
    });
    world.resource_mut::<NextState<Mode>>().set(Mode::Ar);
    let mut ar = world.resource_mut::<crate::app::ar::Ar>();
    ar.live_text = addr.clone();
    ar.show_points = true;
    ar.playing = true;
    let s = crate::app::ar::ArSession::start(
        crate::app::ar::ArSource::Tcp(addr),
        organ.seg.clone(),
        ActiveModel::default(),
        None,
    );
    s.send(crate::app::ar::ArCommand::ShowPoints(true));
    s.send(crate::app::ar::ArCommand::Play(true));
    ar.session = Some(s);
    Ok(())
}

#[derive(Resource, Default)]
struct Captured(Arc<Mutex<Option<anyhow::Result<()>>>>);

/// Render `scene` at `width` x `height` into a PNG at `out`.
pub fn render_scene(scene: &str, width: u32, height: u32, out: &Path, warmup_frames: u32) -> anyhow::Result<()> {
    if !known(scene) {
        anyhow::bail!("unknown scene {scene:?}; scenes: {}, {}", SCENES.join(", "), DATA_SCENES.join(", "));
    }
    if !(16..=8192).contains(&width) || !(16..=8192).contains(&height) {
        anyhow::bail!("size {width}x{height} must lie within 16..8192");
    }
    let (mut app, handle) = headless_app(scene, width, height)?;
    for _ in 0..warmup_frames.max(4) {
        app.update();
    }
    // The AR view waits for its worker's first overlay (a minute at most).
    let t0 = std::time::Instant::now();
    while scene.starts_with("ar")
        && app.world().resource::<crate::app::ar::Ar>().last.as_ref().is_none_or(|l| l.index < 3)
    {
        if t0.elapsed().as_secs() > 60 {
            anyhow::bail!("the AR view showed no frame within 60 s");
        }
        if app.world().resource::<crate::app::ar::Ar>().session.is_none() {
            let last = app.world().resource::<UiMessages>().last().map(|m| m.1.clone()).unwrap_or_default();
            anyhow::bail!("the AR session stopped: {last}");
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
        app.update();
    }
    for _ in 0..3 {
        app.update();
    }
    let captured = Captured::default();
    let slot = captured.0.clone();
    let path = out.to_path_buf();
    app.world_mut().spawn(Screenshot::image(handle)).observe(move |ev: On<ScreenshotCaptured>| {
        let r = ev.image.clone().try_into_dynamic().map_err(anyhow::Error::from).and_then(|img| {
            let mut bytes = Vec::new();
            img.to_rgba8().write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)?;
            umesh_core::write_atomic(&path, &bytes).with_context(|| path.display().to_string())
        });
        if let Ok(mut s) = slot.lock() {
            *s = Some(r);
        }
    });
    for _ in 0..30 {
        app.update();
        if let Some(r) = captured.0.lock().ok().and_then(|mut s| s.take()) {
            return r;
        }
        if let Some(exit) = app.should_exit() {
            anyhow::bail!("the renderer stopped: {exit:?}");
        }
    }
    Err(anyhow::anyhow!("the screenshot was not captured within 30 frames (no usable GPU or EGL adapter?)"))
}

/// An app rendering `scene` offscreen into an image of `width` x `height`.
pub fn headless_app(scene: &str, width: u32, height: u32) -> anyhow::Result<(App, Handle<Image>)> {
    let mut app = App::new();
    app.add_plugins(
        DefaultPlugins
            .set(WindowPlugin { primary_window: None, exit_condition: ExitCondition::DontExit, ..default() })
            .set(crate::app::render_plugin(true))
            // wgpu's GL backend logs a harmless texture-view heuristic every frame.
            .set(bevy::log::LogPlugin { filter: "wgpu=error,wgpu_hal=off,naga=warn".into(), ..default() })
            .disable::<WinitPlugin>(),
    )
    .add_plugins(crate::app::ViewPlugins)
    .insert_resource(EguiGlobalSettings { auto_create_primary_context: false, ..default() });
    app.finish();
    app.cleanup();
    // The adapter decides the quality and the organ's display surface: before the scene loads.
    app.world_mut().run_system_cached(crate::app::shell::view3d::detect_adapter)?;
    prepare_scene(app.world_mut(), scene)?;
    let mut target = Image::new_target_texture(width, height, TextureFormat::Rgba8UnormSrgb, None);
    target.asset_usage = RenderAssetUsages::RENDER_WORLD;
    let handle = app.world_mut().resource_mut::<Assets<Image>>().add(target);
    crate::app::spawn_cameras(app.world_mut(), Some(RenderTarget::Image(handle.clone().into())));
    Ok((app, handle))
}

/// Frame times (ms) of the app, rendering offscreen, while an SVK solve runs in the
/// background: the UI must stay responsive.
pub fn frame_times_during_solve(width: u32, height: u32) -> anyhow::Result<(Vec<f64>, Vec<f64>, f64)> {
    let (mut app, _) = headless_app("probes", width, height)?;
    for _ in 0..5 {
        app.update();
    }
    let idle: Vec<f64> = (0..30)
        .map(|_| {
            let t = std::time::Instant::now();
            app.update();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    let organ = app.world().resource::<Organ>().data.clone().context("no organ")?;
    let grid = app.world().resource::<GridState>().grid.clone().context("no grid")?;
    let probes = app.world().resource::<Probes>().list.clone();
    let t0 = std::time::Instant::now();
    app.world_mut()
        .resource_mut::<tasks::Jobs>()
        .spawn("simulate", compute::simulate_job(organ, grid, FixedChoice::default(), probes));
    let mut times = Vec::new();
    while !app.world().resource::<tasks::Jobs>().running.is_empty() {
        let t = std::time::Instant::now();
        app.update();
        times.push(t.elapsed().as_secs_f64() * 1e3);
        if t0.elapsed().as_secs() > 600 {
            anyhow::bail!("the solve did not finish within 10 minutes");
        }
    }
    Ok((times, idle, t0.elapsed().as_secs_f64() * 1e3))
}

/// Frame times (ms) of the app in `mode` while a training job runs (3 epochs on a 12-sample
/// dataset of the bundled configuration, generated once into the temporary folder).
pub fn frame_times_during_training(width: u32, height: u32, mode: Mode) -> anyhow::Result<(Vec<f64>, f64)> {
    let (mut app, _) = headless_app("phantom", width, height)?;
    let organ = app.world().resource::<Organ>().data.clone().context("no organ")?;
    let data = small_dataset(&organ, "bench-dataset", 12)?;
    let model = scene_cache("bench-model", &());
    let _ = std::fs::remove_dir_all(&model);
    app.world_mut().resource_mut::<NextState<Mode>>().set(mode);
    let settings = umesh_net::TrainSettings { epochs: 3, batch_size: 2, ..Default::default() };
    let id = app
        .world_mut()
        .resource_mut::<crate::app::jobs::queue::WorkQueue>()
        .submit(crate::app::jobs::queue::WorkKind::Train { dataset: data, settings, resume: false }, model)?;
    {
        let mut j = app.world_mut().resource_mut::<crate::app::jobs::panel::JobsUi>();
        j.dash = Some(crate::app::jobs::panel::DashSource::Job(id));
    }
    for _ in 0..5 {
        app.update();
    }
    let t0 = std::time::Instant::now();
    let mut times = Vec::new();
    while app.world().resource::<crate::app::jobs::queue::WorkQueue>().items.iter().any(|i| i.status.is_active()) {
        let t = std::time::Instant::now();
        app.update();
        times.push(t.elapsed().as_secs_f64() * 1e3);
        if t0.elapsed().as_secs() > 900 {
            anyhow::bail!("the training did not finish within 15 minutes");
        }
    }
    if let Some(crate::app::jobs::queue::WorkStatus::Failed(e)) =
        app.world().resource::<crate::app::jobs::queue::WorkQueue>().items.last().map(|i| i.status.clone())
    {
        anyhow::bail!("training failed: {e:#}");
    }
    Ok((times, t0.elapsed().as_secs_f64() * 1e3))
}

/// The AR view playing a synthetic recording (20 frames at 20 fps, 640x480): UI frame
/// times (ms), the rate frames were shown at (per second) and the recording's rate.
/// `on_demand`: the UI updates as the desktop window does (when the worker wakes it with a
/// frame, or after 100 ms); otherwise it renders continuously (the worst case: every UI frame
/// competes with the registration for the cores).
pub fn ar_playback(width: u32, height: u32, on_demand: bool) -> anyhow::Result<ArPlayback> {
    let (mut app, _) = headless_app("phantom", width, height)?;
    let organ = app.world().resource::<Organ>().data.clone().context("no organ")?;
    let model = ActiveModel::default();
    let dir = synthetic_recording(&organ, "bench-recording", 20)?;
    app.world_mut().resource_mut::<NextState<Mode>>().set(Mode::Ar);
    let woken = std::sync::Arc::new((std::sync::Mutex::new(false), std::sync::Condvar::new()));
    let waker: Option<crate::app::ar::Waker> = on_demand.then(|| {
        let w = woken.clone();
        Box::new(move || {
            *w.0.lock().unwrap_or_else(|e| e.into_inner()) = true;
            w.1.notify_one();
        }) as crate::app::ar::Waker
    });
    // The winit settings' reactive wait (src/app/mod.rs).
    let wait_for_wake = || {
        let mut flag = woken.0.lock().unwrap_or_else(|e| e.into_inner());
        if !*flag {
            flag =
                woken.1.wait_timeout(flag, std::time::Duration::from_millis(100)).unwrap_or_else(|e| e.into_inner()).0;
        }
        *flag = false;
    };
    let s = crate::app::ar::ArSession::start(crate::app::ar::ArSource::Recording(dir), organ.seg.clone(), model, waker);
    app.world_mut().resource_mut::<crate::app::ar::Ar>().session = Some(s);
    // The first frame (with ICP) before playing.
    let t0 = std::time::Instant::now();
    while app.world().resource::<crate::app::ar::Ar>().last.is_none() {
        app.update();
        if t0.elapsed().as_secs() > 120 || app.world().resource::<crate::app::ar::Ar>().session.is_none() {
            anyhow::bail!("the AR view showed no frame");
        }
    }
    let fps = app.world().resource::<crate::app::ar::Ar>().fps;
    let frames = app.world().resource::<crate::app::ar::Ar>().frames.unwrap_or(0);
    if let Some(s) = &app.world().resource::<crate::app::ar::Ar>().session {
        s.send(crate::app::ar::ArCommand::Play(true));
    }
    let (mut times, mut shown, mut worker_ms) = (Vec::new(), std::collections::BTreeSet::new(), Vec::new());
    let start = std::time::Instant::now();
    let mut last_new = start;
    loop {
        if on_demand {
            wait_for_wake();
        }
        let t = std::time::Instant::now();
        app.update();
        times.push(t.elapsed().as_secs_f64() * 1e3);
        if let Some(f) = &app.world().resource::<crate::app::ar::Ar>().last
            && shown.insert(f.index)
        {
            last_new = std::time::Instant::now();
            worker_ms.push(f.report.latency.total_ms);
        }
        let ar = app.world().resource::<crate::app::ar::Ar>();
        if shown.contains(&(frames.saturating_sub(1)))
            || !ar.playing && start.elapsed().as_secs() > 1
            || start.elapsed().as_secs() > 120
        {
            break;
        }
    }
    let secs = last_new.duration_since(start).as_secs_f64().max(1e-3);
    // Frames after the first shown, over the time they took: the display rate.
    Ok(ArPlayback {
        ui_ms: times,
        shown_fps: (shown.len().saturating_sub(1)) as f64 / secs,
        recording_fps: fps,
        shown: shown.len(),
        worker_ms,
    })
}

/// What `ar_playback` measured.
pub struct ArPlayback {
    /// The UI's frame times (ms).
    pub ui_ms: Vec<f64>,
    /// Frames shown per second after the first.
    pub shown_fps: f64,
    pub recording_fps: f64,
    pub shown: usize,
    /// The registration's time (ms) for each frame shown, measured on the worker while the UI
    /// renders beside it: what bounds the shown rate when it is above the frame interval.
    pub worker_ms: Vec<f64>,
}

/// Compare two images: the fraction of pixels whose largest channel difference exceeds
/// `threshold` (0-255). Sizes must match.
pub fn image_difference(a: &image::RgbaImage, b: &image::RgbaImage, threshold: u8) -> anyhow::Result<f64> {
    if a.dimensions() != b.dimensions() {
        anyhow::bail!("sizes differ: {:?} vs {:?}", a.dimensions(), b.dimensions());
    }
    let bad = a
        .pixels()
        .zip(b.pixels())
        .filter(|(p, q)| (0..3).any(|c| (p[c] as i16 - q[c] as i16).unsigned_abs() > threshold as u16))
        .count();
    Ok(bad as f64 / (a.width() as f64 * a.height() as f64))
}
