//! Stopping a run from outside: the flag the CLI's Ctrl-C / SIGTERM
//! handler raises through [`request_stop`] and the training loop checks,
//! and the guard that marks the loop as running.

use std::sync::atomic::{AtomicBool, Ordering};

/// Set by [`request_stop`] (the CLI's Ctrl-C / SIGTERM handler): the
/// training loop saves a checkpoint after the current step and returns
/// [`TrainError::Interrupted`](super::TrainError::Interrupted).
static STOP_REQUESTED: AtomicBool = AtomicBool::new(false);
/// Whether a training loop is running (and so will act on a stop request);
/// outside it, an interrupt may end the process at once.
static IN_TRAINING_LOOP: AtomicBool = AtomicBool::new(false);

/// Asks the running training loop to checkpoint and stop.
pub fn request_stop() {
    STOP_REQUESTED.store(true, Ordering::SeqCst);
}

/// Whether a stop was requested.
pub fn stop_requested() -> bool {
    STOP_REQUESTED.load(Ordering::SeqCst)
}

/// Whether a training loop is running (it acts on [`request_stop`]).
pub fn in_training_loop() -> bool {
    IN_TRAINING_LOOP.load(Ordering::SeqCst)
}

/// Marks the training loop as running while alive.
pub(super) struct LoopGuard;

impl LoopGuard {
    pub(super) fn enter() -> Self {
        IN_TRAINING_LOOP.store(true, Ordering::SeqCst);
        Self
    }
}

impl Drop for LoopGuard {
    fn drop(&mut self) {
        IN_TRAINING_LOOP.store(false, Ordering::SeqCst);
    }
}
