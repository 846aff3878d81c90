//! Camera paths for novel-view renders: orbits and dollies, written as `transforms.json` so a
//! render needs no hand-written JSON (`colf-cameras`).

use crate::camera::{look_at, Cameras, Frame, Intrinsics};
use anyhow::{bail, Result};
use glam::DVec3;

/// Image size and field of view shared by every frame of a path.
#[derive(Clone, Copy, Debug)]
pub struct Lens {
    pub width: u32,
    pub height: u32,
    /// Horizontal field of view, degrees.
    pub fov_x_degrees: f64,
}

impl Lens {
    fn intrinsics(&self) -> Result<Intrinsics> {
        if !(self.fov_x_degrees > 0.0 && self.fov_x_degrees < 180.0) {
            bail!(
                "field of view {} is not in (0, 180) degrees",
                self.fov_x_degrees
            );
        }
        let k = Intrinsics::from_fov(self.width, self.height, self.fov_x_degrees);
        k.validate("lens")?;
        Ok(k)
    }
}

/// Frame names of a path: `frame_0000.png`, … (render writes `frame_0000.png`).
fn frame_name(index: usize) -> String {
    format!("frame_{index:04}.png")
}

fn check_frames(frames: usize) -> Result<()> {
    if frames == 0 || frames > 100_000 {
        bail!("frame count {frames} is not in 1..=100000");
    }
    Ok(())
}

/// Camera position at `azimuth` / `elevation` (degrees) on a sphere about `center`; +Z is up
/// and azimuth 0 is the +X axis.
pub fn spherical_position(
    center: DVec3,
    radius: f64,
    azimuth_deg: f64,
    elevation_deg: f64,
) -> DVec3 {
    let (az, el) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
    center + radius * DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin())
}

/// An orbit of `frames` cameras about `center`, all looking at it, evenly spaced in azimuth
/// starting at `start_azimuth` degrees.
pub fn orbit(
    center: DVec3,
    radius: f64,
    elevation_deg: f64,
    start_azimuth_deg: f64,
    frames: usize,
    lens: Lens,
) -> Result<Cameras> {
    check_frames(frames)?;
    if !(radius.is_finite() && radius > 0.0) {
        bail!("radius {radius} must be a positive number");
    }
    if elevation_deg.is_nan() || elevation_deg.abs() >= 90.0 {
        bail!("elevation {elevation_deg} must be strictly between -90 and 90 degrees");
    }
    if !center.is_finite() || !start_azimuth_deg.is_finite() {
        bail!("centre and start azimuth must be finite");
    }
    let intrinsics = lens.intrinsics()?;
    let frames = (0..frames)
        .map(|i| {
            let azimuth = start_azimuth_deg + 360.0 * i as f64 / frames as f64;
            let eye = spherical_position(center, radius, azimuth, elevation_deg);
            Ok(Frame {
                file_path: Some(frame_name(i)),
                intrinsics,
                camera_to_world: look_at(eye, center, DVec3::Z)?,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Cameras { frames })
}

/// A dolly: `frames` cameras moving on a straight line from `from` to `to` while looking at a
/// target that moves from `look_from` to `look_to`.
pub fn line(
    from: DVec3,
    to: DVec3,
    look_from: DVec3,
    look_to: DVec3,
    frames: usize,
    lens: Lens,
) -> Result<Cameras> {
    check_frames(frames)?;
    for v in [from, to, look_from, look_to] {
        if !v.is_finite() {
            bail!("positions must be finite");
        }
    }
    let intrinsics = lens.intrinsics()?;
    let frames = (0..frames)
        .map(|i| {
            let t = if frames == 1 {
                0.0
            } else {
                i as f64 / (frames - 1) as f64
            };
            let eye = from.lerp(to, t);
            let target = look_from.lerp(look_to, t);
            let camera_to_world = look_at(eye, target, DVec3::Z).map_err(|e| {
                anyhow::anyhow!("frame {i}: {e} (camera at {eye:?}, target {target:?})")
            })?;
            Ok(Frame {
                file_path: Some(frame_name(i)),
                intrinsics,
                camera_to_world,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Cameras { frames })
}

#[cfg(test)]
mod tests {
    use super::*;

    const LENS: Lens = Lens {
        width: 32,
        height: 32,
        fov_x_degrees: 49.13,
    };

    #[test]
    fn orbit_cameras_look_at_the_centre_from_the_radius() {
        let c = DVec3::new(1.0, 2.0, 0.5);
        let cams = orbit(c, 12.4, 40.0, 0.0, 8, LENS).unwrap();
        assert_eq!(cams.frames.len(), 8);
        for f in &cams.frames {
            assert!(((f.origin() - c).length() - 12.4).abs() < 1e-9);
            let centre_ray = f.ray_at(16.0, 16.0);
            assert!(centre_ray.origin.cross(centre_ray.direction).is_finite());
            assert!((centre_ray.direction - (c - f.origin()).normalize()).length() < 1e-9);
            // Elevation 40°: height above the centre is r·sin 40°.
            assert!((f.origin().z - c.z - 12.4 * 40f64.to_radians().sin()).abs() < 1e-9);
        }
        assert_eq!(cams.frames[3].stem().as_deref(), Some("frame_0003"));
        let round = Cameras::from_json(cams.to_json().as_bytes(), "orbit").unwrap();
        assert_eq!(round.frames.len(), 8);
    }

    #[test]
    fn line_interpolates_the_pose() {
        let cams = line(
            DVec3::new(10.0, 0.0, 3.0),
            DVec3::new(4.0, 0.0, 3.0),
            DVec3::ZERO,
            DVec3::ZERO,
            4,
            LENS,
        )
        .unwrap();
        assert!((cams.frames[0].origin() - DVec3::new(10.0, 0.0, 3.0)).length() < 1e-12);
        assert!((cams.frames[3].origin() - DVec3::new(4.0, 0.0, 3.0)).length() < 1e-12);
    }

    #[test]
    fn bad_paths_are_errors() {
        assert!(orbit(DVec3::ZERO, 0.0, 40.0, 0.0, 8, LENS).is_err());
        assert!(orbit(DVec3::ZERO, 5.0, 90.0, 0.0, 8, LENS).is_err());
        assert!(orbit(DVec3::ZERO, 5.0, 40.0, 0.0, 0, LENS).is_err());
        let wide = Lens {
            fov_x_degrees: 180.0,
            ..LENS
        };
        assert!(orbit(DVec3::ZERO, 5.0, 40.0, 0.0, 8, wide).is_err());
        // Looking straight down the up axis has no defined roll.
        assert!(line(
            DVec3::new(0.0, 0.0, 5.0),
            DVec3::new(0.0, 0.0, 6.0),
            DVec3::ZERO,
            DVec3::ZERO,
            2,
            LENS
        )
        .is_err());
    }
}
