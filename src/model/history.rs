//! How a model was trained: the `training` metadata of a model file, one record per training
//! run, oldest first (a curriculum's stages, or a model fine-tuned from another: `--init` copies
//! the initial model's records and appends its own).
//!
//! The records describe; they are not part of the model's identity (the weights and config
//! are), so older files, which have none, keep their identities, and `colf-train info` prints
//! `"training": null` for them — except the bundled `supervised` model, whose runs are written
//! down from its recipe in `bundled_records.json` and recognised by its identity. Whether a run read ground-truth masks is recorded as
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
    /// How a wider `slot_dim` among the overrides was filled, when not by copies (`fresh`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slot_values: Option<crate::model::grow::SlotValues>,
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
    /// The views each scene encoded together (`--context-views`); not written when empty (one
    /// random view).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub context_views: Vec<usize>,
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
    /// The mask losses counted unsure proposal pixels within this many pixels of an instance
    /// to it (`--mask-claim`); not written when 0.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub mask_claim: usize,
    pub mask_shadow_depth: f64,
    pub seed: u64,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
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

/// Whether any run used masks: `Some(true)` if one did; `Some(false)` only if none did and the
/// records reach back to a fresh model; `None` (unknown) for a model with no records, or one
/// whose first recorded run started from a model that has none ([`unrecorded_init`]).
pub fn masks_used(runs: &[TrainingRun]) -> Option<bool> {
    if runs.iter().any(|r| r.masks_used) {
        Some(true)
    } else if runs.is_empty() || unrecorded_init(runs).is_some() {
        None
    } else {
        Some(false)
    }
}

/// The identity of the model the first recorded run started from, when it has one: that
/// model's own training is not in the records (a file written before colf-train recorded
/// training, or a `colf-train init` model).
pub fn unrecorded_init(runs: &[TrainingRun]) -> Option<&str> {
    runs.first().and_then(|r| r.init.as_deref())
}

/// Records of the bundled models whose files predate training records, keyed by identity
/// (`bundled_records.json`: the `supervised` model's runs, written down from its recipe).
/// Records are not part of a model's identity, so a file's identity says which model it is.
const BUNDLED_RECORDS: &str = include_str!("bundled_records.json");

#[derive(Deserialize)]
struct BundledRecord {
    identity: String,
    /// Each a [`TrainingRun`] with a `reconstructed` note saying where it came from.
    runs: Vec<serde_json::Value>,
}

/// The written-down records of the bundled model `identity` (each with its `reconstructed`
/// note), if it is one whose file predates training records.
pub fn bundled_records(identity: &str) -> Option<Vec<serde_json::Value>> {
    let table: Vec<BundledRecord> =
        serde_json::from_str(BUNDLED_RECORDS).expect("bundled_records.json is valid");
    table
        .into_iter()
        .find(|r| r.identity == identity)
        .map(|r| r.runs)
}

/// A model's training history as far as it is known: the file's records, preceded by the
/// written-down records of a bundled model they start from (or that the file is), as JSON
/// values (written-down runs carry their `reconstructed` note) and as parsed runs.
pub fn known_history(
    own: &[TrainingRun],
    identity: &str,
) -> Result<(Vec<serde_json::Value>, Vec<TrainingRun>)> {
    let mut values: Vec<serde_json::Value> = own
        .iter()
        .map(serde_json::to_value)
        .collect::<Result<_, _>>()?;
    let mut runs = own.to_vec();
    // Each step reaches one model further back; a bundled chain is a few models long.
    for _ in 0..8 {
        let start = match runs.first() {
            Some(first) => first.init.clone(),
            None => Some(identity.to_string()),
        };
        let Some(earlier) = start.as_deref().and_then(bundled_records) else {
            break;
        };
        let parsed = earlier
            .iter()
            .map(|v| serde_json::from_value::<TrainingRun>(v.clone()))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| anyhow!("bundled_records.json: {e}"))?;
        values.splice(0..0, earlier);
        runs.splice(0..0, parsed);
    }
    Ok((values, runs))
}

/// What `colf-train info` prints of a model read from `file`: identity, size, config and
/// training records (`null` when nothing is known), completed by the written-down records of
/// the bundled models ([`known_history`]); `unrecorded_init` names the model the first known
/// run started from when its training is not known, and `masks_used` is then `null` unless a
/// known run used masks.
pub fn describe(model: &super::Colf, file: &str) -> Result<serde_json::Value> {
    let identity = model.identity()?;
    let (values, runs) = known_history(model.training(), &identity)?;
    Ok(serde_json::json!({
        "file": file,
        "identity": identity,
        "parameters": model.num_parameters(),
        "config": model.config(),
        "training": (!values.is_empty()).then_some(values),
        "unrecorded_init": unrecorded_init(&runs),
        "masks_used": masks_used(&runs),
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
            slot_values: None,
            frozen: vec!["encoder.".into()],
            lr_scale: vec![("hypernet_bg.fc1.".into(), 20.0)],
            steps: 10,
            planned_steps: 20,
            batch: 4,
            views: 2,
            context_views: vec![0, 1],
            rays: 512,
            lr: 5e-5,
            warmup: 100,
            decay_from: None,
            final_lr: None,
            losses: BTreeMap::from([("l2".into(), 1.0), ("latent".into(), 1e-4)]),
            object_fraction: 0.0,
            mask_margin: 0,
            mask_claim: 0,
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
        assert_eq!(masks_used(&[]), None);
        // A run without learning-rate factors is written as before they existed.
        let plain = TrainingRun {
            lr_scale: vec![],
            context_views: vec![],
            ..run()
        };
        assert!(!to_json(std::slice::from_ref(&plain)).contains("lr_scale"));
        // Nor, with one random input view, as before context views existed.
        assert!(!to_json(&[plain]).contains("context_views"));
    }

    /// Issue 38: a history whose first run starts from a model with no records cannot say
    /// that no masks were used; one that reaches a fresh model can.
    #[test]
    fn masks_used_is_unknown_when_the_first_run_starts_from_an_unrecorded_model() {
        let from_unrecorded = run();
        assert_eq!(
            unrecorded_init(std::slice::from_ref(&from_unrecorded)),
            Some("c1fd4506bf2ce4e6")
        );
        assert_eq!(masks_used(std::slice::from_ref(&from_unrecorded)), None);
        let fresh = TrainingRun {
            init: None,
            preset: Some("small".into()),
            ..run()
        };
        assert_eq!(unrecorded_init(std::slice::from_ref(&fresh)), None);
        assert_eq!(
            masks_used(&[fresh.clone(), from_unrecorded.clone()]),
            Some(false)
        );
        let supervised = TrainingRun {
            masks_used: true,
            ..from_unrecorded
        };
        assert_eq!(masks_used(&[supervised]), Some(true));
    }

    /// The bundled `supervised` model's written-down records parse, reach a fresh model, used
    /// masks and end in the run that started from stage 5; a history starting from it is
    /// completed with them, and an unknown start is left as it is.
    #[test]
    fn bundled_records_complete_the_supervised_chain() {
        let (values, runs) = known_history(&[], "c1fd4506bf2ce4e6").unwrap();
        assert_eq!(runs.len(), 6);
        assert_eq!(values.len(), 6);
        assert!(values.iter().all(|v| v["reconstructed"].is_string()));
        assert_eq!(runs[0].preset.as_deref(), Some("small"));
        assert_eq!(unrecorded_init(&runs), None);
        assert_eq!(masks_used(&runs), Some(true));
        assert_eq!(runs[5].init.as_deref(), Some("03efe939d096181c"));
        assert_eq!(runs.iter().map(|r| r.steps).sum::<u64>(), 102_250);

        let blender = run(); // starts from c1fd4506bf2ce4e6, used no masks
        let (values, runs) =
            known_history(std::slice::from_ref(&blender), "9d08eb4992c38067").unwrap();
        assert_eq!(runs.len(), 7);
        assert_eq!(runs[6], blender);
        assert!(values[6].get("reconstructed").is_none());
        assert_eq!(masks_used(&runs), Some(true));

        let unknown = TrainingRun {
            init: Some("0123456789abcdef".into()),
            ..run()
        };
        let (_, runs) = known_history(std::slice::from_ref(&unknown), "x").unwrap();
        assert_eq!(runs, vec![unknown]);
        assert_eq!(known_history(&[], "x").unwrap().1, vec![]);
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
