//! The slot codes file (its contract: `docs/formats.md`): a safetensors file holding an encoded scene.
//!
//! | tensor | shape | meaning |
//! | --- | --- | --- |
//! | `slots` | [K, D] | foreground slot latents; K may be 0 |
//! | `slot_to_world` | [K, 4, 4] | slot k's light-field frame → world, row-major |
//! | `slot_mass` | [K] | share of the image's attention slot k took at encoding, in [0, 1] |
//! | `background` | [D] | background latent (world frame) |
//!
//! Metadata: `format` = `colf-codes/1`, `model` = identity of the encoding model, `sources` =
//! JSON array naming each slot's origin. Unknown tensors and metadata keys are ignored.

use crate::camera::{validate_rigid, RIGID_TOLERANCE};
use crate::tensorfile::{serialize_f32, F32Tensor, TensorFile};
use anyhow::{anyhow, bail, Result};
use glam::DMat4;
use std::collections::BTreeMap;

/// The `format` metadata value of a codes file.
pub const CODES_FORMAT: &str = "colf-codes/1";

/// Largest slot count accepted from a file: far beyond any real scene, small enough to refuse
/// a corrupt header before allocating.
pub const MAX_SLOTS: usize = 100_000;

/// One foreground object: its latent and where its light field sits in the world.
#[derive(Clone, Debug, PartialEq)]
pub struct Slot {
    pub latent: Vec<f32>,
    /// Maps the slot's light-field frame to world (rigid).
    pub slot_to_world: DMat4,
    /// Share of the encoded image's attention this slot took, in [0, 1].
    pub mass: f32,
    /// Where the slot came from, e.g. `scene7.png#3`.
    pub source: String,
}

/// An encoded scene: foreground slots and the background latent.
#[derive(Clone, Debug, PartialEq)]
pub struct Codes {
    pub slots: Vec<Slot>,
    pub background: Vec<f32>,
    /// Identity of the model that encoded these codes (render refuses another model's codes).
    pub model: String,
}

impl Codes {
    /// Latent dimension D.
    pub fn dim(&self) -> usize {
        self.background.len()
    }

    /// Parses and validates a codes file; `name` (the file) prefixes every error.
    pub fn from_bytes(bytes: &[u8], name: &str) -> Result<Codes> {
        let file = TensorFile::parse(bytes, name)?;
        let format = file.require_metadata("format")?;
        if format != CODES_FORMAT {
            bail!(
                "{name}: format is `{format}`, expected `{CODES_FORMAT}` (not a colf codes file?)"
            );
        }
        let model = file.require_metadata("model")?.to_string();
        let (bg_shape, background) = file.f32_tensor("background", &[None])?;
        let dim = bg_shape[0];
        if dim == 0 {
            bail!("{name}: tensor `background` is empty");
        }
        let (slots_shape, latents) = file.f32_tensor("slots", &[None, Some(dim)])?;
        let k = slots_shape[0];
        if k > MAX_SLOTS {
            bail!("{name}: {k} slots is more than the {MAX_SLOTS} accepted");
        }
        let (_, frames) = file.f32_tensor("slot_to_world", &[Some(k), Some(4), Some(4)])?;
        let (_, masses) = file.f32_tensor("slot_mass", &[Some(k)])?;
        let sources: Vec<String> = match file.metadata.get("sources") {
            None => vec![String::new(); k],
            Some(text) => {
                let list: Vec<String> = serde_json::from_str(text).map_err(|e| {
                    anyhow!("{name}: metadata `sources` is not a JSON array of strings ({e})")
                })?;
                if list.len() != k {
                    bail!(
                        "{name}: metadata `sources` names {} slots, the file has {k}",
                        list.len()
                    );
                }
                list
            }
        };
        let slots = (0..k)
            .map(|i| {
                let rows = &frames[16 * i..16 * (i + 1)];
                let slot_to_world = DMat4::from_cols_array(&std::array::from_fn(|c| {
                    // column-major index c = col*4 + row ← row-major file entry row*4 + col
                    rows[(c % 4) * 4 + c / 4] as f64
                }));
                validate_rigid(
                    &slot_to_world,
                    &format!("{name}: slot_to_world[{i}]"),
                    RIGID_TOLERANCE,
                )?;
                let mass = masses[i];
                if !(0.0..=1.0).contains(&mass) {
                    bail!("{name}: slot_mass[{i}] = {mass} is outside [0, 1]");
                }
                Ok(Slot {
                    latent: latents[dim * i..dim * (i + 1)].to_vec(),
                    slot_to_world,
                    mass,
                    source: sources[i].clone(),
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Codes {
            slots,
            background,
            model,
        })
    }

    /// Reads a codes file, or stdin for `-`.
    pub fn read(path: &str) -> Result<Codes> {
        let bytes = crate::io::read_input(path, true)?;
        Codes::from_bytes(&bytes, crate::io::display_name(path))
    }

    /// Checks the invariants a writer must keep, with the checks of [`Codes::from_bytes`] on the
    /// values as they will be stored: at most [`MAX_SLOTS`] slots, latent sizes, finite values,
    /// frames that are rigid and finite in f32 (a translation of 1e39 is finite in f64 only).
    pub fn validate(&self) -> Result<()> {
        let dim = self.dim();
        if dim == 0 {
            bail!("codes have an empty background latent");
        }
        if self.slots.len() > MAX_SLOTS {
            bail!(
                "{} slots is more than the {MAX_SLOTS} a codes file may hold",
                self.slots.len()
            );
        }
        if self.background.iter().any(|v| !v.is_finite()) {
            bail!("background latent has a non-finite value");
        }
        for (i, s) in self.slots.iter().enumerate() {
            if s.latent.len() != dim {
                bail!(
                    "slot {i} has latent size {}, the background has {dim}",
                    s.latent.len()
                );
            }
            if s.latent.iter().any(|v| !v.is_finite()) {
                bail!("slot {i} has a non-finite latent value");
            }
            if !(0.0..=1.0).contains(&s.mass) {
                bail!("slot {i} has mass {} outside [0, 1]", s.mass);
            }
            let what = format!("slot {i}: slot_to_world");
            validate_rigid(&s.slot_to_world, &what, RIGID_TOLERANCE)?;
            let stored =
                DMat4::from_cols_array(&s.slot_to_world.to_cols_array().map(|v| v as f32 as f64));
            if !stored.is_finite() {
                let t = s.slot_to_world.w_axis.truncate();
                bail!(
                    "{what}: the origin [{}, {}, {}] is beyond the range of a codes file (f32, about ±3.4e38)",
                    t.x,
                    t.y,
                    t.z
                );
            }
            validate_rigid(
                &stored,
                &format!("{what} (as stored in f32)"),
                RIGID_TOLERANCE,
            )?;
        }
        Ok(())
    }

    /// The safetensors bytes of these codes (deterministic).
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        self.validate()?;
        let k = self.slots.len();
        let latents: Vec<f32> = self
            .slots
            .iter()
            .flat_map(|s| s.latent.iter().copied())
            .collect();
        let frames: Vec<f32> = self
            .slots
            .iter()
            .flat_map(|s| {
                crate::camera::matrix_rows(&s.slot_to_world)
                    .into_iter()
                    .flatten()
            })
            .map(|v| v as f32)
            .collect();
        let masses: Vec<f32> = self.slots.iter().map(|s| s.mass).collect();
        let sources: Vec<&str> = self.slots.iter().map(|s| s.source.as_str()).collect();
        let mut metadata = BTreeMap::new();
        metadata.insert("format".to_string(), CODES_FORMAT.to_string());
        metadata.insert("model".to_string(), self.model.clone());
        metadata.insert(
            "sources".to_string(),
            serde_json::to_string(&sources).expect("strings"),
        );
        let bytes = serialize_f32(
            &[
                F32Tensor {
                    name: "slots",
                    shape: vec![k, self.dim()],
                    data: &latents,
                },
                F32Tensor {
                    name: "slot_to_world",
                    shape: vec![k, 4, 4],
                    data: &frames,
                },
                F32Tensor {
                    name: "slot_mass",
                    shape: vec![k],
                    data: &masses,
                },
                F32Tensor {
                    name: "background",
                    shape: vec![self.dim()],
                    data: &self.background,
                },
            ],
            &metadata,
        );
        // The reader's own checks, so a writer never writes what a reader refuses.
        Codes::from_bytes(&bytes, "the codes to write")?;
        Ok(bytes)
    }

    /// Writes the codes to a file (atomically) or stdout (`-`, refused on a terminal).
    pub fn write(&self, path: &str) -> Result<()> {
        let bytes = self.to_bytes()?;
        crate::io::write_output(path, &bytes, true)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use glam::DVec3;

    /// A small codes value for tests: `k` slots of dimension 4, slot i translated by (i, 0, 0).
    pub(crate) fn sample(k: usize) -> Codes {
        Codes {
            slots: (0..k)
                .map(|i| Slot {
                    latent: vec![i as f32, 1.0, -2.5, 0.25],
                    slot_to_world: DMat4::from_translation(DVec3::new(i as f64, 0.0, 0.0)),
                    mass: 0.1 * i as f32,
                    source: format!("scene.png#{i}"),
                })
                .collect(),
            background: vec![0.5, -0.5, 1.0, 2.0],
            model: "test-model".into(),
        }
    }

    #[test]
    fn round_trip_is_exact_and_deterministic() {
        for k in [0, 1, 3] {
            let codes = sample(k);
            let bytes = codes.to_bytes().unwrap();
            assert_eq!(bytes, codes.to_bytes().unwrap());
            assert_eq!(Codes::from_bytes(&bytes, "c").unwrap(), codes);
        }
    }

    #[test]
    fn rotated_frames_round_trip_to_f32_precision() {
        let mut codes = sample(1);
        codes.slots[0].slot_to_world = DMat4::from_rotation_translation(
            glam::DQuat::from_axis_angle(DVec3::new(1.0, 2.0, 3.0).normalize(), 0.7),
            DVec3::new(3.0, -2.0, 0.5),
        );
        let back = Codes::from_bytes(&codes.to_bytes().unwrap(), "c").unwrap();
        let err = (back.slots[0].slot_to_world - codes.slots[0].slot_to_world)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, v| a.max(v.abs()));
        assert!(err < 1e-6, "{err}");
    }

    fn with_metadata(codes: &Codes, edit: impl FnOnce(&mut BTreeMap<String, String>)) -> Vec<u8> {
        let bytes = codes.to_bytes().unwrap();
        let file = TensorFile::parse(&bytes, "x").unwrap();
        let mut meta = file.metadata.clone();
        edit(&mut meta);
        let names = ["slots", "slot_to_world", "slot_mass", "background"];
        let owned: Vec<(Vec<usize>, Vec<f32>)> = names
            .iter()
            .map(|n| {
                let v = file.tensors.tensor(n).unwrap();
                let data = v
                    .data()
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect();
                (v.shape().to_vec(), data)
            })
            .collect();
        let tensors: Vec<F32Tensor> = names
            .iter()
            .zip(&owned)
            .map(|(n, (s, d))| F32Tensor {
                name: n,
                shape: s.clone(),
                data: d,
            })
            .collect();
        serialize_f32(&tensors, &meta)
    }

    #[test]
    fn metadata_is_checked() {
        let codes = sample(2);
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (
                with_metadata(&codes, |m| {
                    m.insert("format".into(), "colf-model/1".into());
                }),
                "format is `colf-model/1`",
            ),
            (
                with_metadata(&codes, |m| {
                    m.remove("model");
                }),
                "`model` is missing",
            ),
            (
                with_metadata(&codes, |m| {
                    m.insert("sources".into(), "[\"a\"]".into());
                }),
                "names 1 slots",
            ),
            (
                with_metadata(&codes, |m| {
                    m.insert("sources".into(), "{".into());
                }),
                "not a JSON array",
            ),
        ];
        for (bytes, expected) in cases {
            let msg = format!("{:#}", Codes::from_bytes(&bytes, "in.codes").unwrap_err());
            assert!(
                msg.starts_with("in.codes: ") && msg.contains(expected),
                "{msg}"
            );
        }
        // Unknown metadata keys are ignored; missing sources default to empty names.
        let extra = with_metadata(&codes, |m| {
            m.insert("note".into(), "hello".into());
            m.remove("sources");
        });
        let read = Codes::from_bytes(&extra, "x").unwrap();
        assert_eq!(read.slots.len(), 2);
        assert_eq!(read.slots[0].source, "");
    }

    #[test]
    fn bad_values_are_refused_on_write() {
        let mut codes = sample(2);
        codes.slots[1].latent[0] = f32::INFINITY;
        assert!(codes.to_bytes().is_err());
        let mut codes = sample(2);
        codes.slots[1].slot_to_world = DMat4::from_scale(DVec3::splat(2.0));
        assert!(format!("{:#}", codes.to_bytes().unwrap_err()).contains("orthonormal"));
        let mut codes = sample(2);
        codes.slots[0].latent.pop();
        assert!(codes.to_bytes().is_err());
    }

    #[test]
    fn writers_refuse_what_readers_refuse() {
        // Finite in f64, infinite in the file's f32.
        let mut codes = sample(2);
        codes.slots[1].slot_to_world = DMat4::from_translation(DVec3::new(1e39, 0.0, 0.0));
        let msg = format!("{:#}", codes.to_bytes().unwrap_err());
        assert!(
            msg.contains("slot 1") && msg.contains("beyond the range"),
            "{msg}"
        );
        // More slots than any reader accepts.
        let mut codes = sample(1);
        codes.slots = vec![codes.slots[0].clone(); MAX_SLOTS + 1];
        let msg = format!("{:#}", codes.to_bytes().unwrap_err());
        assert!(
            msg.contains("100001 slots is more than the 100000"),
            "{msg}"
        );
        codes.slots.pop();
        assert!(Codes::from_bytes(&codes.to_bytes().unwrap(), "c").is_ok());
    }
}
