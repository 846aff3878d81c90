//! What a synthetic scene is — objects, background geometry, ground, light — as written to
//! `scene.json`, and how objects turn into solids for the tracer.

use super::geometry::Solid;
use super::room::{ChairDesign, Room};
use super::shading::{albedo_of_srgb8, Ground};
use glam::DVec3;
use serde::{Deserialize, Serialize};

/// CLEVR's 8 colours, sRGB.
pub const CLEVR_COLORS: [(&str, [u8; 3]); 8] = [
    ("gray", [87, 87, 87]),
    ("red", [173, 35, 35]),
    ("blue", [42, 75, 215]),
    ("green", [29, 105, 20]),
    ("brown", [129, 74, 25]),
    ("purple", [129, 38, 192]),
    ("cyan", [41, 208, 208]),
    ("yellow", [255, 238, 51]),
];

/// CLEVR's two sizes r: small and large.
pub const CLEVR_SIZES: [(&str, f64); 2] = [("small", 0.35), ("large", 0.7)];

/// Linear albedo of car tyres.
const TYRE_ALBEDO: f64 = 0.03;

/// Dimensions of a boxy car (preset `city`), in its own frame: +X forward, centre of the body
/// box at the object's `position`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CarShape {
    /// Half extents of the body box.
    pub body_half: [f64; 3],
    /// Half extents of the cabin box, which sits on the body.
    pub cabin_half: [f64; 3],
    /// Offset of the cabin centre along the car's +X from the body centre.
    pub cabin_offset: f64,
    /// Half extents of each of the four wheel boxes.
    pub wheel_half: [f64; 3],
}

/// One foreground object, exactly as in `scene.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Object {
    /// `sphere`, `cube`, `cylinder`, `car` or `chair`.
    pub shape: String,
    /// CLEVR colour name.
    pub color: String,
    /// sRGB colour.
    pub rgb: [u8; 3],
    /// CLEVR size r (sphere radius; cylinder radius and half-height; cube half-edge r/√2);
    /// for a car, the half-length of its body; for a chair, its height (floor to the top of
    /// its back).
    pub size: f64,
    /// `small`/`large` for CLEVR shapes, `car` for cars, `chair` for chairs.
    pub size_name: String,
    /// Centre of the object (for CLEVR shapes the solid's centre, for a car the body's centre,
    /// for a chair the seat's centre): always a point inside the object.
    pub position: [f64; 3],
    /// Rotation about +Z, degrees.
    pub rotation_z_degrees: f64,
    /// Radius of the object's footprint on the ground about its centre.
    pub footprint_radius: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub car: Option<CarShape>,
    /// For a chair (presets room-chair, room-diverse), its design.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chair: Option<ChairDesign>,
    /// Mask pixels of this object in each view (filled in after rendering).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub visible_pixels: Vec<u64>,
}

impl Object {
    /// A CLEVR shape of size r resting on the ground at (x, y).
    pub fn clevr(shape: &str, color: usize, size: usize, x: f64, y: f64, yaw_deg: f64) -> Object {
        let (color_name, rgb) = CLEVR_COLORS[color];
        let (size_name, r) = CLEVR_SIZES[size];
        let z = match shape {
            "cube" => r / std::f64::consts::SQRT_2,
            _ => r,
        };
        Object {
            shape: shape.to_string(),
            color: color_name.to_string(),
            rgb,
            size: r,
            size_name: size_name.to_string(),
            position: [x, y, z],
            rotation_z_degrees: yaw_deg,
            // Cube: half-diagonal of a face of half-edge r/√2 is r; the others have radius r.
            footprint_radius: r,
            car: None,
            chair: None,
            visible_pixels: Vec::new(),
        }
    }

    /// Centre as a vector.
    pub fn center(&self) -> DVec3 {
        DVec3::from_array(self.position)
    }

    /// The solids making up the object with their linear albedos. Fails on an unknown shape
    /// (only possible for a hand-edited scene.json).
    pub fn parts(&self) -> anyhow::Result<Vec<(Solid, DVec3)>> {
        let center = self.center();
        let yaw = self.rotation_z_degrees.to_radians();
        let albedo = albedo_of_srgb8(self.rgb);
        let r = self.size;
        Ok(match self.shape.as_str() {
            "sphere" => vec![(Solid::Sphere { center, radius: r }, albedo)],
            "cube" => vec![(
                Solid::Cuboid {
                    center,
                    half: DVec3::splat(r / std::f64::consts::SQRT_2),
                    yaw,
                },
                albedo,
            )],
            "cylinder" => vec![(
                Solid::Cylinder {
                    center,
                    radius: r,
                    half_height: r,
                },
                albedo,
            )],
            "car" => {
                let car = self.car.ok_or_else(|| {
                    anyhow::anyhow!("object of shape `car` lacks its `car` dimensions")
                })?;
                let body = DVec3::from_array(car.body_half);
                let cabin = DVec3::from_array(car.cabin_half);
                let wheel = DVec3::from_array(car.wheel_half);
                let local = |v: DVec3| center + super::geometry::rotate_z(v, yaw);
                let mut parts = vec![
                    (
                        Solid::Cuboid {
                            center,
                            half: body,
                            yaw,
                        },
                        albedo,
                    ),
                    (
                        Solid::Cuboid {
                            center: local(DVec3::new(car.cabin_offset, 0.0, body.z + cabin.z)),
                            half: cabin,
                            yaw,
                        },
                        albedo,
                    ),
                ];
                // Wheels: their bottoms touch the ground (z = 0).
                let wheel_z = -center.z + wheel.z;
                for (sx, sy) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
                    parts.push((
                        Solid::Cuboid {
                            center: local(DVec3::new(
                                sx * 0.62 * body.x,
                                sy * (body.y - 0.6 * wheel.y),
                                wheel_z,
                            )),
                            half: wheel,
                            yaw,
                        },
                        DVec3::splat(TYRE_ALBEDO),
                    ));
                }
                parts
            }
            "chair" => {
                let design = self.chair.ok_or_else(|| {
                    anyhow::anyhow!("object of shape `chair` lacks its `chair` design")
                })?;
                design
                    .parts(center, self.rotation_z_degrees)
                    .iter()
                    .map(|part| (part.solid(), albedo))
                    .collect()
            }
            other => anyhow::bail!("unknown object shape `{other}`"),
        })
    }
}

/// A static box of the background (a building of preset `city`); mask id 0.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Building {
    pub center: [f64; 3],
    pub half: [f64; 3],
    /// Linear albedo.
    pub albedo: [f64; 3],
}

impl Building {
    pub fn solid(&self) -> Solid {
        Solid::Cuboid {
            center: DVec3::from_array(self.center),
            half: DVec3::from_array(self.half),
            yaw: 0.0,
        }
    }
}

/// The scene's one directional light.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Light {
    pub azimuth_degrees: f64,
    pub elevation_degrees: f64,
    /// Unit vector toward the light.
    pub direction: [f64; 3],
}

impl Light {
    pub fn new(azimuth_degrees: f64, elevation_degrees: f64) -> Light {
        Light {
            azimuth_degrees,
            elevation_degrees,
            direction: spherical(azimuth_degrees, elevation_degrees).to_array(),
        }
    }
}

/// How a camera was placed (for `scene.json`; the pose itself is in `transforms.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraPlacement {
    pub file_path: String,
    pub position: [f64; 3],
    pub look_at: [f64; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub azimuth_degrees: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elevation_degrees: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distance: Option<f64>,
}

/// One sampled scene: everything needed to render it.
#[derive(Clone, Debug)]
pub struct Scene {
    pub objects: Vec<Object>,
    pub buildings: Vec<Building>,
    pub ground: Ground,
    /// Whether rays that miss everything see the sky (else black; the ground fills clevr views).
    pub sky: bool,
    pub light: Light,
    pub cameras: Vec<CameraPlacement>,
    /// Preset `city`: x of each row of cars (cameras stand in front of them).
    pub rows: Vec<f64>,
    /// The room presets: the walls around the floor.
    pub room: Option<Room>,
}

/// Unit vector at azimuth (from +X toward +Y) and elevation (above the XY plane), degrees.
pub fn spherical(azimuth_degrees: f64, elevation_degrees: f64) -> DVec3 {
    let (sa, ca) = azimuth_degrees.to_radians().sin_cos();
    let (se, ce) = elevation_degrees.to_radians().sin_cos();
    DVec3::new(ce * ca, ce * sa, se)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clevr_shapes_rest_on_the_ground_with_the_contract_sizes() {
        for shape in ["sphere", "cube", "cylinder"] {
            for (size, &(_, r)) in CLEVR_SIZES.iter().enumerate() {
                let o = Object::clevr(shape, 1, size, 1.0, -2.0, 30.0);
                let parts = o.parts().unwrap();
                assert_eq!(parts.len(), 1);
                let solid = parts[0].0;
                // Lowest point at z = 0: just above is inside, just below is not.
                let c = o.center();
                let bottom = DVec3::new(c.x, c.y, 0.0);
                assert!(solid.contains(bottom + 1e-6 * DVec3::Z), "{shape}");
                assert!(!solid.contains(bottom - 1e-6 * DVec3::Z), "{shape}");
                match solid {
                    Solid::Sphere { radius, .. } => assert_eq!(radius, r),
                    Solid::Cylinder {
                        radius,
                        half_height,
                        ..
                    } => assert_eq!((radius, half_height), (r, r)),
                    Solid::Cuboid { half, .. } => {
                        assert!((half.x - r / 2f64.sqrt()).abs() < 1e-15)
                    }
                    other => panic!("{shape} made of {other:?}"),
                }
                assert!(solid.contains(c));
            }
        }
    }

    #[test]
    fn scene_objects_round_trip_through_json() {
        let o = Object::clevr("cube", 7, 1, 0.5, 0.25, 12.0);
        let text = serde_json::to_string(&o).unwrap();
        let back: Object = serde_json::from_str(&text).unwrap();
        assert_eq!(o, back);
        let bad = Object {
            shape: "torus".into(),
            ..o
        };
        assert!(format!("{:#}", bad.parts().unwrap_err()).contains("torus"));
    }

    #[test]
    fn light_direction_is_a_unit_vector_toward_the_light() {
        let l = Light::new(30.0, 55.0);
        let d = DVec3::from_array(l.direction);
        assert!((d.length() - 1.0).abs() < 1e-12);
        assert!((d.z - 55f64.to_radians().sin()).abs() < 1e-12);
        assert!(d.x > 0.0 && d.y > 0.0);
    }
}
