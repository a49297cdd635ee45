//! The app's logic, headless: `MinimalPlugins` and `app.update()`, no window, no renderer.

use bevy::prelude::*;
use nalgebra::Vector3;
use std::time::{Duration, Instant};
use umesh::app::CorePlugins;
use umesh::app::jobs::{JobOutput, Jobs, grid_job, load_job, simulate_job};
use umesh::app::probes::ProbeRay;
use umesh::app::state::*;

fn app() -> App {
    let mut app = App::new();
    app.add_plugins(MinimalPlugins).add_plugins(CorePlugins);
    app
}

fn phantom() -> OrganData {
    let job = load_job(OpenRequest { path: None, organ_labels: vec![], structure_labels: vec![] });
    match job(&Default::default(), &Default::default()) {
        Ok(JobOutput::Loaded(d)) => d,
        _ => panic!("the bundled phantom did not load"),
    }
}

/// Update until no job runs (or time runs out).
fn finish_jobs(app: &mut App, limit: Duration) {
    let t = Instant::now();
    loop {
        app.update();
        if app.world().resource::<Jobs>().running.is_empty() {
            return;
        }
        assert!(t.elapsed() < limit, "jobs still running after {limit:?}");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn a_ray_on_the_organ_places_a_probe_on_its_surface_and_a_miss_places_none() {
    let mut app = app();
    let organ = phantom();
    let (lo, hi) = organ.surface.bounds().unwrap();
    let c = (lo + hi) * 0.5;
    app.world_mut().resource_mut::<Organ>().set(organ.clone());
    // From the anterior side, straight back: hits the anterior surface.
    app.world_mut().write_message(ProbeRay { origin_mm: Vector3::new(c.x, hi.y + 200.0, c.z), direction: -Vector3::y() });
    app.update();
    let probes = app.world().resource::<Probes>();
    assert_eq!(probes.list.len(), 1);
    let p = &probes.list[0];
    let nearest = organ.surface.positions.iter().map(|v| (v - p.point_mm).norm()).fold(f64::INFINITY, f64::min);
    assert!(nearest < 3.0, "the probe lies {nearest} mm off the surface");
    assert!(p.point_mm.y > c.y, "the anterior side is hit first");
    assert!(p.normal.y > 0.3, "outward normal faces the ray: {:?}", p.normal);
    assert!(p.force_n.dot(&p.normal) < 0.0, "a new probe pushes inward");
    // A ray beside the organ.
    app.world_mut().write_message(ProbeRay { origin_mm: Vector3::new(hi.x + 100.0, hi.y + 200.0, c.z), direction: -Vector3::y() });
    app.update();
    assert_eq!(app.world().resource::<Probes>().list.len(), 1);
}

#[test]
fn jobs_run_in_the_background_finish_into_the_state_and_can_be_cancelled() {
    let mut app = app();
    let organ = phantom();
    app.world_mut().resource_mut::<Organ>().set(organ.clone());
    app.world_mut().resource_mut::<Jobs>().spawn("grid", grid_job(organ.seg.clone(), Default::default()));
    // The frame loop does not wait for the job.
    let t = Instant::now();
    app.update();
    assert!(t.elapsed() < Duration::from_millis(500));
    finish_jobs(&mut app, Duration::from_secs(60));
    let grid = app.world().resource::<GridState>().grid.clone().expect("the grid job delivered its grid");
    assert!(app.world().resource::<GridState>().stats.as_ref().unwrap().cells > 100);
    // A simulation, cancelled at once.
    let probe = Probe { point_mm: organ.surface.positions[0], normal: Vector3::y(), force_n: Vector3::new(0.0, -0.5, 0.0) };
    let id = app
        .world_mut()
        .resource_mut::<Jobs>()
        .spawn("simulate", simulate_job(organ.clone(), grid.clone(), FixedChoice::default(), vec![probe.clone()]));
    app.world().resource::<Jobs>().cancel(id);
    finish_jobs(&mut app, Duration::from_secs(120));
    let (label, outcome, _) = app.world().resource::<Jobs>().finished.last().unwrap().clone();
    assert_eq!(label, "simulate");
    assert!(outcome.contains("cancelled"), "{outcome}");
    assert!(app.world().resource::<Simulation>().result.is_none());
    // And one that runs to the end.
    app.world_mut().resource_mut::<Jobs>().spawn("simulate", simulate_job(organ, grid, FixedChoice::default(), vec![probe]));
    finish_jobs(&mut app, Duration::from_secs(300));
    let sim = app.world().resource::<Simulation>();
    let d = sim.result.as_ref().expect("the simulation delivered a deformation");
    assert!(d.max_mm > 0.01 && sim.show_deformed, "{}", d.max_mm);
    assert!(!d.history.is_empty());
}

#[test]
fn loading_errors_are_shown_in_the_ui_not_panicked_on() {
    let mut app = app();
    let dir = std::env::temp_dir().join(format!("umesh-app-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bad = dir.join("broken.nii.gz");
    std::fs::write(&bad, b"\x1f\x8bnot really gzip").unwrap();
    app.world_mut()
        .resource_mut::<Jobs>()
        .spawn("load", load_job(OpenRequest { path: Some(bad.clone()), organ_labels: vec![1], structure_labels: vec![] }));
    finish_jobs(&mut app, Duration::from_secs(30));
    let m = app.world().resource::<UiMessages>();
    assert_eq!(m.unread_errors, 1);
    let (lvl, text) = m.last().unwrap();
    assert_eq!(*lvl, Level::Error);
    assert!(text.contains("broken.nii.gz"), "{text}");
    assert!(app.world().resource::<Organ>().data.is_none(), "nothing half-loaded");
    // A probe ray with no organ: a message, no panic.
    app.world_mut().write_message(ProbeRay { origin_mm: Vector3::zeros(), direction: Vector3::x() });
    app.update();
    assert_eq!(app.world().resource::<UiMessages>().unread_errors, 2);
}

#[test]
fn the_real_totalsegmentator_case_opens_with_liver_and_two_vessels() {
    let path = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/totalsegmentator/example_seg.nii.gz");
    if !path.exists() {
        eprintln!("SKIPPED: {} not found", path.display());
        return;
    }
    // File > Open first lists the labels with their names, guessing the roles.
    let inspect = umesh::app::jobs::inspect_job(path.clone());
    let Ok(JobOutput::Inspected(_, labels)) = inspect(&Default::default(), &Default::default()) else { panic!("inspect failed") };
    let pending = PendingOpen::new(path.clone(), labels);
    let liver = pending.labels.iter().find(|l| l.0 == 5).unwrap();
    assert_eq!((liver.1.as_str(), liver.3), ("liver", 1));
    let mut app = app();
    let req = OpenRequest { path: Some(path), organ_labels: vec![5], structure_labels: vec![63, 64] };
    app.world_mut().resource_mut::<Jobs>().spawn("load", load_job(req));
    finish_jobs(&mut app, Duration::from_secs(60));
    let organ = app.world().resource::<Organ>();
    let d = organ.data.as_ref().expect("loaded");
    let names: Vec<&str> = d.structures.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(names, ["inferior_vena_cava", "portal_vein_and_splenic_vein"]);
    assert!(d.surface.topology().is_watertight());
}
