//! Rays as the light fields see them: 6-D Plücker coordinates in each slot's frame, with
//! normalised, smoothly bounded moments; plus the per-slot shift that makes ordering values
//! comparable across frames.
//!
//! For a world ray (origin o, direction d) and a slot with frame `slot_to_world` = [R | t]:
//! - the ray is taken into the slot's frame (o' = slot_to_world⁻¹·o, d' = R⁻¹·d, normalised);
//!   the background's frame is the world;
//! - Plücker coordinates (d', m') with m' = o' × d': |m'| is the distance of the line from the
//!   frame's origin, so it grows with the scene's extent. The authors fed it raw; here it is
//!   divided by s = `Config::line_scale` (`scene_scale`, or for a foreground slot `slot_scale`
//!   when set) and bounded smoothly, m̂ = (m'/s) / √(1 + |m'/s|²): ≈ m'/s near the
//!   object, |m̂| < 1 always, so a camera 10⁴ units away or a slot moved 10⁴ units away gives
//!   finite, bounded inputs (such rays pass far from the slot and all look alike to it);
//! - optional Fourier features sin/cos(2^k·π·x) of the 6 coordinates (`ray_fourier_freqs`);
//! - with `floor_fourier_freqs` = L > 0, the background's floor columns after those
//!   ([`encode_floor`]): where the camera ray meets the floor plane z = 0 ahead of its origin
//!   at (x, y), a hit flag 1, (x, y)/s bounded as the moment is (s = `scene_scale`), then
//!   sin/cos(2^k·π·x), sin/cos(2^k·π·y) for k < L with x, y in world units (periods
//!   2^(1−k) world units, whatever `scene_scale`: a floor's texture has a size in the world);
//!   zeros on a ray that misses the floor, and in the foreground slots' rows and every shadow
//!   line (one input width for every field);
//! - the shift dot(t − o, d): where the point of the ray closest to the slot's frame origin lies
//!   along the ray, measured from the ray's origin. The light field only sees the line, so its
//!   ordering value can only be measured from that closest point; adding the shift turns it into
//!   a distance from the ray origin, comparable between slots in different frames (see
//!   `compositor.rs`). Computed in f64; per ray the smallest shift (`base`) is subtracted before
//!   the values go to f32 so precision is kept when everything is 10⁴ units away;
//! - with `fg_locality` = r > 0, a foreground slot's shift also grows by ρ²/r, ρ = the ray's
//!   distance from the slot's frame origin: a locality bound (uORF bounded its slots with a
//!   box) that pushes a slot behind the others on rays far from where it lives, so no slot can
//!   claim the whole image. It moves with the frame, so moved and merged slots keep it;
//! - with `cull_behind` = c > 0, a foreground slot whose frame origin lies more than c behind
//!   the ray's origin along it (shift < −c) is pushed [`BEHIND_PUSH`] further back, behind
//!   everything (its compositor weight vanishes), and the background's ordering is not measured
//!   from it. Without that, a slot behind a camera standing among the objects has the most
//!   negative shift and comes first.

use super::config::Config;
use super::decode_kernel::RayMotion;
use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use glam::{DMat4, DVec2, DVec3};
use rayon::prelude::*;
use std::sync::Arc;

/// One scene's rays: its K foreground slot frames and R world rays.
#[derive(Clone, Copy, Debug)]
pub struct SceneRays<'a> {
    pub slot_to_world: &'a [DMat4],
    pub origins: &'a [DVec3],
    pub dirs: &'a [DVec3],
}

/// Rays of B scenes with S = 1 + K light fields each (background first).
#[derive(Debug)]
pub struct RayBatch {
    /// Encoded rays [B·S, R, in], field-major within a scene.
    pub coords: Tensor,
    /// With `Config::shadow_light`: each ray's shadow line (see [`shadow_line`]), encoded like
    /// `coords` [B·S, R, in], and [B, R, 1] 1 where the ray meets the ground, else 0.
    pub shadow_lines: Option<(Tensor, Tensor)>,
    /// Ordering shifts minus `base`, [B, R, S], world units.
    pub shift: Tensor,
    /// Per ray the subtracted base shift [B·R], world units.
    pub base: Vec<f64>,
    pub scenes: usize,
    pub fields: usize,
    pub rays: usize,
    /// When the rays move with a few offsets (refinement moving the frames): the tensors above
    /// are the rays at offsets 0, and gradients reach the offsets through the decode kernel.
    pub motion: Option<MovingRays>,
}

/// The offsets a [`RayBatch`] moves with (a variable [N], zero when read), and how.
#[derive(Clone, Debug)]
pub struct MovingRays {
    pub offsets: Tensor,
    pub motion: Arc<dyn RayMotion>,
}

/// The 6 bounded Plücker coordinates of a ray in a frame given by its inverse `world_to_frame`.
pub fn plucker_in_frame(world_to_frame: &DMat4, o: DVec3, d: DVec3, scene_scale: f64) -> [f64; 6] {
    let o_f = world_to_frame.transform_point3(o);
    let d_f = world_to_frame.transform_vector3(d).normalize();
    let m = o_f.cross(d_f) / scene_scale;
    let m = m / (1.0 + m.length_squared()).sqrt();
    [d_f.x, d_f.y, d_f.z, m.x, m.y, m.z]
}

/// Writes the encoding of the line (o, d) in the frame `world_to_frame` to `out`
/// (`Config::ray_input_dim` values): the 6 bounded Plücker coordinates, then sin/cos of each at
/// `freqs` octaves. The one encoding of rays and shadow lines, here and in `render/fast.rs`.
///
/// `bound` (as [`within_reach`] reads it; None: none): a line that only matters within a reach
/// of the frame origin and passes beyond it gets its Plücker coordinates (what every decoder
/// decides the reach from) and zeros for the Fourier features no decoder reads there (the kernel
/// and the fast renderer skip such a line, the candle reference masks what the field makes of
/// it). Returns whether the line is within the bound.
pub fn encode_line(
    out: &mut [f32],
    world_to_frame: &DMat4,
    (o, d): (DVec3, DVec3),
    scene_scale: f64,
    freqs: usize,
    bound: Option<f32>,
) -> bool {
    let p = plucker_in_frame(world_to_frame, o, d, scene_scale);
    for (c, v) in p.iter().enumerate() {
        out[c] = *v as f32;
    }
    let within = within_reach(out, bound);
    if within {
        write_fourier_features(out, &p, freqs);
    } else {
        out[6..6 + 12 * freqs].fill(0.0);
    }
    within
}

/// The Fourier features of the Plücker coordinates `p` (see [`encode_line`]).
fn write_fourier_features(out: &mut [f32], p: &[f64; 6], freqs: usize) {
    if freqs == 0 {
        return;
    }
    for (c, v) in p.iter().enumerate() {
        // sin/cos(2^f·π·v) by the double-angle formulas from f = 0: one sin/cos per coordinate
        // instead of one per frequency (sin/cos were 4 % of a training step); f64 keeps the
        // error of ≤ 16 doublings far below f32 resolution.
        let (mut sin, mut cos) = (std::f64::consts::PI * v).sin_cos();
        for f in 0..freqs {
            out[6 + 12 * f + c] = sin as f32;
            out[12 + 12 * f + c] = cos as f32;
            (sin, cos) = (2.0 * sin * cos, 1.0 - 2.0 * sin * sin);
        }
    }
}

/// Writes the floor columns of a light field's input (`Config::floor_input_dim` values, for
/// `freqs` = `Config::floor_fourier_freqs` octaves) to `out`: for a `ray` (o, d) that meets
/// the floor plane z = 0 ahead of its origin ([`ground_point`]) at (x, y), a hit flag 1, then
/// p̂ = p/√(1 + |p|²) for p = (x, y)/`scene_scale` (bounded as the Plücker moment is), then for
/// k < `freqs`: sin(2^k·π·x), cos(2^k·π·x), sin(2^k·π·y), cos(2^k·π·y), x and y in world
/// units. Every column is written: zeros when `ray` is None (a foreground slot, a shadow line)
/// or misses the floor, so a reused buffer keeps nothing stale.
pub fn encode_floor(out: &mut [f32], ray: Option<(DVec3, DVec3)>, scene_scale: f64, freqs: usize) {
    debug_assert_eq!(out.len(), super::config::floor_columns(freqs));
    // Without floor features (every model before them) there is nothing to write: no floor
    // hit is computed on the renderer's per-ray path.
    if freqs == 0 {
        return;
    }
    let Some(hit) = ray.and_then(|(o, d)| ground_point(o, d)) else {
        out.fill(0.0);
        return;
    };
    let p = DVec2::new(hit.x, hit.y) / scene_scale;
    let p = p / (1.0 + p.length_squared()).sqrt();
    out[0] = 1.0;
    out[1] = p.x as f32;
    out[2] = p.y as f32;
    for (c, v) in [hit.x, hit.y].into_iter().enumerate() {
        // As `write_fourier_features`: one sin/cos, then the double-angle formulas in f64.
        let (mut sin, mut cos) = (std::f64::consts::PI * v).sin_cos();
        for k in 0..freqs {
            out[3 + 4 * k + 2 * c] = sin as f32;
            out[4 + 4 * k + 2 * c] = cos as f32;
            (sin, cos) = (2.0 * sin * cos, 1.0 - 2.0 * sin * sin);
        }
    }
}

/// Where the ray (o, d) meets the ground plane z = 0 ahead of its origin: None unless the
/// origin is above the plane and the ray points down (and the point is finite).
pub fn ground_point(o: DVec3, d: DVec3) -> Option<DVec3> {
    if !(o.z > 0.0 && d.z < 0.0) {
        return None;
    }
    let ground = o + d * (-o.z / d.z);
    ground.is_finite().then_some(ground)
}

/// The unit vector toward a light at [azimuth, elevation] degrees (azimuth from +X toward +Y,
/// elevation above the ground plane; world +Z up).
pub fn light_direction([azimuth, elevation]: [f64; 2]) -> DVec3 {
    let (sa, ca) = azimuth.to_radians().sin_cos();
    let (se, ce) = elevation.to_radians().sin_cos();
    DVec3::new(ce * ca, ce * sa, se)
}

/// The shadow line of the ray (o, d) for a light in direction `to_light`: the line through
/// the point where the ray meets the ground plane z = 0 and the light — the point is in a slot's
/// shadow when that line passes through the slot's object. Returned as (that ground point,
/// −`to_light`): oriented from the light down to the ground, as the camera rays the light fields
/// were trained on look down at the scene. None when the ray does not meet the ground ahead.
pub fn shadow_line(o: DVec3, d: DVec3, to_light: DVec3) -> Option<(DVec3, DVec3)> {
    ground_point(o, d).map(|ground| (ground, -to_light))
}

/// Whether a line encoded as `encoded` (its [`encode_line`] values in a slot's frame) passes
/// within a reach of the frame origin, for the bound `Config::shadow_reach_bound` (a shadow
/// line) or `Config::slot_reach_bound` (a camera ray); None: no bound. Decided on the f32
/// encoding, so every decoder that evaluates the line decides alike.
pub fn within_reach(encoded: &[f32], bound: Option<f32>) -> bool {
    bound.is_none_or(|q| {
        encoded[3] * encoded[3] + encoded[4] * encoded[4] + encoded[5] * encoded[5] <= q
    })
}

/// Checks frames and rays; returns each frame's inverse.
fn check(scene: usize, rays: &SceneRays) -> Result<Vec<DMat4>> {
    if rays.origins.len() != rays.dirs.len() {
        bail!(
            "scene {scene}: {} ray origins but {} directions",
            rays.origins.len(),
            rays.dirs.len()
        );
    }
    check_rays(rays.origins, rays.dirs).with_context(|| format!("scene {scene}"))?;
    world_to_slot(rays.slot_to_world).with_context(|| format!("scene {scene}"))
}

/// Refuses a ray with a non-finite origin or a zero or non-finite direction: the one check of
/// rays, made wherever rays enter a renderer.
pub fn check_rays(origins: &[DVec3], dirs: &[DVec3]) -> Result<()> {
    for (i, (o, d)) in origins.iter().zip(dirs).enumerate() {
        if !o.is_finite() || !d.is_finite() || d.length_squared() < 1e-24 {
            bail!("ray {i} has a non-finite origin or a zero/non-finite direction");
        }
    }
    Ok(())
}

/// The world-to-slot transforms: the inverse of each `slot_to_world`, refused unless it is
/// finite and invertible (|det| ≥ 1e-12).
pub fn world_to_slot(slot_to_world: &[DMat4]) -> Result<Vec<DMat4>> {
    slot_to_world
        .iter()
        .enumerate()
        .map(|(k, m)| {
            let det = m.determinant();
            if !m.is_finite() || !det.is_finite() || det.abs() < 1e-12 {
                bail!("slot {k}'s slot_to_world is not an invertible finite matrix");
            }
            Ok(m.inverse())
        })
        .collect()
}

/// [`RayBatch`]'s values on the host, before they become tensors.
#[derive(Clone, Debug)]
pub struct HostRays {
    /// [B·S, R, in], field-major within a scene.
    pub coords: Vec<f32>,
    /// With `Config::shadow_light`: the shadow lines [B·S, R, in] and the on-ground flags [B, R].
    pub shadow_lines: Option<(Vec<f32>, Vec<f32>)>,
    /// Ordering shifts minus `base` [B, R, S].
    pub shift: Vec<f32>,
    /// Per ray the subtracted base shift [B·R].
    pub base: Vec<f64>,
    pub scenes: usize,
    pub fields: usize,
    pub rays: usize,
}

impl HostRays {
    /// The batch as tensors on `dev`.
    pub fn into_batch(self, cfg: &Config, dev: &Device) -> Result<RayBatch> {
        let (b, s, r) = (self.scenes, self.fields, self.rays);
        let in_dim = cfg.ray_input_dim();
        let shadow_lines = match self.shadow_lines {
            Some((lines, on_ground)) => Some((
                Tensor::from_vec(lines, (b * s, r, in_dim), dev)?,
                Tensor::from_vec(on_ground, (b, r, 1), dev)?,
            )),
            None => None,
        };
        Ok(RayBatch {
            coords: Tensor::from_vec(self.coords, (b * s, r, in_dim), dev)?,
            shadow_lines,
            shift: Tensor::from_vec(self.shift, (b, r, s), dev)?,
            base: self.base,
            scenes: b,
            fields: s,
            rays: r,
            motion: None,
        })
    }
}

impl RayBatch {
    /// Encodes the rays of `scenes` (all with the same K and R).
    pub fn new(cfg: &Config, scenes: &[SceneRays], dev: &Device) -> Result<RayBatch> {
        HostRays::new(cfg, scenes)?.into_batch(cfg, dev)
    }
}

impl HostRays {
    /// Encodes the rays of `scenes` (all with the same K and R) on the host.
    pub fn new(cfg: &Config, scenes: &[SceneRays]) -> Result<HostRays> {
        // 1. Sizes: every scene of a batch has the same slots and rays.
        let (b, k, r) = batch_shape(scenes)?;
        let s = 1 + k;
        let in_dim = cfg.ray_input_dim();
        let mut coords = vec![0f32; b * s * r * in_dim];
        let mut shift = vec![0f32; b * r * s];
        let mut base = vec![0f64; b * r];
        let mut shadow = cfg
            .shadow_light
            .map(|_| (vec![0f32; b * s * r * in_dim], vec![0f32; b * r]));
        for (bi, scene) in scenes.iter().enumerate() {
            // 2. Each field's frame: the background's is the world.
            let inverses = check(bi, scene)?;
            let frames = field_frames(&inverses, scene.slot_to_world);
            // 3. The camera rays in each field's frame.
            let per_scene = s * r * in_dim;
            let camera_lines: Vec<(DVec3, DVec3)> = scene
                .origins
                .iter()
                .copied()
                .zip(scene.dirs.iter().copied())
                .collect();
            let scene_coords = &mut coords[bi * per_scene..(bi + 1) * per_scene];
            encode_fields(
                cfg,
                scene_coords,
                &frames,
                &camera_lines,
                cfg.slot_reach_bound(),
                true,
            );
            // 4. With shadows, the rays' shadow lines the same way.
            if let Some((shadow_coords, on_ground)) = shadow.as_mut() {
                let to_light = light_direction(cfg.shadow_light.expect("shadow buffers"));
                // Rays that miss the ground keep their own line (any finite line): masked.
                let lines: Vec<(DVec3, DVec3)> = camera_lines
                    .iter()
                    .enumerate()
                    .map(|(ri, &(o, d))| match shadow_line(o, d, to_light) {
                        Some(line) => {
                            on_ground[bi * r + ri] = 1.0;
                            line
                        }
                        None => (o, d),
                    })
                    .collect();
                let scene_lines = &mut shadow_coords[bi * per_scene..(bi + 1) * per_scene];
                encode_fields(
                    cfg,
                    scene_lines,
                    &frames,
                    &lines,
                    cfg.shadow_reach_bound(),
                    false,
                );
            }
            // 5. The ordering shifts that make slots in different frames comparable.
            for (ri, &(o, d)) in camera_lines.iter().enumerate() {
                let row = &mut shift[(bi * r + ri) * s..(bi * r + ri + 1) * s];
                base[bi * r + ri] = ordering_shifts(cfg, &frames, o, d, row);
            }
        }
        Ok(HostRays {
            coords,
            shadow_lines: shadow,
            shift,
            base,
            scenes: b,
            fields: s,
            rays: r,
        })
    }
}

/// The derivatives of a [`HostRays`]' values with respect to moving the foreground frames'
/// origins along one world axis (all frames together; each field's share is its own), written
/// out. Refinement reads only the shifts' ([`HostRays::shift_derivatives`]) and contracts the
/// encoded lines' on the fly (`MovingLines` in `encode/refine.rs`); these are the reference it
/// is tested against.
#[derive(Clone, Debug)]
pub struct FrameDerivatives {
    /// ∂coords/∂t_axis [B·S, R, in] (0 for the background, and for the floor columns).
    pub coords: Vec<f32>,
    /// ∂(shadow lines)/∂t_axis, with `Config::shadow_light`.
    pub shadow_lines: Option<Vec<f32>>,
    /// ∂(ordering shift, before the base is subtracted)/∂t_axis [B, R, S]. The background's
    /// entry is its shift's derivative along the frame it follows (`background_follows`).
    pub shift: Vec<f32>,
    /// Per ray [B·R], the foreground field (≥ 1) whose frame the background's ordering shift
    /// moves with (`Config::background_from_nearest_slot`), or 0 when it moves with none.
    pub background_follows: Vec<u32>,
}

/// ∂(encoded line)/∂δ for the line's frame origin moved by δ along the world vector whose image
/// in the frame is `frame_axis` (= A⁻¹·e, A the frame's linear part): the line's origin in the
/// frame moves by −δ·`frame_axis`, its direction not at all, so only the bounded moment and its
/// Fourier features change. `encoded` is the line's encoding ([`encode_line`]); `d_frame` its
/// unit direction in the frame.
fn encode_line_derivative(
    out: &mut [f32],
    encoded: &[f32],
    d_frame: DVec3,
    frame_axis: DVec3,
    scene_scale: f64,
    freqs: usize,
) {
    // m = o' × d' / s, so ∂m = −(axis × d') / s; m̂ = m/√(1 + |m|²) gives
    // ∂m̂ = √(1 − |m̂|²)·(∂m − m̂ (m̂·∂m)).
    let m_hat = DVec3::new(encoded[3] as f64, encoded[4] as f64, encoded[5] as f64);
    let dm = -frame_axis.cross(d_frame) / scene_scale;
    let dm_hat = (1.0 - m_hat.length_squared()).max(0.0).sqrt() * (dm - m_hat * m_hat.dot(dm));
    let dv = [0.0, 0.0, 0.0, dm_hat.x, dm_hat.y, dm_hat.z];
    for (c, d) in dv.iter().enumerate() {
        out[c] = *d as f32;
        let mut omega = std::f64::consts::PI;
        for f in 0..freqs {
            let (sin, cos) = (
                encoded[6 + 12 * f + c] as f64,
                encoded[12 + 12 * f + c] as f64,
            );
            out[6 + 12 * f + c] = (omega * cos * d) as f32;
            out[12 + 12 * f + c] = (-omega * sin * d) as f32;
            omega *= 2.0;
        }
    }
}

impl HostRays {
    /// The derivatives of these rays' values (encoded from `scenes`, as [`HostRays::new`] did)
    /// with respect to the foreground frames' origins along world axis `axis` (0, 1, 2).
    pub fn frame_derivatives(
        &self,
        cfg: &Config,
        scenes: &[SceneRays],
        axis: usize,
    ) -> Result<FrameDerivatives> {
        let (s, r) = (self.fields, self.rays);
        let in_dim = cfg.ray_input_dim();
        let (shift, background_follows) = self.shift_derivatives(cfg, scenes, axis)?;
        let mut coords = vec![0f32; self.coords.len()];
        let mut lines = self.shadow_lines.as_ref().map(|(l, _)| vec![0f32; l.len()]);
        let to_light = cfg.shadow_light.map(light_direction);
        let mut world_axis = DVec3::ZERO;
        world_axis[axis] = 1.0;
        for (bi, scene) in scenes.iter().enumerate() {
            let inverses = check(bi, scene)?;
            for (k, inv) in inverses.iter().enumerate() {
                let field = bi * s + 1 + k;
                let frame_axis = inv.transform_vector3(world_axis);
                for ri in 0..r {
                    let (o, d) = (scene.origins[ri], scene.dirs[ri]);
                    let at = (field * r + ri) * in_dim;
                    let d_frame = inv.transform_vector3(d).normalize();
                    encode_line_derivative(
                        &mut coords[at..at + in_dim],
                        &self.coords[at..at + in_dim],
                        d_frame,
                        frame_axis,
                        cfg.line_scale(1 + k),
                        cfg.ray_fourier_freqs,
                    );
                    if let (Some(out), Some((encoded, _)), Some(to_light)) =
                        (lines.as_mut(), &self.shadow_lines, to_light)
                    {
                        // A ray off the ground keeps its own line (masked in the decoder).
                        let line_dir = shadow_line(o, d, to_light).map_or(d, |(_, dir)| dir);
                        encode_line_derivative(
                            &mut out[at..at + in_dim],
                            &encoded[at..at + in_dim],
                            inv.transform_vector3(line_dir).normalize(),
                            frame_axis,
                            cfg.line_scale(1 + k),
                            cfg.ray_fourier_freqs,
                        );
                    }
                }
            }
        }
        Ok(FrameDerivatives {
            coords,
            shadow_lines: lines,
            shift,
            background_follows,
        })
    }

    /// [`FrameDerivatives::shift`] and [`FrameDerivatives::background_follows`] alone: what
    /// refinement still needs written out once the encoded lines' derivatives are contracted
    /// with their gradient on the fly (`encode/refine.rs`).
    pub fn shift_derivatives(
        &self,
        cfg: &Config,
        scenes: &[SceneRays],
        axis: usize,
    ) -> Result<(Vec<f32>, Vec<u32>)> {
        let (s, r) = (self.fields, self.rays);
        let mut shift = vec![0f32; self.shift.len()];
        let mut background_follows = vec![0u32; scenes.len() * r];
        for (bi, scene) in scenes.iter().enumerate() {
            let inverses = check(bi, scene)?;
            // The background's shift moves with the nearest frame's along = (t − o)·d̂.
            let frames = field_frames(&inverses, scene.slot_to_world);
            for ri in 0..r {
                let d_hat = scene.dirs[ri].normalize();
                if let Some(nearest) = background_anchor(cfg, &frames, scene.origins[ri], d_hat) {
                    shift[(bi * r + ri) * s] = d_hat[axis] as f32;
                    background_follows[bi * r + ri] = nearest as u32;
                }
            }
            for (k, m) in scene.slot_to_world.iter().enumerate() {
                let t = m.w_axis.truncate();
                for ri in 0..r {
                    let (o, d) = (scene.origins[ri], scene.dirs[ri]);
                    // along = (t − o)·d̂; with a locality bound ρ²/r, ρ² = |t − o|² − along².
                    let d_hat = d.normalize();
                    let along = (t - o).dot(d_hat);
                    let mut ds = d_hat[axis];
                    if cfg.fg_locality > 0.0 {
                        ds += 2.0 * ((t - o)[axis] - along * d_hat[axis]) / cfg.fg_locality;
                    }
                    shift[(bi * r + ri) * s + 1 + k] = ds as f32;
                }
            }
        }
        Ok((shift, background_follows))
    }
}

/// Each field's frame (world-to-field, origin), the background's first: the world's.
fn field_frames(inverses: &[DMat4], slot_to_world: &[DMat4]) -> Vec<(DMat4, DVec3)> {
    std::iter::once((DMat4::IDENTITY, DVec3::ZERO))
        .chain(
            inverses
                .iter()
                .zip(slot_to_world)
                .map(|(inv, m)| (*inv, m.w_axis.truncate())),
        )
        .collect()
}

/// A batch's scenes, slots and rays, refused unless every scene has the same (and some rays).
fn batch_shape(scenes: &[SceneRays]) -> Result<(usize, usize, usize)> {
    let Some(first) = scenes.first() else {
        bail!("no scenes to render");
    };
    let (k, r) = (first.slot_to_world.len(), first.origins.len());
    if scenes
        .iter()
        .any(|s| s.slot_to_world.len() != k || s.origins.len() != r)
    {
        bail!("scenes of one batch must have the same number of slots and rays");
    }
    if r == 0 {
        bail!("no rays to render");
    }
    Ok((scenes.len(), k, r))
}

/// Encodes `lines` in each field's frame (`frames`: world-to-field and origin) into `dest`,
/// field-major [S, R, in_dim]; fields in parallel. A foreground field's line beyond `reach`
/// (the bound of [`encode_line`]) gets no Fourier features: no decoder reads them. The floor
/// columns ([`encode_floor`]) hold the background's floor features when `camera` (the lines
/// are camera rays), else zeros, as every foreground field's.
fn encode_fields(
    cfg: &Config,
    dest: &mut [f32],
    frames: &[(DMat4, DVec3)],
    lines: &[(DVec3, DVec3)],
    reach: Option<f32>,
    camera: bool,
) {
    let in_dim = cfg.ray_input_dim();
    let line_dim = cfg.line_input_dim();
    dest.par_chunks_mut(lines.len() * in_dim)
        .zip(frames.par_iter())
        .enumerate()
        .for_each(|(f, (field, (inv, _)))| {
            let scale = cfg.line_scale(f);
            let bound = if f > 0 { reach } else { None };
            let floor = camera && f == 0;
            for (out, (o, d)) in field.chunks_exact_mut(in_dim).zip(lines) {
                encode_line(out, inv, (*o, *d), scale, cfg.ray_fourier_freqs, bound);
                encode_floor(
                    &mut out[line_dim..],
                    floor.then_some((*o, *d)),
                    scale,
                    cfg.floor_fourier_freqs,
                );
            }
        });
}

/// How far back (world units) `cull_behind` pushes a slot behind the ray's origin: far enough
/// that the compositor's monotone gap prior gives it no weight, finite so every score stays
/// finite.
pub const BEHIND_PUSH: f64 = 1e6;

/// Whether a foreground slot whose frame origin lies `along` the ray from its origin is culled
/// (`Config::cull_behind`).
fn behind_the_ray(cfg: &Config, along: f64) -> bool {
    cfg.cull_behind > 0.0 && along < -cfg.cull_behind
}

/// The ordering shifts of the ray (o, d) for each field (`frames`' origins): how far along the
/// ray its frame origin lies (plus ρ²/`Config::fg_locality` for foreground slots with a locality
/// bound, ρ the ray's distance from the origin; the background's from the nearest foreground
/// origin with `Config::background_from_nearest_slot`), written into `row` relative to the
/// smallest, which is returned as the ray's base.
fn ordering_shifts(
    cfg: &Config,
    frames: &[(DMat4, DVec3)],
    o: DVec3,
    d: DVec3,
    row: &mut [f32],
) -> f64 {
    let d = d.normalize();
    let mut shifts: Vec<f64> = frames
        .iter()
        .enumerate()
        .map(|(si, (_, t))| {
            let along = (*t - o).dot(d);
            let mut shift = along;
            if si > 0 && cfg.fg_locality > 0.0 {
                shift += ((*t - o) - along * d).length_squared() / cfg.fg_locality;
            }
            if si > 0 && behind_the_ray(cfg, along) {
                shift += BEHIND_PUSH;
            }
            shift
        })
        .collect();
    if let Some(nearest) = background_anchor(cfg, frames, o, d) {
        shifts[0] = (frames[nearest].1 - o).dot(d);
    }
    let lo = shifts.iter().copied().fold(f64::INFINITY, f64::min);
    for (out, v) in row.iter_mut().zip(&shifts) {
        *out = (v - lo) as f32;
    }
    lo
}

/// With `Config::background_from_nearest_slot` and some slots: the field (≥ 1) whose frame
/// origin lies nearest along the ray (o, d̂), from which the background's ordering is measured
/// (the first on ties); `None` when the background keeps the world origin.
fn background_anchor(
    cfg: &Config,
    frames: &[(DMat4, DVec3)],
    o: DVec3,
    d_hat: DVec3,
) -> Option<usize> {
    if !cfg.background_from_nearest_slot {
        return None;
    }
    let mut nearest: Option<(usize, f64)> = None;
    for (field, (_, t)) in frames.iter().enumerate().skip(1) {
        let along = (*t - o).dot(d_hat);
        if behind_the_ray(cfg, along) {
            continue;
        }
        if nearest.is_none_or(|(_, best)| along < best) {
            nearest = Some((field, along));
        }
    }
    nearest.map(|(field, _)| field)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The host encoding of one scene's rays (test shorthand).
    fn host_rays(cfg: &Config, frames: &[DMat4], origins: &[DVec3], dirs: &[DVec3]) -> HostRays {
        HostRays::new(
            cfg,
            &[SceneRays {
                slot_to_world: frames,
                origins,
                dirs,
            }],
        )
        .unwrap()
    }

    /// The analytic frame derivatives agree with forward differences of the encoding, one
    /// frame moved at a time: its own field's values move by its derivatives, the background's
    /// ordering shift by its own where it follows that frame, nothing else.
    #[test]
    fn frame_derivatives_match_forward_differences() {
        // And with the slots' own line scale.
        // And with the background's floor columns (world frame: they never move).
        for (from_nearest, slot_scale, floor) in [
            (false, 0.0, 0),
            (true, 0.0, 0),
            (false, 1.5, 0),
            (true, 0.0, 2),
        ] {
            let mut cfg = Config::small();
            cfg.floor_fourier_freqs = floor;
            cfg.ray_fourier_freqs = 3;
            cfg.fg_locality = 2.0;
            cfg.shadow_head = true;
            cfg.shadow_light = Some([30.0, 55.0]);
            cfg.background_from_nearest_slot = from_nearest;
            cfg.slot_scale = slot_scale;
            check_frame_derivatives(&cfg);
        }
    }

    /// `slot_scale` changes the foreground slots' encodings (moments divided by it) and leaves
    /// the background's, whose frame is the world, at the scene's scale; set to `scene_scale`
    /// it is the model without it, to the bit.
    #[test]
    fn the_slots_line_scale_applies_to_the_slots_only() {
        let frames = [DMat4::from_translation(DVec3::new(-2.0, 1.5, 0.4))];
        let origins = [DVec3::new(8.0, -9.0, 7.0), DVec3::new(-10.0, 2.5, 6.0)];
        let dirs = [
            DVec3::new(-0.6, 0.8, -0.5).normalize(),
            DVec3::new(1.0, -0.1, -0.6).normalize(),
        ];
        let coords = |slot_scale: f64| {
            let cfg = Config {
                ray_fourier_freqs: 2,
                slot_scale,
                ..Config::small()
            };
            let rays = host_rays(&cfg, &frames, &origins, &dirs);
            let field = rays.coords.len() / 2;
            (rays.coords[..field].to_vec(), rays.coords[field..].to_vec())
        };
        let (bg, fg) = coords(0.0);
        let (bg_scaled, fg_scaled) = coords(1.5);
        assert_eq!(bg, bg_scaled);
        assert_ne!(fg, fg_scaled);
        let per_ray = fg.len() / 2;
        assert_eq!(coords(Config::small().scene_scale), (bg, fg));
        // The slot's encoding is the line's at that scale.
        let mut expected = vec![0f32; per_ray];
        let inv = frames[0].inverse();
        encode_line(&mut expected, &inv, (origins[0], dirs[0]), 1.5, 2, None);
        assert_eq!(&fg_scaled[..expected.len()], &expected[..]);
    }

    fn check_frame_derivatives(cfg: &Config) {
        let frames = [
            DMat4::from_rotation_translation(
                glam::DQuat::from_rotation_z(0.7),
                DVec3::new(0.5, -1.0, 0.3),
            ),
            DMat4::from_translation(DVec3::new(-2.0, 1.5, 0.4)),
        ];
        // The first ray passes nearest to the first frame, the second to the second.
        let origins = [DVec3::new(8.0, -9.0, 7.0), DVec3::new(-10.0, 2.5, 6.0)];
        let dirs = [DVec3::new(-0.6, 0.8, -0.5), DVec3::new(1.0, -0.1, -0.6)];
        let (s, r) = (3, 2);
        let scene_at = |f: &'_ [DMat4]| -> HostRays { host_rays(cfg, f, &origins, &dirs) };
        let at = scene_at(&frames);
        let absolute = |h: &HostRays| -> Vec<f64> {
            h.shift
                .chunks_exact(s)
                .zip(&h.base)
                .flat_map(|(row, b)| row.iter().map(move |v| *v as f64 + b))
                .collect()
        };
        let close = |fd: f64, a: f32| (fd - a as f64).abs() < 2e-3 * (1.0 + fd.abs());
        let per_field = r * cfg.ray_input_dim();
        for axis in 0..3 {
            let analytic = at
                .frame_derivatives(
                    cfg,
                    &[SceneRays {
                        slot_to_world: &frames,
                        origins: &origins,
                        dirs: &dirs,
                    }],
                    axis,
                )
                .unwrap();
            let follows = &analytic.background_follows;
            if cfg.background_from_nearest_slot {
                assert_eq!(follows, &[1, 2]);
            } else {
                assert_eq!(follows, &[0, 0]);
            }
            for moved_field in 1..s {
                let step = 1e-4;
                let mut moved = frames;
                moved[moved_field - 1].w_axis[axis] += step;
                let ahead = scene_at(&moved);
                // A value of field f moves with this frame when f is the moved field.
                let owned = |i: usize| i / per_field == moved_field;
                for (i, a) in analytic.coords.iter().enumerate() {
                    let fd = (ahead.coords[i] as f64 - at.coords[i] as f64) / step;
                    let a = if owned(i) { *a } else { 0.0 };
                    assert!(close(fd, a), "axis {axis}, coordinate {i}: {fd} vs {a}");
                }
                let (ahead_l, at_l) = (
                    &ahead.shadow_lines.as_ref().unwrap().0,
                    &at.shadow_lines.as_ref().unwrap().0,
                );
                for (i, a) in analytic.shadow_lines.as_ref().unwrap().iter().enumerate() {
                    let fd = (ahead_l[i] as f64 - at_l[i] as f64) / step;
                    let a = if owned(i) { *a } else { 0.0 };
                    assert!(close(fd, a), "axis {axis}, line value {i}: {fd} vs {a}");
                }
                let (sa, sb) = (absolute(&ahead), absolute(&at));
                for (i, a) in analytic.shift.iter().enumerate() {
                    let (ray, field) = (i / s, i % s);
                    let moves = field == moved_field
                        || (field == 0 && follows[ray] as usize == moved_field);
                    let a = if moves { *a } else { 0.0 };
                    let fd = (sa[i] - sb[i]) / step;
                    // Shifts are stored in f32 relative to the base: allow their rounding.
                    let rounding = 2.0 * f32::EPSILON as f64 * (1.0 + sb[i].abs()) / step;
                    assert!(
                        (fd - a as f64).abs() < 2e-3 * (1.0 + fd.abs()) + rounding,
                        "axis {axis}, shift {i}: {fd} vs {a}"
                    );
                }
            }
        }
    }

    /// On a long street the world origin lies far in front of the cars on a ray: measured from
    /// it the background's ordering is far ahead of every slot; from the nearest slot it is not.
    #[test]
    fn the_background_can_be_measured_from_the_nearest_slot() {
        let car = |x: f64| (DMat4::IDENTITY, DVec3::new(x, 0.0, 0.5));
        let frames = [(DMat4::IDENTITY, DVec3::ZERO), car(120.0), car(100.0)];
        // A camera at x = 90 looking down the street (+x).
        let (o, d) = (DVec3::new(90.0, 0.0, 1.0), DVec3::new(1.0, 0.0, -0.01));
        let mut cfg = Config::small();
        cfg.fg_locality = 2.0;
        let mut row = [0f32; 3];
        let base = ordering_shifts(&cfg, &frames, o, d, &mut row);
        // From the world origin: about −90, the smallest, so the background comes first.
        assert_eq!(row[0], 0.0);
        assert!(base < -89.0 && row[2] > 99.0, "{base} {row:?}");
        cfg.background_from_nearest_slot = true;
        let base = ordering_shifts(&cfg, &frames, o, d, &mut row);
        let nearest = (frames[2].1 - o).dot(d.normalize());
        // The nearest car's along (no locality term), against its own with the term.
        assert!(
            (base - nearest).abs() < 1e-12 && row[0] == 0.0,
            "{base} {row:?}"
        );
        assert!(row[2] > 0.0 && row[1] > row[2], "{row:?}");
        assert_eq!(background_anchor(&cfg, &frames, o, d.normalize()), Some(2));
        // Without slots the world origin it is.
        assert_eq!(
            background_anchor(&cfg, &frames[..1], o, d.normalize()),
            None
        );
    }

    /// A camera standing among the objects: a slot behind it would come first (the most
    /// negative shift) and anchor the background; culled, it goes far back and the nearest slot
    /// ahead anchors the background.
    #[test]
    fn slots_behind_the_camera_are_culled() {
        let car = |x: f64| (DMat4::IDENTITY, DVec3::new(x, 0.0, 0.5));
        let frames = [
            (DMat4::IDENTITY, DVec3::ZERO),
            car(80.0),
            car(100.0),
            car(89.0),
        ];
        let (o, d) = (DVec3::new(90.0, 0.0, 1.0), DVec3::new(1.0, 0.0, -0.01));
        let mut cfg = Config::small();
        cfg.background_from_nearest_slot = true;
        let mut row = [0f32; 4];
        ordering_shifts(&cfg, &frames, o, d, &mut row);
        // The car 10 units behind comes first and anchors the background.
        assert_eq!(background_anchor(&cfg, &frames, o, d.normalize()), Some(1));
        assert!(row[1] == 0.0 && row[2] > 19.0, "{row:?}");
        cfg.cull_behind = 2.0;
        let base = ordering_shifts(&cfg, &frames, o, d, &mut row);
        // Culled: pushed back; the car 1 unit behind (within the margin) is kept and now
        // anchors the background; the one ahead keeps its place.
        assert_eq!(background_anchor(&cfg, &frames, o, d.normalize()), Some(3));
        assert!(row[1] as f64 > 0.9 * BEHIND_PUSH, "{row:?}");
        let along = |x: f64| (DVec3::new(x, 0.0, 0.5) - o).dot(d.normalize());
        assert!((base - along(89.0)).abs() < 1e-9, "{base}");
        assert!(
            (row[2] as f64 - (along(100.0) - along(89.0))).abs() < 1e-4,
            "{row:?}"
        );
        // A camera outside the scene (every frame ahead) is unchanged by the option.
        let far = DVec3::new(-50.0, 0.0, 5.0);
        let (mut plain, mut culled) = ([0f32; 4], [0f32; 4]);
        cfg.cull_behind = 0.0;
        let b0 = ordering_shifts(&cfg, &frames, far, d, &mut plain);
        cfg.cull_behind = 2.0;
        let b1 = ordering_shifts(&cfg, &frames, far, d, &mut culled);
        assert_eq!((b0, plain), (b1, culled));
    }

    #[test]
    fn plucker_is_bounded_and_origin_invariant() {
        let id = DMat4::IDENTITY;
        let d = DVec3::new(0.3, -0.2, 1.0);
        let o = DVec3::new(1.0, 2.0, 3.0);
        let a = plucker_in_frame(&id, o, d, 8.0);
        let b = plucker_in_frame(&id, o + 5.0 * d, d, 8.0);
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() < 1e-12);
        }
        let far = plucker_in_frame(&id, DVec3::new(1e4, -3e4, 2e4), d, 8.0);
        let m = DVec3::new(far[3], far[4], far[5]).length();
        assert!(far.iter().all(|v| v.is_finite()) && m < 1.0);
    }

    /// With reaches, a foreground field's ray or shadow line beyond its reach keeps its Plücker
    /// coordinates (the reach is decided from them) and gets zero Fourier features; within it,
    /// and for the background, the encoding is [`encode_line`]'s.
    #[test]
    fn lines_beyond_a_reach_get_no_fourier_features() {
        let cfg = Config {
            ray_fourier_freqs: 3,
            slot_reach: 3.0,
            shadow_reach: 3.0,
            shadow_light: Some([30.0, 55.0]),
            ..Config::small()
        };
        let frames = [DMat4::from_translation(DVec3::new(1.0, -0.5, 0.5))];
        // A ray through the slot's frame origin, and one passing far from it.
        let eye = DVec3::new(9.0, -7.0, 6.0);
        let origins = [eye, eye];
        let dirs = [
            (DVec3::new(1.0, -0.5, 0.5) - eye).normalize(),
            (DVec3::new(-30.0, 40.0, 0.0) - eye).normalize(),
        ];
        let rays = host_rays(&cfg, &frames, &origins, &dirs);
        let in_dim = cfg.ray_input_dim();
        let inv = frames[0].inverse();
        let (lines, _) = rays.shadow_lines.as_ref().unwrap();
        let to_light = light_direction([30.0, 55.0]);
        let mut reached = [0usize; 2];
        for (encoded, bound, line_of) in [
            (&rays.coords, cfg.slot_reach_bound(), None),
            (lines, cfg.shadow_reach_bound(), Some(to_light)),
        ] {
            for ri in 0..2 {
                let (o, d) = match line_of {
                    None => (origins[ri], dirs[ri]),
                    Some(l) => {
                        shadow_line(origins[ri], dirs[ri], l).unwrap_or((origins[ri], dirs[ri]))
                    }
                };
                let mut full = vec![0f32; in_dim];
                encode_line(&mut full, &inv, (o, d), cfg.line_scale(1), 3, None);
                let slot = &encoded[(2 + ri) * in_dim..(3 + ri) * in_dim];
                assert_eq!(slot[..6], full[..6]);
                if within_reach(&full, bound) {
                    assert_eq!(slot, &full[..]);
                    reached[ri] += 1;
                } else {
                    assert!(slot[6..].iter().all(|&v| v == 0.0));
                }
                // The background has no reach.
                let mut bg = vec![0f32; in_dim];
                encode_line(
                    &mut bg,
                    &DMat4::IDENTITY,
                    (o, d),
                    cfg.line_scale(0),
                    3,
                    None,
                );
                assert_eq!(&encoded[ri * in_dim..(ri + 1) * in_dim], &bg[..]);
            }
        }
        // The near ray is within both reaches, the far one within neither.
        assert_eq!(reached, [2, 0]);
    }

    #[test]
    fn fourier_features_match_direct_sin_cos() {
        let mut cfg = Config::small();
        cfg.ray_fourier_freqs = 10;
        let frames = [DMat4::from_translation(DVec3::new(0.3, -0.2, 0.1))];
        let origins = [DVec3::new(3.0, -9.0, 7.0), DVec3::new(-12.0, 0.5, 2.0)];
        let dirs = [DVec3::new(-0.2, 1.0, -0.5), DVec3::new(1.0, 0.1, -0.3)];
        let scene = SceneRays {
            slot_to_world: &frames,
            origins: &origins,
            dirs: &dirs,
        };
        let batch = RayBatch::new(&cfg, &[scene], &Device::Cpu).unwrap();
        let coords = batch
            .coords
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let in_dim = cfg.ray_input_dim();
        for (i, row) in coords.chunks_exact(in_dim).enumerate() {
            for c in 0..6 {
                let v = row[c] as f64;
                for f in 0..10 {
                    let arg = (1u64 << f) as f64 * std::f64::consts::PI * v;
                    // row[c] is v rounded to f32: allow for the rounding times 2^f·π.
                    let tol = 1e-5 + (1u64 << f) as f64 * std::f64::consts::PI * 6e-8;
                    assert!(
                        (row[6 + 12 * f + c] as f64 - arg.sin()).abs() < tol,
                        "ray {i}"
                    );
                    assert!(
                        (row[12 + 12 * f + c] as f64 - arg.cos()).abs() < tol,
                        "ray {i}"
                    );
                }
            }
        }
    }

    /// The background's floor columns at a hand-computed floor hit are the flag, the bounded
    /// (x, y)/s and direct sin/cos of 2^k·π·x and 2^k·π·y; zero on rays that look up, run
    /// level or start below the floor, in the slots' rows and in every shadow line; the line
    /// columns before them are those of the model without floor features.
    #[test]
    fn floor_features_match_direct_sin_cos_at_the_floor_hit() {
        const L: usize = 5;
        let cfg = Config {
            ray_fourier_freqs: 2,
            floor_fourier_freqs: L,
            shadow_head: true,
            shadow_light: Some([30.0, 55.0]),
            ..Config::small()
        };
        let frames = [DMat4::from_translation(DVec3::new(0.3, -0.2, 0.5))];
        let origins = [
            DVec3::new(1.0, 2.0, 6.0),   // meets the floor at (2.5, 2, 0)
            DVec3::new(-3.0, 0.25, 4.0), // meets the floor at (1, −1.75, 0)
            DVec3::new(0.0, 0.0, 5.0),   // looks up
            DVec3::new(0.0, 0.0, 5.0),   // runs level
            DVec3::new(0.5, 0.5, -1.0),  // starts below the floor, looks down
        ];
        let dirs = [
            DVec3::new(0.5, 0.0, -2.0),
            DVec3::new(1.0, -0.5, -1.0),
            DVec3::new(1.0, 0.0, 0.2),
            DVec3::X,
            DVec3::NEG_Z,
        ];
        let hits = [Some((2.5, 2.0)), Some((1.0, -1.75)), None, None, None];
        let rays = host_rays(&cfg, &frames, &origins, &dirs);
        let (in_dim, line_dim) = (cfg.ray_input_dim(), cfg.line_input_dim());
        assert_eq!(in_dim - line_dim, 3 + 4 * L);
        let r = origins.len();
        let row = |buf: &[f32], field: usize, ri: usize| -> Vec<f32> {
            buf[(field * r + ri) * in_dim..(field * r + ri + 1) * in_dim].to_vec()
        };
        for (ri, hit) in hits.iter().enumerate() {
            let floor = row(&rays.coords, 0, ri)[line_dim..].to_vec();
            match hit {
                Some((x, y)) => {
                    let s = cfg.scene_scale;
                    let n = (1.0 + (x / s).powi(2) + (y / s).powi(2)).sqrt();
                    let mut expected = vec![1.0, x / s / n, y / s / n];
                    for k in 0..L {
                        let w = (1u64 << k) as f64 * std::f64::consts::PI;
                        let (sx, cx) = (w * x).sin_cos();
                        let (sy, cy) = (w * y).sin_cos();
                        expected.extend([sx, cx, sy, cy]);
                    }
                    for (c, (got, want)) in floor.iter().zip(&expected).enumerate() {
                        assert!(
                            (*got as f64 - want).abs() < 1e-6,
                            "ray {ri}, column {c}: {got} vs {want}"
                        );
                    }
                }
                None => assert!(floor.iter().all(|v| *v == 0.0), "ray {ri}: {floor:?}"),
            }
            // The slot's floor columns are zero; so are every shadow line's.
            assert!(row(&rays.coords, 1, ri)[line_dim..]
                .iter()
                .all(|v| *v == 0.0));
            let (lines, _) = rays.shadow_lines.as_ref().unwrap();
            for field in 0..2 {
                assert!(row(lines, field, ri)[line_dim..].iter().all(|v| *v == 0.0));
            }
        }
        // The line columns are the model's without floor features, to the bit.
        let plain = Config {
            floor_fourier_freqs: 0,
            ..cfg.clone()
        };
        let without = host_rays(&plain, &frames, &origins, &dirs);
        for field in 0..2 {
            for ri in 0..r {
                let at = (field * r + ri) * line_dim;
                assert_eq!(
                    &row(&rays.coords, field, ri)[..line_dim],
                    &without.coords[at..at + line_dim]
                );
            }
        }
        assert_eq!(rays.shift, without.shift);
        // A reused buffer: every column is written, a miss included.
        let mut out = vec![f32::NAN; 3 + 4 * L];
        encode_floor(&mut out, Some((origins[2], dirs[2])), 8.0, L);
        assert!(out.iter().all(|v| *v == 0.0));
        out.fill(f32::NAN);
        encode_floor(&mut out, None, 8.0, L);
        assert!(out.iter().all(|v| *v == 0.0));
        // The hit point itself.
        let hit = ground_point(origins[1], dirs[1]).unwrap();
        assert!(hit.abs_diff_eq(DVec3::new(1.0, -1.75, 0.0), 1e-12));
    }

    #[test]
    fn shadow_lines_start_on_the_ground_and_point_at_the_light() {
        let to_light = light_direction([30.0, 55.0]);
        assert!((to_light.length() - 1.0).abs() < 1e-12);
        assert!((to_light.z - 55f64.to_radians().sin()).abs() < 1e-12);
        assert!((to_light.y / to_light.x - 30f64.to_radians().tan()).abs() < 1e-12);
        let (ground, dir) = shadow_line(
            DVec3::new(1.0, 2.0, 6.0),
            DVec3::new(0.5, 0.0, -2.0),
            to_light,
        )
        .unwrap();
        assert!(ground.abs_diff_eq(DVec3::new(2.5, 2.0, 0.0), 1e-12));
        assert_eq!(dir, -to_light);
        // Rays that look up, run level, or start below the ground meet no ground ahead.
        for (o, d) in [
            (DVec3::new(0.0, 0.0, 5.0), DVec3::new(1.0, 0.0, 0.2)),
            (DVec3::new(0.0, 0.0, 5.0), DVec3::X),
            (DVec3::new(0.0, 0.0, -1.0), DVec3::NEG_Z),
        ] {
            assert!(shadow_line(o, d, to_light).is_none());
        }
        // In a batch: the shadow lines' coordinates and the ground mask.
        let mut cfg = Config::small();
        cfg.shadow_head = true;
        cfg.shadow_light = Some([30.0, 55.0]);
        let frames = [DMat4::from_translation(DVec3::new(0.3, -0.2, 0.5))];
        let origins = [DVec3::new(1.0, 2.0, 6.0), DVec3::new(0.0, 0.0, 5.0)];
        let dirs = [DVec3::new(0.5, 0.0, -2.0), DVec3::new(1.0, 0.0, 0.2)];
        let scene = SceneRays {
            slot_to_world: &frames,
            origins: &origins,
            dirs: &dirs,
        };
        let batch = RayBatch::new(&cfg, &[scene], &Device::Cpu).unwrap();
        let (lines, on_ground) = batch.shadow_lines.unwrap();
        let on_ground = on_ground.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(on_ground, vec![1.0, 0.0]);
        let lines = lines.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let in_dim = cfg.ray_input_dim();
        // Field 1 (the slot), ray 0: the line from the light to (2.5, 2, 0) in its frame.
        let mut expected = vec![0f32; in_dim];
        encode_line(
            &mut expected,
            &frames[0].inverse(),
            (DVec3::new(2.5, 2.0, 0.0), -to_light),
            cfg.scene_scale,
            cfg.ray_fourier_freqs,
            None,
        );
        let got = &lines[2 * in_dim..3 * in_dim];
        assert!(got.iter().zip(&expected).all(|(a, b)| (a - b).abs() < 1e-6));
    }

    #[test]
    fn locality_pushes_slots_back_by_squared_distance_over_radius() {
        let mut cfg = Config::small();
        cfg.fg_locality = 2.0;
        // Slot 0 on the ray, slot 1 three units to its side, both 5 units along it.
        let frames = [
            DMat4::from_translation(DVec3::new(0.0, 0.0, 5.0)),
            DMat4::from_translation(DVec3::new(3.0, 0.0, 5.0)),
        ];
        let origins = [DVec3::ZERO];
        let dirs = [DVec3::Z];
        let scene = SceneRays {
            slot_to_world: &frames,
            origins: &origins,
            dirs: &dirs,
        };
        let batch = RayBatch::new(&cfg, &[scene], &Device::Cpu).unwrap();
        let shift = batch.shift.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        // Background (world origin) at 0, slot 0 at 5, slot 1 at 5 + 3²/2.
        assert_eq!(batch.base, vec![0.0]);
        assert_eq!(shift, vec![0.0, 5.0, 9.5]);
    }

    #[test]
    fn shifts_measure_frame_origins_along_the_ray() {
        let cfg = Config::small();
        let frames = [
            DMat4::from_translation(DVec3::new(0.0, 0.0, -2.0)),
            DMat4::from_translation(DVec3::new(0.0, 0.0, -7.0)),
        ];
        let origins = [DVec3::new(0.0, 0.0, 10.0)];
        let dirs = [DVec3::new(0.0, 0.0, -2.0)];
        let batch = RayBatch::new(
            &cfg,
            &[SceneRays {
                slot_to_world: &frames,
                origins: &origins,
                dirs: &dirs,
            }],
            &Device::Cpu,
        )
        .unwrap();
        let shift = batch.shift.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        // Background (world origin) at 10, slots at 12 and 17 from the ray origin.
        assert_eq!(batch.base, vec![10.0]);
        assert_eq!(shift, vec![0.0, 2.0, 7.0]);
    }
}
