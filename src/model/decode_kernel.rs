//! The light-field decoder as one candle op with a hand-written backward: every slot's light
//! field (on the camera ray and, with `shadow_light`, on its shadow line), the colour, ordering
//! and shadow heads, the shadows and the compositor, for all rays of a batch.
//!
//! Why: built from candle ops, a training step spent most of its time outside the matmuls —
//! gathers and permutes of [B, R, S] tensors, element-wise passes with an allocation each, and
//! a backward that ran on under one core (`docs/speed.md`). Here, in the manner of llm.c and
//! tiny-cuda-nn:
//! - **Field passes** (one work unit per scene and field, ray chunks of [`CHUNK`] rays that stay
//!   in cache): the light field's layers and the heads as one `gemm` each, bias and ReLU in the
//!   same pass; their activations are kept for the backward.
//! - **Ray passes** (one unit per scene and chunk of rays): the shadows, the compositor's MLP V
//!   (one `gemm` per layer over the chunk's rays × fields), the softmax and the blend.
//! - The backward runs the same units in reverse: per ray the compositor's and the blend's
//!   derivatives, then per field the heads' and the light field's layers (two `gemm`s each: the
//!   input's and the weight's gradient), down to the generated weights, the shared heads'
//!   parameters and — when they are differentiable, as in refinement with moving frames — the
//!   encoded rays and ordering shifts, or the few offsets they move with ([`RayMotion`]).
//!
//! Units run in parallel on rayon's threads with single-threaded `gemm`s; each unit's share of a
//! shared gradient is kept apart and the shares are summed in unit order, so the result is the
//! same bytes whatever the thread count. `tests/decode_kernel.rs` checks values and every
//! gradient against the candle composition (`ColfNet::decode_reference`) on random models.
//! With a support ([`DecodeOp::with_support`]) a field runs only on the rays listed for it.
//!
//! The op's inputs: the S·B light fields' generated parameters packed as [B·S, P] (per layer the
//! weight [in, out] row-major, then the bias), the heads' and compositor's parameters packed as
//! [Q] ([`SharedLayout`]), and the rays. Its output packs, per ray, [`Channels`]: the composited
//! colour, the log-weights, the weights, the world orderings, the shadow densities and each
//! field's colour; `ColfNet::decode` narrows it into a `Decoded`.

use super::config::Config;
use super::heads::SHADOW_LOGIT_GAIN;
use super::light_field::SlotWeights;
use super::net::{Decoded, LightFieldDecoder};
use super::rays::{within_reach, RayBatch};
use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Storage, Tensor};
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Wall time the kernel has run in this process, forward and backward, in nanoseconds.
static KERNEL_NANOS: AtomicU64 = AtomicU64::new(0);

/// Seconds the decode kernel has run in this process so far (forward and backward passes,
/// wall time). The trainer logs each step's difference, so a step's decoder share is measured
/// inside the step rather than estimated from a separate benchmark.
pub fn kernel_seconds() -> f64 {
    KERNEL_NANOS.load(Ordering::Relaxed) as f64 * 1e-9
}

/// Adds the time from its creation to its drop to [`KERNEL_NANOS`].
struct KernelTimer(Instant);

impl KernelTimer {
    fn start() -> Self {
        Self(Instant::now())
    }
}

impl Drop for KernelTimer {
    fn drop(&mut self) {
        let nanos = u64::try_from(self.0.elapsed().as_nanos()).unwrap_or(u64::MAX);
        KERNEL_NANOS.fetch_add(nanos, Ordering::Relaxed);
    }
}

/// Rays per chunk of a field pass: a chunk's activations (128 × 256 floats per layer at the
/// paper's width) stay in the core's L2 cache between a layer's forward and the next.
const CHUNK: usize = 128;
/// Rays per unit of the ray passes.
const RAY_CHUNK: usize = 64;

/// One dense layer of an MLP inside a flat parameter buffer: y = act(x·W + b) with W read as
/// an [in, out] matrix at `w` with row stride `w_rs` and column stride `w_cs` (a generated
/// weight is [in, out] row-major; a `Linear` weight [out, in] is read transposed).
#[derive(Clone, Copy, Debug)]
pub struct DenseLayer {
    pub w: usize,
    pub w_rs: usize,
    pub w_cs: usize,
    pub bias: Option<usize>,
    pub fan_in: usize,
    pub fan_out: usize,
    pub relu: bool,
}

/// An MLP's layers, input layer first, ReLU after every layer but the last.
#[derive(Clone, Debug, Default)]
pub struct MlpLayout {
    pub layers: Vec<DenseLayer>,
}

impl MlpLayout {
    fn out_dim(&self) -> usize {
        self.layers.last().map_or(0, |l| l.fan_out)
    }
    fn widest(&self) -> usize {
        self.layers
            .iter()
            .map(|l| l.fan_in.max(l.fan_out))
            .max()
            .unwrap_or(0)
    }
    /// Multiply-adds per row of one forward pass.
    fn macs(&self) -> usize {
        self.layers.iter().map(|l| l.fan_in * l.fan_out).sum()
    }
}

/// Lays out `Linear`-style layers (weight [out, in] then bias [out], or no bias on the last
/// layer when `last_bias` is false) one after the other from `offset`; returns the layout and
/// the offset after it.
fn linear_layers(dims: &[usize], last_bias: bool, mut offset: usize) -> (MlpLayout, usize) {
    let mut layers = Vec::new();
    for l in 0..dims.len() - 1 {
        let (fan_in, fan_out) = (dims[l], dims[l + 1]);
        let last = l + 2 == dims.len();
        let w = offset;
        offset += fan_in * fan_out;
        let bias = (!last || last_bias).then(|| {
            offset += fan_out;
            offset - fan_out
        });
        layers.push(DenseLayer {
            w,
            w_rs: 1,
            w_cs: fan_in,
            bias,
            fan_in,
            fan_out,
            relu: !last,
        });
    }
    (MlpLayout { layers }, offset)
}

/// The generated light field's layers inside one field's packed parameters: per layer the
/// weight [in, out] row-major, then the bias [out]. Returns the layout and P.
pub fn field_layout(cfg: &Config) -> (MlpLayout, usize) {
    let dims = cfg.lfn_dims();
    let mut offset = 0;
    let mut layers = Vec::new();
    for l in 0..dims.len() - 1 {
        let (fan_in, fan_out) = (dims[l], dims[l + 1]);
        layers.push(DenseLayer {
            w: offset,
            w_rs: fan_out,
            w_cs: 1,
            bias: Some(offset + fan_in * fan_out),
            fan_in,
            fan_out,
            relu: l + 2 < dims.len(),
        });
        offset += fan_in * fan_out + fan_out;
    }
    (MlpLayout { layers }, offset)
}

/// Where the heads' and the compositor's parameters lie in the packed shared vector, in the
/// order `ColfNet::decode` packs them: `heads.color.*`, `heads.ordering.*`, `heads.shadow.*`
/// (with a shadow head), `compositor.v.*`, `compositor.gap_log_slope`.
#[derive(Clone, Debug)]
pub struct SharedLayout {
    pub color: MlpLayout,
    pub ordering: MlpLayout,
    /// Offsets of the shadow head's weight [F] and bias [1].
    pub shadow: Option<(usize, usize)>,
    pub v: MlpLayout,
    pub gap_log_slope: usize,
    pub len: usize,
}

impl SharedLayout {
    pub fn new(cfg: &Config) -> SharedLayout {
        let f = cfg.lfn_features;
        let head_dims = |out: usize| {
            let mut d = vec![f];
            d.extend(std::iter::repeat_n(cfg.head_hidden, cfg.head_hidden_layers));
            d.push(out);
            d
        };
        let (color, offset) = linear_layers(&head_dims(3), true, 0);
        let (ordering, mut offset) = linear_layers(&head_dims(1), true, offset);
        let shadow = cfg.shadow_head.then(|| {
            offset += f + 1;
            (offset - f - 1, offset - 1)
        });
        let mut v_dims = vec![2];
        v_dims.extend(std::iter::repeat_n(
            cfg.compositor_hidden,
            cfg.compositor_hidden_layers,
        ));
        v_dims.push(1);
        let (v, offset) = linear_layers(&v_dims, false, offset);
        SharedLayout {
            color,
            ordering,
            shadow,
            v,
            gap_log_slope: offset,
            len: offset + 1,
        }
    }
}

/// Per ray, the op's output channels: [rgb 3 | log-weights S | weights S | orderings S |
/// shadow σ S | colours 3·S].
#[derive(Clone, Copy, Debug)]
pub struct Channels {
    pub fields: usize,
}

impl Channels {
    pub const RGB: usize = 0;
    pub fn log_weights(&self) -> usize {
        3
    }
    pub fn weights(&self) -> usize {
        3 + self.fields
    }
    pub fn ordering(&self) -> usize {
        3 + 2 * self.fields
    }
    pub fn shadow(&self) -> usize {
        3 + 3 * self.fields
    }
    pub fn colors(&self) -> usize {
        3 + 4 * self.fields
    }
    pub fn count(&self) -> usize {
        3 + 7 * self.fields
    }
}

/// Everything about a decode that is not a tensor: sizes and layouts.
#[derive(Clone, Debug)]
pub struct DecodeShape {
    pub scenes: usize,
    pub fields: usize,
    pub rays: usize,
    pub in_dim: usize,
    pub field: MlpLayout,
    pub field_params: usize,
    pub shared: SharedLayout,
    /// Shadows read on each ray's shadow line (a second light-field pass), not on the ray.
    pub shadow_lines: bool,
    pub scene_scale: f32,
    /// With shadow lines, `Config::shadow_reach_bound`: lines beyond it are not evaluated.
    pub shadow_reach: Option<f32>,
    /// `Config::slot_reach_bound`: a foreground field is absent on the rays beyond it, as
    /// outside a support ([`DecodeOp::with_support`]).
    pub slot_reach: Option<f32>,
}

impl DecodeShape {
    pub fn new(cfg: &Config, scenes: usize, fields: usize, rays: usize) -> DecodeShape {
        let (field, field_params) = field_layout(cfg);
        DecodeShape {
            scenes,
            fields,
            rays,
            in_dim: cfg.ray_input_dim(),
            field,
            field_params,
            shared: SharedLayout::new(cfg),
            shadow_lines: cfg.shadow_head && cfg.shadow_light.is_some(),
            scene_scale: cfg.scene_scale as f32,
            shadow_reach: cfg.shadow_reach_bound(),
            slot_reach: cfg.slot_reach_bound(),
        }
    }

    fn channels(&self) -> Channels {
        Channels {
            fields: self.fields,
        }
    }

    /// Multiply-adds of one forward pass over all rays and fields (light fields, heads,
    /// shadow head, shadow-line passes of the foreground fields, compositor), and of the
    /// backward the op runs: two per forward one (the input's and the weight's gradient), less
    /// the light fields' first-layer input gradients unless `ray_grads`. ×2 for FLOPs.
    pub fn macs(&self, ray_grads: bool) -> (f64, f64) {
        let (b, s, r) = (self.scenes as f64, self.fields as f64, self.rays as f64);
        let lfn = self.field.macs() as f64;
        let first = (self.field.layers[0].fan_in * self.field.layers[0].fan_out) as f64;
        let heads = (self.shared.color.macs() + self.shared.ordering.macs()) as f64;
        let v = self.shared.v.macs() as f64;
        let fg = (s - 1.0).max(0.0);
        let shadow_head = if self.shared.shadow.is_some() {
            fg * self.field.out_dim() as f64
        } else {
            0.0
        };
        let passes = s + if self.shadow_lines && self.shared.shadow.is_some() {
            fg
        } else {
            0.0
        };
        let fwd = b * r * (passes * lfn + s * (heads + v) + shadow_head);
        let skipped = if ray_grads {
            0.0
        } else {
            b * r * passes * first
        };
        (fwd, 2.0 * fwd - skipped)
    }
}

/// dst (+)= lhs · rhs for strided [m, k] · [k, n] views of slices, on one thread.
#[allow(clippy::too_many_arguments)]
fn matmul(
    (m, n, k): (usize, usize, usize),
    dst: &mut [f32],
    (dst_rs, dst_cs): (usize, usize),
    accumulate: bool,
    lhs: &[f32],
    (lhs_rs, lhs_cs): (usize, usize),
    rhs: &[f32],
    (rhs_rs, rhs_cs): (usize, usize),
) {
    if m == 0 || n == 0 {
        return;
    }
    let last = |rows: usize, cols: usize, rs: usize, cs: usize| (rows - 1) * rs + (cols - 1) * cs;
    assert!(
        last(m, n, dst_rs, dst_cs) < dst.len(),
        "matmul: dst too small"
    );
    if k == 0 {
        if !accumulate {
            for i in 0..m {
                for j in 0..n {
                    dst[i * dst_rs + j * dst_cs] = 0.0;
                }
            }
        }
        return;
    }
    assert!(
        last(m, k, lhs_rs, lhs_cs) < lhs.len(),
        "matmul: lhs too small"
    );
    assert!(
        last(k, n, rhs_rs, rhs_cs) < rhs.len(),
        "matmul: rhs too small"
    );
    // SAFETY: the asserts above keep every element each view addresses inside its slice; dst
    // does not alias lhs or rhs (a &mut and two & borrows).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            dst_cs as isize,
            dst_rs as isize,
            accumulate,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// y [n, out] = act(x [n, in] · W + b).
fn dense_forward(layer: &DenseLayer, params: &[f32], x: &[f32], n: usize, y: &mut [f32]) {
    let (i, o) = (layer.fan_in, layer.fan_out);
    matmul(
        (n, o, i),
        &mut y[..n * o],
        (o, 1),
        false,
        &x[..n * i],
        (i, 1),
        &params[layer.w..],
        (layer.w_rs, layer.w_cs),
    );
    let bias = layer.bias.map(|b| &params[b..b + o]);
    for row in y[..n * o].chunks_exact_mut(o) {
        if let Some(bias) = bias {
            for (v, b) in row.iter_mut().zip(bias) {
                *v += b;
            }
        }
        if layer.relu {
            for v in row.iter_mut() {
                *v = v.max(0.0);
            }
        }
    }
}

/// The backward of [`dense_forward`]: `g` [n, out] holds dL/dy on entry (it is masked by the
/// ReLU in place); adds dL/dW and dL/db to `grads` (laid out like `params`) and, when `dx` is
/// given, writes dL/dx [n, in] there.
#[allow(clippy::too_many_arguments)]
fn dense_backward(
    layer: &DenseLayer,
    params: &[f32],
    x: &[f32],
    y: &[f32],
    n: usize,
    g: &mut [f32],
    grads: &mut [f32],
    dx: Option<&mut [f32]>,
) {
    let (i, o) = (layer.fan_in, layer.fan_out);
    let g = &mut g[..n * o];
    if layer.relu {
        // A select, not a conditional store, so the loop vectorises.
        for (gv, yv) in g.iter_mut().zip(&y[..n * o]) {
            *gv = if *yv > 0.0 { *gv } else { 0.0 };
        }
    }
    // dW [in, out] += xᵀ [in, n] · g [n, out].
    matmul(
        (i, o, n),
        &mut grads[layer.w..],
        (layer.w_rs, layer.w_cs),
        true,
        &x[..n * i],
        (1, i),
        g,
        (o, 1),
    );
    if let Some(b) = layer.bias {
        let db = &mut grads[b..b + o];
        for row in g.chunks_exact(o) {
            for (d, v) in db.iter_mut().zip(row) {
                *d += v;
            }
        }
    }
    if let Some(dx) = dx {
        // dx [n, in] = g [n, out] · Wᵀ [out, in].
        matmul(
            (n, i, o),
            &mut dx[..n * i],
            (i, 1),
            false,
            g,
            (o, 1),
            &params[layer.w..],
            (layer.w_cs, layer.w_rs),
        );
    }
}

/// An MLP's activations for all rows of a unit, one buffer per layer ([rows, out]). The buffers
/// come from [`BUFFERS`] and go back there when the activations are dropped (with the op, after
/// the backward), so a training run's steps reuse the same memory instead of zeroing ~100 MB of
/// fresh buffers each.
#[derive(Debug, Default)]
struct Activations {
    layers: Vec<Vec<f32>>,
}

/// Activation buffers kept for the next op: their contents are stale, and every element is
/// written by a forward pass before anything reads it (each layer's `gemm` writes all its rows).
static BUFFERS: Mutex<Vec<Vec<f32>>> = Mutex::new(Vec::new());

/// At most this many buffers wait in [`BUFFERS`] (a step of K = 60 slots needs ~2,000).
const MAX_KEPT_BUFFERS: usize = 4096;

/// A buffer of `len` floats whose contents are unspecified (a kept one when one is large enough).
fn buffer(len: usize) -> Vec<f32> {
    let kept = {
        let mut kept = BUFFERS.lock().unwrap_or_else(|e| e.into_inner());
        let best = kept
            .iter()
            .enumerate()
            .filter(|(_, b)| b.capacity() >= len)
            .min_by_key(|(_, b)| b.capacity())
            .map(|(i, _)| i);
        best.map(|i| kept.swap_remove(i))
    };
    match kept {
        Some(mut b) => {
            // Shrinking keeps the old values; growing within the capacity zero-fills the rest.
            b.resize(len, 0.0);
            b
        }
        None => vec![0f32; len],
    }
}

impl Drop for Activations {
    fn drop(&mut self) {
        let mut kept = BUFFERS.lock().unwrap_or_else(|e| e.into_inner());
        for b in self.layers.drain(..) {
            if kept.len() < MAX_KEPT_BUFFERS && b.capacity() > 0 {
                kept.push(b);
            }
        }
    }
}

impl Activations {
    fn new(mlp: &MlpLayout, rows: usize) -> Activations {
        Activations {
            layers: mlp
                .layers
                .iter()
                .map(|l| buffer(rows * l.fan_out))
                .collect(),
        }
    }
    fn output(&self) -> &[f32] {
        self.layers.last().map_or(&[], |v| v.as_slice())
    }
}

/// Forward of `mlp` on rows [r0, r0 + n) of `x` (the whole unit's input, [rows, in]).
fn mlp_forward(
    mlp: &MlpLayout,
    params: &[f32],
    x: &[f32],
    acts: &mut Activations,
    r0: usize,
    n: usize,
) {
    for (l, layer) in mlp.layers.iter().enumerate() {
        let (before, rest) = acts.layers.split_at_mut(l);
        let input = if l == 0 {
            &x[r0 * layer.fan_in..]
        } else {
            &before[l - 1][r0 * layer.fan_in..]
        };
        dense_forward(layer, params, input, n, &mut rest[0][r0 * layer.fan_out..]);
    }
}

/// Scratch rows for an MLP's backward: two ping-pong gradient buffers.
struct Scratch {
    a: Vec<f32>,
    b: Vec<f32>,
}

impl Scratch {
    fn new(width: usize, n: usize) -> Scratch {
        Scratch {
            a: vec![0f32; width * n],
            b: vec![0f32; width * n],
        }
    }
}

/// Backward of `mlp` on rows [r0, r0 + n): `g_out` [n, out] is dL/d(output); parameter
/// gradients are added to `grads`; dL/dx [n, in] is written to `dx` when given.
#[allow(clippy::too_many_arguments)]
fn mlp_backward(
    mlp: &MlpLayout,
    params: &[f32],
    x: &[f32],
    acts: &Activations,
    r0: usize,
    n: usize,
    g_out: &[f32],
    grads: &mut [f32],
    dx: Option<&mut [f32]>,
    scratch: &mut Scratch,
) {
    let last = mlp.layers.len() - 1;
    scratch.a[..n * mlp.out_dim()].copy_from_slice(&g_out[..n * mlp.out_dim()]);
    let mut dx = dx;
    for l in (0..=last).rev() {
        let layer = &mlp.layers[l];
        let input = if l == 0 {
            &x[r0 * layer.fan_in..]
        } else {
            &acts.layers[l - 1][r0 * layer.fan_in..]
        };
        let y = &acts.layers[l][r0 * layer.fan_out..];
        let Scratch { a, b } = scratch;
        let target = if l > 0 {
            Some(&mut b[..])
        } else {
            dx.as_deref_mut()
        };
        dense_backward(layer, params, input, y, n, a, grads, target);
        std::mem::swap(&mut scratch.a, &mut scratch.b);
    }
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// softplus(x) = max(x, 0) + ln(1 + e^−|x|), as `heads.rs` computes it.
fn softplus(x: f32) -> f32 {
    x.max(0.0) + (-x.abs()).exp().ln_1p()
}

/// The rays' data, borrowed from the op's inputs.
struct Rays<'a> {
    coords: &'a [f32],
    lines: Option<&'a [f32]>,
    on_ground: Option<&'a [f32]>,
    shift: &'a [f32],
}

/// One field's forward activations (all the scene's rays).
#[derive(Debug, Default)]
struct FieldPass {
    lfn: Activations,
    color: Activations,
    /// sigmoid of the colour head [R, 3].
    rgb: Vec<f32>,
    ordering: Activations,
    /// The shadow-line pass (foreground fields with shadow lines), on the shadow rows.
    shadow_lfn: Option<Activations>,
    /// With shadow lines: the rows whose line is evaluated — on the ground (elsewhere σ is 0)
    /// and within `shadow_reach` — in order; None: every row.
    shadow_rows: Option<Vec<u32>>,
    /// With `shadow_rows`: those rows' shadow lines, gathered.
    shadow_inputs: Option<Vec<f32>>,
    /// w·f + b of the shadow head (foreground fields with a shadow head), per shadow row
    /// (with shadow lines) or per row.
    shadow_affine: Vec<f32>,
    /// σ [R] (0 for the background and for rays off the ground).
    sigma: Vec<f32>,
    /// With a support ([`DecodeOp::with_support`]): the rays this field is evaluated on, in
    /// order; every per-ray array above then has one row per such ray. None: every ray.
    rows: Option<Vec<u32>>,
    /// With a support: each ray's row, [`INACTIVE`] where the field is not evaluated.
    position: Vec<u32>,
    /// With a support: the rows' inputs (ray coordinates, shadow lines), gathered.
    inputs: Option<Vec<f32>>,
    line_inputs: Option<Vec<f32>>,
}

/// A ray a field is not evaluated on ([`FieldPass::position`]).
const INACTIVE: u32 = u32::MAX;

impl FieldPass {
    /// The row of ray `r`, None where the field is not evaluated on it.
    fn row(&self, r: usize) -> Option<usize> {
        match &self.rows {
            None => Some(r),
            Some(_) => match self.position[r] {
                INACTIVE => None,
                p => Some(p as usize),
            },
        }
    }

    /// The ray of row `i`.
    fn ray(&self, i: usize) -> usize {
        self.rows.as_ref().map_or(i, |rows| rows[i] as usize)
    }

    /// Number of rows.
    fn len(&self) -> usize {
        self.sigma.len()
    }

    /// The row of shadow row `j`.
    fn shadow_row(&self, j: usize) -> usize {
        self.shadow_rows.as_ref().map_or(j, |rows| rows[j] as usize)
    }
}

/// One ray chunk's compositor activations.
#[derive(Debug, Default)]
struct RayPass {
    /// V's input [n·S, 2] and activations.
    v_in: Vec<f32>,
    v: Activations,
    world: Vec<f32>,
    gap: Vec<f32>,
    weights: Vec<f32>,
    lit: Vec<f32>,
    /// Colours after the shadows [n, S, 3].
    colors: Vec<f32>,
}

/// What the forward keeps for the backward.
#[derive(Debug, Default)]
struct Saved {
    fields: Vec<FieldPass>,
    rays: Vec<RayPass>,
}

/// Where the rays come from: inside the op's third input (when they need gradients: the
/// input is [coords | shadow lines | shift] flattened), held by the op with only the
/// coordinates as its third input (no copies), or held by the op with the third input the
/// offsets they move with ([`RayMotion`]).
#[derive(Debug)]
pub enum RayInputs {
    Packed {
        on_ground: Option<Vec<f32>>,
    },
    Held {
        lines: Option<Tensor>,
        on_ground: Option<Vec<f32>>,
        shift: Tensor,
    },
    Moving {
        coords: Tensor,
        lines: Option<Tensor>,
        on_ground: Option<Vec<f32>>,
        shift: Tensor,
        motion: Arc<dyn RayMotion>,
    },
}

/// Encoded rays that are a function of a few offsets (test-time refinement moves the
/// foreground frames' origins, `encode/refine.rs`), linearised at offsets 0: the op's third
/// input is the offsets, and its backward contracts each field's ray gradients to theirs inside
/// the parallel field passes. Handing candle the gradient of every encoded ray instead (the
/// packed input) cost a refinement step about ten serial passes over megabytes: the packing, a
/// zeroed buffer and a sum per tensor in candle's backward, the copies of the ops that contract
/// it.
pub trait RayMotion: Send + Sync + std::fmt::Debug {
    /// Number of offsets (the op's third input).
    fn offsets(&self) -> usize;
    /// dL/d(offsets) through field `u`'s (= b·S + s) encoded rays `coords` [R, in] and, with
    /// shadow lines, its lines [R, in] (their gradient 0 where the field casts none), each
    /// given with its gradient.
    fn field_gradient(
        &self,
        u: usize,
        coords: (&[f32], &[f32]),
        lines: Option<(&[f32], &[f32])>,
    ) -> Vec<f64>;
    /// dL/d(offsets) through the ordering shifts, from their gradient [B, R, S].
    fn shift_gradient(&self, d_shift: &[f32]) -> Vec<f64>;
}

/// The op: see the module documentation.
#[derive(Debug)]
pub struct DecodeOp {
    pub shape: DecodeShape,
    pub rays: RayInputs,
    /// Per field (B·S lists), the rays it is evaluated on (sorted); None: all (see
    /// [`DecodeOp::with_support`]).
    support: Option<Vec<Vec<u32>>>,
    saved: Mutex<Saved>,
}

/// A held tensor's f32 values (contiguous, of length `len`).
fn held_f32<'a>(
    storage: &'a Storage,
    layout: &Layout,
    what: &str,
    len: usize,
) -> Result<&'a [f32]> {
    let Storage::Cpu(cpu) = storage else {
        candle_core::bail!("decode kernel: {what} must be on the CPU")
    };
    let v = storage_f32(cpu, layout, what)?;
    if v.len() != len {
        candle_core::bail!("decode kernel: {what} have the wrong length");
    }
    Ok(v)
}

fn storage_f32<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    let CpuStorage::F32(v) = s else {
        candle_core::bail!("decode kernel: {what} must be f32")
    };
    let Some((a, b)) = l.contiguous_offsets() else {
        candle_core::bail!("decode kernel: {what} must be contiguous")
    };
    Ok(&v[a..b])
}

/// Runs `f` on rays whose lines and shifts the op holds (`nl`, `ns`: their expected lengths).
fn held_rays<T>(
    coords: &[f32],
    lines: Option<&Tensor>,
    on_ground: Option<&[f32]>,
    shift: &Tensor,
    (nl, ns): (usize, usize),
    f: impl FnOnce(&Rays) -> Result<T>,
) -> Result<T> {
    let line_guard = lines.map(|t| t.storage_and_layout());
    let shift_guard = shift.storage_and_layout();
    let lines = match &line_guard {
        Some((g, l)) if nl > 0 => Some(held_f32(g, l, "shadow lines", nl)?),
        _ => None,
    };
    let shift = held_f32(&shift_guard.0, shift_guard.1, "shifts", ns)?;
    f(&Rays {
        coords,
        lines,
        on_ground,
        shift,
    })
}

/// Unit ranges of the ray passes: (scene, first ray, rays).
fn ray_units(shape: &DecodeShape) -> Vec<(usize, usize, usize)> {
    let mut units = Vec::new();
    for b in 0..shape.scenes {
        let mut r0 = 0;
        while r0 < shape.rays {
            let n = RAY_CHUNK.min(shape.rays - r0);
            units.push((b, r0, n));
            r0 += n;
        }
    }
    units
}

impl DecodeOp {
    pub fn new(shape: DecodeShape, rays: RayInputs) -> DecodeOp {
        DecodeOp {
            shape,
            rays,
            support: None,
            saved: Mutex::new(Saved::default()),
        }
    }

    /// Evaluates field u only on the rays `support[u]` (sorted, in range): elsewhere the field
    /// counts as absent — compositor weight 0 (log-weight −∞), ordering +∞, no shadow, no
    /// colour, no gradient. For test-time refinement, where a slot's weight is negligible
    /// outside its object's neighbourhood (`encode/refine.rs` decides where, and with what
    /// margin). The background fields (s = 0) must keep every ray.
    pub fn with_support(mut self, support: Vec<Vec<u32>>) -> Result<DecodeOp> {
        let sh = &self.shape;
        if support.len() != sh.scenes * sh.fields {
            candle_core::bail!("decode kernel: a support per field is needed");
        }
        for (u, rows) in support.iter().enumerate() {
            let sorted = rows.windows(2).all(|w| w[0] < w[1]);
            let in_range = rows.last().is_none_or(|&r| (r as usize) < sh.rays);
            if !sorted || !in_range || (u % sh.fields == 0 && rows.len() != sh.rays) {
                candle_core::bail!("decode kernel: field {u}'s support is not valid");
            }
        }
        self.support = Some(support);
        Ok(self)
    }

    /// Length of the packed ray input (coords, lines, shift).
    pub fn packed_len(&self) -> (usize, usize, usize) {
        let sh = &self.shape;
        let coords = sh.scenes * sh.fields * sh.rays * sh.in_dim;
        let lines = if sh.shadow_lines { coords } else { 0 };
        (coords, lines, sh.scenes * sh.rays * sh.fields)
    }

    /// Runs `f` on the rays: `input` is the op's third input.
    fn with_rays<T>(&self, input: &[f32], f: impl FnOnce(&Rays) -> Result<T>) -> Result<T> {
        let (nc, nl, ns) = self.packed_len();
        match &self.rays {
            RayInputs::Packed { on_ground } => {
                if input.len() != nc + nl + ns {
                    candle_core::bail!("decode kernel: packed rays have the wrong length");
                }
                f(&Rays {
                    coords: &input[..nc],
                    lines: (nl > 0).then(|| &input[nc..nc + nl]),
                    on_ground: on_ground.as_deref(),
                    shift: &input[nc + nl..],
                })
            }
            RayInputs::Held {
                lines,
                on_ground,
                shift,
            } => {
                if input.len() != nc {
                    candle_core::bail!("decode kernel: ray coordinates have the wrong length");
                }
                held_rays(
                    input,
                    lines.as_ref(),
                    on_ground.as_deref(),
                    shift,
                    (nl, ns),
                    f,
                )
            }
            RayInputs::Moving {
                coords,
                lines,
                on_ground,
                shift,
                motion,
            } => {
                // The held rays are those at offsets 0: other offsets would need the motion's
                // forward, which refinement never asks for (it moves the frames between steps).
                if input.len() != motion.offsets() || input.iter().any(|v| *v != 0.0) {
                    candle_core::bail!("decode kernel: ray offsets must be zero when read");
                }
                let (guard, layout) = coords.storage_and_layout();
                let coords = held_f32(&guard, layout, "ray coordinates", nc)?;
                held_rays(
                    coords,
                    lines.as_ref(),
                    on_ground.as_deref(),
                    shift,
                    (nl, ns),
                    f,
                )
            }
        }
    }

    /// The field passes: light field and heads of field u = b·S + s on all of scene b's rays.
    fn field_forward(&self, u: usize, fields: &[f32], shared: &[f32], rays: &Rays) -> FieldPass {
        let sh = &self.shape;
        let (r, s, in_dim) = (sh.rays, u % sh.fields, sh.in_dim);
        let params = &fields[u * sh.field_params..(u + 1) * sh.field_params];
        let x_all = &rays.coords[u * r * in_dim..(u + 1) * r * in_dim];
        let support = self.support.as_ref().map(|support| &support[u]);
        // A foreground field within `slot_reach` only: the support's rays (or all) that are.
        let reached = sh.slot_reach.filter(|_| s > 0).and_then(|bound| {
            let within = |&ri: &u32| {
                let ri = ri as usize;
                within_reach(&x_all[ri * in_dim..(ri + 1) * in_dim], Some(bound))
            };
            let kept: Vec<u32> = match support {
                Some(rows) => rows.iter().copied().filter(within).collect(),
                None => (0..r as u32).filter(within).collect(),
            };
            (kept.len() < support.map_or(r, Vec::len)).then_some(kept)
        });
        let active = reached.as_ref().or(support);
        let n_rows = active.map_or(r, Vec::len);
        let gather = |src: &[f32], rows: &[u32]| -> Vec<f32> {
            rows.iter()
                .flat_map(|&ri| {
                    src[ri as usize * in_dim..(ri as usize + 1) * in_dim]
                        .iter()
                        .copied()
                })
                .collect()
        };
        let casts = s > 0 && sh.shared.shadow.is_some();
        let lines_all = rays
            .lines
            .filter(|_| casts)
            .map(|l| &l[u * r * in_dim..(u + 1) * r * in_dim]);
        let mut pass = FieldPass {
            lfn: Activations::new(&sh.field, n_rows),
            color: Activations::new(&sh.shared.color, n_rows),
            rgb: vec![0f32; n_rows * 3],
            ordering: Activations::new(&sh.shared.ordering, n_rows),
            inputs: active.map(|rows| gather(x_all, rows)),
            line_inputs: active.and_then(|rows| lines_all.map(|l| gather(l, rows))),
            rows: active.cloned(),
            ..FieldPass::default()
        };
        if let Some(rows) = active {
            pass.position = vec![INACTIVE; r];
            for (i, &ri) in rows.iter().enumerate() {
                pass.position[ri as usize] = i as u32;
            }
        }
        let x = pass.inputs.take();
        let x_rows: &[f32] = x.as_deref().unwrap_or(x_all);
        let line_rows = pass.line_inputs.take();
        let lines: Option<&[f32]> = line_rows.as_deref().or(lines_all);
        let b0 = u / sh.fields * r;
        let ground = |i: usize| match (sh.shadow_lines, rays.on_ground) {
            (true, Some(g)) => g[b0 + active.map_or(i, |rows| rows[i] as usize)],
            _ => 1.0,
        };
        // The shadow lines worth evaluating: σ is 0 off the ground and beyond the reach.
        if let Some(lines) = lines {
            let kept: Vec<u32> = (0..n_rows)
                .filter(|&i| {
                    ground(i) != 0.0
                        && within_reach(&lines[i * in_dim..(i + 1) * in_dim], sh.shadow_reach)
                })
                .map(|i| i as u32)
                .collect();
            if kept.len() < n_rows {
                pass.shadow_inputs = Some(gather(lines, &kept));
                pass.shadow_rows = Some(kept);
            }
        }
        let n_shadow = pass.shadow_rows.as_ref().map_or(n_rows, Vec::len);
        let shadow_x = pass.shadow_inputs.take();
        let shadow_lines: Option<&[f32]> = shadow_x.as_deref().or(lines);
        if shadow_lines.is_some() {
            pass.shadow_lfn = Some(Activations::new(&sh.field, n_shadow));
        }
        let mut r0 = 0;
        while r0 < n_rows {
            let n = CHUNK.min(n_rows - r0);
            mlp_forward(&sh.field, params, x_rows, &mut pass.lfn, r0, n);
            let features = pass.lfn.output();
            mlp_forward(&sh.shared.color, shared, features, &mut pass.color, r0, n);
            mlp_forward(
                &sh.shared.ordering,
                shared,
                features,
                &mut pass.ordering,
                r0,
                n,
            );
            r0 += n;
        }
        if let (Some(lines), Some(acts)) = (shadow_lines, pass.shadow_lfn.as_mut()) {
            let mut j0 = 0;
            while j0 < n_shadow {
                let n = CHUNK.min(n_shadow - j0);
                mlp_forward(&sh.field, params, lines, acts, j0, n);
                j0 += n;
            }
        }
        for (c, l) in pass.rgb.iter_mut().zip(pass.color.output()) {
            *c = sigmoid(*l);
        }
        pass.sigma = vec![0f32; n_rows];
        if let (true, Some((w, b))) = (casts, sh.shared.shadow) {
            let f = sh.field.out_dim();
            let w = &shared[w..w + f];
            let bias = shared[b];
            let features = match &pass.shadow_lfn {
                Some(acts) => acts.output(),
                None => pass.lfn.output(),
            };
            pass.shadow_affine = features
                .chunks_exact(f)
                .map(|row| row.iter().zip(w).map(|(a, b)| a * b).sum::<f32>() + bias)
                .collect();
            for (j, a) in pass.shadow_affine.iter().enumerate() {
                let i = pass.shadow_row(j);
                pass.sigma[i] = softplus(SHADOW_LOGIT_GAIN as f32 * a) * ground(i);
            }
        }
        pass.inputs = x;
        pass.line_inputs = line_rows;
        pass.shadow_inputs = shadow_x;
        pass
    }

    /// The ray pass of rays [r0, r0 + n) of scene b: shadows, compositor, blend; writes the
    /// output channels of those rays to `out` [n, C].
    fn ray_forward(
        &self,
        (b, r0, n): (usize, usize, usize),
        fields: &[FieldPass],
        shared: &[f32],
        rays: &Rays,
        out: &mut [f32],
    ) -> RayPass {
        let sh = &self.shape;
        let (s, scale) = (sh.fields, sh.scene_scale);
        let ch = sh.channels();
        let scene = &fields[b * s..(b + 1) * s];
        let mut pass = RayPass {
            v_in: vec![0f32; n * s * 2],
            v: Activations::new(&sh.shared.v, n * s),
            world: vec![0f32; n * s],
            gap: vec![0f32; n * s],
            weights: vec![0f32; n * s],
            lit: vec![0f32; n],
            colors: vec![0f32; n * s * 3],
        };
        // Each (ray, field)'s row in its field pass; None where the field is not evaluated.
        let rows: Vec<Option<usize>> = (0..n)
            .flat_map(|i| scene.iter().map(move |f| f.row(r0 + i)))
            .collect();
        for i in 0..n {
            let r = r0 + i;
            let shift = sh_row(rays.shift, b * sh.rays + r, s);
            let world = &mut pass.world[i * s..(i + 1) * s];
            for f in 0..s {
                world[f] = match rows[i * s + f] {
                    Some(p) => scene[f].ordering.output()[p] * scale + shift[f],
                    None => f32::INFINITY,
                };
            }
            let front = world.iter().copied().fold(f32::INFINITY, f32::min);
            for f in 0..s {
                let Some(p) = rows[i * s + f] else {
                    continue;
                };
                let gap = (world[f] - front) / scale;
                pass.gap[i * s + f] = gap;
                let squashed = gap / (gap * gap + 1.0).sqrt();
                pass.v_in[(i * s + f) * 2] = scene[f].ordering.output()[p];
                pass.v_in[(i * s + f) * 2 + 1] = -squashed;
            }
        }
        mlp_forward(&sh.shared.v, shared, &pass.v_in, &mut pass.v, 0, n * s);
        let slope = shared[sh.shared.gap_log_slope].exp();
        let learned = pass.v.output();
        let mut scores = vec![0f32; s];
        for (i, row) in out.chunks_exact_mut(ch.count()).enumerate().take(n) {
            let active = &rows[i * s..(i + 1) * s];
            for f in 0..s {
                scores[f] = match active[f] {
                    Some(_) => learned[i * s + f] - pass.gap[i * s + f] * slope,
                    None => f32::NEG_INFINITY,
                };
            }
            let max = scores.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let sum: f32 = scores.iter().map(|v| (v - max).exp()).sum();
            let log_sum = sum.ln();
            let sigma = |f: usize| active[f].map_or(0.0, |p| scene[f].sigma[p]);
            let lit = (-(1..s).map(sigma).sum::<f32>()).exp();
            pass.lit[i] = lit;
            let mut rgb = [0f32; 3];
            for f in 0..s {
                let log_w = scores[f] - max - log_sum;
                let w = log_w.exp();
                pass.weights[i * s + f] = w;
                row[ch.log_weights() + f] = log_w;
                row[ch.weights() + f] = w;
                row[ch.ordering() + f] = pass.world[i * s + f];
                row[ch.shadow() + f] = if f == 0 { 0.0 } else { sigma(f) };
                let Some(p) = active[f] else {
                    continue;
                };
                for c in 0..3 {
                    let mut color = scene[f].rgb[p * 3 + c];
                    if f == 0 {
                        color *= lit;
                    }
                    pass.colors[(i * s + f) * 3 + c] = color;
                    row[ch.colors() + f * 3 + c] = color;
                    rgb[c] += w * color;
                }
            }
            row[..3].copy_from_slice(&rgb);
        }
        pass
    }
}

fn sh_row(v: &[f32], row: usize, s: usize) -> &[f32] {
    &v[row * s..(row + 1) * s]
}

/// Splits `buf` into consecutive mutable pieces of the given lengths.
fn split_lengths<'a>(mut buf: &'a mut [f32], lengths: &[usize]) -> Vec<&'a mut [f32]> {
    let mut pieces = Vec::with_capacity(lengths.len());
    for &len in lengths {
        let (head, tail) = std::mem::take(&mut buf).split_at_mut(len);
        pieces.push(head);
        buf = tail;
    }
    pieces
}

/// Per ray and field, the gradients the ray pass hands to the field pass.
#[derive(Debug, Default, Clone)]
struct RayGrads {
    /// dL/d(field colour before the shadows) [n, S, 3].
    color: Vec<f32>,
    /// dL/d(ordering head output) [n, S].
    ordering: Vec<f32>,
    /// dL/dσ [n, S].
    sigma: Vec<f32>,
    /// dL/d(shift) [n, S].
    shift: Vec<f32>,
    /// This unit's share of the shared parameters' gradient (V and the gap slope).
    shared: Vec<f32>,
}

impl CustomOp3 for DecodeOp {
    fn name(&self) -> &'static str {
        "colf-decode"
    }

    fn cpu_fwd(
        &self,
        fs: &CpuStorage,
        fl: &Layout,
        ss: &CpuStorage,
        sl: &Layout,
        rs: &CpuStorage,
        rl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let _timer = KernelTimer::start();
        let sh = &self.shape;
        let fields = storage_f32(fs, fl, "field parameters")?;
        let shared = storage_f32(ss, sl, "shared parameters")?;
        if fields.len() != sh.scenes * sh.fields * sh.field_params || shared.len() != sh.shared.len
        {
            candle_core::bail!("decode kernel: parameters do not match the model's layout");
        }
        let ch = sh.channels().count();
        let mut out = vec![0f32; sh.scenes * sh.rays * ch];
        let saved = self.with_rays(storage_f32(rs, rl, "rays")?, |rays| {
            // One field a task: fields differ in size (a slot's reach, the background on every
            // ray), so rayon's default halving left one thread idle behind a heavy batch.
            let passes: Vec<FieldPass> = (0..sh.scenes * sh.fields)
                .into_par_iter()
                .with_max_len(1)
                .map(|u| self.field_forward(u, fields, shared, rays))
                .collect();
            let units = ray_units(sh);
            let lengths: Vec<usize> = units.iter().map(|u| u.2 * ch).collect();
            let ray_passes: Vec<RayPass> = split_lengths(&mut out, &lengths)
                .into_par_iter()
                .zip(units.par_iter())
                .map(|(piece, unit)| self.ray_forward(*unit, &passes, shared, rays, piece))
                .collect();
            Ok(Saved {
                fields: passes,
                rays: ray_passes,
            })
        })?;
        *self.saved.lock().expect("decode kernel state") = saved;
        Ok((CpuStorage::F32(out), Shape::from((sh.scenes, sh.rays, ch))))
    }

    fn bwd(
        &self,
        field_params: &Tensor,
        shared_params: &Tensor,
        ray_input: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let _timer = KernelTimer::start();
        let sh = &self.shape;
        let grad_res = grad_res.contiguous()?;
        let (g_guard, g_layout) = grad_res.storage_and_layout();
        let (f_guard, f_layout) = field_params.storage_and_layout();
        let (s_guard, s_layout) = shared_params.storage_and_layout();
        let (r_guard, r_layout) = ray_input.storage_and_layout();
        let ch = sh.channels().count();
        let grad_out = held_f32(
            &g_guard,
            g_layout,
            "output gradient",
            sh.scenes * sh.rays * ch,
        )?;
        let fields = held_f32(
            &f_guard,
            f_layout,
            "field parameters",
            sh.scenes * sh.fields * sh.field_params,
        )?;
        let shared = held_f32(&s_guard, s_layout, "shared parameters", sh.shared.len)?;
        let Storage::Cpu(r_cpu) = &*r_guard else {
            candle_core::bail!("decode kernel: rays must be on the CPU")
        };
        let ray_data = storage_f32(r_cpu, r_layout, "rays")?;
        let want_rays = !matches!(self.rays, RayInputs::Held { .. });
        let saved = self.saved.lock().expect("decode kernel state");
        if saved.fields.len() != sh.scenes * sh.fields {
            candle_core::bail!("decode kernel: backward without a forward");
        }
        let (d_fields, d_shared, d_rays) = self.with_rays(ray_data, |rays| {
            Ok(self.backward(&saved, fields, shared, rays, grad_out, want_rays))
        })?;
        drop(saved);
        let dev = field_params.device();
        let d_fields = Tensor::from_vec(d_fields, field_params.shape(), dev)?;
        let d_shared = Tensor::from_vec(d_shared, shared_params.shape(), dev)?;
        let d_rays = match d_rays {
            Some(d) => Some(Tensor::from_vec(d, ray_input.shape(), dev)?),
            None => None,
        };
        Ok((Some(d_fields), Some(d_shared), d_rays))
    }
}

impl DecodeOp {
    /// The whole backward: gradients of the field parameters, the shared parameters and (with
    /// `want_rays`) the op's third input: the packed rays, or the offsets of moving ones.
    fn backward(
        &self,
        saved: &Saved,
        fields: &[f32],
        shared: &[f32],
        rays: &Rays,
        grad_out: &[f32],
        want_rays: bool,
    ) -> (Vec<f32>, Vec<f32>, Option<Vec<f32>>) {
        let sh = &self.shape;
        // 1. Ray passes in reverse: blend, shadows, compositor.
        let units = ray_units(sh);
        let ray_grads: Vec<RayGrads> = units
            .par_iter()
            .zip(saved.rays.par_iter())
            .map(|(unit, pass)| self.ray_backward(*unit, pass, &saved.fields, shared, grad_out))
            .collect();
        // Per field the rows of dL/d(colour, ordering, σ), field-major [B·S, R, ·].
        let (b_n, s_n, r_n) = (sh.scenes, sh.fields, sh.rays);
        let mut d_color = vec![0f32; b_n * s_n * r_n * 3];
        let mut d_ordering = vec![0f32; b_n * s_n * r_n];
        let mut d_sigma = vec![0f32; b_n * s_n * r_n];
        let mut d_shift = vec![0f32; if want_rays { b_n * r_n * s_n } else { 0 }];
        for ((b, r0, n), g) in units.iter().zip(&ray_grads) {
            for i in 0..*n {
                let r = r0 + i;
                for f in 0..s_n {
                    let row = (b * s_n + f) * r_n + r;
                    d_color[row * 3..row * 3 + 3]
                        .copy_from_slice(&g.color[(i * s_n + f) * 3..(i * s_n + f) * 3 + 3]);
                    d_ordering[row] = g.ordering[i * s_n + f];
                    d_sigma[row] = g.sigma[i * s_n + f];
                }
                if want_rays {
                    let at = (b * r_n + r) * s_n;
                    d_shift[at..at + s_n].copy_from_slice(&g.shift[i * s_n..(i + 1) * s_n]);
                }
            }
        }
        // 2. Field passes in reverse: heads, light fields, down to the generated parameters.
        // Moving rays: each field's ray gradients stay in the unit, contracted to the offsets.
        let motion = match &self.rays {
            RayInputs::Moving { motion, .. } => Some(motion.as_ref()),
            _ => None,
        };
        let packed = want_rays && motion.is_none();
        let (nc, nl, _) = self.packed_len();
        let mut d_fields = vec![0f32; fields.len()];
        let mut d_coords = vec![0f32; if packed { nc } else { 0 }];
        let mut d_lines = vec![0f32; if packed { nl } else { 0 }];
        let per_field_input = r_n * sh.in_dim;
        let coord_pieces: Vec<Option<&mut [f32]>> = if packed {
            d_coords.chunks_mut(per_field_input).map(Some).collect()
        } else {
            (0..b_n * s_n).map(|_| None).collect()
        };
        let line_pieces: Vec<Option<&mut [f32]>> = if packed && nl > 0 {
            d_lines.chunks_mut(per_field_input).map(Some).collect()
        } else {
            (0..b_n * s_n).map(|_| None).collect()
        };
        let field_parts: Vec<(Vec<f32>, Option<Vec<f64>>)> = d_fields
            .par_chunks_mut(sh.field_params)
            .zip(coord_pieces)
            .zip(line_pieces)
            .enumerate()
            .with_max_len(1)
            .map(|(u, ((d_params, d_x), d_l))| {
                let grads = FieldGrads {
                    color: &d_color[u * r_n * 3..(u + 1) * r_n * 3],
                    ordering: &d_ordering[u * r_n..(u + 1) * r_n],
                    sigma: &d_sigma[u * r_n..(u + 1) * r_n],
                };
                // Moving rays: the field's ray gradients in buffers of its own, contracted below.
                let mut own = motion.map(|_| {
                    let lines = if nl > 0 { per_field_input } else { 0 };
                    (vec![0f32; per_field_input], vec![0f32; lines])
                });
                let (d_x, d_l) = match own.as_mut() {
                    Some((x, l)) => (Some(&mut x[..]), (nl > 0).then_some(&mut l[..])),
                    None => (d_x, d_l),
                };
                let shared_part = self.field_backward(
                    u,
                    &saved.fields[u],
                    fields,
                    shared,
                    rays,
                    grads,
                    d_params,
                    d_x,
                    d_l,
                );
                let d_offsets = motion.zip(own).map(|(motion, (d_x, d_l))| {
                    let block = u * per_field_input..(u + 1) * per_field_input;
                    let lines = rays.lines.map(|l| (&l[block.clone()], &d_l[..]));
                    motion.field_gradient(u, (&rays.coords[block], &d_x), lines)
                });
                (shared_part, d_offsets)
            })
            .collect();
        // 3. The shared parameters' gradient: every unit's share, summed in unit order.
        let mut d_shared = vec![0f32; shared.len()];
        for part in field_parts
            .iter()
            .map(|p| &p.0)
            .chain(ray_grads.iter().map(|g| &g.shared))
        {
            for (d, v) in d_shared.iter_mut().zip(part) {
                *d += v;
            }
        }
        let d_rays = match motion {
            // The offsets' gradient: the shifts' share, then each field's in field order.
            Some(motion) => {
                let mut sum = motion.shift_gradient(&d_shift);
                for part in field_parts.iter().filter_map(|p| p.1.as_ref()) {
                    for (d, v) in sum.iter_mut().zip(part) {
                        *d += v;
                    }
                }
                Some(sum.into_iter().map(|v| v as f32).collect())
            }
            None => want_rays.then(|| {
                let mut packed = d_coords;
                packed.extend(d_lines);
                packed.extend(d_shift);
                packed
            }),
        };
        (d_fields, d_shared, d_rays)
    }
}

/// dL/d(colour, ordering, σ) of one field's rays.
struct FieldGrads<'a> {
    color: &'a [f32],
    ordering: &'a [f32],
    sigma: &'a [f32],
}

impl DecodeOp {
    /// The backward of [`DecodeOp::ray_forward`] for one ray unit.
    fn ray_backward(
        &self,
        (b, r0, n): (usize, usize, usize),
        pass: &RayPass,
        fields: &[FieldPass],
        shared: &[f32],
        grad_out: &[f32],
    ) -> RayGrads {
        let sh = &self.shape;
        let (s, scale) = (sh.fields, sh.scene_scale);
        let ch = sh.channels();
        let scene = &fields[b * s..(b + 1) * s];
        let slope = shared[sh.shared.gap_log_slope].exp();
        let mut out = RayGrads {
            color: vec![0f32; n * s * 3],
            ordering: vec![0f32; n * s],
            sigma: vec![0f32; n * s],
            shift: vec![0f32; n * s],
            shared: vec![0f32; shared.len()],
        };
        // 1. Blend and softmax: dL/d(score) per ray and field, the colours' gradients.
        let mut d_score = vec![0f32; n * s];
        let mut d_gap = vec![0f32; n * s];
        let mut d_slope = 0f32;
        let mut d_w = vec![0f32; s];
        // Whether each (ray, field) was evaluated (always, without a support).
        let active: Vec<bool> = (0..n)
            .flat_map(|i| scene.iter().map(move |f| f.row(r0 + i).is_some()))
            .collect();
        for i in 0..n {
            let r = r0 + i;
            let g = &grad_out[(b * sh.rays + r) * ch.count()..(b * sh.rays + r + 1) * ch.count()];
            let w = &pass.weights[i * s..(i + 1) * s];
            let on = &active[i * s..(i + 1) * s];
            let colors = &pass.colors[i * s * 3..(i + 1) * s * 3];
            let lit = pass.lit[i];
            let bg_row = scene[0]
                .row(r)
                .expect("the background is evaluated on every ray");
            let mut d_lit = 0f32;
            for f in 0..s {
                if !on[f] {
                    d_w[f] = 0.0;
                    continue;
                }
                let mut dw = g[ch.weights() + f];
                for c in 0..3 {
                    dw += g[c] * colors[f * 3 + c];
                    // dL/d(colour after the shadows), then before them.
                    let d_shaded = w[f] * g[c] + g[ch.colors() + f * 3 + c];
                    if f == 0 {
                        out.color[(i * s) * 3 + c] = d_shaded * lit;
                        d_lit += d_shaded * scene[0].rgb[bg_row * 3 + c];
                    } else {
                        out.color[(i * s + f) * 3 + c] = d_shaded;
                    }
                }
                d_w[f] = dw;
            }
            // σ_f lowers lit = exp(−Σσ); the σ output channel adds its own gradient.
            for f in (1..s).filter(|&f| on[f]) {
                out.sigma[i * s + f] = -lit * d_lit + g[ch.shadow() + f];
            }
            let g_log_sum: f32 = (0..s)
                .filter(|&f| on[f])
                .map(|f| g[ch.log_weights() + f])
                .sum();
            let w_dot: f32 = w.iter().zip(&d_w).map(|(a, b)| a * b).sum();
            for f in (0..s).filter(|&f| on[f]) {
                let ds = g[ch.log_weights() + f] - w[f] * g_log_sum + w[f] * (d_w[f] - w_dot);
                d_score[i * s + f] = ds;
                // score = learned − gap·slope.
                d_gap[i * s + f] = -ds * slope;
                d_slope -= ds * pass.gap[i * s + f] * slope;
            }
        }
        // 2. V's backward: dL/d(V's input) [n·S, 2] and V's parameter gradients.
        let mut d_v_in = vec![0f32; n * s * 2];
        let mut scratch = Scratch::new(sh.shared.v.widest(), n * s);
        mlp_backward(
            &sh.shared.v,
            shared,
            &pass.v_in,
            &pass.v,
            0,
            n * s,
            &d_score,
            &mut out.shared,
            Some(&mut d_v_in),
            &mut scratch,
        );
        out.shared[sh.shared.gap_log_slope] += d_slope;
        // 3. Gaps, the front and the world orderings, down to the heads' ordering values.
        for i in 0..n {
            let world = &pass.world[i * s..(i + 1) * s];
            let g = &grad_out[(b * sh.rays + r0 + i) * ch.count()..];
            let front = world.iter().copied().fold(f32::INFINITY, f32::min);
            let mut d_world = vec![0f32; s];
            let mut d_front = 0f32;
            let on = &active[i * s..(i + 1) * s];
            for f in (0..s).filter(|&f| on[f]) {
                let gap = pass.gap[i * s + f];
                // squashed = gap / √(1 + gap²), fed to V negated.
                let d_squashed = -d_v_in[(i * s + f) * 2 + 1];
                let dg = d_gap[i * s + f] + d_squashed / (1.0 + gap * gap).powf(1.5);
                d_world[f] += dg / scale;
                d_front -= dg / scale;
            }
            // The minimum passes its gradient to every field that attains it (as candle's).
            for f in 0..s {
                if world[f] == front {
                    d_world[f] += d_front;
                }
            }
            for f in (0..s).filter(|&f| on[f]) {
                let dw = d_world[f] + g[ch.ordering() + f];
                out.ordering[i * s + f] = dw * scale + d_v_in[(i * s + f) * 2];
                out.shift[i * s + f] = dw;
            }
        }
        out
    }

    /// The backward of [`DecodeOp::field_forward`] for field u: its generated parameters'
    /// gradient into `d_params`, the rays' into `d_x` / `d_lines` when given; returns the
    /// field's share of the shared parameters' gradient.
    #[allow(clippy::too_many_arguments)]
    fn field_backward(
        &self,
        u: usize,
        pass: &FieldPass,
        fields: &[f32],
        shared: &[f32],
        rays: &Rays,
        grads: FieldGrads,
        d_params: &mut [f32],
        mut d_x: Option<&mut [f32]>,
        mut d_lines: Option<&mut [f32]>,
    ) -> Vec<f32> {
        let sh = &self.shape;
        let (r, s) = (sh.rays, u % sh.fields);
        let f_dim = sh.field.out_dim();
        let params = &fields[u * sh.field_params..(u + 1) * sh.field_params];
        let in_dim = sh.in_dim;
        let x = pass
            .inputs
            .as_deref()
            .unwrap_or(&rays.coords[u * r * in_dim..(u + 1) * r * in_dim]);
        let n_rows = pass.len();
        let sparse = pass.rows.is_some();
        let mut d_shared = vec![0f32; shared.len()];
        let widest = sh
            .field
            .widest()
            .max(sh.shared.color.widest())
            .max(sh.shared.ordering.widest());
        let mut scratch = Scratch::new(widest, CHUNK);
        let mut d_features = vec![0f32; CHUNK * f_dim];
        let mut d_head = vec![0f32; CHUNK * f_dim];
        let mut g_color = vec![0f32; CHUNK * 3];
        let casts = s > 0 && sh.shared.shadow.is_some();
        let b0 = u / sh.fields * r;
        let lines = pass.line_inputs.as_deref().or(rays
            .lines
            .filter(|_| casts)
            .map(|l| &l[u * r * in_dim..(u + 1) * r * in_dim]));
        let mut g_ordering = vec![0f32; CHUNK];
        // With a support or shadow rows, the rays' gradients go through a chunk buffer to
        // their rays' rows.
        let mut dx_rows = vec![0f32; CHUNK * in_dim];
        let ray_of_row = |i: usize| pass.ray(i);
        let mut r0 = 0;
        while r0 < n_rows {
            let n = CHUNK.min(n_rows - r0);
            let features = pass.lfn.output();
            // Colour head: through the sigmoid.
            for i in 0..n {
                let ray = pass.ray(r0 + i);
                g_ordering[i] = grads.ordering[ray];
                for c in 0..3 {
                    let v = pass.rgb[(r0 + i) * 3 + c];
                    g_color[i * 3 + c] = grads.color[ray * 3 + c] * v * (1.0 - v);
                }
            }
            mlp_backward(
                &sh.shared.color,
                shared,
                features,
                &pass.color,
                r0,
                n,
                &g_color,
                &mut d_shared,
                Some(&mut d_features),
                &mut scratch,
            );
            mlp_backward(
                &sh.shared.ordering,
                shared,
                features,
                &pass.ordering,
                r0,
                n,
                &g_ordering,
                &mut d_shared,
                Some(&mut d_head),
                &mut scratch,
            );
            for (a, b) in d_features[..n * f_dim].iter_mut().zip(&d_head[..n * f_dim]) {
                *a += b;
            }
            // Shadow head read from the ray's own features: σ = softplus(g·(w·f + b))·ground.
            if let (true, None, Some(head)) = (casts, &pass.shadow_lfn, sh.shared.shadow) {
                for i in 0..n {
                    let ga = self.shadow_affine_grad(pass, r0 + i, b0, rays, &grads);
                    shadow_head_backward(
                        ga,
                        &features[(r0 + i) * f_dim..(r0 + i + 1) * f_dim],
                        head,
                        shared,
                        &mut d_shared,
                        &mut d_features[i * f_dim..(i + 1) * f_dim],
                    );
                }
            }
            // The light field on the ray.
            LfnRows {
                params,
                r0,
                n,
                in_dim,
                ray_of: sparse.then_some(&ray_of_row as &dyn Fn(usize) -> usize),
            }
            .backward(
                &sh.field,
                x,
                &pass.lfn,
                &d_features,
                d_params,
                d_x.as_deref_mut(),
                &mut dx_rows,
                &mut scratch,
            );
            r0 += n;
        }
        // The shadow lines' light-field pass, on its own rows: σ = softplus(g·(w·f + b))·ground.
        if let (Some(acts), Some(head)) = (&pass.shadow_lfn, sh.shared.shadow) {
            let lines = pass
                .shadow_inputs
                .as_deref()
                .or(lines)
                .expect("shadow lines");
            let sparse_lines = sparse || pass.shadow_rows.is_some();
            let ray_of = |j: usize| pass.ray(pass.shadow_row(j));
            let source = acts.output();
            let n_shadow = pass.shadow_rows.as_ref().map_or(n_rows, Vec::len);
            let mut j0 = 0;
            while j0 < n_shadow {
                let n = CHUNK.min(n_shadow - j0);
                // The line's features feed only the shadow head: their gradient starts at 0.
                d_head[..n * f_dim].fill(0.0);
                for i in 0..n {
                    let ga = self.shadow_affine_grad(pass, j0 + i, b0, rays, &grads);
                    shadow_head_backward(
                        ga,
                        &source[(j0 + i) * f_dim..(j0 + i + 1) * f_dim],
                        head,
                        shared,
                        &mut d_shared,
                        &mut d_head[i * f_dim..(i + 1) * f_dim],
                    );
                }
                LfnRows {
                    params,
                    r0: j0,
                    n,
                    in_dim,
                    ray_of: sparse_lines.then_some(&ray_of as &dyn Fn(usize) -> usize),
                }
                .backward(
                    &sh.field,
                    lines,
                    acts,
                    &d_head,
                    d_params,
                    d_lines.as_deref_mut(),
                    &mut dx_rows,
                    &mut scratch,
                );
                j0 += n;
            }
        }
        d_shared
    }

    /// dL/d(w·f + b) of the shadow head on its row `j` (a shadow row with shadow lines, else
    /// a row): through σ = softplus(g·a)·ground.
    fn shadow_affine_grad(
        &self,
        pass: &FieldPass,
        j: usize,
        b0: usize,
        rays: &Rays,
        grads: &FieldGrads,
    ) -> f32 {
        let sh = &self.shape;
        let gain = SHADOW_LOGIT_GAIN as f32;
        let ray = pass.ray(if pass.shadow_lfn.is_some() {
            pass.shadow_row(j)
        } else {
            j
        });
        let ground = match (sh.shadow_lines, rays.on_ground) {
            (true, Some(g)) => g[b0 + ray],
            _ => 1.0,
        };
        let a = pass.shadow_affine[j];
        grads.sigma[ray] * ground * gain * sigmoid(gain * a)
    }
}

/// The shadow head's backward on one row, given `ga` = dL/d(w·f + b): adds ga·f to w's and ga to
/// b's gradient in `d_shared` (`head` = their offsets) and ga·w to the features' gradient.
fn shadow_head_backward(
    ga: f32,
    feature: &[f32],
    (w, bias): (usize, usize),
    shared: &[f32],
    d_shared: &mut [f32],
    d_feature: &mut [f32],
) {
    let f_dim = feature.len();
    d_shared[bias] += ga;
    for (d, v) in d_shared[w..w + f_dim].iter_mut().zip(feature) {
        *d += ga * v;
    }
    for (d, wv) in d_feature.iter_mut().zip(&shared[w..w + f_dim]) {
        *d += ga * wv;
    }
}

/// Rows [r0, r0 + n) of a field pass, for the light field's backward.
struct LfnRows<'a> {
    params: &'a [f32],
    r0: usize,
    n: usize,
    in_dim: usize,
    /// The ray of each row when rows are not rays (a support, or shadow rows); None: row = ray.
    ray_of: Option<&'a dyn Fn(usize) -> usize>,
}

impl LfnRows<'_> {
    /// The light field's backward on these rows of `input` (the rays' coordinates or shadow
    /// lines): parameter gradients into `d_params`; the inputs' gradients into `d_rays` when
    /// given — at the rows' rays, through `dx_rows` when the pass has a support.
    #[allow(clippy::too_many_arguments)]
    fn backward(
        &self,
        lfn: &MlpLayout,
        input: &[f32],
        acts: &Activations,
        g: &[f32],
        d_params: &mut [f32],
        d_rays: Option<&mut [f32]>,
        dx_rows: &mut [f32],
        scratch: &mut Scratch,
    ) {
        let (r0, n, in_dim) = (self.r0, self.n, self.in_dim);
        let run = |dx: Option<&mut [f32]>, d_params: &mut [f32], scratch: &mut Scratch| {
            mlp_backward(
                lfn,
                self.params,
                input,
                acts,
                r0,
                n,
                g,
                d_params,
                dx,
                scratch,
            )
        };
        match d_rays {
            None => run(None, d_params, scratch),
            Some(d) => match self.ray_of {
                None => run(Some(&mut d[r0 * in_dim..]), d_params, scratch),
                Some(ray_of) => {
                    run(Some(&mut dx_rows[..]), d_params, scratch);
                    for i in 0..n {
                        let ray = ray_of(r0 + i);
                        d[ray * in_dim..(ray + 1) * in_dim]
                            .copy_from_slice(&dx_rows[i * in_dim..(i + 1) * in_dim]);
                    }
                }
            },
        }
    }
}

/// [`crate::model::ColfNet::decode`] through the kernel: packs the parameters and rays, runs
/// the op, and narrows its output into a `Decoded`.
pub fn decode(
    cfg: &Config,
    lf: &LightFieldDecoder,
    fields: &SlotWeights,
    rays: &RayBatch,
    support: Option<Vec<Vec<u32>>>,
) -> Result<Decoded> {
    let (b, s, r) = (rays.scenes, rays.fields, rays.rays);
    let shape = DecodeShape::new(cfg, b, s, r);
    // The generated parameters, per field [W₀ | b₀ | W₁ | b₁ | …].
    let mut pieces = Vec::with_capacity(2 * fields.layers.len());
    for layer in &fields.layers {
        pieces.push(layer.weight.reshape((b * s, ()))?);
        pieces.push(layer.bias.reshape((b * s, ()))?);
    }
    let field_params = Tensor::cat(&pieces, 1)?;
    let mut shared = lf.heads.kernel_parameters();
    shared.extend(lf.compositor.kernel_parameters());
    let shared = shared
        .iter()
        .map(|t| t.flatten_all())
        .collect::<Result<Vec<_>>>()?;
    let shared = Tensor::cat(&shared, 0)?;
    if shared.elem_count() != shape.shared.len || field_params.dim(1)? != shape.field_params {
        candle_core::bail!("decode kernel: the model's parameters do not match its config");
    }
    // The rays: packed into the op's input when they need gradients, else held by the op.
    let lines = rays
        .shadow_lines
        .as_ref()
        .filter(|_| shape.shadow_lines)
        .map(|(l, _)| l);
    let on_ground = match (&rays.shadow_lines, shape.shadow_lines) {
        (Some((_, g)), true) => Some(g.flatten_all()?.to_vec1::<f32>()?),
        _ => None,
    };
    let tracked =
        rays.coords.track_op() || rays.shift.track_op() || lines.is_some_and(|l| l.track_op());
    let (ray_input, ray_inputs) = if let Some(moving) = &rays.motion {
        if tracked {
            candle_core::bail!("decode kernel: moving rays must not need gradients themselves");
        }
        (
            moving.offsets.flatten_all()?,
            RayInputs::Moving {
                coords: rays.coords.contiguous()?,
                lines: lines.map(|l| l.contiguous()).transpose()?,
                on_ground,
                shift: rays.shift.contiguous()?,
                motion: moving.motion.clone(),
            },
        )
    } else if tracked {
        let mut packed = vec![rays.coords.flatten_all()?];
        if let Some(l) = lines {
            packed.push(l.flatten_all()?);
        }
        packed.push(rays.shift.flatten_all()?);
        (Tensor::cat(&packed, 0)?, RayInputs::Packed { on_ground })
    } else {
        (
            rays.coords.flatten_all()?,
            RayInputs::Held {
                lines: lines.map(|l| l.contiguous()).transpose()?,
                on_ground,
                shift: rays.shift.contiguous()?,
            },
        )
    };
    let ch = shape.channels();
    let has_shadow = cfg.shadow_head;
    let mut op = DecodeOp::new(shape, ray_inputs);
    if let Some(support) = support {
        op = op.with_support(support)?;
    }
    let out = field_params.apply_op3(&shared, &ray_input.contiguous()?, op)?;
    let colors = out
        .narrow(2, ch.colors(), 3 * s)?
        .contiguous()?
        .reshape((b, r, s, 3))?;
    // Contiguous copies: [B, R, ≤ S] each, small beside the op, and what later ops expect.
    let channel = |at: usize, n: usize| out.narrow(2, at, n)?.contiguous();
    Ok(Decoded {
        rgb: channel(Channels::RGB, 3)?,
        weights: channel(ch.weights(), s)?,
        log_weights: channel(ch.log_weights(), s)?,
        colors,
        ordering: channel(ch.ordering(), s)?,
        shadow: has_shadow.then(|| channel(ch.shadow(), s)).transpose()?,
    })
}
