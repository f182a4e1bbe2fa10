//! Writing files without ever losing one: the single home of the pipeline's
//! file-safety rules, used by every command that writes (render, gen, train,
//! bake, mesh, bench).
//!
//! - [`AtomicFile`] / [`write_atomic`]: a file is written to a hidden
//!   temporary name in the same folder, flushed to disk, then renamed over
//!   the target. A reader (or a kill at any instant) sees the old file or the
//!   new one, never a half-written one; a writer dropped before
//!   [`AtomicFile::commit`] removes its temporary file, and a command ended
//!   by a signal removes every one still open ([`remove_pending_temp_files`]),
//!   with every folder still being assembled ([`create_tracked_dir`],
//!   [`track_pending_dir`], [`rename_dir_into_place`]: a checkpoint's
//!   `checkpoint.tmp/`, a fresh model folder before its first checkpoint)
//!   and every output folder it made that is still empty
//!   ([`create_output_dir`], [`remove_new_empty_dirs`]).
//! - [`ensure_not_input`]: an output path that names one of the command's
//!   inputs (the same file, under any spelling or hard link) is refused
//!   before any work, so a slip of the flags cannot overwrite the training
//!   data, a scene or a reference image.
//! - [`crash_point`]: named points where the tests kill the process
//!   (`NPPP_CRASH_AT=name`), to prove that every file survives a kill at
//!   every step of a multi-file write (a model checkpoint).
//! - [`open_regular`] / [`read_regular`] / [`check_regular`]: every input
//!   file is opened through these, which refuse what is not a regular file
//!   before opening it (a device such as `/dev/zero` would be read until
//!   memory runs out, opening a named pipe waits for a writer forever, a
//!   folder gives a misleading error).
//! - [`ScratchDir`]: a test's temporary folder, removed when the test is
//!   done (kept when it fails).
//! - [`available_memory`]: what a command may plan to allocate, so that a
//!   flag or a file that claims gigabytes is refused with a message instead
//!   of aborting on allocation.
//! - [`note!`]: `eprintln!` that never panics (a closed pipe made it end
//!   a render with exit code 101).
//! - [`format_bytes`], [`format_rate`] and [`progress_style`]: the one way
//!   every command prints sizes and rates (summaries and progress bars say
//!   `0.229 M samples/s` alike).

/// `eprintln!` that never panics. Notes and warnings on stderr are best
/// effort: with stderr a closed pipe (`nppp render ... 2>&1 | head -5`),
/// `eprintln!` panicked (exit code 101) in the middle of a render, where
/// the command should go on and finish its files.
///
/// Control characters in what it prints (names and notes read from files)
/// are escaped ([`printable`]).
#[macro_export]
macro_rules! note {
    ($($arg:tt)*) => {{
        use ::std::io::Write as _;
        let text = ::std::format!($($arg)*);
        let _ = ::std::writeln!(::std::io::stderr(), "{}", $crate::printable(&text));
    }};
}

/// `s` with its control characters other than newline and tab escaped
/// (`\u{1b}`): mesh names, keys and notes come from files, and a terminal
/// would act on an escape sequence printed raw (an adversarial scene turned
/// an error message red and rang the bell). A word (a run without spaces)
/// longer than [`PRINTED_WORD_MAX`] characters keeps its two ends: a scene
/// with a 20 MB mesh name printed all of it in an error.
pub fn printable(s: &str) -> std::borrow::Cow<'_, str> {
    let control = |c: char| c.is_control() && c != '\n' && c != '\t';
    let long_word = || {
        s.split(char::is_whitespace)
            .any(|w| w.len() > PRINTED_WORD_MAX && w.chars().count() > PRINTED_WORD_MAX)
    };
    if !s.chars().any(control) && !long_word() {
        return std::borrow::Cow::Borrowed(s);
    }
    let mut escaped = String::with_capacity(s.len() + 16);
    for c in s.chars() {
        if control(c) {
            escaped.extend(c.escape_unicode());
        } else {
            escaped.push(c);
        }
    }
    let mut out = String::with_capacity(escaped.len().min(1 << 16));
    let mut rest = escaped.as_str();
    while !rest.is_empty() {
        let end = rest.find(char::is_whitespace).unwrap_or(rest.len());
        let (word, after) = rest.split_at(end);
        let n = word.chars().count();
        if n > PRINTED_WORD_MAX {
            let keep = PRINTED_WORD_MAX / 2 - 20;
            out.extend(word.chars().take(keep));
            out.push_str(&format!("...[{} characters left out]...", n - 2 * keep));
            out.extend(word.chars().skip(n - keep));
        } else {
            out.push_str(word);
        }
        let space = after.chars().next().map_or(0, char::len_utf8);
        out.push_str(&after[..space]);
        rest = &after[space..];
    }
    std::borrow::Cow::Owned(out)
}

/// The longest word [`printable`] prints whole: longer than any path a
/// file system takes (4,096 bytes on Linux) would be too long to read.
pub const PRINTED_WORD_MAX: usize = 4200;

use std::ffi::OsString;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};

/// The temporary files this process is writing whose targets are not yet
/// replaced: what [`remove_pending_temp_files`] deletes when a signal ends
/// the process, which runs no destructor (an interrupted `nppp gen` left
/// its half-written data behind, one hidden file per run).
static PENDING: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn pending() -> MutexGuard<'static, Vec<PathBuf>> {
    PENDING.lock().unwrap_or_else(|e| e.into_inner())
}

/// Creates (or truncates) the temporary file `tmp` and tracks it, as one
/// step against a signal handler's [`remove_pending_temp_files`]: a file
/// created outside the lock could appear just after the handler's cleanup
/// and stay behind.
fn create_tracked(tmp: &Path) -> io::Result<File> {
    let mut list = pending();
    let file = File::create(tmp)?;
    list.push(tmp.to_path_buf());
    Ok(file)
}

fn untrack(tmp: &Path) {
    let mut list = pending();
    if let Some(i) = list.iter().rposition(|p| p == tmp) {
        list.swap_remove(i);
    }
}

/// The outputs this process has put in place so far (for the message of a
/// command stopped by a signal: those are new, every other keeps its old
/// contents).
static WRITTEN: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// Renames `tmp` onto `path` and stops tracking it, as one step against a
/// signal handler's [`remove_pending_temp_files`]: a signal either finds the
/// temporary file pending and deletes it (the output keeps its old
/// contents) or finds the output in place and says so. Without the lock a
/// signal during the rename reported old contents for a file already new.
fn rename_into_place(tmp: &Path, path: &Path) -> io::Result<()> {
    put_into_place(tmp, path, true)
}

/// [`rename_into_place`], or (`replace` false) never over an existing file:
/// the output is linked to its new name, which fails where a file already
/// has it, and the temporary name removed. A filesystem without hard links
/// gets a check and a rename (a window the link closes).
fn put_into_place(tmp: &Path, path: &Path, replace: bool) -> io::Result<()> {
    let mut list = pending();
    if replace {
        std::fs::rename(tmp, path)?;
    } else {
        match std::fs::hard_link(tmp, path) {
            Ok(()) => std::fs::remove_file(tmp)?,
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => return Err(e),
            Err(_) if path.symlink_metadata().is_ok() => {
                return Err(io::Error::from(io::ErrorKind::AlreadyExists));
            }
            Err(_) => std::fs::rename(tmp, path)?,
        }
    }
    if let Some(i) = list.iter().rposition(|p| p == tmp) {
        list.swap_remove(i);
    }
    // Outputs only: a file inside a folder still being assembled (a
    // checkpoint's `checkpoint.tmp/`) is not in place yet; and each once.
    let staged = path
        .parent()
        .and_then(Path::file_name)
        .is_some_and(|d| d.to_string_lossy().ends_with(".tmp"));
    let mut written = WRITTEN.lock().unwrap_or_else(|e| e.into_inner());
    if !staged && !written.iter().any(|p| p == path) {
        written.push(path.to_path_buf());
    }
    Ok(())
}

/// Folders this process is assembling that are not in place yet (a
/// checkpoint's `checkpoint.tmp/`, a model folder before its first
/// checkpoint): [`remove_pending_temp_files`] removes them whole. A second
/// Ctrl-C during a fresh `nppp train` left both behind.
static PENDING_DIRS: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn pending_dirs() -> MutexGuard<'static, Vec<PathBuf>> {
    PENDING_DIRS.lock().unwrap_or_else(|e| e.into_inner())
}

/// Tracks folder `dir`, which this process created, as not yet in place
/// (a folder still to be made: [`create_tracked_dir`]).
pub fn track_pending_dir(dir: &Path) {
    pending_dirs().push(dir.to_path_buf());
}

/// Creates folder `dir` (with its parents) and tracks it as not yet in
/// place, as one step against a signal handler's
/// [`remove_pending_temp_files`], which holds the same lock to the end: a
/// signal finds the folder either tracked or not made, and one that comes
/// first leaves it unmade. Tracked first and created after, a signal in
/// between found nothing to remove and the folder was made after it.
pub fn create_tracked_dir(dir: &Path) -> io::Result<()> {
    let mut list = pending_dirs();
    std::fs::create_dir_all(dir)?;
    list.push(dir.to_path_buf());
    Ok(())
}

/// Stops tracking `dir` (it is in place, or was removed).
pub fn untrack_pending_dir(dir: &Path) {
    let mut list = pending_dirs();
    list.retain(|d| d != dir);
}

/// Renames folder `tmp` onto `path` and stops tracking `tmp` and the
/// folders in `settled` (which the rename completes), as one step against a
/// signal handler's [`remove_pending_temp_files`]: a signal either finds
/// them pending and removes them or finds the folder in place.
pub fn rename_dir_into_place(tmp: &Path, path: &Path, settled: &[&Path]) -> io::Result<()> {
    let mut list = pending_dirs();
    std::fs::rename(tmp, path)?;
    list.retain(|d| d != tmp && !settled.contains(&d.as_path()));
    Ok(())
}

/// Folders this process created to hold its outputs, outermost first:
/// [`remove_pending_temp_files`] and [`remove_new_empty_dirs`] remove those
/// still empty (a `gen --out new/d.nppd` or a `bench` interrupted before its
/// first file left `new/` or `--out/<scene>/` behind, empty).
static NEW_DIRS: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn new_dirs() -> MutexGuard<'static, Vec<PathBuf>> {
    NEW_DIRS.lock().unwrap_or_else(|e| e.into_inner())
}

/// Creates folder `dir` and its missing parents for outputs, remembering
/// the folders it made so that a run that ends before writing into them
/// (a signal, an error) can remove them again ([`remove_new_empty_dirs`]).
/// Folders that existed are never removed; a folder that holds anything
/// when the run ends is kept.
pub fn create_output_dir(dir: &Path) -> io::Result<()> {
    if dir.as_os_str().is_empty() || dir.is_dir() {
        return Ok(());
    }
    // The missing folders, innermost first.
    let missing: Vec<&Path> = dir
        .ancestors()
        .filter(|d| !d.as_os_str().is_empty())
        .take_while(|d| std::fs::symlink_metadata(d).is_err())
        .collect();
    let there = dir.ancestors().nth(missing.len());
    if let Some(d) = there.filter(|d| !d.as_os_str().is_empty() && !d.exists()) {
        // Said plainly: creating under it fails with "File exists".
        return Err(io::Error::other(format!(
            "{} is a symbolic link to a missing folder (or a loop of links)",
            d.display()
        )));
    }
    let mut list = new_dirs();
    for d in missing.into_iter().rev() {
        match std::fs::create_dir(d) {
            Ok(()) => list.push(d.to_path_buf()),
            // Made by another process in between: not ours to remove.
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists && d.is_dir() => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

/// Removes the folders [`create_output_dir`] made that are still empty,
/// innermost first; for a run that ends without its outputs.
pub fn remove_new_empty_dirs() {
    remove_empty(&mut new_dirs());
}

fn remove_empty(list: &mut Vec<PathBuf>) {
    for dir in list.drain(..).rev() {
        // Fails, as it should, on a folder that holds anything.
        let _ = std::fs::remove_dir(&dir);
    }
}

/// Deletes the temporary file of every write still in progress and every
/// folder still being assembled, then the output folders this run made
/// that are left empty; for a signal handler about to end the process (the
/// targets keep their old contents, as after a kill). Returns the outputs
/// already put in place before it ran.
pub fn remove_pending_temp_files() -> Vec<PathBuf> {
    let mut list = pending();
    for tmp in list.drain(..) {
        let _ = std::fs::remove_file(tmp);
    }
    let mut dirs = pending_dirs();
    // Latest first: a folder inside another goes before it.
    for dir in dirs.drain(..).rev() {
        // The thread writing into it runs on: a file it creates while
        // remove_dir_all runs leaves the folder not empty (1 second Ctrl-C
        // in 20 left a resumed run's `checkpoint.tmp/`), so try again until
        // it is gone; once it is, that thread's next file cannot be made
        // (nor the folder again: `create_tracked_dir` waits on this lock).
        for _ in 0..200 {
            match std::fs::remove_dir_all(&dir) {
                Err(e) if e.kind() != io::ErrorKind::NotFound => {
                    std::thread::sleep(std::time::Duration::from_millis(1));
                }
                _ => break,
            }
        }
    }
    let mut made = new_dirs();
    remove_empty(&mut made);
    // Held until the process exits: no rename completes after this, and
    // no output folder is made.
    std::mem::forget(list);
    std::mem::forget(dirs);
    std::mem::forget(made);
    WRITTEN.lock().unwrap_or_else(|e| e.into_inner()).clone()
}

/// The environment variable that names a crash point (tests only).
pub const CRASH_ENV: &str = "NPPP_CRASH_AT";

/// Opens an input file for reading, refusing anything but a regular file
/// (a device, a pipe, a socket or a folder) with an error that says so.
pub fn open_regular(path: &Path) -> io::Result<File> {
    // Before opening: opening a named pipe blocks until a writer comes.
    check_regular(path)?;
    let f = File::open(path)?;
    // And what was opened, should the name have changed in between.
    regular_or_error(f.metadata()?.file_type())?;
    Ok(f)
}

/// Refuses what is not a regular file, without opening it (see
/// [`open_regular`]); for readers that open the file themselves (an EXR
/// decoder).
pub fn check_regular(path: &Path) -> io::Result<()> {
    regular_or_error(std::fs::metadata(path)?.file_type())
}

fn regular_or_error(kind: std::fs::FileType) -> io::Result<()> {
    if kind.is_file() {
        return Ok(());
    }
    let what = if kind.is_dir() {
        "a folder"
    } else {
        "a device, pipe or socket"
    };
    Err(io::Error::new(
        io::ErrorKind::InvalidInput,
        format!("not a regular file ({what})"),
    ))
}

/// Reads a whole input file (see [`open_regular`]).
pub fn read_regular(path: &Path) -> io::Result<Vec<u8>> {
    use std::io::Read;
    let mut f = open_regular(path)?;
    let mut bytes = Vec::new();
    f.read_to_end(&mut bytes)?;
    Ok(bytes)
}

/// Reads a whole input text file (see [`open_regular`]); not UTF-8 is an
/// error, as [`std::fs::read_to_string`] has it.
pub fn read_regular_to_string(path: &Path) -> io::Result<String> {
    String::from_utf8(read_regular(path)?).map_err(|_| {
        io::Error::new(
            io::ErrorKind::InvalidData,
            "stream did not contain valid UTF-8",
        )
    })
}

/// `dir/.name.<pid>.tmp`: in the target's own folder (a rename must not
/// cross filesystems), hidden, and unique per process.
pub fn temp_path(path: &Path) -> PathBuf {
    let file = path.file_name().unwrap_or_else(|| "out".as_ref());
    let mut name = OsString::from(".");
    // A name near the file system's 255-byte limit would not fit with the
    // temporary suffix (a valid 254-character --out failed with "File name
    // too long"): such a name is cut, and a hash of the whole keeps the
    // temporary names of two long outputs apart.
    const KEEP: usize = 200;
    let bytes = file.as_encoded_bytes();
    if bytes.len() > KEEP {
        let text = file.to_string_lossy();
        let mut cut = KEEP;
        while !text.is_char_boundary(cut.min(text.len())) {
            cut -= 1;
        }
        let hash = bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
            (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3)
        });
        name.push(format!("{}.{hash:016x}", &text[..cut.min(text.len())]));
    } else {
        name.push(file);
    }
    name.push(format!(".{}.tmp", std::process::id()));
    path.with_file_name(name)
}

/// Creates the folder that will hold `path`, if it has one and it is
/// missing ([`create_output_dir`]: removed again if the run ends before
/// anything is written into it).
pub fn create_parent(path: &Path) -> io::Result<()> {
    match path.parent() {
        Some(d) => create_output_dir(d),
        None => Ok(()),
    }
}

/// A file being written under a temporary name; [`Self::commit`] moves it
/// into place. Dropped without commit (an error, a panic), it removes the
/// temporary file and leaves the target as it was.
pub struct AtomicFile {
    path: PathBuf,
    tmp: PathBuf,
    file: Option<BufWriter<File>>,
}

impl AtomicFile {
    /// Starts writing `path`; its folder must exist ([`create_parent`]
    /// makes it, for callers that want that).
    pub fn create(path: &Path) -> io::Result<Self> {
        if path.file_name().is_none() {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("{} names a folder, not a file", path.display()),
            ));
        }
        let tmp = temp_path(path);
        let file = create_tracked(&tmp)?;
        Ok(Self {
            path: path.to_path_buf(),
            tmp,
            file: Some(BufWriter::with_capacity(1 << 20, file)),
        })
    }

    /// The final path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Flushes the data to disk and renames the file into place.
    pub fn commit(mut self) -> io::Result<()> {
        self.finish(true)
    }

    /// [`Self::commit`], but never over a file that has appeared at the
    /// path since the command checked it was free (another run that
    /// finished first): the data is then kept beside it, under
    /// `<stem>.<pid>.<extension>`, and the error says so. For outputs that
    /// took long to make and that a command replaces only when told to
    /// (`gen --overwrite`).
    pub fn commit_new(mut self) -> io::Result<()> {
        match self.finish(false) {
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
                let saved = match keep_beside(&self.tmp, &self.path) {
                    Some(k) => format!("this run's output is kept as {}", k.display()),
                    None => "this run's output could not be kept".to_string(),
                };
                Err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    format!(
                        "a file appeared at this path while the command ran (another run?) \
                         and was left as it was; {saved}"
                    ),
                ))
            }
            other => other,
        }
    }

    /// Flushes, syncs and puts the file into place (`replace`: over an
    /// existing one). Where `replace` is false and a file is in the way,
    /// the temporary file is kept, still tracked, for [`keep_beside`].
    fn finish(&mut self, replace: bool) -> io::Result<()> {
        let w = self
            .file
            .take()
            .ok_or_else(|| io::Error::other("already committed"))?;
        let result: io::Result<()> = (|| {
            let file = w.into_inner().map_err(|e| e.into_error())?;
            file.sync_all()?;
            drop(file);
            crash_point(&format!("before-rename:{}", file_label(&self.path)));
            put_into_place(&self.tmp, &self.path, replace)?;
            sync_parent(&self.path);
            Ok(())
        })();
        let kept =
            !replace && matches!(&result, Err(e) if e.kind() == io::ErrorKind::AlreadyExists);
        if !kept {
            if result.is_err() {
                let _ = std::fs::remove_file(&self.tmp);
            }
            untrack(&self.tmp);
        }
        result
    }
}

/// Puts the finished temporary file `tmp` at a free name beside `path`
/// (`<stem>.<pid>.<extension>`, then `.<pid>-1.` and on), never over a file;
/// removes it where none can be had.
fn keep_beside(tmp: &Path, path: &Path) -> Option<PathBuf> {
    let stem = path.file_stem()?.to_string_lossy().into_owned();
    let ext = path
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    let pid = std::process::id();
    for k in 0..100 {
        let tag = if k == 0 {
            pid.to_string()
        } else {
            format!("{pid}-{k}")
        };
        let alt = path.with_file_name(format!("{stem}.{tag}{ext}"));
        match put_into_place(tmp, &alt, false) {
            Ok(()) => {
                sync_parent(&alt);
                return Some(alt);
            }
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
            Err(_) => break,
        }
    }
    let _ = std::fs::remove_file(tmp);
    untrack(tmp);
    None
}

impl Write for AtomicFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        match &mut self.file {
            Some(f) => f.write(buf),
            None => Err(io::Error::other("already committed")),
        }
    }

    fn write_all(&mut self, buf: &[u8]) -> io::Result<()> {
        match &mut self.file {
            Some(f) => f.write_all(buf),
            None => Err(io::Error::other("already committed")),
        }
    }

    fn flush(&mut self) -> io::Result<()> {
        match &mut self.file {
            Some(f) => f.flush(),
            None => Ok(()),
        }
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        if self.file.take().is_some() {
            let _ = std::fs::remove_file(&self.tmp);
            untrack(&self.tmp);
        }
    }
}

/// Replaces `path` with `bytes` atomically (see [`AtomicFile`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let mut f = AtomicFile::create(path)?;
    f.write_all(bytes)?;
    f.commit()
}

/// Replaces `path` atomically with what `write` puts at the temporary path
/// it is given (for writers that insist on opening a path themselves, such
/// as the EXR encoder); its folder must exist. The temporary file is
/// removed on any error.
pub fn write_atomic_via_path<E: std::fmt::Display>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> io::Result<()> {
    if path.file_name().is_none() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{} names a folder, not a file", path.display()),
        ));
    }
    let tmp = temp_path(path);
    // Created here, under the handler's lock; the writer truncates it.
    drop(create_tracked(&tmp)?);
    let result = (|| {
        write(&tmp).map_err(|e| io::Error::other(e.to_string()))?;
        File::open(&tmp)?.sync_all()?;
        crash_point(&format!("before-rename:{}", file_label(path)));
        rename_into_place(&tmp, path)?;
        sync_parent(path);
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    untrack(&tmp);
    result
}

/// Makes a rename durable (best effort: not every filesystem syncs folders).
fn sync_parent(path: &Path) {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
}

/// `folder/name` of a path: how crash points name the file being replaced
/// (`before-rename:checkpoint.tmp/state.json`).
fn file_label(path: &Path) -> String {
    let name = |p: Option<&std::ffi::OsStr>| p.map(|n| n.to_string_lossy().into_owned());
    let file = name(path.file_name()).unwrap_or_default();
    match name(path.parent().and_then(Path::file_name)) {
        Some(dir) => format!("{dir}/{file}"),
        None => file,
    }
}

/// The longest file name (one part of a path) in bytes: Linux's NAME_MAX on
/// its file systems (ext4, xfs, btrfs, tmpfs) and macOS's.
pub const NAME_MAX_BYTES: usize = 255;
/// Linux's PATH_MAX: a path passed to the kernel is shorter.
pub const PATH_MAX_BYTES: usize = 4096;

/// Checks, before any work, that a file can be created at `path`: it names a
/// file, not a folder, its name and path are not too long, and the nearest
/// existing ancestor folder accepts a new file (tried with a probe removed
/// at once). Creates nothing that stays.
pub fn check_writable(path: &Path) -> Result<(), String> {
    if path.file_name().is_none() || path.as_os_str().to_string_lossy().ends_with('/') {
        return Err("names a folder, not a file".into());
    }
    if path.is_dir() {
        return Err("is a folder".into());
    }
    // The probe below goes under a short name, which the file system takes
    // whatever the real name's length: names too long for it failed only
    // when the output was put in place, after all the work.
    if let Some(c) = path
        .components()
        .find(|c| c.as_os_str().len() > NAME_MAX_BYTES)
    {
        return Err(format!(
            "cannot be written: its part \"{}…\" is {} bytes, more than the {NAME_MAX_BYTES} a \
             file name may have",
            c.as_os_str()
                .to_string_lossy()
                .chars()
                .take(32)
                .collect::<String>(),
            c.as_os_str().len()
        ));
    }
    if path.as_os_str().len() >= PATH_MAX_BYTES {
        return Err(format!(
            "cannot be written: the path is {} bytes, more than the {} a path may have",
            path.as_os_str().len(),
            PATH_MAX_BYTES - 1
        ));
    }
    let parent = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let mut dir = parent.as_path();
    // Up to the nearest folder that is there. A link whose target is
    // missing (or a loop of links) is there but cannot be followed:
    // `exists()` is false for it, and the folder beside it was probed
    // instead, so the render ran to its end before the folder could not
    // be made.
    while std::fs::symlink_metadata(dir).is_err() {
        match dir.parent() {
            Some(d) if !d.as_os_str().is_empty() => dir = d,
            _ => {
                dir = Path::new(".");
                break;
            }
        }
    }
    if !dir.exists() {
        return Err(format!(
            "{} is a symbolic link to a missing folder (or a loop of links), so the file \
             cannot be created",
            dir.display()
        ));
    }
    if !dir.is_dir() {
        return Err(format!(
            "{} is not a folder, so the file cannot be created",
            dir.display()
        ));
    }
    let probe = if dir == parent.as_path() {
        temp_path(path)
    } else {
        dir.join(format!(".nppp-write-check.{}.tmp", std::process::id()))
    };
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => {
            let _ = std::fs::remove_file(&probe);
            Ok(())
        }
        Err(e) => Err(format!("cannot be written: {e}")),
    }
}

/// `path` made absolute with every existing part resolved (symbolic links,
/// `.` and `..`), the rest normalized as written: two spellings of one file,
/// existing or about to be created (`out/../x.exr` before `out/` exists),
/// give the same result.
pub fn resolve(path: &Path) -> PathBuf {
    use std::path::Component;
    if let Ok(p) = path.canonicalize() {
        return p;
    }
    let abs = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let mut out = PathBuf::new();
    for c in abs.components() {
        match c {
            Component::Prefix(_) | Component::RootDir => out.push(c.as_os_str()),
            Component::CurDir => {}
            // `out` is canonical while it exists, so this is its real parent.
            Component::ParentDir => {
                out.pop();
            }
            Component::Normal(n) => {
                out.push(n);
                if let Ok(real) = out.canonicalize() {
                    out = real;
                }
            }
        }
    }
    out
}

/// Whether `a` and `b` name the same file: the same resolved path, or, when
/// both exist, the same device and inode (a hard link).
pub fn same_file(a: &Path, b: &Path) -> bool {
    if resolve(a) == resolve(b) {
        return true;
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if let (Ok(x), Ok(y)) = (std::fs::metadata(a), std::fs::metadata(b)) {
            return x.dev() == y.dev() && x.ino() == y.ino();
        }
    }
    false
}

/// Whether `path` is `dir` or lies inside it (after resolving both).
pub fn is_inside(path: &Path, dir: &Path) -> bool {
    resolve(path).starts_with(resolve(dir))
}

/// Refuses an output that names one of the command's inputs. `inputs` are
/// (what the input is, e.g. "--data (the training data)", its path), as
/// borrowed or owned strings and paths (`Scene::input_files` as it is).
pub fn ensure_not_input<S: AsRef<str>, P: AsRef<Path>>(
    out_flag: &str,
    out: &Path,
    inputs: &[(S, P)],
) -> Result<(), String> {
    for (what, input) in inputs {
        if same_file(out, input.as_ref()) {
            return Err(format!(
                "{out_flag} {} is {}: writing it would destroy an input. Choose another {out_flag}",
                out.display(),
                what.as_ref()
            ));
        }
    }
    Ok(())
}

/// Aborts the process here if `NPPP_CRASH_AT` names this point: the tests'
/// stand-in for a kill (no destructor runs, nothing is cleaned up), at an
/// exact step of a write. Without the variable this is one lookup.
pub fn crash_point(name: &str) {
    if let Some(v) = std::env::var_os(CRASH_ENV)
        && v == name
    {
        crate::note!("{CRASH_ENV}={name}: aborting here (crash test)");
        std::process::abort();
    }
}

/// A fresh, empty folder in the temp dir for a test's (or a tool's)
/// scratch files: removed with everything in it when dropped, kept when
/// the thread is panicking (a failed test's files stay to be looked at;
/// its path is in the failure's message). The test suites used to leave
/// every folder behind (670 after a day of runs).
#[derive(Debug)]
pub struct ScratchDir(PathBuf);

impl ScratchDir {
    /// `name` under the temp dir, emptied first if a run before left it.
    /// Panics if it cannot be made (for tests).
    pub fn new(name: &str) -> Self {
        let d = std::env::temp_dir().join(name);
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap_or_else(|e| panic!("creating {}: {e}", d.display()));
        Self(d)
    }
}

impl std::ops::Deref for ScratchDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for ScratchDir {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<std::ffi::OsStr> for ScratchDir {
    fn as_ref(&self) -> &std::ffi::OsStr {
        self.0.as_os_str()
    }
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// Bytes of memory the system can still give this process: the least of
/// Linux' `MemAvailable`, the room left under the memory limit of each
/// control group the process is in (a container's limit: `MemAvailable`
/// counts the whole host's memory), and the room left in its address space
/// limit (`ulimit -v`). `None` where none of these can be read.
pub fn available_memory() -> Option<u64> {
    let read = |p: &Path| std::fs::read_to_string(p).ok();
    let mut least = read(Path::new("/proc/meminfo")).and_then(|t| meminfo_available(&t));
    if let Some(groups) = read(Path::new("/proc/self/cgroup")) {
        for dir in cgroup_memory_dirs(&groups) {
            // Every ancestor's limit applies too.
            let mut d = dir.as_path();
            loop {
                let room = cgroup_room(
                    read(&d.join("memory.max")).or_else(|| read(&d.join("memory.limit_in_bytes"))),
                    read(&d.join("memory.current"))
                        .or_else(|| read(&d.join("memory.usage_in_bytes"))),
                    read(&d.join("memory.stat")),
                );
                least = min_known(least, room);
                match d.parent() {
                    Some(parent) if parent.starts_with("/sys/fs/cgroup") && parent != d => {
                        d = parent
                    }
                    _ => break,
                }
            }
        }
    }
    if let (Some(limits), Some(status)) = (
        read(Path::new("/proc/self/limits")),
        read(Path::new("/proc/self/status")),
    ) {
        least = min_known(least, address_space_room(&limits, &status));
    }
    least
}

fn min_known(a: Option<u64>, b: Option<u64>) -> Option<u64> {
    match (a, b) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// `MemAvailable` of `/proc/meminfo`'s text, in bytes.
fn meminfo_available(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// The memory control groups' folders named by `/proc/self/cgroup`'s text:
/// version 2's `0::/path` under `/sys/fs/cgroup`, version 1's
/// `N:memory:/path` under `/sys/fs/cgroup/memory`.
fn cgroup_memory_dirs(cgroup: &str) -> Vec<PathBuf> {
    let root = Path::new("/sys/fs/cgroup");
    cgroup
        .lines()
        .filter_map(|l| {
            let mut parts = l.splitn(3, ':');
            let (_, controllers, path) = (parts.next()?, parts.next()?, parts.next()?);
            let rel = path.trim_start_matches('/');
            if rel.split('/').any(|c| c == "..") {
                return None;
            }
            match controllers {
                "" => Some(root.join(rel)),
                c if c.split(',').any(|c| c == "memory") => Some(root.join("memory").join(rel)),
                _ => None,
            }
        })
        .collect()
}

/// The room under a control group's limit (`memory.max` or
/// `memory.limit_in_bytes`) given its usage, less the inactive file cache
/// its `memory.stat` counts (the kernel reclaims it when needed, and a
/// container that reads files sits near its limit with it: the working set
/// as the kubelet computes it); `None` without a limit ("max", or version
/// 1's near-2^63 "unlimited") or where limit or usage cannot be read.
fn cgroup_room(limit: Option<String>, usage: Option<String>, stat: Option<String>) -> Option<u64> {
    let limit: u64 = limit?.trim().parse().ok()?;
    if limit >= 1 << 62 {
        return None;
    }
    let usage: u64 = usage?.trim().parse().ok()?;
    // Version 2 says `inactive_file`, version 1 `total_inactive_file`
    // (with the group's descendants) beside its own `inactive_file`.
    let inactive = |key: &str| {
        stat.as_deref()?.lines().find_map(|l| {
            let mut parts = l.split_whitespace();
            (parts.next()? == key)
                .then(|| parts.next()?.parse::<u64>().ok())
                .flatten()
        })
    };
    let cache = inactive("total_inactive_file")
        .or_else(|| inactive("inactive_file"))
        .unwrap_or(0);
    Some(limit.saturating_sub(usage.saturating_sub(cache)))
}

/// The room left under the address space limit (`/proc/self/limits`'
/// "Max address space", soft) given the process' size (`/proc/self/status`'
/// `VmSize`); `None` when unlimited or unreadable.
fn address_space_room(limits: &str, status: &str) -> Option<u64> {
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max address space"))?;
    let soft: u64 = line
        .trim_start_matches("Max address space")
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    let size = status.lines().find(|l| l.starts_with("VmSize:"))?;
    let kib: u64 = size.split_whitespace().nth(1)?.parse().ok()?;
    Some(soft.saturating_sub(kib.saturating_mul(1024)))
}

/// A byte count for people: `512 B`, `1.50 KiB`, `16.04 MiB`, `8.00 GiB`.
pub fn format_bytes(b: u64) -> String {
    const KIB: f64 = 1024.0;
    let x = b as f64;
    if x >= KIB * KIB * KIB {
        format!("{:.2} GiB", x / (KIB * KIB * KIB))
    } else if x >= KIB * KIB {
        format!("{:.2} MiB", x / (KIB * KIB))
    } else if x >= KIB {
        format!("{:.2} KiB", x / KIB)
    } else {
        format!("{b} B")
    }
}

/// A rate for people: `12.3 steps/s`, `4.56 k rays/s`, `0.229 M samples/s`
/// (three significant digits; M from 100,000 on, as the summaries print).
pub fn format_rate(per_second: f64, unit: &str) -> String {
    let x = if per_second.is_finite() {
        per_second.max(0.0)
    } else {
        0.0
    };
    if x >= 1e5 {
        format!("{:.3} M {unit}/s", x / 1e6)
    } else if x >= 1e3 {
        format!("{:.2} k {unit}/s", x / 1e3)
    } else if x >= 10.0 {
        format!("{x:.1} {unit}/s")
    } else {
        format!("{x:.2} {unit}/s")
    }
}

/// An indicatif style from `template`, where `{rate}` prints the bar's
/// rate with [`format_rate`] in `unit`s.
pub fn progress_style(template: &str, unit: &'static str) -> indicatif::ProgressStyle {
    indicatif::ProgressStyle::with_template(template)
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .with_key(
            "rate",
            move |s: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                let _ = w.write_str(&format_rate(s.per_sec(), unit));
            },
        )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn temporary_names_of_long_outputs_fit_the_file_system() {
        let long = "x".repeat(254) + ".exr";
        let t = temp_path(&Path::new("/tmp").join(&long));
        let name = t.file_name().unwrap().to_string_lossy().into_owned();
        assert!(
            name.len() <= 255 && name.starts_with('.') && name.ends_with(".tmp"),
            "{name}"
        );
        let other = temp_path(&Path::new("/tmp").join("x".repeat(254) + ".png"));
        assert_ne!(t, other);
        let short = temp_path(Path::new("/tmp/out.exr"));
        assert_eq!(
            short.file_name().unwrap().to_string_lossy(),
            format!(".out.exr.{}.tmp", std::process::id())
        );
        let dir = scratch("long-name");
        let p = dir.join("é".repeat(120) + ".txt");
        write_atomic(&p, b"ok").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"ok");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn printable_escapes_control_characters_but_newlines_and_tabs() {
        assert!(matches!(
            printable("plain \"knot\"\n\tnext"),
            std::borrow::Cow::Borrowed(_)
        ));
        assert_eq!(printable("a\u{1b}[31mred\u{7}"), "a\\u{1b}[31mred\\u{7}");
        assert_eq!(printable("\u{9b}x"), "\\u{9b}x");
    }

    /// A 20 MB name in a message keeps its ends; words up to the longest
    /// path stay whole, and so does everything around the long word.
    #[test]
    fn printable_shortens_only_words_longer_than_any_path() {
        let path = "/d".repeat(2048);
        assert!(matches!(printable(&path), std::borrow::Cow::Borrowed(_)));
        let name = format!("a{}z", "\u{e9}".repeat(20_000_000));
        let msg = format!("unknown mesh \"x\" (defined: \"{name}\")\n\tnext");
        let shown = printable(&msg);
        assert!(shown.len() < 2 * PRINTED_WORD_MAX + 100, "{}", shown.len());
        assert!(shown.starts_with("unknown mesh \"x\" (defined: \"a\u{e9}"));
        assert!(
            shown.ends_with("\u{e9}z\")\n\tnext"),
            "{}",
            &shown[shown.len() - 20..]
        );
        assert!(
            shown.contains("...[19995845 characters left out]..."),
            "{shown:.300}"
        );
        // Escaped control characters count as what is printed.
        let bells = "\u{7}".repeat(1000);
        let shown = printable(&bells);
        assert!(
            shown.contains("...[840 characters left out]..."),
            "{shown:.100}"
        );
        assert!(
            shown.chars().count() < PRINTED_WORD_MAX,
            "{}",
            shown.chars().count()
        );
    }

    fn scratch(name: &str) -> ScratchDir {
        ScratchDir::new(&format!("nppp-files-{}-{name}", std::process::id()))
    }

    #[test]
    fn atomic_write_replaces_and_leaves_no_temp() {
        let d = scratch("atomic");
        let p = d.join("a.txt");
        std::fs::write(&p, b"old").unwrap();
        write_atomic(&p, b"new").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new");
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 1);
    }

    #[test]
    fn dropped_writer_keeps_the_old_file() {
        let d = scratch("dropped");
        let p = d.join("a.txt");
        std::fs::write(&p, b"old").unwrap();
        {
            let mut f = AtomicFile::create(&p).unwrap();
            f.write_all(b"half").unwrap();
        }
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 1);
    }

    /// `commit_new` puts a file where none is, and where one appeared while
    /// it was written (another run finishing first) leaves that one as it
    /// was and keeps its own data beside it, saying where.
    #[test]
    fn commit_new_never_replaces_a_file_that_appeared() {
        let d = scratch("commit-new");
        let p = d.join("data.nppd");
        let mut f = AtomicFile::create(&p).unwrap();
        f.write_all(b"first").unwrap();
        f.commit_new().unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"first");

        let mut f = AtomicFile::create(&p).unwrap();
        f.write_all(b"second").unwrap();
        let e = f.commit_new().unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::AlreadyExists);
        assert_eq!(std::fs::read(&p).unwrap(), b"first");
        let kept = d.join(format!("data.{}.nppd", std::process::id()));
        assert!(e.to_string().contains(&kept.display().to_string()), "{e}");
        assert_eq!(std::fs::read(&kept).unwrap(), b"second");
        // Nothing else: no temporary file left.
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 2);
        assert!(pending().iter().all(|t| !t.starts_with(&*d)));
    }

    /// Output folders a run made are removed when it ends without writing
    /// into them; folders that hold a file, and folders that were there
    /// before, stay.
    #[test]
    fn only_new_empty_output_folders_are_removed() {
        let d = scratch("new-dirs");
        create_output_dir(&d.join("a/b/c")).unwrap();
        create_output_dir(&d.join("a/kept")).unwrap();
        std::fs::write(d.join("a/kept/out.exr"), b"x").unwrap();
        create_parent(&d.join("e/f.nppd")).unwrap();
        // Already there: nothing to remember.
        create_output_dir(&d).unwrap();
        assert!(d.join("a/b/c").is_dir() && d.join("e").is_dir());
        remove_new_empty_dirs();
        assert!(!d.join("a/b").exists());
        assert!(!d.join("e").exists());
        assert_eq!(std::fs::read(d.join("a/kept/out.exr")).unwrap(), b"x");
        assert!(d.is_dir());
        // A folder made by a later run of the function, after the first
        // clean-up, is that run's.
        create_output_dir(&d.join("g")).unwrap();
        remove_new_empty_dirs();
        assert!(!d.join("g").exists() && d.is_dir());
    }

    /// An output under a link whose target is missing, or a loop of links,
    /// is refused before any work, naming the link (a render ran to its
    /// end, then failed with "File exists").
    #[cfg(unix)]
    #[test]
    fn outputs_under_a_dangling_link_are_refused_up_front() {
        let d = scratch("dangling");
        std::os::unix::fs::symlink(d.join("gone"), d.join("dang")).unwrap();
        std::os::unix::fs::symlink(d.join("loop"), d.join("loop")).unwrap();
        for link in ["dang", "loop"] {
            for out in [d.join(link).join("a.exr"), d.join(link).join("x/a.exr")] {
                let e = check_writable(&out).unwrap_err();
                assert!(e.contains(link) && e.contains("symbolic link"), "{e}");
                let e = create_parent(&out).unwrap_err().to_string();
                assert!(e.contains(link) && e.contains("symbolic link"), "{e}");
            }
        }
        assert!(!d.join("gone").exists());
    }

    #[test]
    fn failed_path_writer_keeps_the_old_file() {
        let d = scratch("via-path");
        let p = d.join("a.exr");
        std::fs::write(&p, b"old").unwrap();
        let r = write_atomic_via_path(&p, |tmp| {
            std::fs::write(tmp, b"half").map_err(|e| e.to_string())?;
            Err::<(), _>("encoder failed".to_string())
        });
        assert!(r.is_err());
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 1);
    }

    #[test]
    fn same_file_sees_through_spellings_and_links() {
        let d = scratch("same");
        let a = d.join("data.nppd");
        std::fs::write(&a, b"x").unwrap();
        std::fs::create_dir_all(d.join("sub")).unwrap();
        assert!(same_file(&a, &d.join("sub/../data.nppd")));
        assert!(same_file(&a, &d.join("./data.nppd")));
        let link = d.join("hard.nppd");
        std::fs::hard_link(&a, &link).unwrap();
        assert!(same_file(&a, &link));
        #[cfg(unix)]
        {
            let sym = d.join("sym.nppd");
            std::os::unix::fs::symlink(&a, &sym).unwrap();
            assert!(same_file(&sym, &a));
        }
        assert!(!same_file(&a, &d.join("other.nppd")));
        // A file about to be created, spelled two ways, through a folder
        // that does not exist yet.
        assert!(same_file(&d.join("new/x.exr"), &d.join("sub/../new/x.exr")));
        assert!(same_file(
            &d.join("data.nppd"),
            &d.join("missing/../data.nppd")
        ));
        assert!(same_file(&d.join("a/b/../../data.nppd"), &a));
        let e =
            ensure_not_input("--out", &d.join("sub/../data.nppd"), &[("--data", &a)]).unwrap_err();
        assert!(e.contains("--out") && e.contains("--data"), "{e}");
    }

    #[test]
    fn inside() {
        let d = scratch("inside");
        std::fs::create_dir_all(d.join("m/checkpoint")).unwrap();
        assert!(is_inside(&d.join("m/checkpoint/x.nppp"), &d.join("m")));
        assert!(is_inside(
            &d.join("m/../m/checkpoint"),
            &d.join("m/checkpoint")
        ));
        assert!(!is_inside(&d.join("mm/x"), &d.join("m")));
    }

    #[test]
    fn rates_are_formatted() {
        assert_eq!(format_rate(229_100.587_1, "samples"), "0.229 M samples/s");
        assert_eq!(format_rate(4560.0, "rays"), "4.56 k rays/s");
        assert_eq!(format_rate(12.34, "steps"), "12.3 steps/s");
        assert_eq!(format_rate(0.5, "steps"), "0.50 steps/s");
        assert_eq!(format_rate(f64::NAN, "steps"), "0.00 steps/s");
    }

    #[test]
    fn bytes_are_formatted() {
        assert_eq!(format_bytes(512), "512 B");
        assert_eq!(format_bytes(1536), "1.50 KiB");
        assert_eq!(format_bytes(207 << 20), "207.00 MiB");
        assert_eq!(format_bytes(8 << 30), "8.00 GiB");
    }

    #[test]
    fn memory_is_known_on_linux() {
        if cfg!(target_os = "linux") {
            assert!(available_memory().unwrap() > 1 << 20);
        }
    }

    /// Each source of the available memory is read from its text, and the
    /// least one counts: a container's limit below the host's free memory,
    /// `ulimit -v`.
    #[test]
    fn available_memory_takes_the_tightest_limit() {
        assert_eq!(
            meminfo_available("MemTotal: 100 kB\nMemAvailable:    2048 kB\n"),
            Some(2 << 20)
        );
        assert_eq!(meminfo_available("MemTotal: 100 kB\n"), None);
        let dirs = cgroup_memory_dirs(
            "12:pids:/a\n4:memory:/process_api/x\n0::/user.slice/s\n3:cpu,memory:/b\n1:memory:/../etc\n",
        );
        let want: Vec<PathBuf> = [
            "/sys/fs/cgroup/memory/process_api/x",
            "/sys/fs/cgroup/user.slice/s",
            "/sys/fs/cgroup/memory/b",
        ]
        .iter()
        .map(PathBuf::from)
        .collect();
        assert_eq!(dirs, want);
        assert_eq!(
            cgroup_room(Some("max\n".into()), Some("5\n".into()), None),
            None
        );
        assert_eq!(
            cgroup_room(Some("9223372036854771712\n".into()), Some("5".into()), None),
            None
        );
        assert_eq!(
            cgroup_room(Some("1000\n".into()), Some("300\n".into()), None),
            Some(700)
        );
        assert_eq!(
            cgroup_room(Some("1000".into()), Some("3000".into()), None),
            Some(0)
        );
        assert_eq!(cgroup_room(Some("1000".into()), None, None), None);
        // A group at its limit with file cache the kernel can drop still has
        // that cache's room (v2, then v1 with its hierarchy's total).
        let v2 = "anon 100\nfile 900\nactive_file 200\ninactive_file 700\n";
        assert_eq!(
            cgroup_room(Some("1000".into()), Some("1000".into()), Some(v2.into())),
            Some(700)
        );
        let v1 = "cache 900\ninactive_file 5\ntotal_cache 900\ntotal_inactive_file 650\n";
        assert_eq!(
            cgroup_room(Some("1000".into()), Some("990".into()), Some(v1.into())),
            Some(660)
        );
        assert_eq!(
            cgroup_room(Some("1000".into()), Some("100".into()), Some(v2.into())),
            Some(1000)
        );
        assert_eq!(
            cgroup_room(
                Some("1000".into()),
                Some("990".into()),
                Some("garbage".into())
            ),
            Some(10)
        );
        let limits = "Limit                     Soft Limit           Hard Limit           Units\n\
                      Max address space         1073741824           unlimited            bytes\n";
        assert_eq!(
            address_space_room(limits, "Name: nppp\nVmSize:\t  262144 kB\n"),
            Some(768 << 20)
        );
        let unlimited =
            "Max address space         unlimited            unlimited            bytes\n";
        assert_eq!(address_space_room(unlimited, "VmSize: 1 kB\n"), None);
        assert_eq!(min_known(Some(3), Some(2)), Some(2));
        assert_eq!(min_known(None, Some(2)), Some(2));
        assert_eq!(min_known(None, None), None);
    }
}
