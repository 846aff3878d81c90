//! The fuzz harness shared by `examples/fuzz/main.rs` (`make fuzz`) and `tests/fuzz_smoke.rs`:
//! seeded, structure-aware mutations of valid inputs, fed in-process to the parsers the CLIs
//! use, each under `catch_unwind` and a clock. See docs/fuzzing.md.

// The example and the test each use part of the report.
#![allow(dead_code)]

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::time::{Duration, Instant};

use colf::camera::Cameras;
use colf::codes::{Codes, Slot};
use colf::model::{Colf, Config};
use glam::DMat4;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde_json::{Map, Value};

/// The parsers, in the order of the report.
pub const PARSERS: [&str; 7] = [
    "codes",
    "model",
    "transforms",
    "uorf_rt",
    "edits",
    "png",
    "plot",
];

/// An input that takes longer than this is a failure (a hang).
pub const MAX_INPUT_TIME: Duration = Duration::from_secs(1);

/// Address space the harness allows itself (`RLIMIT_AS`), so a giant allocation fails instead
/// of exhausting the machine.
pub const MEMORY_LIMIT_BYTES: u64 = 4 << 30;

/// Sets `RLIMIT_AS` to [`MEMORY_LIMIT_BYTES`] (or leaves a lower limit in place).
pub fn limit_memory() -> std::io::Result<()> {
    let mut old = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: plain libc calls on a local struct.
    unsafe {
        if libc::getrlimit(libc::RLIMIT_AS, &mut old) != 0 {
            return Err(std::io::Error::last_os_error());
        }
        let cur = old.rlim_cur.min(MEMORY_LIMIT_BYTES as libc::rlim_t);
        let new = libc::rlimit {
            rlim_cur: cur,
            rlim_max: old.rlim_max,
        };
        if libc::setrlimit(libc::RLIMIT_AS, &new) != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    Ok(())
}

/// What went wrong with one input.
#[derive(Debug)]
pub struct Failure {
    pub parser: &'static str,
    pub index: u64,
    pub what: String,
    pub input: Vec<u8>,
}

/// Per-parser figures of a run.
#[derive(Debug, Default)]
pub struct Report {
    pub parser: &'static str,
    pub inputs: u64,
    pub errors: u64,
    pub failures: Vec<Failure>,
    pub slowest: Duration,
    pub slowest_index: u64,
    pub total: Duration,
}

/// Valid inputs of every parser, built in-process, and the mutators.
pub struct Fuzzer {
    codes: Vec<u8>,
    model: Vec<u8>,
    transforms: Vec<u8>,
    uorf_rt: Vec<u8>,
    edits: Vec<u8>,
    pngs: Vec<Vec<u8>>,
    log: Vec<u8>,
}

/// The `training` metadata of the fuzzed model: two runs, as `colf-train` writes them.
const FUZZ_TRAINING_RUNS: &str = r#"[{"batch":4,"config_overrides":[],"data":"data/train",
"decay_from":null,"engine":"analytic","final_lr":null,"init":null,"losses":{"l2":1.0,"latent":0.0001},
"lr":0.0002,"mask_margin":0,"mask_shadow_depth":0.0,"masks_in_data":true,"masks_used":false,
"object_fraction":0.0,"planned_steps":100,"preset":"small","rays":512,"scenes":400,"seed":0,
"steps":100,"views":2,"warmup":500},{"batch":4,"config_overrides":["ray_fourier_freqs=6"],
"data":"bl/train","decay_from":60,"engine":"blender","final_lr":5e-6,"init":"c1fd4506bf2ce4e6",
"losses":{"l2":1.0,"mask":0.1},"lr":5e-5,"mask_margin":1,"mask_shadow_depth":0.1,
"masks_in_data":true,"masks_used":true,"object_fraction":0.2,"planned_steps":80,"preset":null,
"rays":256,"scenes":320,"seed":31,"steps":80,"views":4,"warmup":200}]"#;

/// The smallest model the tests build (tests/model_core.rs `tiny`).
pub fn tiny_config() -> Config {
    Config {
        preset: "tiny".into(),
        encoder_size: 16,
        encoder_first_stride: 2,
        encoder_channels: 8,
        encoder_channels_low: 8,
        feature_dim: 8,
        slot_dim: 8,
        slot_iters: 1,
        slot_mlp_hidden: 8,
        default_slots: 2,
        lfn_hidden: 8,
        lfn_hidden_layers: 1,
        lfn_features: 8,
        ray_fourier_freqs: 1,
        hypernet_hidden: 8,
        head_hidden: 8,
        head_hidden_layers: 1,
        compositor_hidden: 8,
        compositor_hidden_layers: 1,
        scene_scale: 4.0,
        ..Config::small()
    }
}

/// A valid scene of five slots with 8-dimensional latents (enough for the demo's edits, the
/// edits target's seed, to apply).
pub fn small_codes() -> Codes {
    let slot = |i: usize| Slot {
        latent: (0..8)
            .map(|k| (k as f32 - 3.5) * 0.1 * (i + 1) as f32)
            .collect(),
        slot_to_world: DMat4::from_translation(glam::DVec3::new(i as f64, -0.5, 0.25)),
        mass: 0.3,
        source: format!("scene.png#{i}"),
    };
    Codes {
        slots: (0..5).map(slot).collect(),
        background: vec![0.5; 8],
        model: "fuzz-model".into(),
    }
}

impl Fuzzer {
    pub fn new() -> anyhow::Result<Fuzzer> {
        let codes = small_codes().to_bytes()?;
        // With a training record, so the mutations reach the `training` metadata reader too.
        let training = colf::model::history::parse(FUZZ_TRAINING_RUNS, "fuzz")?;
        let model = Colf::init(&tiny_config(), 7)?
            .with_training(training)
            .to_bytes()?
            .0;
        let transforms = br#"{"camera_angle_x": 0.6911, "w": 64, "h": 64,
 "frames": [
  {"file_path": "view_000.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]},
  {"file_path": "view_001.png", "fl_x": 80.0, "fl_y": 80.0, "cx": 32, "cy": 32,
   "transform_matrix": [[0,0,1,4],[1,0,0,0],[0,1,0,0],[0,0,0,1]]}
 ]}"#
        .to_vec();
        let uorf_rt = b"1 0 0 0\n0 -1 0 0\n0 0 -1 5\n0 0 0 1\n".to_vec();
        let edits = include_bytes!("../demo-edits.json").to_vec();
        let mut rgb = Vec::new();
        for i in 0..8 * 6 {
            rgb.extend([i as f32 / 48.0, 0.5, 1.0 - i as f32 / 48.0]);
        }
        let grey: Vec<u8> = (0..8 * 6).map(|i| (i % 4) as u8 * 60).collect();
        let pngs = vec![
            colf::image_io::encode_png_rgb(8, 6, &rgb),
            colf::image_io::encode_png_grey(8, 6, &grey),
        ];
        let mut log = String::new();
        for step in 0..6 {
            log.push_str(&format!(
                "{{\"step\": {}, \"loss\": {}, \"psnr\": {}, \"obj_psnr\": 18.5, \"fg_share\": 0.2, \"fg_ari\": 0.7}}\n",
                step * 10,
                1.0 / (step + 1) as f64,
                20.0 + step as f64
            ));
            if step % 2 == 1 {
                log.push_str(&format!(
                    "{{\"step\": {}, \"eval\": {{\"psnr\": 21.5, \"fg_ari\": 0.8}}}}\n",
                    step * 10
                ));
            }
        }
        Ok(Fuzzer {
            codes,
            model,
            transforms,
            uorf_rt,
            edits,
            pngs,
            log: log.into_bytes(),
        })
    }

    /// Input `index` of `parser` under `seed`: the same three give the same bytes.
    pub fn input(&self, parser: &str, seed: u64, index: u64) -> Vec<u8> {
        let salt = parser.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
            (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
        });
        let mut rng =
            StdRng::seed_from_u64(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ salt ^ index);
        match parser {
            "codes" => mutate_safetensors(&self.codes, &mut rng),
            "model" => {
                let bytes = mutate_safetensors(&self.model, &mut rng);
                if rng.random_bool(0.7) {
                    restamp_identity(bytes)
                } else {
                    bytes
                }
            }
            "transforms" | "edits" => {
                let base = if parser == "edits" {
                    &self.edits
                } else {
                    &self.transforms
                };
                mutate_json_bytes(base, &mut rng)
            }
            "uorf_rt" => mutate_lines(&self.uorf_rt, &mut rng, false),
            "png" => {
                let base = &self.pngs[rng.random_range(0..self.pngs.len())];
                mutate_png(base, &mut rng)
            }
            "plot" => mutate_lines(&self.log, &mut rng, true),
            other => panic!("unknown parser {other}"),
        }
    }
}

/// Runs one parser's entry points (those its CLIs call) on `bytes`; errors are fine.
pub fn run_parser(parser: &str, bytes: &[u8]) -> Result<(), String> {
    let name = "fuzz-input";
    let ok = |r: anyhow::Result<()>| r.map_err(|e| format!("{e:#}"));
    match parser {
        "codes" => ok(Codes::from_bytes(bytes, name).and_then(|c| {
            // What colf-edit does next with a file it read: the writer's own checks.
            c.to_bytes().map(|_| ())
        })),
        "model" => ok(Colf::from_bytes(bytes, name).map(|_| ())),
        "transforms" => ok(Cameras::from_json(bytes, name).map(|c| {
            // The camera rays the renderer would need: only check that the pixel grid maps.
            for f in &c.frames {
                let _ = f.ray_at(0.5, 0.5);
            }
        })),
        "uorf_rt" => {
            ok(Cameras::uorf_pose_from_text(&String::from_utf8_lossy(bytes), name).map(|_| ()))
        }
        // colf-edit applies the ops it parsed to a codes file: so does the harness.
        "edits" => ok(colf::edit::parse_edits(bytes, name)
            .and_then(|ops| colf::edit::apply_edits(&small_codes(), &ops, name).map(|_| ()))),
        "png" => {
            let a = colf::image_io::png_dimensions(bytes, name).map(|_| ());
            let b = colf::image_io::decode_rgb(bytes, name).map(|_| ());
            let c = colf::image_io::decode_labels(bytes, name).map(|_| ());
            let d = colf::dataset::uorf_mask_levels(bytes, name).map(|_| ());
            ok(a.and(b).and(c).and(d))
        }
        "plot" => ok(
            colf::train::plot::read_log(&String::from_utf8_lossy(bytes), name).and_then(|curves| {
                let run = colf::train::plot::Run {
                    label: name.to_string(),
                    curves,
                };
                colf::train::plot::plot_png(&[run], 96, 64).map(|_| ())
            }),
        ),
        other => Err(format!("unknown parser {other}")),
    }
}

/// Runs `bytes` through `parser` under `catch_unwind` and the clock; `Err` is a failure
/// (panic or over [`MAX_INPUT_TIME`]), `Ok(is_error)` otherwise.
pub fn check(parser: &str, bytes: &[u8]) -> (Result<bool, String>, Duration) {
    let start = Instant::now();
    let outcome = catch_unwind(AssertUnwindSafe(|| run_parser(parser, bytes)));
    let took = start.elapsed();
    let result = match outcome {
        Err(payload) => {
            let msg = payload
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "panic".into());
            Err(format!("panic: {msg}"))
        }
        Ok(_) if took > MAX_INPUT_TIME => Err(format!("took {:.2} s", took.as_secs_f64())),
        Ok(r) => Ok(r.is_err()),
    };
    (result, took)
}

/// Silences the panic hook while `f` runs (panics are caught and reported), then restores it.
pub fn with_silent_panics<T>(f: impl FnOnce() -> T) -> T {
    let old = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let out = f();
    std::panic::set_hook(old);
    out
}

/// Runs inputs `0..iterations` of `parser` under `seed`.
pub fn fuzz_parser(fuzzer: &Fuzzer, parser: &'static str, seed: u64, iterations: u64) -> Report {
    let mut report = Report {
        parser,
        ..Report::default()
    };
    for index in 0..iterations {
        let input = fuzzer.input(parser, seed, index);
        // An abort (an allocation refused under RLIMIT_AS) cannot be caught: with
        // COLF_FUZZ_TRACE=FILE each input is written there before it runs.
        if let Some(trace) = std::env::var_os("COLF_FUZZ_TRACE") {
            let _ = std::fs::write(trace, &input);
            eprintln!("{parser} {index}");
        }
        let (result, took) = check(parser, &input);
        report.inputs += 1;
        report.total += took;
        if took > report.slowest {
            report.slowest = took;
            report.slowest_index = index;
        }
        match result {
            Ok(is_error) => report.errors += is_error as u64,
            Err(what) => report.failures.push(Failure {
                parser,
                index,
                what,
                input,
            }),
        }
    }
    report
}

// ---------------------------------------------------------------------------------------------
// Mutators.

const EXTREME_NUMBERS: [&str; 16] = [
    "1e39",
    "-1e39",
    "-0",
    "0",
    "1e308",
    "-1e308",
    "1e-320",
    "1e400",
    "-1e400",
    "4294967297",
    "18446744073709551616",
    "9007199254740993",
    "-1",
    "2147483648",
    "3.4028236e38",
    "1e-45",
];

fn extreme_number(rng: &mut StdRng) -> Value {
    let text = EXTREME_NUMBERS[rng.random_range(0..EXTREME_NUMBERS.len())];
    serde_json::from_str(text).unwrap_or_else(|_| Value::from(f64::MAX))
}

fn random_value(rng: &mut StdRng, depth: u32) -> Value {
    match rng.random_range(0..9) {
        0 => Value::Null,
        1 => Value::Bool(rng.random()),
        2 => extreme_number(rng),
        3 => Value::from(rng.random_range(-3i64..20)),
        4 => Value::from(rng.random_range(-2.0..2.0f64)),
        5 => Value::String(long_or_odd_string(rng)),
        6 if depth < 3 => Value::Array(
            (0..rng.random_range(0..5))
                .map(|_| random_value(rng, depth + 1))
                .collect(),
        ),
        7 if depth < 3 => {
            let mut m = Map::new();
            m.insert("x".into(), random_value(rng, depth + 1));
            Value::Object(m)
        }
        _ => Value::Array(vec![]),
    }
}

fn long_or_odd_string(rng: &mut StdRng) -> String {
    match rng.random_range(0..6) {
        0 => "x".repeat(rng.random_range(1000..50_000)),
        1 => String::new(),
        2 => "\u{0}\u{202e}é\u{10ffff}".into(),
        3 => "NaN".into(),
        4 => "../../etc/passwd".into(),
        _ => "1e39".into(),
    }
}

/// Visits a random node of the tree and changes it (or its parent's entry).
fn mutate_tree(v: &mut Value, rng: &mut StdRng, dup_keys: &mut Vec<String>) {
    // Walk down to a random depth.
    let descend = rng.random_bool(0.7);
    match v {
        Value::Object(m) if !m.is_empty() => {
            let keys: Vec<String> = m.keys().cloned().collect();
            let key = keys[rng.random_range(0..keys.len())].clone();
            if descend {
                mutate_tree(m.get_mut(&key).unwrap(), rng, dup_keys);
                return;
            }
            match rng.random_range(0..5) {
                0 => {
                    m.remove(&key);
                }
                1 => dup_keys.push(key),
                2 => {
                    m.insert(key, random_value(rng, 0));
                }
                3 => {
                    m.insert(long_or_odd_string(rng), random_value(rng, 0));
                }
                _ => {
                    let val = m.get(&key).cloned().unwrap();
                    m.insert(key, Value::Array(vec![val]));
                }
            }
        }
        Value::Array(a) if !a.is_empty() => {
            let i = rng.random_range(0..a.len());
            if descend {
                mutate_tree(&mut a[i], rng, dup_keys);
                return;
            }
            match rng.random_range(0..5) {
                0 => {
                    a.remove(i);
                }
                1 => {
                    let x = a[i].clone();
                    // Now and then a long array, of about 1 MB at most, so that the time
                    // limit measures the parser, not the size of the input.
                    let n = if rng.random_bool(0.01) {
                        (1 << 20) / (x.to_string().len() + 1)
                    } else {
                        1
                    };
                    for _ in 0..n {
                        a.push(x.clone());
                    }
                }
                2 => a[i] = random_value(rng, 0),
                3 => a.truncate(i),
                _ => a.insert(i, random_value(rng, 0)),
            }
        }
        _ => {
            *v = match rng.random_range(0..4) {
                0 => extreme_number(rng),
                1 => random_value(rng, 0),
                2 => {
                    // Deep nesting.
                    let depth = rng.random_range(1..200);
                    let mut x = v.clone();
                    for _ in 0..depth {
                        x = Value::Array(vec![x]);
                    }
                    x
                }
                _ => match v {
                    Value::Number(n) => {
                        let f = n.as_f64().unwrap_or(0.0);
                        Value::from(f * [1e30, -1.0, 1e-30, 0.0][rng.random_range(0..4)])
                    }
                    Value::String(_) => Value::from(1e39),
                    _ => Value::String("1".into()),
                },
            };
        }
    }
}

/// Serialises with one copy of every key named in `dup` (serde_json maps cannot hold two).
fn to_text_with_duplicates(v: &Value, dup: &[String], out: &mut String) {
    match v {
        Value::Object(m) => {
            out.push('{');
            let mut first = true;
            for (k, val) in m {
                let times = 1 + dup.iter().any(|d| d == k) as usize;
                for _ in 0..times {
                    if !first {
                        out.push(',');
                    }
                    first = false;
                    out.push_str(&Value::String(k.clone()).to_string());
                    out.push(':');
                    to_text_with_duplicates(val, dup, out);
                }
            }
            out.push('}');
        }
        Value::Array(a) => {
            out.push('[');
            for (i, x) in a.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                to_text_with_duplicates(x, dup, out);
            }
            out.push(']');
        }
        other => out.push_str(&other.to_string()),
    }
}

/// Tree mutations of a JSON document, then sometimes raw byte damage.
fn mutate_json_value_text(base: &[u8], rng: &mut StdRng) -> Vec<u8> {
    let Ok(mut v) = serde_json::from_slice::<Value>(base) else {
        return base.to_vec();
    };
    let mut dup = Vec::new();
    for _ in 0..rng.random_range(1..4) {
        mutate_tree(&mut v, rng, &mut dup);
    }
    let mut text = String::new();
    to_text_with_duplicates(&v, &dup, &mut text);
    text.into_bytes()
}

fn mutate_json_bytes(base: &[u8], rng: &mut StdRng) -> Vec<u8> {
    let mut bytes = if rng.random_bool(0.85) {
        mutate_json_value_text(base, rng)
    } else {
        base.to_vec()
    };
    if rng.random_bool(0.2) {
        raw_damage(&mut bytes, rng);
    }
    bytes
}

/// A model file whose stored identity no longer matches its contents is refused before its
/// tensors are built; to reach past that check, the identity the reader computes (from its
/// error message) is written in place of the stored one when both have the same length.
fn restamp_identity(mut bytes: Vec<u8>) -> Vec<u8> {
    let outcome = catch_unwind(AssertUnwindSafe(|| {
        colf::model::checkpoint::from_bytes(&bytes, "m").map(|_| ())
    }));
    let Ok(Err(e)) = outcome else { return bytes };
    let msg = e.to_string();
    let Some(rest) = msg.strip_prefix("m: model identity ") else {
        return bytes;
    };
    let Some((stored, tail)) = rest.split_once(" does not match the file's contents (") else {
        return bytes;
    };
    let Some((computed, _)) = tail.split_once(')') else {
        return bytes;
    };
    if stored.len() != computed.len() || stored.is_empty() {
        return bytes;
    }
    let (stored, computed) = (stored.as_bytes(), computed.as_bytes());
    if let Some(at) = bytes.windows(stored.len()).position(|w| w == stored) {
        bytes[at..at + stored.len()].copy_from_slice(computed);
    }
    bytes
}

/// Byte flips, a truncation, an extension.
fn raw_damage(bytes: &mut Vec<u8>, rng: &mut StdRng) {
    match rng.random_range(0..4) {
        0 if !bytes.is_empty() => {
            for _ in 0..rng.random_range(1..8) {
                let i = rng.random_range(0..bytes.len());
                bytes[i] ^= 1 << rng.random_range(0..8);
            }
        }
        1 => {
            let keep = rng.random_range(0..=bytes.len());
            bytes.truncate(keep);
        }
        2 => {
            let n = rng.random_range(1..64);
            bytes.extend((0..n).map(|_| rng.random::<u8>()));
        }
        _ if !bytes.is_empty() => {
            let i = rng.random_range(0..bytes.len());
            bytes[i] = [0u8, 0xff, b'"', b'{', b'[', b'\\'][rng.random_range(0..6)];
        }
        _ => {}
    }
}

/// Mutates a safetensors file: its JSON header (shapes, dtypes, offsets, metadata values,
/// keys) and its data (NaN/inf floats, truncation, extension), or its length prefix.
fn mutate_safetensors(base: &[u8], rng: &mut StdRng) -> Vec<u8> {
    let header_len = u64::from_le_bytes(base[..8].try_into().unwrap()) as usize;
    let header: Value = serde_json::from_slice(&base[8..8 + header_len]).unwrap();
    let mut data = base[8 + header_len..].to_vec();
    let mut header = header;
    let mut dup = Vec::new();
    for _ in 0..rng.random_range(1..4) {
        match rng.random_range(0..10) {
            0..=3 => safetensors_header_mutation(&mut header, rng),
            4 => mutate_tree(&mut header, rng, &mut dup),
            5 | 6 => {
                // Special floats in the data.
                if data.len() >= 4 {
                    let i = rng.random_range(0..data.len() / 4) * 4;
                    let f = [
                        f32::NAN,
                        f32::INFINITY,
                        f32::NEG_INFINITY,
                        -0.0,
                        f32::MAX,
                        1e-45,
                    ][rng.random_range(0..6)];
                    data[i..i + 4].copy_from_slice(&f.to_le_bytes());
                }
            }
            7 => {
                let keep = rng.random_range(0..=data.len());
                data.truncate(keep);
            }
            8 => data.extend(std::iter::repeat_n(0u8, rng.random_range(1..64))),
            _ => raw_damage(&mut data, rng),
        }
    }
    let mut text = String::new();
    to_text_with_duplicates(&header, &dup, &mut text);
    let mut out = Vec::with_capacity(8 + text.len() + data.len());
    let mut len = text.len() as u64;
    if rng.random_bool(0.05) {
        len = [0, 1, u64::MAX, len + 1, len.saturating_sub(1), 1 << 40][rng.random_range(0..6)];
    }
    out.extend(len.to_le_bytes());
    out.extend(text.as_bytes());
    out.extend(data);
    if rng.random_bool(0.03) {
        raw_damage(&mut out, rng);
    }
    out
}

fn safetensors_header_mutation(header: &mut Value, rng: &mut StdRng) {
    let Value::Object(m) = header else { return };
    let keys: Vec<String> = m.keys().cloned().collect();
    let key = keys[rng.random_range(0..keys.len())].clone();
    let entry = m.get_mut(&key).unwrap();
    if key == "__metadata__" {
        let Value::Object(meta) = entry else { return };
        let mkeys: Vec<String> = meta.keys().cloned().collect();
        if mkeys.is_empty() {
            return;
        }
        let mk = mkeys[rng.random_range(0..mkeys.len())].clone();
        match rng.random_range(0..4) {
            0 => {
                meta.remove(&mk);
            }
            1 => {
                // A metadata value is text: numbers inside it (or a JSON config) mutated.
                let text = meta[&mk].as_str().unwrap_or("").to_string();
                let new = if let Ok(mut v) = serde_json::from_str::<Value>(&text) {
                    let mut dup = Vec::new();
                    mutate_tree(&mut v, rng, &mut dup);
                    let mut t = String::new();
                    to_text_with_duplicates(&v, &dup, &mut t);
                    t
                } else {
                    EXTREME_NUMBERS[rng.random_range(0..EXTREME_NUMBERS.len())].to_string()
                };
                meta.insert(mk, Value::String(new));
            }
            2 => {
                meta.insert(mk, Value::String(long_or_odd_string(rng)));
            }
            _ => {
                meta.insert(mk, random_value(rng, 0));
            }
        }
        return;
    }
    let Value::Object(t) = entry else { return };
    match rng.random_range(0..6) {
        0 => {
            // Shape: huge, zero, negative, wrong rank.
            let dims: Vec<Value> = match rng.random_range(0..5) {
                0 => vec![Value::from(u64::MAX), Value::from(2)],
                1 => vec![Value::from(0)],
                2 => vec![Value::from(-1)],
                3 => vec![],
                _ => vec![Value::from(1u64 << 33), Value::from(1u64 << 33)],
            };
            t.insert("shape".into(), Value::Array(dims));
        }
        1 => {
            let d = [
                "F16", "BF16", "F64", "I64", "U8", "BOOL", "F8_E4M3", "X", "",
            ][rng.random_range(0..9)];
            t.insert("dtype".into(), Value::from(d));
        }
        2 => {
            let offs = match rng.random_range(0..4) {
                0 => vec![Value::from(u64::MAX), Value::from(0)],
                1 => vec![Value::from(0), Value::from(1u64 << 40)],
                2 => vec![Value::from(1)],
                _ => vec![Value::from(4), Value::from(4)],
            };
            t.insert("data_offsets".into(), Value::Array(offs));
        }
        3 => {
            if let Some(Value::Array(shape)) = t.get_mut("shape") {
                if let Some(d) = shape.first_mut() {
                    *d = Value::from(d.as_u64().unwrap_or(1) + 1);
                }
            }
        }
        4 => {
            m.remove(&key);
        }
        _ => {
            let v = m[&key].clone();
            m.insert(format!("{key}.copy"), v);
        }
    }
}

/// Line-level mutations of a text file (an `_RT.txt`, a JSON-lines log): numbers to extremes
/// (±1e308, NaN), lines dropped, duplicated, shuffled, damaged.
fn mutate_lines(base: &[u8], rng: &mut StdRng, json_lines: bool) -> Vec<u8> {
    let text = String::from_utf8_lossy(base);
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    for _ in 0..rng.random_range(1..4) {
        if lines.is_empty() {
            lines.push(String::new());
        }
        let i = rng.random_range(0..lines.len());
        match rng.random_range(0..8) {
            0 => {
                lines.remove(i);
            }
            1 => {
                let l = lines[i].clone();
                // Now and then a long file (a log of 20,000 steps; 2,000 lines of numbers).
                let n = if rng.random_bool(0.01) {
                    if json_lines {
                        20_000
                    } else {
                        2_000
                    }
                } else {
                    1
                };
                for _ in 0..n {
                    lines.insert(i, l.clone());
                }
            }
            2 => {
                let j = rng.random_range(0..lines.len());
                lines.swap(i, j);
            }
            3 if json_lines => {
                let mut b = mutate_json_value_text(lines[i].as_bytes(), rng);
                if rng.random_bool(0.1) {
                    raw_damage(&mut b, rng);
                }
                lines[i] = String::from_utf8_lossy(&b).into_owned();
            }
            _ => lines[i] = replace_a_number(&lines[i], rng),
        }
    }
    let mut out = lines.join("\n").into_bytes();
    if rng.random_bool(0.1) {
        raw_damage(&mut out, rng);
    }
    out
}

fn replace_a_number(line: &str, rng: &mut StdRng) -> String {
    // Spans of number characters.
    let bytes = line.as_bytes();
    let mut spans = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i].is_ascii_digit() || bytes[i] == b'-' {
            let s = i;
            while i < bytes.len() && (bytes[i].is_ascii_digit() || b"-+.eE".contains(&bytes[i])) {
                i += 1;
            }
            spans.push((s, i));
        } else {
            i += 1;
        }
    }
    if spans.is_empty() {
        return line.to_string();
    }
    let (s, e) = spans[rng.random_range(0..spans.len())];
    let new = [
        "1e308",
        "-1e308",
        "NaN",
        "nan",
        "inf",
        "-inf",
        "1e39",
        "-0",
        "1e-320",
        "1e400",
        "0x10",
        "",
        "1 2",
        "9999999999999999999999",
    ][rng.random_range(0..14)];
    format!("{}{}{}", &line[..s], new, &line[e..])
}

// PNG.

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xffff_ffffu32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

struct Chunk {
    kind: [u8; 4],
    data: Vec<u8>,
}

fn png_chunks(bytes: &[u8]) -> Vec<Chunk> {
    let mut chunks = Vec::new();
    let mut i = 8;
    while i + 12 <= bytes.len() {
        let len = u32::from_be_bytes(bytes[i..i + 4].try_into().unwrap()) as usize;
        if i + 12 + len > bytes.len() {
            break;
        }
        chunks.push(Chunk {
            kind: bytes[i + 4..i + 8].try_into().unwrap(),
            data: bytes[i + 8..i + 8 + len].to_vec(),
        });
        i += 12 + len;
    }
    chunks
}

/// Mutates a PNG: IHDR fields (huge or zero sides, bit depth, colour type, interlace), chunks
/// (dropped, duplicated, inserted, data damaged; CRCs right or wrong), truncation.
fn mutate_png(base: &[u8], rng: &mut StdRng) -> Vec<u8> {
    let mut chunks = png_chunks(base);
    let mut bad_crc = false;
    for _ in 0..rng.random_range(1..4) {
        let i = rng.random_range(0..chunks.len());
        match rng.random_range(0..9) {
            0..=2 if chunks[0].data.len() >= 13 => {
                let ihdr = &mut chunks[0].data;
                match rng.random_range(0..6) {
                    0 | 1 => {
                        let at = if rng.random_bool(0.5) { 0 } else { 4 };
                        let side = [0u32, 1, 8193, 20000, 65535, 1 << 24, u32::MAX, 0x7fff_ffff]
                            [rng.random_range(0..8)];
                        ihdr[at..at + 4].copy_from_slice(&side.to_be_bytes());
                    }
                    2 => ihdr[8] = [1u8, 2, 4, 8, 16, 0, 3, 255][rng.random_range(0..8)],
                    3 => ihdr[9] = [0u8, 2, 3, 4, 6, 1, 7, 255][rng.random_range(0..8)],
                    4 => ihdr[12] = rng.random_range(0..3),
                    _ => ihdr[10 + rng.random_range(0..2)] = rng.random(),
                }
            }
            3 => {
                if i > 0 {
                    chunks.remove(i);
                }
            }
            4 => {
                let c = Chunk {
                    kind: chunks[i].kind,
                    data: chunks[i].data.clone(),
                };
                chunks.insert(i, c);
            }
            5 => {
                let kind = [
                    *b"PLTE", *b"tRNS", *b"gAMA", *b"iCCP", *b"zTXt", *b"acTL", *b"fcTL", *b"sBIT",
                    *b"IDAT", *b"IEND",
                ][rng.random_range(0..10)];
                let n = rng.random_range(0..40);
                let data = (0..n).map(|_| rng.random()).collect();
                chunks.insert(rng.random_range(1..=chunks.len()), Chunk { kind, data });
            }
            6 => {
                let d = &mut chunks[i].data;
                if !d.is_empty() {
                    let j = rng.random_range(0..d.len());
                    d[j] ^= 1 << rng.random_range(0..8);
                }
            }
            7 => bad_crc = true,
            _ => {
                let d = &mut chunks[i].data;
                let keep = rng.random_range(0..=d.len());
                d.truncate(keep);
            }
        }
    }
    let mut out = base[..8].to_vec();
    for c in &chunks {
        out.extend((c.data.len() as u32).to_be_bytes());
        out.extend(c.kind);
        out.extend(&c.data);
        let mut crc = crc32(&[&c.kind[..], &c.data[..]].concat());
        if bad_crc && rng.random_bool(0.5) {
            crc ^= 1;
        }
        out.extend(crc.to_be_bytes());
    }
    if rng.random_bool(0.15) {
        let keep = rng.random_range(0..=out.len());
        out.truncate(keep);
    }
    out
}
