//! The pre-flight check of a dataset job: a small batch of the job's own samples, spread over
//! its indices, solved in parallel before anything is written. It projects the acceptance, the
//! achieved displacement and the total time, and names the likely cause when the job would
//! store too little (`dataset generate`, `prepare` and the app's New patient stop on it unless
//! forced).

use std::collections::BTreeMap;

/// How the check runs and what it accepts.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PreflightSettings {
    /// Samples solved (spread over the dataset's indices). The check runs only for jobs with
    /// more samples than this: a smaller job costs no more than its check.
    pub samples: usize,
    /// Below this projected acceptance the job is refused.
    pub min_acceptance: f64,
    /// Below this mean achieved / target displacement of the accepted samples the job is
    /// refused too: it would store samples, but not the deformations asked for.
    #[serde(default = "default_min_achieved")]
    pub min_achieved: f64,
}

fn default_min_achieved() -> f64 {
    PreflightSettings::default().min_achieved
}

impl Default for PreflightSettings {
    fn default() -> Self {
        // 16 samples: on 2 cores about a minute on a 2 l liver; a set-up accepting 97 % is
        // refused (2 or more rejections) with probability 0.08.
        // 0.75: the datasets are asked to reach their target within 25 %; every configuration
        // of the robustness sweep averages 0.87-0.97, an organ held at its core without the
        // strain limit 0.43 (and 17 % of its samples rejected, which 6 samples do not show).
        Self { samples: 16, min_acceptance: 0.9, min_achieved: 0.75 }
    }
}

impl PreflightSettings {
    pub fn validate(&self) -> Result<(), crate::Invalid> {
        if self.samples == 0 || self.samples > 1000 {
            return Err(crate::Invalid(format!("{} pre-flight samples: between 1 and 1000", self.samples)));
        }
        if !(0.0..=1.0).contains(&self.min_acceptance) {
            return Err(crate::Invalid(format!("pre-flight acceptance {}: must lie in [0, 1]", self.min_acceptance)));
        }
        if !(0.0..=1.0).contains(&self.min_achieved) {
            return Err(crate::Invalid(format!(
                "pre-flight achieved / target {}: must lie in [0, 1]",
                self.min_achieved
            )));
        }
        Ok(())
    }
}

/// What the check measured and projects for the whole job.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Preflight {
    pub samples: usize,
    pub accepted: usize,
    /// Accepted samples kept below their target (the converged state nearest an unreachable one).
    pub below_target: usize,
    /// Samples whose target the strain limit lowered, and the median lowered / drawn.
    pub strain_limited: usize,
    pub strain_limited_factor: Option<f64>,
    pub rejected: BTreeMap<String, usize>,
    /// accepted / samples: the projected acceptance of the job.
    pub acceptance: f64,
    /// Mean over the accepted samples of achieved / target mean displacement.
    pub achieved_over_target: Option<f64>,
    /// Median single-threaded time of one sample (s), accepted or not.
    pub sample_seconds: f64,
    pub threads: usize,
    /// The whole job's projected dataset stage (minutes) at this machine's parallelism.
    pub projected_minutes: f64,
    /// Wall time of the check itself (s), the grid and the load calibration included.
    pub seconds: f64,
    /// What the camera sees of the organ surface, and what the fixed region holds of its nodes.
    pub visible_fraction: f64,
    pub fixed_fraction: f64,
    pub fixed_nodes: usize,
    pub nodes: usize,
    /// The likely cause when the acceptance is below the threshold, with the option to change.
    pub cause: Option<String>,
}

impl Preflight {
    /// One line for the terminal and the app.
    pub fn summary(&self) -> String {
        let rejected = if self.rejected.is_empty() {
            String::new()
        } else {
            format!(
                " (rejected: {})",
                self.rejected.iter().map(|(k, v)| format!("{v} {k}")).collect::<Vec<_>>().join(", ")
            )
        };
        let limited = match self.strain_limited_factor {
            Some(f) if self.strain_limited > 0 => {
                format!(
                    " ({} targets lowered by the strain limit, to {:.2} of the drawn one in the median)",
                    self.strain_limited, f
                )
            }
            _ => String::new(),
        };
        format!(
            "pre-flight: {}/{} samples accepted ({:.0} %){rejected}, achieved / target {}{limited}, {:.1} s a sample: about {:.0} min for the dataset on {} threads",
            self.accepted,
            self.samples,
            self.acceptance * 100.0,
            self.achieved_over_target.map(|r| format!("{r:.2}")).unwrap_or_else(|| "-".into()),
            self.sample_seconds,
            self.projected_minutes,
            self.threads
        )
    }

    /// The largest acceptance the check's samples leave plausible: the upper end of the
    /// one-sided 95 % Wilson interval of accepted / samples. 16 samples are few: 13 of them
    /// (81 %) came from a configuration that accepted 95 of 100.
    pub fn acceptance_upper_bound(&self) -> f64 {
        wilson_upper(self.accepted, self.samples, 1.645)
    }

    /// Whether the job would store too little: even the upper bound of the acceptance is below
    /// `min_acceptance` (16 samples: 12 accepted or fewer), or the accepted samples reach less
    /// than `min_achieved` of their targets on average.
    pub fn is_doomed(&self, settings: &PreflightSettings) -> bool {
        self.acceptance_upper_bound() < settings.min_acceptance
            || self.achieved_over_target.is_some_and(|r| r < settings.min_achieved)
    }

    /// The refusal message, when the job is doomed (`is_doomed`).
    pub fn refusal(&self, settings: &PreflightSettings) -> Option<String> {
        self.is_doomed(settings).then(|| {
            let what = if self.acceptance_upper_bound() < settings.min_acceptance {
                format!(
                    "the job would store {:.0} % of its samples (at most {:.0} % at 95 % confidence; at least {:.0} % needed)",
                    self.acceptance * 100.0,
                    self.acceptance_upper_bound() * 100.0,
                    settings.min_acceptance * 100.0
                )
            } else {
                format!(
                    "the accepted samples reach {:.0} % of their target displacement on average (at least {:.0} % needed)",
                    self.achieved_over_target.unwrap_or(0.0) * 100.0,
                    settings.min_achieved * 100.0
                )
            };
            format!("{}; {what}. Likely cause: {} (--force runs it anyway)", self.summary(), self.cause.as_deref().unwrap_or("unknown"))
        })
    }
}

/// Upper end of the Wilson score interval for `k` successes in `n` trials at normal quantile
/// `z` (1 for no trial).
pub fn wilson_upper(k: usize, n: usize, z: f64) -> f64 {
    if n == 0 {
        return 1.0;
    }
    let (n, p) = (n as f64, k as f64 / n as f64);
    let z2 = z * z;
    let centre = p + z2 / (2.0 * n);
    let margin = z * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt();
    ((centre + margin) / (1.0 + z2 / n)).min(1.0)
}
