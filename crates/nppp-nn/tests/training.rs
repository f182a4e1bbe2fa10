//! Training on synthetic data: it learns, it is reproducible, it resumes,
//! and it stops cleanly on a non-finite loss.

mod common;

use std::fs;
use std::path::{Path, PathBuf};

use nppp_nn::synthetic::SyntheticObject;
use nppp_nn::train::files;
use nppp_nn::{
    BackendKind, DatasetInfo, TrainError, TrainOptions, TrainingData, synthetic_header,
    train_with_data,
};

fn tmp(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("nppp-nn-{name}"));
    let _ = fs::remove_dir_all(&d);
    d
}

fn mirror_data(n: usize, k: usize) -> (DatasetInfo, TrainingData) {
    let rays = SyntheticObject::Mirror { radius: 0.6 }.rays(n, k, 11);
    (
        synthetic_header("mirror", k),
        TrainingData::build(rays, k, 10).unwrap(),
    )
}

/// A small, fast configuration on NdArray.
fn opts(out: &Path) -> TrainOptions {
    common::small_opts(out)
}

fn log_rows(dir: &Path) -> Vec<Vec<String>> {
    fs::read_to_string(dir.join(files::LOG))
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(String::from).collect())
        .collect()
}

#[test]
fn tiny_run_learns_and_is_deterministic() {
    let (info, data) = mirror_data(1500, 8);
    let dir = tmp("learns");
    let mut o = opts(&dir);
    o.batch = Some(64);
    o.epochs = Some(12);
    let rep = train_with_data(&o, info.clone(), data.clone()).unwrap();
    assert_eq!(rep.steps, 300);
    let rows = log_rows(&dir);
    assert_eq!(rows.len(), 12);
    // Column 5: Chamfer averaged over the epoch. The mirror ball's exits are
    // a deterministic function of the ray, so it can fall towards zero: in
    // 300 steps it falls about 8x (18.4 -> 2.1 when this test was written).
    let first: f64 = rows[0][5].parse().unwrap();
    let last: f64 = rows[11][5].parse().unwrap();
    assert!(last < first / 5.0, "chamfer {first} -> {last}");
    let m = rep.metrics.unwrap();
    assert!(m.mask_accuracy > 0.85, "{m:?}");

    // Same seed, same data: the same log, bit for bit (CPU backend).
    let dir2 = tmp("learns2");
    train_with_data(&o.clone().with_out(&dir2), info, data).unwrap();
    let strip = |rows: Vec<Vec<String>>| -> Vec<Vec<String>> {
        // elapsed_s and seconds_per_step are wall-clock: drop them.
        rows.into_iter()
            .map(|r| {
                r.into_iter()
                    .enumerate()
                    .filter(|(i, _)| *i != 2 && *i != 18)
                    .map(|x| x.1)
                    .collect()
            })
            .collect()
    };
    assert_eq!(strip(log_rows(&dir)), strip(log_rows(&dir2)));
}

/// Every weight of a model directory's checkpoint, in a fixed order.
fn weights(dir: &Path) -> Vec<u32> {
    let m = nppp_nn::load_model_dir(dir, &BackendKind::Ndarray.device().unwrap())
        .unwrap()
        .model;
    [&m.encoder, &m.decoder, &m.mask]
        .iter()
        .flat_map(|n| n.to_mlp().unwrap().layers)
        .flat_map(|l| l.weight.into_iter().chain(l.bias))
        .map(f32::to_bits)
        .collect()
}

trait Tap {
    fn tap_epochs(self, e: usize) -> Self;
    fn with_out(self, dir: &Path) -> Self;
}
impl Tap for TrainOptions {
    fn tap_epochs(mut self, e: usize) -> Self {
        self.epochs = Some(e);
        self
    }
    fn with_out(mut self, dir: &Path) -> Self {
        self.out = dir.to_path_buf();
        self
    }
}

#[test]
fn resume_continues_from_the_saved_step() {
    let (info, data) = mirror_data(600, 8);
    // Uninterrupted: 3 epochs.
    let a = tmp("resume-a");
    train_with_data(&opts(&a).tap_epochs(3), info.clone(), data.clone()).unwrap();
    // Interrupted after 1 epoch, then resumed to 3.
    let b = tmp("resume-b");
    let mut o1 = opts(&b).tap_epochs(3);
    o1.stop_after = Some(25);
    let r1 = train_with_data(&o1, info.clone(), data.clone()).unwrap();
    assert_eq!(r1.steps, 25);
    // A second fresh run into the same directory is refused.
    let err = train_with_data(&opts(&b).tap_epochs(1), info.clone(), data.clone()).unwrap_err();
    assert!(err.to_string().contains("--resume"), "{err}");
    // Unless asked to start afresh.
    let mut ow = opts(&tmp("overwrite")).tap_epochs(1);
    train_with_data(&ow, info.clone(), data.clone()).unwrap();
    ow.overwrite = true;
    assert_eq!(
        train_with_data(&ow, info.clone(), data.clone())
            .unwrap()
            .steps_this_run,
        25
    );
    let mut o = opts(&b).tap_epochs(3);
    o.resume = true;
    let r2 = train_with_data(&o, info.clone(), data.clone()).unwrap();
    assert_eq!(r2.steps, 75);
    assert_eq!(r2.steps_this_run, 50);
    // Changing a hyperparameter on resume is refused with a clear message.
    let mut o2 = o.clone();
    o2.batch = Some(17);
    let err = train_with_data(&o2, info.clone(), data.clone()).unwrap_err();
    assert!(
        err.to_string()
            .contains("--batch 17 differs from the checkpoint's"),
        "{err}"
    );
    // A model hyperparameter likewise.
    let mut o3 = o.clone();
    o3.decoder_width = Some(24);
    let err = train_with_data(&o3, info, data).unwrap_err();
    assert!(
        err.to_string().contains("--decoder-width 24 differs"),
        "{err}"
    );
    // Same weights as the uninterrupted run, bit for bit (the files
    // themselves differ: they carry random parameter ids).
    assert_eq!(
        weights(&a),
        weights(&b),
        "resumed weights differ from the uninterrupted run's"
    );
    assert_eq!(log_rows(&b).len(), 3);
}

#[test]
fn non_finite_loss_stops_and_keeps_the_last_good_checkpoint() {
    let (info, data) = mirror_data(600, 8);
    let dir = tmp("nan");
    train_with_data(&opts(&dir).tap_epochs(1), info.clone(), data.clone()).unwrap();
    let good = weights(&dir);
    // An absurd learning rate blows the weights up within a few steps.
    let mut o = opts(&dir).tap_epochs(4);
    o.resume = true;
    o.lr = Some(1e30);
    let err = train_with_data(&o, info.clone(), data.clone()).unwrap_err();
    let msg = err.to_string();
    let Some(TrainError::NonFinite {
        step, last_good, ..
    }) = err.downcast_ref::<TrainError>()
    else {
        panic!("expected a non-finite error, got {msg}");
    };
    assert!(*step > 25 && *step <= 100, "{msg}");
    assert_eq!(*last_good, Some(25));
    assert!(msg.contains(&format!("step {step}")), "{msg}");
    assert!(
        weights(&dir) == good,
        "the last good checkpoint was overwritten"
    );
    // And it still resumes normally.
    let mut o = opts(&dir).tap_epochs(2);
    o.resume = true;
    assert_eq!(train_with_data(&o, info, data).unwrap().steps, 50);
}

/// A fresh run that diverges before its first checkpoint has nothing to
/// resume: the message says so, and an older model in the folder
/// (`--overwrite`) is untouched.
#[test]
fn divergence_before_the_first_checkpoint_says_there_is_none() {
    let (info, data) = mirror_data(600, 8);
    let fresh = tmp("nan-fresh");
    let mut o = opts(&fresh).tap_epochs(4);
    o.steps_per_epoch = Some(400);
    o.lr = Some(1e30);
    let err = train_with_data(&o, info.clone(), data.clone()).unwrap_err();
    let msg = err.to_string();
    let Some(TrainError::NonFinite { last_good, .. }) = err.downcast_ref::<TrainError>() else {
        panic!("expected a non-finite error, got {msg}");
    };
    assert_eq!(*last_good, None, "{msg}");
    assert!(
        msg.contains("before this run saved any checkpoint"),
        "{msg}"
    );
    assert!(!msg.contains("--resume"), "{msg}");
    // A fresh run without a checkpoint leaves no folder (its copies and
    // lock files made it look like a model to the next `train`).
    assert!(!fresh.exists(), "{} is left behind", fresh.display());

    let dir = tmp("nan-overwrite");
    train_with_data(&opts(&dir).tap_epochs(1), info.clone(), data.clone()).unwrap();
    let good = weights(&dir);
    let mut o = o.with_out(&dir);
    o.overwrite = true;
    let msg = train_with_data(&o, info, data).unwrap_err().to_string();
    assert!(msg.contains("before --overwrite is untouched"), "{msg}");
    assert!(weights(&dir) == good, "the old model changed");
}

#[test]
fn loading_a_model_waits_for_a_checkpoint_being_swapped_in() {
    // `bake` during training: train holds the checkpoint lock exclusively
    // while it swaps a checkpoint in; a load waits for it instead of reading
    // a half-moved directory (a healthy model was called corrupt).
    let (info, data) = mirror_data(300, 4);
    let dir = tmp("checkpoint-lock");
    train_with_data(&opts(&dir).tap_epochs(1), info, data).unwrap();
    let lock = fs::OpenOptions::new()
        .write(true)
        .open(dir.join(files::CHECKPOINT_LOCK))
        .unwrap();
    lock.lock().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let d = dir.clone();
    let loader = std::thread::spawn(move || {
        let device = BackendKind::Ndarray.device().unwrap();
        let loaded = nppp_nn::load_model_dir(&d, &device).map(|_| ());
        tx.send(()).unwrap();
        loaded
    });
    assert!(
        rx.recv_timeout(std::time::Duration::from_millis(300))
            .is_err(),
        "the model loaded while its checkpoint was locked"
    );
    lock.unlock().unwrap();
    rx.recv_timeout(std::time::Duration::from_secs(60))
        .expect("the load never finished");
    loader.join().unwrap().unwrap();
}

#[test]
fn corrupt_checkpoint_is_an_error_not_a_panic() {
    let (info, data) = mirror_data(300, 4);
    let dir = tmp("corrupt");
    train_with_data(&opts(&dir).tap_epochs(1), info.clone(), data.clone()).unwrap();
    fs::write(
        dir.join(files::CHECKPOINT).join(files::WEIGHTS),
        b"not a burnpack file",
    )
    .unwrap();
    let mut o = opts(&dir).tap_epochs(2);
    o.resume = true;
    let err = train_with_data(&o, info.clone(), data.clone()).unwrap_err();
    assert!(format!("{err:#}").contains("model.bpk"), "{err:#}");
    fs::write(dir.join(files::CHECKPOINT).join(files::STATE), b"{").unwrap();
    let err = train_with_data(&o, info.clone(), data.clone()).unwrap_err();
    assert!(format!("{err:#}").contains("state.json"), "{err:#}");
    // Without its state.json the folder is no checkpoint a run can read,
    // but its weights are still someone's: a fresh run without --overwrite
    // leaves them, and every reader names what is missing.
    fs::remove_file(dir.join(files::CHECKPOINT).join(files::STATE)).unwrap();
    let weights = fs::read(dir.join(files::CHECKPOINT).join(files::WEIGHTS)).unwrap();
    let err = train_with_data(&opts(&dir).tap_epochs(1), info.clone(), data.clone()).unwrap_err();
    assert!(format!("{err:#}").contains("--overwrite"), "{err:#}");
    assert_eq!(
        fs::read(dir.join(files::CHECKPOINT).join(files::WEIGHTS)).unwrap(),
        weights,
        "a fresh run replaced the weights"
    );
    let err = train_with_data(&o, info, data).unwrap_err();
    assert!(
        format!("{err:#}").contains("incomplete or damaged"),
        "{err:#}"
    );
    let err = nppp_nn::load_model_dir(&dir, &BackendKind::Ndarray.device().unwrap())
        .err()
        .unwrap();
    assert!(
        format!("{err:#}").contains("incomplete or damaged"),
        "{err:#}"
    );
    let err = nppp_nn::load_model_dir(&dir.join("nope"), &BackendKind::Ndarray.device().unwrap())
        .err()
        .unwrap();
    assert!(err.to_string().contains("does not exist"), "{err}");
    // A folder that is not a model gets no lock file from being read.
    let plain = tmp("not-a-model");
    fs::create_dir_all(&plain).unwrap();
    let err = nppp_nn::load_model_dir(&plain, &BackendKind::Ndarray.device().unwrap())
        .err()
        .unwrap();
    assert!(
        format!("{err:#}").contains("holds no checkpoint"),
        "{err:#}"
    );
    assert_eq!(
        fs::read_dir(&plain).unwrap().count(),
        0,
        "reading it wrote into it"
    );
}

/// The saved configuration says what ran: a file with fewer exits per ray
/// than the default (or the asked-for) k trains with the file's k and
/// records it.
#[test]
fn k_follows_the_data_file() {
    let (info, data) = mirror_data(300, 4);
    let dir = tmp("k-file");
    let mut o = opts(&dir).tap_epochs(1);
    o.k = None;
    train_with_data(&o, info.clone(), data.clone()).unwrap();
    let saved = fs::read_to_string(dir.join(files::CHECKPOINT).join(files::TRAIN_CONFIG)).unwrap();
    let v: serde_json::Value = serde_json::from_str(&saved).unwrap();
    assert_eq!(v["k"], 4, "{saved}");
    assert_eq!(
        nppp_nn::TrainConfig::new(nppp_nn::ModelConfig::new()).k,
        nppp_estimator::recipe::DEFAULT_K as usize,
        "TrainConfig's default k is the recipe's"
    );
    let big = tmp("k-too-big");
    let mut o = opts(&big).tap_epochs(1);
    o.k = Some(16);
    train_with_data(&o, info, data).unwrap();
    let saved = fs::read_to_string(big.join(files::CHECKPOINT).join(files::TRAIN_CONFIG)).unwrap();
    let v: serde_json::Value = serde_json::from_str(&saved).unwrap();
    assert_eq!(v["k"], 4, "{saved}");
}

/// Rows every `log_every` steps with the training losses; held-out columns
/// filled at evaluations (`eval_every`, epoch ends and the last step).
#[test]
fn the_log_has_rows_every_n_steps_and_evaluations_at_intervals() {
    let (info, data) = mirror_data(600, 8);
    let dir = tmp("log-every");
    let mut o = opts(&dir);
    o.steps_per_epoch = Some(1000);
    o.steps = Some(300);
    o.log_every = 50;
    o.eval_every = 150;
    train_with_data(&o, info, data).unwrap();
    let rows = log_rows(&dir);
    let steps: Vec<&str> = rows.iter().map(|r| r[1].as_str()).collect();
    assert_eq!(steps, ["50", "100", "150", "200", "250", "300"]);
    let evaluated: Vec<bool> = rows.iter().map(|r| !r[8].is_empty()).collect();
    assert_eq!(evaluated, [false, false, true, false, false, true]);
    for r in &rows {
        assert_eq!(r.len(), 19, "{r:?}");
        let loss: f64 = r[4].parse().unwrap();
        assert!(loss.is_finite() && loss > 0.0, "{r:?}");
    }
}

/// An object that returns no light (an emitter's data: every exit's
/// throughput 0) scores its throughput errors against a throughput of 1,
/// not against its ~0 mean (they read billions of percent).
#[test]
fn an_object_that_returns_no_light_scores_finite_errors() {
    let mut rays = SyntheticObject::Mirror { radius: 0.6 }.rays(300, 4, 11);
    for r in &mut rays {
        for e in &mut r.exits {
            e.throughput = glam::Vec3::ZERO;
        }
    }
    let data = TrainingData::build(rays, 4, 10).unwrap();
    let dir = tmp("no-light");
    let rep = train_with_data(
        &opts(&dir).tap_epochs(1),
        synthetic_header("mirror", 4),
        data,
    )
    .unwrap();
    let m = rep.metrics.unwrap();
    assert!(m.mean_throughput < 1e-6, "{m:?}");
    for v in [
        m.throughput_error,
        m.throughput_rms_error,
        m.throughput_bias.abs(),
    ] {
        assert!(v.is_finite() && v < 10.0, "{m:?}");
    }
}
