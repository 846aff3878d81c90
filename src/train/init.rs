//! `colf-train init`: a freshly initialised model file.

use crate::model::{Colf, Config};
use anyhow::Result;

/// `colf-train init`: writes a freshly initialised model of `preset` to `output` (`-`: stdout)
/// and returns a one-line summary (preset, parameters, size, identity).
pub fn init_model_file(
    preset: &str,
    overrides: &[String],
    seed: u64,
    output: &str,
) -> Result<String> {
    let cfg = Config::preset(preset)?.with_overrides(overrides)?;
    let model = Colf::init(&cfg, seed)?;
    let (bytes, id) = model.to_bytes()?;
    crate::io::write_output(output, &bytes, true)?;
    Ok(format!(
        "wrote {} (preset {preset}, seed {seed}, {} parameters, {} bytes, identity {id})",
        if crate::io::is_stdio(output) {
            "<stdout>"
        } else {
            output
        },
        model.num_parameters(),
        bytes.len()
    ))
}
