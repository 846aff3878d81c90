//! Where parameter values come from when a model is built: `VarBuilder` backends that the
//! modules' `new(cfg, vb)` constructors read through.
//!
//! - [`SeededInit`] realises each module's initialisation hint (`candle_nn::Init`) from a
//!   `rand` `StdRng` seeded by (seed, tensor name). candle's own initialisers draw from its CPU
//!   RNG, which cannot be seeded; seeding per name also makes a tensor's initial value
//!   independent of the order in which modules are built.
//! - [`CheckedTensors`] serves tensors read from a checkpoint, recording (instead of panicking
//!   on) a missing name or a wrong shape, and which names were used, so loading can report
//!   missing, misshapen and unexpected tensors by name.

use candle_core::{DType, Device, Result as CandleResult, Shape, Tensor};
use candle_nn::init::{Init, NormalOrUniform};
use candle_nn::var_builder::SimpleBackend;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use sha2::{Digest, Sha256};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Mutex;

/// A seed for one tensor: the first 8 bytes of sha256(seed ‖ name).
pub fn tensor_seed(seed: u64, name: &str) -> u64 {
    let mut hasher = Sha256::new();
    hasher.update(seed.to_le_bytes());
    hasher.update(name.as_bytes());
    let digest = hasher.finalize();
    u64::from_le_bytes(digest[..8].try_into().expect("8 bytes"))
}

/// Draws `n` values following `init` for a tensor of `shape`.
pub fn sample_init(init: Init, shape: &Shape, rng: &mut StdRng) -> Vec<f32> {
    let n = shape.elem_count();
    let uniform = |rng: &mut StdRng, lo: f64, up: f64| -> Vec<f32> {
        (0..n)
            .map(|_| (lo + (up - lo) * rng.random::<f64>()) as f32)
            .collect()
    };
    let normal = |rng: &mut StdRng, mean: f64, std: f64| -> Vec<f32> {
        (0..n)
            .map(|_| (mean + std * rng.sample::<f64, _>(StandardNormal)) as f32)
            .collect()
    };
    match init {
        Init::Const(v) => vec![v as f32; n],
        Init::Uniform { lo, up } => uniform(rng, lo, up),
        Init::Randn { mean, stdev } => normal(rng, mean, stdev),
        Init::Kaiming {
            dist,
            fan,
            non_linearity,
        } => {
            let std = non_linearity.gain() / (fan.for_shape(shape).max(1) as f64).sqrt();
            match dist {
                NormalOrUniform::Uniform => uniform(rng, -3f64.sqrt() * std, 3f64.sqrt() * std),
                NormalOrUniform::Normal => normal(rng, 0.0, std),
            }
        }
    }
}

/// Fresh, reproducible parameters: every requested tensor is drawn from its init hint with a
/// `StdRng` seeded by (seed, name), and remembered (a name asked twice gets the same tensor).
pub struct SeededInit {
    seed: u64,
    made: Mutex<BTreeMap<String, Tensor>>,
}

impl SeededInit {
    pub fn new(seed: u64) -> SeededInit {
        SeededInit {
            seed,
            made: Mutex::new(BTreeMap::new()),
        }
    }

    /// Shares the made tensors with the caller after the model was built.
    pub fn tensors(&self) -> BTreeMap<String, Tensor> {
        self.made.lock().expect("init lock").clone()
    }
}

impl SimpleBackend for SeededInit {
    fn get(
        &self,
        s: Shape,
        name: &str,
        h: Init,
        dtype: DType,
        dev: &Device,
    ) -> CandleResult<Tensor> {
        let mut made = self.made.lock().expect("init lock");
        if let Some(t) = made.get(name) {
            if t.shape() != &s {
                candle_core::bail!("parameter {name} requested with two shapes");
            }
            return Ok(t.clone());
        }
        let mut rng = StdRng::seed_from_u64(tensor_seed(self.seed, name));
        let data = sample_init(h, &s, &mut rng);
        let t = Tensor::from_vec(data, s, dev)?.to_dtype(dtype)?;
        made.insert(name.to_string(), t.clone());
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> CandleResult<Tensor> {
        candle_core::bail!("parameter {name}: shape unknown")
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.made.lock().expect("init lock").contains_key(name)
    }
}

/// Tensors read from a file, served by name with shape checks; problems are collected as
/// readable messages for the loader instead of surfacing as candle errors.
pub struct CheckedTensors {
    tensors: HashMap<String, Tensor>,
    used: Mutex<BTreeSet<String>>,
    problems: Mutex<Vec<String>>,
}

impl CheckedTensors {
    pub fn new(tensors: HashMap<String, Tensor>) -> CheckedTensors {
        CheckedTensors {
            tensors,
            used: Mutex::new(BTreeSet::new()),
            problems: Mutex::new(Vec::new()),
        }
    }

    /// Missing or misshapen tensors met while building, then tensors the model never asked for.
    pub fn problems(&self) -> Vec<String> {
        let mut problems = self.problems.lock().expect("lock").clone();
        let used = self.used.lock().expect("lock");
        let mut extra: Vec<&String> = self.tensors.keys().filter(|k| !used.contains(*k)).collect();
        extra.sort();
        for name in extra {
            problems.push(format!("unexpected tensor `{name}`"));
        }
        problems
    }
}

impl SimpleBackend for CheckedTensors {
    fn get(
        &self,
        s: Shape,
        name: &str,
        _: Init,
        dtype: DType,
        dev: &Device,
    ) -> CandleResult<Tensor> {
        self.used.lock().expect("lock").insert(name.to_string());
        let problem = match self.tensors.get(name) {
            Some(t) if t.shape() == &s => return t.to_dtype(dtype)?.to_device(dev),
            Some(t) => format!(
                "tensor `{name}` has shape {:?}, expected {:?}",
                t.dims(),
                s.dims()
            ),
            None => format!("tensor `{name}` is missing"),
        };
        self.problems.lock().expect("lock").push(problem.clone());
        candle_core::bail!("{problem}")
    }

    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> CandleResult<Tensor> {
        match self.tensors.get(name) {
            Some(t) => t.to_dtype(dtype)?.to_device(dev),
            None => candle_core::bail!("tensor `{name}` is missing"),
        }
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.tensors.contains_key(name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeded_init_depends_on_seed_and_name_only() {
        let dev = Device::Cpu;
        let hint = candle_nn::init::DEFAULT_KAIMING_NORMAL;
        let a = SeededInit::new(3);
        let b = SeededInit::new(3);
        let c = SeededInit::new(4);
        // Different request orders must not matter.
        let a1 = a.get((4, 5).into(), "x", hint, DType::F32, &dev).unwrap();
        let _ = b.get((2, 2).into(), "y", hint, DType::F32, &dev).unwrap();
        let b1 = b.get((4, 5).into(), "x", hint, DType::F32, &dev).unwrap();
        let c1 = c.get((4, 5).into(), "x", hint, DType::F32, &dev).unwrap();
        let v = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(v(&a1), v(&b1));
        assert_ne!(v(&a1), v(&c1));
        // Kaiming normal with fan-in 5: std √(2/5) ≈ 0.63.
        let big = a
            .get((64, 500).into(), "big", hint, DType::F32, &dev)
            .unwrap();
        let vals = v(&big);
        let std = (vals.iter().map(|x| x * x).sum::<f32>() / vals.len() as f32).sqrt();
        assert!((std - (2.0f32 / 500.0).sqrt()).abs() < 0.005, "std {std}");
    }

    #[test]
    fn checked_tensors_report_problems_by_name() {
        let dev = Device::Cpu;
        let mut map = HashMap::new();
        map.insert(
            "a".to_string(),
            Tensor::zeros((2, 3), DType::F32, &dev).unwrap(),
        );
        map.insert("b".to_string(), Tensor::zeros(4, DType::F32, &dev).unwrap());
        map.insert(
            "extra".to_string(),
            Tensor::zeros(1, DType::F32, &dev).unwrap(),
        );
        let checked = CheckedTensors::new(map);
        let hint = Init::Const(0.0);
        assert!(checked
            .get((2, 3).into(), "a", hint, DType::F32, &dev)
            .is_ok());
        assert!(checked
            .get((5,).into(), "b", hint, DType::F32, &dev)
            .is_err());
        assert!(checked
            .get((1,).into(), "c", hint, DType::F32, &dev)
            .is_err());
        let problems = checked.problems();
        assert_eq!(problems.len(), 3, "{problems:?}");
        assert!(problems[0].contains("`b` has shape [4], expected [5]"));
        assert!(problems[1].contains("`c` is missing"));
        assert!(problems[2].contains("unexpected tensor `extra`"));
    }
}
