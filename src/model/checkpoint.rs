//! The model file: safetensors, every parameter an F32 tensor (or F16: a model written with
//! half-precision storage, `colf-train configure --half`) under its module path (see
//! `docs/model.md`), and `__metadata__`:
//! - `format` = `colf-model/1`;
//! - `config` = the [`Config`] as JSON;
//! - `identity` = the first 16 hex digits of sha256 over the format, the config JSON and every
//!   tensor (sorted by name: name, shape, little-endian f32 bytes of the values as read, so
//!   F16 tensors count as their exact f32 widening). Codes files record it, and
//!   `colf-render` refuses codes of another model;
//! - `training` (optional) = how the model was trained, a JSON list of runs
//!   ([`super::history`]); descriptive, so not part of the identity.
//!
//! Written deterministically (sorted keys, `crate::tensorfile`), so `colf-train init --seed S`
//! is byte-reproducible. Reading validates the format, the config, that every value is finite
//! and that the stored identity matches the contents; names and shapes are checked against the
//! model the config describes when the model is built (`Colf::from_bytes`).

use super::config::Config;
use super::history::{self, TrainingRun};
use crate::tensorfile::{round_to_f16, serialize, F32Tensor, Stored, TensorFile};
use anyhow::{anyhow, bail, Result};
use candle_core::{Device, Tensor};
use sha2::{Digest, Sha256};
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// The `format` metadata value of a model file.
pub const FORMAT: &str = "colf-model/1";

/// Parameters by name, flattened to host vectors with their shapes.
pub type HostParams = BTreeMap<String, (Vec<usize>, Vec<f32>)>;

/// Copies tensors to host vectors.
pub fn to_host(params: &BTreeMap<String, Tensor>) -> Result<HostParams> {
    params
        .iter()
        .map(|(name, t)| {
            let data = t.flatten_all()?.to_vec1::<f32>()?;
            Ok((name.clone(), (t.dims().to_vec(), data)))
        })
        .collect()
}

/// The model identity: 16 hex digits of sha256(format, config JSON, tensors by name).
pub fn identity(config_json: &str, params: &HostParams) -> String {
    let mut hasher = Sha256::new();
    hasher.update(FORMAT.as_bytes());
    hasher.update([0u8]);
    hasher.update(config_json.as_bytes());
    hasher.update([0u8]);
    for (name, (shape, data)) in params {
        hasher.update(name.as_bytes());
        hasher.update([0u8]);
        hasher.update((shape.len() as u64).to_le_bytes());
        for d in shape {
            hasher.update((*d as u64).to_le_bytes());
        }
        let mut bytes = Vec::with_capacity(4 * data.len());
        for v in data {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        hasher.update(&bytes);
    }
    let digest = hasher.finalize();
    digest[..8].iter().map(|b| format!("{b:02x}")).collect()
}

/// Serialises a model and its training records, the parameters named in `half` in half
/// precision; returns (bytes, identity). The identity is that of the values as they will be
/// read (the half ones rounded).
pub fn to_bytes(
    cfg: &Config,
    params: &HostParams,
    training: &[TrainingRun],
    half: &BTreeSet<String>,
) -> (Vec<u8>, String) {
    let rounded: HostParams;
    let params = if half.is_empty() {
        params
    } else {
        rounded = params
            .iter()
            .map(|(name, (shape, data))| {
                let data = if half.contains(name) {
                    data.iter().map(|&v| round_to_f16(v)).collect()
                } else {
                    data.clone()
                };
                (name.clone(), (shape.clone(), data))
            })
            .collect();
        &rounded
    };
    let config_json = cfg.to_json();
    let id = identity(&config_json, params);
    let mut metadata = BTreeMap::new();
    metadata.insert("format".to_string(), FORMAT.to_string());
    metadata.insert("config".to_string(), config_json);
    metadata.insert("identity".to_string(), id.clone());
    if !training.is_empty() {
        metadata.insert(
            history::METADATA_KEY.to_string(),
            history::to_json(training),
        );
    }
    let tensors: Vec<F32Tensor> = params
        .iter()
        .map(|(name, (shape, data))| F32Tensor {
            name,
            shape: shape.clone(),
            data,
        })
        .collect();
    let stored = |name: &str| {
        if half.contains(name) {
            Stored::F16
        } else {
            Stored::F32
        }
    };
    (serialize(&tensors, stored, &metadata), id)
}

/// A parsed model file: config, tensors and identity (names and shapes not yet checked
/// against the config).
pub struct Checkpoint {
    pub config: Config,
    pub tensors: HashMap<String, Tensor>,
    pub identity: String,
    /// How it was trained (empty when the file does not say).
    pub training: Vec<TrainingRun>,
    /// The tensors stored in half precision.
    pub half: BTreeSet<String>,
}

/// Parses and validates model-file bytes; `name` (the file) starts every error.
pub fn from_bytes(bytes: &[u8], name: &str) -> Result<Checkpoint> {
    let file = TensorFile::parse(bytes, name)?;
    let format = file.require_metadata("format")?;
    if format != FORMAT {
        bail!("{name}: not a colf model (format `{format}`, expected `{FORMAT}`)");
    }
    let config_json = file.require_metadata("config")?;
    let config = Config::from_json(config_json).map_err(|e| anyhow!("{name}: {e:#}"))?;
    let stored_id = file.require_metadata("identity")?.to_string();
    let training = history::from_metadata(&file.metadata, name)?;
    let mut host = HostParams::new();
    let mut half = BTreeSet::new();
    for tensor in file.tensors.names() {
        let rank = file
            .tensors
            .tensor(tensor)
            .map_err(|e| anyhow!("{name}: tensor `{tensor}`: {e}"))?
            .shape()
            .len();
        let (shape, data, stored) = file.f32_or_f16_tensor(tensor, &vec![None; rank])?;
        if stored == Stored::F16 {
            half.insert(tensor.to_string());
        }
        host.insert(tensor.to_string(), (shape, data));
    }
    let id = identity(config_json, &host);
    if id != stored_id {
        bail!("{name}: model identity {stored_id} does not match the file's contents ({id}); the file is damaged or was edited");
    }
    let tensors = host
        .into_iter()
        .map(|(n, (shape, data))| Ok((n, Tensor::from_vec(data, shape, &Device::Cpu)?)))
        .collect::<Result<HashMap<_, _>>>()?;
    Ok(Checkpoint {
        config,
        tensors,
        identity: id,
        training,
        half,
    })
}
