//! Deterministic safetensors writing and checked reading, shared by codes files and model
//! checkpoints.
//!
//! The `safetensors` crate keeps `__metadata__` in a `HashMap`, so two runs can write the same
//! content in different byte orders; colf promises byte-identical outputs for identical inputs,
//! so the (simple) format is written here with sorted keys: an 8-byte little-endian header
//! length, a JSON header padded with spaces to a multiple of 8, then the raw little-endian data.
//! Reading goes through the `safetensors` crate, which validates offsets and sizes.
//!
//! Values are F32, except that a model file may store a tensor as F16 ([`Stored::F16`]; codes
//! files are F32 only): half the bytes, and widened back to f32 exactly on reading.

use anyhow::{anyhow, bail, Result};
use safetensors::{Dtype, SafeTensors};
use std::collections::BTreeMap;

/// One f32 tensor to write.
pub struct F32Tensor<'a> {
    pub name: &'a str,
    pub shape: Vec<usize>,
    pub data: &'a [f32],
}

/// How a tensor's values are written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stored {
    F32,
    /// IEEE half precision, rounded to nearest (`half::f16::from_f32`): the caller rounds the
    /// values first ([`round_to_f16`]) when it needs to know what will be read back.
    F16,
}

impl Stored {
    fn bytes(self) -> usize {
        match self {
            Stored::F32 => 4,
            Stored::F16 => 2,
        }
    }
}

/// `v` as it reads back from an F16 tensor.
pub fn round_to_f16(v: f32) -> f32 {
    half::f16::from_f32(v).to_f32()
}

/// Serialises f32 tensors and string metadata into safetensors bytes, deterministically.
pub fn serialize_f32(tensors: &[F32Tensor], metadata: &BTreeMap<String, String>) -> Vec<u8> {
    serialize(tensors, |_| Stored::F32, metadata)
}

/// Serialises tensors, each stored as `stored(name)` says, and string metadata into
/// safetensors bytes, deterministically.
pub fn serialize(
    tensors: &[F32Tensor],
    stored: impl Fn(&str) -> Stored,
    metadata: &BTreeMap<String, String>,
) -> Vec<u8> {
    let mut sorted: Vec<(&F32Tensor, Stored)> =
        tensors.iter().map(|t| (t, stored(t.name))).collect();
    sorted.sort_by(|a, b| a.0.name.cmp(b.0.name));
    let mut header = serde_json::Map::new();
    if !metadata.is_empty() {
        header.insert(
            "__metadata__".into(),
            serde_json::to_value(metadata).expect("string map"),
        );
    }
    let mut offset = 0usize;
    for (t, how) in &sorted {
        assert_eq!(
            t.shape.iter().product::<usize>(),
            t.data.len(),
            "tensor {} shape/data mismatch",
            t.name
        );
        let end = offset + how.bytes() * t.data.len();
        let dtype = match how {
            Stored::F32 => "F32",
            Stored::F16 => "F16",
        };
        header.insert(
            t.name.to_string(),
            serde_json::json!({"dtype": dtype, "shape": t.shape, "data_offsets": [offset, end]}),
        );
        offset = end;
    }
    // serde_json's Map is a BTreeMap here (no preserve_order feature): keys come out sorted.
    let mut header_bytes = serde_json::to_vec(&header).expect("json");
    header_bytes.resize(header_bytes.len().next_multiple_of(8), b' ');
    let mut out = Vec::with_capacity(8 + header_bytes.len() + offset);
    out.extend_from_slice(&(header_bytes.len() as u64).to_le_bytes());
    out.extend_from_slice(&header_bytes);
    for (t, how) in &sorted {
        match how {
            Stored::F32 => {
                for v in t.data {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
            Stored::F16 => {
                for v in t.data {
                    out.extend_from_slice(&half::f16::from_f32(*v).to_le_bytes());
                }
            }
        }
    }
    out
}

/// The `__metadata__` of the safetensors file at `path`, read from its header alone (a
/// checkpoint's step without reading its hundreds of megabytes of weights).
pub fn read_header_metadata(path: &std::path::Path) -> Result<BTreeMap<String, String>> {
    use std::io::Read;
    let name = path.display();
    let mut file = std::fs::File::open(path).map_err(|e| anyhow!("{name}: cannot open ({e})"))?;
    let mut len = [0u8; 8];
    file.read_exact(&mut len)
        .map_err(|_| anyhow!("{name}: not a safetensors file (under 8 bytes)"))?;
    let len = u64::from_le_bytes(len);
    // The header is JSON; anything near this size is a damaged length, not a header.
    if len > 100_000_000 {
        bail!("{name}: not a safetensors file (header length {len})");
    }
    let mut header = vec![0u8; len as usize];
    file.read_exact(&mut header)
        .map_err(|_| anyhow!("{name}: not a safetensors file (header cut short)"))?;
    let header: serde_json::Value = serde_json::from_slice(&header)
        .map_err(|e| anyhow!("{name}: not a safetensors file (header: {e})"))?;
    let mut metadata = BTreeMap::new();
    if let Some(map) = header.get("__metadata__").and_then(|m| m.as_object()) {
        for (key, value) in map {
            let value = value
                .as_str()
                .ok_or_else(|| anyhow!("{name}: metadata `{key}` is not a string"))?;
            metadata.insert(key.clone(), value.to_string());
        }
    }
    Ok(metadata)
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
        let (shape, values, _) = self.stored_tensor(tensor, expected, false)?;
        Ok((shape, values))
    }

    /// [`TensorFile::f32_tensor`] for a tensor stored as F32 or F16 (widened exactly), and how
    /// it was stored.
    pub fn f32_or_f16_tensor(
        &self,
        tensor: &str,
        expected: &[Option<usize>],
    ) -> Result<(Vec<usize>, Vec<f32>, Stored)> {
        self.stored_tensor(tensor, expected, true)
    }

    fn stored_tensor(
        &self,
        tensor: &str,
        expected: &[Option<usize>],
        half_allowed: bool,
    ) -> Result<(Vec<usize>, Vec<f32>, Stored)> {
        let name = &self.name;
        let view = self
            .tensors
            .tensor(tensor)
            .map_err(|_| anyhow!("{name}: tensor `{tensor}` is missing"))?;
        let stored = match view.dtype() {
            Dtype::F32 => Stored::F32,
            Dtype::F16 if half_allowed => Stored::F16,
            other => {
                let want = if half_allowed { "F32 or F16" } else { "F32" };
                bail!("{name}: tensor `{tensor}` has dtype {other:?}, expected {want}");
            }
        };
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
        let values: Vec<f32> = match stored {
            Stored::F32 => view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
            Stored::F16 => view
                .data()
                .chunks_exact(2)
                .map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
        };
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            bail!("{name}: tensor `{tensor}` has a non-finite value at flat index {i}");
        }
        Ok((shape, values, stored))
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
    fn header_metadata_reads_without_the_data() {
        let dir = tempfile::tempdir().unwrap();
        let a = [1.0f32; 8];
        let mut meta = BTreeMap::new();
        meta.insert("step".to_string(), "12".to_string());
        let bytes = serialize_f32(
            &[F32Tensor {
                name: "a",
                shape: vec![8],
                data: &a,
            }],
            &meta,
        );
        let path = dir.path().join("m.safetensors");
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(read_header_metadata(&path).unwrap(), meta);
        // The header alone is enough: the data cut off still reads.
        let header_len = 8 + u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        std::fs::write(&path, &bytes[..header_len]).unwrap();
        assert_eq!(read_header_metadata(&path).unwrap(), meta);
        // A header cut short, garbage, and a missing file: errors naming the file.
        for junk in [
            &bytes[..header_len - 1],
            b"hello world, not a tensor",
            b"abc",
        ] {
            std::fs::write(&path, junk).unwrap();
            let err = read_header_metadata(&path).unwrap_err().to_string();
            assert!(err.starts_with(&path.display().to_string()), "{err}");
        }
        assert!(read_header_metadata(&dir.path().join("none")).is_err());
    }

    #[test]
    fn half_tensors_round_trip_where_allowed() {
        let a = [1.0f32, -0.1, 3.0e-3, 65504.0, 1.0e-9];
        let b = [0.25f32, 0.5];
        let tensors = [
            F32Tensor {
                name: "a",
                shape: vec![5],
                data: &a,
            },
            F32Tensor {
                name: "b",
                shape: vec![2],
                data: &b,
            },
        ];
        let half_a = |n: &str| if n == "a" { Stored::F16 } else { Stored::F32 };
        let bytes = serialize(&tensors, half_a, &BTreeMap::new());
        assert_eq!(bytes, serialize(&tensors, half_a, &BTreeMap::new()));
        // Two bytes a value fewer (the headers differ only in the offsets' digits).
        let full = serialize_f32(&tensors, &BTreeMap::new());
        assert!(full.len() - bytes.len() >= 2 * a.len() - 8);
        let file = TensorFile::parse(&bytes, "h.safetensors").unwrap();
        let (shape, values, stored) = file.f32_or_f16_tensor("a", &[None]).unwrap();
        assert_eq!((shape, stored), (vec![5], Stored::F16));
        let rounded: Vec<f32> = a.iter().map(|&v| round_to_f16(v)).collect();
        assert_eq!(values, rounded);
        assert_eq!(values[0], 1.0);
        assert_eq!(values[3], 65504.0);
        assert_eq!(values[4], 0.0, "below half's smallest subnormal");
        assert!((values[1] + 0.1).abs() < 1e-4);
        let (_, values, stored) = file.f32_or_f16_tensor("b", &[None]).unwrap();
        assert_eq!((values, stored), (b.to_vec(), Stored::F32));
        // Where only F32 is allowed (codes files), a half tensor is refused by name.
        let err = file.f32_tensor("a", &[None]).unwrap_err();
        assert!(format!("{err}").contains("tensor `a` has dtype F16, expected F32"));
        // A value beyond half's range is infinite when read, and refused.
        let big = [1.0e5f32];
        let bytes = serialize(
            &[F32Tensor {
                name: "big",
                shape: vec![1],
                data: &big,
            }],
            |_| Stored::F16,
            &BTreeMap::new(),
        );
        let file = TensorFile::parse(&bytes, "big.safetensors").unwrap();
        let err = file.f32_or_f16_tensor("big", &[None]).unwrap_err();
        assert!(format!("{err}").contains("non-finite"));
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
