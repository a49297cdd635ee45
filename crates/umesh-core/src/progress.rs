//! Progress reporting and cooperative cancellation shared by the CLI and the GUI.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

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
