//! The workflow recipes: the patient folder and its settings.

#[test]
fn a_patient_resumes_with_camera_coordinates_that_have_decimals() {
    use umesh_core::dataset::DatasetConfig;
    use umesh_core::fem::FixedRegion;
    use umesh_core::visible::Camera;
    use umesh_workflow::patient::{PrepareSettings, same_as_stored};
    // patient.json is written and read back as JSON; every one of these settings must be
    // recognised as itself after the round trip.
    let mut differs = 0;
    for i in 0..2000 {
        let x = -173.0 + i as f64 * 0.173_205_080_756_887_7;
        let mut c = DatasetConfig::paper(FixedRegion::Label { label: 2, distance_mm: 6.0 });
        c.visibility.camera =
            Some(Camera { position_mm: [x, 0.1 * x + 0.3, 88.81], direction: [0.01 * x, -1.0, 0.3], fov_deg: 47.3 });
        let s = PrepareSettings::paper(c, "chosen".into());
        let stored: PrepareSettings = serde_json::from_str(&serde_json::to_string_pretty(&s).unwrap()).unwrap();
        differs += (stored != s) as usize;
        assert!(same_as_stored(&stored, &s).unwrap(), "camera x {x}");
    }
    eprintln!("{differs} of 2000 settings differ from themselves after the JSON round trip");
    // Other settings are still told apart.
    let base =
        PrepareSettings::paper(DatasetConfig::paper(FixedRegion::Label { label: 2, distance_mm: 6.0 }), "a".into());
    let mut other = base.clone();
    other.eval_markers += 1;
    assert!(!same_as_stored(&base, &other).unwrap());
}

#[test]
fn the_verdict_is_ready_only_with_a_good_network_and_check_and_says_what_to_do_otherwise() {
    use umesh_net::eval::EvalReport;
    use umesh_net::training::EpochMetrics;
    use umesh_workflow::patient::{CheckReport, SummaryRecord, judge};
    let eval = |tre: f64, motion: f64| EvalReport {
        samples: 100,
        markers_per_sample: 20,
        tre_mean_mm: tre,
        tre_std_mm: 0.5,
        tre_max_mm: 3.0 * tre,
        marker_displacement_mean_mm: motion,
        per_sample_tre_mm: Vec::new(),
        per_marker_tre_mm: Vec::new(),
    };
    // Validation loss falling to the last epoch, or best at epoch 2 of 4.
    let epochs = |losses: &[f64]| -> Vec<EpochMetrics> {
        losses
            .iter()
            .enumerate()
            .map(|(k, &l)| EpochMetrics {
                epoch: k + 1,
                train_loss: l,
                val_loss: l,
                val_tre_mean_mm: l,
                val_tre_max_mm: l,
                seconds: 60.0,
                train_samples_per_s: 10.0,
            })
            .collect()
    };
    let check = |tre: f64, rigid: f64, motion: f64| CheckReport {
        summary: SummaryRecord::default(),
        last_frame_tre_mm: Some(tre),
        last_frame_tre_rigid_mm: Some(rigid),
        last_frame_marker_displacement_mm: Some(motion),
        log: Vec::new(),
        warning: None,
        correction: None,
    };
    let dir = std::path::Path::new("/patients/p1");
    let falling = epochs(&[4.0, 3.0, 2.5, 2.0]);
    let time =
        Some("time budget: another epoch (about 60 s) would end after 600 s of training; stopped after epoch 4 of 20");
    // Ready: 14 % of the motion, the check at 1.2 mm (10 % of rigid).
    let v = judge(&falling, 20, None, &eval(1.4, 10.0), &check(1.2, 12.0, 12.0), dir);
    assert!(v.ready && v.problems.is_empty() && v.line() == "ready", "{v:?}");
    // The new-user case: 4 of 20 epochs, 3.71 mm at 5.9 mm (63 %), a check at 2.96 mm
    // of motion reading 0.50 mm: not ready, says to train on, and that the check says little.
    let v = judge(&falling, 20, time, &eval(3.71, 5.9), &check(0.5, 2.9, 2.96), dir);
    assert!(!v.ready, "{v:?}");
    assert!(
        v.line().contains("63 %")
            && v.line().contains("4 of 20 epochs")
            && v.line().contains("--init-from /patients/p1/model"),
        "{}",
        v.line()
    );
    assert!(v.notes.iter().any(|n| n.contains("only 3.0 mm")), "{v:?}");
    // Cut by time at 5 of 20 epochs with one noisy last epoch (a 2.15 l liver prepared beside
    // other jobs: 6.8, 5.8, 5.2, 4.0, 4.1 mm): still falling, the advice is to train on.
    let noisy = epochs(&[6.8, 5.81, 5.22, 4.04, 4.13]);
    let five = Some(
        "time budget: another epoch (about 368 s) would end after 1807 s of training; stopped after epoch 5 of 20",
    );
    let v = judge(&noisy, 20, five, &eval(4.04, 9.69), &check(1.48, 8.46, 8.45), dir);
    assert!(!v.ready && v.line().contains("5 of 20 epochs") && v.line().contains("--init-from"), "{}", v.line());
    // Stopped by a plateau, not by time: training longer is not the advice.
    let plateau = epochs(&[4.0, 3.0, 3.2, 3.3]);
    let v = judge(&plateau, 20, Some("validation plateau: ..."), &eval(3.0, 10.0), &check(1.0, 12.0, 12.0), dir);
    assert!(!v.ready && !v.line().contains("--init-from") && v.line().contains("30 %"), "{v:?}");
    // A good network, a check far off at 12 mm of motion: not ready, names the tracking form.
    let v = judge(&falling, 20, None, &eval(1.4, 10.0), &check(3.0, 12.0, 12.0), dir);
    assert!(!v.ready && v.line().contains("3.00 mm") && v.line().contains("--correction-form tracking"), "{v:?}");
    // Good, but cut by time while improving: ready, with a note.
    let v = judge(&falling, 20, time, &eval(1.4, 10.0), &check(1.2, 12.0, 12.0), dir);
    assert!(v.ready && v.notes.iter().any(|n| n.contains("4 of 20 epochs")), "{v:?}");
    // No check: not ready, the reason given.
    let v = judge(
        &falling,
        20,
        None,
        &eval(1.4, 10.0),
        &CheckReport::not_run("the check recording could not be made".into()),
        dir,
    );
    assert!(!v.ready && v.line().contains("could not be made"), "{v:?}");
    // A validation set that did not move cannot be judged ready.
    assert!(!judge(&falling, 20, None, &eval(0.0, 0.0), &check(1.2, 12.0, 12.0), dir).ready);
}

#[test]
fn a_grid_over_the_node_limit_gets_larger_cells_and_says_why() {
    use umesh_core::dataset::DatasetConfig;
    use umesh_core::fem::FixedRegion;
    use umesh_core::grid::ImmersedGrid;
    use umesh_workflow::patient::{MAX_GRID_NODES, PrepareSettings, fit_grid_to_budget, same_as_stored};
    let seg = umesh_core::segmentation::bundled_phantom(umesh_workflow::input::PHANTOM_BYTES).unwrap();
    let cancel = umesh_core::Cancel::new();
    let nodes = |s: &PrepareSettings| {
        ImmersedGrid::from_mask(&seg.organ_mask(), &s.dataset.grid, &umesh_core::Progress::none(), &cancel)
            .unwrap()
            .node_count()
    };
    let base =
        PrepareSettings::paper(DatasetConfig::paper(FixedRegion::Label { label: 2, distance_mm: 6.0 }), "a".into());
    assert_eq!(base.max_grid_nodes, MAX_GRID_NODES);
    // The phantom fits the default limit at its 7 mm: kept, and said.
    let kept = fit_grid_to_budget(&seg, &base, &cancel).unwrap();
    assert_eq!(kept.dataset.grid.cell_size_mm, base.dataset.grid.cell_size_mm);
    let at_7 = nodes(&kept);
    assert!(at_7 <= MAX_GRID_NODES, "{at_7}");
    assert!(kept.grid_description.contains(&format!("{at_7} nodes")), "{}", kept.grid_description);
    // Half its nodes: the smallest 1 mm step that fits, with both grids in the description.
    let half = PrepareSettings { max_grid_nodes: at_7 / 2, ..base.clone() };
    let grown = fit_grid_to_budget(&seg, &half, &cancel).unwrap();
    let cell = grown.dataset.grid.cell_size_mm;
    assert!(cell > 7.0 && (cell - 7.0).fract() == 0.0, "{cell}");
    assert!(nodes(&grown) <= at_7 / 2, "{} nodes at {cell} mm", nodes(&grown));
    let one_step_less = PrepareSettings {
        dataset: DatasetConfig {
            grid: umesh_core::grid::GridSettings { cell_size_mm: cell - 1.0, ..grown.dataset.grid.clone() },
            ..grown.dataset.clone()
        },
        ..grown.clone()
    };
    assert!(nodes(&one_step_less) > at_7 / 2, "{cell} mm is not the smallest step that fits");
    assert!(
        grown.grid_description.contains(&format!("{cell} mm")) && grown.grid_description.contains(&at_7.to_string()),
        "{}",
        grown.grid_description
    );
    // No limit: the cell size as asked.
    let none = fit_grid_to_budget(&seg, &PrepareSettings { max_grid_nodes: 0, ..half }, &cancel).unwrap();
    assert_eq!(none.dataset.grid.cell_size_mm, 7.0);
    // A folder from before the limit (neither field) is the same patient as the one fitted now.
    let mut before = kept.clone();
    before.max_grid_nodes = 0;
    before.grid_description.clear();
    assert!(same_as_stored(&before, &kept).unwrap());
}

#[test]
fn a_surface_over_the_triangle_limit_is_marched_at_a_coarser_step_and_says_why() {
    use umesh_core::dataset::{DatasetConfig, organ_surface};
    use umesh_core::fem::FixedRegion;
    use umesh_workflow::patient::{MAX_SURFACE_TRIANGLES, PrepareSettings, fit_surface_to_budget, same_as_stored};
    let seg = umesh_core::segmentation::bundled_phantom(umesh_workflow::input::PHANTOM_BYTES).unwrap();
    let cancel = umesh_core::Cancel::new();
    let mask = seg.organ_mask();
    let base =
        PrepareSettings::paper(DatasetConfig::paper(FixedRegion::Label { label: 2, distance_mm: 6.0 }), "a".into());
    assert_eq!(base.max_surface_triangles, MAX_SURFACE_TRIANGLES);
    let asked = base.dataset.surface_step;
    let at_asked = organ_surface(&mask, asked).triangles.len();
    // A limit the surface fits: the step as asked, and said.
    let roomy = PrepareSettings { max_surface_triangles: at_asked, ..base.clone() };
    let kept = fit_surface_to_budget(&seg, &roomy, &cancel).unwrap();
    assert_eq!(kept.dataset.surface_step, asked);
    assert!(kept.surface_description.contains(&format!("{at_asked} triangles")), "{}", kept.surface_description);
    // Half its triangles: the smallest coarser step that fits, both counts in the description.
    let half = PrepareSettings { max_surface_triangles: at_asked / 2, ..base.clone() };
    let coarse = fit_surface_to_budget(&seg, &half, &cancel).unwrap();
    let step = coarse.dataset.surface_step;
    let at_step = organ_surface(&mask, step).triangles.len();
    assert!(step > asked && at_step <= at_asked / 2, "step {step}: {at_step} triangles");
    assert!(organ_surface(&mask, step - 1).triangles.len() > at_asked / 2, "step {step} is not the smallest that fits");
    for n in [at_step, at_asked] {
        assert!(coarse.surface_description.contains(&n.to_string()), "{}", coarse.surface_description);
    }
    // No limit: the step as asked.
    let none = fit_surface_to_budget(&seg, &PrepareSettings { max_surface_triangles: 0, ..half }, &cancel).unwrap();
    assert_eq!(none.dataset.surface_step, asked);
    // A folder from before the limit (neither field) is the same patient as the one fitted now.
    let mut before = kept.clone();
    before.max_surface_triangles = 0;
    before.surface_description.clear();
    assert!(same_as_stored(&before, &kept).unwrap());
}

#[test]
fn a_patient_starts_from_the_bundled_model_only_when_its_network_and_input_are_the_jobs() {
    use umesh_core::dataset::DatasetConfig;
    use umesh_core::fem::FixedRegion;
    use umesh_workflow::patient::{PrepareSettings, Prior, resolve_prior, same_as_stored};
    let base =
        PrepareSettings::paper(DatasetConfig::paper(FixedRegion::Label { label: 2, distance_mm: 6.0 }), "a".into());
    assert_eq!(base.prior, Prior::Bundled);
    // The default network and input: the bundled model's weights.
    let bundled = resolve_prior(&base).unwrap();
    assert_eq!(bundled.train.prior.as_deref(), Some(umesh_workflow::input::bundled_model().as_path()));
    assert!(bundled.prior_description.contains("bundled"), "{}", bundled.prior_description);
    // Another network: random weights, and why.
    let mut paper = base.clone();
    paper.train.model = umesh_net::UNetConfig::paper();
    let r = resolve_prior(&paper).unwrap();
    assert!(r.train.prior.is_none() && r.prior_description.contains("not this job's"), "{}", r.prior_description);
    // A named model of another network is refused, naming the option; none is random weights.
    let named = PrepareSettings { prior: Prior::Model(umesh_workflow::input::bundled_model()), ..paper };
    let e = resolve_prior(&named).unwrap_err().to_string();
    assert!(e.contains("--prior"), "{e}");
    let none = resolve_prior(&PrepareSettings { prior: Prior::None, ..base.clone() }).unwrap();
    assert!(none.train.prior.is_none() && none.prior_description.contains("random"), "{}", none.prior_description);
    // Where training starts does not make another patient: a folder from before priors resumes.
    assert!(same_as_stored(&PrepareSettings { prior: Prior::None, ..base }, &bundled).unwrap());
}
