//! RealSense cameras without a camera: genuine RealSense recordings (.db3) written from the
//! project's synthetic recordings by librealsense's software_device and recorder
//! (tests/realsense/make_recording.py), then imported, registered, streamed through the
//! bridge into `umesh register --source` and the AR view, and damaged in the ways files are.

use bevy::prelude::*;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use crate::support::{json, umesh};

fn tmp(name: &str) -> PathBuf {
    crate::support::scratch("camera", name)
}

/// The Python with pyrealsense2 (scripts/setup.sh installs it); None, said, where the wheel
/// could not be installed. In CI it must be there.
fn realsense_python() -> Option<PathBuf> {
    let py = umesh_core::rgbd::realsense::python();
    let ok = Command::new(&py).args(["-c", "import pyrealsense2, numpy, PIL"]).status().is_ok_and(|s| s.success());
    if !ok {
        assert!(
            std::env::var_os("CI").is_none(),
            "pyrealsense2 is missing in CI for {}: scripts/setup.sh should have installed it",
            py.display()
        );
        eprintln!("SKIPPED: {} has no pyrealsense2 (run scripts/setup.sh)", py.display());
        return None;
    }
    Some(py)
}

/// Write a RealSense recording from a recording folder (extra: the maker's options).
fn make_db3(py: &Path, src: &Path, out: &Path, extra: &[&str]) {
    let _ = std::fs::remove_file(out);
    let maker = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/realsense/make_recording.py");
    let o = Command::new(py).arg(&maker).arg(src).arg(out).args(extra).output().unwrap();
    assert!(o.status.success(), "make_recording.py: {}", String::from_utf8_lossy(&o.stderr));
}

/// One synthetic recording of 6 frames at 1 frame a second (slow enough that a registration
/// keeps up when it is played at its own rate), its copy without masks, and its .db3.
struct Fixture {
    rec: PathBuf,
    nomask: PathBuf,
    db3: PathBuf,
    py: PathBuf,
}

fn fixture() -> Option<&'static Fixture> {
    static F: OnceLock<Option<Fixture>> = OnceLock::new();
    F.get_or_init(|| {
        let py = realsense_python()?;
        let rec = tmp("rec");
        let _ = std::fs::remove_dir_all(&rec);
        let (ok, _, err) =
            umesh(&["rgbd", "synth", "--frames", "6", "--fps", "1", "--seed", "3", "--out", rec.to_str().unwrap()]);
        assert!(ok, "{err}");
        // Both sides without masks: a RealSense recording carries none.
        let nomask = tmp("rec-nomask");
        let _ = std::fs::remove_dir_all(&nomask);
        std::fs::create_dir_all(&nomask).unwrap();
        for e in std::fs::read_dir(&rec).unwrap().flatten() {
            let name = e.file_name();
            if name == "mask" {
                continue;
            }
            let to = nomask.join(&name);
            if e.path().is_dir() {
                std::fs::create_dir_all(&to).unwrap();
                for f in std::fs::read_dir(e.path()).unwrap().flatten() {
                    std::fs::copy(f.path(), to.join(f.file_name())).unwrap();
                }
            } else {
                std::fs::copy(e.path(), to).unwrap();
            }
        }
        let db3 = tmp("rec.db3");
        make_db3(&py, &rec, &db3, &[]);
        Some(Fixture { rec, nomask, db3, py })
    })
    .as_ref()
}

fn tres(report_dir: &Path) -> Vec<f64> {
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report_dir.join("report.json")).unwrap()).unwrap();
    r["frames"].as_array().unwrap().iter().map(|f| f["tre_mean_mm"].as_f64().unwrap()).collect()
}

#[test]
fn a_realsense_recording_imports_and_registers_with_the_tre_of_the_folder_it_came_from() {
    let Some(f) = fixture() else { return };
    let imp = tmp("imported");
    let (ok, out, err) = umesh(&["rgbd", "import", f.db3.to_str().unwrap(), "--out", imp.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let v = json(&out);
    assert_eq!(
        (v["frames"].as_u64(), v["dropped"].as_u64(), v["frames_without_color"].as_u64()),
        (Some(6), Some(0), Some(0)),
        "{v}"
    );
    assert_eq!(v["depth_scale"].as_f64(), Some(1000.0), "{v}");
    assert!((v["fps"].as_f64().unwrap() - 1.0).abs() < 1e-6, "{v}");
    // The device's intrinsics are the folder's.
    let k = |p: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap() };
    assert_eq!(k(&imp.join("intrinsics.json")), k(&f.rec.join("intrinsics.json")));
    // Frame numbers and timestamps kept, one per frame, in order.
    let frames = k(&imp.join("frames.json"));
    let numbers: Vec<u64> = frames.as_array().unwrap().iter().map(|x| x["device_frame"].as_u64().unwrap()).collect();
    assert_eq!(numbers, vec![1, 2, 3, 4, 5, 6]);
    // Registered as the folder is (its ground truth and trajectory beside it): TRE per frame
    // within 0.05 mm.
    for name in ["ground_truth.json", "trajectory.log"] {
        std::fs::copy(f.rec.join(name), imp.join(name)).unwrap();
    }
    let reg = |rec: &Path, out: &str, extra: &[&str]| {
        let out = tmp(out);
        let mut args = vec![
            "register",
            "--recording",
            rec.to_str().unwrap(),
            "--no-overlay",
            "--json",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let (ok, stdout, err) = umesh(&args);
        assert!(ok, "{err}");
        (json(&stdout), tres(&out))
    };
    let (va, a) = reg(&f.nomask, "reg-folder", &[]);
    let (vb, b) = reg(&imp, "reg-imported", &[]);
    assert_eq!(va["pose"], "tracked", "a trajectory with a pose a frame is followed: {va}");
    assert_eq!((a.len(), b.len()), (6, 6));
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        assert!((x - y).abs() <= 0.05, "frame {i}: folder {x} mm, imported {y} mm");
    }
    assert_eq!(vb["pose"], va["pose"]);
    // The .db3 registered directly (imported on the way): no trajectory in it, so the given
    // initial pose and icp-first, against the folder the same way.
    let traj = f.rec.join("trajectory.log");
    let truth = f.rec.join("ground_truth.json");
    let common = ["--pose", "icp-first", "--initial-pose", traj.to_str().unwrap()];
    let (_, c) = reg(&f.nomask, "reg-folder-icp", &common);
    let mut direct = common.to_vec();
    direct.extend(["--ground-truth", truth.to_str().unwrap()]);
    let (vd, d) = reg(&f.db3, "reg-db3", &direct);
    assert_eq!(vd["pose"], "icp-first", "{vd}");
    assert_eq!(d.len(), 6, "{vd}");
    for (i, (x, y)) in c.iter().zip(&d).enumerate() {
        assert!((x - y).abs() <= 0.05, "frame {i}: folder {x} mm, .db3 {y} mm");
    }
    // Without a pose, the direct registration says what is missing.
    let (ok, _, err) =
        umesh(&["register", "--recording", f.db3.to_str().unwrap(), "--out", tmp("reg-nopose").to_str().unwrap()]);
    assert!(!ok && err.contains("initial camera pose"), "{err}");
}

#[test]
fn damaged_or_wrong_realsense_files_each_give_one_clear_error_and_leave_the_output_alone() {
    let Some(f) = fixture() else { return };
    let out = tmp("import-bad");
    // An earlier import that must survive every failed one.
    let (ok, _, err) = umesh(&["rgbd", "import", f.db3.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(ok, "{err}");
    let before = std::fs::read(out.join("frames.json")).unwrap();
    let truncated = tmp("truncated.db3");
    let bytes = std::fs::read(&f.db3).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let garbage = tmp("garbage.db3");
    std::fs::write(&garbage, b"this is a text file, not a RealSense recording\n".repeat(100)).unwrap();
    let color_only = tmp("color-only.db3");
    make_db3(&f.py, &f.rec, &color_only, &["--color-only", "--frames", "3"]);
    let resized = tmp("resized.db3");
    make_db3(&f.py, &f.rec, &resized, &["--resize-depth-at", "2", "--frames", "4"]);
    let missing = tmp("missing.db3");
    for (file, expect) in [
        (&truncated, "not a RealSense recording"),
        (&garbage, "not a RealSense recording"),
        (&color_only, "no depth stream"),
        (&resized, "size"),
        (&missing, "no such file"),
    ] {
        let (ok, stdout, err) = umesh(&["rgbd", "import", file.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        let name = file.file_name().unwrap().to_string_lossy().into_owned();
        assert!(!ok, "{name}: exit 0 ({stdout})");
        assert!(err.contains(&name) && err.contains(expect), "{name}: {err}");
        assert!(!err.contains("Traceback") && !err.contains("panicked"), "{name}: {err}");
        assert_eq!(std::fs::read(out.join("frames.json")).unwrap(), before, "{name}: the earlier import was touched");
    }
}

/// Serve the fixture's .db3 at its own rate through `umesh rgbd realsense`, with the
/// synthetic camera's poses as a tracker would give them; returns the server and its address.
fn serve(f: &Fixture, name: &str) -> (std::process::Child, String, PathBuf) {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let log = tmp(name);
    let child = Command::new(env!("CARGO_BIN_EXE_umesh"))
        .args(["rgbd", "realsense", "--file", f.db3.to_str().unwrap(), "--realtime", "--listen", &addr])
        .args(["--pose-file", f.rec.join("trajectory.log").to_str().unwrap()])
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while !std::fs::read_to_string(&log).unwrap_or_default().contains("serving") {
        assert!(
            t0.elapsed().as_secs() < 30,
            "the bridge did not start: {}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    (child, addr, log)
}

#[test]
fn the_bridge_streams_a_realsense_recording_into_register_with_its_tracked_pose_and_end_to_end_latency() {
    let Some(f) = fixture() else { return };
    let (mut server, addr, log) = serve(f, "serve-register.log");
    let out = tmp("reg-live");
    let (ok, stdout, err) =
        umesh(&["register", "--source", &addr, "--no-overlay", "--json", "--out", out.to_str().unwrap()]);
    let _ = server.wait();
    assert!(ok, "{err}\nbridge: {}", std::fs::read_to_string(&log).unwrap_or_default());
    let v = json(&stdout);
    let (frames, dropped) = (v["frames"].as_u64().unwrap(), v["dropped"].as_u64().unwrap());
    assert!(frames >= 5, "{frames} of 6 frames registered: {v}");
    assert_eq!(frames + dropped, 6, "every frame arrives or is counted as dropped: {v}");
    // The stream carries the tracker's pose on every frame: followed without a flag.
    assert_eq!(v["pose"], "tracked", "{v}");
    assert!(v["pose_reason"].as_str().unwrap().contains("every frame"), "{v}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    for fr in report["frames"].as_array().unwrap() {
        let e = fr["end_to_end_ms"].as_f64().unwrap_or(-1.0);
        let total = fr["latency"]["total_ms"].as_f64().unwrap();
        assert!(e >= total && e < 60_000.0, "frame {}: end to end {e} ms, registration {total} ms", fr["frame"]);
    }
    assert!(v["end_to_end_ms_median"].as_f64().is_some(), "{v}");
}

#[test]
fn the_ar_view_plays_a_realsense_recording_through_the_bridge_and_names_a_missing_library() {
    use umesh::app::ar::{Ar, ArSession, ArSource};
    use umesh::app::state::{ActiveModel, OpenRequest, UiMessages};
    let Some(f) = fixture() else { return };
    let mut app = App::new();
    app.add_plugins(MinimalPlugins).add_plugins(umesh::app::CorePlugins);
    let organ =
        match umesh::app::model::compute::load_job(OpenRequest::default())(&Default::default(), &Default::default()) {
            Ok(umesh::app::shell::tasks::JobOutput::Loaded(d)) => d,
            _ => panic!("the bundled phantom did not load"),
        };
    // Played at its own rate, as a camera: half a frame a second, so that a registration on a
    // machine busy with other tests keeps up (the first frame builds the correction's model).
    let slow = tmp("ar-slow.db3");
    make_db3(&f.py, &f.rec, &slow, &["--fps", "0.5"]);
    let req = umesh_core::rgbd::realsense::RealSenseRequest::recording(&slow);
    let s = ArSession::start(ArSource::RealSense(req), organ.seg.clone(), ActiveModel::default(), None);
    s.send(umesh::app::ar::ArCommand::Play(true));
    app.world_mut().resource_mut::<Ar>().session = Some(s);
    let t = Instant::now();
    let mut seen = std::collections::BTreeSet::new();
    let mut dropped = 0;
    loop {
        app.update();
        let ar = app.world().resource::<Ar>();
        if let Some(fr) = &ar.last {
            seen.insert(fr.report.frame);
            dropped = fr.dropped;
        }
        let ended = app.world().resource::<UiMessages>().list.iter().any(|(_, m)| m.contains("ended"));
        if ended {
            break;
        }
        assert!(ar.session.is_some(), "{:?}", app.world().resource::<UiMessages>().list);
        assert!(t.elapsed() < Duration::from_secs(120), "the recording did not end: {seen:?}");
        std::thread::sleep(Duration::from_millis(5));
    }
    let ar = app.world().resource::<Ar>();
    assert!(seen.len() >= 5, "frames shown {seen:?}, dropped {dropped}");
    assert!(seen.len() as u64 + dropped >= 6, "frames shown {seen:?}, dropped {dropped}");
    assert!(ar.label.contains("RealSense recording"), "{}", ar.label);
    let (_, why) = ar.pose_in_use.as_ref().expect("the pose in use is said");
    assert!(why.contains("icp-first"), "a RealSense file carries no tracked pose: {why}");
    // A file the bridge cannot read: one message in the panel naming it, the session closed.
    let mut app2 = App::new();
    app2.add_plugins(MinimalPlugins).add_plugins(umesh::app::CorePlugins);
    let garbage = tmp("ar-garbage.db3");
    std::fs::write(&garbage, b"not a recording\n".repeat(50)).unwrap();
    let req = umesh_core::rgbd::realsense::RealSenseRequest::recording(&garbage);
    let s = ArSession::start(ArSource::RealSense(req), organ.seg.clone(), ActiveModel::default(), None);
    app2.world_mut().resource_mut::<Ar>().session = Some(s);
    let t = Instant::now();
    loop {
        app2.update();
        let msgs = &app2.world().resource::<UiMessages>().list;
        if let Some((_, m)) = msgs.iter().find(|(_, m)| m.contains("ar-garbage.db3")) {
            assert!(m.contains("not a RealSense recording"), "{m}");
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "no message: {msgs:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(app2.world().resource::<Ar>().session.is_none(), "the failed session is closed");
}

#[test]
fn without_pyrealsense2_the_camera_commands_say_how_to_install_it() {
    let Some(f) = fixture() else { return };
    // A Python without site-packages: no pyrealsense2.
    let fake = tmp("python-without-site.sh");
    std::fs::write(&fake, "#!/bin/sh\nexec python3 -S \"$@\"\n").unwrap();
    std::process::Command::new("chmod").arg("+x").arg(&fake).status().unwrap();
    for args in [
        vec!["rgbd", "import", f.db3.to_str().unwrap(), "--out", tmp("import-nolib").to_str().unwrap()],
        vec!["rgbd", "realsense", "--list"],
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_umesh")).args(&args).env("UMESH_PYTHON", &fake).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}: exit 0");
        assert!(err.contains("pyrealsense2") && err.contains("scripts/setup.sh"), "{args:?}: {err}");
    }
    // No camera on this machine: the list is empty, said plainly.
    let (ok, out, err) = umesh(&["rgbd", "realsense", "--list"]);
    assert!(ok && out.contains("no RealSense camera"), "{out}{err}");
    // Serving a camera that is not there ends with one error once a client connects.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let child = Command::new(env!("CARGO_BIN_EXE_umesh"))
        .args(["rgbd", "realsense", "--listen", &addr])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let client = loop {
        if let Ok(c) = std::net::TcpStream::connect(&addr) {
            break c;
        }
        assert!(t0.elapsed().as_secs() < 30, "the bridge did not listen");
        std::thread::sleep(Duration::from_millis(50));
    };
    let out = child.wait_with_output().unwrap();
    drop(client);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("no RealSense camera is connected"), "{err}");
}
