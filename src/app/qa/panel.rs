//! Panels of the dataset QA browser: open, sort, filter, step, flag (left); the sample's
//! numbers and the dataset's histograms (right).

use crate::app::qa::{Qa, QaFilter, QaSort};
use crate::app::state::{ActiveModel, Organ, UiMessages};
use bevy_egui::egui;
use egui_plot::{Bar, BarChart, Plot};
use std::path::PathBuf;

pub fn left_panel(ui: &mut egui::Ui, qa: &mut Qa, organ: &Organ, model: &ActiveModel, messages: &mut UiMessages) {
    ui.heading("Dataset QA");
    if qa.path_text.is_empty() {
        qa.path_text = "out/gui-dataset".into();
    }
    ui.horizontal(|ui| {
        ui.label("folder");
        ui.add(egui::TextEdit::singleline(&mut qa.path_text).desired_width(150.0));
    });
    ui.horizontal(|ui| {
        if ui.add_enabled(qa.busy().is_none(), egui::Button::new("Open dataset")).clicked()
            && let Err(e) = qa.open(PathBuf::from(qa.path_text.trim()), organ, model)
        {
            messages.error(format!("{e:#}"));
        }
        if let Some(b) = qa.busy() {
            ui.spinner();
            ui.weak(b);
        }
    });
    ui.weak(format!("model: {} ({})", crate::app::state::short_path(&model.dir), model.checkpoint));
    let Some(m) = &qa.manifest else {
        ui.label("Open a dataset written by `umesh dataset generate` or the Jobs view, for the organ loaded now.");
        return;
    };
    ui.label(format!(
        "{} samples: {} accepted, {} rejected, {} flagged",
        m.samples.len(),
        m.accepted().count(),
        m.samples.iter().filter(|s| !s.accepted).count(),
        m.samples.iter().filter(|s| s.flagged).count()
    ));
    ui.separator();
    let (old_sort, old_filter) = (qa.sort, qa.filter);
    egui::ComboBox::from_label("sort").selected_text(format!("{:?}", qa.sort)).show_ui(ui, |ui| {
        ui.selectable_value(&mut qa.sort, QaSort::Index, "index");
        ui.selectable_value(&mut qa.sort, QaSort::LargestDisplacement, "largest displacement");
        ui.selectable_value(&mut qa.sort, QaSort::MostIterations, "most Newton iterations");
        ui.selectable_value(&mut qa.sort, QaSort::LargestError, "largest network error");
    });
    egui::ComboBox::from_label("show").selected_text(format!("{:?}", qa.filter)).show_ui(ui, |ui| {
        ui.selectable_value(&mut qa.filter, QaFilter::Accepted, "accepted, not flagged");
        ui.selectable_value(&mut qa.filter, QaFilter::Flagged, "flagged");
        ui.selectable_value(&mut qa.filter, QaFilter::Rejected, "rejected by the solver");
        ui.selectable_value(&mut qa.filter, QaFilter::All, "all");
    });
    if qa.sort != old_sort || qa.filter != old_filter {
        qa.reorder();
    }
    if qa.sort == QaSort::LargestError && qa.tre.is_empty() {
        ui.weak("errors are known after \"Evaluate all\"");
    }
    if qa.order.is_empty() {
        ui.label("No sample matches.");
        return;
    }
    let mut c = qa.cursor;
    let n = qa.order.len();
    ui.add(egui::Slider::new(&mut c, 0..=n - 1).text(format!("of {n}")));
    if c != qa.cursor {
        let d = c as i64 - qa.cursor as i64;
        qa.step(d);
    }
    ui.horizontal(|ui| {
        if ui.button("◀ previous").clicked() {
            qa.step(-1);
        }
        if ui.button("next ▶").clicked() {
            qa.step(1);
        }
    });
    ui.weak("keys: left / right arrow step, R flags or unflags");
    if let Some(r) = qa.current_record().cloned() {
        let label = if r.flagged { "Unflag (keep for training)" } else { "Flag as rejected (training skips it)" };
        if ui.button(label).clicked() {
            match qa.toggle_flag() {
                Ok(msg) => messages.info(msg),
                Err(e) => messages.error(format!("{e:#}")),
            }
        }
    }
    ui.separator();
    ui.checkbox(&mut qa.show_u_s, "show the input u_s (arrows)");
    let has_model = qa.predictor.is_some();
    ui.add_enabled(has_model, egui::Checkbox::new(&mut qa.show_prediction, "prediction beside the FE truth"));
    if ui.add_enabled(has_model && qa.busy().is_none(), egui::Button::new("Evaluate all (per-sample TRE)")).clicked() {
        qa.evaluate_all();
    }
}

fn histogram(ui: &mut egui::Ui, id: &str, title: &str, values: &[f64], bins: usize) {
    if values.is_empty() {
        return;
    }
    let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let w = ((hi - lo) / bins as f64).max(1e-9);
    let mut counts = vec![0usize; bins];
    for v in values {
        counts[(((v - lo) / w) as usize).min(bins - 1)] += 1;
    }
    ui.label(title);
    let bars: Vec<Bar> =
        counts.iter().enumerate().map(|(i, &c)| Bar::new(lo + (i as f64 + 0.5) * w, c as f64).width(w * 0.9)).collect();
    Plot::new(id)
        .height(90.0)
        .allow_drag(false)
        .allow_zoom(false)
        .allow_scroll(false)
        .show(ui, |p| p.bar_chart(BarChart::new(title, bars)));
}

pub fn right_panel(ui: &mut egui::Ui, qa: &Qa) {
    ui.heading("Sample");
    match (qa.current_record(), &qa.sample) {
        (Some(r), s) => {
            egui::Grid::new("sample").num_columns(2).show(ui, |ui| {
                ui.label("index");
                ui.label(r.index.to_string());
                ui.end_row();
                ui.label("status");
                ui.label(if !r.accepted {
                    format!("rejected: {}", r.reason.clone().unwrap_or_default())
                } else if r.flagged {
                    "flagged".into()
                } else {
                    "accepted".into()
                });
                ui.end_row();
                ui.label("max displacement");
                ui.label(format!("{:.2} mm", r.max_displacement_mm));
                ui.end_row();
                ui.label("mean displacement");
                ui.label(format!("{:.2} mm", r.mean_displacement_mm));
                ui.end_row();
                ui.label("Newton iterations");
                ui.label(r.newton_iterations.to_string());
                ui.end_row();
                ui.label("solve time");
                ui.label(r.solve_ms.map(|t| format!("{t:.0} ms")).unwrap_or("-".into()));
                ui.end_row();
                if let Some(s) = s.as_ref().filter(|s| s.index == r.index) {
                    ui.label("probes");
                    let total: f64 = s.forces_n.iter().map(|f| f.norm()).sum();
                    ui.label(format!("{} ({total:.2} N in total)", s.probes_mm.len()));
                    ui.end_row();
                    if let Some(t) = s.tre_mm {
                        ui.label("network TRE");
                        ui.strong(format!("{t:.2} mm"));
                        ui.end_row();
                    }
                    if let Some((_, err, _)) = &s.predicted {
                        ui.label("surface error");
                        ui.label(format!("{:.2} mm max", err.iter().copied().fold(0.0, f32::max)));
                        ui.end_row();
                    }
                }
            });
            if !r.accepted {
                ui.weak("Rejected samples have no displacement to show.");
            }
        }
        (None, _) => {
            ui.label("No sample.");
        }
    }
    ui.separator();
    ui.heading("Dataset");
    let Some(m) = &qa.manifest else { return };
    let acc: Vec<_> = m.accepted().collect();
    histogram(
        ui,
        "h_disp",
        "max displacement (mm)",
        &acc.iter().map(|s| s.max_displacement_mm).collect::<Vec<_>>(),
        20,
    );
    histogram(
        ui,
        "h_newton",
        "Newton iterations",
        &acc.iter().map(|s| s.newton_iterations as f64).collect::<Vec<_>>(),
        10,
    );
    let tre: Vec<f64> = qa.tre.values().copied().collect();
    if tre.len() > 1 {
        histogram(
            ui,
            "h_tre",
            &format!("network TRE (mm), mean {:.2}", tre.iter().sum::<f64>() / tre.len() as f64),
            &tre,
            20,
        );
    }
}
