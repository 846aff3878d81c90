//! The room presets (`room-chair`, `room-diverse`): procedural chairs built from boxes and
//! cylinders, procedural floor textures, and the room's walls.
//!
//! A chair is a [`ChairDesign`]: seat (box or disc), a base (four legs, square or round,
//! straight or splayed, with optional stretchers; or a pedestal on a disc or a cross), a back
//! (a panel, vertical slats or horizontal rails between two posts, tilted back), and optional
//! arms. [`ChairDesign::parts`] turns it into solids the analytic tracer intersects exactly;
//! the Blender engine builds the same solids as meshes. `room-chair` uses one design
//! ([`ChairDesign::room_chair`]); `room-diverse` a family of [`DIVERSE_DESIGNS`] designs, design
//! i drawn from its own seed ([`ChairDesign::diverse`]). Floors are [`FloorTexture`]s, functions
//! of the floor point: 3 fixed ones for `room-chair` ([`room_chair_floor`]), a family of
//! [`DIVERSE_FLOORS`] for `room-diverse` ([`diverse_floor`]).

use super::geometry::Solid;
use super::hash::mix64;
use super::scene::Building;
use super::shading::{srgb_to_linear, value_noise};
use glam::{DMat3, DQuat, DVec3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

/// Chair designs of `room-diverse` (uORF's Room-Diverse draws from 1,200 ShapeNet chairs).
pub const DIVERSE_DESIGNS: u64 = 1200;
/// Floor textures of `room-diverse` (as uORF's Room-Diverse).
pub const DIVERSE_FLOORS: usize = 50;
/// Floor textures of `room-chair` (as uORF's Room-Chair).
pub const ROOM_CHAIR_FLOORS: usize = 3;

/// Half the side of the square room: walls stand at x = ±ROOM_HALF_EXTENT, y = ±ROOM_HALF_EXTENT.
pub const ROOM_HALF_EXTENT: f64 = 8.0;
/// Height of the walls (no ceiling).
pub const WALL_HEIGHT: f64 = 6.0;
/// Thickness of the walls (outside the room).
pub const WALL_THICKNESS: f64 = 0.2;

/// The room: four walls around the floor, background (mask id 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Room {
    pub half_extent: f64,
    pub wall_height: f64,
    pub wall_thickness: f64,
    /// Linear albedo of the walls.
    pub wall_albedo: [f64; 3],
}

impl Room {
    pub fn new(wall_albedo: [f64; 3]) -> Room {
        Room {
            half_extent: ROOM_HALF_EXTENT,
            wall_height: WALL_HEIGHT,
            wall_thickness: WALL_THICKNESS,
            wall_albedo,
        }
    }

    /// The four walls as boxes standing on the floor just outside [−R, R]²; they overlap at
    /// the corners, so the room is closed.
    pub fn walls(&self) -> Vec<Building> {
        let (r, t, h) = (self.half_extent, self.wall_thickness, self.wall_height);
        let mut walls = Vec::with_capacity(4);
        for side in [-1.0, 1.0] {
            walls.push(Building {
                center: [side * (r + 0.5 * t), 0.0, 0.5 * h],
                half: [0.5 * t, r + t, 0.5 * h],
                albedo: self.wall_albedo,
            });
            walls.push(Building {
                center: [0.0, side * (r + 0.5 * t), 0.5 * h],
                half: [r + t, 0.5 * t, 0.5 * h],
                albedo: self.wall_albedo,
            });
        }
        walls
    }
}

/// The seat's outline.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SeatShape {
    /// A box, `seat_width` × `seat_depth`.
    Box,
    /// A disc of diameter min(`seat_width`, `seat_depth`).
    Round,
}

/// What holds the seat up.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ChairBase {
    /// Four legs under the seat's corners.
    FourLegs,
    /// A central column on a flat disc.
    PedestalDisc,
    /// A central column on a cross of two bars.
    PedestalCross,
}

/// The cross-section of the legs (and of the pedestal's column: always round).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LegSection {
    Square,
    Round,
}

/// Bars between the four legs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stretchers {
    None,
    /// Front-to-back bars on both sides.
    Sides,
    /// Side bars and a crossbar between them.
    H,
    /// Bars on all four sides.
    Box,
}

/// The backrest.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BackStyle {
    /// A solid panel over the top `back_panel_fraction` of the back (on two posts below it).
    Panel,
    /// `back_count` vertical slats between two posts under a top rail.
    Slats,
    /// `back_count` horizontal rails between two posts.
    Rails,
}

/// One chair's geometry. Lengths are world units (the seat is about a unit wide), angles
/// degrees. The chair's frame: +X forward (where a sitter faces), +Y to its left, +Z up, origin
/// on the floor under the seat's centre.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChairDesign {
    /// Index in the `room-diverse` family; absent for the `room-chair` design.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub design_index: Option<u64>,
    pub seat_shape: SeatShape,
    /// Extent along Y.
    pub seat_width: f64,
    /// Extent along X.
    pub seat_depth: f64,
    /// Height of the seat's top above the floor.
    pub seat_height: f64,
    pub seat_thickness: f64,
    pub base: ChairBase,
    pub leg_section: LegSection,
    /// Side of a square leg, diameter of a round leg or of the pedestal's column.
    pub leg_thickness: f64,
    /// How far the legs' tops sit inside the seat's edge.
    pub leg_inset: f64,
    /// Outward tilt of the legs from vertical (0: straight).
    pub leg_splay_degrees: f64,
    pub stretchers: Stretchers,
    /// Height of the stretchers as a share of the legs' height.
    pub stretcher_height: f64,
    /// Radius of the pedestal's disc or half-length of its cross bars.
    pub pedestal_radius: f64,
    pub back_style: BackStyle,
    /// Height of the back above the seat's top (along the tilted back).
    pub back_height: f64,
    /// Width of the back as a share of the seat's width.
    pub back_width: f64,
    pub back_thickness: f64,
    /// How far the back leans back from vertical.
    pub back_tilt_degrees: f64,
    /// Panel: share of the back's height the panel covers, from the top (1: a full panel).
    pub back_panel_fraction: f64,
    /// Slats or rails: how many.
    pub back_count: u32,
    pub arms: bool,
    /// Height of the arms' top above the seat's top.
    pub arm_height: f64,
    pub arm_width: f64,
}

/// The shape of one part of a chair.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PartShape {
    /// Half extents along the part's axes.
    Box { half: DVec3 },
    /// Axis along the part's third axis.
    Cylinder { radius: f64, half_height: f64 },
}

/// One part of a chair: a box or a cylinder with its centre and axes (the columns of
/// `rotation`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChairPart {
    pub shape: PartShape,
    pub center: DVec3,
    pub rotation: DMat3,
}

impl ChairPart {
    /// The part as a solid of the tracer.
    pub fn solid(&self) -> Solid {
        match self.shape {
            PartShape::Box { half } => Solid::OrientedBox {
                center: self.center,
                half,
                rotation: self.rotation,
            },
            PartShape::Cylinder {
                radius,
                half_height,
            } => Solid::OrientedCylinder {
                center: self.center,
                radius,
                half_height,
                rotation: self.rotation,
            },
        }
    }

    /// The part turned by `yaw` radians about +Z and then moved by `offset`.
    pub fn placed(&self, yaw: f64, offset: DVec3) -> ChairPart {
        let turn = DMat3::from_rotation_z(yaw);
        ChairPart {
            shape: self.shape,
            center: offset + turn * self.center,
            rotation: turn * self.rotation,
        }
    }

    /// The corners of a box enclosing the part.
    pub fn corners(&self) -> [DVec3; 8] {
        let half = match self.shape {
            PartShape::Box { half } => half,
            PartShape::Cylinder {
                radius,
                half_height,
            } => DVec3::new(radius, radius, half_height),
        };
        let mut out = [DVec3::ZERO; 8];
        for (k, corner) in out.iter_mut().enumerate() {
            let s = DVec3::new(
                if k & 1 == 0 { -1.0 } else { 1.0 },
                if k & 2 == 0 { -1.0 } else { 1.0 },
                if k & 4 == 0 { -1.0 } else { 1.0 },
            );
            *corner = self.center + self.rotation * (s * half);
        }
        out
    }
}

/// Collects the parts of a chair (in the chair's frame: origin on the floor).
#[derive(Default)]
struct Parts(Vec<ChairPart>);

impl Parts {
    fn cuboid(&mut self, center: DVec3, half: DVec3, rotation: DMat3) {
        self.0.push(ChairPart {
            shape: PartShape::Box { half },
            center,
            rotation,
        });
    }

    fn upright_box(&mut self, center: DVec3, half: DVec3) {
        self.cuboid(center, half, DMat3::IDENTITY);
    }

    fn upright_cylinder(&mut self, center: DVec3, radius: f64, half_height: f64) {
        self.0.push(ChairPart {
            shape: PartShape::Cylinder {
                radius,
                half_height,
            },
            center,
            rotation: DMat3::IDENTITY,
        });
    }

    /// A bar from `a` to `b`, lengthened by `extend` at both ends, square (side `thickness`)
    /// or round (diameter `thickness`); its cross-section is turned from the upright one by
    /// the shortest rotation.
    fn bar(&mut self, a: DVec3, b: DVec3, thickness: f64, section: LegSection, extend: f64) {
        let axis = (b - a).normalize();
        let rotation = DMat3::from_quat(DQuat::from_rotation_arc(DVec3::Z, axis));
        let half_height = 0.5 * (b - a).length() + extend;
        let shape = match section {
            LegSection::Square => PartShape::Box {
                half: DVec3::new(0.5 * thickness, 0.5 * thickness, half_height),
            },
            LegSection::Round => PartShape::Cylinder {
                radius: 0.5 * thickness,
                half_height,
            },
        };
        self.0.push(ChairPart {
            shape,
            center: 0.5 * (a + b),
            rotation,
        });
    }
}

/// The frame of a chair's back: a pivot on the seat's rear edge and the back's tilt. In it, a
/// runs forward through the back, b across it and c up it.
struct BackFrame {
    pivot: DVec3,
    rotation: DMat3,
}

impl BackFrame {
    /// A box of the back centred across at `b`, from `c0` to `c1` up the back, `half_width`
    /// across and `half_thickness` through.
    fn piece(&self, p: &mut Parts, b: f64, c0: f64, c1: f64, half_width: f64, half_thickness: f64) {
        let local = DVec3::new(0.0, b, 0.5 * (c0 + c1));
        p.cuboid(
            self.pivot + self.rotation * local,
            DVec3::new(half_thickness, half_width, 0.5 * (c1 - c0)),
            self.rotation,
        );
    }
}

/// `x` rounded to a multiple of `step`.
fn quantise(x: f64, step: f64) -> f64 {
    (x / step).round() * step
}

impl ChairDesign {
    /// The one design of `room-chair`: a dining chair with four straight square legs and a
    /// back of four vertical slats.
    pub fn room_chair() -> ChairDesign {
        ChairDesign {
            design_index: None,
            seat_shape: SeatShape::Box,
            seat_width: 1.0,
            seat_depth: 0.95,
            seat_height: 0.9,
            seat_thickness: 0.1,
            base: ChairBase::FourLegs,
            leg_section: LegSection::Square,
            leg_thickness: 0.09,
            leg_inset: 0.03,
            leg_splay_degrees: 0.0,
            stretchers: Stretchers::Sides,
            stretcher_height: 0.3,
            pedestal_radius: 0.0,
            back_style: BackStyle::Slats,
            back_height: 1.0,
            back_width: 1.0,
            back_thickness: 0.08,
            back_tilt_degrees: 8.0,
            back_panel_fraction: 0.0,
            back_count: 4,
            arms: false,
            arm_height: 0.0,
            arm_width: 0.0,
        }
    }

    /// Design `index` of the `room-diverse` family, drawn from its own seed; lengths are
    /// multiples of 0.01, angles of 0.5°.
    pub fn diverse(index: u64) -> ChairDesign {
        let mut rng = StdRng::seed_from_u64(mix64(0x4348_4149_5200_0001 ^ mix64(index)));
        let mut length = |lo: f64, hi: f64| quantise(rng.random_range(lo..=hi), 0.01);
        let seat_width = length(0.8, 1.25);
        let seat_depth = length(0.75, 1.15);
        let seat_height = length(0.7, 1.05);
        let seat_thickness = length(0.05, 0.16);
        let leg_thickness = length(0.05, 0.12);
        let leg_inset = length(0.0, 0.08);
        let back_height = length(0.55, 1.25);
        let back_thickness = length(0.05, 0.12);
        let stretcher_height = length(0.15, 0.45);
        let pedestal_radius = length(0.3, 0.5);
        let arm_height = length(0.22, 0.4);
        let arm_width = length(0.06, 0.12);
        let back_width = length(0.75, 1.0);
        let back_panel_fraction = length(0.35, 1.0);
        let mut angle = |lo: f64, hi: f64| quantise(rng.random_range(lo..=hi), 0.5);
        let splay = angle(3.0, 10.0);
        let tilt = angle(0.0, 16.0);
        let seat_shape = if rng.random_bool(0.25) {
            SeatShape::Round
        } else {
            SeatShape::Box
        };
        let base = match rng.random_range(0..10) {
            0 => ChairBase::PedestalDisc,
            1 => ChairBase::PedestalCross,
            _ => ChairBase::FourLegs,
        };
        let leg_section = if rng.random_bool(0.4) {
            LegSection::Round
        } else {
            LegSection::Square
        };
        let splayed = base == ChairBase::FourLegs && rng.random_bool(0.35);
        let stretchers = if base != ChairBase::FourLegs || splayed {
            Stretchers::None
        } else {
            [
                Stretchers::None,
                Stretchers::Sides,
                Stretchers::H,
                Stretchers::Box,
            ][rng.random_range(0..4)]
        };
        let back_style =
            [BackStyle::Panel, BackStyle::Slats, BackStyle::Rails][rng.random_range(0..3)];
        let back_count = match back_style {
            BackStyle::Panel => 1,
            BackStyle::Slats => rng.random_range(2..=6),
            BackStyle::Rails => rng.random_range(2..=5),
        };
        let arms = rng.random_bool(0.3);
        ChairDesign {
            design_index: Some(index),
            seat_shape,
            seat_width,
            seat_depth,
            seat_height,
            seat_thickness,
            base,
            leg_section,
            leg_thickness,
            leg_inset,
            leg_splay_degrees: if splayed { splay } else { 0.0 },
            stretchers,
            stretcher_height: if stretchers == Stretchers::None {
                0.0
            } else {
                stretcher_height
            },
            pedestal_radius: if base == ChairBase::FourLegs {
                0.0
            } else {
                pedestal_radius
            },
            back_style,
            back_height,
            back_width,
            back_thickness,
            back_tilt_degrees: tilt,
            back_panel_fraction: if back_style == BackStyle::Panel {
                back_panel_fraction
            } else {
                0.0
            },
            back_count,
            arms,
            arm_height: if arms { arm_height } else { 0.0 },
            arm_width: if arms { arm_width } else { 0.0 },
        }
    }

    /// Half extents of the seat along X and Y (a round seat: its radius twice).
    fn seat_half(&self) -> (f64, f64) {
        match self.seat_shape {
            SeatShape::Box => (0.5 * self.seat_depth, 0.5 * self.seat_width),
            SeatShape::Round => {
                let r = 0.5 * self.seat_width.min(self.seat_depth);
                (r, r)
            }
        }
    }

    /// Height of the seat's centre above the floor: the chair's `position` is this point
    /// above its footprint's centre, inside the seat.
    pub fn seat_center_height(&self) -> f64 {
        self.seat_height - 0.5 * self.seat_thickness
    }

    /// The parts in the chair's frame (origin on the floor under the seat's centre).
    pub fn local_parts(&self) -> Vec<ChairPart> {
        let mut p = Parts::default();
        let h = self.seat_height;
        let ts = self.seat_thickness;
        let under = h - ts;
        let (hx, hy) = self.seat_half();
        let lt = self.leg_thickness;
        let seat_center = DVec3::new(0.0, 0.0, h - 0.5 * ts);
        match self.seat_shape {
            SeatShape::Box => p.upright_box(seat_center, DVec3::new(hx, hy, 0.5 * ts)),
            SeatShape::Round => p.upright_cylinder(seat_center, hx, 0.5 * ts),
        }

        // The base.
        match self.base {
            ChairBase::FourLegs => {
                let (lx, ly) = match self.seat_shape {
                    SeatShape::Box => (
                        hx - self.leg_inset - 0.5 * lt,
                        hy - self.leg_inset - 0.5 * lt,
                    ),
                    SeatShape::Round => {
                        let a = (hx - self.leg_inset - 0.71 * lt) / std::f64::consts::SQRT_2;
                        (a, a)
                    }
                };
                let splay = self.leg_splay_degrees.to_radians();
                // A splayed leg runs from under the seat out along the diagonal to the floor,
                // lengthened so that its tilted ends sink into the seat and the floor.
                let reach = under * splay.tan();
                let extend = 0.5 * lt * splay.sin();
                for (sx, sy) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
                    let top = DVec3::new(sx * lx, sy * ly, under);
                    let out = DVec3::new(sx, sy, 0.0).normalize() * reach;
                    let foot = DVec3::new(top.x, top.y, 0.0) + out;
                    if splay == 0.0 {
                        match self.leg_section {
                            LegSection::Square => p.upright_box(
                                DVec3::new(top.x, top.y, 0.5 * under),
                                DVec3::new(0.5 * lt, 0.5 * lt, 0.5 * under),
                            ),
                            LegSection::Round => p.upright_cylinder(
                                DVec3::new(top.x, top.y, 0.5 * under),
                                0.5 * lt,
                                0.5 * under,
                            ),
                        }
                    } else {
                        p.bar(foot, top, lt, self.leg_section, extend);
                    }
                }
                let st = 0.6 * lt;
                let z = self.stretcher_height * under;
                let along_x = |p: &mut Parts, y: f64| {
                    p.upright_box(DVec3::new(0.0, y, z), DVec3::new(lx, 0.5 * st, 0.5 * st))
                };
                let along_y = |p: &mut Parts, x: f64| {
                    p.upright_box(DVec3::new(x, 0.0, z), DVec3::new(0.5 * st, ly, 0.5 * st))
                };
                match self.stretchers {
                    Stretchers::None => {}
                    Stretchers::Sides => {
                        along_x(&mut p, ly);
                        along_x(&mut p, -ly);
                    }
                    Stretchers::H => {
                        along_x(&mut p, ly);
                        along_x(&mut p, -ly);
                        along_y(&mut p, 0.0);
                    }
                    Stretchers::Box => {
                        along_x(&mut p, ly);
                        along_x(&mut p, -ly);
                        along_y(&mut p, lx);
                        along_y(&mut p, -lx);
                    }
                }
            }
            ChairBase::PedestalDisc | ChairBase::PedestalCross => {
                let foot_height = 0.06;
                let r = self.pedestal_radius;
                if self.base == ChairBase::PedestalDisc {
                    p.upright_cylinder(
                        DVec3::new(0.0, 0.0, 0.5 * foot_height),
                        r,
                        0.5 * foot_height,
                    );
                } else {
                    for angle in [45f64, 135.0] {
                        p.cuboid(
                            DVec3::new(0.0, 0.0, 0.5 * foot_height),
                            DVec3::new(r, 0.05, 0.5 * foot_height),
                            DMat3::from_rotation_z(angle.to_radians()),
                        );
                    }
                }
                let column = 0.5 * (under - foot_height);
                p.upright_cylinder(
                    DVec3::new(0.0, 0.0, foot_height + column),
                    (0.5 * lt).max(0.04),
                    column,
                );
            }
        }

        // The back: built in its own frame (a: forward through the back, b: across, c: up the
        // back) about a pivot on the seat's rear edge, then tilted back about +Y.
        let tb = self.back_thickness;
        let tilt = self.back_tilt_degrees.to_radians();
        let (back_x, back_half_width) = match self.seat_shape {
            SeatShape::Box => (-hx + 0.5 * tb, 0.5 * self.back_width * self.seat_width),
            // On a disc the back stands on a chord, its corners near the rim.
            SeatShape::Round => (-0.7 * hx, 0.7 * hx * self.back_width),
        };
        let pivot = DVec3::new(back_x, 0.0, h);
        let back_rotation = DMat3::from_rotation_y(-tilt);
        // Parts reach down into the seat, so no gap opens under a tilted back.
        let sink = 0.5 * ts;
        let hb = self.back_height;
        let back = BackFrame {
            pivot,
            rotation: back_rotation,
        };
        let post = lt.max(0.05).min(0.3 * back_half_width);
        let post_b = back_half_width - 0.5 * post;
        let posts = |p: &mut Parts, top: f64| {
            for side in [-1.0, 1.0] {
                back.piece(p, side * post_b, -sink, top, 0.5 * post, 0.5 * tb);
            }
        };
        match self.back_style {
            BackStyle::Panel => {
                let bottom = hb * (1.0 - self.back_panel_fraction);
                if self.back_panel_fraction >= 0.995 {
                    back.piece(&mut p, 0.0, -sink, hb, back_half_width, 0.5 * tb);
                } else {
                    posts(&mut p, bottom + 0.5 * tb);
                    back.piece(&mut p, 0.0, bottom, hb, back_half_width, 0.5 * tb);
                }
            }
            BackStyle::Slats => {
                let rail = (0.12 * hb).clamp(0.06, 0.16);
                posts(&mut p, hb);
                back.piece(&mut p, 0.0, hb - rail, hb, back_half_width - post, 0.5 * tb);
                let span = 2.0 * (back_half_width - post);
                let n = self.back_count.max(1) as f64;
                for k in 0..self.back_count {
                    let b = -0.5 * span + (k as f64 + 0.5) * span / n;
                    let half_width = 0.25 * span / n;
                    back.piece(&mut p, b, -sink, hb - rail, half_width, 0.3 * tb);
                }
            }
            BackStyle::Rails => {
                posts(&mut p, hb);
                let n = self.back_count.max(1) as f64;
                // Rails fill the upper 60 % of the back, the top one at the top.
                let pitch = 0.6 * hb / n;
                let rail = (0.55 * pitch).min(0.16);
                for k in 0..self.back_count {
                    let top = hb - k as f64 * pitch;
                    back.piece(
                        &mut p,
                        0.0,
                        top - rail,
                        top,
                        back_half_width - post,
                        0.35 * tb,
                    );
                }
            }
        }

        // Arms: a bar on each side from the back to the seat's front, on a post at the front.
        if self.arms {
            let aw = self.arm_width;
            let z_top = h + self.arm_height;
            let arm_thickness = 0.06;
            let front = 0.92 * hx;
            // The tilted back has moved back at the arms' height.
            let rear = back_x - self.arm_height * tilt.tan() - 0.5 * tb;
            let y = match self.seat_shape {
                SeatShape::Box => hy - 0.5 * aw,
                SeatShape::Round => 0.85 * hy - 0.5 * aw,
            };
            for side in [-1.0, 1.0] {
                p.upright_box(
                    DVec3::new(0.5 * (front + rear), side * y, z_top - 0.5 * arm_thickness),
                    DVec3::new(0.5 * (front - rear), 0.5 * aw, 0.5 * arm_thickness),
                );
                let post_height = self.arm_height + 0.5 * ts;
                p.upright_box(
                    DVec3::new(front - 0.5 * aw, side * y, z_top - 0.5 * post_height),
                    DVec3::new(0.5 * aw, 0.5 * aw, 0.5 * post_height),
                );
            }
        }
        p.0
    }

    /// The parts of the chair whose seat centre is at `position`, turned by `yaw_degrees`
    /// about +Z.
    pub fn parts(&self, position: DVec3, yaw_degrees: f64) -> Vec<ChairPart> {
        let origin = position - DVec3::Z * self.seat_center_height();
        self.local_parts()
            .iter()
            .map(|part| part.placed(yaw_degrees.to_radians(), origin))
            .collect()
    }

    /// Radius about the footprint's centre of a circle enclosing the chair's footprint, and
    /// the height of its top.
    pub fn extent(&self) -> (f64, f64) {
        let corners = self
            .local_parts()
            .iter()
            .flat_map(|p| p.corners())
            .collect::<Vec<_>>();
        let radius = corners.iter().map(|c| c.x.hypot(c.y)).fold(0.0, f64::max);
        let top = corners.iter().map(|c| c.z).fold(0.0, f64::max);
        (radius, top)
    }

    /// The geometry quantised to `step` (lengths) and `step`·100 degrees (angles), for telling
    /// designs apart.
    pub fn geometry_key(&self, step: f64) -> Vec<i64> {
        let q = |x: f64| (x / step).round() as i64;
        let qa = |x: f64| (x / (100.0 * step)).round() as i64;
        let (hx, hy) = self.seat_half();
        vec![
            self.seat_shape as i64,
            q(hx),
            q(hy),
            q(self.seat_height),
            q(self.seat_thickness),
            self.base as i64,
            self.leg_section as i64,
            q(self.leg_thickness),
            q(self.leg_inset),
            qa(self.leg_splay_degrees),
            self.stretchers as i64,
            q(self.stretcher_height),
            q(self.pedestal_radius),
            self.back_style as i64,
            q(self.back_height),
            q(self.back_width),
            q(self.back_thickness),
            qa(self.back_tilt_degrees),
            q(self.back_panel_fraction),
            self.back_count as i64,
            self.arms as i64,
            q(self.arm_height),
            q(self.arm_width),
        ]
    }
}

/// The pattern of a floor texture.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FloorPattern {
    /// Boards of width `scale` and length `scale`·`length_ratio` in staggered rows, each its own
    /// shade between `albedo_a` and `albedo_b`, with a grain along the boards.
    Planks,
    /// Square blocks of side `scale`, each of three strips, alternately along u and v.
    Parquet,
    /// Square tiles of side `scale` with grout joints, each its own shade.
    Tiles,
    /// A checkerboard of squares of side `scale`.
    Checker,
    /// Bands of width `scale`, alternately `albedo_a` and `albedo_b` (a striped carpet).
    Stripes,
    /// Mottled stone: three octaves of value noise of feature size `scale` between the two
    /// albedos.
    Stone,
}

/// The patterns, in the order `room-diverse` cycles through them.
pub const FLOOR_PATTERNS: [FloorPattern; 6] = [
    FloorPattern::Planks,
    FloorPattern::Parquet,
    FloorPattern::Tiles,
    FloorPattern::Checker,
    FloorPattern::Stripes,
    FloorPattern::Stone,
];

/// A procedural floor texture: linear albedo as a function of the floor point.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FloorTexture {
    /// `room-chair` or `room-diverse`.
    pub family: String,
    /// Index in its family.
    pub index: usize,
    pub pattern: FloorPattern,
    /// Size of the pattern's element (board width, block, tile, square, band, feature).
    pub scale: f64,
    /// Planks: board length over width.
    pub length_ratio: f64,
    /// The pattern's axes u, v are the floor's x, y turned by this angle.
    pub rotation_degrees: f64,
    /// Linear albedos the pattern's elements lie between.
    pub albedo_a: [f64; 3],
    pub albedo_b: [f64; 3],
    /// Linear albedo of the joints (planks, parquet, tiles).
    pub joint_albedo: [f64; 3],
    /// Width of the joints.
    pub joint_width: f64,
    /// Amplitude of the fine noise (grain, speckle) as a share of the albedo.
    pub grain: f64,
    pub seed: u64,
}

/// Uniform in [0, 1) from a seed and a cell.
fn cell_hash(seed: u64, i: i64, j: i64) -> f64 {
    let h = mix64(seed ^ mix64((i as u64) ^ (j as u64).rotate_left(32)));
    (h >> 11) as f64 / (1u64 << 53) as f64
}

fn lerp3(a: [f64; 3], b: [f64; 3], t: f64) -> DVec3 {
    DVec3::from_array(a).lerp(DVec3::from_array(b), t)
}

impl FloorTexture {
    /// The texture's first albedo where `which` is 0, its second elsewhere (checks, stripes).
    fn two_tone(&self, which: i64) -> DVec3 {
        DVec3::from_array(if which == 0 {
            self.albedo_a
        } else {
            self.albedo_b
        })
    }

    /// Linear albedo at floor point (x, y).
    pub fn albedo(&self, x: f64, y: f64) -> DVec3 {
        let (s, c) = self.rotation_degrees.to_radians().sin_cos();
        let (u, v) = (c * x + s * y, -s * x + c * y);
        let w = self.scale;
        let jw = self.joint_width;
        let seed = self.seed;
        let joint = DVec3::from_array(self.joint_albedo);
        let grain = |n: f64| 1.0 + self.grain * (2.0 * n - 1.0);
        match self.pattern {
            FloorPattern::Planks => {
                let length = w * self.length_ratio;
                let row = (v / w).floor();
                let shift = cell_hash(seed, row as i64, -7) * length;
                let along = u + shift;
                let col = (along / length).floor();
                let (fu, fv) = (along - col * length, v - row * w);
                if fu < jw || fv < jw {
                    return joint;
                }
                let shade = cell_hash(seed, row as i64, col as i64);
                let n = value_noise(along / (1.5 * w), v / (0.06 * w), seed ^ row as u64);
                lerp3(self.albedo_a, self.albedo_b, shade) * grain(n)
            }
            FloorPattern::Parquet => {
                let (i, j) = ((u / w).floor(), (v / w).floor());
                let (fu, fv) = (u - i * w, v - j * w);
                let strip_width = w / 3.0;
                // Blocks alternate: strips along u, then along v.
                let along_u = (i as i64 + j as i64) & 1 == 0;
                let (across, along) = if along_u { (fv, fu) } else { (fu, fv) };
                let strip = (across / strip_width).floor();
                let in_strip = across - strip * strip_width;
                if along < jw || in_strip < jw {
                    return joint;
                }
                let shade = cell_hash(seed, i as i64 * 3 + strip as i64, j as i64);
                let (gu, gv) = if along_u {
                    (u / (0.8 * w), v / (0.05 * w))
                } else {
                    (u / (0.05 * w), v / (0.8 * w))
                };
                let n = value_noise(gu, gv, seed ^ 0x5041);
                lerp3(self.albedo_a, self.albedo_b, shade) * grain(n)
            }
            FloorPattern::Tiles => {
                let (i, j) = ((u / w).floor(), (v / w).floor());
                let (fu, fv) = (u - i * w, v - j * w);
                if fu < jw || fv < jw {
                    return joint;
                }
                let shade = cell_hash(seed, i as i64, j as i64);
                let n = value_noise(u / (0.08 * w), v / (0.08 * w), seed ^ 0x5449);
                lerp3(self.albedo_a, self.albedo_b, shade) * grain(n)
            }
            FloorPattern::Checker => {
                let parity = ((u / w).floor() as i64 + (v / w).floor() as i64) & 1;
                let n = value_noise(u / (0.5 * w), v / (0.5 * w), seed ^ 0x4348);
                self.two_tone(parity) * grain(n)
            }
            FloorPattern::Stripes => {
                let band = (v / w).floor() as i64 & 1;
                let n = value_noise(u / (0.03 * w), v / (0.03 * w), seed ^ 0x5354);
                self.two_tone(band) * grain(n)
            }
            FloorPattern::Stone => {
                let n = 0.55 * value_noise(u / w, v / w, seed)
                    + 0.3 * value_noise(2.3 * u / w, 2.3 * v / w, seed ^ 0x1)
                    + 0.15 * value_noise(5.1 * u / w, 5.1 * v / w, seed ^ 0x2);
                let t = ((n - 0.3) / 0.4).clamp(0.0, 1.0);
                let fine = value_noise(u / (0.04 * w), v / (0.04 * w), seed ^ 0x3);
                lerp3(self.albedo_a, self.albedo_b, t * t * (3.0 - 2.0 * t)) * grain(fine)
            }
        }
    }
}

impl FloorTexture {
    /// The texture over the square [−`half_extent`, `half_extent`]² as an `n`×`n` 8-bit sRGB
    /// RGB image (row 0 at +y, column 0 at −x), each texel the mean linear albedo of 2×2
    /// points: the Blender engine's floor image.
    pub fn bake(&self, half_extent: f64, n: u32) -> Vec<u8> {
        let texel = 2.0 * half_extent / n as f64;
        let mut rgb = Vec::with_capacity(3 * (n * n) as usize);
        for row in 0..n {
            for col in 0..n {
                let mut sum = DVec3::ZERO;
                for (du, dv) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
                    let x = -half_extent + (col as f64 + du) * texel;
                    let y = half_extent - (row as f64 + dv) * texel;
                    sum += self.albedo(x, y);
                }
                let mean = sum / 4.0;
                rgb.extend([mean.x, mean.y, mean.z].map(super::shading::linear_to_srgb8));
            }
        }
        rgb
    }
}

/// Linear albedo of an sRGB colour given as bytes.
fn linear(rgb: [f64; 3]) -> [f64; 3] {
    rgb.map(|c| srgb_to_linear(c / 255.0))
}

/// Linear wall albedo of `room-chair`: a warm light grey.
pub const ROOM_CHAIR_WALL: [u8; 3] = [200, 196, 188];

/// Floor texture `k` (0, 1 or 2) of `room-chair`: oak planks, grey stone tiles, walnut
/// parquet.
pub fn room_chair_floor(k: usize) -> FloorTexture {
    let base = FloorTexture {
        family: "room-chair".into(),
        index: k,
        pattern: FloorPattern::Planks,
        scale: 0.45,
        length_ratio: 6.0,
        rotation_degrees: 0.0,
        albedo_a: linear([192.0, 148.0, 100.0]),
        albedo_b: linear([178.0, 134.0, 88.0]),
        joint_albedo: linear([150.0, 110.0, 74.0]),
        joint_width: 0.02,
        grain: 0.04,
        seed: 0x726f_6f6d_0000_0000 | k as u64,
    };
    match k {
        0 => base,
        1 => FloorTexture {
            pattern: FloorPattern::Tiles,
            scale: 1.2,
            albedo_a: linear([174.0, 174.0, 168.0]),
            albedo_b: linear([160.0, 160.0, 155.0]),
            joint_albedo: linear([132.0, 132.0, 128.0]),
            joint_width: 0.04,
            grain: 0.02,
            rotation_degrees: 0.0,
            ..base
        },
        _ => FloorTexture {
            pattern: FloorPattern::Parquet,
            scale: 0.9,
            albedo_a: linear([124.0, 81.0, 50.0]),
            albedo_b: linear([110.0, 71.0, 43.0]),
            joint_albedo: linear([92.0, 60.0, 38.0]),
            joint_width: 0.015,
            grain: 0.04,
            rotation_degrees: 45.0,
            ..base
        },
    }
}

/// Floor texture `index` of `room-diverse` and its wall's linear albedo: the patterns in turn
/// (index mod 6), every parameter and colour drawn from the index's own seed.
pub fn diverse_floor(index: usize) -> (FloorTexture, [f64; 3]) {
    let mut rng = StdRng::seed_from_u64(mix64(0x464c_4f4f_5200_0001 ^ mix64(index as u64)));
    let pattern = FLOOR_PATTERNS[index % FLOOR_PATTERNS.len()];
    // The textures of one pattern (index / 6 = 0..=8) step through 9 lightness levels, so no
    // two of them share a colour: woods for boards, tinted greys and muted colours otherwise
    // (sRGB levels).
    const WOOD_HUES: [[f64; 3]; 6] = [
        [1.0, 0.78, 0.53],
        [1.0, 0.70, 0.45],
        [1.0, 0.67, 0.43],
        [1.0, 0.87, 0.68],
        [1.0, 0.65, 0.44],
        [1.0, 0.74, 0.56],
    ];
    let step = |k: usize| 80.0 + 17.0 * (k % 9) as f64;
    let k = index / FLOOR_PATTERNS.len();
    let tinted = |rng: &mut StdRng, level: f64| -> [f64; 3] {
        [(); 3].map(|_| (level * rng.random_range(0.85..=1.15)).clamp(20.0, 235.0))
    };
    let (a, b) = match pattern {
        FloorPattern::Planks | FloorPattern::Parquet => {
            let hue = WOOD_HUES[rng.random_range(0..WOOD_HUES.len())];
            let a = hue.map(|c| c * (step(k) + 30.0).min(235.0));
            let darker = rng.random_range(0.7..=0.9);
            (a, a.map(|c| c * darker))
        }
        FloorPattern::Tiles | FloorPattern::Stone => {
            let a = tinted(&mut rng, step(k));
            let darker = rng.random_range(0.75..=0.92);
            (a, a.map(|c| c * darker))
        }
        FloorPattern::Checker | FloorPattern::Stripes => {
            // The second colour is 4 or 5 levels away from the first.
            (tinted(&mut rng, step(k)), tinted(&mut rng, step(k + 4)))
        }
    };
    let joint = a.map(|c| c * rng.random_range(0.4..=0.6));
    let scale = match pattern {
        FloorPattern::Planks => rng.random_range(0.25..=0.6),
        FloorPattern::Parquet => rng.random_range(0.6..=1.4),
        FloorPattern::Tiles => rng.random_range(0.6..=1.8),
        FloorPattern::Checker => rng.random_range(0.5..=1.6),
        FloorPattern::Stripes => rng.random_range(0.3..=1.2),
        FloorPattern::Stone => rng.random_range(0.8..=3.0),
    };
    let texture = FloorTexture {
        family: "room-diverse".into(),
        index,
        pattern,
        scale: quantise(scale, 0.01),
        length_ratio: quantise(rng.random_range(3.0..=9.0), 0.1),
        rotation_degrees: quantise(rng.random_range(0.0..90.0), 0.5),
        albedo_a: linear(a),
        albedo_b: linear(b),
        joint_albedo: linear(joint),
        joint_width: quantise(rng.random_range(0.01..=0.04), 0.005),
        grain: quantise(rng.random_range(0.04..=0.18), 0.01),
        seed: mix64(rng.random::<u64>()),
    };
    let wall_grey: f64 = rng.random_range(150.0..=225.0);
    let wall = [
        wall_grey * rng.random_range(0.92..=1.05),
        wall_grey * rng.random_range(0.92..=1.05),
        wall_grey * rng.random_range(0.92..=1.05),
    ]
    .map(|c: f64| c.min(240.0));
    (texture, linear(wall))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::shading::linear_to_srgb;
    use std::collections::HashSet;

    /// The union of the parts as a point test (the reference of the tracer's intersection).
    fn inside(parts: &[Solid], p: DVec3) -> bool {
        parts.iter().any(|s| s.contains(p))
    }

    /// The first hit of the union by marching along the ray in steps of `step`, refined by
    /// bisection: a reference that knows only point membership.
    fn march(
        parts: &[Solid],
        origin: DVec3,
        dir: DVec3,
        t_min: f64,
        t_max: f64,
        step: f64,
    ) -> Option<f64> {
        assert!(!inside(parts, origin + t_min * dir));
        let mut t = t_min;
        while t < t_max {
            let next = t + step;
            if inside(parts, origin + next * dir) {
                let (mut lo, mut hi) = (t, next);
                for _ in 0..50 {
                    let mid = 0.5 * (lo + hi);
                    if inside(parts, origin + mid * dir) {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                return Some(hi);
            }
            t = next;
        }
        None
    }

    fn nearest(parts: &[Solid], origin: DVec3, dir: DVec3) -> Option<f64> {
        parts
            .iter()
            .filter_map(|s| s.intersect(origin, dir, f64::INFINITY))
            .map(|h| h.t)
            .min_by(f64::total_cmp)
    }

    /// For chairs of every kind, turned and placed, the tracer's nearest hit agrees with
    /// marching the union of the parts: the same rays hit, at the same distance. Where the
    /// march (steps of STEP) misses a hit or finds a later one, the ray must only graze the
    /// chair: its chord inside is shorter than a step.
    #[test]
    fn chair_intersection_matches_a_brute_force_reference() {
        const STEP: f64 = 0.004;
        let mut state = 99u64;
        let mut uniform = || {
            state = mix64(state);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        // The room-chair design and the first diverse design of every kind.
        let mut designs = vec![ChairDesign::room_chair()];
        let mut kinds = HashSet::new();
        for i in 0..DIVERSE_DESIGNS {
            let d = ChairDesign::diverse(i);
            let kind = (
                d.base,
                d.back_style,
                d.seat_shape,
                d.arms,
                d.leg_splay_degrees > 0.0,
                d.stretchers,
            );
            if kinds.insert(kind) {
                designs.push(d);
            }
        }
        assert!(designs.len() > 40, "{} kinds", designs.len());
        let (mut hits, mut rays) = (0, 0);
        for (k, design) in designs.iter().enumerate() {
            let position = DVec3::new(0.7, -0.4, design.seat_center_height());
            let yaw = 37.0 * k as f64;
            let parts: Vec<Solid> = design
                .parts(position, yaw)
                .iter()
                .map(|p| p.solid())
                .collect();
            let (radius, top) = design.extent();
            let chord = |origin: DVec3, dir: DVec3, t: f64| {
                (1..200)
                    .take_while(|&i| inside(&parts, origin + (t + 1e-5 * i as f64) * dir))
                    .count() as f64
                    * 1e-5
            };
            for _ in 0..100 {
                let az = uniform() * std::f64::consts::TAU;
                let el = 0.2 + uniform() * 1.1;
                let origin = DVec3::new(position.x, position.y, 0.0)
                    + 5.0 * DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                let target = DVec3::new(
                    position.x + (uniform() - 0.5) * 2.0 * radius,
                    position.y + (uniform() - 0.5) * 2.0 * radius,
                    uniform() * top,
                );
                let dir = (target - origin).normalize();
                rays += 1;
                let exact = nearest(&parts, origin, dir);
                let reference = march(&parts, origin, dir, 1.5, 9.0, STEP);
                match (exact, reference) {
                    (Some(a), Some(b)) if (a - b).abs() < 1e-6 => hits += 1,
                    (Some(a), b) if b.is_none_or(|b| a < b) => {
                        let c = chord(origin, dir, a);
                        assert!(c < STEP, "design {k}: the march missed a chord of {c}");
                    }
                    (None, None) => {}
                    (a, b) => panic!("design {k}: tracer {a:?}, reference {b:?}"),
                }
            }
        }
        assert!(hits > rays / 3, "{hits} hits of {rays} rays");
    }

    #[test]
    fn chairs_stand_on_the_floor_within_their_footprint() {
        for design in
            std::iter::once(ChairDesign::room_chair()).chain((0..300).map(ChairDesign::diverse))
        {
            let parts = design.local_parts();
            let solids: Vec<Solid> = parts.iter().map(|p| p.solid()).collect();
            let (radius, top) = design.extent();
            assert!((0.4..1.3).contains(&radius), "{radius} {design:?}");
            assert!((1.1..2.6).contains(&top), "{top} {design:?}");
            // The seat's centre (the object's position) is inside the chair.
            assert!(inside(&solids, DVec3::Z * design.seat_center_height()));
            // Something touches the floor: just above z = 0 is inside near some part's
            // bottom; nothing hovers (the lowest enclosing corner is at or below the floor).
            let lowest = parts
                .iter()
                .flat_map(|p| p.corners())
                .map(|c| c.z)
                .fold(f64::INFINITY, f64::min);
            assert!(lowest <= 1e-9 && lowest > -0.03, "{lowest} {design:?}");
        }
    }

    #[test]
    fn the_diverse_family_has_over_a_thousand_distinct_geometries() {
        let keys: HashSet<Vec<i64>> = (0..DIVERSE_DESIGNS)
            .map(|i| ChairDesign::diverse(i).geometry_key(0.02))
            .collect();
        eprintln!("{} distinct geometries of {DIVERSE_DESIGNS}", keys.len());
        assert!(keys.len() >= 1000, "{} distinct", keys.len());
        // Seeded: the same index gives the same design.
        assert_eq!(ChairDesign::diverse(17), ChairDesign::diverse(17));
        // Every kind of base, back and seat occurs.
        let designs: Vec<ChairDesign> = (0..DIVERSE_DESIGNS).map(ChairDesign::diverse).collect();
        for base in [
            ChairBase::FourLegs,
            ChairBase::PedestalDisc,
            ChairBase::PedestalCross,
        ] {
            assert!(designs.iter().any(|d| d.base == base));
        }
        for back in [BackStyle::Panel, BackStyle::Slats, BackStyle::Rails] {
            assert!(designs.iter().any(|d| d.back_style == back));
        }
        assert!(designs.iter().any(|d| d.seat_shape == SeatShape::Round));
        assert!(designs.iter().any(|d| d.arms));
    }

    /// Every pair of textures of a family differs visibly: on a grid over the floor their mean
    /// absolute difference of sRGB-encoded albedo is above 0.03 (8 levels of 255).
    #[test]
    fn floor_textures_are_distinct() {
        let sample = |t: &FloorTexture| -> Vec<DVec3> {
            (0..48 * 48)
                .map(|k| {
                    let (i, j) = ((k % 48) as f64, (k / 48) as f64);
                    t.albedo(-6.0 + 0.25 * i + 0.013, -6.0 + 0.25 * j + 0.007)
                })
                .collect()
        };
        let chair: Vec<FloorTexture> = (0..ROOM_CHAIR_FLOORS).map(room_chair_floor).collect();
        let diverse: Vec<FloorTexture> = (0..DIVERSE_FLOORS).map(|i| diverse_floor(i).0).collect();
        for family in [&chair, &diverse] {
            let samples: Vec<Vec<DVec3>> = family.iter().map(sample).collect();
            for (i, a) in samples.iter().enumerate() {
                assert!(
                    a.iter()
                        .all(|c| c.min_element() >= 0.0 && c.max_element() <= 1.0),
                    "texture {i}: albedo out of range"
                );
                for (j, b) in samples.iter().enumerate().skip(i + 1) {
                    let diff = a
                        .iter()
                        .zip(b)
                        .map(|(x, y)| {
                            let (x, y) = (x.to_array(), y.to_array());
                            (0..3)
                                .map(|c| (linear_to_srgb(x[c]) - linear_to_srgb(y[c])).abs())
                                .sum::<f64>()
                                / 3.0
                        })
                        .sum::<f64>()
                        / a.len() as f64;
                    assert!(diff > 0.03, "textures {i} and {j} look alike ({diff})");
                }
            }
        }
        assert_eq!(diverse.len(), 50);
        let patterns: HashSet<_> = diverse.iter().map(|t| t.pattern).collect();
        assert_eq!(patterns.len(), FLOOR_PATTERNS.len());
        assert_eq!(diverse_floor(7), diverse_floor(7));
    }

    #[test]
    fn walls_close_the_room() {
        let room = Room::new([0.5; 3]);
        let walls: Vec<Solid> = room.walls().iter().map(|w| w.solid()).collect();
        // From the centre, at a height below the walls' top, every horizontal ray hits a wall
        // at the room's edge.
        for k in 0..72 {
            let a = (k as f64 * 5.0).to_radians();
            let dir = DVec3::new(a.cos(), a.sin(), 0.0);
            let t = nearest(&walls, DVec3::new(0.0, 0.0, 1.0), dir).expect("a wall");
            let p = dir * t;
            assert!(
                (p.x.abs().max(p.y.abs()) - ROOM_HALF_EXTENT).abs() < 1e-9,
                "{p}"
            );
        }
    }
}
