//! Where foreground slots live: the frame (`slot_to_world`) each slot's light field works in.
//!
//! By default every slot of an image gets that image's camera frame (the paper's choice). With
//! `Config::attention_frames`, each foreground slot's frame is the camera frame moved to where
//! the slot attends: the frame origin is put on the ray through the slot's attention centroid,
//! at the depth of the point on the optical axis closest to the world origin (the scene centre
//! the cameras look at; `scene_scale` if that point is behind the camera). Why: an object then
//! sits near its slot's frame origin, so rays that hit it have small Plücker moments in that
//! frame and the light field needs no latent-dependent notion of "where in the image" (trained
//! with camera frames, the foreground slots carved the image into fixed regions instead of
//! following the objects); and the ordering shift of each slot (`rays.rs`) becomes roughly its
//! distance along the ray. Frames stay rigid (the camera's rotation), so edits compose as
//! before, and they are stored in the codes file like any other frame.

use super::config::Config;
use crate::camera::Frame;
use glam::{DMat4, DVec3};

/// The frames of foreground slots attending at `centroids` ((x, y) in [0, 1] of the image
/// `camera` saw), one per slot.
pub fn slot_frames(cfg: &Config, camera: &Frame, centroids: &[[f32; 2]]) -> Vec<DMat4> {
    if !cfg.attention_frames {
        return vec![camera.camera_to_world; centroids.len()];
    }
    let origin = camera.origin();
    let forward = -camera.camera_to_world.z_axis.truncate().normalize();
    let depth = {
        let d = (-origin).dot(forward);
        if d.is_finite() && d > 1e-6 * cfg.scene_scale {
            d
        } else {
            cfg.scene_scale
        }
    };
    let (w, h) = (camera.intrinsics.w as f64, camera.intrinsics.h as f64);
    centroids
        .iter()
        .map(|&[x, y]| {
            let (x, y) = ((x as f64).clamp(0.0, 1.0), (y as f64).clamp(0.0, 1.0));
            let dir = camera.ray_at(x * w, y * h).direction;
            // The point of the ray at `depth` along the optical axis, or where it meets the
            // plane z = frame_ground_height (kept within 1/4–4 times that depth, so a ray near
            // the horizon or the camera cannot throw the frame away).
            let along = dir.dot(forward).max(1e-6);
            let mut axial = depth;
            let height = cfg.frame_ground_height;
            if height > 0.0 && dir.z < -1e-9 && origin.z > height {
                let t = (origin.z - height) / -dir.z;
                axial = (t * along).clamp(0.25 * depth, 4.0 * depth);
            }
            let at: DVec3 = origin + dir * (axial / along);
            let mut frame = camera.camera_to_world;
            frame.w_axis = at.extend(1.0);
            frame
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{look_at, Intrinsics};

    fn camera() -> Frame {
        Frame {
            file_path: None,
            intrinsics: Intrinsics::from_fov(64, 64, 49.13),
            camera_to_world: look_at(DVec3::new(0.0, -8.0, 9.0), DVec3::ZERO, DVec3::Z).unwrap(),
        }
    }

    #[test]
    fn camera_frames_by_default() {
        let cam = camera();
        let frames = slot_frames(&Config::small(), &cam, &[[0.1, 0.9], [0.5, 0.5]]);
        assert!(frames.iter().all(|f| *f == cam.camera_to_world));
    }

    #[test]
    fn attention_frames_sit_on_the_centroid_ray_at_the_scene_depth() {
        let mut cfg = Config::small();
        cfg.attention_frames = true;
        let cam = camera();
        let frames = slot_frames(&cfg, &cam, &[[0.5, 0.5], [0.2, 0.7]]);
        // The image centre looks at the world origin: that slot's frame is centred there.
        assert!(frames[0].w_axis.truncate().length() < 1e-9);
        // The other lies on its pixel's ray and projects back to its centroid.
        let (u, v) = cam.project(frames[1].w_axis.truncate()).unwrap();
        assert!((u - 0.2 * 64.0).abs() < 1e-6 && (v - 0.7 * 64.0).abs() < 1e-6);
        // Rotation is the camera's: frames are rigid.
        let rot = |m: &DMat4| glam::DMat3::from_mat4(*m);
        assert!(rot(&frames[1]).abs_diff_eq(rot(&cam.camera_to_world), 1e-12));
    }

    #[test]
    fn ground_frames_sit_where_the_centroid_ray_meets_the_plane() {
        let mut cfg = Config::small();
        cfg.attention_frames = true;
        cfg.frame_ground_height = 0.5;
        let cam = camera();
        let object = DVec3::new(2.0, 1.5, 0.5);
        let (u, v) = cam.project(object).unwrap();
        let frames = slot_frames(&cfg, &cam, &[[(u / 64.0) as f32, (v / 64.0) as f32]]);
        assert!((frames[0].w_axis.truncate() - object).length() < 1e-6);
        let rot = |m: &DMat4| glam::DMat3::from_mat4(*m);
        assert!(rot(&frames[0]).abs_diff_eq(rot(&cam.camera_to_world), 1e-12));
        // A ray above the horizon keeps the scene-depth frame; one grazing the plane far away
        // stays within 4× the scene depth.
        let low = Frame {
            camera_to_world: look_at(DVec3::new(0.0, -12.0, 1.5), DVec3::ZERO, DVec3::Z).unwrap(),
            ..camera()
        };
        let top = [0.5f32, 0.0];
        let grazing = [0.5f32, 0.38]; // 0.86° below the horizon: meets the plane ~66 away
        let plain = slot_frames(
            &Config {
                frame_ground_height: 0.0,
                ..cfg.clone()
            },
            &low,
            &[top],
        );
        let ground = slot_frames(&cfg, &low, &[top, grazing]);
        assert_eq!(ground[0], plain[0]);
        let forward = -low.camera_to_world.z_axis.truncate().normalize();
        let axial = (ground[1].w_axis.truncate() - low.origin()).dot(forward);
        let depth = low.origin().length();
        assert!((axial - 4.0 * depth).abs() < 1e-6, "{axial} vs {depth}");
    }
}
