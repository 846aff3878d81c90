//! Which model a stage uses: `--model PATH`, else `$COLF_MODEL`, else the bundled default model
//! found beside the installed programs or in the source tree.

use crate::model::Colf;
use anyhow::{anyhow, Result};
use std::path::{Path, PathBuf};

/// File name of the bundled default model.
pub const DEFAULT_MODEL_FILE: &str = "default.safetensors";

/// Where the bundled default model is looked for, in order:
/// 1. `<folder of the running program>/../share/colf/default.safetensors` — where
///    `make install` puts it beside `$(PREFIX)/bin`;
/// 2. `<source tree>/models/default.safetensors` (the path of the crate when it was built) —
///    a fresh clone's `target/release/colf-*` and `cargo run` find it there.
pub fn default_model_candidates() -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Some(dir) = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent().map(Path::to_path_buf))
    {
        out.push(dir.join("../share/colf").join(DEFAULT_MODEL_FILE));
    }
    out.push(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("models")
            .join(DEFAULT_MODEL_FILE),
    );
    out
}

/// The default model: `$COLF_MODEL` when set (and not empty), else the first existing
/// [`default_model_candidates`] entry.
pub fn default_model_path() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("COLF_MODEL").filter(|p| !p.is_empty()) {
        return Ok(PathBuf::from(p));
    }
    let candidates = default_model_candidates();
    candidates
        .iter()
        .find(|p| p.is_file())
        .cloned()
        .ok_or_else(|| {
            let list: Vec<String> = candidates.iter().map(|p| p.display().to_string()).collect();
            anyhow!(
                "no model given and no default model found (set COLF_MODEL or pass --model; looked in {})",
                list.join(", ")
            )
        })
}

/// `explicit` (a `--model` argument) if given, else [`default_model_path`].
pub fn resolve_model_path(explicit: Option<&str>) -> Result<PathBuf> {
    match explicit {
        Some(p) => Ok(PathBuf::from(p)),
        None => default_model_path(),
    }
}

/// Loads the model `explicit` (a `--model` argument) names, else the default one.
pub fn load_model(explicit: Option<&str>) -> Result<Colf> {
    Colf::load(&resolve_model_path(explicit)?)
}
