//! `nppp bench`: time against error, for plain path tracing and for path
//! tracing with estimators, on the benchmark scenes.
//!
//! Per scene: a reference (plain path tracing at M, many samples, rendered
//! once and cached with its settings), then every configuration (PT at
//! M = 1..M, PT + NPPP at P = 0..3 with the full M, optionally PT + oracle)
//! at a ladder of sample counts and several seeds. Every figure in the
//! report is measured in the same run, on the same machine, against the same
//! reference; ratios are taken against PT at the full M.
//!
//! The files, one concern each:
//!
//! - `plan`: what is measured: the scene list, the spp and PT bounce
//!   ladders, the configurations (`Kind`, `Config`) and the fixed constants.
//! - `harness`: running it: the per-scene loop, warm-up, timing
//!   (`robust_seconds`) and attaching each configuration's estimators.
//! - `reference`: the cached high-spp reference per scene and the scene
//!   hash and path helpers it is keyed by.
//! - `analysis`: turning measurements into numbers: the mean over seeds per
//!   cell, FLIP, log-log interpolation and the speed-up at equal error.
//! - `machine`: what the report says about where it ran (CPU, commit, date,
//!   peak memory).
//! - `report`: results.md and results.csv.
//! - `plots`: the time-vs-error plots, from a run or from an earlier
//!   results.csv.

mod analysis;
mod harness;
mod machine;
mod plan;
mod plots;
mod reference;
mod report;

pub(crate) use harness::run;
