//! Deterministic safetensors writing and checked reading, shared by codes files and model
//! checkpoints.
//!
//! The `safetensors` crate keeps `__metadata__` in a `HashMap`, so two runs can write the same
//! content in different byte orders; colf promises byte-identical outputs for identical inputs,
//! so the (simple) format is written here with sorted keys: an 8-byte little-endian header
//! length, a JSON header padded with spaces to a multiple of 8, then the raw little-endian data.
//! Reading goes through the `safetensors` crate, which validates offsets and sizes.

use anyhow::{anyhow, bail, Result};
use safetensors::{Dtype, SafeTensors};
use std::collections::BTreeMap;

/// One f32 tensor to write.
pub struct F32Tensor<'a> {
    pub name: &'a str,
    pub shape: Vec<usize>,
    pub data: &'a [f32],
}

/// Serialises f32 tensors and string metadata into safetensors bytes, deterministically.
pub fn serialize_f32(tensors: &[F32Tensor], metadata: &BTreeMap<String, String>) -> Vec<u8> {
    let mut sorted: Vec<&F32Tensor> = tensors.iter().collect();
    sorted.sort_by(|a, b| a.name.cmp(b.name));
    let mut header = serde_json::Map::new();
    if !metadata.is_empty() {
        header.insert(
            "__metadata__".into(),
            serde_json::to_value(metadata).expect("string map"),
        );
    }
    let mut offset = 0usize;
    for t in &sorted {
        assert_eq!(
            t.shape.iter().product::<usize>(),
            t.data.len(),
            "tensor {} shape/data mismatch",
            t.name
        );
        let end = offset + 4 * t.data.len();
        header.insert(
            t.name.to_string(),
            serde_json::json!({"dtype": "F32", "shape": t.shape, "data_offsets": [offset, end]}),
        );
        offset = end;
    }
    // serde_json's Map is a BTreeMap here (no preserve_order feature): keys come out sorted.
    let mut header_bytes = serde_json::to_vec(&header).expect("json");
    header_bytes.resize(header_bytes.len().next_multiple_of(8), b' ');
    let mut out = Vec::with_capacity(8 + header_bytes.len() + offset);
    out.extend_from_slice(&(header_bytes.len() as u64).to_le_bytes());
    out.extend_from_slice(&header_bytes);
    for t in &sorted {
        for v in t.data {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// A parsed safetensors file with its metadata.
pub struct TensorFile<'a> {
    pub tensors: SafeTensors<'a>,
    pub metadata: BTreeMap<String, String>,
    name: String,
}

impl<'a> TensorFile<'a> {
    /// Parses safetensors bytes; `name` (the file) prefixes every error.
    pub fn parse(bytes: &'a [u8], name: &str) -> Result<TensorFile<'a>> {
        if bytes.len() < 8 {
            bail!(
                "{name}: not a safetensors file (only {} bytes)",
                bytes.len()
            );
        }
        let (_, meta) = SafeTensors::read_metadata(bytes)
            .map_err(|e| anyhow!("{name}: not a valid safetensors file ({e})"))?;
        let metadata: BTreeMap<String, String> = meta
            .metadata()
            .as_ref()
            .map(|m| m.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
            .unwrap_or_default();
        let tensors = SafeTensors::deserialize(bytes)
            .map_err(|e| anyhow!("{name}: not a valid safetensors file ({e})"))?;
        Ok(TensorFile {
            tensors,
            metadata,
            name: name.to_string(),
        })
    }

    /// The file's name, as given to `parse`.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// True when the file holds a tensor of that name.
    pub fn has(&self, tensor: &str) -> bool {
        self.tensors.names().contains(&tensor)
    }

    /// A metadata value, or an error naming the missing key.
    pub fn require_metadata(&self, key: &str) -> Result<&str> {
        self.metadata
            .get(key)
            .map(String::as_str)
            .ok_or_else(|| anyhow!("{}: metadata key `{key}` is missing", self.name))
    }

    /// Reads an F32 tensor, checking its shape with `expected` (`None` = any size on that axis)
    /// and that every value is finite. Returns (shape, values).
    pub fn f32_tensor(
        &self,
        tensor: &str,
        expected: &[Option<usize>],
    ) -> Result<(Vec<usize>, Vec<f32>)> {
        let name = &self.name;
        let view = self
            .tensors
            .tensor(tensor)
            .map_err(|_| anyhow!("{name}: tensor `{tensor}` is missing"))?;
        if view.dtype() != Dtype::F32 {
            bail!(
                "{name}: tensor `{tensor}` has dtype {:?}, expected F32",
                view.dtype()
            );
        }
        let shape = view.shape().to_vec();
        let shape_ok = shape.len() == expected.len()
            && shape
                .iter()
                .zip(expected)
                .all(|(&s, e)| e.is_none_or(|e| e == s));
        if !shape_ok {
            let want: Vec<String> = expected
                .iter()
                .map(|e| e.map_or("*".to_string(), |v| v.to_string()))
                .collect();
            bail!(
                "{name}: tensor `{tensor}` has shape {shape:?}, expected [{}]",
                want.join(", ")
            );
        }
        let values: Vec<f32> = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            bail!("{name}: tensor `{tensor}` has a non-finite value at flat index {i}");
        }
        Ok((shape, values))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_determinism() {
        let a = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0];
        let b: [f32; 0] = [];
        let mut meta = BTreeMap::new();
        for k in ["zeta", "alpha", "format", "model"] {
            meta.insert(k.to_string(), format!("value of {k}"));
        }
        let tensors = [
            F32Tensor {
                name: "b",
                shape: vec![0, 4],
                data: &b,
            },
            F32Tensor {
                name: "a",
                shape: vec![2, 3],
                data: &a,
            },
        ];
        let bytes = serialize_f32(&tensors, &meta);
        assert_eq!(bytes, serialize_f32(&tensors, &meta.clone()));
        assert_eq!((bytes.len() - 8) % 4, 0);
        let file = TensorFile::parse(&bytes, "t.safetensors").unwrap();
        assert_eq!(file.metadata, meta);
        let (shape, values) = file.f32_tensor("a", &[Some(2), None]).unwrap();
        assert_eq!((shape, values), (vec![2, 3], a.to_vec()));
        let (shape, values) = file.f32_tensor("b", &[None, Some(4)]).unwrap();
        assert_eq!((shape, values.len()), (vec![0, 4], 0));
        let err = file.f32_tensor("a", &[Some(3), None]).unwrap_err();
        assert!(format!("{err}").contains("shape [2, 3], expected [3, *]"));
        assert!(file.f32_tensor("c", &[None]).is_err());
    }

    #[test]
    fn truncated_and_garbage_files_are_errors() {
        let a = [1.0f32; 8];
        let bytes = serialize_f32(
            &[F32Tensor {
                name: "a",
                shape: vec![8],
                data: &a,
            }],
            &BTreeMap::new(),
        );
        for cut in [0, 5, 8, 20, bytes.len() - 1] {
            let err = TensorFile::parse(&bytes[..cut], "cut.safetensors")
                .err()
                .expect("truncated file must fail");
            assert!(format!("{err}").starts_with("cut.safetensors: "));
        }
        assert!(TensorFile::parse(b"hello world, not a tensor file", "g").is_err());
    }

    #[test]
    fn non_finite_values_are_rejected() {
        let a = [1.0f32, f32::NAN];
        let bytes = serialize_f32(
            &[F32Tensor {
                name: "a",
                shape: vec![2],
                data: &a,
            }],
            &BTreeMap::new(),
        );
        let file = TensorFile::parse(&bytes, "n").unwrap();
        let err = file.f32_tensor("a", &[None]).unwrap_err();
        assert!(format!("{err}").contains("non-finite"));
    }
}
