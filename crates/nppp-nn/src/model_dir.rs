//! The model directory `nppp train` writes and `nppp bake` reads, and the
//! rules that keep it from ever being lost.
//!
//! ```text
//! out/
//!   checkpoint/            the model: complete or absent, never half-written
//!     model.bpk optim.bpk  weights and Adam state (Burn)
//!     train_config.json    TrainConfig (Burn Config), the model config inside
//!     model_config.json    ModelConfig (the same as train_config.json's "model")
//!     meta.json            ModelMeta: the object, the exit transform, the data path
//!     log.csv              the training log up to this checkpoint
//!     state.json           progress, and the size and CRC-32 of every file above
//!   train_config.json model_config.json meta.json log.csv
//!                          copies of the checkpoint's, for people and tools
//! ```
//!
//! A checkpoint is written whole into `checkpoint.tmp/`, `state.json` last,
//! and swapped in by two renames (`checkpoint` -> `checkpoint.old`,
//! `checkpoint.tmp` -> `checkpoint`); a kill at any instant leaves
//! `checkpoint/` or, between the renames, `checkpoint.old/` complete. The
//! copies beside it are replaced atomically after the swap; readers (resume,
//! bake) use only the checkpoint's own files and check every checksum, so a
//! stale or damaged copy, or a flipped byte in the weights, is never used.
//! A fresh run into a directory that holds a model (`--overwrite`) leaves the
//! old checkpoint, log and copies in place until it has saved its first
//! checkpoint.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::config::Config;
use burn::module::Module;
use burn::optim::ModuleOptimizer;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::eval::HeldoutMetrics;
use crate::features::INPUT_FEATURES;
use crate::io::ModelMeta;
use crate::model::{ModelConfig, NpppModel};
use crate::train::TrainConfig;

/// File names inside a model directory.
pub mod files {
    pub const MODEL_CONFIG: &str = "model_config.json";
    pub const TRAIN_CONFIG: &str = "train_config.json";
    pub const META: &str = "meta.json";
    pub const LOG: &str = "log.csv";
    /// The training curves `nppp train` draws from the log (`nppp plot-log`).
    pub const LOG_SVG: &str = "log.svg";
    pub const LOG_PNG: &str = "log.png";
    pub const CHECKPOINT: &str = "checkpoint";
    pub const CHECKPOINT_TMP: &str = "checkpoint.tmp";
    pub const CHECKPOINT_OLD: &str = "checkpoint.old";
    pub const WEIGHTS: &str = "model.bpk";
    pub const OPTIMIZER: &str = "optim.bpk";
    pub const STATE: &str = "state.json";
    /// Held (an OS file lock, released when the process ends, however it
    /// ends) by the one `nppp train` writing the directory.
    pub const LOCK: &str = ".nppp-train.lock";
    /// Held exclusively while `nppp train` swaps a checkpoint in and
    /// refreshes the copies beside it, and shared while a model is loaded
    /// from the directory (`bake`), so that a bake during training reads
    /// one whole checkpoint (it read a swapped-out file about once in 20
    /// tries and called a healthy model corrupt, or panicked).
    pub const CHECKPOINT_LOCK: &str = ".nppp-checkpoint.lock";
    /// Every name `nppp train` may create in a model directory: a fresh run
    /// refuses a non-empty `--out` holding anything else (a user's folder).
    pub const ALL: &[&str] = &[
        MODEL_CONFIG,
        TRAIN_CONFIG,
        META,
        LOG,
        LOG_SVG,
        LOG_PNG,
        CHECKPOINT,
        CHECKPOINT_TMP,
        CHECKPOINT_OLD,
        LOCK,
        CHECKPOINT_LOCK,
    ];
    /// The files a checkpoint holds besides `state.json`, which lists them.
    pub const IN_CHECKPOINT: &[&str] = &[WEIGHTS, OPTIMIZER, TRAIN_CONFIG, MODEL_CONFIG, META, LOG];
}

/// Version of `state.json`. 2: the checkpoint holds its own configs, meta
/// and log, and the size and CRC-32 of each file (version 1 had none).
pub const STATE_VERSION: u32 = 2;

/// What identifies the data a checkpoint was trained on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DataFingerprint {
    pub rays: usize,
    pub hits: usize,
    pub k: usize,
    pub mesh_hash: u64,
    pub material_hash: u64,
}

impl std::fmt::Display for DataFingerprint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} rays, {} hits, k = {}, mesh hash {:016x}, material hash {:016x}",
            self.rays, self.hits, self.k, self.mesh_hash, self.material_hash
        )
    }
}

/// The size and checksum of one file of a checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FileSum {
    pub name: String,
    pub bytes: u64,
    pub crc32: u32,
}

impl FileSum {
    fn of(dir: &Path, name: &str) -> Result<Self> {
        let p = dir.join(name);
        let data = fs::read(&p).with_context(|| format!("reading back {}", p.display()))?;
        Ok(Self {
            name: name.to_string(),
            bytes: data.len() as u64,
            crc32: crc32fast::hash(&data),
        })
    }
}

/// Progress saved with every checkpoint (`checkpoint/state.json`), written
/// last: it is the checkpoint's table of contents.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainState {
    pub version: u32,
    /// Optimizer steps done.
    pub step: u64,
    pub steps_per_epoch: usize,
    /// Training time over all invocations.
    pub elapsed_s: f64,
    /// Running sums of the training losses (total, chamfer, energy, bce)
    /// since the last log row, and their count, so a resumed run logs the
    /// same averages as an uninterrupted one.
    pub epoch_sums: [f64; 4],
    pub epoch_count: u64,
    pub data: DataFingerprint,
    pub last_metrics: Option<HeldoutMetrics>,
    /// The run's length after fitting it into a `--minutes` budget (None:
    /// the configured length): the learning-rate schedule follows it, so a
    /// time-limited run still ends with its decay phase.
    #[serde(default)]
    pub schedule_steps: Option<u64>,
    /// Size and CRC-32 of every other file of the checkpoint.
    #[serde(default)]
    pub files: Vec<FileSum>,
}

/// A checkpoint read back and checked: every file present, every checksum
/// right, the configs and meta parsed and valid for this build.
pub struct Checkpoint {
    pub dir: PathBuf,
    pub state: TrainState,
    pub train_config: TrainConfig,
    pub meta: ModelMeta,
    /// The training log up to this checkpoint (header first).
    pub log: String,
}

/// The checkpoint folder of a model directory: `checkpoint/`, or
/// `checkpoint.old/` when a kill fell between the two renames of a swap.
pub fn checkpoint_dir(out: &Path) -> Option<PathBuf> {
    [files::CHECKPOINT, files::CHECKPOINT_OLD]
        .iter()
        .map(|n| out.join(n))
        .find(|d| d.join(files::STATE).is_file())
}

/// A checkpoint folder of `out` that holds files but no `state.json`
/// (damaged, or cut short by hand): not a checkpoint a run can read, but
/// its weights may still be someone's, so a fresh run does not replace it
/// without `--overwrite`, and readers name it instead of saying there is no
/// checkpoint.
pub fn incomplete_checkpoint(out: &Path) -> Option<PathBuf> {
    [files::CHECKPOINT, files::CHECKPOINT_OLD]
        .iter()
        .map(|n| out.join(n))
        .find(|d| {
            !d.join(files::STATE).is_file()
                && fs::read_dir(d).is_ok_and(|mut entries| entries.next().is_some())
        })
}

/// What to say of a model directory without a readable checkpoint: that it
/// has none, or that its checkpoint folder lacks its state.
pub fn no_checkpoint_message(dir: &Path, none: &str) -> String {
    match incomplete_checkpoint(dir) {
        Some(d) => format!(
            "{} holds no {}: the checkpoint is incomplete or damaged; retrain with `nppp \
             train --data DATA.nppd --out {} --overwrite`",
            d.display(),
            files::STATE,
            dir.display()
        ),
        None => format!("{} {none}", dir.display()),
    }
}

/// Reads and checks the checkpoint of `model_dir`; `Ok(None)` when it has
/// none. `rebuild` is the command that makes the model again, named in
/// messages about files this build cannot use.
pub fn open_checkpoint(model_dir: &Path) -> Result<Option<Checkpoint>> {
    let Some(dir) = checkpoint_dir(model_dir) else {
        return Ok(None);
    };
    let rebuild = format!(
        "retrain it with `nppp train --data DATA.nppd --out {} --overwrite`",
        model_dir.display()
    );
    let sp = dir.join(files::STATE);
    let text = nppp_files::read_regular_to_string(&sp)
        .with_context(|| format!("reading {}", sp.display()))?;
    #[derive(Deserialize)]
    struct Version {
        version: u32,
    }
    let v: Version = serde_json::from_str(&text)
        .with_context(|| format!("{} is corrupt (not a checkpoint state)", sp.display()))?;
    if v.version > STATE_VERSION {
        bail!(
            "{}: checkpoint format version {}, newer than this build reads ({STATE_VERSION}): \
             it was written by a newer nppp; use that build (retraining with --overwrite would \
             replace it)",
            sp.display(),
            v.version
        );
    }
    if v.version != STATE_VERSION {
        bail!(
            "{}: checkpoint format version {} (this build reads version {STATE_VERSION}: \
             checkpoints now carry checksums and their own configs); {rebuild}",
            sp.display(),
            v.version
        );
    }
    let state: TrainState =
        serde_json::from_str(&text).with_context(|| format!("{} is corrupt", sp.display()))?;
    check_known_keys(&sp, &text, &state)?;
    // Not checksummed itself: values no run writes went into the log (a
    // 309-digit time, a negative one, a 300-digit loss).
    // (1e10 s is 317 years of training.)
    let bad = if !(0.0..=1e10).contains(&state.elapsed_s) {
        Some(format!("elapsed_s = {}", state.elapsed_s))
    } else {
        state
            .epoch_sums
            .iter()
            .position(|v| !v.is_finite() || v.abs() > 1e30)
            .map(|i| format!("epoch_sums[{i}] = {:e}", state.epoch_sums[i]))
    };
    if let Some(what) = bad {
        bail!(
            "{}: {what} is not a value a run writes: the file is damaged; {rebuild}",
            sp.display()
        );
    }
    for name in files::IN_CHECKPOINT {
        let Some(want) = state.files.iter().find(|f| f.name == *name) else {
            bail!(
                "{} does not list {name}: the checkpoint is incomplete; {rebuild}",
                sp.display()
            );
        };
        let p = dir.join(name);
        let data = nppp_files::read_regular(&p).with_context(|| {
            format!(
                "{} is missing or unreadable: the checkpoint is damaged",
                p.display()
            )
        })?;
        if data.len() as u64 != want.bytes || crc32fast::hash(&data) != want.crc32 {
            bail!(
                "{} is corrupt: {} bytes with CRC-32 {:08x}, the checkpoint recorded {} bytes with \
                 {:08x}. The file was damaged after it was written; restore it from a backup or {rebuild}",
                p.display(),
                data.len(),
                crc32fast::hash(&data),
                want.bytes,
                want.crc32
            );
        }
    }
    let tc = dir.join(files::TRAIN_CONFIG);
    let tc_text = nppp_files::read_regular_to_string(&tc)
        .with_context(|| format!("reading {}", tc.display()))?;
    let train_config = TrainConfig::load_binary(tc_text.as_bytes())
        .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", tc.display()))?;
    check_known_keys(&tc, &tc_text, &train_config)?;
    train_config
        .check_values()
        .with_context(|| format!("{}", tc.display()))?;
    let mp = dir.join(files::META);
    let meta_text = nppp_files::read_regular_to_string(&mp)
        .with_context(|| format!("reading {}", mp.display()))?;
    let meta: ModelMeta =
        serde_json::from_str(&meta_text).with_context(|| format!("{} is corrupt", mp.display()))?;
    if meta.format != ModelMeta::FORMAT {
        bail!(
            "{}: not an nppp model's meta.json (format {:?}, not {:?})",
            mp.display(),
            meta.format,
            ModelMeta::FORMAT
        );
    }
    if meta.version > ModelMeta::VERSION {
        bail!(
            "{}: model format version {}, newer than this build reads ({}): it was written by \
             a newer nppp; use that build (retraining with --overwrite would replace it)",
            mp.display(),
            meta.version,
            ModelMeta::VERSION
        );
    }
    if meta.version != ModelMeta::VERSION {
        bail!(
            "{}: model format version {} (this build reads version {}); {rebuild}",
            mp.display(),
            meta.version,
            ModelMeta::VERSION
        );
    }
    check_known_keys(&mp, &meta_text, &meta)?;
    if let Err(what) = meta.dataset.check() {
        bail!("{}: dataset: {what}; {rebuild}", mp.display());
    }
    // The two files must describe one model: a resume trained on without
    // the vertex head's transform, and only bake refused it later.
    if train_config.model.vertex_head != meta.vertex_transform.is_some() {
        bail!(
            "{}: {} a vertex_transform, and {} says the model {} a vertex head: the two \
             files are from different models; {rebuild}",
            mp.display(),
            if meta.vertex_transform.is_some() {
                "has"
            } else {
                "has no"
            },
            tc.display(),
            if train_config.model.vertex_head {
                "has"
            } else {
                "has no"
            }
        );
    }
    if meta.dataset.k != state.data.k as u32 {
        bail!(
            "{}: dataset.k = {}, and the checkpoint's state.json records data with k = {}: \
             the files are from different runs; {rebuild}",
            mp.display(),
            meta.dataset.k,
            state.data.k
        );
    }
    let transforms = [
        (
            "transform",
            Some((&meta.transform.mean[..], &meta.transform.std[..])),
        ),
        (
            "vertex_transform",
            meta.vertex_transform
                .as_ref()
                .map(|v| (&v.mean[..], &v.std[..])),
        ),
    ];
    for (key, t) in transforms {
        if let Some((mean, std)) = t
            && let Some(what) = nppp_estimator::exit::transform_problem(mean, std)
        {
            bail!("{}: {key}.{what}; {rebuild}", mp.display());
        }
    }
    if meta.input_features != INPUT_FEATURES {
        bail!(
            "{}: the model was trained on {} input features, this build computes {}; {rebuild}",
            mp.display(),
            meta.input_features,
            INPUT_FEATURES
        );
    }
    let lp = dir.join(files::LOG);
    let log = nppp_files::read_regular_to_string(&lp)
        .with_context(|| format!("reading {}", lp.display()))?;
    Ok(Some(Checkpoint {
        dir,
        state,
        train_config,
        meta,
        log,
    }))
}

/// Refuses a JSON file with a key this build does not read. Serde (and
/// Burn's config derive) skip unknown keys, so a misspelt key in a
/// hand-edited file (`"lerning_rate"`) would otherwise train or bake with
/// the default silently. `parsed` is what was read from `text`; a key of
/// the file that `parsed` does not write back is one nothing read.
fn check_known_keys<T: Serialize>(path: &Path, text: &str, parsed: &T) -> Result<()> {
    let (Ok(file), Ok(known)) = (
        serde_json::from_str::<serde_json::Value>(text),
        serde_json::to_value(parsed),
    ) else {
        return Ok(());
    };
    match first_unknown_key(&file, &known, "") {
        Some(key) => bail!(
            "{}: unknown key \"{key}\" (this build does not read it: a misspelt key, or a file \
             from another version of nppp)",
            path.display()
        ),
        None => Ok(()),
    }
}

/// The path (`model.hidden`, `files[2].crc`) of the first key of `file`
/// that `known` lacks. A key whose value is `null` or `false` counts as
/// absent: optional and flag fields are left out when written in those
/// states (`skip_serializing_if`), and may be written either way.
fn first_unknown_key(
    file: &serde_json::Value,
    known: &serde_json::Value,
    at: &str,
) -> Option<String> {
    use serde_json::Value;
    match (file, known) {
        (Value::Object(f), Value::Object(k)) => f.iter().find_map(|(key, v)| {
            let path = if at.is_empty() {
                key.clone()
            } else {
                format!("{at}.{key}")
            };
            match k.get(key) {
                Some(kv) => first_unknown_key(v, kv, &path),
                None if v.is_null() || *v == Value::Bool(false) => None,
                None => Some(path),
            }
        }),
        (Value::Array(f), Value::Array(k)) => f
            .iter()
            .zip(k)
            .enumerate()
            .find_map(|(i, (v, kv))| first_unknown_key(v, kv, &format!("{at}[{i}]"))),
        _ => None,
    }
}

/// Runs `f`, turning a panic inside Burn (it panics on some malformed files)
/// into an error.
fn no_panic<T>(what: &str, f: impl FnOnce() -> Result<T>) -> Result<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => {
            let msg = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            bail!("{what}: the file is corrupt or from another model ({msg})")
        }
    }
}

/// Loads the weights of a checked checkpoint onto `device`.
pub fn load_weights(ckpt: &Checkpoint, device: &Device) -> Result<NpppModel> {
    let path = ckpt.dir.join(files::WEIGHTS);
    let fresh = NpppModel::init(&ckpt.train_config.model, 0, device)?;
    // Read whole, then decoded: a record read from the file lazily would
    // read it after a checkpoint lock is released.
    let bytes = fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    no_panic(&format!("loading {}", path.display()), || {
        let record =
            burn::store::ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(bytes))
                .map_err(|e| anyhow::anyhow!("loading {}: {e}", path.display()))?;
        fresh.try_load_record(record).map_err(|e| {
            anyhow::anyhow!(
                "loading {}: its weights do not fit the network {} describes (the model \
                 directory was edited or mixed from two runs; retrain it): {}",
                path.display(),
                files::TRAIN_CONFIG,
                first_mismatch(&e.to_string())
            )
        })
    })
}

/// The first of Burn's list of tensors that do not fit, in plain words
/// (`decoder.layers.0.weight: shape mismatch, expected Shape { dims: [20,
/// 32] } but …`, one per tensor), and how many more there are.
fn first_mismatch(message: &str) -> String {
    let plain = message
        .replace("Shape { dims: ", "")
        .replace("] }", "]")
        .replace("Record validation error: Apply errors: ", "");
    let items: Vec<&str> = plain
        .trim_matches(|c| c == '[' || c == ']')
        .split("\", \"")
        .map(|i| i.trim_matches('"'))
        .collect();
    match items.as_slice() {
        [first, rest @ ..] if !rest.is_empty() => {
            format!("{first} (and {} more tensors)", rest.len())
        }
        _ => plain,
    }
}

/// Loads the Adam state of a checked checkpoint into `optim`.
pub fn load_optimizer(
    ckpt: &Checkpoint,
    optim: ModuleOptimizer,
    model: &NpppModel,
) -> Result<ModuleOptimizer> {
    let path = ckpt.dir.join(files::OPTIMIZER);
    let optim = no_panic(&format!("loading {}", path.display()), || {
        optim.load(&path).map_err(|e| {
            anyhow::anyhow!(
                "loading {}: {e} (the Adam state is damaged or from another model: resume \
                     cannot go on from it; retrain with --overwrite)",
                path.display()
            )
        })
    })?;
    // Burn loads any record it can parse and starts the parameters it
    // finds no state for afresh: the weights file copied over this one
    // (its checksum forged to match) resumed with a fresh Adam state,
    // silently. Every parameter has its moments once a step is done.
    let states = optim.to_record().len();
    let params = burn::module::list_param_ids(model).len();
    if ckpt.state.step > 0 && states < params {
        bail!(
            "{}: holds optimizer state for {states} tensors, and the model has {params} \
             parameters after {} steps: it is not this model's Adam state (resume cannot go on \
             from it); retrain with --overwrite",
            path.display(),
            ckpt.state.step
        );
    }
    Ok(optim)
}

/// Whether `name`, in a model directory, is something `nppp train` writes:
/// one of [`files::ALL`] or a hidden temporary file of an atomic write.
fn written_by_train(name: &str) -> bool {
    files::ALL.contains(&name) || (name.starts_with('.') && name.ends_with(".tmp"))
}

/// Whether `name`, in a checkpoint folder, is `nppp train`'s: one of a
/// checkpoint's files, or the temporary file of one being written.
fn in_checkpoint_by_train(name: &str) -> bool {
    let own = |n: &str| n == files::STATE || files::IN_CHECKPOINT.contains(&n);
    own(name)
        || (name.ends_with(".tmp")
            && std::iter::once(files::STATE)
                .chain(files::IN_CHECKPOINT.iter().copied())
                .any(|f| name.trim_start_matches('.').starts_with(f)))
}

/// Refuses a model directory whose checkpoint folders (`checkpoint`,
/// `checkpoint.old`, `checkpoint.tmp`) hold anything `nppp train` did not
/// write. Each swap deletes the folder it replaces with all it holds:
/// training data, an image or a second model placed inside `checkpoint/`
/// was deleted without a word by the next checkpoint.
pub fn check_checkpoint_folders(out: &Path) -> Result<()> {
    for sub in [
        files::CHECKPOINT,
        files::CHECKPOINT_OLD,
        files::CHECKPOINT_TMP,
    ] {
        let dir = out.join(sub);
        if let Some(name) = foreign_entry(&dir)? {
            bail!(
                "{} holds {name:?}, which `nppp train` did not write: every checkpoint \
                 replaces that folder whole, so move it out of the model directory first",
                dir.display()
            );
        }
    }
    Ok(())
}

/// The first entry of checkpoint folder `dir` that `nppp train` did not
/// write (none where `dir` is not a folder).
fn foreign_entry(dir: &Path) -> Result<Option<String>> {
    if !fs::symlink_metadata(dir).is_ok_and(|m| m.is_dir()) {
        return Ok(None);
    }
    for e in fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let name = e?.file_name().to_string_lossy().into_owned();
        if !in_checkpoint_by_train(&name) {
            return Ok(Some(name));
        }
    }
    Ok(None)
}

/// Deletes a checkpoint folder `nppp train` replaces, unless it holds a
/// file of someone else's ([`check_checkpoint_folders`], checked again
/// here: such a file may have been put there while the run trained).
fn remove_checkpoint_folder(dir: &Path) -> Result<()> {
    if let Some(name) = foreign_entry(dir)? {
        bail!(
            "{} holds {name:?}, which `nppp train` did not write; it was kept, and so was the \
             folder: move the file out of the model directory, then run `nppp train --resume` \
             again",
            dir.display()
        );
    }
    fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))
}

/// Whether a fresh run may write into `out`: it does not exist, is empty,
/// or holds nothing but what `nppp train` writes (so a user's own folder is
/// never filled with, or stripped of, files).
pub fn check_fresh_out(out: &Path) -> Result<()> {
    if !out.exists() {
        return Ok(());
    }
    if !out.is_dir() {
        bail!(
            "--out {} is a file; name a folder for the model",
            out.display()
        );
    }
    let entries = fs::read_dir(out).with_context(|| format!("reading {}", out.display()))?;
    for e in entries {
        let name = e?.file_name().to_string_lossy().into_owned();
        let ours = written_by_train(&name);
        if !ours {
            bail!(
                "--out {} holds {name:?}, which `nppp train` did not write: it is not a model \
                 directory. Choose a new or empty folder",
                out.display()
            );
        }
    }
    Ok(())
}

/// Waits for and takes the checkpoint lock of model directory `dir`
/// ([`files::CHECKPOINT_LOCK`]): exclusive for the one writer, shared for
/// readers. A reader that cannot create the lock file (a read-only model
/// directory, which no training run can be writing) reads without it.
fn checkpoint_lock(dir: &Path, exclusive: bool) -> Result<Option<fs::File>> {
    let p = dir.join(files::CHECKPOINT_LOCK);
    let f = match fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&p)
    {
        Ok(f) => f,
        Err(_) if !exclusive => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("opening {}", p.display())),
    };
    if exclusive { f.lock() } else { f.lock_shared() }
        .with_context(|| format!("locking {}", p.display()))?;
    Ok(Some(f))
}

/// The shared checkpoint lock of a model directory for a reader of its
/// checkpoint (`bake`, `train --resume`): held while it reads, a training
/// run writing the folder cannot swap a checkpoint in under it. A folder
/// without a checkpoint gets no lock file (it is not a model, or not yet).
pub fn checkpoint_read_lock(dir: &Path) -> Result<Option<fs::File>> {
    match checkpoint_dir(dir) {
        Some(_) => checkpoint_lock(dir, false),
        None => Ok(None),
    }
}

/// Takes the model directory for this process (creating it if needed): two
/// runs writing one directory would interleave their checkpoints. The lock
/// is the OS's (`flock`), so a killed run never leaves a stale one.
pub fn lock_model_dir(out: &Path) -> Result<ModelDirLock> {
    let created = !out.exists();
    // Its parents as output folders: removed again when a run that
    // created them ends before its first checkpoint.
    nppp_files::create_parent(out)
        .and_then(|()| fs::create_dir_all(out))
        .with_context(|| format!("creating {}", out.display()))?;
    let p = out.join(files::LOCK);
    let f = fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&p)
        .with_context(|| format!("opening {}", p.display()))?;
    match f.try_lock() {
        Ok(()) => {
            if created {
                // Removed by a signal until its first checkpoint is in place
                // (`save_checkpoint`). Only once the lock is this run's: a
                // run that lost the race for the folder must not remove it.
                nppp_files::track_pending_dir(out);
            }
            Ok(ModelDirLock {
                _file: f,
                dir: out.to_path_buf(),
                created,
            })
        }
        Err(fs::TryLockError::WouldBlock) => bail!(
            "{}: another `nppp train` is writing this model directory; wait for it, or train \
             into another --out",
            out.display()
        ),
        Err(fs::TryLockError::Error(e)) => {
            Err(e).with_context(|| format!("locking {}", p.display()))
        }
    }
}

/// The lock on a model directory, held while training writes it. A folder
/// the run created is removed again when the run ends without a complete
/// checkpoint in it (an error, a full disk or a divergence before the first
/// checkpoint was swapped in): its lock files, copies and partial
/// `checkpoint.tmp` looked like a model folder to the user and to the next
/// `train` without `--overwrite`.
pub struct ModelDirLock {
    _file: fs::File,
    dir: PathBuf,
    created: bool,
}

impl Drop for ModelDirLock {
    fn drop(&mut self) {
        nppp_files::untrack_pending_dir(&self.dir);
        if !self.created || checkpoint_dir(&self.dir).is_some() {
            return;
        }
        // Only what `nppp train` writes: the folder is this run's own.
        let ours = fs::read_dir(&self.dir).is_ok_and(|entries| {
            entries
                .filter_map(|e| e.ok())
                .all(|e| written_by_train(&e.file_name().to_string_lossy()))
        });
        if ours {
            let _ = fs::remove_dir_all(&self.dir);
        }
    }
}

/// What a checkpoint holds besides the state.
pub struct CheckpointContent<'a> {
    pub train_config: &'a TrainConfig,
    pub meta: &'a ModelMeta,
    pub model: &'a NpppModel,
    pub optim: &'a ModuleOptimizer,
    /// The whole training log so far, header first.
    pub log: &'a str,
}

fn sync_file(p: &Path) -> Result<()> {
    fs::File::open(p)
        .and_then(|f| f.sync_all())
        .with_context(|| format!("syncing {}", p.display()))
}

/// Writes a complete checkpoint and swaps it in (see the module doc), then
/// refreshes the copies beside it. `state.files` is filled in here.
pub fn save_checkpoint(out: &Path, c: &CheckpointContent, state: &TrainState) -> Result<()> {
    let tmp = out.join(files::CHECKPOINT_TMP);
    let texts = match write_checkpoint_tmp(&tmp, c, state) {
        Ok(texts) => texts,
        Err(e) => {
            // A full disk or an unwritable file: the last complete checkpoint
            // stays as it was, and no partial one is left beside it.
            let _ = fs::remove_dir_all(&tmp);
            nppp_files::untrack_pending_dir(&tmp);
            return Err(e);
        }
    };
    let cur = out.join(files::CHECKPOINT);
    let old = out.join(files::CHECKPOINT_OLD);
    let _lock = checkpoint_lock(out, true)?;
    // Swap. `checkpoint` is the last complete one if it exists; otherwise
    // (a kill between renames) `checkpoint.old` is, and stays until the new
    // one is in place.
    if cur.join(files::STATE).is_file() {
        if old.exists() {
            remove_checkpoint_folder(&old)?;
        }
        fs::rename(&cur, &old).with_context(|| format!("moving {}", cur.display()))?;
        nppp_files::crash_point("checkpoint:between-renames");
    } else if cur.exists() {
        // Not a checkpoint (no state): debris of a crash, never read.
        remove_checkpoint_folder(&cur)?;
    }
    // The model folder holds a checkpoint from here on: a signal no longer
    // removes it.
    nppp_files::rename_dir_into_place(&tmp, &cur, &[out])
        .with_context(|| format!("moving {} into place", tmp.display()))?;
    nppp_files::crash_point("checkpoint:swapped");
    if old.exists() {
        remove_checkpoint_folder(&old)?;
    }
    write_copies(out, &texts)
}

/// Writes a complete checkpoint into `tmp` (replacing what is there) and
/// returns the text files it holds, for the copies beside it.
fn write_checkpoint_tmp(
    tmp: &Path,
    c: &CheckpointContent,
    state: &TrainState,
) -> Result<Vec<(&'static str, String)>> {
    if tmp.exists() {
        remove_checkpoint_folder(tmp)?;
    }
    nppp_files::create_tracked_dir(tmp).with_context(|| format!("creating {}", tmp.display()))?;
    let w = tmp.join(files::WEIGHTS);
    c.model
        .clone()
        .save_file(&w)
        .map_err(|e| anyhow::anyhow!("saving weights to {}: {e}", w.display()))?;
    sync_file(&w)?;
    nppp_files::crash_point("checkpoint:weights-written");
    let o = tmp.join(files::OPTIMIZER);
    c.optim
        .save(&o)
        .map_err(|e| anyhow::anyhow!("saving optimizer state to {}: {e}", o.display()))?;
    sync_file(&o)?;
    let texts = texts(c)?;
    for (name, text) in &texts {
        let p = tmp.join(name);
        nppp_files::write_atomic(&p, text.as_bytes())
            .with_context(|| format!("writing {}", p.display()))?;
    }
    let mut state = state.clone();
    state.version = STATE_VERSION;
    state.files = files::IN_CHECKPOINT
        .iter()
        .map(|n| FileSum::of(tmp, n))
        .collect::<Result<_>>()?;
    let sp = tmp.join(files::STATE);
    nppp_files::write_atomic(&sp, serde_json::to_string_pretty(&state)?.as_bytes())
        .with_context(|| format!("writing {}", sp.display()))?;
    nppp_files::crash_point("checkpoint:complete");
    Ok(texts)
}

/// Replaces the copies beside the checkpoint with its own files' content
/// (at every checkpoint, and when a run resumes: a kill between a swap and
/// the copies may have left them stale).
pub fn refresh_copies(out: &Path, c: &CheckpointContent) -> Result<()> {
    let texts = texts(c)?;
    let _lock = checkpoint_lock(out, true)?;
    write_copies(out, &texts)
}

fn write_copies(out: &Path, texts: &[(&'static str, String)]) -> Result<()> {
    for (name, text) in texts {
        let p = out.join(name);
        nppp_files::write_atomic(&p, text.as_bytes())
            .with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}

/// The text files of a checkpoint: name and content.
fn texts(c: &CheckpointContent) -> Result<Vec<(&'static str, String)>> {
    Ok(vec![
        (files::TRAIN_CONFIG, c.train_config.to_string()),
        (files::MODEL_CONFIG, c.train_config.model.to_string()),
        (files::META, serde_json::to_string_pretty(c.meta)?),
        (files::LOG, c.log.to_string()),
    ])
}

/// A trained model loaded back from its directory, for baking and evaluation.
pub struct LoadedModel {
    pub dir: PathBuf,
    pub model_config: ModelConfig,
    pub train_config: TrainConfig,
    pub meta: ModelMeta,
    pub model: NpppModel,
    pub state: TrainState,
}

/// Loads the checked checkpoint of a model directory (no autodiff) onto `device`.
pub fn load_model_dir(dir: &Path, device: &Device) -> Result<LoadedModel> {
    if !dir.is_dir() {
        if dir.exists() {
            bail!(
                "model directory {} is a file; name the folder `nppp train --out` wrote",
                dir.display()
            );
        }
        bail!("model directory {} does not exist", dir.display());
    }
    // A training run may be swapping a checkpoint in: read one whole.
    let lock = checkpoint_read_lock(dir)?;
    let ckpt = open_checkpoint(dir)?
        .with_context(|| no_checkpoint_message(dir, "holds no checkpoint (train first)"))?;
    let device = device.clone().without_autodiff();
    let model = load_weights(&ckpt, &device)?;
    drop(lock);
    Ok(LoadedModel {
        dir: dir.to_path_buf(),
        model_config: ckpt.train_config.model.clone(),
        train_config: ckpt.train_config,
        meta: ckpt.meta,
        model,
        state: ckpt.state,
    })
}
