//! Adam whose state we own, so a checkpoint can hold it and `--resume` continues exactly.
//!
//! candle's `AdamW` keeps its moment buffers private (and decays weights by 0.01 by default),
//! so its state cannot be saved. This is the textbook Adam (Kingma & Ba) with bias correction
//! and optional global-norm gradient clipping, over named `Var`s.

use crate::tensorfile::{serialize_f32, F32Tensor, TensorFile};
use anyhow::{anyhow, bail, Result};
use candle_core::backprop::GradStore;
use candle_core::{CpuStorage, InplaceOp2, Layout, Storage, Tensor, Var};
use std::collections::BTreeMap;
use std::sync::Mutex;

/// A named host tensor: (name, shape, values).
pub type NamedHostTensor = (String, Vec<usize>, Vec<f32>);

/// Adam hyper-parameters.
#[derive(Clone, Copy, Debug)]
pub struct AdamConfig {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Clip the global gradient norm to this value (None: no clipping).
    pub clip_norm: Option<f64>,
}

impl Default for AdamConfig {
    fn default() -> Self {
        AdamConfig {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            clip_norm: Some(1.0),
        }
    }
}

/// Adam over a fixed, named set of parameters.
pub struct Adam {
    pub config: AdamConfig,
    params: Vec<(String, Var)>,
    /// Moments on the host, updated in one pass per parameter (as candle ops, an update took
    /// ~15 element-wise passes, each allocating: 10 % of a training step).
    first_moment: Vec<Vec<f32>>,
    second_moment: Vec<Vec<f32>>,
    /// Each parameter's multiplier of the step's learning rate (1 unless
    /// [`Adam::scale_learning_rate`] set it).
    lr_scale: Vec<f64>,
    /// Number of updates taken.
    pub step: u64,
}

/// What one update saw.
#[derive(Clone, Copy, Debug)]
pub struct StepStats {
    /// Global gradient norm before clipping.
    pub grad_norm: f64,
    /// Parameters that received no gradient this step.
    pub missing_grads: usize,
}

impl Adam {
    /// An optimizer for `params` (name, var), sorted by name for a stable state layout.
    pub fn new(mut params: Vec<(String, Var)>, config: AdamConfig) -> Result<Adam> {
        params.sort_by(|a, b| a.0.cmp(&b.0));
        let first_moment: Vec<Vec<f32>> = params
            .iter()
            .map(|(_, v)| vec![0.0; v.elem_count()])
            .collect();
        let second_moment = first_moment.clone();
        let lr_scale = vec![1.0; params.len()];
        Ok(Adam {
            config,
            params,
            first_moment,
            second_moment,
            lr_scale,
            step: 0,
        })
    }

    /// Multiplies the learning rate of every parameter whose name starts with `prefix` by
    /// `factor` (a later call for the same parameter replaces the factor). Adam moves each
    /// weight by about the learning rate a step whatever its gradient's size, so weights that
    /// start far from where they must go (a layer grown at zero) need a larger rate, not a
    /// larger gradient. Returns how many parameters matched.
    pub fn scale_learning_rate(&mut self, prefix: &str, factor: f64) -> Result<usize> {
        if !(factor > 0.0 && factor.is_finite()) {
            bail!("a learning-rate factor must be a positive number (got {factor} for `{prefix}`)");
        }
        let mut matched = 0;
        for ((name, _), scale) in self.params.iter().zip(self.lr_scale.iter_mut()) {
            if name.starts_with(prefix) {
                *scale = factor;
                matched += 1;
            }
        }
        Ok(matched)
    }

    /// Parameter names, in state order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.params.iter().map(|(n, _)| n.as_str())
    }

    /// One update with learning rate `lr` from `grads`. Returns the pre-clip gradient norm.
    ///
    /// Two passes over each gradient, read where candle left it (a sum of squares, then the
    /// update), and the weights changed in place: copying the gradients and weights out to
    /// vectors and back took half the update's time on the hypernetwork-sized parameters.
    pub fn step(&mut self, grads: &GradStore, lr: f64) -> Result<StepStats> {
        let c = self.config;
        let grads: Vec<Option<Tensor>> = self
            .params
            .iter()
            .map(|(_, v)| grads.get(v.as_tensor()).map(|g| g.contiguous()).transpose())
            .collect::<candle_core::Result<_>>()?;
        let missing_grads = grads.iter().filter(|g| g.is_none()).count();
        let mut sum_sq = 0f64;
        for g in grads.iter().flatten() {
            sum_sq += with_f32(g, sum_of_squares)?;
        }
        let grad_norm = sum_sq.sqrt();
        if !grad_norm.is_finite() {
            bail!("gradient norm is not finite");
        }
        let scale = match c.clip_norm {
            Some(max) if grad_norm > max => (max / grad_norm) as f32,
            _ => 1.0,
        };
        self.step += 1;
        let t = self.step as i32;
        let step_size = lr / (1.0 - c.beta1.powi(t));
        let inv_bias2 = (1.0 / (1.0 - c.beta2.powi(t))) as f32;
        for (i, g) in grads.into_iter().enumerate() {
            let Some(g) = g else { continue };
            let var = &self.params[i].1;
            let update = AdamUpdate {
                moments: Mutex::new((&mut self.first_moment[i], &mut self.second_moment[i])),
                scale,
                beta1: c.beta1 as f32,
                beta2: c.beta2 as f32,
                step_size: (step_size * self.lr_scale[i]) as f32,
                inv_bias2,
                eps: c.eps as f32,
            };
            var.as_tensor().inplace_op2(&g, &update)?;
        }
        Ok(StepStats {
            grad_norm,
            missing_grads,
        })
    }

    /// The optimizer state as named host tensors: `{prefix}m/<name>`, `{prefix}v/<name>`.
    pub fn state_tensors(&self, prefix: &str) -> Result<Vec<NamedHostTensor>> {
        let mut owned = Vec::new();
        for (i, (name, _)) in self.params.iter().enumerate() {
            let dims = self.params[i].1.dims().to_vec();
            for (moment, t) in [("m", &self.first_moment[i]), ("v", &self.second_moment[i])] {
                owned.push((format!("{prefix}{moment}/{name}"), dims.clone(), t.clone()));
            }
        }
        Ok(owned)
    }

    /// Restores moments written by [`Adam::state_tensors`] with the same prefix, and the step.
    pub fn load_state_tensors(&mut self, file: &TensorFile, prefix: &str, step: u64) -> Result<()> {
        for (i, (pname, var)) in self.params.iter().enumerate() {
            let dims: Vec<Option<usize>> = var.dims().iter().map(|&d| Some(d)).collect();
            for (moment, slot) in [
                ("m", &mut self.first_moment[i]),
                ("v", &mut self.second_moment[i]),
            ] {
                let (_, data) = file.f32_tensor(&format!("{prefix}{moment}/{pname}"), &dims)?;
                *slot = data;
            }
        }
        self.step = step;
        Ok(())
    }

    /// The optimizer state alone as safetensors bytes (metadata `format`, `step`).
    pub fn state_bytes(&self) -> Result<Vec<u8>> {
        let owned = self.state_tensors("")?;
        let tensors: Vec<F32Tensor> = owned
            .iter()
            .map(|(n, s, d)| F32Tensor {
                name: n,
                shape: s.clone(),
                data: d,
            })
            .collect();
        let mut meta = BTreeMap::new();
        meta.insert("format".to_string(), "colf-adam/1".to_string());
        meta.insert("step".to_string(), self.step.to_string());
        Ok(serialize_f32(&tensors, &meta))
    }

    /// Restores state written by [`Adam::state_bytes`] for the same parameters.
    pub fn load_state(&mut self, bytes: &[u8], name: &str) -> Result<()> {
        let file = TensorFile::parse(bytes, name)?;
        if file.require_metadata("format")? != "colf-adam/1" {
            bail!("{name}: not an optimizer state file");
        }
        let step: u64 = file
            .require_metadata("step")?
            .parse()
            .map_err(|_| anyhow!("{name}: metadata `step` is not a number"))?;
        self.load_state_tensors(&file, "", step)
    }
}

/// Calls `f` on the values of a contiguous f32 CPU tensor.
fn with_f32<T>(t: &Tensor, f: impl FnOnce(&[f32]) -> T) -> Result<T> {
    let (storage, layout) = t.storage_and_layout();
    match (&*storage, layout.contiguous_offsets()) {
        (Storage::Cpu(CpuStorage::F32(data)), Some((start, end))) => Ok(f(&data[start..end])),
        _ => bail!("Adam: a gradient is not a contiguous f32 CPU tensor"),
    }
}

/// Σ x² in f64, in 8 independent lanes so the loop vectorises.
fn sum_of_squares(values: &[f32]) -> f64 {
    let mut lanes = [0f64; 8];
    let chunks = values.chunks_exact(8);
    let tail: f64 = chunks
        .remainder()
        .iter()
        .map(|&x| (x as f64) * (x as f64))
        .sum();
    for chunk in chunks {
        for (lane, &x) in lanes.iter_mut().zip(chunk) {
            *lane += (x as f64) * (x as f64);
        }
    }
    lanes.iter().sum::<f64>() + tail
}

/// Adam's update of one parameter in place: the weights (the op's target), its moments, from
/// its gradient (the op's operand).
struct AdamUpdate<'a> {
    moments: Mutex<(&'a mut Vec<f32>, &'a mut Vec<f32>)>,
    /// The clipping factor of the gradient.
    scale: f32,
    beta1: f32,
    beta2: f32,
    /// The learning rate over the first moment's bias correction.
    step_size: f32,
    /// 1 / the second moment's bias correction.
    inv_bias2: f32,
    eps: f32,
}

impl InplaceOp2 for AdamUpdate<'_> {
    fn name(&self) -> &'static str {
        "colf-adam"
    }

    fn cpu_fwd(
        &self,
        weights: &mut CpuStorage,
        weights_layout: &Layout,
        grad: &CpuStorage,
        grad_layout: &Layout,
    ) -> candle_core::Result<()> {
        let (CpuStorage::F32(w), CpuStorage::F32(g), Some((w0, w1)), Some((g0, g1))) = (
            weights,
            grad,
            weights_layout.contiguous_offsets(),
            grad_layout.contiguous_offsets(),
        ) else {
            candle_core::bail!("Adam: weights and gradient must be contiguous f32");
        };
        let mut moments = self.moments.lock().expect("Adam moments");
        let (m, v) = &mut *moments;
        let (w, g) = (&mut w[w0..w1], &g[g0..g1]);
        if w.len() != g.len() || m.len() != w.len() || v.len() != w.len() {
            candle_core::bail!("Adam: weights, gradient and moments differ in size");
        }
        let (beta1, beta2) = (self.beta1, self.beta2);
        for (((w, m), v), g) in w.iter_mut().zip(m.iter_mut()).zip(v.iter_mut()).zip(g) {
            let g = g * self.scale;
            *m = beta1 * *m + (1.0 - beta1) * g;
            *v = beta2 * *v + (1.0 - beta2) * g * g;
            *w -= self.step_size * *m / ((*v * self.inv_bias2).sqrt() + self.eps);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    fn quadratic_loss(w: &Var) -> Tensor {
        // (w - 3)² summed: minimum at 3.
        (w.as_tensor() - 3.0)
            .unwrap()
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
    }

    #[test]
    fn minimises_a_quadratic() {
        let w = Var::from_vec(vec![0.0f32, 10.0], 2, &Device::Cpu).unwrap();
        let mut adam = Adam::new(
            vec![("w".into(), w.clone())],
            AdamConfig {
                clip_norm: None,
                ..Default::default()
            },
        )
        .unwrap();
        for _ in 0..2000 {
            let grads = quadratic_loss(&w).backward().unwrap();
            adam.step(&grads, 0.05).unwrap();
        }
        let v = w.as_tensor().to_vec1::<f32>().unwrap();
        assert!(v.iter().all(|x| (x - 3.0).abs() < 1e-2), "{v:?}");
    }

    #[test]
    fn state_round_trip_resumes_exactly() {
        let run = |split: Option<usize>| -> Vec<f32> {
            let w = Var::from_vec(vec![0.5f32, -2.0, 7.0], 3, &Device::Cpu).unwrap();
            let mut adam = Adam::new(vec![("w".into(), w.clone())], AdamConfig::default()).unwrap();
            for i in 0..20 {
                if Some(i) == split {
                    // Simulate a stop: new optimizer and var restored from the saved state.
                    let state = adam.state_bytes().unwrap();
                    let saved = w.as_tensor().copy().unwrap();
                    let w2 = Var::from_tensor(&saved).unwrap();
                    let mut adam2 =
                        Adam::new(vec![("w".into(), w2.clone())], AdamConfig::default()).unwrap();
                    adam2.load_state(&state, "state").unwrap();
                    assert_eq!(adam2.step, i as u64);
                    for _ in i..20 {
                        let grads = quadratic_loss(&w2).backward().unwrap();
                        adam2.step(&grads, 0.1).unwrap();
                    }
                    return w2.as_tensor().to_vec1().unwrap();
                }
                let grads = quadratic_loss(&w).backward().unwrap();
                adam.step(&grads, 0.1).unwrap();
            }
            w.as_tensor().to_vec1().unwrap()
        };
        assert_eq!(run(None), run(Some(7)));
    }

    #[test]
    fn a_learning_rate_factor_scales_only_its_parameters_steps() {
        let start = vec![5.0f32, -5.0];
        let fast = Var::from_vec(start.clone(), 2, &Device::Cpu).unwrap();
        let slow = Var::from_vec(start.clone(), 2, &Device::Cpu).unwrap();
        let mut adam = Adam::new(
            vec![("bg.w".into(), fast.clone()), ("fg.w".into(), slow.clone())],
            AdamConfig::default(),
        )
        .unwrap();
        assert_eq!(adam.scale_learning_rate("bg.", 4.0).unwrap(), 1);
        assert_eq!(adam.scale_learning_rate("nothing.", 2.0).unwrap(), 0);
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(adam.scale_learning_rate("bg.", bad).is_err(), "{bad}");
        }
        let loss = (quadratic_loss(&fast) + quadratic_loss(&slow)).unwrap();
        adam.step(&loss.backward().unwrap(), 0.01).unwrap();
        // Adam's first step is the learning rate times the gradient's sign, per weight.
        let moved = |v: &Var| -> Vec<f32> {
            let now = v.as_tensor().to_vec1::<f32>().unwrap();
            now.iter().zip(&start).map(|(a, b)| (a - b).abs()).collect()
        };
        for (f, s) in moved(&fast).into_iter().zip(moved(&slow)) {
            assert!(
                (s - 0.01).abs() < 1e-5 && (f - 0.04).abs() < 1e-5,
                "{f} {s}"
            );
        }
    }

    #[test]
    fn clipping_bounds_the_step() {
        let w = Var::from_vec(vec![1000.0f32], 1, &Device::Cpu).unwrap();
        let mut adam = Adam::new(vec![("w".into(), w.clone())], AdamConfig::default()).unwrap();
        let stats = adam
            .step(&quadratic_loss(&w).backward().unwrap(), 0.1)
            .unwrap();
        assert!(stats.grad_norm > 1000.0);
        assert_eq!(stats.missing_grads, 0);
    }
}
