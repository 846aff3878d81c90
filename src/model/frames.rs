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

/// With `Config::frames_from_residual`, the least share of a slot's attention on the object
/// pixels for it to be placed from them alone (a slot that attends to background places as
/// before).
pub const MIN_OBJECT_SHARE: f64 = 0.05;

/// The frames of foreground slots attending at `centroids` ((x, y) in [0, 1] of the image
/// `camera` saw), one per slot; `bottoms` (y in [0, 1], one per slot) is how far down each
/// slot's attention reaches, read only with `Config::frame_ground_contact`.
pub fn slot_frames(
    cfg: &Config,
    camera: &Frame,
    centroids: &[[f32; 2]],
    bottoms: &[f32],
) -> Vec<DMat4> {
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
    // The depth (along the optical axis) at which the ray from the camera along `dir` meets
    // the plane z = `height`, kept within 1/4–4 times `reference`, so a ray near the horizon
    // or the camera cannot throw the frame away; None for a ray that does not.
    let meets_plane = |dir: DVec3, height: f64, reference: f64| {
        (dir.z < -1e-9 && origin.z > height).then(|| {
            let t = (origin.z - height) / -dir.z;
            (t * dir.dot(forward).max(1e-6)).clamp(0.25 * reference, 4.0 * reference)
        })
    };
    centroids
        .iter()
        .enumerate()
        .map(|(slot, &[x, y])| {
            let (x, y) = ((x as f64).clamp(0.0, 1.0), (y as f64).clamp(0.0, 1.0));
            let dir = camera.ray_at(x * w, y * h).direction;
            // The point of the ray at `depth` along the optical axis, or at the depth where it
            // meets the plane z = frame_ground_height, or where the ray below the centroid
            // through the attention's lower edge meets the ground.
            let along = dir.dot(forward).max(1e-6);
            let mut axial = depth;
            if cfg.frame_ground_height > 0.0 {
                axial = meets_plane(dir, cfg.frame_ground_height, depth).unwrap_or(depth);
            } else if cfg.frame_ground_contact {
                // Bounded by the scene scale, not the scene depth: a camera looking along a
                // street passes the world origin at almost no depth.
                let bottom = bottoms.get(slot).map_or(y, |&b| (b as f64).clamp(y, 1.0));
                let contact = camera.ray_at(x * w, bottom * h).direction;
                axial = meets_plane(contact, 0.0, cfg.scene_scale).unwrap_or(cfg.scene_scale);
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
        let frames = slot_frames(&Config::small(), &cam, &[[0.1, 0.9], [0.5, 0.5]], &[]);
        assert!(frames.iter().all(|f| *f == cam.camera_to_world));
    }

    #[test]
    fn attention_frames_sit_on_the_centroid_ray_at_the_scene_depth() {
        let mut cfg = Config::small();
        cfg.attention_frames = true;
        let cam = camera();
        let frames = slot_frames(&cfg, &cam, &[[0.5, 0.5], [0.2, 0.7]], &[]);
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
        let frames = slot_frames(&cfg, &cam, &[[(u / 64.0) as f32, (v / 64.0) as f32]], &[]);
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
            &[],
        );
        let ground = slot_frames(&cfg, &low, &[top, grazing], &[]);
        assert_eq!(ground[0], plain[0]);
        let forward = -low.camera_to_world.z_axis.truncate().normalize();
        let axial = (ground[1].w_axis.truncate() - low.origin()).dot(forward);
        let depth = low.origin().length();
        assert!((axial - 4.0 * depth).abs() < 1e-6, "{axial} vs {depth}");
    }

    #[test]
    fn contact_frames_sit_at_the_depth_where_the_attention_meets_the_ground() {
        let mut cfg = Config::small();
        cfg.attention_frames = true;
        cfg.frame_ground_contact = true;
        // A street camera 1.2 up, looking along +X and slightly down; a car 15 ahead and 2
        // to the side, its centre 0.5 up and its contact with the ground below that.
        let street = Frame {
            intrinsics: Intrinsics::from_fov(128, 128, 49.13),
            camera_to_world: look_at(
                DVec3::new(0.0, 0.0, 1.2),
                DVec3::new(30.0, 0.0, 0.36),
                DVec3::Z,
            )
            .unwrap(),
            file_path: None,
        };
        let (centre, contact) = (DVec3::new(15.0, 2.0, 0.5), DVec3::new(15.0, 2.0, 0.0));
        let at = |p: DVec3| {
            let (u, v) = street.project(p).unwrap();
            [(u / 128.0) as f32, (v / 128.0) as f32]
        };
        let [x, y] = at(centre);
        let bottom = at(contact)[1];
        let frames = slot_frames(&cfg, &street, &[[x, y]], &[bottom]);
        // On the centroid ray, at the car's depth along the optical axis (to 0.1 %: the camera
        // pitches down, so the contact's image column is not quite the centre's).
        let forward = -street.camera_to_world.z_axis.truncate().normalize();
        let axial = |p: DVec3| (p - street.origin()).dot(forward);
        let origin = frames[0].w_axis.truncate();
        assert!((axial(origin) - axial(centre)).abs() < 0.02, "{origin}");
        let (u, v) = street.project(origin).unwrap();
        assert!((u / 128.0 - x as f64).abs() < 1e-6 && (v / 128.0 - y as f64).abs() < 1e-6);
        // The scene-depth frame puts it where the optical axis passes nearest the world
        // origin: almost at the camera, on a street.
        let plain = slot_frames(
            &Config {
                frame_ground_contact: false,
                ..cfg.clone()
            },
            &street,
            &[[x, y]],
            &[bottom],
        );
        assert!(axial(plain[0].w_axis.truncate()) < 0.1);
        // A lower edge above the centroid reads as the centroid (whose ray meets the ground
        // farther away); one above the horizon gives the scene scale.
        let at_centroid = slot_frames(&cfg, &street, &[[x, y]], &[0.0]);
        let horizon = slot_frames(&cfg, &street, &[[0.5, 0.1]], &[0.1]);
        assert!(axial(at_centroid[0].w_axis.truncate()) > axial(centre));
        assert!((axial(horizon[0].w_axis.truncate()) - cfg.scene_scale).abs() < 1e-6);
    }
}
