//! The training loop: Chamfer (+ optional energy distance) on the exits of
//! hit rays, BCE on the mask of all rays, Adam, per-epoch held-out
//! evaluation, CSV log, checkpoints and resume.
//!
//! Everything random (batches, the k-subsets of exits, the decoder's r, the
//! initial weights) comes from `SampleRng` streams keyed by (seed, step), not
//! from Burn's generator: a run is then reproducible on CPU backends, and a
//! resumed run draws exactly what the uninterrupted run would have drawn.
//!
//! This module holds the loop itself ([`train`], [`train_with_data`]); the
//! configuration, the step, the log, the report and the stop flag live in
//! the submodules.

mod config;
mod logging;
mod report;
mod step;
mod stop;

use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::optim::ModuleOptimizer;
use indicatif::{ProgressBar, ProgressDrawTarget};

use crate::data::TrainingData;
use crate::eval::{BurnEstimator, EvalOptions, HeldoutMetrics, evaluate};
use crate::io::{DatasetInfo, ModelMeta, load_dataset};
use crate::model::NpppModel;
use crate::model_dir::{
    Checkpoint, CheckpointContent, STATE_VERSION, TrainState, checkpoint_dir, load_optimizer,
    load_weights, lock_model_dir, open_checkpoint, refresh_copies, save_checkpoint,
};
use config::{fingerprint, resolve_config};
use logging::{LOG_HEADER, append_live_row, log_row};
use step::{epoch_permutation, make_batch, make_optimizer, train_step};
use stop::LoopGuard;

pub use crate::model_dir::files;
pub use config::{TrainConfig, TrainOptions};
pub use report::{TrainError, TrainReport};
pub use stop::{in_training_loop, request_stop, stop_requested};

/// Steps timed before a `--minutes` budget shortens the schedule.
const CALIBRATION_STEPS: u64 = 300;
/// Share of the measured pace the budget plans for: evaluations,
/// checkpoints and a busy machine take the rest.
const TIME_SAFETY: f64 = 0.85;

/// A checkpoint is also written this often (seconds) within long epochs, so
/// an interrupted run loses little.
const CHECKPOINT_EVERY_S: f64 = 300.0;

/// What identifies a checkpoint's contents: its step and its files' sizes
/// and checksums.
fn state_key(s: &TrainState) -> String {
    serde_json::to_string(&(s.step, &s.files)).unwrap_or_default()
}

/// Trains on the data file named in `opts` (see [`TrainOptions`]).
pub fn train(opts: &TrainOptions) -> Result<TrainReport> {
    let (cfg, ckpt) = resolve_config(opts)?;
    let (info, rays) = load_dataset(&opts.data, opts.quiet)?;
    let data = TrainingData::build(rays, info.k as usize, cfg.holdout_every)
        .with_context(|| format!("preparing {}", opts.data.display()))?;
    train_on(opts, cfg, ckpt, info, data)
}

/// Trains on data already in memory (the tests and tools use this with
/// synthetic rays; `info` names the object as a data file header would).
pub fn train_with_data(
    opts: &TrainOptions,
    info: DatasetInfo,
    data: TrainingData,
) -> Result<TrainReport> {
    let (cfg, ckpt) = resolve_config(opts)?;
    train_on(opts, cfg, ckpt, info, data)
}

fn train_on(
    opts: &TrainOptions,
    cfg: TrainConfig,
    ckpt: Option<Checkpoint>,
    info: DatasetInfo,
    data: TrainingData,
) -> Result<TrainReport> {
    let out = &opts.out;
    let mut cfg = cfg;
    // The vertex head trains exactly when the data has picked vertices.
    let has_vertices = data.vertex_transform.is_some();
    if ckpt.is_none() {
        cfg.model.vertex_head = has_vertices;
    } else if cfg.model.vertex_head != has_vertices {
        bail!(
            "--resume: the checkpoint was trained {} a vertex head, and {} {} picked vertices",
            if cfg.model.vertex_head {
                "with"
            } else {
                "without"
            },
            opts.data.display(),
            if has_vertices { "has" } else { "has no" }
        );
    }
    // The exits per ray a step uses can only be as many as the file holds;
    // the saved config says what actually runs.
    if cfg.k > data.k {
        // Said even with --quiet when the user asked for that k.
        if !opts.quiet || opts.k.is_some() {
            nppp_files::note!(
                "note: {} holds {} exits per ray, so each step uses k = {} (not {}); \
                 train_config.json records {}",
                opts.data.display(),
                data.k,
                data.k,
                cfg.k,
                data.k
            );
        }
        cfg.k = data.k;
    }
    if data.heldout.is_empty() {
        bail!(
            "{}: no held-out rays: the data has {} rays and every {}th is held out (fewer \
             than that many rays, or --holdout-every too large)",
            opts.data.display(),
            data.train.len(),
            cfg.holdout_every
        );
    }
    let device = opts.backend.device()?;
    let ad = device.clone().autodiff();
    let n_hit = data.train.hits();
    let spe = if cfg.steps_per_epoch > 0 {
        cfg.steps_per_epoch
    } else {
        n_hit.div_ceil(cfg.batch)
    };
    // The schedule's length, and where this invocation stops.
    let total_steps = if cfg.epochs > 0 {
        (cfg.epochs as u64)
            .checked_mul(spe as u64)
            .with_context(|| {
                format!(
                    "--epochs {} of {spe} steps each is more steps than can be counted; give \
                     fewer epochs or --steps",
                    cfg.epochs
                )
            })?
    } else {
        cfg.steps
    };
    let mut total_steps = total_steps;
    let mut stop_at = opts.stop_after.map_or(total_steps, |s| s.min(total_steps));
    let fp = fingerprint(&info, &data);
    let _lock = lock_model_dir(out)?;
    // Looked at again now that the folder is this run's: another run may
    // have finished in it while this one loaded its data. A fresh run then
    // replaced the model it saved without --overwrite; a resumed one
    // trained on from its newer weights, counting from the older step.
    match &ckpt {
        None => config::check_fresh_target(opts).map_err(|e| {
            e.context(format!(
                "another `nppp train` saved into {} after this run started",
                out.display()
            ))
        })?,
        Some(c) => {
            let now = open_checkpoint(out)?.map(|n| n.state);
            if now.as_ref().map(state_key) != Some(state_key(&c.state)) {
                bail!(
                    "--resume: another `nppp train` saved a checkpoint into {} (now at step \
                     {}) after this run read the one at step {}; run --resume again to go on \
                     from the newest",
                    out.display(),
                    now.map_or_else(|| "none".to_string(), |s| s.step.to_string()),
                    c.state.step
                );
            }
        }
    }

    // Start fresh or resume. A fresh run writes nothing into `out` until
    // its first checkpoint: a model already there (--overwrite) stays whole
    // until then, whatever happens to this run.
    let resumed_from = ckpt.as_ref().map(|c| c.state.step);
    let (mut model, mut optim, mut state, meta, mut log) = if let Some(ckpt) = ckpt {
        let state = ckpt.state.clone();
        if state.data != fp {
            bail!(
                "--resume: the checkpoint was trained on other data ({}) than {} ({})",
                state.data,
                opts.data.display(),
                fp
            );
        }
        if state.steps_per_epoch != spe {
            bail!(
                "--resume: steps per epoch changed ({} -> {spe})",
                state.steps_per_epoch
            );
        }
        if state.step > total_steps {
            bail!(
                "--resume: the checkpoint is at step {}, past the {total_steps} steps asked for \
                 (--steps or --epochs); ask for more steps to go on training",
                state.step
            );
        }
        let model = load_weights(&ckpt, &ad)?;
        let optim = load_optimizer(&ckpt, make_optimizer(&cfg), &model)?;
        (model, optim, state, ckpt.meta, ckpt.log)
    } else {
        let mut meta = ModelMeta::new(info.clone(), data.transform.clone(), opts.data.clone());
        meta.vertex_transform = data.vertex_transform.clone();
        let model = NpppModel::init(&cfg.model, cfg.seed, &ad)?;
        let state = TrainState {
            version: STATE_VERSION,
            step: 0,
            steps_per_epoch: spe,
            elapsed_s: 0.0,
            epoch_sums: [0.0; 4],
            epoch_count: 0,
            data: fp,
            last_metrics: None,
            schedule_steps: None,
            files: Vec::new(),
        };
        (
            model,
            make_optimizer(&cfg),
            state,
            meta,
            format!("{LOG_HEADER}\n"),
        )
    };
    // The step of the newest checkpoint of *this* run (resumed from, or
    // saved since): what a divergence message may point to.
    let mut last_saved = resumed_from;
    if resumed_from.is_some() {
        let content = CheckpointContent {
            train_config: &cfg,
            meta: &meta,
            model: &model,
            optim: &optim,
            log: &log,
        };
        refresh_copies(out, &content)?;
    }

    if let Some(s) = state.schedule_steps {
        if opts.steps.is_some() || opts.epochs.is_some() {
            // A length asked for again: the schedule follows it (a run
            // shortened by --minutes could never be lengthened).
            state.schedule_steps = None;
        } else {
            if s < state.step {
                bail!(
                    "--resume: {}'s state.json is at step {} past its own schedule of {s} \
                     steps: the checkpoint is damaged",
                    out.display(),
                    state.step
                );
            }
            total_steps = total_steps.min(s);
            stop_at = stop_at.min(total_steps);
        }
    }
    let start_step = state.step;
    let pb = if opts.quiet {
        ProgressBar::hidden()
    } else {
        let pb = ProgressBar::with_draw_target(Some(stop_at), ProgressDrawTarget::stderr());
        pb.set_style(nppp_files::progress_style(
            "train {bar:30} {pos}/{len} steps ({rate}, eta {eta}) {msg}",
            "steps",
        ));
        pb.set_position(start_step);
        pb
    };
    let t0 = Instant::now();
    let base_elapsed = state.elapsed_s;
    let mut last_ckpt = Instant::now();
    let mut perm_epoch = u64::MAX;
    let mut perm = Vec::new();
    let mut stopped_by_time = false;
    let mut step_time = 0.0f64;
    let eval_opts = EvalOptions {
        max_hit_rays: cfg.eval_rays,
        ..EvalOptions::default()
    };
    let save = |model: &NpppModel, optim: &ModuleOptimizer, state: &TrainState, log: &str| {
        let content = CheckpointContent {
            train_config: &cfg,
            meta: &meta,
            model,
            optim,
            log,
        };
        save_checkpoint(out, &content, state)
    };

    let evaluate_model = |model: &NpppModel| -> Result<HeldoutMetrics> {
        let mut est =
            BurnEstimator::new(model, data.transform.clone(), &info, cfg.model.noise_dim)?;
        est.vertex_transform = data.vertex_transform.clone();
        evaluate(
            &mut est,
            &data.heldout,
            data.k,
            &data.transform,
            data.vertex_transform.as_ref(),
            &eval_opts,
        )
    };

    let mut last_row_at = Instant::now();
    let mut last_row_step = start_step;
    let _in_loop = LoopGuard::enter();
    while state.step < stop_at {
        if stop_requested() {
            pb.abandon();
            if state.step > start_step {
                state.elapsed_s = base_elapsed + t0.elapsed().as_secs_f64();
                save(&model, &optim, &state, &log)?;
            }
            return Err(TrainError::Interrupted {
                step: state.step,
                dir: out.clone(),
                data: opts.data.clone(),
                saved: last_saved.is_some() || state.step > start_step,
            }
            .into());
        }
        let epoch = state.step / spe as u64;
        if epoch != perm_epoch {
            perm = epoch_permutation(cfg.seed, epoch, n_hit);
            perm_epoch = epoch;
        }
        let ts = Instant::now();
        let batch = make_batch(&cfg, &data, &perm, state.step, spe);
        // Fit the schedule into the time budget once the pace is known, and
        // again after each evaluation (which the first estimate misses).
        let timed = state.step - start_step;
        if opts.minutes > 0.0
            && timed > 0
            && (timed == CALIBRATION_STEPS || state.step.is_multiple_of(spe as u64))
        {
            let per_step = t0.elapsed().as_secs_f64() / timed as f64;
            let left = opts.minutes * 60.0 - t0.elapsed().as_secs_f64();
            let fits = state.step + (TIME_SAFETY * left / per_step).max(0.0) as u64;
            if fits < total_steps {
                let line = format!(
                    "--minutes {}: {total_steps} steps do not fit at {:.1} ms/step; the run \
                     is shortened to {fits} steps (its learning-rate decay included)",
                    opts.minutes,
                    per_step * 1e3
                );
                if pb.is_hidden() {
                    if !opts.quiet {
                        nppp_files::note!("{line}");
                    }
                } else {
                    pb.println(line);
                }
                total_steps = fits;
                stop_at = stop_at.min(fits);
                state.schedule_steps = Some(fits);
                pb.set_length(stop_at);
            }
        }
        let lr = cfg.lr_at(state.step, total_steps);
        let stepped = train_step(model, &mut optim, &cfg, lr, batch, &ad);
        step_time += ts.elapsed().as_secs_f64();
        let (m, v) = match stepped {
            Ok(x) => x,
            Err((_, value)) => {
                pb.abandon();
                return Err(TrainError::NonFinite {
                    step: state.step + 1,
                    value,
                    last_good: last_saved,
                    dir: out.clone(),
                    kept_previous: last_saved.is_none() && checkpoint_dir(out).is_some(),
                }
                .into());
            }
        };
        model = m;
        state.step += 1;
        for (s, x) in state.epoch_sums.iter_mut().zip(v) {
            *s += x as f64;
        }
        state.epoch_count += 1;
        pb.set_position(state.step);
        if state.step % 10 == 0 {
            pb.set_message(format!("loss {:.4}", v[0]));
        }
        let epoch_end = state.step % spe as u64 == 0;
        let last = state.step >= stop_at;
        let over_time = opts.minutes > 0.0 && t0.elapsed().as_secs_f64() > opts.minutes * 60.0;
        let evaluate_now = epoch_end
            || last
            || over_time
            || (opts.eval_every > 0 && state.step.is_multiple_of(opts.eval_every));
        let log_now = opts.log_every > 0 && state.step.is_multiple_of(opts.log_every);
        if evaluate_now || log_now {
            state.elapsed_s = base_elapsed + t0.elapsed().as_secs_f64();
            let metrics = if evaluate_now {
                let m = evaluate_model(&model)?;
                if !(m.chamfer.is_finite() && m.mask_bce.is_finite()) {
                    pb.abandon();
                    return Err(TrainError::NonFinite {
                        step: state.step,
                        value: m.chamfer as f32,
                        last_good: last_saved,
                        dir: out.clone(),
                        kept_previous: last_saved.is_none() && checkpoint_dir(out).is_some(),
                    }
                    .into());
                }
                Some(m)
            } else {
                None
            };
            let c = state.epoch_count.max(1) as f64;
            let avg: Vec<f64> = state.epoch_sums.iter().map(|s| s / c).collect();
            let window = (state.step - last_row_step).max(1) as f64;
            let sps = last_row_at.elapsed().as_secs_f64() / window;
            let row = log_row(
                state.step as f64 / spe as f64,
                state.step,
                state.elapsed_s,
                lr,
                &avg,
                metrics.as_ref(),
                sps,
            );
            state.epoch_sums = [0.0; 4];
            state.epoch_count = 0;
            last_row_at = Instant::now();
            last_row_step = state.step;
            log.push_str(&row);
            log.push('\n');
            if let Some(metrics) = metrics {
                state.last_metrics = Some(metrics);
                save(&model, &optim, &state, &log)?;
                last_saved = Some(state.step);
                last_ckpt = Instant::now();
                let line = format!(
                    "epoch {:.2}: train {:.4}  held-out chamfer {:.4}  mask acc {:.2}%  throughput err {:.2}% (rms {:.2}%, bias {:+.2}%, floor {:.2}%)",
                    state.step as f64 / spe as f64,
                    avg[0],
                    metrics.chamfer,
                    100.0 * metrics.mask_accuracy,
                    100.0 * metrics.throughput_error,
                    100.0 * metrics.throughput_rms_error,
                    100.0 * metrics.throughput_bias,
                    100.0 * metrics.throughput_noise_floor,
                );
                // A hidden bar (no terminal, or --quiet) prints nothing: then the
                // epoch lines go to stderr directly unless --quiet.
                if !pb.is_hidden() {
                    pb.println(line);
                } else if !opts.quiet {
                    nppp_files::note!("{line}");
                }
            } else if last_saved.is_some() {
                // The folder is this run's: show the row at once (the
                // checkpoint's own log gets it at the next checkpoint).
                append_live_row(&out.join(files::LOG), &row);
            }
            if over_time && !last {
                stopped_by_time = true;
                break;
            }
        } else if last_ckpt.elapsed().as_secs_f64() > CHECKPOINT_EVERY_S {
            state.elapsed_s = base_elapsed + t0.elapsed().as_secs_f64();
            save(&model, &optim, &state, &log)?;
            last_saved = Some(state.step);
            last_ckpt = Instant::now();
        }
    }
    pb.finish_and_clear();
    let run = state.step - start_step;
    Ok(TrainReport {
        model_dir: out.clone(),
        backend: opts.backend,
        steps: state.step,
        steps_this_run: run,
        epochs_completed: state.step as f64 / spe as f64,
        elapsed_s: state.elapsed_s,
        seconds_per_step: t0.elapsed().as_secs_f64() / run.max(1) as f64,
        step_seconds: step_time / run.max(1) as f64,
        stopped_by_time,
        schedule_steps: total_steps,
        metrics: state.last_metrics,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::SyntheticObject;

    /// 200 rays of a mirror ball, k = 4.
    fn mirror_data() -> (DatasetInfo, TrainingData) {
        let rays = SyntheticObject::Mirror { radius: 0.6 }.rays(200, 4, 3);
        let info = crate::io::synthetic_header("mirror", 4);
        (info, TrainingData::build(rays, 4, 10).unwrap())
    }

    fn small(out: &std::path::Path) -> TrainOptions {
        let mut o = TrainOptions::new("synthetic", out);
        o.backend = crate::backend::BackendKind::Ndarray;
        o.quiet = true;
        o.batch = Some(16);
        o.k = Some(4);
        o.mask_batch = Some(32);
        o.encoder_width = Some(32);
        o.decoder_width = Some(16);
        o.eval_rays = Some(16);
        o.steps_per_epoch = Some(5);
        o.steps = Some(5);
        o.minutes = 0.0;
        o
    }

    /// What this run checked before it loaded its data must still hold
    /// once it holds the folder: a run that finished in the folder in
    /// between is neither replaced by a fresh run (without --overwrite)
    /// nor mixed into a resumed one.
    #[test]
    fn a_run_that_finished_in_the_folder_meanwhile_is_kept() {
        let dir = std::env::temp_dir().join(format!("nppp-train-race-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let (info, data) = mirror_data();
        let o = small(&dir);

        // B looks at the empty folder, then A trains a whole model there.
        let (cfg, ckpt) = resolve_config(&o).unwrap();
        train_with_data(&o, info.clone(), data.clone()).unwrap();
        let saved = std::fs::read(dir.join("checkpoint").join(files::WEIGHTS)).unwrap();
        let e = train_on(&o, cfg, ckpt, info.clone(), data.clone()).unwrap_err();
        let text = format!("{e:#}");
        assert!(
            text.contains("after this run started") && text.contains("already holds a checkpoint"),
            "{text}"
        );
        assert_eq!(
            std::fs::read(dir.join("checkpoint").join(files::WEIGHTS)).unwrap(),
            saved
        );

        // B reads the checkpoint at step 5 to resume it; A resumes it to 10
        // first.
        let mut r = o.clone();
        r.resume = true;
        r.steps = Some(20);
        let (cfg, ckpt) = resolve_config(&r).unwrap();
        let mut a = r.clone();
        a.stop_after = Some(10);
        train_with_data(&a, info.clone(), data.clone()).unwrap();
        let e = train_on(&r, cfg, ckpt, info, data).unwrap_err();
        assert!(
            e.to_string()
                .contains("(now at step 10) after this run read the one at step 5"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A run shortened to fit --minutes records its schedule's length; a
    /// resume that asks for a length again gets it (it stayed at the
    /// shortened one, "152 of 152"), one that does not keeps the schedule,
    /// and a schedule shorter than the step reached is damage.
    #[test]
    fn a_schedule_shortened_by_minutes_can_be_lengthened() {
        let dir = std::env::temp_dir().join(format!("nppp-train-sched-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let (info, data) = mirror_data();
        let mut o = small(&dir);
        o.steps = Some(10);
        o.stop_after = Some(5);
        train_with_data(&o, info.clone(), data.clone()).unwrap();
        // As --minutes leaves it: the schedule cut to the steps done.
        let set_schedule = |n: u64| {
            let p = dir.join("checkpoint").join(files::STATE);
            let mut v: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
            v["schedule_steps"] = n.into();
            std::fs::write(&p, v.to_string()).unwrap();
        };
        set_schedule(5);
        let mut r = small(&dir);
        r.resume = true;
        r.steps = None;
        assert_eq!(
            train_with_data(&r, info.clone(), data.clone())
                .unwrap()
                .steps,
            5
        );
        set_schedule(3);
        let e = train_with_data(&r, info.clone(), data.clone()).unwrap_err();
        assert!(e.to_string().contains("past its own schedule of 3"), "{e}");
        r.steps = Some(12);
        let rep = train_with_data(&r, info, data).unwrap();
        assert_eq!((rep.steps, rep.steps_this_run), (12, 7));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
