//! The randomised look (`SynthOptions::randomize_look`): per scene a floor albedo, a light
//! direction, intensity and softness, an exposure and a sensor noise level, so that a model
//! trained on the scenes does not depend on one exact appearance. The draws come from their
//! own stream (derived from the scene seed), so the objects and cameras of a scene are the
//! same with or without it; without it every scene has [`Look::default`], the reference
//! appearance.

use super::hash::mix64;
use super::scene::Light;
use super::shading::{AMBIENT, DIFFUSE};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::Serialize;

/// How a scene is lit and exposed by the analytic tracer.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Look {
    /// Ambient share: linear = albedo × (ambient + diffuse · max(0, n·l) · lit) × exposure.
    pub ambient: f64,
    /// Direct share (the light's intensity).
    pub diffuse: f64,
    /// Angular radius of the light, degrees (0: hard shadows); shadow rays of a pixel's 3×3
    /// samples go to 9 fixed points of the disc, so shadows get a penumbra.
    pub softness_degrees: f64,
    /// Linear multiplier of the radiance.
    pub exposure: f64,
    /// Standard deviation of Gaussian noise added to each 8-bit sRGB channel value in [0, 1]
    /// before quantisation (0: none).
    pub noise_sigma: f64,
    /// Seed of the noise (view v uses `mix64(noise_seed ^ v)`).
    pub noise_seed: u64,
}

impl Default for Look {
    /// The reference look: hard shadows, no exposure change, no noise.
    fn default() -> Look {
        Look {
            ambient: AMBIENT,
            diffuse: DIFFUSE,
            softness_degrees: 0.0,
            exposure: 1.0,
            noise_sigma: 0.0,
            noise_seed: 0,
        }
    }
}

/// Ranges of the randomised look.
pub const FLOOR_ALBEDO: (f64, f64) = (0.25, 0.75);
pub const LIGHT_ELEVATION: (f64, f64) = (30.0, 75.0);
pub const AMBIENT_RANGE: (f64, f64) = (0.2, 0.5);
pub const DIFFUSE_RANGE: (f64, f64) = (0.45, 0.85);
pub const SOFTNESS_DEGREES: (f64, f64) = (0.0, 8.0);
/// Exposure is 2^U(−EV, EV).
pub const EXPOSURE_EV: f64 = 0.5;
pub const NOISE_SIGMA: (f64, f64) = (0.0, 0.02);

/// A randomised look for the scene with seed `scene_seed`: the look, a light (azimuth
/// uniform in [0°, 360°), elevation in LIGHT_ELEVATION) and a floor albedo (used where the
/// floor is uniform).
pub fn sample_look(scene_seed: u64) -> (Look, Light, f64) {
    let mut rng = StdRng::seed_from_u64(mix64(scene_seed ^ 0x4c4f_4f4b_0000_0003));
    let mut uniform = |(lo, hi): (f64, f64)| rng.random_range(lo..=hi);
    let floor = uniform(FLOOR_ALBEDO);
    let light = Light::new(uniform((0.0, 360.0)), uniform(LIGHT_ELEVATION));
    let look = Look {
        ambient: uniform(AMBIENT_RANGE),
        diffuse: uniform(DIFFUSE_RANGE),
        softness_degrees: uniform(SOFTNESS_DEGREES),
        exposure: 2f64.powf(uniform((-EXPOSURE_EV, EXPOSURE_EV))),
        noise_sigma: uniform(NOISE_SIGMA),
        noise_seed: mix64(scene_seed ^ 0x4e4f_4953_4500_0004),
    };
    (look, light, floor)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn looks_are_seeded_and_in_range() {
        assert_eq!(sample_look(5), sample_look(5));
        let mut floors = Vec::new();
        for seed in 0..200 {
            let (look, light, floor) = sample_look(seed);
            assert!((0.25..=0.75).contains(&floor));
            assert!((30.0..=75.0).contains(&light.elevation_degrees));
            assert!((0.2..=0.5).contains(&look.ambient));
            assert!((0.45..=0.85).contains(&look.diffuse));
            assert!((0.0..=8.0).contains(&look.softness_degrees));
            assert!((2f64.powf(-0.5)..=2f64.powf(0.5)).contains(&look.exposure));
            assert!((0.0..=0.02).contains(&look.noise_sigma));
            floors.push(floor);
        }
        // The draws vary from scene to scene.
        let mean = floors.iter().sum::<f64>() / floors.len() as f64;
        assert!((mean - 0.5).abs() < 0.05, "{mean}");
        assert!(floors.iter().any(|&f| f < 0.3) && floors.iter().any(|&f| f > 0.7));
    }
}
