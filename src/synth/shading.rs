//! Colour and shading: sRGB ↔ linear, the Lambertian model of the clevr567 contract, the
//! procedural ground materials (uniform, textured checker/noise floor, city street, room
//! floors) and the sky.

use glam::DVec3;
use serde::Serialize;

/// Ambient share of the contract's shading: linear = albedo × (AMBIENT + DIFFUSE·max(0, n·l)·lit).
pub const AMBIENT: f64 = 0.35;
/// Direct share of the shading.
pub const DIFFUSE: f64 = 0.65;

/// sRGB-encoded value in [0, 1] → linear.
pub fn srgb_to_linear(c: f64) -> f64 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear value → sRGB-encoded value in [0, 1] (clamped).
pub fn linear_to_srgb(c: f64) -> f64 {
    let c = c.clamp(0.0, 1.0);
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

/// Linear value → 8-bit sRGB.
pub fn linear_to_srgb8(c: f64) -> u8 {
    (linear_to_srgb(c) * 255.0).round() as u8
}

/// Linear albedo of an 8-bit sRGB colour.
pub fn albedo_of_srgb8(rgb: [u8; 3]) -> DVec3 {
    DVec3::new(
        srgb_to_linear(rgb[0] as f64 / 255.0),
        srgb_to_linear(rgb[1] as f64 / 255.0),
        srgb_to_linear(rgb[2] as f64 / 255.0),
    )
}

/// Linear radiance of a Lambertian surface under the contract's light model.
pub fn lambert(albedo: DVec3, normal: DVec3, to_light: DVec3, lit: bool) -> DVec3 {
    let direct = if lit {
        normal.dot(to_light).max(0.0)
    } else {
        0.0
    };
    albedo * (AMBIENT + DIFFUSE * direct)
}

/// The material of the ground plane z = 0 (which is always background, mask id 0).
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Ground {
    /// One linear albedo everywhere (clevr567: 0.5).
    Uniform { albedo: f64 },
    /// A rotated checkerboard of two linear albedos, modulated by smooth value noise.
    Checker {
        square: f64,
        rotation_degrees: f64,
        albedo_a: [f64; 3],
        albedo_b: [f64; 3],
        noise_scale: f64,
        noise_amplitude: f64,
        noise_seed: u64,
    },
    /// A street along +X: asphalt for |y| < `road_half_width` with a dashed centre line and
    /// solid edge lines, pavement up to `pavement_edge`, then dark ground.
    Street {
        road_half_width: f64,
        pavement_edge: f64,
    },
    /// A room's procedural floor (presets room-chair, room-diverse).
    Floor(super::room::FloorTexture),
}

impl Ground {
    /// Linear albedo at ground point (x, y).
    pub fn albedo(&self, x: f64, y: f64) -> DVec3 {
        match self {
            Ground::Uniform { albedo } => DVec3::splat(*albedo),
            Ground::Checker {
                square,
                rotation_degrees,
                albedo_a,
                albedo_b,
                noise_scale,
                noise_amplitude,
                noise_seed,
            } => {
                let (s, c) = rotation_degrees.to_radians().sin_cos();
                let (u, v) = (c * x + s * y, -s * x + c * y);
                let parity = ((u / square).floor() as i64 + (v / square).floor() as i64) & 1;
                let base = if parity == 0 { albedo_a } else { albedo_b };
                let n = 0.65 * value_noise(x / noise_scale, y / noise_scale, *noise_seed)
                    + 0.35
                        * value_noise(
                            2.1 * x / noise_scale,
                            2.1 * y / noise_scale,
                            noise_seed ^ 0x9e37,
                        );
                let gain = 1.0 + noise_amplitude * (2.0 * n - 1.0);
                DVec3::from_array(*base) * gain
            }
            Ground::Street {
                road_half_width,
                pavement_edge,
            } => {
                let ay = y.abs();
                let line = 0.09;
                if ay < line && x.rem_euclid(6.0) < 3.0 {
                    DVec3::splat(0.75)
                } else if (ay - (road_half_width - 0.25)).abs() < line {
                    DVec3::splat(0.7)
                } else if ay < *road_half_width {
                    DVec3::splat(0.09)
                } else if ay < *pavement_edge {
                    // Paving slabs: faint joints every 1.5 units.
                    let joint = x.rem_euclid(1.5) < 0.05 || (ay - road_half_width) % 1.5 < 0.05;
                    DVec3::splat(if joint { 0.3 } else { 0.42 })
                } else {
                    DVec3::splat(0.25)
                }
            }
            Ground::Floor(texture) => texture.albedo(x, y),
        }
    }
}

/// Linear radiance of the sky seen along `dir` (only visible in presets whose cameras see the
/// horizon): a gradient from a pale horizon to a deeper blue overhead.
pub fn sky(dir: DVec3) -> DVec3 {
    let up = dir.z.clamp(0.0, 1.0);
    DVec3::new(0.62, 0.74, 0.9).lerp(DVec3::new(0.25, 0.42, 0.8), up.sqrt())
}

/// Smooth value noise in [0, 1] on the integer lattice, hashed from `seed`.
pub fn value_noise(x: f64, y: f64, seed: u64) -> f64 {
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let (ix, iy) = (x0 as i64, y0 as i64);
    let corner = |dx: i64, dy: i64| lattice(ix + dx, iy + dy, seed);
    let top = corner(0, 0) + sx * (corner(1, 0) - corner(0, 0));
    let bottom = corner(0, 1) + sx * (corner(1, 1) - corner(0, 1));
    top + sy * (bottom - top)
}

fn lattice(x: i64, y: i64, seed: u64) -> f64 {
    let h = super::hash::mix64(seed ^ super::hash::mix64((x as u64) ^ (y as u64).rotate_left(32)));
    (h >> 11) as f64 / (1u64 << 53) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_round_trips_every_byte() {
        for b in 0..=255u8 {
            let lin = srgb_to_linear(b as f64 / 255.0);
            assert_eq!(linear_to_srgb8(lin), b);
        }
        // The contract's ground: linear 0.5 is sRGB ≈ 188.
        assert_eq!(linear_to_srgb8(0.5), 188);
    }

    #[test]
    fn lambert_follows_the_contract() {
        let a = DVec3::splat(0.5);
        let n = DVec3::Z;
        assert_eq!(lambert(a, n, DVec3::Z, true), DVec3::splat(0.5));
        assert_eq!(lambert(a, n, DVec3::Z, false), DVec3::splat(0.5 * 0.35));
        assert_eq!(lambert(a, n, -DVec3::Z, true), DVec3::splat(0.5 * 0.35));
    }

    #[test]
    fn noise_is_bounded_continuous_and_seeded() {
        let mut prev = value_noise(0.0, 0.3, 7);
        for k in 1..1000 {
            let x = k as f64 * 0.01;
            let v = value_noise(x, 0.3, 7);
            assert!((0.0..=1.0).contains(&v));
            assert!((v - prev).abs() < 0.05, "jump at {x}");
            prev = v;
        }
        assert_ne!(value_noise(0.5, 0.5, 1), value_noise(0.5, 0.5, 2));
    }
}
