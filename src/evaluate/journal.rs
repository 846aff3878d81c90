//! The journal of a long evaluation (`colf-eval --data … --journal FILE`): each scene's scores
//! appended as one JSON line as soon as the scene is done, so an evaluation stopped part way (a
//! session's end, a signal, a lost process) continues where it stopped instead of scoring its
//! scenes again. The first line says which evaluation the rows belong to (model identity, data,
//! protocol, encoding); a journal written for another evaluation is refused, never mixed in or
//! overwritten. A last line cut short by a kill is dropped and scored again.

use super::SceneScores;
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

/// The key of the header line, with the format's version as its value.
const FORMAT_KEY: &str = "colf_eval_journal";
const FORMAT_VERSION: u64 = 1;

/// One finished scene of one encoding seed's run.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JournalRow {
    /// The encoding seed of the run (`--seeds N` runs the protocol with N seeds).
    pub seed: u64,
    /// The scene's index in the data set.
    pub index: usize,
    pub scores: SceneScores,
}

/// An open journal: rows are appended and flushed one scene at a time.
pub struct Journal {
    file: std::fs::File,
    path: PathBuf,
}

impl Journal {
    /// Opens `path` for the evaluation `identity` describes (a JSON object). A missing or empty
    /// file gets the header; an existing one must start with the same header, and its rows
    /// come back in the order they were written.
    pub fn open(path: &Path, identity: &serde_json::Value) -> Result<(Journal, Vec<JournalRow>)> {
        let shown = path.display();
        let mut header = identity.clone();
        let Some(fields) = header.as_object_mut() else {
            bail!("{shown}: the journal's identity must be a JSON object");
        };
        fields.insert(FORMAT_KEY.into(), FORMAT_VERSION.into());
        if std::fs::symlink_metadata(path).is_ok_and(|m| !m.is_file()) {
            bail!("{shown}: is not a regular file, so it cannot be the journal");
        }
        let mut options = std::fs::OpenOptions::new();
        options.create(true).read(true).write(true);
        let mut file = crate::io::open_no_follow(&mut options, path)
            .with_context(|| format!("{shown}: cannot open the journal"))?;
        let mut text = String::new();
        file.read_to_string(&mut text)
            .with_context(|| format!("{shown}: cannot read the journal (not UTF-8 text?)"))?;
        let (rows, kept_bytes) = if text.is_empty() {
            let line = serde_json::to_string(&header)? + "\n";
            file.write_all(line.as_bytes())
                .and_then(|_| file.flush())
                .with_context(|| format!("{shown}: cannot write the journal"))?;
            (Vec::new(), line.len())
        } else {
            parse(&text, &header, path)?
        };
        // Cut a torn last line off, so new rows start on a line of their own.
        if kept_bytes < text.len() {
            file.set_len(kept_bytes as u64)
                .with_context(|| format!("{shown}: cannot cut the journal's torn last line"))?;
        }
        file.seek(std::io::SeekFrom::Start(kept_bytes as u64))?;
        let journal = Journal {
            file,
            path: path.to_path_buf(),
        };
        Ok((journal, rows))
    }

    /// Appends one finished scene (written and flushed before the next scene starts).
    pub fn append(&mut self, row: &JournalRow) -> Result<()> {
        let line = serde_json::to_string(row)? + "\n";
        self.file
            .write_all(line.as_bytes())
            .and_then(|_| self.file.flush())
            .with_context(|| format!("{}: cannot append to the journal", self.path.display()))
    }
}

/// The rows of a journal's `text` written for `header`, and how many bytes of it are whole
/// lines worth keeping (a last line without its newline was cut short and is dropped).
fn parse(text: &str, header: &serde_json::Value, path: &Path) -> Result<(Vec<JournalRow>, usize)> {
    let shown = path.display();
    let mut lines = text.split_inclusive('\n');
    let first = lines.next().unwrap_or_default();
    let found: serde_json::Value = match first.strip_suffix('\n').map(serde_json::from_str) {
        Some(Ok(v)) => v,
        _ => bail!("{shown}: line 1 is not a colf-eval journal's header"),
    };
    if found.get(FORMAT_KEY).is_none() {
        bail!("{shown}: line 1 is not a colf-eval journal's header");
    }
    if &found != header {
        let differs = differing_fields(&found, header);
        bail!(
            "{shown}: this journal belongs to another evaluation ({} differ{}): delete it, or give \
             another --journal",
            differs.join(", "),
            if differs.len() == 1 { "s" } else { "" }
        );
    }
    let mut rows = Vec::new();
    let mut kept = first.len();
    for (i, line) in lines.enumerate() {
        let Some(body) = line.strip_suffix('\n') else {
            break; // torn: the process was stopped while writing it
        };
        let row: JournalRow = serde_json::from_str(body)
            .with_context(|| format!("{shown}: line {} is not a journal row", i + 2))?;
        rows.push(row);
        kept += line.len();
    }
    Ok((rows, kept))
}

/// The top-level fields whose values differ between two headers, for the error message.
fn differing_fields(a: &serde_json::Value, b: &serde_json::Value) -> Vec<String> {
    let (Some(a), Some(b)) = (a.as_object(), b.as_object()) else {
        return vec!["the header".into()];
    };
    let mut keys: Vec<&String> = a.keys().chain(b.keys()).collect();
    keys.sort();
    keys.dedup();
    keys.into_iter()
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| k.to_string())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn identity(model: &str) -> serde_json::Value {
        serde_json::json!({"model": model, "data": "val", "scenes": 3})
    }

    /// Appends `bytes` to the file at `path` as another writer (a killed run, a stray edit) would.
    fn append_raw(path: &Path, bytes: &[u8]) {
        let mut f = std::fs::OpenOptions::new().append(true).open(path).unwrap();
        f.write_all(bytes).unwrap();
    }

    fn row(index: usize, psnr: f64) -> JournalRow {
        JournalRow {
            seed: 0,
            index,
            scores: SceneScores {
                scene: format!("scene_{index:05}"),
                psnr: Some(psnr),
                fg_ari: None,
                slots_used: 3,
                ..Default::default()
            },
        }
    }

    #[test]
    fn rows_come_back_exactly_after_a_reopen() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("j.jsonl");
        let (mut journal, rows) = Journal::open(&path, &identity("a")).unwrap();
        assert!(rows.is_empty());
        // A value whose shortest decimal form needs all 17 digits must come back bit for bit.
        let awkward = 0.1 + 0.2;
        journal.append(&row(0, awkward)).unwrap();
        journal.append(&row(1, 23.5)).unwrap();
        drop(journal);
        let (_, rows) = Journal::open(&path, &identity("a")).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].scores.psnr.unwrap().to_bits(), awkward.to_bits());
        assert_eq!(rows[1].index, 1);
        assert_eq!(rows[1].scores.fg_ari, None);
        assert_eq!(rows[1].scores.slots_used, 3);
    }

    #[test]
    fn a_torn_last_line_is_dropped_and_overwritten() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("j.jsonl");
        let (mut journal, _) = Journal::open(&path, &identity("a")).unwrap();
        journal.append(&row(0, 20.0)).unwrap();
        drop(journal);
        append_raw(&path, b"{\"seed\":0,\"index\":1,\"sco");
        let (mut journal, rows) = Journal::open(&path, &identity("a")).unwrap();
        assert_eq!(rows.len(), 1);
        journal.append(&row(1, 21.0)).unwrap();
        drop(journal);
        let (_, rows) = Journal::open(&path, &identity("a")).unwrap();
        assert_eq!(rows.iter().map(|r| r.index).collect::<Vec<_>>(), [0, 1]);
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(text.lines().count(), 3, "{text}");
    }

    #[test]
    fn another_evaluations_journal_is_refused_and_left_alone() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("j.jsonl");
        let (mut journal, _) = Journal::open(&path, &identity("a")).unwrap();
        journal.append(&row(0, 20.0)).unwrap();
        drop(journal);
        let before = std::fs::read(&path).unwrap();
        let err = Journal::open(&path, &identity("b"))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("another evaluation (model differs)"), "{err}");
        assert_eq!(std::fs::read(&path).unwrap(), before);
    }

    #[test]
    fn a_file_that_is_no_journal_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("notes.txt");
        std::fs::write(&path, "shopping list\n").unwrap();
        let err = Journal::open(&path, &identity("a"))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("line 1 is not a colf-eval journal"), "{err}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "shopping list\n");
        let path = dir.path().join("bad-row.jsonl");
        let (journal, _) = Journal::open(&path, &identity("a")).unwrap();
        drop(journal);
        append_raw(&path, b"[1, 2]\n");
        let err = Journal::open(&path, &identity("a"))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("line 2 is not a journal row"), "{err}");
    }
}
