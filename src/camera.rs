//! Cameras and rays.
//!
//! colf reads cameras in the NeRF / nerfstudio `transforms.json` convention (the contract in
//! `docs/formats.md`): `transform_matrix` is camera-to-world, row-major, OpenGL camera axes (+X right,
//! +Y up, looking along −Z); world is right-handed with +Z up; pixel (column i, row j) is sampled
//! through its centre (i + 0.5, j + 0.5), row 0 at the top. The uORF `*_RT.txt` layout (OpenCV
//! camera axes: +X right, +Y down, looking along +Z) is converted on reading.
//!
//! Everything here is f64: cameras 10⁴ units from the origin must still produce unit directions
//! and exact moments; the network side converts to f32 after normalising.

use anyhow::{anyhow, bail, Context, Result};
use glam::{DMat3, DMat4, DVec3, DVec4};
use serde::{Deserialize, Serialize};

/// Largest accepted image side: big enough for any real render, small enough that a typo
/// (`"w": 6400000`) is an error rather than an out-of-memory kill.
pub const MAX_IMAGE_SIDE: u32 = 16384;

/// Largest (pixel extent from the principal point) / (focal length): a half field of view of
/// 89.99999°, beyond any real lens.
pub const MAX_EXTENT_OVER_FOCAL: f64 = 1e6;

/// Pinhole intrinsics of one frame, in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub w: u32,
    pub h: u32,
    pub fl_x: f64,
    pub fl_y: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// Square-pixel intrinsics from a horizontal field of view, centred principal point.
    pub fn from_fov(w: u32, h: u32, fov_x_degrees: f64) -> Intrinsics {
        let fl = 0.5 * w as f64 / (0.5 * fov_x_degrees.to_radians()).tan();
        Intrinsics {
            w,
            h,
            fl_x: fl,
            fl_y: fl,
            cx: 0.5 * w as f64,
            cy: 0.5 * h as f64,
        }
    }

    /// Direction, in OpenGL camera axes and not normalised, of the ray through pixel
    /// coordinates (u, v) (u = column + 0.5 for a pixel centre, v = row + 0.5).
    pub fn camera_direction(&self, u: f64, v: f64) -> DVec3 {
        DVec3::new((u - self.cx) / self.fl_x, -(v - self.cy) / self.fl_y, -1.0)
    }

    /// Checks sizes and focal lengths; `what` names the frame in the message.
    pub fn validate(&self, what: &str) -> Result<()> {
        if self.w == 0 || self.h == 0 || self.w > MAX_IMAGE_SIDE || self.h > MAX_IMAGE_SIDE {
            bail!(
                "{what}: image size {}x{} is outside 1..={MAX_IMAGE_SIDE}",
                self.w,
                self.h
            );
        }
        for (name, v) in [
            ("fl_x", self.fl_x),
            ("fl_y", self.fl_y),
            ("cx", self.cx),
            ("cy", self.cy),
        ] {
            if !v.is_finite() {
                bail!("{what}: {name} is not a finite number");
            }
        }
        if self.fl_x <= 0.0 || self.fl_y <= 0.0 {
            bail!(
                "{what}: focal length must be positive (fl_x {}, fl_y {})",
                self.fl_x,
                self.fl_y
            );
        }
        // A focal length so short that the image spans 180° (fl_x = 1e-300) gives rays with
        // no usable direction: the image's extent over the focal length is bounded.
        for (name, fl, c, size) in [
            ("fl_x", self.fl_x, self.cx, self.w),
            ("fl_y", self.fl_y, self.cy, self.h),
        ] {
            let extent = c.abs().max((size as f64 - c).abs()).max(1.0);
            if extent / fl > MAX_EXTENT_OVER_FOCAL {
                bail!(
                    "{what}: {name} = {fl:e} is too short a focal length for this {}x{} image (its field of view would be 180°)",
                    self.w,
                    self.h
                );
            }
        }
        Ok(())
    }
}

/// A ray with a unit direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: DVec3,
    /// Unit length.
    pub direction: DVec3,
}

impl Ray {
    /// A ray from `origin` along `direction` (normalised here; must be non-zero and finite).
    pub fn new(origin: DVec3, direction: DVec3) -> Ray {
        Ray {
            origin,
            direction: direction.normalize(),
        }
    }

    /// The ray in another frame: `transform` maps this ray's frame to the new one (rigid).
    pub fn transformed(&self, transform: &DMat4) -> Ray {
        Ray::new(
            transform.transform_point3(self.origin),
            transform.transform_vector3(self.direction),
        )
    }

    /// 6-D Plücker coordinates (d, m) with d the unit direction and m = o × d the moment; |m| is
    /// the distance from the frame's origin to the line, and (d, m) do not depend on where along
    /// the line the origin sits.
    pub fn plucker(&self) -> [f64; 6] {
        let d = self.direction;
        let m = self.origin.cross(d);
        [d.x, d.y, d.z, m.x, m.y, m.z]
    }

    /// Signed distance along the ray from its origin to the point of the line closest to `p`.
    pub fn depth_of_closest_point(&self, p: DVec3) -> f64 {
        (p - self.origin).dot(self.direction)
    }
}

/// One camera: intrinsics, pose and the image it names.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// `file_path` of the frame in `transforms.json`, if any.
    pub file_path: Option<String>,
    pub intrinsics: Intrinsics,
    /// Camera-to-world, OpenGL camera axes.
    pub camera_to_world: DMat4,
}

impl Frame {
    /// The camera centre in world space.
    pub fn origin(&self) -> DVec3 {
        self.camera_to_world.w_axis.truncate()
    }

    /// The ray through pixel coordinates (u, v) in world space.
    pub fn ray_at(&self, u: f64, v: f64) -> Ray {
        let dir_cam = self.intrinsics.camera_direction(u, v);
        Ray::new(
            self.origin(),
            self.camera_to_world.transform_vector3(dir_cam),
        )
    }

    /// The ray through the centre of pixel (column i, row j).
    pub fn pixel_ray(&self, i: u32, j: u32) -> Ray {
        self.ray_at(i as f64 + 0.5, j as f64 + 0.5)
    }

    /// All pixel-centre rays, row-major (row 0 = top).
    pub fn rays(&self) -> Vec<Ray> {
        let (w, h) = (self.intrinsics.w, self.intrinsics.h);
        (0..h)
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .map(|(i, j)| self.pixel_ray(i, j))
            .collect()
    }

    /// Projects a world point to pixel coordinates (u, v); `None` if behind the camera.
    pub fn project(&self, p: DVec3) -> Option<(f64, f64)> {
        let cam = self.camera_to_world.inverse().transform_point3(p);
        if cam.z >= 0.0 {
            return None;
        }
        let k = &self.intrinsics;
        let u = k.cx + k.fl_x * (cam.x / -cam.z);
        let v = k.cy - k.fl_y * (cam.y / -cam.z);
        Some((u, v))
    }

    /// The stem of `file_path` (`"views/view_003.png"` → `"view_003"`), used to name renders.
    pub fn stem(&self) -> Option<String> {
        let path = self.file_path.as_deref()?;
        let stem = std::path::Path::new(path).file_stem()?.to_str()?;
        (!stem.is_empty()).then(|| stem.to_string())
    }
}

/// `v` as a unit vector, scaled by its largest component first so that neither a vector whose
/// squared length overflows ([0, 0, 1e200]) nor one whose squared length underflows
/// ([1e-200, 0, 0]) is lost; `None` for the zero vector or a non-finite one.
pub fn unit_vector(v: DVec3) -> Option<DVec3> {
    let largest = v.abs().max_element();
    if !(largest.is_finite() && largest > 0.0) {
        return None;
    }
    Some((v / largest).normalize())
}

/// Camera-to-world of a camera at `eye` looking at `target`, with `up` roughly up in the image.
pub fn look_at(eye: DVec3, target: DVec3, up: DVec3) -> Result<DMat4> {
    if !eye.is_finite() || !target.is_finite() {
        bail!("camera position {eye:?} or target {target:?} is not finite");
    }
    let forward = target - eye;
    if !forward.is_finite() {
        bail!("the distance from camera position {eye:?} to target {target:?} is beyond the range of numbers");
    }
    let Some(forward) = unit_vector(forward) else {
        bail!("camera position and target coincide");
    };
    let back = -forward;
    let Some(up) = unit_vector(up) else {
        bail!("the up vector is zero");
    };
    let right = up.cross(back);
    if right.length() < 1e-9 {
        bail!("the up vector is parallel to the viewing direction");
    }
    let right = right.normalize();
    let true_up = back.cross(right);
    Ok(DMat4::from_cols(
        right.extend(0.0),
        true_up.extend(0.0),
        back.extend(0.0),
        eye.extend(1.0),
    ))
}

/// Checks that a camera-to-world (or slot-to-world) matrix is finite and rigid: orthonormal
/// rotation with determinant +1 and last row (0, 0, 0, 1). `tolerance` bounds |RᵀR − I|.
pub fn validate_rigid(m: &DMat4, what: &str, tolerance: f64) -> Result<()> {
    let cols = m.to_cols_array();
    if cols.iter().any(|v| !v.is_finite()) {
        bail!("{what}: matrix has a non-finite entry");
    }
    let last_row = m.row(3);
    if (last_row - DVec4::new(0.0, 0.0, 0.0, 1.0))
        .abs()
        .max_element()
        > tolerance
    {
        bail!("{what}: last row must be [0, 0, 0, 1], got {last_row:?}");
    }
    let r = DMat3::from_mat4(*m);
    let det = r.determinant();
    if det.abs() < 1e-12 {
        bail!("{what}: rotation part is singular");
    }
    let err = (r.transpose() * r - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |a, v| a.max(v.abs()));
    if err > tolerance {
        bail!("{what}: rotation part is not orthonormal (|RᵀR − I| = {err:.3e}; scale and shear are not allowed)");
    }
    if det < 0.0 {
        bail!("{what}: rotation part is a reflection (determinant {det:.3})");
    }
    Ok(())
}

/// Rigidity tolerance for matrices read from files: loose enough for 6-digit JSON.
pub const RIGID_TOLERANCE: f64 = 1e-3;

/// uORF's horizontal focal length in units of the image width (350/320: its `Projection`).
pub const UORF_FOCAL_X_PER_WIDTH: f64 = 350.0 / 320.0;
/// uORF's vertical focal length in units of the image height (350/240: its images are 4:3
/// renders, 320×240 at focal length 350, stretched to a square).
pub const UORF_FOCAL_Y_PER_HEIGHT: f64 = 350.0 / 240.0;

/// A set of frames: the content of one `transforms.json`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Cameras {
    pub frames: Vec<Frame>,
}

/// Optional intrinsics as they appear at the top level and in frames of `transforms.json`.
#[derive(Deserialize, Default, Clone, Copy)]
struct RawIntrinsics {
    w: Option<f64>,
    h: Option<f64>,
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    camera_angle_x: Option<f64>,
    camera_angle_y: Option<f64>,
}

impl RawIntrinsics {
    /// `self` with `over`'s fields taking precedence.
    fn overridden_by(self, over: RawIntrinsics) -> RawIntrinsics {
        RawIntrinsics {
            w: over.w.or(self.w),
            h: over.h.or(self.h),
            fl_x: over.fl_x.or(self.fl_x),
            fl_y: over.fl_y.or(self.fl_y),
            cx: over.cx.or(self.cx),
            cy: over.cy.or(self.cy),
            camera_angle_x: over.camera_angle_x.or(self.camera_angle_x),
            camera_angle_y: over.camera_angle_y.or(self.camera_angle_y),
        }
    }

    fn resolve(&self, what: &str) -> Result<Intrinsics> {
        let side = |name: &str, v: Option<f64>| -> Result<u32> {
            let v = v.ok_or_else(|| anyhow!("{what}: missing `{name}`"))?;
            if !v.is_finite() || v.fract() != 0.0 || v < 1.0 || v > MAX_IMAGE_SIDE as f64 {
                bail!("{what}: `{name}` = {v} is not an image size in 1..={MAX_IMAGE_SIDE}");
            }
            Ok(v as u32)
        };
        let w = side("w", self.w)?;
        let h = side("h", self.h)?;
        let from_angle = |angle: f64, size: u32, name: &str| -> Result<f64> {
            if !angle.is_finite() || angle <= 0.0 || angle >= std::f64::consts::PI {
                bail!("{what}: `{name}` = {angle} is not a field of view in (0, π) radians");
            }
            Ok(0.5 * size as f64 / (0.5 * angle).tan())
        };
        let fl_x = match (self.fl_x, self.camera_angle_x) {
            (Some(f), _) => f,
            (None, Some(a)) => from_angle(a, w, "camera_angle_x")?,
            (None, None) => match self.camera_angle_y {
                Some(a) => from_angle(a, h, "camera_angle_y")?,
                None => bail!("{what}: missing focal length (`fl_x` or `camera_angle_x`)"),
            },
        };
        let fl_y = match (self.fl_y, self.camera_angle_y) {
            (Some(f), _) => f,
            (None, Some(a)) => from_angle(a, h, "camera_angle_y")?,
            (None, None) => fl_x,
        };
        let k = Intrinsics {
            w,
            h,
            fl_x,
            fl_y,
            cx: self.cx.unwrap_or(0.5 * w as f64),
            cy: self.cy.unwrap_or(0.5 * h as f64),
        };
        k.validate(what)?;
        Ok(k)
    }
}

#[derive(Deserialize)]
struct RawFrame {
    file_path: Option<String>,
    transform_matrix: Option<Vec<Vec<f64>>>,
    #[serde(flatten)]
    intrinsics: RawIntrinsics,
}

#[derive(Deserialize)]
struct RawTransforms {
    #[serde(flatten)]
    intrinsics: RawIntrinsics,
    frames: Option<Vec<RawFrame>>,
}

#[derive(Serialize)]
struct OutFrame<'a> {
    #[serde(skip_serializing_if = "Option::is_none")]
    file_path: Option<&'a str>,
    transform_matrix: [[f64; 4]; 4],
    #[serde(flatten)]
    intrinsics: Option<OutIntrinsics>,
}

#[derive(Serialize, Clone, Copy, PartialEq)]
struct OutIntrinsics {
    w: u32,
    h: u32,
    fl_x: f64,
    fl_y: f64,
    cx: f64,
    cy: f64,
}

impl From<Intrinsics> for OutIntrinsics {
    fn from(k: Intrinsics) -> Self {
        OutIntrinsics {
            w: k.w,
            h: k.h,
            fl_x: k.fl_x,
            fl_y: k.fl_y,
            cx: k.cx,
            cy: k.cy,
        }
    }
}

/// Row-major 4×4 (or 3×4, the last row then being 0 0 0 1) from JSON rows.
fn matrix_from_rows(rows: &[Vec<f64>], what: &str) -> Result<DMat4> {
    if rows.len() != 4 && rows.len() != 3 {
        bail!("{what}: expected 4 rows (or 3), got {}", rows.len());
    }
    let mut m = [[0.0f64; 4]; 4];
    m[3] = [0.0, 0.0, 0.0, 1.0];
    for (r, row) in rows.iter().enumerate() {
        if row.len() != 4 {
            bail!("{what}: row {r} has {} entries, expected 4", row.len());
        }
        m[r].copy_from_slice(row);
    }
    Ok(DMat4::from_cols_array_2d(&m).transpose())
}

/// Row-major rows of a matrix, for JSON.
pub fn matrix_rows(m: &DMat4) -> [[f64; 4]; 4] {
    m.transpose().to_cols_array_2d()
}

/// OpenCV camera axes (+Y down, +Z forward) ↔ OpenGL camera axes (+Y up, −Z forward): flip the
/// camera's Y and Z axes. The map is its own inverse.
pub fn opencv_to_opengl(camera_to_world: &DMat4) -> DMat4 {
    *camera_to_world * DMat4::from_diagonal(glam::DVec4::new(1.0, -1.0, -1.0, 1.0))
}

impl Cameras {
    /// Parses `transforms.json` text; `name` (the file) prefixes every error.
    pub fn from_json(bytes: &[u8], name: &str) -> Result<Cameras> {
        let raw: RawTransforms = crate::io::parse_json(bytes, name)?;
        let frames = raw
            .frames
            .ok_or_else(|| anyhow!("{name}: no `frames` array"))?;
        if frames.is_empty() {
            bail!("{name}: `frames` is empty");
        }
        let frames = frames
            .iter()
            .enumerate()
            .map(|(index, f)| {
                let what = format!("{name}: frame {index}");
                let rows = f
                    .transform_matrix
                    .as_ref()
                    .ok_or_else(|| anyhow!("{what}: missing `transform_matrix`"))?;
                let camera_to_world = matrix_from_rows(rows, &format!("{what}: transform_matrix"))?;
                validate_rigid(
                    &camera_to_world,
                    &format!("{what}: transform_matrix"),
                    RIGID_TOLERANCE,
                )?;
                Ok(Frame {
                    file_path: f.file_path.clone(),
                    intrinsics: raw.intrinsics.overridden_by(f.intrinsics).resolve(&what)?,
                    camera_to_world,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Cameras { frames })
    }

    /// Reads `transforms.json` from a file or stdin (`-`).
    pub fn read(path: &str) -> Result<Cameras> {
        let bytes = crate::io::read_input(path, false)?;
        Cameras::from_json(&bytes, crate::io::display_name(path))
    }

    /// `transforms.json` text. Intrinsics shared by every frame go to the top level.
    pub fn to_json(&self) -> String {
        let first = self
            .frames
            .first()
            .map(|f| OutIntrinsics::from(f.intrinsics));
        let shared = first.filter(|k| {
            self.frames
                .iter()
                .all(|f| OutIntrinsics::from(f.intrinsics) == *k)
        });
        let frames: Vec<OutFrame> = self
            .frames
            .iter()
            .map(|f| OutFrame {
                file_path: f.file_path.as_deref(),
                transform_matrix: matrix_rows(&f.camera_to_world),
                intrinsics: shared.is_none().then(|| f.intrinsics.into()),
            })
            .collect();
        let mut doc = serde_json::Map::new();
        if let Some(k) = shared {
            if let serde_json::Value::Object(m) = serde_json::to_value(k).expect("plain struct") {
                doc.extend(m);
            }
        }
        doc.insert(
            "frames".into(),
            serde_json::to_value(frames).expect("plain struct"),
        );
        let mut text = serde_json::to_string_pretty(&doc).expect("plain map");
        text.push('\n');
        text
    }

    /// A uORF camera file (`*_RT.txt`: 4×4 camera-to-world in OpenCV axes, whitespace
    /// separated, row-major) converted to our OpenGL axes.
    pub fn uorf_pose_from_text(text: &str, name: &str) -> Result<DMat4> {
        let values = text
            .split_whitespace()
            .map(|t| {
                t.parse::<f64>()
                    .with_context(|| format!("{name}: `{t}` is not a number"))
            })
            .collect::<Result<Vec<_>>>()?;
        if values.len() != 16 && values.len() != 12 {
            bail!(
                "{name}: expected a 4x4 (or 3x4) matrix, found {} numbers",
                values.len()
            );
        }
        let rows: Vec<Vec<f64>> = values.chunks(4).map(|c| c.to_vec()).collect();
        let opencv = matrix_from_rows(&rows, name)?;
        validate_rigid(&opencv, name, RIGID_TOLERANCE)?;
        Ok(opencv_to_opengl(&opencv))
    }

    /// uORF intrinsics for a W×H image (its `models/projection.py`): fx = 350/320·W,
    /// fy = 350/240·H, centred.
    pub fn uorf_intrinsics(w: u32, h: u32) -> Intrinsics {
        Intrinsics {
            w,
            h,
            fl_x: UORF_FOCAL_X_PER_WIDTH * w as f64,
            fl_y: UORF_FOCAL_Y_PER_HEIGHT * h as f64,
            cx: 0.5 * w as f64,
            cy: 0.5 * h as f64,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SAMPLE: &str = r#"{ "w": 64, "h": 64, "fl_x": 70.0, "fl_y": 70.0, "cx": 32.0, "cy": 32.0,
      "frames": [ { "file_path": "view_000.png",
                    "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,5],[0,0,0,1]] },
                  { "file_path": "b.png", "w": 32, "fl_x": 35,
                    "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,5],[0,0,0,1]] } ] }"#;

    #[test]
    fn reads_the_contract_example() {
        let cams = Cameras::from_json(SAMPLE.as_bytes(), "t.json").unwrap();
        assert_eq!(cams.frames.len(), 2);
        let f = &cams.frames[0];
        assert_eq!(f.origin(), DVec3::new(0.0, 0.0, 5.0));
        assert_eq!(f.stem().as_deref(), Some("view_000"));
        // The centre pixel's corner (32, 32) looks straight down −Z.
        let r = f.ray_at(32.0, 32.0);
        assert!((r.direction - DVec3::NEG_Z).length() < 1e-12);
        // Row 0 is the top: its rays point up (+Y), column 0 left (−X).
        let top_left = f.pixel_ray(0, 0);
        assert!(top_left.direction.y > 0.0 && top_left.direction.x < 0.0);
        // Per-frame overrides, the rest inherited.
        let g = &cams.frames[1].intrinsics;
        assert_eq!((g.w, g.h, g.fl_x, g.fl_y, g.cx), (32, 64, 35.0, 70.0, 32.0));
    }

    #[test]
    fn camera_angle_x_gives_the_focal_length() {
        let text = r#"{"w": 100, "h": 50, "camera_angle_x": 1.5707963267948966,
            "frames": [{"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#;
        let k = Cameras::from_json(text.as_bytes(), "t").unwrap().frames[0].intrinsics;
        assert!((k.fl_x - 50.0).abs() < 1e-9 && (k.fl_y - 50.0).abs() < 1e-9);
        assert_eq!((k.cx, k.cy), (50.0, 25.0));
    }

    #[test]
    fn json_round_trip() {
        let cams = Cameras::from_json(SAMPLE.as_bytes(), "t.json").unwrap();
        let again = Cameras::from_json(cams.to_json().as_bytes(), "again").unwrap();
        assert_eq!(cams, again);
    }

    #[test]
    fn projection_inverts_pixel_rays() {
        let eye = DVec3::new(7.0, -3.0, 8.0);
        let frame = Frame {
            file_path: None,
            intrinsics: Intrinsics::from_fov(64, 48, 49.13),
            camera_to_world: look_at(eye, DVec3::ZERO, DVec3::Z).unwrap(),
        };
        let r = frame.pixel_ray(10, 40);
        let p = r.origin + 9.5 * r.direction;
        let (u, v) = frame.project(p).unwrap();
        assert!((u - 10.5).abs() < 1e-9 && (v - 40.5).abs() < 1e-9);
        // look_at: the image centre ray hits the target.
        let c = frame.ray_at(32.0, 24.0);
        assert!(c.origin.cross(c.direction).length() < 1e-9);
    }

    #[test]
    fn plucker_is_independent_of_the_point_on_the_line() {
        let a = Ray::new(DVec3::new(1.0, 2.0, 3.0), DVec3::new(0.3, -0.2, 0.9));
        let b = Ray::new(a.origin + 17.0 * a.direction, a.direction);
        let (pa, pb) = (a.plucker(), b.plucker());
        for k in 0..6 {
            assert!((pa[k] - pb[k]).abs() < 1e-12);
        }
        let d = DVec3::new(pa[0], pa[1], pa[2]);
        assert!((d.length() - 1.0).abs() < 1e-15);
    }

    #[test]
    fn far_cameras_keep_unit_directions() {
        let eye = DVec3::new(1e4, -1e4, 3e3);
        let frame = Frame {
            file_path: None,
            intrinsics: Intrinsics::from_fov(8, 8, 30.0),
            camera_to_world: look_at(eye, DVec3::ZERO, DVec3::Z).unwrap(),
        };
        for r in frame.rays() {
            assert!((r.direction.length() - 1.0).abs() < 1e-12);
            assert!(r.plucker().iter().all(|v| v.is_finite()));
        }
    }

    #[test]
    fn rejects_bad_cameras_with_clear_messages() {
        let cases = [
            (
                r#"{"w":64,"h":64,"fl_x":0,"frames":[{"transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
                "focal length",
            ),
            (
                r#"{"w":64,"h":64,"fl_x":50,"frames":[{"transform_matrix":[[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
                "orthonormal",
            ),
            (
                r#"{"w":64,"h":64,"fl_x":50,"frames":[{"transform_matrix":[[0,0,0,0],[0,0,0,0],[0,0,0,0],[0,0,0,1]]}]}"#,
                "singular",
            ),
            (
                r#"{"w":64,"h":64,"fl_x":50,"frames":[{"transform_matrix":[[-1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
                "reflection",
            ),
            (
                r#"{"w":64,"h":64,"fl_x":50,"frames":[{"transform_matrix":[[1,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
                "row 0 has 3",
            ),
            (
                r#"{"w":64000000,"h":64,"fl_x":50,"frames":[{"transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
                "image size",
            ),
            (
                r#"{"w":64,"h":64,"frames":[{"transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
                "missing focal",
            ),
            (r#"{"w":64,"h":64,"fl_x":50,"frames":[]}"#, "empty"),
            (
                r#"{"w":64,"h":64,"fl_x":50,"frames":[{}]}"#,
                "missing `transform_matrix`",
            ),
            (
                r#"{"w":64,"h":64,"fl_x":50,"frames":[{"transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,1,1]]}]}"#,
                "last row",
            ),
            (
                r#"{"w":64,"h":64,"fl_x":50,"frames":[{"transform_matrix":"x"}]}"#,
                "invalid JSON",
            ),
            (r#"[1, 2"#, "invalid JSON"),
        ];
        for (text, expected) in cases {
            let err = Cameras::from_json(text.as_bytes(), "cams.json").unwrap_err();
            let msg = format!("{err:#}");
            assert!(msg.starts_with("cams.json"), "{msg}");
            assert!(msg.contains(expected), "`{msg}` lacks `{expected}`");
        }
    }

    #[test]
    fn absurdly_short_focal_lengths_are_refused_naming_the_file() {
        let text = r#"{"w": 8, "h": 8, "fl_x": 1e-300, "frames": [{"transform_matrix":
            [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#;
        let msg = format!(
            "{:#}",
            Cameras::from_json(text.as_bytes(), "cams.json").unwrap_err()
        );
        assert!(
            msg.starts_with("cams.json: frame 0: fl_x = 1e-300"),
            "{msg}"
        );
    }

    #[test]
    fn look_at_survives_huge_distances_and_names_the_problem() {
        let far = DVec3::new(7.6e307, 0.0, 6.4e307);
        let m = look_at(far, DVec3::ZERO, DVec3::Z).unwrap();
        // The camera looks at the origin: its back axis points to the camera.
        assert!((m.z_axis.truncate() - unit_vector(far).unwrap()).length() < 1e-12);
        let msg = look_at(
            DVec3::new(1.7e308, 0.0, 0.0),
            DVec3::new(-1.7e308, 0.0, 0.0),
            DVec3::Z,
        )
        .unwrap_err()
        .to_string();
        assert!(msg.contains("beyond the range"), "{msg}");
        assert_eq!(unit_vector(DVec3::new(0.0, 0.0, 1e200)), Some(DVec3::Z));
        assert_eq!(unit_vector(DVec3::new(1e-200, 0.0, 0.0)), Some(DVec3::X));
        assert_eq!(unit_vector(DVec3::ZERO), None);
    }

    #[test]
    fn uorf_pose_is_converted_to_opengl_axes() {
        // An OpenCV camera at (0,0,5) looking down −Z world: its +Z (forward) is world −Z and
        // its +Y (down) is world −Y.
        let text = "1 0 0 0\n0 -1 0 0\n0 0 -1 5\n0 0 0 1\n";
        let m = Cameras::uorf_pose_from_text(text, "00000_sc0000_az00_RT.txt").unwrap();
        let frame = Frame {
            file_path: None,
            intrinsics: Cameras::uorf_intrinsics(64, 64),
            camera_to_world: m,
        };
        let centre = frame.ray_at(32.0, 32.0);
        assert!((centre.direction - DVec3::NEG_Z).length() < 1e-12);
        assert!(
            frame.pixel_ray(0, 0).direction.y > 0.0,
            "row 0 must look up"
        );
        assert!(Cameras::uorf_pose_from_text("1 2 x", "rt").is_err());
    }
}
