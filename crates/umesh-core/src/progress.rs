//! Progress reporting and cooperative cancellation shared by the CLI and the GUI.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// A cancellation flag; clones share it. Long computations poll it and stop with a
/// `Cancelled` error.
#[derive(Clone, Debug, Default)]
pub struct Cancel(Arc<AtomicBool>);

impl Cancel {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn cancel(&self) {
        self.0.store(true, Ordering::Relaxed);
    }
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
    /// `Err(Cancelled)` once the flag is set: `cancel.check()?` in a long loop.
    pub fn check(&self) -> Result<(), crate::Cancelled> {
        if self.is_cancelled() { Err(crate::Cancelled) } else { Ok(()) }
    }
}

/// Progress callback: `(done, total, message)`. Called from worker threads.
#[derive(Clone, Default)]
pub struct Progress(Option<Arc<dyn Fn(u64, u64, &str) + Send + Sync>>);

impl std::fmt::Debug for Progress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Progress")
    }
}

impl Progress {
    /// Reports nothing.
    pub fn none() -> Self {
        Self(None)
    }
    pub fn new(f: impl Fn(u64, u64, &str) + Send + Sync + 'static) -> Self {
        Self(Some(Arc::new(f)))
    }
    pub fn report(&self, done: u64, total: u64, message: &str) {
        if let Some(f) = &self.0 {
            f(done, total, message);
        }
    }
}

/// A job's rate and time left, counted from its first report: a resumed job starts with
/// work done by an earlier run, which this run's clock did not see (counting it made a
/// resumed training say "about 27 s left" with half an hour to go).
#[derive(Clone, Copy, Debug, Default)]
pub struct Eta {
    first: Option<(u64, Instant)>,
}

impl Eta {
    pub fn new() -> Self {
        Self::default()
    }

    /// Record a report; the first one is the baseline.
    pub fn observe(&mut self, done: u64, now: Instant) {
        if self.first.is_none() {
            self.first = Some((done, now));
        }
    }

    /// Units a second since the first report; `None` before any unit is done in this run.
    pub fn rate_per_s(&self, done: u64, now: Instant) -> Option<f64> {
        let (done0, t0) = self.first?;
        let secs = now.saturating_duration_since(t0).as_secs_f64();
        (done > done0 && secs > 0.0).then(|| (done - done0) as f64 / secs)
    }

    /// Seconds left at this run's rate; `None` while the rate is unknown or the job is done.
    pub fn seconds_left(&self, done: u64, total: u64, now: Instant) -> Option<f64> {
        let rate = self.rate_per_s(done, now)?;
        (total > done).then(|| (total - done) as f64 / rate)
    }
}
