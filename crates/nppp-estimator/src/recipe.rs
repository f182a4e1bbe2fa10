//! The default recipe of an estimator, in one place: what `nppp gen` and
//! `nppp train` use when not told otherwise, and what the Makefile's
//! `make data train bake` (and so the committed `models/*.nppp`) ran.

/// Input rays of `nppp gen` (about a minute on 2 cores for the default
/// knot, 207 MiB at k = 64).
pub const DEFAULT_RAYS: u64 = 1_000_000;
/// Exits per hit ray in the data file, and exits per ray per training step
/// (`TrainConfig::k`, which can only be as large as the file's).
pub const DEFAULT_K: u32 = 64;
