//! How a model was trained: the `training` metadata of a model file, one record per training
//! run, oldest first (a curriculum's stages, or a model fine-tuned from another: `--init` copies
//! the initial model's records and appends its own).
//!
//! The records describe; they are not part of the model's identity (the weights and config
//! are), so older files, which have none, keep their identities, and `colf-train info` prints
//! `"training": null` for them. Whether a run read ground-truth masks is recorded as
//! `masks_used`: true when a loss or the ray sampling used them. A dataset's masks may still be
//! read to report FG-ARI in the training log; `masks_in_data` says whether there were any.

use anyhow::{anyhow, bail, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The metadata key of the records in a model file.
pub const METADATA_KEY: &str = "training";

/// Most records a file may hold (a curriculum has a handful; this bounds a damaged file).
pub const MAX_RUNS: usize = 10_000;

/// One training run.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct TrainingRun {
    /// The training data folder, as given to `colf-train --data`.
    pub data: String,
    /// The renderer of the data (`analytic`, `blender`) when its `dataset.json` says.
    #[serde(default)]
    pub engine: Option<String>,
    /// Training scenes used.
    pub scenes: usize,
    /// Whether the training scenes' mask files were read: some were there and the run did not
    /// skip them (`--proposals` never opens them).
    pub masks_in_data: bool,
    /// Whether a loss or the ray sampling used ground-truth masks.
    pub masks_used: bool,
    /// Whether a loss or the ray sampling used object proposals computed from the images
    /// (`--proposals`; no labels).
    #[serde(default)]
    pub proposals: bool,
    /// The identity of the model the run started from (`--init` or a grown model); none for a
    /// fresh model.
    #[serde(default)]
    pub init: Option<String>,
    /// The size preset of a fresh model.
    #[serde(default)]
    pub preset: Option<String>,
    /// Config overrides (`--set`) the run applied.
    #[serde(default)]
    pub config_overrides: Vec<String>,
    /// Prefixes of the parameters the run kept fixed (`--freeze`).
    #[serde(default)]
    pub frozen: Vec<String>,
    /// Learning-rate factors as (parameter-name prefix, factor) in the order applied, a later
    /// one winning where prefixes overlap (`--lr-scale`); not written when empty.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub lr_scale: Vec<(String, f64)>,
    /// Optimisation steps the model file has had from this run: the run started at step 0.
    pub steps: u64,
    /// The run's planned total (`--steps`).
    pub planned_steps: u64,
    pub batch: usize,
    pub views: usize,
    pub rays: usize,
    pub lr: f64,
    pub warmup: u64,
    #[serde(default)]
    pub decay_from: Option<u64>,
    #[serde(default)]
    pub final_lr: Option<f64>,
    /// Loss weights by term (`l2` is always 1).
    pub losses: BTreeMap<String, f64>,
    pub object_fraction: f64,
    pub mask_margin: usize,
    pub mask_shadow_depth: f64,
    pub seed: u64,
}

/// Parses the `training` metadata of `name`. (Numbers past f64, such as `1e999`, are refused by
/// the JSON reader, so every number read is finite.)
pub fn parse(json: &str, name: &str) -> Result<Vec<TrainingRun>> {
    let runs: Vec<TrainingRun> = serde_json::from_str(json)
        .map_err(|e| anyhow!("{name}: training metadata is not a list of training runs: {e}"))?;
    if runs.len() > MAX_RUNS {
        bail!(
            "{name}: training metadata lists {} runs (at most {MAX_RUNS})",
            runs.len()
        );
    }
    Ok(runs)
}

/// The records in a safetensors file's metadata (model file or checkpoint); none if it has
/// no `training` key.
pub fn from_metadata(metadata: &BTreeMap<String, String>, name: &str) -> Result<Vec<TrainingRun>> {
    match metadata.get(METADATA_KEY) {
        Some(json) => parse(json, name),
        None => Ok(Vec::new()),
    }
}

/// The metadata value of `runs` (compact JSON; empty histories are not written).
pub fn to_json(runs: &[TrainingRun]) -> String {
    serde_json::to_string(runs).expect("training records serialise")
}

/// Whether any run used masks; `None` for a model with no records.
pub fn masks_used(runs: &[TrainingRun]) -> Option<bool> {
    (!runs.is_empty()).then(|| runs.iter().any(|r| r.masks_used))
}

/// What `colf-train info` prints of a model read from `file`: identity, size, config and
/// training records (`null` when the file has none).
pub fn describe(model: &super::Colf, file: &str) -> Result<serde_json::Value> {
    let runs = model.training();
    Ok(serde_json::json!({
        "file": file,
        "identity": model.identity()?,
        "parameters": model.num_parameters(),
        "config": model.config(),
        "training": (!runs.is_empty()).then_some(runs),
        "masks_used": masks_used(runs),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run() -> TrainingRun {
        TrainingRun {
            data: "data/train".into(),
            engine: Some("blender".into()),
            scenes: 3,
            masks_in_data: false,
            masks_used: false,
            proposals: true,
            init: Some("c1fd4506bf2ce4e6".into()),
            preset: None,
            config_overrides: vec![],
            frozen: vec!["encoder.".into()],
            lr_scale: vec![("hypernet_bg.fc1.".into(), 20.0)],
            steps: 10,
            planned_steps: 20,
            batch: 4,
            views: 2,
            rays: 512,
            lr: 5e-5,
            warmup: 100,
            decay_from: None,
            final_lr: None,
            losses: BTreeMap::from([("l2".into(), 1.0), ("latent".into(), 1e-4)]),
            object_fraction: 0.0,
            mask_margin: 0,
            mask_shadow_depth: 0.0,
            seed: 0,
        }
    }

    #[test]
    fn records_round_trip() {
        let runs = vec![
            run(),
            TrainingRun {
                masks_used: true,
                ..run()
            },
        ];
        assert_eq!(parse(&to_json(&runs), "m").unwrap(), runs);
        assert_eq!(masks_used(&runs), Some(true));
        assert_eq!(masks_used(&runs[..1]), Some(false));
        assert_eq!(masks_used(&[]), None);
        // A run without learning-rate factors is written as before they existed.
        let plain = TrainingRun {
            lr_scale: vec![],
            ..run()
        };
        assert!(!to_json(&[plain]).contains("lr_scale"));
    }

    #[test]
    fn damaged_records_are_refused_naming_the_file() {
        for bad in ["{", "{}", "[1]", "[{\"data\": 3}]", "null"] {
            let e = parse(bad, "m.safetensors").unwrap_err().to_string();
            assert!(
                e.starts_with("m.safetensors: training metadata"),
                "{bad}: {e}"
            );
        }
        // A number past f64 (read as infinity, or refused by the JSON reader) is an error.
        let mut record = serde_json::to_value(vec![run()]).unwrap();
        record[0]["lr"] = serde_json::json!("LR");
        let text = record.to_string().replace("\"LR\"", "1e999");
        assert!(text.contains("\"lr\":1e999"), "{text}");
        let e = parse(&text, "m").unwrap_err().to_string();
        assert!(e.starts_with("m: training"), "{e}");
    }
}
