//! The inference-only renderer behind `colf-render`: the same weights and the same arithmetic
//! as the candle path ([`Colf::render_rays`], which training uses), laid out for speed.
//!
//! Why a second path: rendering a frame is a few dozen small matrix products per slot, and in
//! candle every layer allocates its activation tensor, every element-wise op (bias, ReLU,
//! sigmoid, the compositor's dozen ops) is a pass over memory, and the heads and compositor see
//! all rays of all slots at once, so the activations stream through main memory between ops. Here
//! - rays are cut into chunks of [`LF_CHUNK`] rays (volumetric: ~[`VOL_POINTS`] sample points),
//!   one chunk per rayon task, so each task's activations (a few hundred KiB) stay in L2;
//! - within a chunk, each slot's whole network runs back to back: one `gemm` call per layer
//!   (single-threaded: the parallelism is across chunks), with bias and ReLU in one pass over
//!   the in-cache output; the colour and ordering heads' first layers share one product, their
//!   output layers one block-diagonal product;
//! - the compositor runs per ray on the slots' values, with its MLP as products per slot;
//! - the volumetric decoder's latent columns are folded into a per-slot bias once (see
//!   `model/volumetric.rs`), and its skip connection reads [h, γ(p)] from one buffer.
//!
//! Each chunk is computed by one thread from its own inputs only, so results do not depend on
//! the number of threads or on scheduling: the same inputs give the same bytes. Agreement with
//! the candle path is tested to 1e-4 (`tests` below and `tests/render_fast.rs`).
//!
//! Adaptive rendering passes an `active` mask (ray × field): a field is evaluated only on the
//! rays where it is active and takes no part in those rays' composition elsewhere (weight 0,
//! ordering +∞). The background (field 0) must always be active. For a model that reads shadows
//! along the light (`shadow_light`), [`Active::shadows`] may say separately on which rays a
//! slot's shadow line is evaluated (a slot darkens pixels it does not win, and wins pixels its
//! shadow does not reach); a shadow not evaluated casts none.

#![allow(clippy::needless_range_loop)] // index loops over small fixed-size colour arrays

use crate::model::heads::shadow_host;
use crate::model::rays::{
    encode_floor, encode_line, light_direction, plucker_in_frame, shadow_line, within_reach,
};
use crate::model::{Colf, Config, PreparedSlots, RayBatch, RayOutput, SceneRays};
use anyhow::{anyhow, bail, Context, Result};
use candle_core::{Device, Tensor};
use glam::{DMat4, DVec3};
use rayon::prelude::*;

/// Rays per light-field task.
pub const LF_CHUNK: usize = 256;
/// Sample points per volumetric task (rays per task = this / samples, at least 1).
pub const VOL_POINTS: usize = 1024;

/// One dense layer on the host: y = act(x·W + b), W [in, out] row-major.
#[derive(Clone, Debug)]
pub struct HostDense {
    pub input: usize,
    pub output: usize,
    pub w: Vec<f32>,
    pub b: Vec<f32>,
}

impl HostDense {
    /// From a candle `Linear` layout: weight [out, in], bias [out] (None: zeros).
    pub fn from_linear(weight: &Tensor, bias: Option<&Tensor>) -> Result<HostDense> {
        let (out, inp) = weight.dims2()?;
        let w = weight.t()?.contiguous()?.flatten_all()?.to_vec1::<f32>()?;
        let b = match bias {
            Some(b) => b.flatten_all()?.to_vec1::<f32>()?,
            None => vec![0.0; out],
        };
        if b.len() != out {
            bail!("bias of {} values for {out} outputs", b.len());
        }
        Ok(HostDense {
            input: inp,
            output: out,
            w,
            b,
        })
    }

    /// `rows` rows of x (row stride `x_rs`, the first `input` columns) → y (row stride `y_rs`,
    /// the first `output` columns).
    pub fn run(&self, x: &[f32], x_rs: usize, rows: usize, y: &mut [f32], y_rs: usize, relu: bool) {
        self.run_bias(x, x_rs, rows, y, y_rs, relu, &self.b);
    }

    /// As [`HostDense::run`] with another bias vector (the volumetric per-slot biases).
    #[allow(clippy::too_many_arguments)]
    pub fn run_bias(
        &self,
        x: &[f32],
        x_rs: usize,
        rows: usize,
        y: &mut [f32],
        y_rs: usize,
        relu: bool,
        bias: &[f32],
    ) {
        if rows == 0 {
            return;
        }
        let (k, n) = (self.input, self.output);
        assert!(x_rs >= k && y_rs >= n && bias.len() == n);
        assert!(x.len() >= (rows - 1) * x_rs + k, "dense: x too short");
        assert!(y.len() >= (rows - 1) * y_rs + n, "dense: y too short");
        // SAFETY: the asserts above keep every read of x (rows × k with row stride x_rs), of W
        // ([k, n] row-major, built that way) and every write of y (rows × n, row stride y_rs)
        // inside their slices; y is written before it is read (read_dst = false).
        unsafe {
            gemm::gemm(
                rows,
                n,
                k,
                y.as_mut_ptr(),
                1,
                y_rs as isize,
                false,
                x.as_ptr(),
                1,
                x_rs as isize,
                self.w.as_ptr(),
                1,
                n as isize,
                0.0,
                1.0,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
        for row in y.chunks_mut(y_rs).take(rows) {
            for (v, b) in row[..n].iter_mut().zip(bias) {
                let t = *v + b;
                *v = if relu { t.max(0.0) } else { t };
            }
        }
    }
}

fn param<'a>(colf: &'a Colf, name: &str) -> Result<&'a Tensor> {
    colf.parameters()
        .get(name)
        .ok_or_else(|| anyhow!("the model has no tensor `{name}`"))
}

fn linear(colf: &Colf, prefix: &str, bias: bool) -> Result<HostDense> {
    let w = param(colf, &format!("{prefix}.weight"))?;
    let b = if bias {
        Some(param(colf, &format!("{prefix}.bias"))?)
    } else {
        None
    };
    HostDense::from_linear(w, b).with_context(|| prefix.to_string())
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Light-field weights on the host.
struct LightFieldHost {
    /// Per field (background first), its MLP layers.
    fields: Vec<Vec<HostDense>>,
    /// Heads: first layer of both heads side by side (F → 2H, or F → 4 without hidden layers).
    head_first: HostDense,
    /// Hidden layers 1 … h − 1: (colour, ordering), each H → H.
    head_mid: Vec<(HostDense, HostDense)>,
    /// Output layer, block-diagonal 2H → 4 (colour 3, ordering 1); None without hidden layers.
    head_out: Option<HostDense>,
    /// The shadow head, with `Config::shadow_head`.
    shadow: Option<ShadowHost>,
    head_hidden: usize,
    /// Compositor V, layers in order (the last without a bias: zeros).
    comp: Vec<HostDense>,
    gap_slope: f32,
    scene_scale: f64,
    freqs: usize,
    in_dim: usize,
    /// `Config::floor_fourier_freqs`, and where the floor columns start in a row
    /// (`Config::line_input_dim`).
    floor_freqs: usize,
    line_dim: usize,
    /// The model's config with Fourier and floor features off, for the shifts of `RayBatch`.
    shift_cfg: Config,
    /// `Config::slot_reach_bound`: a foreground slot is absent on the rays beyond it.
    slot_reach: Option<f32>,
}

/// `heads.shadow` on the host.
struct ShadowHost {
    /// w, one per feature (the [F, 1] weight of a `HostDense`).
    weight: Vec<f32>,
    bias: f32,
    /// Toward the light, with `Config::shadow_light`.
    to_light: Option<DVec3>,
    /// `Config::shadow_reach_bound`: shadow lines beyond it cast nothing.
    reach: Option<f32>,
}

impl ShadowHost {
    /// σ of one ray (or shadow line) feature, as `ShadowHead::forward`.
    fn sigma(&self, feature: &[f32]) -> f32 {
        let affine: f32 = self.bias
            + feature
                .iter()
                .zip(&self.weight)
                .map(|(a, b)| a * b)
                .sum::<f32>();
        shadow_host(affine)
    }
}

impl LightFieldHost {
    fn new(colf: &Colf, prepared: &PreparedSlots) -> Result<LightFieldHost> {
        let cfg = colf.config();
        let fields_w = prepared
            .light_fields()
            .ok_or_else(|| anyhow!("slots were not prepared for a light-field model"))?;
        let s = 1 + prepared.num_fg();
        let mut fields: Vec<Vec<HostDense>> = (0..s).map(|_| Vec::new()).collect();
        for layer in &fields_w.layers {
            let (ls, inp, out) = layer.weight.dims3()?;
            if ls != s {
                bail!("{ls} prepared light fields for {s} slots");
            }
            let w = layer.weight.flatten_all()?.to_vec1::<f32>()?;
            let b = layer.bias.flatten_all()?.to_vec1::<f32>()?;
            for (i, f) in fields.iter_mut().enumerate() {
                f.push(HostDense {
                    input: inp,
                    output: out,
                    w: w[i * inp * out..(i + 1) * inp * out].to_vec(),
                    b: b[i * out..(i + 1) * out].to_vec(),
                });
            }
        }
        let h = cfg.head_hidden_layers;
        let color: Vec<HostDense> = (0..=h)
            .map(|i| linear(colf, &format!("heads.color.layers.{i}"), true))
            .collect::<Result<_>>()?;
        let ordering: Vec<HostDense> = (0..=h)
            .map(|i| linear(colf, &format!("heads.ordering.layers.{i}"), true))
            .collect::<Result<_>>()?;
        let side_by_side = |a: &HostDense, b: &HostDense| -> HostDense {
            let (inp, oa, ob) = (a.input, a.output, b.output);
            let mut w = vec![0f32; inp * (oa + ob)];
            for r in 0..inp {
                w[r * (oa + ob)..r * (oa + ob) + oa].copy_from_slice(&a.w[r * oa..(r + 1) * oa]);
                w[r * (oa + ob) + oa..(r + 1) * (oa + ob)]
                    .copy_from_slice(&b.w[r * ob..(r + 1) * ob]);
            }
            let mut bias = a.b.clone();
            bias.extend(&b.b);
            HostDense {
                input: inp,
                output: oa + ob,
                w,
                b: bias,
            }
        };
        let head_first = side_by_side(&color[0], &ordering[0]);
        let head_mid = (1..h)
            .map(|i| (color[i].clone(), ordering[i].clone()))
            .collect();
        let head_out = if h == 0 {
            None
        } else {
            let (c, o) = (&color[h], &ordering[h]);
            let hh = c.input;
            let mut w = vec![0f32; 2 * hh * 4];
            for r in 0..hh {
                w[r * 4..r * 4 + 3].copy_from_slice(&c.w[r * 3..(r + 1) * 3]);
                w[(hh + r) * 4 + 3] = o.w[r];
            }
            Some(HostDense {
                input: 2 * hh,
                output: 4,
                w,
                b: vec![c.b[0], c.b[1], c.b[2], o.b[0]],
            })
        };
        let c = cfg.compositor_hidden_layers;
        let comp = (0..=c)
            .map(|i| linear(colf, &format!("compositor.v.layers.{i}"), i < c))
            .collect::<Result<_>>()?;
        let slope = param(colf, "compositor.gap_log_slope")?
            .exp()?
            .flatten_all()?
            .to_vec1::<f32>()?[0];
        let shadow = if cfg.shadow_head {
            let logit = linear(colf, "heads.shadow", true)?;
            Some(ShadowHost {
                weight: logit.w,
                bias: logit.b[0],
                to_light: cfg.shadow_light.map(light_direction),
                reach: cfg.shadow_reach_bound(),
            })
        } else {
            None
        };
        Ok(LightFieldHost {
            fields,
            head_first,
            head_mid,
            head_out,
            shadow,
            head_hidden: cfg.head_hidden,
            comp,
            gap_slope: slope,
            scene_scale: cfg.scene_scale,
            freqs: cfg.ray_fourier_freqs,
            in_dim: cfg.ray_input_dim(),
            floor_freqs: cfg.floor_fourier_freqs,
            line_dim: cfg.line_input_dim(),
            slot_reach: cfg.slot_reach_bound(),
            shift_cfg: Config {
                ray_fourier_freqs: 0,
                floor_fourier_freqs: 0,
                shadow_light: None,
                shadow_reach: 0.0,
                ..cfg.clone()
            },
        })
    }

    /// Runs field `si`'s light field on the first `m` rows of `sc.a` (encoded lines): ReLU
    /// layers, then the linear feature layer; the features end in `sc.a`. Returns their width.
    fn run_field(&self, si: usize, m: usize, sc: &mut Scratch) -> usize {
        let layers = &self.fields[si];
        let mut x_w = self.in_dim;
        for (li, layer) in layers.iter().enumerate() {
            let relu = li + 1 < layers.len();
            layer.run(&sc.a, x_w, m, &mut sc.b, layer.output, relu);
            std::mem::swap(&mut sc.a, &mut sc.b);
            x_w = layer.output;
        }
        x_w
    }

    fn max_width(&self) -> usize {
        let mut w = self.in_dim.max(2 * self.head_hidden).max(4);
        for f in &self.fields {
            for l in f {
                w = w.max(l.output);
            }
        }
        for l in &self.comp {
            w = w.max(l.output).max(l.input);
        }
        w
    }
}

/// Per-task buffers, reused across the chunks a thread renders.
#[derive(Default)]
struct Scratch {
    a: Vec<f32>,
    b: Vec<f32>,
    c: Vec<f32>,
    rows: Vec<usize>,
    lit_rows: Vec<usize>,
    colors: Vec<f32>,
    order: Vec<f32>,
    world: Vec<f32>,
    score: Vec<f32>,
    front: Vec<f32>,
    shift: Vec<f32>,
    base: Vec<f64>,
    sigma: Vec<f32>,
}

fn grow(v: &mut Vec<f32>, n: usize) {
    if v.len() < n {
        v.resize(n, 0.0);
    }
}

/// Which light-field evaluations a render does (adaptive rendering; see the module
/// documentation): both masks are ray × field, row-major like [`RayOutput::weights`].
#[derive(Clone, Copy, Debug)]
pub struct Active<'a> {
    /// Where each field is evaluated on the ray and composited; the background column must be
    /// all true.
    pub fields: &'a [bool],
    /// Where each foreground slot's shadow line is evaluated, for a model that reads shadows
    /// along the light ([`FastRenderer::shadows_along_light`]); `None`: where its field is.
    /// (A model that reads shadows from the ray's own features evaluates them with the field.)
    pub shadows: Option<&'a [bool]>,
}

/// Every field's light field evaluated on a set of rays ([`FastRenderer::evaluate_fields`]):
/// what the composition reads, so that any subset of the slots can be composited without
/// evaluating them again ([`FastRenderer::composite`]; the redundant-slot drop judges a dozen
/// subsets of one encoding).
pub struct FieldValues {
    fields: usize,
    /// [rays, fields, 3], before shadows.
    colors: Vec<f32>,
    /// The ordering heads' outputs [rays, fields].
    order: Vec<f32>,
    /// The ordering shifts [rays, fields] and their per-ray base.
    shift: Vec<f32>,
    base: Vec<f64>,
    /// The shadow densities the foreground slots cast [rays, fields].
    shadow: Vec<f32>,
    /// With `Config::slot_reach`: whether each field is present on each ray [rays, fields];
    /// empty without a reach (every field on every ray).
    present: Vec<bool>,
}

/// A scene ready for the fast renderer: host copies of the weights, made once.
pub struct FastRenderer {
    kind: Kind,
    /// Frame inverses for the 1 + K fields (background: identity).
    inverses: Vec<DMat4>,
    /// The K foreground frames (for `RayBatch`).
    slot_to_world: Vec<DMat4>,
}

enum Kind {
    LightField(Box<LightFieldHost>),
    Volumetric(Box<VolumetricHost>),
}

impl FastRenderer {
    /// Host copies of `prepared`'s weights (and the model's shared ones); checks the frames.
    pub fn new(colf: &Colf, prepared: &PreparedSlots, slot_to_world: &[DMat4]) -> Result<Self> {
        if slot_to_world.len() != prepared.num_fg() {
            bail!(
                "{} slot frames for {} slots",
                slot_to_world.len(),
                prepared.num_fg()
            );
        }
        let mut inverses = vec![DMat4::IDENTITY];
        inverses.extend(crate::model::rays::world_to_slot(slot_to_world)?);
        let kind = if colf.model().volumetric().is_some() {
            Kind::Volumetric(Box::new(VolumetricHost::new(colf, prepared)?))
        } else {
            Kind::LightField(Box::new(LightFieldHost::new(colf, prepared)?))
        };
        Ok(FastRenderer {
            kind,
            inverses,
            slot_to_world: slot_to_world.to_vec(),
        })
    }

    /// Renders without the shadows foreground slots cast (`Config::shadow_head`): one
    /// light-field evaluation per ray and slot instead of two with `shadow_light`, the
    /// background undarkened. No effect on a model without shadows.
    pub fn drop_shadows(&mut self) {
        if let Kind::LightField(lf) = &mut self.kind {
            lf.shadow = None;
        }
    }

    /// Leaves out the shadow lines and the (ray, slot) pairs that `reached` — the model's
    /// config with other reaches, as `RefineOptions::reached_config` gives — bounds
    /// (`Config::shadow_reach`, `Config::slot_reach`), instead of the model's own bounds: a
    /// cheaper, approximate render for judging encodings. None, or a volumetric model: the
    /// renderer as it is.
    pub fn within_reaches(mut self, reached: Option<&Config>) -> Self {
        if let (Some(reached), Kind::LightField(lf)) = (reached, &mut self.kind) {
            lf.slot_reach = reached.slot_reach_bound();
            if let Some(shadow) = &mut lf.shadow {
                shadow.reach = reached.shadow_reach_bound();
            }
        }
        self
    }

    /// Number of fields 1 + K.
    pub fn fields(&self) -> usize {
        self.inverses.len()
    }

    /// True for a volumetric model.
    pub fn is_volumetric(&self) -> bool {
        matches!(self.kind, Kind::Volumetric(_))
    }

    /// Renders world rays. `samples`: samples per ray of a volumetric model (None: its
    /// config's); must be None for light fields. `active`: optional ray × field mask (light
    /// fields only; the background column must be all true).
    pub fn render(
        &self,
        origins: &[DVec3],
        dirs: &[DVec3],
        samples: Option<usize>,
        active: Option<&[bool]>,
    ) -> Result<RayOutput> {
        let active = active.map(|fields| Active {
            fields,
            shadows: None,
        });
        self.render_with(origins, dirs, samples, active)
    }

    /// Renders light-field rays with the evaluations `active` names (see [`Active`]).
    pub fn render_active(
        &self,
        origins: &[DVec3],
        dirs: &[DVec3],
        active: Active,
    ) -> Result<RayOutput> {
        self.render_with(origins, dirs, None, Some(active))
    }

    /// Every field's light field on the rays, once, for [`Self::composite`]: the stage of a
    /// render that costs (the compositor's is a small part of it). Light-field models only.
    pub fn evaluate_fields(&self, origins: &[DVec3], dirs: &[DVec3]) -> Result<FieldValues> {
        let Kind::LightField(lf) = &self.kind else {
            bail!("composing subsets of the slots applies to light-field models only");
        };
        let (s, r) = (self.fields(), origins.len());
        if dirs.len() != r {
            bail!("{r} ray origins but {} directions", dirs.len());
        }
        crate::model::rays::check_rays(origins, dirs)?;
        let mut values = FieldValues {
            fields: s,
            colors: vec![0.0; 3 * s * r],
            order: vec![0.0; s * r],
            shift: vec![0.0; s * r],
            base: vec![0.0; r],
            shadow: vec![0.0; s * r],
            present: Vec::new(),
        };
        let present = self
            .within_slot_reach(lf, origins, dirs, None)
            .map_or(Vec::new(), |(fields, _)| fields);
        let c = LF_CHUNK;
        values
            .colors
            .par_chunks_mut(3 * s * c)
            .zip(values.order.par_chunks_mut(s * c))
            .zip(values.shift.par_chunks_mut(s * c))
            .zip(values.base.par_chunks_mut(c))
            .zip(values.shadow.par_chunks_mut(s * c))
            .enumerate()
            .try_for_each_init(
                Scratch::default,
                |sc, (ci, ((((colors, order), shift), base), shadow))| {
                    let (start, n) = (ci * c, base.len());
                    let rays = start..start + n;
                    let active = (!present.is_empty()).then(|| Active {
                        fields: &present[s * start..s * (start + n)],
                        shadows: None,
                    });
                    self.lf_fields(lf, sc, &origins[rays.clone()], &dirs[rays], active, shadow)?;
                    colors.copy_from_slice(&sc.colors[..3 * s * n]);
                    order.copy_from_slice(&sc.order[..s * n]);
                    shift.copy_from_slice(&sc.shift[..s * n]);
                    base.copy_from_slice(&sc.base[..n]);
                    Ok::<(), anyhow::Error>(())
                },
            )?;
        values.present = present;
        Ok(values)
    }

    /// The render of `values`' rays by the fields `keep` names (one flag per field; the
    /// background's must be set): the same output as [`Self::render`] with those fields active
    /// on every ray, from the light fields evaluated once.
    pub fn composite(&self, values: &FieldValues, keep: &[bool]) -> Result<RayOutput> {
        let Kind::LightField(lf) = &self.kind else {
            bail!("composing subsets of the slots applies to light-field models only");
        };
        let s = self.fields();
        if values.fields != s || keep.len() != s {
            bail!(
                "{} kept flags and field values of {} fields for {s} fields",
                keep.len(),
                values.fields
            );
        }
        if !keep[0] {
            bail!("the background must be kept");
        }
        let r = values.base.len();
        let mut out = RayOutput::zeros(r, s);
        // The kept fields, where present (`Config::slot_reach`).
        let active: Vec<bool> = if values.present.is_empty() {
            keep.repeat(r)
        } else {
            values
                .present
                .iter()
                .enumerate()
                .map(|(u, &p)| p && keep[u % s])
                .collect()
        };
        par_ray_chunks(&mut out, LF_CHUNK, |sc, start, out| {
            let n = out.rgb.len() / 3;
            let active = &active[s * start..s * (start + n)];
            let copy_into = |v: &mut Vec<f32>, src: &[f32]| {
                v.clear();
                v.extend_from_slice(src);
            };
            copy_into(
                &mut sc.colors,
                &values.colors[3 * s * start..3 * s * (start + n)],
            );
            copy_into(&mut sc.order, &values.order[s * start..s * (start + n)]);
            copy_into(&mut sc.shift, &values.shift[s * start..s * (start + n)]);
            sc.base.clear();
            sc.base.extend_from_slice(&values.base[start..start + n]);
            let width = lf.max_width();
            grow(&mut sc.b, n * width);
            grow(&mut sc.c, n * width);
            grow(&mut sc.world, n * s);
            grow(&mut sc.score, n * s);
            // A left-out slot casts no shadow, as in a render where it is not evaluated.
            for (ri, row) in out.shadow.chunks_exact_mut(s).enumerate() {
                for (si, v) in row.iter_mut().enumerate() {
                    *v = if active[ri * s + si] {
                        values.shadow[(start + ri) * s + si]
                    } else {
                        0.0
                    };
                }
            }
            let fields = Some(&active[..n * s]);
            self.lf_scores(lf, sc, n, fields);
            self.lf_composite(lf, sc, n, fields, out);
            Ok(())
        })?;
        Ok(out)
    }

    /// True for a light-field model whose slots cast shadows read along the light
    /// (`Config::shadow_light`, and shadows not dropped): its shadow evaluations can be masked
    /// apart from its fields ([`Active::shadows`]).
    pub fn shadows_along_light(&self) -> bool {
        matches!(&self.kind, Kind::LightField(lf)
            if lf.shadow.as_ref().is_some_and(|sh| sh.to_light.is_some()))
    }

    fn render_with(
        &self,
        origins: &[DVec3],
        dirs: &[DVec3],
        samples: Option<usize>,
        active: Option<Active>,
    ) -> Result<RayOutput> {
        let s = self.fields();
        let r = origins.len();
        if dirs.len() != r {
            bail!("{r} ray origins but {} directions", dirs.len());
        }
        crate::model::rays::check_rays(origins, dirs)?;
        if let Some(a) = active {
            for (what, mask) in [("active", Some(a.fields)), ("shadow", a.shadows)] {
                if let Some(mask) = mask.filter(|m| m.len() != r * s) {
                    bail!(
                        "{what} mask of {} entries for {r} rays × {s} fields",
                        mask.len()
                    );
                }
            }
            if a.fields.chunks_exact(s).any(|row| !row[0]) {
                bail!("the background must be evaluated on every ray");
            }
        }
        let mut out = RayOutput::zeros(r, s);
        match &self.kind {
            Kind::LightField(lf) => {
                if samples.is_some() {
                    bail!("samples per ray apply to volumetric models only; this model renders light fields (one evaluation per ray)");
                }
                par_ray_chunks(&mut out, LF_CHUNK, |scratch, start, out| {
                    let n = out.rgb.len() / 3;
                    let rays = (&origins[start..start + n], &dirs[start..start + n]);
                    let rows = start * s..(start + n) * s;
                    let active = active.map(|a| Active {
                        fields: &a.fields[rows.clone()],
                        shadows: a.shadows.map(|m| &m[rows.clone()]),
                    });
                    self.lf_chunk(lf, scratch, rays.0, rays.1, active, out)
                })?;
            }
            Kind::Volumetric(vol) => {
                if active.is_some() {
                    bail!("adaptive rendering applies to light-field models only");
                }
                let n_samples = samples.unwrap_or(vol.samples);
                if n_samples == 0 || n_samples > 4096 {
                    bail!("samples per ray must be in 1..=4096, not {n_samples}");
                }
                let chunk = (VOL_POINTS / n_samples).max(1);
                par_ray_chunks(&mut out, chunk, |scratch, start, out| {
                    let n = out.rgb.len() / 3;
                    let rays = (&origins[start..start + n], &dirs[start..start + n]);
                    self.vol_chunk(
                        vol,
                        scratch,
                        rays.0,
                        rays.1,
                        n_samples,
                        out.rgb,
                        out.weights,
                        out.ordering,
                    );
                    Ok(())
                })?;
            }
        }
        Ok(out)
    }

    /// One chunk of light-field rays, in three stages: every field's light field and heads
    /// ([`Self::lf_field`]), the compositor's scores ([`Self::lf_scores`]), and the shadows and
    /// softmax that give the outputs ([`Self::lf_composite`]). See the module documentation.
    fn lf_chunk(
        &self,
        lf: &LightFieldHost,
        sc: &mut Scratch,
        origins: &[DVec3],
        dirs: &[DVec3],
        active: Option<Active>,
        out: ChunkOut,
    ) -> Result<()> {
        let reach = self.within_slot_reach(lf, origins, dirs, active);
        let active = match &reach {
            Some((fields, shadows)) => Some(Active {
                fields,
                shadows: shadows.as_deref(),
            }),
            None => active,
        };
        self.lf_fields(lf, sc, origins, dirs, active, out.shadow)?;
        let fields = active.map(|a| a.fields);
        self.lf_scores(lf, sc, origins.len(), fields);
        self.lf_composite(lf, sc, origins.len(), fields, out);
        Ok(())
    }

    /// With `Config::slot_reach`, `active` narrowed to the slots' reach: the ray × field mask
    /// of the fields evaluated (and, when `active` names them apart, of the shadow lines), each
    /// foreground slot left out of the rays beyond its reach — decided on the f32 moment of the
    /// ray encoded in the slot's frame, as the decode kernel decides. None without a reach.
    fn within_slot_reach(
        &self,
        lf: &LightFieldHost,
        origins: &[DVec3],
        dirs: &[DVec3],
        active: Option<Active>,
    ) -> Option<(Vec<bool>, Option<Vec<bool>>)> {
        let bound = lf.slot_reach?;
        let s = self.fields();
        let mut within = vec![true; origins.len() * s];
        for (ri, (o, d)) in origins.iter().zip(dirs).enumerate() {
            for si in 1..s {
                let line_scale = lf.shift_cfg.line_scale(si);
                let m = plucker_in_frame(&self.inverses[si], *o, *d, line_scale).map(|v| v as f32);
                within[ri * s + si] = within_reach(&m, Some(bound));
            }
        }
        let and = |mask: &[bool]| -> Vec<bool> {
            mask.iter().zip(&within).map(|(a, b)| *a && *b).collect()
        };
        Some(match active {
            Some(a) => (and(a.fields), a.shadows.map(and)),
            None => (within, None),
        })
    }

    /// Stage 1 of [`Self::lf_chunk`] for every field: the scratch sized for the chunk, the
    /// ordering shifts, and each field's colours, orderings and shadows ([`Self::lf_field`]).
    fn lf_fields(
        &self,
        lf: &LightFieldHost,
        sc: &mut Scratch,
        origins: &[DVec3],
        dirs: &[DVec3],
        active: Option<Active>,
        shadow: &mut [f32],
    ) -> Result<()> {
        let s = self.fields();
        let n = origins.len();
        let width = lf.max_width();
        grow(&mut sc.a, n * width);
        grow(&mut sc.b, n * width);
        grow(&mut sc.c, n * width);
        grow(&mut sc.colors, n * s * 3);
        grow(&mut sc.order, n * s);
        grow(&mut sc.world, n * s);
        grow(&mut sc.score, n * s);
        // The ordering shifts (and their per-ray base) by the code the candle path uses
        // (`RayBatch`, with Fourier features off: only the shifts are used from it), so the two
        // cannot drift apart; ray coordinates below, for the rays a field is evaluated on only.
        let rays = RayBatch::new(
            &lf.shift_cfg,
            &[SceneRays {
                slot_to_world: &self.slot_to_world,
                origins,
                dirs,
            }],
            &Device::Cpu,
        )?;
        sc.shift = rays.shift.flatten_all()?.to_vec1::<f32>()?; // [n, S]
        sc.base = rays.base;
        for si in 0..s {
            self.lf_field(lf, sc, si, origins, dirs, active, shadow)?;
        }
        Ok(())
    }

    /// Stage 1 of [`Self::lf_chunk`]: field `si`'s light field on the rays it is active on —
    /// colours and orderings into `sc` — and, for a foreground slot with a shadow head, its
    /// shadow density into `shadow`: from its shadow lines on the rays `active.shadows` names
    /// (`shadow_light`), or from the ray features where the field is active.
    #[allow(clippy::too_many_arguments)]
    fn lf_field(
        &self,
        lf: &LightFieldHost,
        sc: &mut Scratch,
        si: usize,
        origins: &[DVec3],
        dirs: &[DVec3],
        active: Option<Active>,
        shadow: &mut [f32],
    ) -> Result<()> {
        let s = self.fields();
        let n = origins.len();
        let in_dim = lf.in_dim;
        let h2 = lf.head_first.output;
        let is_active = |ri: usize| active.is_none_or(|a| a.fields[ri * s + si]);
        let inv = &self.inverses[si];
        let shadow_head = lf.shadow.as_ref().filter(|_| si > 0);
        // The length this field's moments are divided by (`Config::line_scale`).
        let line_scale = lf.shift_cfg.line_scale(si);
        // Shadow density along the light, as `ShadowHead`: the field on the line from the light
        // through the ray's ground point, on the rays the shadow mask names.
        if let Some((sh, to_light)) = shadow_head.and_then(|sh| Some((sh, sh.to_light?))) {
            let casts = |ri: usize| match active.and_then(|a| a.shadows) {
                Some(m) => m[ri * s + si],
                None => is_active(ri),
            };
            sc.lit_rows.clear();
            for ri in (0..n).filter(|&ri| casts(ri)) {
                if let Some((o, d)) = shadow_line(origins[ri], dirs[ri], to_light) {
                    let j = sc.lit_rows.len();
                    let out = &mut sc.a[j * in_dim..(j + 1) * in_dim];
                    // A line beyond the slot's reach casts nothing: not evaluated.
                    if encode_line(out, inv, (o, d), line_scale, lf.freqs, sh.reach) {
                        // Shadow lines have no floor features: zeros over the scratch.
                        encode_floor(&mut out[lf.line_dim..], None, line_scale, lf.floor_freqs);
                        sc.lit_rows.push(ri);
                    }
                }
            }
            if !sc.lit_rows.is_empty() {
                let x_w = lf.run_field(si, sc.lit_rows.len(), sc);
                for (j, &ri) in sc.lit_rows.iter().enumerate() {
                    shadow[ri * s + si] = sh.sigma(&sc.a[j * x_w..(j + 1) * x_w]);
                }
            }
        }
        sc.rows.clear();
        sc.rows.extend((0..n).filter(|&ri| is_active(ri)));
        let m = sc.rows.len();
        if m == 0 {
            return Ok(());
        }
        // Bounded Plücker coordinates and Fourier features, as `RayBatch`, then the floor
        // columns: the background's floor features, zeros for a slot. Every column of every
        // row is written: `sc.a` holds the last field's activations.
        for (j, &ri) in sc.rows.iter().enumerate() {
            let out = &mut sc.a[j * in_dim..(j + 1) * in_dim];
            let ray = (origins[ri], dirs[ri]);
            encode_line(out, inv, ray, line_scale, lf.freqs, None);
            encode_floor(
                &mut out[lf.line_dim..],
                (si == 0).then_some(ray),
                line_scale,
                lf.floor_freqs,
            );
        }
        let x_w = lf.run_field(si, m, sc);
        // Shadow density from the ray's own features (no `shadow_light`).
        if let Some(sh) = shadow_head.filter(|sh| sh.to_light.is_none()) {
            for (j, &ri) in sc.rows.iter().enumerate() {
                shadow[ri * s + si] = sh.sigma(&sc.a[j * x_w..(j + 1) * x_w]);
            }
        }
        // Heads (features in a).
        lf.head_first
            .run(&sc.a, x_w, m, &mut sc.b, h2, lf.head_out.is_some());
        std::mem::swap(&mut sc.a, &mut sc.b);
        for (c, o) in &lf.head_mid {
            let hh = c.input;
            c.run(&sc.a, h2, m, &mut sc.b, h2, true);
            o.run(&sc.a[hh..], h2, m, &mut sc.b[hh..], h2, true);
            std::mem::swap(&mut sc.a, &mut sc.b);
        }
        if let Some(out) = &lf.head_out {
            out.run(&sc.a, h2, m, &mut sc.b, 4, false);
            std::mem::swap(&mut sc.a, &mut sc.b);
        }
        for (j, &ri) in sc.rows.iter().enumerate() {
            let v = &sc.a[j * 4..j * 4 + 4];
            let at = ri * s + si;
            for c in 0..3 {
                sc.colors[at * 3 + c] = sigmoid(v[c]);
            }
            sc.order[at] = v[3];
        }
        Ok(())
    }

    /// Stage 2 of [`Self::lf_chunk`]: the compositor's score of every active field on every
    /// ray (learned − prior) into `sc.score`, from world-comparable orderings.
    fn lf_scores(&self, lf: &LightFieldHost, sc: &mut Scratch, n: usize, active: Option<&[bool]>) {
        let s = self.fields();
        let is_active = |ri: usize, si: usize| active.is_none_or(|a| a[ri * s + si]);
        // Compositor: world-comparable orderings, the front one, V's inputs.
        let scale = lf.scene_scale as f32;
        for ri in 0..n {
            for si in 0..s {
                let at = ri * s + si;
                sc.world[at] = if is_active(ri, si) {
                    sc.order[at] * scale + sc.shift[at]
                } else {
                    f32::INFINITY
                };
            }
        }
        sc.front.clear();
        sc.front.extend(
            sc.world[..n * s]
                .chunks_exact(s)
                .map(|row| row.iter().copied().fold(f32::INFINITY, f32::min)),
        );
        for si in 0..s {
            sc.rows.clear();
            sc.rows.extend((0..n).filter(|&ri| is_active(ri, si)));
            let m = sc.rows.len();
            if m == 0 {
                continue;
            }
            for (j, &ri) in sc.rows.iter().enumerate() {
                let gap = (sc.world[ri * s + si] - sc.front[ri]) / scale;
                let squashed = gap / (gap * gap + 1.0).sqrt();
                sc.c[j * 2] = sc.order[ri * s + si];
                sc.c[j * 2 + 1] = -squashed;
                sc.score[ri * s + si] = -gap * lf.gap_slope;
            }
            let mut x_w = 2;
            let last = lf.comp.len() - 1;
            let (mut x, mut y) = (std::mem::take(&mut sc.c), std::mem::take(&mut sc.b));
            for (li, layer) in lf.comp.iter().enumerate() {
                layer.run(&x, x_w, m, &mut y, layer.output, li < last);
                std::mem::swap(&mut x, &mut y);
                x_w = layer.output;
            }
            for (j, &ri) in sc.rows.iter().enumerate() {
                // learned − prior, as the candle compositor.
                let at = ri * s + si;
                sc.score[at] += x[j];
            }
            // Put the buffers back (both are scratch of the same size).
            sc.c = y;
            sc.b = x;
        }
    }

    /// Stage 3 of [`Self::lf_chunk`]: shadows darken the background, then a max-subtracted
    /// softmax over the active fields gives the weights, the colour and the orderings.
    fn lf_composite(
        &self,
        lf: &LightFieldHost,
        sc: &mut Scratch,
        n: usize,
        active: Option<&[bool]>,
        out: ChunkOut,
    ) {
        let ChunkOut {
            rgb,
            weights,
            ordering,
            shadow,
        } = out;
        let s = self.fields();
        let is_active = |ri: usize, si: usize| active.is_none_or(|a| a[ri * s + si]);
        // The shadows the evaluated foreground slots cast darken the background's colour.
        if lf.shadow.is_some() {
            for ri in 0..n {
                let cast: f32 = shadow[ri * s + 1..(ri + 1) * s].iter().sum();
                let lit = (-cast).exp();
                for c in 0..3 {
                    sc.colors[ri * s * 3 + c] *= lit;
                }
            }
        }
        // Softmax over the active fields, colour, outputs.
        for ri in 0..n {
            let mut max = f32::NEG_INFINITY;
            for si in 0..s {
                if is_active(ri, si) {
                    max = max.max(sc.score[ri * s + si]);
                }
            }
            let mut sum = 0f32;
            for si in 0..s {
                let e = if is_active(ri, si) {
                    (sc.score[ri * s + si] - max).exp()
                } else {
                    0.0
                };
                weights[ri * s + si] = e;
                sum += e;
            }
            let mut col = [0f32; 3];
            for si in 0..s {
                let w = weights[ri * s + si] / sum;
                weights[ri * s + si] = w;
                for c in 0..3 {
                    col[c] += w * sc.colors[(ri * s + si) * 3 + c];
                }
                ordering[ri * s + si] = if is_active(ri, si) {
                    (sc.world[ri * s + si] as f64 + sc.base[ri]) as f32
                } else {
                    f32::INFINITY
                };
            }
            rgb[ri * 3..ri * 3 + 3].copy_from_slice(&col);
        }
    }

    /// One chunk of volumetric rays, in two stages: every field's density and colour at the
    /// samples ([`Self::vol_field`]), then alpha compositing along each ray
    /// ([`Self::vol_composite`]). See `model/volumetric.rs`.
    #[allow(clippy::too_many_arguments)]
    fn vol_chunk(
        &self,
        vol: &VolumetricHost,
        sc: &mut Scratch,
        origins: &[DVec3],
        dirs: &[DVec3],
        n_samples: usize,
        rgb: &mut [f32],
        weights: &mut [f32],
        ordering: &mut [f32],
    ) {
        let s = self.fields();
        let n = origins.len();
        let m = n * n_samples;
        let (w, e) = (vol.hidden, vol.pos_dim);
        let he = w + e;
        let heads = vol.bg.head.output; // 1 + colour hidden
        let wide = he.max(heads).max(w);
        grow(&mut sc.a, m * wide);
        grow(&mut sc.b, m * wide);
        grow(&mut sc.c, m * he);
        grow(&mut sc.sigma, s * m);
        grow(&mut sc.colors, s * m * 3);
        let delta = (vol.far - vol.near) / n_samples as f64;
        let depths: Vec<f64> = (0..n_samples)
            .map(|i| vol.near + (i as f64 + 0.5) * delta)
            .collect();
        for si in 0..s {
            self.vol_field(vol, sc, si, origins, dirs, &depths);
        }
        self.vol_composite(vol, sc, n, &depths, delta, rgb, weights, ordering);
    }

    /// Stage 1 of [`Self::vol_chunk`]: field `si`'s density and colour at every sample of every
    /// ray (`depths` along it), into `sc.sigma` and `sc.colors`.
    fn vol_field(
        &self,
        vol: &VolumetricHost,
        sc: &mut Scratch,
        si: usize,
        origins: &[DVec3],
        dirs: &[DVec3],
        depths: &[f64],
    ) {
        let n = origins.len();
        let n_samples = depths.len();
        let m = n * n_samples;
        let (w, e) = (vol.hidden, vol.pos_dim);
        let he = w + e;
        let heads = vol.bg.head.output;
        let (net, biases) = if si == 0 {
            (&vol.bg, &vol.slot_bias[0])
        } else {
            (&vol.fg, &vol.slot_bias[si])
        };
        // γ(p) into columns W … W + E of c (the skip layer's [h, γ(p)]) and into a.
        let inv = &self.inverses[si];
        for ri in 0..n {
            let d = dirs[ri].normalize();
            for (k, t) in depths.iter().enumerate() {
                let p = inv.transform_point3(origins[ri] + *t * d) / vol.scene_scale;
                let row = ri * n_samples + k;
                crate::model::volumetric::encode_point(
                    [p.x, p.y, p.z],
                    vol.pos_freqs,
                    &mut sc.c[row * he + w..(row + 1) * he],
                );
                sc.a[row * e..(row + 1) * e].copy_from_slice(&sc.c[row * he + w..(row + 1) * he]);
            }
        }
        // Layers before the skip; the last writes into c's first W columns.
        let before = vol.before;
        let mut x_w = e;
        for li in 0..before {
            let layer = &net.layers[li];
            let bias = if li == 0 { &biases.0 } else { &layer.b };
            if li + 1 == before {
                layer.run_bias(&sc.a, x_w, m, &mut sc.c, he, true, bias);
            } else {
                layer.run_bias(&sc.a, x_w, m, &mut sc.b, w, true, bias);
                std::mem::swap(&mut sc.a, &mut sc.b);
            }
            x_w = w;
        }
        // The skip layer on [h, γ(p)] (z folded into its bias), then the rest.
        net.layers[before].run_bias(&sc.c, he, m, &mut sc.a, w, true, &biases.1);
        for layer in &net.layers[before + 1..] {
            layer.run(&sc.a, w, m, &mut sc.b, w, true);
            std::mem::swap(&mut sc.a, &mut sc.b);
        }
        // Density and colour hidden in one product (both ReLU), then the colour output.
        net.head.run(&sc.a, w, m, &mut sc.b, heads, true);
        net.color_out.run(&sc.b[1..], heads, m, &mut sc.a, 3, false);
        for i in 0..m {
            sc.sigma[si * m + i] = sc.b[i * heads];
            for c in 0..3 {
                sc.colors[(si * m + i) * 3 + c] = sigmoid(sc.a[i * 3 + c]);
            }
        }
    }

    /// Stage 2 of [`Self::vol_chunk`]: density-weighted slots, alpha compositing along each ray.
    #[allow(clippy::too_many_arguments)]
    fn vol_composite(
        &self,
        vol: &VolumetricHost,
        sc: &Scratch,
        n: usize,
        depths: &[f64],
        delta: f64,
        rgb: &mut [f32],
        weights: &mut [f32],
        ordering: &mut [f32],
    ) {
        let s = self.fields();
        let n_samples = depths.len();
        let m = n * n_samples;
        for ri in 0..n {
            let mut optical = 0f64;
            let mut col = [0f64; 3];
            let mut wsum = 0f64;
            let wrow = &mut weights[ri * s..(ri + 1) * s];
            let orow = &mut ordering[ri * s..(ri + 1) * s];
            wrow.fill(0.0);
            orow.fill(0.0);
            for (k, t) in depths.iter().enumerate() {
                let i = ri * n_samples + k;
                let total: f32 = (0..s).map(|si| sc.sigma[si * m + i]).sum();
                let total = total as f64;
                let alpha = 1.0 - (-total * delta).exp();
                let trans = (-optical).exp();
                optical += total * delta;
                let wi = trans * alpha;
                wsum += wi;
                let inv_total = 1.0 / (total + 1e-10);
                for si in 0..s {
                    let share = sc.sigma[si * m + i] as f64 * inv_total;
                    if share == 0.0 {
                        continue;
                    }
                    let ws = wi * share;
                    wrow[si] += ws as f32;
                    orow[si] += (ws * t) as f32;
                    for c in 0..3 {
                        col[c] += ws * sc.colors[(si * m + i) * 3 + c] as f64;
                    }
                }
            }
            for si in 0..s {
                orow[si] = if wrow[si] > 0.0 {
                    orow[si] / wrow[si]
                } else {
                    vol.far as f32
                };
            }
            wrow[0] += (1.0 - wsum) as f32;
            for c in 0..3 {
                rgb[ri * 3 + c] = col[c] as f32;
            }
        }
    }
}

/// One volumetric network on the host: layer 0's and the skip layer's weights restricted to
/// their γ(p) (and h) columns; the latent columns are folded into per-slot biases.
struct VolNetHost {
    layers: Vec<HostDense>,
    /// Density (column 0) and colour hidden (1 …) side by side.
    head: HostDense,
    color_out: HostDense,
    /// Latent columns of layer 0 and of the skip layer, [D, W] row-major.
    z0: HostDense,
    z_skip: HostDense,
}

struct VolumetricHost {
    bg: VolNetHost,
    fg: VolNetHost,
    /// Per field: (layer-0 bias, skip-layer bias) with W·z added.
    slot_bias: Vec<(Vec<f32>, Vec<f32>)>,
    hidden: usize,
    pos_dim: usize,
    pos_freqs: usize,
    before: usize,
    samples: usize,
    near: f64,
    far: f64,
    scene_scale: f64,
}

impl VolNetHost {
    fn new(colf: &Colf, prefix: &str, before: usize, e: usize) -> Result<VolNetHost> {
        let cfg = colf.config();
        let v = cfg.volumetric.as_ref().expect("volumetric config");
        let n = v.layers_before_skip + v.layers_after_skip;
        let mut layers = Vec::with_capacity(n);
        let (mut z0, mut z_skip) = (None, None);
        for i in 0..n {
            let full = linear(colf, &format!("{prefix}.layers.{i}"), true)?;
            if i == 0 || i == before {
                // Rows of W [in, out]: (h,) γ(p), then z.
                let keep = full.input - cfg.slot_dim;
                let out = full.output;
                let main = HostDense {
                    input: keep,
                    output: out,
                    w: full.w[..keep * out].to_vec(),
                    b: full.b.clone(),
                };
                let z = HostDense {
                    input: cfg.slot_dim,
                    output: out,
                    w: full.w[keep * out..].to_vec(),
                    b: full.b.clone(),
                };
                if i == 0 {
                    z0 = Some(z);
                } else {
                    z_skip = Some(z);
                }
                layers.push(main);
            } else {
                layers.push(full);
            }
        }
        let density = linear(colf, &format!("{prefix}.density"), true)?;
        let color_hidden = linear(colf, &format!("{prefix}.color.layers.0"), true)?;
        let color_out = linear(colf, &format!("{prefix}.color.layers.1"), true)?;
        let (wd, ch) = (density.input, color_hidden.output);
        let mut w = vec![0f32; wd * (1 + ch)];
        for r in 0..wd {
            w[r * (1 + ch)] = density.w[r];
            w[r * (1 + ch) + 1..(r + 1) * (1 + ch)]
                .copy_from_slice(&color_hidden.w[r * ch..(r + 1) * ch]);
        }
        let mut b = density.b.clone();
        b.extend(&color_hidden.b);
        let _ = e;
        Ok(VolNetHost {
            layers,
            head: HostDense {
                input: wd,
                output: 1 + ch,
                w,
                b,
            },
            color_out,
            z0: z0.expect("layer 0"),
            z_skip: z_skip.expect("skip layer"),
        })
    }

    /// (layer-0 bias, skip bias) for latent z: b + z·W_z.
    fn slot_bias(&self, z: &[f32]) -> (Vec<f32>, Vec<f32>) {
        let mut a = vec![0f32; self.z0.output];
        let mut b = vec![0f32; self.z_skip.output];
        let (na, nb) = (a.len(), b.len());
        self.z0.run(z, z.len(), 1, &mut a, na, false);
        self.z_skip.run(z, z.len(), 1, &mut b, nb, false);
        (a, b)
    }
}

impl VolumetricHost {
    fn new(colf: &Colf, prepared: &PreparedSlots) -> Result<VolumetricHost> {
        let cfg = colf.config();
        let v = cfg
            .volumetric
            .as_ref()
            .ok_or_else(|| anyhow!("not a volumetric model"))?;
        let e = v.pos_dim();
        let before = v.layers_before_skip;
        let bg = VolNetHost::new(colf, "volumetric.bg", before, e)?;
        let fg = VolNetHost::new(colf, "volumetric.fg", before, e)?;
        let slot_bias = prepared
            .latents()
            .iter()
            .enumerate()
            .map(|(i, z)| {
                if i == 0 {
                    bg.slot_bias(z)
                } else {
                    fg.slot_bias(z)
                }
            })
            .collect();
        Ok(VolumetricHost {
            bg,
            fg,
            slot_bias,
            hidden: v.hidden,
            pos_dim: e,
            pos_freqs: v.pos_freqs,
            before,
            samples: v.samples,
            near: v.near,
            far: v.far,
            scene_scale: cfg.scene_scale,
        })
    }
}

/// One chunk's rays (origins, directions).
/// One chunk's outputs: the `RayOutput` rows of its rays.
struct ChunkOut<'a> {
    rgb: &'a mut [f32],
    weights: &'a mut [f32],
    ordering: &'a mut [f32],
    shadow: &'a mut [f32],
}

/// Runs `task(scratch, first_ray, outputs)` on the chunks of `chunk` rays of `out`, in
/// parallel, each with its own scratch buffers; the first error stops the rest.
fn par_ray_chunks<F>(out: &mut RayOutput, chunk: usize, task: F) -> Result<()>
where
    F: Fn(&mut Scratch, usize, ChunkOut) -> Result<()> + Sync + Send,
{
    let s = out.fields;
    out.rgb
        .par_chunks_mut(3 * chunk)
        .zip(out.weights.par_chunks_mut(s * chunk))
        .zip(out.ordering.par_chunks_mut(s * chunk))
        .zip(out.shadow.par_chunks_mut(s * chunk))
        .enumerate()
        .try_for_each_init(
            Scratch::default,
            |scratch, (ci, (((rgb, weights), ordering), shadow))| {
                let start = ci * chunk;
                let out = ChunkOut {
                    rgb,
                    weights,
                    ordering,
                    shadow,
                };
                task(scratch, start, out)
            },
        )
}
