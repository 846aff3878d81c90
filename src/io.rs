//! Input and output the Unix way: `-` is stdin/stdout, files are replaced atomically, and
//! binary data is never sprayed onto a terminal.

use anyhow::{bail, Context, Result};
use std::io::{IsTerminal, Read, Write};
use std::path::Path;

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

/// Writes `bytes` to `path` atomically: a temporary file in the same folder is written, flushed
/// and renamed over the target, so a failed run never leaves a partial file and never clobbers
/// a good one.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let shown = path.display();
    // Outputs are ordinary files: readable by others, like any file a shell redirect makes
    // (tempfile's default of 0600 would otherwise survive the rename).
    #[cfg(unix)]
    let permissions = {
        use std::os::unix::fs::PermissionsExt;
        std::fs::Permissions::from_mode(0o644)
    };
    let mut builder = tempfile::Builder::new();
    #[cfg(unix)]
    builder.permissions(permissions);
    let mut tmp = builder
        .prefix(".colf-tmp-")
        .tempfile_in(dir)
        .with_context(|| {
            format!(
                "{shown}: cannot create a temporary file in {}",
                dir.display()
            )
        })?;
    tmp.write_all(bytes)
        .and_then(|_| tmp.as_file().sync_all())
        .with_context(|| format!("{shown}: write failed"))?;
    tmp.persist(path)
        .map_err(|e| e.error)
        .with_context(|| format!("{shown}: cannot replace the file"))?;
    Ok(())
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
