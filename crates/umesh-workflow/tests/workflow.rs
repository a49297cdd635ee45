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
        c.visibility.camera = Some(Camera { position_mm: [x, 0.1 * x + 0.3, 88.81], direction: [0.01 * x, -1.0, 0.3], fov_deg: 47.3 });
        let s = PrepareSettings::paper(c, "chosen".into());
        let stored: PrepareSettings = serde_json::from_str(&serde_json::to_string_pretty(&s).unwrap()).unwrap();
        differs += (stored != s) as usize;
        assert!(same_as_stored(&stored, &s).unwrap(), "camera x {x}");
    }
    eprintln!("{differs} of 2000 settings differ from themselves after the JSON round trip");
    // Other settings are still told apart.
    let base = PrepareSettings::paper(DatasetConfig::paper(FixedRegion::Label { label: 2, distance_mm: 6.0 }), "a".into());
    let mut other = base.clone();
    other.eval_markers += 1;
    assert!(!same_as_stored(&base, &other).unwrap());
}
