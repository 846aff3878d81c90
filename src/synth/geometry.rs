//! Ray–primitive intersection for the analytic tracer: spheres, boxes rotated about +Z, upright
//! cylinders, boxes and cylinders in any orientation (the parts of chairs), and the ground plane
//! z = 0. Everything is f64 and closed-form, so masks are exact.

use glam::{DMat3, DVec3};

/// Hits closer than this along a ray are ignored, so a shadow ray leaving a surface does not
/// find the surface it left.
pub const EPSILON: f64 = 1e-7;

/// A ray–surface hit: distance along the (unit) ray and the outward unit normal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f64,
    pub normal: DVec3,
}

/// A closed solid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Solid {
    Sphere {
        center: DVec3,
        radius: f64,
    },
    /// A box with half extents `half` along its own axes, rotated by `yaw` radians about +Z.
    Cuboid {
        center: DVec3,
        half: DVec3,
        yaw: f64,
    },
    /// A cylinder with its axis along +Z.
    Cylinder {
        center: DVec3,
        radius: f64,
        half_height: f64,
    },
    /// A box with half extents `half` along the columns of `rotation` (a rotation matrix: its
    /// columns are the box's axes in world space).
    OrientedBox {
        center: DVec3,
        half: DVec3,
        rotation: DMat3,
    },
    /// A cylinder whose axis is the third column of `rotation` (a rotation matrix).
    OrientedCylinder {
        center: DVec3,
        radius: f64,
        half_height: f64,
        rotation: DMat3,
    },
}

impl Solid {
    /// Centre of the solid.
    pub fn center(&self) -> DVec3 {
        match *self {
            Solid::Sphere { center, .. }
            | Solid::Cuboid { center, .. }
            | Solid::Cylinder { center, .. }
            | Solid::OrientedBox { center, .. }
            | Solid::OrientedCylinder { center, .. } => center,
        }
    }

    /// The same solid moved by `delta`.
    pub fn translated(&self, delta: DVec3) -> Solid {
        let mut s = *self;
        match &mut s {
            Solid::Sphere { center, .. }
            | Solid::Cuboid { center, .. }
            | Solid::Cylinder { center, .. }
            | Solid::OrientedBox { center, .. }
            | Solid::OrientedCylinder { center, .. } => *center += delta,
        }
        s
    }

    /// Radius of a sphere about `center()` that encloses the solid (for quick rejection).
    pub fn bounding_radius(&self) -> f64 {
        match *self {
            Solid::Sphere { radius, .. } => radius,
            Solid::Cuboid { half, .. } | Solid::OrientedBox { half, .. } => half.length(),
            Solid::Cylinder {
                radius,
                half_height,
                ..
            }
            | Solid::OrientedCylinder {
                radius,
                half_height,
                ..
            } => radius.hypot(half_height),
        }
    }

    /// Whether `p` lies strictly inside the solid.
    pub fn contains(&self, p: DVec3) -> bool {
        match *self {
            Solid::Sphere { center, radius } => (p - center).length_squared() < radius * radius,
            Solid::Cuboid { center, half, yaw } => {
                let local = rotate_z(p - center, -yaw);
                local.x.abs() < half.x && local.y.abs() < half.y && local.z.abs() < half.z
            }
            Solid::Cylinder {
                center,
                radius,
                half_height,
            } => {
                let d = p - center;
                d.x * d.x + d.y * d.y < radius * radius && d.z.abs() < half_height
            }
            Solid::OrientedBox {
                center,
                half,
                rotation,
            } => {
                let d = p - center;
                (0..3).all(|axis| d.dot(rotation.col(axis)).abs() < half[axis])
            }
            Solid::OrientedCylinder {
                center,
                radius,
                half_height,
                rotation,
            } => {
                let d = p - center;
                let along = d.dot(rotation.z_axis);
                (d - along * rotation.z_axis).length_squared() < radius * radius
                    && along.abs() < half_height
            }
        }
    }

    /// Nearest hit of the ray `origin + t·dir` (unit `dir`) with EPSILON < t < `t_max`.
    pub fn intersect(&self, origin: DVec3, dir: DVec3, t_max: f64) -> Option<Hit> {
        // Quick rejection against the bounding sphere.
        let to_center = self.center() - origin;
        let along = to_center.dot(dir);
        let r = self.bounding_radius();
        let miss2 = to_center.length_squared() - along * along;
        if miss2 > r * r || along + r < EPSILON || along - r > t_max {
            return None;
        }
        match *self {
            Solid::Sphere { center, radius } => {
                let disc = radius * radius - miss2;
                let root = disc.sqrt();
                [along - root, along + root]
                    .into_iter()
                    .find(|&t| t > EPSILON && t < t_max)
                    .map(|t| Hit {
                        t,
                        normal: ((origin + t * dir - center) / radius).normalize(),
                    })
            }
            Solid::Cuboid { center, half, yaw } => {
                let o = rotate_z(origin - center, -yaw);
                let d = rotate_z(dir, -yaw);
                box_hit(o, d, half, t_max).map(|h| Hit {
                    t: h.t,
                    normal: rotate_z(h.normal, yaw),
                })
            }
            Solid::Cylinder {
                center,
                radius,
                half_height,
            } => cylinder_hit(origin - center, dir, radius, half_height, t_max),
            Solid::OrientedBox {
                center,
                half,
                rotation,
            } => {
                // The frame is orthonormal: distances along the ray are the same in it.
                let to_local = rotation.transpose();
                box_hit(to_local * (origin - center), to_local * dir, half, t_max).map(|h| Hit {
                    t: h.t,
                    normal: (rotation * h.normal).normalize(),
                })
            }
            Solid::OrientedCylinder {
                center,
                radius,
                half_height,
                rotation,
            } => {
                let to_local = rotation.transpose();
                cylinder_hit(
                    to_local * (origin - center),
                    to_local * dir,
                    radius,
                    half_height,
                    t_max,
                )
                .map(|h| Hit {
                    t: h.t,
                    normal: (rotation * h.normal).normalize(),
                })
            }
        }
    }
}

/// Nearest hit with EPSILON < t < `t_max` of the ray `o + t·d` (box frame) with the box of half
/// extents `half` centred at the origin; the normal in the box's frame.
fn box_hit(o: DVec3, d: DVec3, half: DVec3, t_max: f64) -> Option<Hit> {
    let (mut t_near, mut t_far) = (f64::NEG_INFINITY, f64::INFINITY);
    let (mut near_axis, mut far_axis) = (0usize, 0usize);
    for axis in 0..3 {
        let (oa, da, ha) = (o[axis], d[axis], half[axis]);
        if da.abs() < 1e-300 {
            if oa.abs() > ha {
                return None;
            }
            continue;
        }
        let (mut t0, mut t1) = ((-ha - oa) / da, (ha - oa) / da);
        if t0 > t1 {
            std::mem::swap(&mut t0, &mut t1);
        }
        if t0 > t_near {
            t_near = t0;
            near_axis = axis;
        }
        if t1 < t_far {
            t_far = t1;
            far_axis = axis;
        }
    }
    if t_near > t_far {
        return None;
    }
    let (t, axis) = if t_near > EPSILON {
        (t_near, near_axis)
    } else {
        (t_far, far_axis)
    };
    if t <= EPSILON || t >= t_max {
        return None;
    }
    let mut n = DVec3::ZERO;
    n[axis] = (o[axis] + t * d[axis]).signum();
    Some(Hit { t, normal: n })
}

/// Nearest hit with EPSILON < t < `t_max` of the ray `o + t·d` (cylinder frame) with the
/// cylinder of axis +Z centred at the origin; the normal in the cylinder's frame.
fn cylinder_hit(o: DVec3, dir: DVec3, radius: f64, half_height: f64, t_max: f64) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    let mut consider = |t: f64, normal: DVec3| {
        if t > EPSILON && t < t_max && best.is_none_or(|b| t < b.t) {
            best = Some(Hit { t, normal });
        }
    };
    // Side: (ox + t dx)² + (oy + t dy)² = r².
    let a = dir.x * dir.x + dir.y * dir.y;
    if a > 1e-300 {
        let b = o.x * dir.x + o.y * dir.y;
        let c = o.x * o.x + o.y * o.y - radius * radius;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let root = disc.sqrt();
            for t in [(-b - root) / a, (-b + root) / a] {
                let p = o + t * dir;
                if p.z.abs() <= half_height {
                    consider(t, DVec3::new(p.x, p.y, 0.0) / radius);
                }
            }
        }
    }
    // Caps.
    if dir.z.abs() > 1e-300 {
        for (z, nz) in [(half_height, 1.0), (-half_height, -1.0)] {
            let t = (z - o.z) / dir.z;
            let p = o + t * dir;
            if p.x * p.x + p.y * p.y <= radius * radius {
                consider(t, DVec3::new(0.0, 0.0, nz));
            }
        }
    }
    best.map(|h| Hit {
        t: h.t,
        normal: h.normal.normalize(),
    })
}

/// `v` rotated by `angle` radians about +Z.
pub fn rotate_z(v: DVec3, angle: f64) -> DVec3 {
    let (s, c) = angle.sin_cos();
    DVec3::new(c * v.x - s * v.y, s * v.x + c * v.y, v.z)
}

/// Distance along the ray to the ground plane z = 0, if the ray goes down to it.
pub fn ground_hit(origin: DVec3, dir: DVec3) -> Option<f64> {
    if dir.z < 0.0 && origin.z > 0.0 {
        Some(-origin.z / dir.z)
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shapes() -> Vec<Solid> {
        vec![
            Solid::Sphere {
                center: DVec3::new(0.3, -0.2, 0.7),
                radius: 0.7,
            },
            Solid::Cuboid {
                center: DVec3::new(0.3, -0.2, 0.5),
                half: DVec3::new(0.5, 0.4, 0.5),
                yaw: 0.6,
            },
            Solid::Cylinder {
                center: DVec3::new(0.3, -0.2, 0.35),
                radius: 0.35,
                half_height: 0.35,
            },
            Solid::OrientedBox {
                center: DVec3::new(0.3, -0.2, 0.5),
                half: DVec3::new(0.5, 0.3, 0.4),
                rotation: DMat3::from_euler(glam::EulerRot::ZYX, 0.7, -0.4, 0.3),
            },
            Solid::OrientedCylinder {
                center: DVec3::new(0.3, -0.2, 0.5),
                radius: 0.3,
                half_height: 0.6,
                rotation: DMat3::from_euler(glam::EulerRot::ZYX, -1.1, 0.5, 0.2),
            },
        ]
    }

    /// Every hit lies on the surface: just outside along the normal is outside the solid, just
    /// inside is inside, and rays aimed at the centre always hit with a normal facing the ray.
    #[test]
    fn hits_lie_on_the_surface_with_outward_normals() {
        let mut state = 12345u64;
        let mut uniform = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for solid in shapes() {
            for _ in 0..2000 {
                let origin = DVec3::new(
                    uniform() * 20.0 - 10.0,
                    uniform() * 20.0 - 10.0,
                    uniform() * 10.0 + 2.0,
                );
                let jitter = DVec3::new(uniform() - 0.5, uniform() - 0.5, uniform() - 0.5) * 0.3;
                let dir = (solid.center() + jitter - origin).normalize();
                let hit = solid
                    .intersect(origin, dir, f64::INFINITY)
                    .expect("a ray at the centre hits");
                let p = origin + hit.t * dir;
                assert!((hit.normal.length() - 1.0).abs() < 1e-9);
                assert!(hit.normal.dot(dir) < 0.0, "{solid:?}");
                assert!(!solid.contains(p + 1e-6 * hit.normal), "{solid:?}");
                assert!(solid.contains(p - 1e-6 * hit.normal), "{solid:?}");
                assert!(!solid.contains(origin + 0.999 * hit.t * dir));
                // A shorter ray stops before the surface.
                assert!(solid.intersect(origin, dir, 0.99 * hit.t).is_none());
            }
        }
    }

    #[test]
    fn rays_that_pass_by_miss() {
        for solid in shapes() {
            let origin = DVec3::new(-10.0, 0.0, 5.0);
            assert!(solid.intersect(origin, DVec3::Z, f64::INFINITY).is_none());
            assert!(solid
                .intersect(origin, DVec3::new(-1.0, 0.0, 0.0), f64::INFINITY)
                .is_none());
        }
    }

    #[test]
    fn ground_is_hit_only_from_above_going_down() {
        let o = DVec3::new(0.0, 0.0, 2.0);
        let d = DVec3::new(1.0, 0.0, -1.0).normalize();
        let t = ground_hit(o, d).unwrap();
        assert!((o + t * d).z.abs() < 1e-12);
        assert!(ground_hit(o, DVec3::Z).is_none());
    }

    #[test]
    fn rotation_is_about_z() {
        let v = rotate_z(DVec3::X, std::f64::consts::FRAC_PI_2);
        assert!((v - DVec3::Y).length() < 1e-15);
    }
}
