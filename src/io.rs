//! Input and output the Unix way: `-` is stdin/stdout, files are replaced atomically, and
//! binary data is never sprayed onto a terminal.

use anyhow::{bail, Context, Result};
use std::io::{IsTerminal, Read, Write};
use std::path::{Path, PathBuf};

/// True when `path` names stdin or stdout.
pub fn is_stdio(path: &str) -> bool {
    path == "-"
}

/// A human name for an input or output path, used in error messages.
pub fn display_name(path: &str) -> &str {
    if is_stdio(path) {
        "<stdin/stdout>"
    } else {
        path
    }
}

/// Reads a whole input: a file, or stdin for `-`. Refuses to read binary data from a terminal
/// when `binary` is set (a user who forgot the input would otherwise see a hung program).
pub fn read_input(path: &str, binary: bool) -> Result<Vec<u8>> {
    if is_stdio(path) {
        let stdin = std::io::stdin();
        if binary && stdin.is_terminal() {
            bail!("<stdin>: refusing to read binary data from a terminal (give a file or pipe one in)");
        }
        let mut bytes = Vec::new();
        stdin
            .lock()
            .read_to_end(&mut bytes)
            .context("<stdin>: read failed")?;
        Ok(bytes)
    } else {
        std::fs::read(path).with_context(|| format!("{path}: cannot read"))
    }
}

/// Temporary files being written right now, removed by the signal thread on SIGINT/SIGTERM. The
/// lock is held while a temporary file is created and registered, and while one is renamed
/// into place and unregistered, so the signal thread (which exits holding it) sees every
/// temporary file that exists and never one that has become an output.
static LIVE_TEMPS: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

fn live_temps() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    LIVE_TEMPS
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// A temporary file in the registry: dropping it (a failed write) deletes it and unregisters it.
struct LiveTemp {
    file: Option<tempfile::NamedTempFile>,
}

impl LiveTemp {
    fn create(builder: &tempfile::Builder, dir: &Path) -> std::io::Result<LiveTemp> {
        let mut live = live_temps();
        let file = builder.tempfile_in(dir)?;
        live.push(file.path().to_path_buf());
        Ok(LiveTemp { file: Some(file) })
    }

    fn file(&mut self) -> &mut std::fs::File {
        self.file
            .as_mut()
            .expect("present until persisted")
            .as_file_mut()
    }

    /// Renames the file to `target` and unregisters it.
    fn persist(mut self, target: &Path) -> std::io::Result<()> {
        let mut live = live_temps();
        let file = self.file.take().expect("present until persisted");
        let tmp_path = file.path().to_path_buf();
        live.retain(|p| *p != tmp_path);
        // On failure the returned file is dropped here, deleting it.
        file.persist(target).map(drop).map_err(|e| e.error)
    }
}

impl Drop for LiveTemp {
    fn drop(&mut self) {
        if let Some(file) = self.file.take() {
            let mut live = live_temps();
            let tmp_path = file.path().to_path_buf();
            drop(file);
            live.retain(|p| *p != tmp_path);
        }
    }
}

/// The signal a stage was interrupted by (`colf::cli::run` exits with 128 + the signal).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Interrupted {
    pub signal: i32,
}

impl Interrupted {
    /// The exit status of a process stopped by this signal: 130 for SIGINT, 143 for SIGTERM.
    pub fn exit_code(&self) -> i32 {
        128 + self.signal
    }

    fn signal_name(&self) -> &'static str {
        match self.signal {
            signal_hook::consts::SIGINT => "SIGINT",
            signal_hook::consts::SIGTERM => "SIGTERM",
            _ => "a signal",
        }
    }
}

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "interrupted by {}", self.signal_name())
    }
}

impl std::error::Error for Interrupted {}

/// Set while a stage stops by itself on a signal (see [`defer_signals`]).
static DEFERRED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
/// Set by the first signal while deferred: the stage's stop flag.
static STOP: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
/// The signal that set [`STOP`] (0: none).
static PENDING: std::sync::atomic::AtomicI32 = std::sync::atomic::AtomicI32::new(0);

/// Starts (once per process) the thread that handles SIGINT and SIGTERM for stage
/// `colf-<stage>`: it deletes every temporary file of [`write_atomic`] still being written,
/// prints `colf-<stage>: interrupted by SIG…` and exits with 128 + the signal (130, 143), so an
/// interrupted stage leaves no partial or temporary file and every finished output intact.
pub fn install_signal_cleanup(stage: &str) -> Result<()> {
    use std::sync::atomic::Ordering;
    static INSTALLED: std::sync::OnceLock<()> = std::sync::OnceLock::new();
    if INSTALLED.get().is_some() {
        return Ok(());
    }
    let mut signals = signal_hook::iterator::Signals::new([
        signal_hook::consts::SIGINT,
        signal_hook::consts::SIGTERM,
    ])
    .context("cannot install the signal handlers")?;
    // Set by the signal handler itself, at delivery: the main thread can tell that the signal
    // thread is about to end the process (see [`exiting_on_signal`]).
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, std::sync::Arc::clone(signalled()))
            .context("cannot install the signal handlers")?;
    }
    let stage = stage.to_string();
    std::thread::Builder::new()
        .name("colf-signals".into())
        .spawn(move || {
            for signal in signals.forever() {
                // A deferring stage stops at its next safe point; a second signal stops at once.
                if DEFERRED.load(Ordering::SeqCst) && !STOP.swap(true, Ordering::SeqCst) {
                    PENDING.store(signal, Ordering::SeqCst);
                    continue;
                }
                let live = live_temps();
                for path in live.iter() {
                    let _ = std::fs::remove_file(path);
                }
                let interrupted = Interrupted { signal };
                eprintln!("colf-{stage}: {interrupted}");
                // Exits holding the lock: no temporary file can be created or renamed now.
                std::process::exit(interrupted.exit_code());
            }
        })
        .context("cannot start the signal thread")?;
    let _ = INSTALLED.set(());
    Ok(())
}

fn signalled() -> &'static std::sync::Arc<std::sync::atomic::AtomicBool> {
    static SIGNALLED: std::sync::OnceLock<std::sync::Arc<std::sync::atomic::AtomicBool>> =
        std::sync::OnceLock::new();
    SIGNALLED.get_or_init(Default::default)
}

/// True once SIGINT or SIGTERM has arrived in a stage that does not defer them: the signal
/// thread is removing temporary files and will exit. An error the interruption caused (a
/// closed stdin, say) must then not be reported as the stage's own.
pub fn exiting_on_signal() -> bool {
    use std::sync::atomic::Ordering;
    signalled().load(Ordering::SeqCst) && !DEFERRED.load(Ordering::SeqCst)
}

/// From now on the first SIGINT/SIGTERM only sets the returned flag (a stage that checkpoints
/// before it stops, like `colf-train`); [`pending_signal`] then says which signal came. A
/// second signal still stops at once, removing temporary files.
pub fn defer_signals() -> &'static std::sync::atomic::AtomicBool {
    DEFERRED.store(true, std::sync::atomic::Ordering::SeqCst);
    &STOP
}

/// The signal that set [`defer_signals`]'s flag, if one came.
pub fn pending_signal() -> Option<Interrupted> {
    match PENDING.load(std::sync::atomic::Ordering::SeqCst) {
        0 => None,
        signal => Some(Interrupted { signal }),
    }
}

/// An output file being written (see [`write_atomic_with`] for the rules): a temporary file
/// beside a regular file, renamed over it by [`AtomicOutput::commit`]; dropped uncommitted, it
/// is deleted and the old file kept. A device or FIFO is written through.
pub struct AtomicOutput {
    shown: String,
    target: PathBuf,
    sink: Sink,
}

/// Whether an output path's existing link or special file is followed.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Follow {
    /// A file the user named: links to regular files and special files are written through.
    UserNamed,
    /// A file the stage names inside its output folder: replaced, never followed.
    Never,
}

enum Sink {
    Temp(LiveTemp, std::io::BufWriter<std::fs::File>),
    Through(std::io::BufWriter<std::fs::File>),
}

impl AtomicOutput {
    /// Opens `path`, a file the user named (`-o FILE`), for writing: a link to a regular file
    /// has its target replaced, and a device or FIFO is written through, as a shell redirect
    /// would (see [`write_atomic_with`]).
    pub fn create(path: &Path) -> Result<AtomicOutput> {
        Self::open(path, Follow::UserNamed)
    }

    /// Opens `path`, a file a stage names itself inside its output folder (a frame, a mask,
    /// a scene file, a checkpoint), for writing: whatever is at `path` — a link, a device, a
    /// FIFO — is replaced by a regular file at commit, never opened or followed, so nothing is
    /// written outside the folder (see [`write_in_folder`]).
    pub fn create_in_folder(path: &Path) -> Result<AtomicOutput> {
        Self::open(path, Follow::Never)
    }

    fn open(path: &Path, follow: Follow) -> Result<AtomicOutput> {
        let shown = path.display().to_string();
        let buffered = |file: std::fs::File| std::io::BufWriter::with_capacity(1 << 16, file);
        let existing = match follow {
            Follow::UserNamed => std::fs::metadata(path).ok(),
            // Renamed over whatever is there; nothing at the path is ever opened.
            Follow::Never => None,
        };
        let target = match existing {
            Some(meta) if !meta.is_file() => {
                let file = std::fs::OpenOptions::new()
                    .write(true)
                    .open(path)
                    .with_context(|| format!("{shown}: cannot open for writing"))?;
                return Ok(AtomicOutput {
                    shown,
                    target: path.to_path_buf(),
                    sink: Sink::Through(buffered(file)),
                });
            }
            Some(_) if path.is_symlink() => std::fs::canonicalize(path)
                .with_context(|| format!("{shown}: cannot resolve the link"))?,
            _ => path.to_path_buf(),
        };
        let dir = match target.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        // Outputs are ordinary files: readable by others, like any file a shell redirect makes
        // (tempfile's default of 0600 would otherwise survive the rename).
        let mut builder = tempfile::Builder::new();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            builder.permissions(std::fs::Permissions::from_mode(0o644));
        }
        builder.prefix(".colf-tmp-");
        let mut tmp = LiveTemp::create(&builder, &dir).with_context(|| {
            format!(
                "{shown}: cannot create a temporary file in {}",
                dir.display()
            )
        })?;
        let file = tmp
            .file()
            .try_clone()
            .with_context(|| format!("{shown}: cannot create a temporary file"))?;
        Ok(AtomicOutput {
            shown,
            target,
            sink: Sink::Temp(tmp, buffered(file)),
        })
    }

    /// Flushes and syncs the file and renames it over the target (a device: flushes).
    pub fn commit(self) -> Result<()> {
        let shown = self.shown;
        match self.sink {
            Sink::Through(mut w) => w.flush().with_context(|| format!("{shown}: write failed")),
            Sink::Temp(tmp, w) => {
                let file = w
                    .into_inner()
                    .map_err(|e| e.into_error())
                    .with_context(|| format!("{shown}: write failed"))?;
                file.sync_all()
                    .with_context(|| format!("{shown}: write failed"))?;
                drop(file);
                tmp.persist(&self.target)
                    .with_context(|| format!("{shown}: cannot replace the file"))
            }
        }
    }
}

impl Write for AtomicOutput {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match &mut self.sink {
            Sink::Temp(_, w) | Sink::Through(w) => w.write(buf),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match &mut self.sink {
            Sink::Temp(_, w) | Sink::Through(w) => w.flush(),
        }
    }
}

/// Writes `bytes` to `path`; see [`write_atomic_with`].
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes).map_err(Into::into))
}

/// Writes an output file the user named (`-o FILE`, `colf-train --out MODEL`) with `write`,
/// which streams its bytes to the writer it is given. (Files a stage names itself inside an
/// output folder go through [`write_in_folder`] instead, which never follows a link.)
///
/// A regular file (or a missing one) is written atomically: a temporary file in the same
/// folder is written, flushed and renamed over the target, so a failed or interrupted run never
/// leaves a partial file and never clobbers a good one (a symbolic link to a regular file is
/// kept, and its target replaced). Anything else that exists (`/dev/null`, `/dev/full`, a FIFO,
/// a terminal) is written through, opened for writing as a shell redirect would: renaming over
/// it would replace a device or a pipe with a regular file.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> Result<()>,
) -> Result<()> {
    let mut out = AtomicOutput::create(path)?;
    write(&mut out).with_context(|| format!("{}: write failed", path.display()))?;
    out.commit()
}

/// Writes `bytes` to `path`, a file a stage names itself inside an output folder (frames,
/// masks, EXRs, scene files, checkpoints, kept snapshots): atomically, like [`write_atomic`],
/// but whatever is at `path` is replaced by the new regular file and never followed, so a link
/// planted there (`out/frame_0000.png -> ../victim.png`) is replaced and its target untouched.
pub fn write_in_folder(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut out = AtomicOutput::create_in_folder(path)?;
    out.write_all(bytes)
        .with_context(|| format!("{}: write failed", path.display()))?;
    out.commit()
}

/// Makes the folder `path`, which a stage names itself inside its output folder (colf-synth's
/// `scene_NNNNN`), with its missing parents: a link found at `path` is removed and a real
/// folder made in its place, so files written into it stay inside the output folder.
pub fn create_folder_in_folder(path: &Path) -> Result<()> {
    let shown = path.display();
    if std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink()) {
        std::fs::remove_file(path).with_context(|| format!("{shown}: cannot replace the link"))?;
    }
    std::fs::create_dir_all(path).with_context(|| format!("{shown}: cannot create the folder"))?;
    // create_dir_all accepts a link that appeared in between; a real folder is required.
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.is_dir() => Ok(()),
        _ => bail!("{shown}: is not a folder (a link or a file appeared in its place)"),
    }
}

/// Opens `path`, a log a stage names itself beside its output, for appending: a link or
/// special file found there is removed first (a fresh log is started), and the file is opened
/// without following links, so appending never writes through a planted link.
pub fn open_log_in_folder(path: &Path) -> Result<std::fs::File> {
    let shown = path.display();
    if std::fs::symlink_metadata(path).is_ok_and(|m| !m.is_file()) {
        std::fs::remove_file(path)
            .with_context(|| format!("{shown}: cannot replace it with a regular file"))?;
    }
    let mut options = std::fs::OpenOptions::new();
    options.create(true).append(true);
    open_no_follow(&mut options, path).with_context(|| format!("{shown}: cannot open the log"))
}

/// Opens `path` with `options` without following a link at `path` itself (a planted link is an
/// error, not a way to write elsewhere).
pub fn open_no_follow(
    options: &mut std::fs::OpenOptions,
    path: &Path,
) -> std::io::Result<std::fs::File> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NOFOLLOW);
    }
    options.open(path)
}

/// Checks, before a long run, that [`write_atomic`] will be able to write `path`: it is not a
/// folder, and a temporary file can be made beside it (then removed).
pub fn check_writable(path: &Path) -> Result<()> {
    let shown = path.display();
    if path.is_dir() {
        bail!("{shown}: is a folder, not a file to write");
    }
    if std::fs::metadata(path).is_ok_and(|m| !m.is_file()) {
        return Ok(()); // a device or FIFO: written through
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut builder = tempfile::Builder::new();
    builder.prefix(".colf-tmp-");
    LiveTemp::create(&builder, dir)
        .map(drop)
        .with_context(|| format!("{shown}: cannot write in {}", dir.display()))
}

/// Writes a stage's output: stdout for `-` (refused when stdout is a terminal and the data is
/// binary), else an atomic file write.
pub fn write_output(path: &str, bytes: &[u8], binary: bool) -> Result<()> {
    if is_stdio(path) {
        let stdout = std::io::stdout();
        if binary && stdout.is_terminal() {
            bail!("refusing to write binary data to a terminal (use -o FILE or a pipe)");
        }
        let mut lock = stdout.lock();
        match lock.write_all(bytes).and_then(|_| lock.flush()) {
            Ok(()) => Ok(()),
            // A closed pipe (`| head`) is the reader's choice, not our error.
            Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
            Err(e) => Err(e).context("<stdout>: write failed"),
        }
    } else {
        write_atomic(Path::new(path), bytes)
    }
}

/// Parses a JSON document, naming the file and the line/column of a syntax error.
pub fn parse_json<T: serde::de::DeserializeOwned>(bytes: &[u8], name: &str) -> Result<T> {
    serde_json::from_slice(bytes).map_err(|e| anyhow::anyhow!("{name}: invalid JSON: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_and_leaves_no_temp_files() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("out.bin");
        write_atomic(&target, b"first").unwrap();
        write_atomic(&target, b"second").unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"second");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1, "temporary files were left behind");
    }

    #[cfg(unix)]
    #[test]
    fn atomic_write_makes_a_world_readable_file() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("out.bin");
        write_atomic(&target, b"x").unwrap();
        let mode = std::fs::metadata(&target).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o644);
    }

    fn file_type(path: &Path) -> std::fs::FileType {
        std::fs::symlink_metadata(path).unwrap().file_type()
    }

    /// Special files are written through, never replaced: a FIFO keeps its reader and stays a
    /// FIFO, /dev/full reports "no space", /dev/null stays a character device. The FIFO, in a
    /// temporary folder, is checked first, so wrong logic fails before it could touch /dev.
    #[cfg(unix)]
    #[test]
    fn special_files_are_written_through_not_replaced() {
        use std::os::unix::fs::FileTypeExt;
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe");
        let c_path = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        assert_eq!(unsafe { libc::mkfifo(c_path.as_ptr(), 0o644) }, 0);
        let reader = {
            let fifo = fifo.clone();
            std::thread::spawn(move || std::fs::read(fifo).unwrap())
        };
        write_atomic(&fifo, b"through the pipe").unwrap();
        assert_eq!(reader.join().unwrap(), b"through the pipe");
        assert!(file_type(&fifo).is_fifo(), "the FIFO was replaced");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

        let err = write_atomic(Path::new("/dev/full"), b"x").unwrap_err();
        let msg = format!("{err:#}");
        assert!(msg.starts_with("/dev/full: write failed"), "{msg}");
        assert!(msg.contains("No space left"), "{msg}");
        write_atomic(Path::new("/dev/null"), b"x").unwrap();
        assert!(file_type(Path::new("/dev/null")).is_char_device());
        assert!(file_type(Path::new("/dev/full")).is_char_device());
    }

    #[cfg(unix)]
    #[test]
    fn a_link_to_a_regular_file_stays_a_link() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("real.bin");
        let link = dir.path().join("link.bin");
        std::fs::write(&target, b"old").unwrap();
        std::os::unix::fs::symlink(&target, &link).unwrap();
        write_atomic(&link, b"new").unwrap();
        assert!(file_type(&link).is_symlink());
        assert_eq!(std::fs::read(&target).unwrap(), b"new");
    }

    /// Issue 38: a file a stage names inside its output folder replaces a planted link (to a
    /// file, to a missing file, to a folder) or FIFO, and never writes the link's target.
    #[cfg(unix)]
    #[test]
    fn files_named_in_a_folder_replace_links_and_never_follow_them() {
        let dir = tempfile::tempdir().unwrap();
        let victim = dir.path().join("victim.png");
        std::fs::write(&victim, b"victim").unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        let targets = [
            victim.clone(),
            dir.path().join("missing.png"),
            dir.path().to_path_buf(),
        ];
        for (i, target) in targets.iter().enumerate() {
            let link = out.join(format!("frame_{i}.png"));
            std::os::unix::fs::symlink(target, &link).unwrap();
            write_in_folder(&link, b"frame").unwrap();
            assert!(
                file_type(&link).is_file(),
                "{} still a link",
                link.display()
            );
            assert_eq!(std::fs::read(&link).unwrap(), b"frame");
        }
        let fifo = out.join("fifo.png");
        let c_path = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        assert_eq!(unsafe { libc::mkfifo(c_path.as_ptr(), 0o644) }, 0);
        write_in_folder(&fifo, b"frame").unwrap();
        assert!(file_type(&fifo).is_file());
        assert_eq!(std::fs::read(&victim).unwrap(), b"victim");
        assert!(!dir.path().join("missing.png").exists());
        assert_eq!(
            std::fs::read_dir(&out).unwrap().count(),
            4,
            "temporary files left"
        );

        // A planted link to a folder where a stage makes its own folder is replaced too, and a
        // planted link where it appends a log: the log starts afresh, the victim untouched.
        let elsewhere = dir.path().join("elsewhere");
        std::fs::create_dir(&elsewhere).unwrap();
        let scene = out.join("scene_00000");
        std::os::unix::fs::symlink(&elsewhere, &scene).unwrap();
        create_folder_in_folder(&scene).unwrap();
        assert!(file_type(&scene).is_dir());
        create_folder_in_folder(&scene).unwrap();
        let log = out.join("m.log.jsonl");
        std::os::unix::fs::symlink(&victim, &log).unwrap();
        writeln!(open_log_in_folder(&log).unwrap(), "line").unwrap();
        writeln!(open_log_in_folder(&log).unwrap(), "more").unwrap();
        assert!(file_type(&log).is_file());
        assert_eq!(std::fs::read(&log).unwrap(), b"line\nmore\n");
        assert_eq!(std::fs::read(&victim).unwrap(), b"victim");
        assert_eq!(std::fs::read_dir(&elsewhere).unwrap().count(), 0);
    }

    #[test]
    fn failed_streamed_writes_leave_nothing_and_keep_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("out.bin");
        std::fs::write(&target, b"good").unwrap();
        let err = write_atomic_with(&target, |w| {
            w.write_all(b"half")?;
            bail!("encoder failed")
        })
        .unwrap_err();
        assert!(format!("{err:#}").contains("encoder failed"));
        assert_eq!(std::fs::read(&target).unwrap(), b"good");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        assert!(!live_temps().iter().any(|p| p.starts_with(dir.path())));
    }

    #[test]
    fn writability_is_checked_up_front() {
        let dir = tempfile::tempdir().unwrap();
        assert!(check_writable(&dir.path().join("out.bin")).is_ok());
        assert!(check_writable(dir.path()).is_err());
        let msg = format!(
            "{:#}",
            check_writable(&dir.path().join("no/such/out.bin")).unwrap_err()
        );
        assert!(msg.contains("no/such/out.bin: cannot write"), "{msg}");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn atomic_write_into_missing_folder_fails_cleanly() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("no/such/dir/out.bin");
        let err = write_atomic(&target, b"x").unwrap_err();
        assert!(format!("{err:#}").contains("out.bin"));
    }

    #[test]
    fn read_input_names_the_missing_file() {
        let err = read_input("/no/such/file.json", false).unwrap_err();
        assert!(format!("{err:#}").contains("/no/such/file.json"));
    }

    #[test]
    fn json_errors_name_the_file_and_position() {
        let err = parse_json::<serde_json::Value>(b"{\"a\": ", "edits.json").unwrap_err();
        let msg = format!("{err:#}");
        assert!(msg.starts_with("edits.json: invalid JSON"), "{msg}");
        assert!(msg.contains("line 1"), "{msg}");
    }
}
