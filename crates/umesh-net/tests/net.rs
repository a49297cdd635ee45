//! The network: shapes, errors, learning, save/load, TRE, and training end to end.

use burn::optim::{AdamConfig, GradientsParams};
use burn::prelude::*;
use nalgebra::Vector3;
use umesh_net::TrainSettings;
use umesh_net::inference::Predictor;
use umesh_net::model::{load_weights, save_weights};
use umesh_net::training::run_train;
use umesh_net::{ModelInfo, UNetConfig, tre};

fn tiny(steps: usize, channels: usize) -> UNetConfig {
    UNetConfig { steps, channels, in_channels: 3, out_channels: 3 }
}

fn tmp(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("umesh-net-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn output_shape_equals_input_shape_for_every_allowed_grid() {
    let device = Device::flex();
    for (steps, shape) in [(1, [2, 4, 6]), (2, [4, 8, 12]), (3, [8, 16, 8]), (3, [32, 24, 24])] {
        let model = tiny(steps, 2).init(&device);
        let x = Tensor::<5>::zeros([1, 3, shape[0], shape[1], shape[2]], &device);
        assert_eq!(model.forward(x).dims(), [1, 3, shape[0], shape[1], shape[2]], "steps {steps}, {shape:?}");
    }
    // Max pooling keeps the maximum of each 2x2x2 block.
    let x = Tensor::<5>::from_data(
        TensorData::new((0..64).map(|v| v as f32).collect::<Vec<_>>(), [1, 1, 4, 4, 4]),
        &device,
    );
    let p: Vec<f32> = umesh_net::model::max_pool_2x2x2(x).into_data().try_to_vec().unwrap();
    assert_eq!(p, vec![21.0, 23.0, 29.0, 31.0, 53.0, 55.0, 61.0, 63.0]);
}

#[test]
fn wrong_shapes_give_clear_errors() {
    let cfg = tiny(3, 2);
    assert!(cfg.check_shape([1, 3, 32, 24, 24]).is_ok());
    let e = cfg.check_shape([1, 3, 32, 20, 24]).unwrap_err();
    assert!(e.to_string().contains("not divisible by 2^3"), "{e}");
    let e = cfg.check_shape([1, 4, 32, 24, 24]).unwrap_err();
    assert!(e.to_string().contains("4 channels"), "{e}");
    let device = Device::flex();
    let info = info_for(cfg.clone(), [8, 8, 8]);
    let mut p = Predictor::from_model(info, cfg.init(&device), device);
    assert!(p.predict(&vec![0.0; 3 * 8 * 8 * 8], [8, 8, 8]).is_ok());
    let e = p.predict(&[0.0; 10], [8, 8, 8]).unwrap_err().to_string();
    assert!(e.contains("10 values"), "{e}");
    assert!(p.predict(&vec![0.0; 3 * 6 * 8 * 8], [6, 8, 8]).is_err());
}

fn info_for(config: UNetConfig, padded_shape: [usize; 3]) -> ModelInfo {
    ModelInfo {
        config: config.clone(),
        normalization: umesh_net::data::Normalization { input_scale_mm: 1.0, output_scale_mm: 1.0 },
        padded_shape,
        dataset: String::new(),
        train_indices: vec![],
        val_indices: vec![],
        settings: TrainSettings { model: config, ..Default::default() },
        grid_hash: None,
        dataset_config: None,
    }
}

#[test]
fn the_fast_forward_pass_matches_burns_within_1e_4_of_the_largest_output() {
    let device = Device::flex();
    for (cfg, shape, seed) in [
        (UNetConfig { in_channels: 4, ..UNetConfig::cpu() }, [16, 8, 24], 3),
        (tiny(2, 3), [8, 16, 8], 5),
        (tiny(3, 6), [8, 8, 8], 9),
        // Wide layers (40 to 160 channels): the matrix-product path of the paper preset.
        (UNetConfig { steps: 2, channels: 40, in_channels: 3, out_channels: 3 }, [8, 12, 4], 13),
    ] {
        device.seed(seed);
        let info = info_for(cfg.clone(), shape);
        let mut p = Predictor::from_model(info, cfg.init(&device), device.clone());
        let n = cfg.in_channels * shape.iter().product::<usize>();
        let mut rng = umesh_core::rng::SplitMix64(seed);
        // Inputs as sparse as an encoded view: most voxels zero.
        let input: Vec<f32> =
            (0..n).map(|_| if rng.next_f64() < 0.3 { (rng.next_f64() * 4.0 - 2.0) as f32 } else { 0.0 }).collect();
        let fast = p.predict(&input, shape).unwrap().to_vec();
        p.use_burn = true;
        let burn = p.predict(&input, shape).unwrap().to_vec();
        let scale = burn.iter().fold(0f32, |m, v| m.max(v.abs()));
        let worst = fast.iter().zip(&burn).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(scale > 0.0 && worst <= 1e-4 * scale, "{cfg:?}: largest difference {worst} at output scale {scale}");
    }
}

#[test]
fn outputs_read_only_at_the_organ_voxels_are_the_same_bits_as_the_whole_pass_and_0_elsewhere() {
    let device = Device::flex();
    for (cfg, shape, seed) in [
        (UNetConfig { in_channels: 4, ..UNetConfig::cpu() }, [16, 8, 24], 3),
        (tiny(2, 3), [8, 16, 8], 5),
        // Wide layers compute every voxel (the head, 3 channels, still only those asked for).
        (UNetConfig { steps: 2, channels: 40, in_channels: 3, out_channels: 3 }, [8, 12, 4], 13),
    ] {
        device.seed(seed);
        let info = info_for(cfg.clone(), shape);
        let mut p = Predictor::from_model(info, cfg.init(&device), device.clone());
        let n = shape.iter().product::<usize>();
        let mut rng = umesh_core::rng::SplitMix64(seed);
        let input: Vec<f32> = (0..cfg.in_channels * n)
            .map(|_| if rng.next_f64() < 0.3 { (rng.next_f64() * 4.0 - 2.0) as f32 } else { 0.0 })
            .collect();
        // An organ's nodes: an ellipsoid in the middle of the box, as a padded grid holds one.
        let [a, b, c] = shape;
        let voxels: Vec<usize> = (0..n)
            .filter(|&v| {
                let (i, j, k) = (v / (b * c), (v / c) % b, v % c);
                let r = |x: usize, d: usize| (x as f64 + 0.5 - d as f64 / 2.0) / (0.4 * d as f64);
                r(i, a).powi(2) + r(j, b).powi(2) + r(k, c).powi(2) <= 1.0
            })
            .collect();
        assert!(voxels.len() > n / 10 && voxels.len() < n / 2, "{} of {n}", voxels.len());
        let whole = p.predict(&input, shape).unwrap().to_vec();
        p.read_only_at(&voxels);
        let part = p.predict(&input, shape).unwrap().to_vec();
        let mut asked = vec![false; n];
        voxels.iter().for_each(|&v| asked[v] = true);
        for ch in 0..3 {
            for v in 0..n {
                let (w, q) = (whole[ch * n + v], part[ch * n + v]);
                if asked[v] {
                    assert_eq!(w.to_bits(), q.to_bits(), "{cfg:?}: channel {ch}, voxel {v}: {w} against {q}");
                } else {
                    assert_eq!(q, 0.0, "{cfg:?}: channel {ch}, voxel {v} not asked for");
                }
            }
        }
        // An index outside the box: every output computed again.
        p.read_only_at(&[n]);
        assert_eq!(p.predict(&input, shape).unwrap(), whole.as_slice(), "{cfg:?}");
    }
}

#[test]
fn a_tiny_network_overfits_a_handful_of_samples() {
    let device = Device::flex();
    device.seed(1);
    let ad = device.autodiff();
    let mut model = tiny(1, 8).init(&ad);
    let mut optim = AdamConfig::new().init();
    // Smooth inputs (random values on a 2^3 lattice, each repeated over a 4^3 block), like
    // displacement fields, and a target the network can express: a scaled copy.
    // Inputs from our own generator: the backend's RNG is global and shared with the tests
    // running beside this one.
    let mut rng = umesh_core::rng::SplitMix64(11);
    let vals: Vec<f32> = (0..4 * 3 * 8).map(|_| (rng.next_f64() * 2.0 - 1.0) as f32).collect();
    let coarse = Tensor::<5>::from_data(TensorData::new(vals, [4, 3, 2, 2, 2]), &ad);
    let x = coarse.repeat_dim(2, 4).reshape([4, 3, 4, 2, 2, 2]).swap_dims(2, 3).reshape([4, 3, 8, 2, 2]);
    let x = x.repeat_dim(3, 4).reshape([4, 3, 8, 4, 2, 2]).swap_dims(3, 4).reshape([4, 3, 8, 8, 2]);
    let x = x.repeat_dim(4, 4).reshape([4, 3, 8, 8, 4, 2]).swap_dims(4, 5).reshape([4, 3, 8, 8, 8]).detach();
    let y = (x.clone() * 0.5).detach();
    let mut first = 0.0;
    let mut last = 0.0;
    for step in 0..700 {
        let loss = (model.forward(x.clone()) - y.clone()).square().mean();
        let v = loss.clone().into_scalar::<f32>() as f64;
        if step == 0 {
            first = v;
        }
        last = v;
        let grads = GradientsParams::from_grads(loss.backward(), &model);
        model = optim.step(if step < 400 { 3e-3 } else { 1e-3 }, model, grads);
    }
    eprintln!("overfitting: loss {first:e} -> {last:e}");
    // The initial weights come from the backend's global RNG, which the tests beside this one
    // draw from too: the loss fell 255-450 times in three runs alone and 89 times in one full
    // run; at least 50 times says the network learns.
    assert!(last < first / 50.0, "loss {first:e} -> {last:e}");
}

#[test]
fn save_then_load_reproduces_predictions_exactly() {
    let device = Device::flex();
    device.seed(7);
    let cfg = tiny(2, 3);
    let model = cfg.init(&device);
    let dir = tmp("saveload");
    save_weights(&model, &dir.join("model.safetensors")).unwrap();
    info_for(cfg.clone(), [8, 8, 8]).write(&dir).unwrap();
    let input: Vec<f32> = (0..3 * 512).map(|i| ((i * 37 % 101) as f32 - 50.0) / 10.0).collect();
    let mut a = Predictor::from_model(info_for(cfg.clone(), [8, 8, 8]), model, device.clone());
    let pa = a.predict(&input, [8, 8, 8]).unwrap().to_vec();
    let mut b = Predictor::load(&dir).unwrap();
    let pb = b.predict(&input, [8, 8, 8]).unwrap().to_vec();
    assert_eq!(pa, pb);
    // A fresh model differs until the weights are loaded into it.
    let mut fresh = cfg.init(&device);
    load_weights(&mut fresh, &dir.join("model.safetensors")).unwrap();
    let mut c = Predictor::from_model(info_for(cfg, [8, 8, 8]), fresh, device);
    assert_eq!(c.predict(&input, [8, 8, 8]).unwrap(), &pb[..]);
    // Missing or corrupt weights are clear errors.
    std::fs::write(dir.join("model.safetensors"), b"junk").unwrap();
    assert!(Predictor::load(&dir).unwrap_err().to_string().contains("model.safetensors"));
}

#[test]
fn tre_of_a_known_offset_is_that_offset() {
    let r = Vector3::new(30.0, 20.0, 15.0);
    let s = umesh_core::grid::GridSettings { cell_size_mm: 5.0, pooling_steps: 2, ..Default::default() };
    let g = umesh_core::grid::build(
        -r,
        r,
        move |p| p.coords.component_div(&r).norm() <= 1.0,
        &s,
        &Default::default(),
        &Default::default(),
    )
    .unwrap();
    let [x, y, z] = g.padded_shape();
    let cells = x * y * z;
    let mut truth = vec![0f32; 3 * cells];
    for n in 0..g.node_count() {
        let p = g.node_position(n);
        let d = g.dense_index(n);
        truth[d] = (0.1 * p.x) as f32; // a linear field, reproduced exactly by the interpolation
        truth[cells + d] = 2.0;
    }
    let mut pred = truth.clone();
    for n in 0..g.node_count() {
        let d = g.dense_index(n);
        pred[2 * cells + d] += 3.0;
        pred[cells + d] -= 4.0;
    }
    let markers = tre::markers(&g, 10, 1);
    assert_eq!(markers.len(), 10);
    assert_eq!(markers, tre::markers(&g, 10, 1), "markers are fixed by the seed");
    let (err, moved) = tre::marker_errors(&g, &markers, &pred, &truth);
    for (e, (m, p)) in err.iter().zip(moved.iter().zip(&markers)) {
        assert!((e - 5.0).abs() < 1e-5, "{e}");
        assert!((m - ((0.1 * p.x).powi(2) + 4.0).sqrt()).abs() < 1e-5);
    }
    let (mean, std, max) = tre::summary(&err);
    assert!((mean - 5.0).abs() < 1e-5 && std < 1e-5 && (max - 5.0).abs() < 1e-5);
}

#[test]
fn training_end_to_end_writes_a_model_that_evaluates_and_resumes() {
    let seg = umesh_core::segmentation::bundled_phantom(
        &std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/../../assets/phantom.nii.gz")).unwrap(),
    )
    .unwrap();
    let mut c =
        umesh_core::dataset::DatasetConfig::paper(umesh_core::fem::FixedRegion::Label { label: 2, distance_mm: 8.0 });
    c.samples = 10;
    c.shard_size = 5;
    c.grid.cell_size_mm = 14.0;
    c.forces.probes = 20;
    c.surface_step = 3;
    let ds = tmp("ds");
    umesh_core::dataset::run_generate(
        &seg,
        &ds,
        &c,
        umesh_core::dataset::ShardSelection::all(),
        &Default::default(),
        &Default::default(),
    )
    .unwrap();
    let out = tmp("model");
    let settings = TrainSettings { model: tiny(3, 2), epochs: 2, batch_size: 2, ..Default::default() };
    let reports = std::sync::Arc::new(std::sync::Mutex::new(Vec::<(u64, u64, String)>::new()));
    let progress = {
        let r = reports.clone();
        umesh_core::Progress::new(move |done, total, msg| r.lock().unwrap().push((done, total, msg.to_string())))
    };
    let r = run_train(&ds, &out, &settings, false, &progress, &|_| {}, &Default::default()).unwrap();
    assert_eq!(r.epochs.len(), 2);
    // Progress never goes back, the confidence calibration after the last epoch included (a
    // job maps the fraction onto its own units: a step back reads as the stage starting over).
    let reports = reports.lock().unwrap().clone();
    assert!(reports.iter().any(|(_, _, m)| m.contains("confidence range")), "{reports:?}");
    for w in reports.windows(2) {
        let frac = |(d, t, _): &(u64, u64, String)| *d as f64 / (*t).max(1) as f64;
        assert!(frac(&w[1]) >= frac(&w[0]), "progress went back: {:?} then {:?}", w[0], w[1]);
    }
    assert_eq!(r.train_samples + r.val_samples, 10);
    assert!(r.epochs.iter().all(|e| e.train_loss.is_finite() && e.val_tre_mean_mm.is_finite()));
    for f in ["model.json", "model.safetensors", "last.safetensors", "metrics.jsonl", "grid.npz"] {
        assert!(out.join(f).exists(), "{f}");
    }
    let info = ModelInfo::read(&out).unwrap();
    // The model knows its grid and refuses another.
    let manifest = umesh_core::dataset::Manifest::read(&ds).unwrap();
    assert_eq!(info.grid_hash.as_deref(), Some(manifest.grid_hash.as_str()));
    assert_eq!(info.dataset_config.as_ref(), Some(&c));
    assert!(info.check_grid(&manifest.grid_hash, manifest.padded_shape).is_ok());
    let e = info.check_grid("0123", manifest.padded_shape).unwrap_err().to_string();
    assert!(e.contains("another grid"), "{e}");
    assert!(info.val_indices.iter().all(|i| i % 5 == 4));
    let ev = umesh_net::eval::run_eval(&out, &ds, 10).unwrap();
    assert_eq!(ev.samples, r.val_samples);
    assert!(ev.tre_mean_mm > 0.0 && ev.marker_displacement_mean_mm > 0.0);
    // The prediction from a camera view does not depend on the order of its points or on
    // repeating them, and little on their density.
    assert_eq!(info.settings.observation.as_ref().map(|o| o.encoding), Some(umesh_core::observation::Encoding::Corner));
    let dataset = umesh_core::dataset::Dataset::open(&ds).unwrap();
    let view = dataset.load_views(&dataset.manifest.shards[0]).unwrap().remove(0);
    let grid_npz = umesh_core::npz::Npz::read(&out.join("grid.npz")).unwrap();
    let surface = umesh_net::data::rest_surface(&grid_npz).unwrap();
    let grid = umesh_core::grid::ImmersedGrid::from_npz(&grid_npz).unwrap();
    let mut obs =
        umesh_core::observation::Observer::new(&grid, &surface, info.settings.observation.clone().unwrap()).unwrap();
    let mut p = Predictor::load(&out).unwrap();
    let mut predict = |pts: &[Vector3<f64>]| {
        let mut x = Vec::new();
        obs.encode(pts, &mut x);
        p.predict(&x, manifest.padded_shape).unwrap().to_vec()
    };
    let base = predict(&view);
    let mut shuffled = view.clone();
    let mut rng = umesh_core::rng::SplitMix64(5);
    for i in (1..shuffled.len()).rev() {
        shuffled.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
    }
    let doubled: Vec<Vector3<f64>> = view.iter().flat_map(|p| [*p, *p]).collect();
    let half: Vec<Vector3<f64>> = view.iter().step_by(2).copied().collect();
    let max_diff = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    let range = base.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
    let (d_shuffle, d_double, d_half) =
        (max_diff(&base, &predict(&shuffled)), max_diff(&base, &predict(&doubled)), max_diff(&base, &predict(&half)));
    eprintln!(
        "prediction change (mm, largest node component; prediction up to {range:.2}): shuffled {d_shuffle:.2e}, doubled {d_double:.2e}, every second point {d_half:.3}"
    );
    // Tolerances: float summation order (1e-3 mm); half the points, 10 % of the largest predicted value.
    assert!(d_shuffle < 1e-3 && d_double < 1e-3, "{d_shuffle} {d_double}");
    assert!(d_half < 0.1 * range.max(1.0), "{d_half} of {range}");
    // Resume continues from the last epoch; a correction form chosen for the old weights is
    // not carried over to the new ones.
    std::fs::write(out.join(umesh_core::register::correction::CorrectionChoice::FILE), "{}").unwrap();
    let more = TrainSettings { epochs: 3, ..settings };
    let r2 = run_train(&ds, &out, &more, true, &Default::default(), &|_| {}, &Default::default()).unwrap();
    assert_eq!(r2.epochs.len(), 3);
    assert_eq!(r2.epochs[0].epoch, 1);
    assert!((r2.epochs[0].train_loss - r.epochs[0].train_loss).abs() < 1e-12);
    assert!(
        !out.join(umesh_core::register::correction::CorrectionChoice::FILE).exists(),
        "a stale correction choice was kept"
    );
    assert_eq!(r2.epochs[2].epoch, 3);
    assert_eq!(std::fs::read_to_string(out.join("metrics.jsonl")).unwrap().lines().count(), 3);
    // A new training that fails (an --init-from that is not a model) or is cancelled leaves the
    // model folder byte for byte; a finished one leaves no file of the earlier model.
    let weights = std::fs::read(out.join("model.safetensors")).unwrap();
    let bad = TrainSettings { init_from: Some(tmp("not-a-model")), ..more.clone() };
    assert!(run_train(&ds, &out, &bad, false, &Default::default(), &|_| {}, &Default::default()).is_err());
    let cancel = umesh_core::Cancel::new();
    cancel.cancel();
    let e = run_train(&ds, &out, &more, false, &Default::default(), &|_| {}, &cancel).unwrap_err();
    assert!(matches!(e, umesh_net::NetError::Cancelled(_)), "{e}");
    assert_eq!(std::fs::read(out.join("model.safetensors")).unwrap(), weights);
    assert_eq!(std::fs::read_to_string(out.join("metrics.jsonl")).unwrap().lines().count(), 3);
    std::fs::write(out.join("stale.txt"), "from the earlier model").unwrap();
    let r3 = run_train(&ds, &out, &more, false, &Default::default(), &|_| {}, &Default::default()).unwrap();
    assert_eq!(r3.epochs.len(), 3);
    assert_eq!(std::fs::read_to_string(out.join("metrics.jsonl")).unwrap().lines().count(), 3);
    assert!(!out.join("stale.txt").exists() && !umesh_core::StagedDir::pending_path(&out).exists());
    // A checkpoint named by a session is a file of the model folder, never a path out of it.
    for name in ["../../../../etc/passwd", "/etc/passwd", "model.json"] {
        let e = match umesh_net::inference::Predictor::load_checkpoint(&out, name) {
            Ok(_) => panic!("{name} was loaded"),
            Err(e) => e.to_string(),
        };
        assert!(e.contains("checkpoint") && e.contains(".safetensors"), "{e}");
    }
    assert!(umesh_net::inference::Predictor::load_checkpoint(&out, "last.safetensors").is_ok());
    // A prior: a model of another grid starts the training (its weights and the scales they
    // expect); a network of another size is refused, naming the option.
    let c2 = umesh_core::dataset::DatasetConfig {
        samples: 5,
        shard_size: 5,
        grid: umesh_core::grid::GridSettings { cell_size_mm: 16.0, ..c.grid.clone() },
        ..c.clone()
    };
    let ds2 = tmp("ds-other-grid");
    umesh_core::dataset::run_generate(
        &seg,
        &ds2,
        &c2,
        umesh_core::dataset::ShardSelection::all(),
        &Default::default(),
        &Default::default(),
    )
    .unwrap();
    let prior = ModelInfo::read(&out).unwrap();
    let from_prior = TrainSettings { prior: Some(out.clone()), epochs: 1, ..more.clone() };
    let out2 = tmp("model-from-prior");
    run_train(&ds2, &out2, &from_prior, false, &Default::default(), &|_| {}, &Default::default()).unwrap();
    let fine_tuned = ModelInfo::read(&out2).unwrap();
    assert_ne!(fine_tuned.grid_hash, prior.grid_hash);
    assert_eq!(fine_tuned.normalization, prior.normalization);
    let scratch = TrainSettings { prior: None, ..from_prior.clone() };
    let out3 = tmp("model-from-scratch");
    run_train(&ds2, &out3, &scratch, false, &Default::default(), &|_| {}, &Default::default()).unwrap();
    assert_ne!(ModelInfo::read(&out3).unwrap().normalization, prior.normalization);
    let other_size = TrainSettings { model: tiny(2, 2), ..from_prior };
    let e =
        run_train(&ds2, &tmp("model-bad-prior"), &other_size, false, &Default::default(), &|_| {}, &Default::default())
            .unwrap_err()
            .to_string();
    assert!(e.contains("--prior") && e.contains("differs"), "{e}");
}
