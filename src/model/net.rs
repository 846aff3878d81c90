//! [`ColfNet`]: the module tree on candle tensors — encoder, slot attention, and the decoder
//! (hypernetworks, light fields, heads, compositor; or the volumetric baseline). It is
//! differentiable; training and test-time refinement run through it.

use super::decode_kernel;
use super::*;
use candle_core::Tensor;
use candle_nn::VarBuilder;
use rand::rngs::StdRng;

/// The differentiable model. Parameters live under `encoder.`, `slot_attention.`
/// (`background_reader.` with `Config::background_reader`) and the
/// decoder's prefixes: `hypernet_fg.`, `hypernet_bg.` (or `background_field.`), `heads.` and
/// `compositor.` for light
/// fields, `volumetric.` for the volumetric baseline (`Config::volumetric`).
#[derive(Clone, Debug)]
pub struct ColfNet {
    pub cfg: Config,
    pub encoder: encoder::Encoder,
    pub slot_attention: slot_attention::SlotAttention,
    /// With `Config::background_reader`: where the background latent comes from.
    pub background_reader: Option<background_reader::BackgroundReader>,
    pub decoder: Decoder,
    /// Decode through the composition of candle ops ([`ColfNet::decode_reference`]) instead of
    /// the fused kernel (`decode_kernel.rs`): the same function, at a fraction of the speed;
    /// kept as the reference the kernel is tested against.
    pub reference_decoder: bool,
}

/// How slots become pixels.
#[derive(Clone, Debug)]
pub enum Decoder {
    /// COLF: per-slot light fields from hypernetworks, heads and the compositor.
    LightField(Box<LightFieldDecoder>),
    /// The uORF-style volumetric baseline (inference only; see `volumetric.rs`).
    Volumetric(Box<volumetric::Volumetric>),
}

/// The light-field decoder's modules.
#[derive(Clone, Debug)]
pub struct LightFieldDecoder {
    pub hypernet_fg: hypernet::HyperNet,
    pub background: hypernet::BackgroundField,
    pub heads: heads::Heads,
    pub compositor: compositor::Compositor,
}

/// What [`ColfNet::decode`] returns.
#[derive(Clone, Debug)]
pub struct Decoded {
    /// Composited colour [B, R, 3].
    pub rgb: Tensor,
    /// Compositor weights [B, R, S], S = 1 + K, index 0 = background.
    pub weights: Tensor,
    /// log of `weights`, by log-softmax (use for losses on the weights) [B, R, S].
    pub log_weights: Tensor,
    /// Each field's colour [B, R, S, 3]; the background's already darkened by the shadows.
    pub colors: Tensor,
    /// World-comparable ordering values minus the per-ray `RayBatch::base` [B, R, S].
    pub ordering: Tensor,
    /// Each field's shadow density σ [B, R, S] (0 for the background), with a shadow head.
    pub shadow: Option<Tensor>,
}

/// A light-field model's decoder modules read as fields of the model (`model.heads`,
/// `model.hypernet_fg`, …), as before the volumetric baseline existed.
///
/// # Panics
/// On a volumetric model, which has none of them: code that handles any model uses
/// [`ColfNet::light_field`], and [`ColfNet::prepare`] / [`ColfNet::decode`] return errors.
impl std::ops::Deref for ColfNet {
    type Target = LightFieldDecoder;
    fn deref(&self) -> &LightFieldDecoder {
        self.light_field()
            .expect("a light-field model (this one is volumetric)")
    }
}

impl ColfNet {
    pub fn new(cfg: &Config, vb: VarBuilder) -> candle_core::Result<ColfNet> {
        let encoder = encoder::Encoder::new(cfg, vb.pp("encoder"))?;
        let slot_attention = slot_attention::SlotAttention::new(cfg, vb.pp("slot_attention"))?;
        let background_reader = if cfg.background_reader {
            Some(background_reader::BackgroundReader::new(
                cfg,
                vb.pp("background_reader"),
            )?)
        } else {
            None
        };
        let decoder = if cfg.is_volumetric() {
            Decoder::Volumetric(Box::new(volumetric::Volumetric::new(
                cfg,
                vb.pp("volumetric"),
            )?))
        } else {
            Decoder::LightField(Box::new(LightFieldDecoder {
                hypernet_fg: hypernet::HyperNet::new(cfg, vb.pp("hypernet_fg"))?,
                background: hypernet::BackgroundField::new(cfg, vb.clone())?,
                heads: heads::Heads::new(cfg, vb.pp("heads"))?,
                compositor: compositor::Compositor::new(cfg, vb.pp("compositor"))?,
            }))
        };
        Ok(ColfNet {
            cfg: cfg.clone(),
            encoder,
            slot_attention,
            background_reader,
            decoder,
            reference_decoder: false,
        })
    }

    /// The light-field decoder (None for a volumetric model).
    pub fn light_field(&self) -> Option<&LightFieldDecoder> {
        match &self.decoder {
            Decoder::LightField(lf) => Some(lf),
            Decoder::Volumetric(_) => None,
        }
    }

    /// The volumetric decoder (None for a light-field model).
    pub fn volumetric(&self) -> Option<&volumetric::Volumetric> {
        match &self.decoder {
            Decoder::Volumetric(v) => Some(v),
            Decoder::LightField(_) => None,
        }
    }

    fn light_field_or_err(&self) -> candle_core::Result<&LightFieldDecoder> {
        self.light_field().ok_or_else(|| {
            candle_core::Error::Msg(
                "this is a volumetric (baseline) model: it renders, but light-field training and decoding do not apply".into(),
            )
        })
    }

    /// images [B, 3, S, S] (S = `encoder_size`, values in [0, 1]) → K foreground slots and the
    /// background slot; the slot noise comes from `rng`.
    pub fn encode(
        &self,
        images: &Tensor,
        k: usize,
        rng: &mut StdRng,
    ) -> candle_core::Result<SlotOutput> {
        let tokens = self.encoder.forward(images)?;
        let mut out = self.slot_attention.forward(&tokens, k, rng)?;
        if self.cfg.zero_background {
            out.bg = out.bg.zeros_like()?;
        } else if let Some(reader) = &self.background_reader {
            out.bg = reader.forward(&tokens)?;
        }
        Ok(out)
    }

    /// Runs the hypernetworks once: fg [B, K, D], bg [B, D] → the B·(1 + K) light fields,
    /// scene-major, background first in each scene.
    pub fn prepare(&self, fg: &Tensor, bg: &Tensor) -> candle_core::Result<SlotWeights> {
        let lf = self.light_field_or_err()?;
        let (b, k, d) = fg.dims3()?;
        let bg_w = SlotWeights {
            layers: lf.background.forward(bg)?,
        };
        if k == 0 {
            return Ok(bg_w);
        }
        let fg_w = SlotWeights {
            layers: lf.hypernet_fg.forward(&fg.reshape((b * k, d))?)?,
        };
        SlotWeights::join_scenes(&bg_w, Some(&fg_w), b, k)
    }

    /// Evaluates prepared light fields on encoded rays and composites them: by the fused kernel
    /// (`decode_kernel.rs`) on the CPU, else (or with `reference_decoder`) by candle ops.
    pub fn decode(&self, fields: &SlotWeights, rays: &RayBatch) -> candle_core::Result<Decoded> {
        let lf = self.light_field_or_err()?;
        let f32_cpu = |t: &Tensor| t.device().is_cpu() && t.dtype() == candle_core::DType::F32;
        if self.reference_decoder
            || !f32_cpu(&rays.coords)
            || !fields.layers.iter().all(|l| f32_cpu(&l.weight))
        {
            return self.decode_reference(fields, rays);
        }
        self.check_fields(fields, rays)?;
        decode_kernel::decode(&self.cfg, lf, fields, rays, None)
    }

    /// [`ColfNet::decode`] with each field evaluated only on some rays: `support[b·S + s]` lists
    /// (sorted) the rays of scene b on which field s is evaluated — all of them for the
    /// background (s = 0). Elsewhere the field is absent: compositor weight 0, ordering +∞, no
    /// shadow, no gradient (`decode_kernel::DecodeOp::with_support`). Always the fused kernel
    /// (CPU, f32).
    pub fn decode_with_support(
        &self,
        fields: &SlotWeights,
        rays: &RayBatch,
        support: Vec<Vec<u32>>,
    ) -> candle_core::Result<Decoded> {
        let lf = self.light_field_or_err()?;
        self.check_fields(fields, rays)?;
        decode_kernel::decode(&self.cfg, lf, fields, rays, Some(support))
    }

    fn check_fields(&self, fields: &SlotWeights, rays: &RayBatch) -> candle_core::Result<()> {
        let (b, s) = (rays.scenes, rays.fields);
        if fields.num_fields()? != b * s {
            candle_core::bail!(
                "{} prepared light fields for {} scenes × {} fields of rays",
                fields.num_fields()?,
                b,
                s
            );
        }
        Ok(())
    }

    /// [`ColfNet::decode`] as a composition of candle ops, differentiated by candle's autograd:
    /// the reference the fused kernel is tested against.
    pub fn decode_reference(
        &self,
        fields: &SlotWeights,
        rays: &RayBatch,
    ) -> candle_core::Result<Decoded> {
        let lf = self.light_field_or_err()?;
        let (b, s, r) = (rays.scenes, rays.fields, rays.rays);
        self.check_fields(fields, rays)?;
        if rays.motion.is_some() {
            candle_core::bail!("the reference decoder takes moving rays in their explicit form");
        }
        let features = fields.forward(&rays.coords)?; // [B·S, R, F]
        let (color, ordering) = lf.heads.forward(&features)?;
        let mut colors = color.reshape((b, s, r, 3))?.permute((0, 2, 1, 3))?; // [B, R, S, 3]
        let ordering = ordering.reshape((b, s, r))?.transpose(1, 2)?; // [B, R, S]
                                                                      // σ from the light field on each ray's shadow line (`shadow_light`), else on the ray.
        let shadow = match &rays.shadow_lines {
            Some((lines, on_ground)) => lf
                .heads
                .shadow(&fields.forward(lines)?)?
                .map(|sigma| {
                    let sigma = sigma
                        .reshape((b, s, r))?
                        .broadcast_mul(&on_ground.reshape((b, 1, r))?)?;
                    match self.cfg.shadow_reach_bound() {
                        // Lines beyond `shadow_reach` cast nothing (and pass no gradient).
                        Some(bound) => {
                            let in_dim = lines.dim(2)?;
                            let reach: Vec<f32> = lines
                                .detach()
                                .flatten_all()?
                                .to_vec1::<f32>()?
                                .chunks_exact(in_dim)
                                .map(|line| {
                                    f32::from(u8::from(rays::within_reach(line, Some(bound))))
                                })
                                .collect();
                            sigma.mul(&Tensor::from_vec(reach, (b, s, r), sigma.device())?)
                        }
                        None => Ok(sigma),
                    }
                })
                .transpose()?,
            None => lf.heads.shadow(&features)?,
        };
        // With `slot_reach`: which slots are present on which rays [B, R, S] (u8, and as f32).
        let present = match self.cfg.slot_reach_bound() {
            Some(bound) => {
                let in_dim = rays.coords.dim(2)?;
                let coords = rays.coords.detach().flatten_all()?.to_vec1::<f32>()?;
                let mut present = vec![1u8; b * r * s];
                for (u, field) in coords.chunks_exact(r * in_dim).enumerate() {
                    let (bi, si) = (u / s, u % s);
                    for (ri, ray) in field.chunks_exact(in_dim).enumerate() {
                        if si > 0 && !rays::within_reach(ray, Some(bound)) {
                            present[(bi * r + ri) * s + si] = 0;
                        }
                    }
                }
                let present = Tensor::from_vec(present, (b, r, s), colors.device())?;
                let as_f32 = present.to_dtype(candle_core::DType::F32)?;
                Some((present, as_f32))
            }
            None => None,
        };
        let shadow = match shadow {
            Some(sigma) => {
                // Only foreground slots cast shadows: the background's σ is reported as 0.
                let sigma = sigma.reshape((b, s, r))?.transpose(1, 2)?; // [B, R, S]
                                                                        // An absent slot casts no shadow.
                let sigma = match &present {
                    Some((_, p)) => sigma.mul(p)?,
                    None => sigma,
                };
                let zero = sigma.narrow(2, 0, 1)?.zeros_like()?;
                if s == 1 {
                    Some(zero)
                } else {
                    let cast = sigma.narrow(2, 1, s - 1)?;
                    let lit = cast.sum_keepdim(2)?.neg()?.exp()?;
                    let shaded = colors.narrow(2, 0, 1)?.broadcast_mul(&lit.unsqueeze(3)?)?;
                    colors = Tensor::cat(&[&shaded, &colors.narrow(2, 1, s - 1)?], 2)?;
                    Some(Tensor::cat(&[&zero, &cast], 2)?)
                }
            }
            None => None,
        };
        if let Some((_, p)) = &present {
            colors = colors.broadcast_mul(&p.unsqueeze(3)?)?;
        }
        let comp = lf.compositor.forward_present(
            &ordering.contiguous()?,
            &rays.shift,
            present.as_ref().map(|(p, _)| p),
        )?;
        let rgb = comp.weights.unsqueeze(3)?.broadcast_mul(&colors)?.sum(2)?;
        Ok(Decoded {
            rgb,
            weights: comp.weights,
            log_weights: comp.log_weights,
            colors,
            ordering: comp.ordering,
            shadow,
        })
    }
}
