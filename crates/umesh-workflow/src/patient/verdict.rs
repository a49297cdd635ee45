//! Whether a prepared patient is ready for the operating room, and if not what is wrong and
//! what to do: read from its figures, never from a single number a reader could mistake (the
//! check recording's TRE at a few millimetres of motion says little about the model).

use super::{CheckReport, Verdict};
use umesh_net::eval::EvalReport;
use umesh_net::training::EpochMetrics;

/// The validation TRE may be at most this share of the validation markers' mean motion: the
/// bundled phantom's model is at about 14 %, the CT patient's at 16-20 %; a model stopped
/// after 4 of 20 epochs was at 63 %.
pub const VAL_SHARE_READY: f64 = 0.25;
/// The check registration's last frame: at most this TRE (mm) and this share of rigid
/// alignment's (the registration benchmark's bar).
pub const CHECK_TRE_READY_MM: f64 = 2.0;
pub const CHECK_RIGID_SHARE_READY: f64 = 0.2;
/// Below this motion (mm) the check recording cannot judge the model: rigid alignment alone
/// is nearly as good.
pub const CHECK_MOTION_MIN_MM: f64 = 5.0;

/// Whether more epochs would likely improve the network: its best epoch among the last two
/// (one noisy epoch after the best does not end a descent: 6.8, 5.8, 5.2, 4.0, 4.1 mm is still
/// falling), or its last validation TRE at least 10 % under the one halfway through.
fn still_falling(metrics: &[EpochMetrics], best: Option<usize>) -> bool {
    let (Some(last), Some(best)) = (metrics.last(), best) else { return false };
    let half = &metrics[(metrics.len() - 1) / 2];
    best + 1 >= last.epoch || last.val_tre_mean_mm <= 0.9 * half.val_tre_mean_mm
}

/// The verdict from the training's epochs (`asked_epochs` asked, `stopped_early` why it
/// stopped before them), the validation evaluation and the registration check.
pub fn judge(
    metrics: &[EpochMetrics],
    asked_epochs: usize,
    stopped_early: Option<&str>,
    eval: &EvalReport,
    check: &CheckReport,
    patient_dir: &std::path::Path,
) -> Verdict {
    let mut v = Verdict::default();
    let p = patient_dir.display();
    let motion = eval.marker_displacement_mean_mm;
    let share = if motion > 0.0 { eval.tre_mean_mm / motion } else { f64::INFINITY };
    let run = metrics.len();
    let best = metrics.iter().min_by(|a, b| a.val_loss.total_cmp(&b.val_loss)).map(|m| m.epoch);
    let still_falling = still_falling(metrics, best);
    let cut_by_time = stopped_early.is_some_and(|s| s.starts_with("time budget"));
    if !(share.is_finite() && share <= VAL_SHARE_READY) {
        let mut what = format!(
            "The network's validation TRE is {:.2} mm, {:.0} % of the {:.1} mm its markers move (at most {:.0} % is ready).",
            eval.tre_mean_mm,
            100.0 * share,
            motion,
            100.0 * VAL_SHARE_READY
        );
        if cut_by_time && still_falling {
            what += &format!(
                " Training had {run} of {asked_epochs} epochs when the time budget ended it, its validation error still falling: train on from this model (umesh train --dataset {p}/dataset --init-from {p}/model --out MODEL --epochs {asked_epochs}, then register with --model MODEL) or prepare again in a new folder with a larger --time-budget-min."
            );
        } else {
            what += " More training will not fix it alone: check the fixed region and the camera (report.html's pictures), or make more samples (--samples).";
        }
        v.problems.push(what);
    } else if cut_by_time && still_falling {
        v.notes.push(format!(
            "Training had {run} of {asked_epochs} epochs when the time budget ended it, its validation error still falling: more epochs would improve it."
        ));
    }
    match (check.last_frame_tre_mm, check.last_frame_tre_rigid_mm, check.last_frame_marker_displacement_mm) {
        (Some(tre), Some(rigid), Some(motion)) => {
            if motion < CHECK_MOTION_MIN_MM {
                v.notes.push(format!(
                    "The check recording moved its markers only {motion:.1} mm at its last frame: its TRE ({tre:.2} mm) does not measure the model at a surgeon's loads; the validation TRE above does."
                ));
            } else if !(tre <= CHECK_TRE_READY_MM && tre <= CHECK_RIGID_SHARE_READY * rigid) {
                v.problems.push(format!(
                    "The check registration's last frame is at {tre:.2} mm ({:.0} % of rigid alignment's {rigid:.2} mm; ready is at most {CHECK_TRE_READY_MM} mm and {:.0} %): register with --correction-form tracking --frame-budget-ms 0 to see whether the full FE correction reaches it, and prefer that form if it does.",
                    100.0 * tre / rigid.max(1e-9),
                    100.0 * CHECK_RIGID_SHARE_READY
                ));
            }
        }
        _ => v.problems.push(format!(
            "The registration check did not run ({}): the model is untested on a recording.",
            check.warning.clone().unwrap_or_else(|| "no frame with ground truth".into())
        )),
    }
    if let Some(c) = &check.correction {
        let budget = umesh_core::register::correction::DEFAULT_FRAME_BUDGET_MS;
        let (form, why) = c.choose(Some(budget));
        if [Some(c.subspace), c.coarse_tracking, Some(c.tracking)].iter().flatten().all(|f| f.frame_ms_median > budget)
        {
            v.notes.push(format!(
                "No correction form met the default frame budget on this machine; {} is used. {why}",
                form.name()
            ));
        }
    }
    v.ready = v.problems.is_empty();
    v
}
