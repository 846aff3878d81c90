//! Which model a stage uses: `--model PATH` (or the name of a bundled model, e.g. `blender`),
//! else `$COLF_MODEL`, else the bundled default model, found beside the installed programs or
//! in the source tree.

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
    bundled_model_candidates(DEFAULT_MODEL_FILE)
}

/// The places a bundled model file `file` is looked for, in the order of
/// [`default_model_candidates`].
fn bundled_model_candidates(file: &str) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Some(dir) = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent().map(Path::to_path_buf))
    {
        out.push(dir.join("../share/colf").join(file));
    }
    out.push(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("models")
            .join(file),
    );
    out
}

/// A bundled model's name: letters, digits, `-` and `_` only (so never a path).
fn is_model_name(text: &str) -> bool {
    !text.is_empty()
        && text
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

/// The default model: `$COLF_MODEL` when set (and not empty), else the first existing
/// [`default_model_candidates`] entry.
pub fn default_model_path() -> Result<PathBuf> {
    if let Some(p) = std::env::var_os("COLF_MODEL").filter(|p| !p.is_empty()) {
        return Ok(PathBuf::from(p));
    }
    let candidates = default_model_candidates();
    first_file(&candidates).ok_or_else(|| {
        anyhow!(
            "no model given and no default model found (set COLF_MODEL or pass --model; looked in {})",
            listed(&candidates)
        )
    })
}

/// `explicit` (a `--model` argument) if given, else [`default_model_path`]. An argument that is
/// no existing file but a bare name (`blender`) names a bundled model, `NAME.safetensors`
/// where the default model is looked for.
pub fn resolve_model_path(explicit: Option<&str>) -> Result<PathBuf> {
    let Some(given) = explicit else {
        return default_model_path();
    };
    let path = PathBuf::from(given);
    if path.exists() || !is_model_name(given) {
        return Ok(path);
    }
    let candidates = bundled_model_candidates(&format!("{given}.safetensors"));
    first_file(&candidates).ok_or_else(|| {
        anyhow!(
            "{given}: no such model file, and no bundled model of that name (looked in {})",
            listed(&candidates)
        )
    })
}

/// The first of `candidates` that is a file.
fn first_file(candidates: &[PathBuf]) -> Option<PathBuf> {
    candidates.iter().find(|p| p.is_file()).cloned()
}

/// `candidates` for an error message, comma-separated.
fn listed(candidates: &[PathBuf]) -> String {
    let list: Vec<String> = candidates.iter().map(|p| p.display().to_string()).collect();
    list.join(", ")
}

/// Loads the model `explicit` (a `--model` argument) names, else the default one.
pub fn load_model(explicit: Option<&str>) -> Result<Colf> {
    Colf::load(&resolve_model_path(explicit)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bare_names_find_bundled_models_and_paths_stay_paths() {
        for name in ["default", "blender"] {
            let found = resolve_model_path(Some(name)).unwrap();
            assert!(found.ends_with(format!("{name}.safetensors")) && found.is_file());
        }
        // A path (or a name with a dot or slash) is taken as given, existing or not.
        for given in ["/x/m.safetensors", "m.safetensors", "models/x"] {
            assert_eq!(
                resolve_model_path(Some(given)).unwrap(),
                PathBuf::from(given)
            );
        }
        let e = resolve_model_path(Some("no-such-model"))
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("no-such-model: no such model file, and no bundled model"),
            "{e}"
        );
        assert!(!is_model_name("") && !is_model_name("a b") && is_model_name("blender_2"));
    }
}
