//! The analytic ray tracer: primary rays against the scene's solids and the ground, one
//! shadow ray toward the directional light, a fixed stratified sample pattern per pixel for the
//! colour, and the exact mask from the pixel-centre ray.

use super::geometry::{ground_hit, Solid};
use super::hash::mix64;
use super::look::Look;
use super::scene::Scene;
use super::shading::{lambert, linear_to_srgb, linear_to_srgb8, sky, Ground};
use crate::camera::Frame;
use anyhow::Result;
use glam::DVec3;
use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

/// Colour samples per pixel: an odd `AA_GRID`×`AA_GRID` grid of cell centres, so the middle
/// sample is the pixel centre and the mask (taken from the centre ray) agrees with the colour.
pub const AA_GRID: usize = 3;

/// One solid with its owner (0 = background, k = object k, 1-based) and linear albedo.
#[derive(Clone, Copy, Debug)]
struct Part {
    solid: Solid,
    albedo: DVec3,
    owner: u8,
}

/// What a ray sees first.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceHit {
    pub t: f64,
    pub normal: DVec3,
    pub albedo: DVec3,
    /// 0 = background (ground, buildings), k = object k.
    pub owner: u8,
}

/// A scene ready for tracing.
pub struct Tracer {
    parts: Vec<Part>,
    ground: Ground,
    sky: bool,
    to_light: DVec3,
    look: Look,
}

/// A rendered view: 8-bit sRGB RGB, row-major, and the mask.
pub struct RenderedView {
    pub rgb: Vec<u8>,
    pub mask: Vec<u8>,
}

impl Tracer {
    /// The tracer of `scene`, with object `moved.0` (1-based) displaced by `moved.1` if given.
    pub fn new(scene: &Scene, moved: Option<(usize, DVec3)>) -> Result<Tracer> {
        anyhow::ensure!(
            scene.objects.len() <= 255,
            "{} objects do not fit 8-bit mask ids",
            scene.objects.len()
        );
        let mut parts = Vec::new();
        for (i, object) in scene.objects.iter().enumerate() {
            let owner = (i + 1) as u8;
            let delta = match moved {
                Some((k, d)) if k == i + 1 => d,
                _ => DVec3::ZERO,
            };
            for (solid, albedo) in object.parts()? {
                parts.push(Part {
                    solid: solid.translated(delta),
                    albedo,
                    owner,
                });
            }
        }
        let walls = scene.room.as_ref().map(|r| r.walls()).unwrap_or_default();
        for b in scene.buildings.iter().chain(&walls) {
            parts.push(Part {
                solid: b.solid(),
                albedo: DVec3::from_array(b.albedo),
                owner: 0,
            });
        }
        Ok(Tracer {
            parts,
            ground: scene.ground.clone(),
            sky: scene.sky,
            to_light: DVec3::from_array(scene.light.direction).normalize(),
            look: Look::default(),
        })
    }

    /// The tracer with `look` instead of the reference look.
    pub fn with_look(mut self, look: Look) -> Tracer {
        self.look = look;
        self
    }

    /// The direction toward the light of colour sample `k` of `n`: the light's direction
    /// itself for hard shadows, else point k of a fixed golden-angle spiral on the light's
    /// disc.
    fn light_sample(&self, k: usize, n: usize) -> DVec3 {
        let radius = self.look.softness_degrees.to_radians();
        if radius == 0.0 {
            return self.to_light;
        }
        let l = self.to_light;
        let a = if l.z.abs() < 0.9 { DVec3::Z } else { DVec3::X };
        let u = l.cross(a).normalize();
        let v = l.cross(u);
        let r = radius * ((k as f64 + 0.5) / n as f64).sqrt();
        let phi = k as f64 * 2.399_963_229_728_653;
        (l + r * (phi.cos() * u + phi.sin() * v)).normalize()
    }

    /// The first surface along the ray (unit `dir`), if any.
    pub fn first_hit(&self, origin: DVec3, dir: DVec3) -> Option<SurfaceHit> {
        let mut best: Option<SurfaceHit> = ground_hit(origin, dir).map(|t| {
            let p = origin + t * dir;
            SurfaceHit {
                t,
                normal: DVec3::Z,
                albedo: self.ground.albedo(p.x, p.y),
                owner: 0,
            }
        });
        for part in &self.parts {
            let t_max = best.map_or(f64::INFINITY, |b| b.t);
            if let Some(hit) = part.solid.intersect(origin, dir, t_max) {
                best = Some(SurfaceHit {
                    t: hit.t,
                    normal: hit.normal,
                    albedo: part.albedo,
                    owner: part.owner,
                });
            }
        }
        best
    }

    /// Whether anything blocks the light from point `p` (the ground never does: the light is
    /// above the horizon).
    fn in_shadow(&self, p: DVec3, to_light: DVec3) -> bool {
        self.parts
            .iter()
            .any(|part| part.solid.intersect(p, to_light, f64::INFINITY).is_some())
    }

    /// Linear radiance and mask id seen along the ray.
    pub fn trace(&self, origin: DVec3, dir: DVec3) -> (DVec3, u8) {
        self.trace_lit(origin, dir, self.to_light)
    }

    /// [`Tracer::trace`] with the light in direction `to_light`.
    fn trace_lit(&self, origin: DVec3, dir: DVec3, to_light: DVec3) -> (DVec3, u8) {
        match self.first_hit(origin, dir) {
            Some(hit) => {
                // Offset along the normal, scaled with the distance, so the shadow ray starts
                // clear of the surface it leaves.
                let p = origin + hit.t * dir + hit.normal * (1e-9 * (1.0 + hit.t));
                let facing = hit.normal.dot(to_light) > 0.0;
                let lit = facing && !self.in_shadow(p, to_light);
                let radiance = if self.look == Look::default() {
                    lambert(hit.albedo, hit.normal, to_light, lit)
                } else {
                    let direct = if lit {
                        hit.normal.dot(to_light).max(0.0)
                    } else {
                        0.0
                    };
                    hit.albedo
                        * (self.look.ambient + self.look.diffuse * direct)
                        * self.look.exposure
                };
                (radiance, hit.owner)
            }
            None if self.sky => (sky(dir), 0),
            None => (DVec3::ZERO, 0),
        }
    }

    /// The mask id of the pixel-centre ray of every pixel, row-major.
    pub fn render_mask(&self, frame: &Frame) -> Vec<u8> {
        frame
            .rays()
            .iter()
            .map(|r| self.first_hit(r.origin, r.direction).map_or(0, |h| h.owner))
            .collect()
    }

    /// Renders one view: colour as the mean linear radiance of the AA_GRID² stratified
    /// samples, written as 8-bit sRGB; mask from the centre sample.
    pub fn render(&self, frame: &Frame) -> RenderedView {
        self.render_view(frame, 0)
    }

    /// [`Tracer::render`] of view number `view` (which seeds the look's sensor noise).
    pub fn render_view(&self, frame: &Frame, view: u64) -> RenderedView {
        let sigma = self.look.noise_sigma;
        let mut noise = (sigma > 0.0).then(|| {
            (
                StdRng::seed_from_u64(mix64(self.look.noise_seed ^ view)),
                Normal::new(0.0, sigma).expect("sigma is finite and positive"),
            )
        });
        let (w, h) = (frame.intrinsics.w as usize, frame.intrinsics.h as usize);
        let mut rgb = Vec::with_capacity(3 * w * h);
        let mut mask = Vec::with_capacity(w * h);
        let n = AA_GRID;
        let centre = n / 2;
        for j in 0..h {
            for i in 0..w {
                let mut sum = DVec3::ZERO;
                let mut centre_id = 0;
                for sy in 0..n {
                    for sx in 0..n {
                        let u = i as f64 + (sx as f64 + 0.5) / n as f64;
                        let v = j as f64 + (sy as f64 + 0.5) / n as f64;
                        let ray = frame.ray_at(u, v);
                        let to_light = self.light_sample(sy * n + sx, n * n);
                        let (radiance, id) = self.trace_lit(ray.origin, ray.direction, to_light);
                        sum += radiance;
                        if sx == centre && sy == centre {
                            centre_id = id;
                        }
                    }
                }
                let mean = sum / (n * n) as f64;
                match &mut noise {
                    None => rgb.extend([mean.x, mean.y, mean.z].map(linear_to_srgb8)),
                    Some((rng, normal)) => {
                        for c in [mean.x, mean.y, mean.z] {
                            let value = linear_to_srgb(c) + normal.sample(rng);
                            rgb.push((value.clamp(0.0, 1.0) * 255.0).round() as u8);
                        }
                    }
                }
                mask.push(centre_id);
            }
        }
        RenderedView { rgb, mask }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{look_at, Intrinsics};
    use crate::synth::scene::{Light, Object};

    fn one_sphere_scene() -> Scene {
        Scene {
            objects: vec![Object::clevr("sphere", 1, 1, 0.0, 0.0, 0.0)],
            buildings: Vec::new(),
            ground: Ground::Uniform { albedo: 0.5 },
            sky: false,
            light: Light::new(0.0, 90.0),
            cameras: Vec::new(),
            rows: Vec::new(),
            room: None,
        }
    }

    fn top_down(size: u32) -> Frame {
        Frame {
            file_path: None,
            intrinsics: Intrinsics::from_fov(size, size, 40.0),
            camera_to_world: look_at(DVec3::new(0.0, 0.0, 10.0), DVec3::ZERO, DVec3::Y).unwrap(),
        }
    }

    #[test]
    fn mask_and_shading_of_a_sphere_under_an_overhead_light() {
        let tracer = Tracer::new(&one_sphere_scene(), None).unwrap();
        let frame = top_down(33);
        let view = tracer.render(&frame);
        let at = |i: usize, j: usize| (view.mask[j * 33 + i], &view.rgb[3 * (j * 33 + i)..][..3]);
        // Centre pixel: the sphere's top, facing the light: albedo × (0.35 + 0.65) = CLEVR red
        // (the off-centre samples see the normal tilted by a few degrees: within one level).
        let (id, rgb) = at(16, 16);
        assert_eq!(id, 1);
        for (got, want) in rgb.iter().zip([173u8, 35, 35]) {
            assert!(got.abs_diff(want) <= 1, "{rgb:?}");
        }
        // Corner: lit ground, linear 0.5 → sRGB 188.
        let (id, rgb) = at(0, 0);
        assert_eq!(id, 0);
        assert_eq!(rgb, [188, 188, 188]);
        // The sphere's own shadow lies straight below it, hidden: the mask area matches the
        // projected disc (radius 0.7 at distance ~9.3 with the 40° lens).
        let pixels = view.mask.iter().filter(|&&m| m == 1).count() as f64;
        let fl = 0.5 * 33.0 / 20f64.to_radians().tan();
        let expected = std::f64::consts::PI * (fl * 0.7 / (10.0 - 0.7)).powi(2);
        assert!(
            (pixels - expected).abs() < 0.2 * expected,
            "{pixels} vs {expected}"
        );
        assert_eq!(tracer.render_mask(&frame), view.mask);
    }

    #[test]
    fn shadows_are_ambient_only() {
        // A light low in +X: the ground just behind the sphere (−X side) is in shadow.
        let mut scene = one_sphere_scene();
        scene.light = Light::new(0.0, 30.0);
        let tracer = Tracer::new(&scene, None).unwrap();
        let down = -DVec3::Z;
        let (shadowed, id) = tracer.trace(DVec3::new(-1.5, 0.0, 5.0), down);
        assert_eq!(id, 0);
        assert!((shadowed - DVec3::splat(0.5 * 0.35)).length() < 1e-12);
        let (lit, _) = tracer.trace(DVec3::new(1.5, 0.0, 5.0), down);
        let expected = 0.5 * (0.35 + 0.65 * 30f64.to_radians().sin());
        assert!((lit - DVec3::splat(expected)).length() < 1e-12);
    }

    #[test]
    fn moving_an_object_moves_its_mask() {
        let scene = one_sphere_scene();
        let frame = top_down(33);
        let before = Tracer::new(&scene, None).unwrap().render_mask(&frame);
        let after = Tracer::new(&scene, Some((1, DVec3::new(2.0, 0.0, 0.0))))
            .unwrap()
            .render_mask(&frame);
        let centroid = |m: &[u8]| {
            let (sum, n) = m
                .iter()
                .enumerate()
                .filter(|(_, &v)| v == 1)
                .fold((0.0, 0.0), |(s, n), (k, _)| (s + (k % 33) as f64, n + 1.0));
            sum / n
        };
        // Camera +X is world +X with up = +Y: moving +X moves the mask to larger columns.
        assert!(centroid(&after) > centroid(&before) + 3.0);
    }

    #[test]
    fn the_look_changes_colour_but_not_the_mask() {
        let scene = one_sphere_scene();
        let frame = top_down(33);
        let reference = Tracer::new(&scene, None).unwrap().render(&frame);
        let look = Look {
            exposure: 1.5,
            noise_sigma: 0.01,
            noise_seed: 7,
            softness_degrees: 6.0,
            ..Look::default()
        };
        let tracer = Tracer::new(&scene, None).unwrap().with_look(look);
        let a = tracer.render_view(&frame, 0);
        assert_eq!(a.mask, reference.mask);
        assert_eq!(a.rgb, tracer.render_view(&frame, 0).rgb, "seeded");
        assert_ne!(
            a.rgb,
            tracer.render_view(&frame, 1).rgb,
            "each view has its own noise"
        );
        // Brighter on average (exposure 1.5), and noisy: flat ground is no longer one value.
        let mean = |v: &[u8]| v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
        assert!(mean(&a.rgb) > mean(&reference.rgb) + 10.0);
        let ground: Vec<u8> = (0..5).map(|i| a.rgb[3 * i]).collect();
        assert!(ground.iter().any(|&g| g != ground[0]), "{ground:?}");
    }

    #[test]
    fn a_soft_light_gives_a_penumbra() {
        // Light low in +X: along the line y = 0 behind the sphere (−X), hard shadows jump from
        // shadowed to lit; a light of radius 8° gives intermediate values in between.
        let mut scene = one_sphere_scene();
        scene.light = Light::new(0.0, 30.0);
        let hard = Tracer::new(&scene, None).unwrap();
        let soft = Tracer::new(&scene, None).unwrap().with_look(Look {
            softness_degrees: 8.0,
            ..Look::default()
        });
        let lit_share = |t: &Tracer, x: f64| {
            let p = DVec3::new(x, 0.0, 1e-9);
            (0..9)
                .filter(|&k| !t.in_shadow(p, t.light_sample(k, 9)))
                .count()
        };
        let xs: Vec<f64> = (0..200).map(|i| -4.0 + 0.02 * i as f64).collect();
        assert!(xs.iter().all(|&x| [0, 9].contains(&lit_share(&hard, x))));
        assert!(xs.iter().any(|&x| (1..9).contains(&lit_share(&soft, x))));
    }
}
