//! `examples/cluster/` run for real on this machine, each result compared byte for byte with one
//! process doing the same work: `parallel.sh` under GNU parallel with local job slots (and an
//! ssh-login file naming this machine), resumed after a failed job; the Slurm job arrays of
//! `slurm-submit.sh` on a one-node cluster (munged, slurmctld and slurmd started here from a
//! generated configuration in a temporary folder); and `colf-render --frames` splitting one
//! camera path across 1, 2 and 4 concurrent processes.
//!
//! GNU parallel and Slurm come from Debian's `parallel`, `slurm-wlm` and `munge` packages
//! (`.ci/run` installs them). Where a tool is missing, or the Slurm daemons cannot start (a
//! container without the privileges), its test prints one line saying so and passes.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant, SystemTime};

/// Frames of the test orbit, its image size, and frames a render job: 6 frames in chunks of 4
/// leave a short last chunk.
const FRAMES: usize = 6;
const SIZE: &str = "32";
const CHUNK: &str = "4";

fn bin_dir() -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_colf-render"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// A colf stage of this build, with no `COLF_MODEL` from the caller's environment.
fn colf(stage: &str) -> Command {
    let mut cmd = Command::new(bin_dir().join(stage));
    cmd.env_remove("COLF_MODEL");
    cmd
}

fn model() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default.safetensors")
}

fn example(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("examples/cluster")
        .join(name)
}

/// Runs `cmd`, which must succeed; returns its output.
fn ok(cmd: &mut Command) -> Output {
    let out = cmd.output().unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
    assert!(
        out.status.success(),
        "{cmd:?} failed ({}):\n{}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// Whether `program` is on PATH (or in /usr/sbin, /sbin, where Debian puts daemons).
fn find_program(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .chain(["/usr/sbin", "/sbin"].map(PathBuf::from))
        .map(|dir| dir.join(program))
        .find(|p| p.is_file())
}

/// The test images in `dir/images` (see `common::photo_folder`; their size is `SIZE`).
fn images(dir: &Path) -> (PathBuf, Vec<&'static str>) {
    common::photo_folder(dir)
}

/// What the cluster scripts must produce, made by one process at a time: each image encoded
/// by one colf-encode (`--fast`: the scripts' mechanics are tested, not the encoding) and all
/// frames of `cameras` rendered by one colf-render, into `dir/reference`.
fn reference(dir: &Path, images: &Path, names: &[&str], cameras: &Path) -> PathBuf {
    let out = dir.join("reference");
    std::fs::create_dir(&out).unwrap();
    for name in names {
        let codes = out.join(format!("{name}.codes"));
        let mut encode = colf("colf-encode");
        encode.arg(images.join(format!("{name}.png")));
        let camera = images.join(format!("{name}.json"));
        if camera.exists() {
            encode.arg("--camera").arg(camera);
        }
        ok(encode
            .arg("--fast")
            .arg("--model")
            .arg(model())
            .arg("-o")
            .arg(&codes));
        ok(colf("colf-render")
            .arg(&codes)
            .arg("--cameras")
            .arg(cameras)
            .arg("--out")
            .arg(out.join(name))
            .args(["--masks", "-q", "--model"])
            .arg(model()));
    }
    out
}

/// The visible files of `dir` (not dot files: stamps, temporary files), name → bytes.
fn visible_files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|entry| entry.unwrap())
        .filter(|entry| entry.file_type().unwrap().is_file())
        .map(|entry| entry.file_name().into_string().unwrap())
        .filter(|name| !name.starts_with('.'))
        .map(|name| (name.clone(), std::fs::read(dir.join(&name)).unwrap()))
        .collect()
}

/// Asserts that `dir` holds exactly the files of `expected`, byte for byte, and no temporary
/// file left behind.
fn same_files(expected: &Path, dir: &Path) {
    let want = visible_files(expected);
    let got = visible_files(dir);
    assert!(!want.is_empty(), "{}: empty", expected.display());
    assert_eq!(
        want.keys().collect::<Vec<_>>(),
        got.keys().collect::<Vec<_>>(),
        "{} and {} hold different files",
        expected.display(),
        dir.display()
    );
    for (name, bytes) in &want {
        assert!(
            &got[name] == bytes,
            "{}/{name} differs from {}/{name}",
            dir.display(),
            expected.display()
        );
    }
    for entry in std::fs::read_dir(dir).unwrap() {
        let name = entry.unwrap().file_name().into_string().unwrap();
        assert!(!name.starts_with(".colf-tmp-"), "{name} left in {dir:?}");
    }
}

/// Asserts that the script's outputs in `out` (codes and frame folders) are those of
/// [`reference`].
fn same_as_reference(reference: &Path, out: &Path, names: &[&str]) {
    for name in names {
        let codes = format!("{name}.codes");
        assert!(
            std::fs::read(out.join(&codes)).unwrap()
                == std::fs::read(reference.join(&codes)).unwrap(),
            "{codes} differs from one colf-encode's"
        );
        same_files(&reference.join(name), &out.join(name));
    }
}

/// Modification times of every file under `dir`.
fn mtimes(dir: &Path) -> BTreeMap<PathBuf, SystemTime> {
    let mut out = BTreeMap::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let entry = entry.unwrap();
        let path = entry.path();
        if entry.file_type().unwrap().is_dir() {
            out.extend(mtimes(&path));
        } else {
            out.insert(path, entry.metadata().unwrap().modified().unwrap());
        }
    }
    out
}

/// `examples/cluster/parallel.sh` with the test settings and `args`.
fn parallel_sh(colf_dir: &Path, args: &[&str], images: &Path, out: &Path) -> Command {
    let mut cmd = Command::new(example("parallel.sh"));
    cmd.args(args)
        .arg(images)
        .arg(out)
        .env_remove("COLF_MODEL")
        .env_remove("CAMERAS")
        .env("COLF", colf_dir)
        .env("MODEL", model())
        .env("FRAMES", FRAMES.to_string())
        .env("SIZE", SIZE)
        .env("CHUNK", CHUNK)
        .env("ENCODE_FLAGS", "--fast");
    cmd
}

/// The exit status column of every job of a GNU parallel `--joblog` (one header line).
fn joblog_statuses(path: &Path) -> Vec<String> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|line| !line.starts_with("Seq\t")) // the header
        .map(|line| line.split('\t').nth(6).unwrap().to_string())
        .collect()
}

#[test]
fn gnu_parallel_example_is_idempotent_resumable_and_byte_identical() {
    if find_program("parallel").is_none() {
        println!("gnu parallel: skipped, `parallel` is not installed (Debian package parallel)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (images, names) = images(dir.path());
    let out = dir.path().join("out");

    // Two local job slots: 2 encode jobs, then 2 images × 2 chunks of frames.
    let first = ok(&mut parallel_sh(&bin_dir(), &["-j", "2"], &images, &out));
    let stdout = text(&first.stdout);
    assert_eq!(stdout.matches("encoding on").count(), 2, "{stdout}");
    assert_eq!(stdout.matches("rendering on").count(), 4, "{stdout}");
    let cameras = out.join("orbit.json");
    let expected = reference(dir.path(), &images, &names, &cameras);
    same_as_reference(&expected, &out, &names);
    assert_eq!(joblog_statuses(&out.join("logs/encode.joblog")), ["0"; 2]);
    assert_eq!(joblog_statuses(&out.join("logs/render.joblog")), ["0"; 4]);

    // Again: every job finds its outputs newer than its inputs and does nothing.
    let before = mtimes(&out.join("alpha"));
    let again = ok(&mut parallel_sh(&bin_dir(), &["-j", "2"], &images, &out));
    let stdout = text(&again.stdout);
    assert_eq!(stdout.matches("up to date").count(), 6, "{stdout}");
    assert!(!stdout.contains(" on "), "work redone:\n{stdout}");
    assert_eq!(mtimes(&out.join("alpha")), before, "outputs rewritten");

    // A failed host: through an ssh-login file naming this machine (`2/:`, two slots), with a
    // colf-render that dies on beta's second chunk while `host-down` exists.
    let hosts = dir.path().join("hosts");
    std::fs::write(&hosts, "2/:\n").unwrap();
    let flaky = dir.path().join("flaky-bin");
    std::fs::create_dir(&flaky).unwrap();
    for stage in ["colf-encode", "colf-cameras"] {
        std::os::unix::fs::symlink(bin_dir().join(stage), flaky.join(stage)).unwrap();
    }
    let down = dir.path().join("host-down");
    let wrapper = flaky.join("colf-render");
    std::fs::write(
        &wrapper,
        format!(
            "#!/bin/sh\ncase \"$*\" in *beta*4..6*) if [ -e '{}' ]; then echo 'host down' >&2; \
             exit 255; fi;; esac\nexec '{}' \"$@\"\n",
            down.display(),
            bin_dir().join("colf-render").display()
        ),
    )
    .unwrap();
    std::fs::set_permissions(
        &wrapper,
        std::os::unix::fs::PermissionsExt::from_mode(0o755),
    )
    .unwrap();
    std::fs::write(&down, "").unwrap();
    let resumed = dir.path().join("resumed");
    let hosts_arg = hosts.to_str().unwrap();
    let failed = parallel_sh(&flaky, &["--hosts", hosts_arg], &images, &resumed)
        .output()
        .unwrap();
    assert_eq!(failed.status.code(), Some(1), "{failed:?}");
    let err = text(&failed.stderr);
    assert!(
        err.contains("parallel.sh: error: 1 render job(s) failed")
            && err.contains("run the same command again"),
        "{err}"
    );
    assert_eq!(err.matches("parallel.sh: error").count(), 1, "{err}");
    let statuses = joblog_statuses(&resumed.join("logs/render.joblog"));
    assert_eq!(
        statuses.iter().filter(|s| *s != "0").count(),
        1,
        "{statuses:?}"
    );
    assert!(!resumed.join("beta/frame_0004.png").exists());
    // The host is back: the same command redoes only the failed chunk.
    std::fs::remove_file(&down).unwrap();
    let done = ok(&mut parallel_sh(
        &flaky,
        &["--hosts", hosts_arg],
        &images,
        &resumed,
    ));
    let stdout = text(&done.stdout);
    assert_eq!(stdout.matches(" on ").count(), 1, "{stdout}");
    assert!(
        stdout.contains("beta frames 4..6: rendering on"),
        "{stdout}"
    );
    same_as_reference(&expected, &resumed, &names);

    // An image changed: only its codes and frames are made again.
    let later = SystemTime::now() + Duration::from_secs(5);
    let f = std::fs::File::options()
        .append(true)
        .open(images.join("beta.png"))
        .unwrap();
    f.set_modified(later).unwrap();
    let changed = ok(&mut parallel_sh(&bin_dir(), &["-j", "2"], &images, &out));
    let stdout = text(&changed.stdout);
    assert_eq!(stdout.matches(" on ").count(), 3, "{stdout}");
    assert!(stdout.contains("beta.codes: encoding on"), "{stdout}");
    assert!(!stdout.contains("alpha.codes: encoding"), "{stdout}");
    // The same bytes: the image's time changed, not its pixels.
    same_as_reference(&expected, &out, &names);

    // Usage errors exit 2, bad input 1, with one line.
    let usage = Command::new(example("parallel.sh")).output().unwrap();
    assert_eq!(usage.status.code(), Some(2));
    let missing = Command::new(example("parallel.sh"))
        .arg(dir.path().join("nope"))
        .arg(&out)
        .output()
        .unwrap();
    assert_eq!(missing.status.code(), Some(1));
    let err = text(&missing.stderr);
    assert!(
        err.starts_with("parallel.sh: error: ") && err.lines().count() == 1,
        "{err}"
    );
}

#[test]
fn frames_split_across_processes_are_byte_identical() {
    let dir = tempfile::tempdir().unwrap();
    let (images, _) = images(dir.path());
    let codes = dir.path().join("alpha.codes");
    ok(colf("colf-encode")
        .arg(images.join("alpha.png"))
        .arg("--camera")
        .arg(images.join("alpha.json"))
        .args(["--fast", "-o"])
        .arg(&codes));
    let cameras = dir.path().join("orbit.json");
    ok(colf("colf-cameras")
        .args(["orbit", "--frames", "8", "--size", SIZE, "-o"])
        .arg(&cameras));
    let render = |out: &Path, frames: Option<&str>, threads: Option<&str>| {
        let mut cmd = colf("colf-render");
        cmd.arg(&codes)
            .arg("--cameras")
            .arg(&cameras)
            .arg("--out")
            .arg(out)
            .args(["--masks", "--exr", "-q"]);
        if let Some(frames) = frames {
            cmd.args(["--frames", frames]);
        }
        match threads {
            Some(n) => cmd.env("RAYON_NUM_THREADS", n),
            None => cmd.env_remove("RAYON_NUM_THREADS"),
        };
        cmd.stdout(Stdio::piped()).stderr(Stdio::piped());
        cmd.spawn().unwrap()
    };
    let all = dir.path().join("all");
    let whole = render(&all, None, None).wait_with_output().unwrap();
    assert!(whole.status.success(), "{whole:?}");
    assert_eq!(visible_files(&all).len(), 8 * 3);
    // 1, 2 and 4 processes at once into one folder, one or two threads each, in every spelling
    // of --frames.
    let splits: [&[&str]; 4] = [
        &["0..8"],
        &["0..4", "4..8"],
        &["0..2", "2..4", "4..6", "6..8"],
        &["..3", "3", "4..7", "7.."],
    ];
    for (s, split) in splits.iter().enumerate() {
        let out = dir.path().join(format!("split{s}"));
        let children: Vec<Child> = split
            .iter()
            .enumerate()
            .map(|(p, frames)| render(&out, Some(frames), Some(["1", "2"][p % 2])))
            .collect();
        for child in children {
            let result = child.wait_with_output().unwrap();
            assert!(result.status.success(), "{split:?}: {result:?}");
        }
        same_files(&all, &out);
    }
}

/// A one-node Slurm cluster in a temporary folder: munged, slurmctld and slurmd, stopped (TERM,
/// then KILL) when dropped.
struct Slurm {
    dir: tempfile::TempDir,
    daemons: Vec<(&'static str, Child)>,
}

impl Slurm {
    fn conf(&self) -> PathBuf {
        self.dir.path().join("slurm.conf")
    }

    /// Sets the cluster's configuration on `cmd`.
    fn env<'a>(&self, cmd: &'a mut Command) -> &'a mut Command {
        cmd.env("SLURM_CONF", self.conf())
    }

    fn log_tail(&self, file: &str) -> String {
        let log = std::fs::read_to_string(self.dir.path().join(file)).unwrap_or_default();
        let last_error = log.lines().rev().find(|l| l.contains("error"));
        match last_error.or(log.lines().next_back()) {
            Some(line) => format!("{file}: {}", line.trim()),
            None => format!("{file} is empty"),
        }
    }

    /// Starts the daemons and waits for the node to be idle; `Err` says why it could not.
    fn start() -> Result<Slurm, String> {
        let mut programs = BTreeMap::new();
        for program in [
            "munged",
            "slurmctld",
            "slurmd",
            "sbatch",
            "scontrol",
            "sinfo",
        ] {
            let path = find_program(program).ok_or(format!("`{program}` is not installed"))?;
            programs.insert(program, path);
        }
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        let path = dir.path().to_path_buf();
        let mut slurm = Slurm {
            dir,
            daemons: Vec::new(),
        };
        use std::os::unix::fs::PermissionsExt;
        // munged wants its socket's folder searchable by all, its key private.
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755))
            .map_err(|e| e.to_string())?;
        for sub in ["state", "spool"] {
            std::fs::create_dir(path.join(sub)).map_err(|e| e.to_string())?;
        }
        let key = path.join("munge.key");
        let bytes: Vec<u8> = (0..1024u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
            .collect();
        std::fs::write(&key, bytes).map_err(|e| e.to_string())?;
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o400))
            .map_err(|e| e.to_string())?;
        let socket = path.join("munge.sock");
        let spawn = |slurm: &mut Slurm, name: &'static str, cmd: &mut Command| {
            let log = std::fs::File::create(path.join(format!("{name}.out")))
                .map_err(|e| e.to_string())?;
            let child = cmd
                .env("SLURM_CONF", path.join("slurm.conf"))
                .stdin(Stdio::null())
                .stdout(log.try_clone().map_err(|e| e.to_string())?)
                .stderr(log)
                .spawn()
                .map_err(|e| format!("{name}: {e}"))?;
            slurm.daemons.push((name, child));
            Ok::<(), String>(())
        };
        spawn(
            &mut slurm,
            "munged",
            Command::new(&programs["munged"])
                .arg("--foreground")
                .arg(format!("--key-file={}", key.display()))
                .arg(format!("--socket={}", socket.display()))
                .arg(format!("--pid-file={}", path.join("munged.pid").display()))
                .arg(format!("--log-file={}", path.join("munged.log").display()))
                .arg(format!(
                    "--seed-file={}",
                    path.join("munged.seed").display()
                )),
        )?;
        slurm.wait_for("munged", Duration::from_secs(10), || socket.exists())?;

        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map_err(|e| e.to_string())?
            .trim()
            .split('.')
            .next()
            .unwrap_or_default()
            .to_string();
        let user = text(
            &Command::new("id")
                .arg("-un")
                .output()
                .map_err(|e| e.to_string())?
                .stdout,
        )
        .trim()
        .to_string();
        let port = || {
            std::net::TcpListener::bind("127.0.0.1:0")
                .and_then(|l| l.local_addr())
                .map(|a| a.port())
                .map_err(|e| e.to_string())
        };
        let (ctld_port, slurmd_port) = (port()?, port()?);
        let p = path.display();
        // 4 CPUs whatever the machine has (config_overrides), so that the render array's tasks
        // run at once; MinJobAge 4 keeps sbatch --wait polling every 2 s.
        let conf = format!(
            "ClusterName=colftest\n\
             SlurmctldHost={host}(127.0.0.1)\n\
             SlurmctldPort={ctld_port}\n\
             SlurmdPort={slurmd_port}\n\
             SlurmUser={user}\n\
             AuthType=auth/munge\n\
             CredType=cred/munge\n\
             AuthInfo=socket={socket}\n\
             StateSaveLocation={p}/state\n\
             SlurmdSpoolDir={p}/spool\n\
             SlurmctldPidFile={p}/slurmctld.pid\n\
             SlurmdPidFile={p}/slurmd.pid\n\
             SlurmctldLogFile={p}/slurmctld.log\n\
             SlurmdLogFile={p}/slurmd.log\n\
             ProctrackType=proctrack/linuxproc\n\
             TaskPlugin=task/none\n\
             SelectType=select/cons_tres\n\
             SelectTypeParameters=CR_CPU\n\
             SchedulerType=sched/backfill\n\
             AccountingStorageType=accounting_storage/none\n\
             JobCompType=jobcomp/none\n\
             JobAcctGatherType=jobacct_gather/none\n\
             MpiDefault=none\n\
             MailProg=/bin/true\n\
             ReturnToService=2\n\
             MinJobAge=4\n\
             SlurmdParameters=config_overrides\n\
             NodeName={host} NodeAddr=127.0.0.1 CPUs=4 State=UNKNOWN\n\
             PartitionName=colftest Nodes=ALL Default=YES MaxTime=INFINITE State=UP\n",
            socket = socket.display()
        );
        std::fs::write(path.join("slurm.conf"), conf).map_err(|e| e.to_string())?;
        let conf = path.join("slurm.conf");
        spawn(
            &mut slurm,
            "slurmctld",
            Command::new(&programs["slurmctld"])
                .args(["-D", "-i", "-f"])
                .arg(&conf),
        )?;
        spawn(
            &mut slurm,
            "slurmd",
            Command::new(&programs["slurmd"])
                .args(["-D", "-f"])
                .arg(&conf)
                .args(["-N", &host]),
        )?;
        let sinfo = programs["sinfo"].clone();
        let mut state = String::new();
        slurm
            .wait_for("the node", Duration::from_secs(30), || {
                if let Ok(o) = Command::new(&sinfo)
                    .args(["-h", "-o", "%T %E"])
                    .env("SLURM_CONF", &conf)
                    .output()
                {
                    state = text(&o.stdout).trim().to_string();
                }
                state == "idle none"
            })
            .map_err(|e| format!("{e} (node state: {state})"))?;
        // Daemons that start but cannot launch a job (no privileges to) are no cluster either.
        let mut probe = Command::new(&programs["sbatch"])
            .args(["--wait", "--output=/dev/null", "--wrap", "true"])
            .env("SLURM_CONF", &conf)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| format!("sbatch: {e}"))?;
        let ran = slurm.wait_for("a trivial job", Duration::from_secs(60), || {
            matches!(probe.try_wait(), Ok(Some(_)))
        });
        if ran.is_err() {
            let _ = probe.kill();
        }
        let probe = probe.wait_with_output().map_err(|e| e.to_string())?;
        ran?;
        if !probe.status.success() {
            return Err(format!(
                "a trivial job failed ({}): {}",
                probe.status,
                text(&probe.stderr).trim()
            ));
        }
        Ok(slurm)
    }

    /// Polls `ready` until it holds; fails early, with the daemon's last log line, when a
    /// daemon exits.
    fn wait_for(
        &mut self,
        what: &str,
        limit: Duration,
        mut ready: impl FnMut() -> bool,
    ) -> Result<(), String> {
        let start = Instant::now();
        loop {
            if ready() {
                return Ok(());
            }
            let exited = self
                .daemons
                .iter_mut()
                .find_map(|(name, child)| Some((*name, child.try_wait().ok()??)));
            if let Some((name, status)) = exited {
                let log = format!("{name}.out");
                return Err(format!("{name} exited ({status}); {}", self.log_tail(&log)));
            }
            if start.elapsed() > limit {
                return Err(format!("{what} not ready after {} s", limit.as_secs()));
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

impl Drop for Slurm {
    fn drop(&mut self) {
        for (_, child) in self.daemons.iter_mut().rev() {
            let _ = Command::new("kill")
                .args(["-TERM", &child.id().to_string()])
                .status();
            let start = Instant::now();
            while matches!(child.try_wait(), Ok(None)) && start.elapsed() < Duration::from_secs(10)
            {
                std::thread::sleep(Duration::from_millis(100));
            }
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// `examples/cluster/slurm-submit.sh --wait` with the test settings on `slurm`.
fn slurm_submit(slurm: &Slurm, images: &Path, out: &Path) -> Output {
    // A bound on the wait, should the jobs never be scheduled.
    let mut cmd = Command::new("timeout");
    slurm
        .env(&mut cmd)
        .arg("300")
        .arg(example("slurm-submit.sh"))
        .arg("--wait")
        .arg(images)
        .arg(out)
        .env_remove("COLF_MODEL")
        .env_remove("CAMERAS")
        .env("COLF", bin_dir())
        .env("MODEL", model())
        .env("FRAMES", FRAMES.to_string())
        .env("SIZE", SIZE)
        .env("CHUNK", CHUNK)
        .env("ENCODE_FLAGS", "--fast")
        .output()
        .unwrap()
}

#[test]
fn slurm_arrays_on_a_one_node_cluster_match_one_process() {
    let slurm = match Slurm::start() {
        Ok(slurm) => slurm,
        Err(why) => {
            println!("slurm: skipped, a one-node cluster could not start here: {why}");
            return;
        }
    };
    let dir = tempfile::tempdir().unwrap();
    let (images, names) = images(dir.path());
    let out = dir.path().join("out");
    let submitted = slurm_submit(&slurm, &images, &out);
    let err = text(&submitted.stderr);
    assert!(
        submitted.status.success(),
        "{submitted:?}\n{}",
        slurm.log_tail("slurmctld.log")
    );
    // Array sizes from the input: 2 images; 2 chunks (4 + 2 frames) of each.
    assert!(
        err.contains("(2 tasks)") && err.contains("(4 tasks: 2 of 4 frames an image, 6 frames)"),
        "{err}"
    );
    let ids: Vec<String> = text(&submitted.stdout)
        .lines()
        .map(str::to_string)
        .collect();
    assert_eq!(ids.len(), 3, "{ids:?}");
    for task in 0..4 {
        let log = out.join(format!("logs/render_{}_{task}.log", ids[1]));
        assert!(log.is_file(), "{} missing", log.display());
    }
    let expected = reference(dir.path(), &images, &names, &out.join("orbit.json"));
    same_as_reference(&expected, &out, &names);
    // The dependent job's contact sheet: each input and its frames, as one colf-sheet makes it.
    let mut cells = Vec::new();
    for name in &names {
        cells.push(images.join(format!("{name}.png")));
        cells.extend((0..FRAMES).map(|f| expected.join(format!("{name}/frame_{f:04}.png"))));
    }
    let sheet = dir.path().join("sheet.png");
    ok(colf("colf-sheet")
        .args(["--cols", "7", "-o"])
        .arg(&sheet)
        .args(&cells));
    assert!(
        std::fs::read(out.join("sheet.png")).unwrap() == std::fs::read(&sheet).unwrap(),
        "the contact sheet differs from one colf-sheet's"
    );

    // An image that cannot be read: its encode task fails, the jobs after it are cancelled, and
    // the submit script says so in one line.
    let broken = dir.path().join("broken");
    std::fs::create_dir(&broken).unwrap();
    std::fs::write(broken.join("bad.png"), "not a png").unwrap();
    let failed = slurm_submit(&slurm, &broken, &dir.path().join("failed"));
    assert_eq!(failed.status.code(), Some(1), "{failed:?}");
    let err = text(&failed.stderr);
    let last = err.lines().last().unwrap_or_default();
    assert!(
        last.starts_with("slurm-submit.sh: error: the jobs did not complete"),
        "{err}"
    );
    assert!(!dir.path().join("failed/sheet.png").exists());
}
