//! The scene: a closed room and objects on its floor, each one parry3d shape with an
//! isometry; exact ray casting, point-to-surface distances, shading, and the JSON
//! description (`gt/scene.json`) it is rebuilt from.

use std::fmt;
use std::path::Path;

use parry3d::math::{Isometry, Point, Vector};
use parry3d::na::{self, Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use parry3d::query::Ray;
use parry3d::shape::SharedShape;
use serde::{Deserialize, Serialize};

use crate::classes::{
    self, BED, BOOKSHELF, CABINET, CEILING, CHAIR, FLOOR, LAMP, SOFA, TABLE, WALL,
};
use crate::config::Config;
use crate::error::{Result, SynthError};
use crate::rng::{tag, Rng};

/// Thickness of the slabs that bound the room (floor, ceiling, walls), metres.
pub const SLAB: f64 = 0.1;

/// Direction toward the fixed light (unnormalised), world frame.
const LIGHT: [f64; 3] = [0.35, 0.25, 1.0];
/// Ambient share of the Lambert shading.
const AMBIENT: f64 = 0.45;

/// The geometry of an object, in its local frame (see [`ObjectSpec`] for the pose).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ShapeSpec {
    /// A box centred at the local origin.
    Cuboid {
        /// Half sizes along local x, y, z.
        half_extents: [f64; 3],
    },
    /// A ball centred at the local origin.
    Ball {
        /// Radius.
        radius: f64,
    },
    /// A cylinder centred at the local origin, axis along local **z** (upright).
    Cylinder {
        /// Half of the axial length.
        half_height: f64,
        /// Radius.
        radius: f64,
    },
    /// A capsule centred at the local origin, axis along local x (lying).
    Capsule {
        /// Half of the segment length (without the caps).
        half_height: f64,
        /// Radius.
        radius: f64,
    },
    /// The chair: a closed triangle mesh with an L-shaped profile (seat block plus back),
    /// footprint centred at the local origin, standing on local z = 0, back at local
    /// x = −depth/2, extruded along local y.
    Chair {
        /// Size along local y.
        width: f64,
        /// Size along local x.
        depth: f64,
        /// Height of the seat's top face.
        seat_height: f64,
        /// Height of the back's top face.
        back_height: f64,
        /// Thickness of the back along local x.
        back_thickness: f64,
    },
}

impl ShapeSpec {
    /// Short name of the shape kind (`cuboid`, `ball`, `cylinder`, `capsule`, `chair`).
    pub fn kind(&self) -> &'static str {
        match self {
            ShapeSpec::Cuboid { .. } => "cuboid",
            ShapeSpec::Ball { .. } => "ball",
            ShapeSpec::Cylinder { .. } => "cylinder",
            ShapeSpec::Capsule { .. } => "capsule",
            ShapeSpec::Chair { .. } => "chair",
        }
    }

    /// Rotation from the parry shape's own frame to the object's local frame (parry's
    /// cylinder axis is y; ours is z).
    fn base_rotation(&self) -> UnitQuaternion<f64> {
        match self {
            ShapeSpec::Cylinder { .. } => {
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2)
            }
            _ => UnitQuaternion::identity(),
        }
    }

    fn dims(&self) -> Vec<f64> {
        match self {
            ShapeSpec::Cuboid { half_extents } => half_extents.to_vec(),
            ShapeSpec::Ball { radius } => vec![*radius],
            ShapeSpec::Cylinder {
                half_height,
                radius,
            }
            | ShapeSpec::Capsule {
                half_height,
                radius,
            } => {
                vec![*half_height, *radius]
            }
            ShapeSpec::Chair {
                width,
                depth,
                seat_height,
                back_height,
                back_thickness,
            } => vec![*width, *depth, *seat_height, *back_height, *back_thickness],
        }
    }

    fn check(&self) -> std::result::Result<(), String> {
        let d = self.dims();
        if !d.iter().all(|v| v.is_finite() && *v > 0.0 && *v < 1e4) {
            return Err(format!(
                "{} dimensions must be finite and in (0, 1e4), got {d:?}",
                self.kind()
            ));
        }
        if let ShapeSpec::Chair {
            depth,
            seat_height,
            back_height,
            back_thickness,
            ..
        } = self
        {
            if back_thickness >= depth || seat_height >= back_height {
                return Err(
                    "chair needs back_thickness < depth and seat_height < back_height".into(),
                );
            }
        }
        Ok(())
    }

    /// The planar faces of a box-like shape as rectangles in the local frame (`None` for
    /// curved shapes). Each is (corner, edge u, edge v, outward normal).
    pub(crate) fn quads(&self) -> Option<Vec<Quad>> {
        match self {
            ShapeSpec::Cuboid { half_extents: h } => {
                Some(box_quads([-h[0], -h[1], -h[2]], [h[0], h[1], h[2]]))
            }
            ShapeSpec::Chair {
                width,
                depth,
                seat_height,
                back_height,
                back_thickness,
            } => Some(chair_quads(
                *width,
                *depth,
                *seat_height,
                *back_height,
                *back_thickness,
            )),
            _ => None,
        }
    }

    /// The parry shape (in parry's own frame; see `base_rotation`).
    fn parry(&self) -> std::result::Result<SharedShape, String> {
        self.check()?;
        let f = |v: f64| v as f32;
        Ok(match self {
            ShapeSpec::Cuboid { half_extents: h } => SharedShape::cuboid(f(h[0]), f(h[1]), f(h[2])),
            ShapeSpec::Ball { radius } => SharedShape::ball(f(*radius)),
            ShapeSpec::Cylinder {
                half_height,
                radius,
            } => SharedShape::cylinder(f(*half_height), f(*radius)),
            ShapeSpec::Capsule {
                half_height,
                radius,
            } => SharedShape::capsule_x(f(*half_height), f(*radius)),
            ShapeSpec::Chair { .. } => {
                let quads = self.quads().unwrap_or_default();
                let mut vertices = Vec::with_capacity(quads.len() * 4);
                let mut indices = Vec::with_capacity(quads.len() * 2);
                for q in &quads {
                    let base = vertices.len() as u32;
                    for c in q.corners() {
                        vertices.push(Point::new(f(c[0]), f(c[1]), f(c[2])));
                    }
                    let [a, b] = q.triangles();
                    indices.push(a.map(|i| base + i));
                    indices.push(b.map(|i| base + i));
                }
                SharedShape::trimesh(vertices, indices).map_err(|e| format!("chair mesh: {e:?}"))?
            }
        })
    }

    /// The shape scaled by `s` (f32-rounded dimensions).
    fn scaled(&self, s: f64) -> ShapeSpec {
        if s == 1.0 {
            return self.clone();
        }
        let f = |v: f64| r32(v * s);
        match self {
            ShapeSpec::Cuboid { half_extents: h } => ShapeSpec::Cuboid {
                half_extents: h.map(f),
            },
            ShapeSpec::Ball { radius } => ShapeSpec::Ball { radius: f(*radius) },
            ShapeSpec::Cylinder {
                half_height,
                radius,
            } => ShapeSpec::Cylinder {
                half_height: f(*half_height),
                radius: f(*radius),
            },
            ShapeSpec::Capsule {
                half_height,
                radius,
            } => ShapeSpec::Capsule {
                half_height: f(*half_height),
                radius: f(*radius),
            },
            ShapeSpec::Chair {
                width,
                depth,
                seat_height,
                back_height,
                back_thickness,
            } => ShapeSpec::Chair {
                width: f(*width),
                depth: f(*depth),
                seat_height: f(*seat_height),
                back_height: f(*back_height),
                back_thickness: f(*back_thickness),
            },
        }
    }

    /// 2D footprint half sizes (along local x, y) for non-overlap tests.
    fn footprint(&self) -> [f64; 2] {
        match self {
            ShapeSpec::Cuboid { half_extents: h } => [h[0], h[1]],
            ShapeSpec::Ball { radius } | ShapeSpec::Cylinder { radius, .. } => [*radius, *radius],
            ShapeSpec::Capsule {
                half_height,
                radius,
            } => [half_height + radius, *radius],
            ShapeSpec::Chair { width, depth, .. } => [depth / 2.0, width / 2.0],
        }
    }

    /// Height of the local origin above the floor for an object resting on the floor.
    fn rest_height(&self) -> f64 {
        match self {
            ShapeSpec::Cuboid { half_extents: h } => h[2],
            ShapeSpec::Ball { radius } | ShapeSpec::Capsule { radius, .. } => *radius,
            ShapeSpec::Cylinder { half_height, .. } => *half_height,
            ShapeSpec::Chair { .. } => 0.0,
        }
    }
}

/// A rectangle: corner `o`, edges `u` and `v`, outward normal `n`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Quad {
    pub o: [f64; 3],
    pub u: [f64; 3],
    pub v: [f64; 3],
    pub n: [f64; 3],
}

impl Quad {
    fn corners(&self) -> [[f64; 3]; 4] {
        let (o, u, v) = (self.o, self.u, self.v);
        [o, add(o, u), add(add(o, u), v), add(o, v)]
    }

    /// Two triangles over `corners()` with counter-clockwise winding seen from outside.
    fn triangles(&self) -> [[u32; 3]; 2] {
        if dot(cross(self.u, self.v), self.n) > 0.0 {
            [[0, 1, 2], [0, 2, 3]]
        } else {
            [[0, 2, 1], [0, 3, 2]]
        }
    }
}

/// The six faces of an axis-aligned box [lo, hi].
fn box_quads(lo: [f64; 3], hi: [f64; 3]) -> Vec<Quad> {
    let s = sub(hi, lo);
    let (ex, ey, ez) = ([s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]);
    vec![
        Quad {
            o: lo,
            u: ey,
            v: ez,
            n: [-1.0, 0.0, 0.0],
        },
        Quad {
            o: [hi[0], lo[1], lo[2]],
            u: ey,
            v: ez,
            n: [1.0, 0.0, 0.0],
        },
        Quad {
            o: lo,
            u: ex,
            v: ez,
            n: [0.0, -1.0, 0.0],
        },
        Quad {
            o: [lo[0], hi[1], lo[2]],
            u: ex,
            v: ez,
            n: [0.0, 1.0, 0.0],
        },
        Quad {
            o: lo,
            u: ex,
            v: ey,
            n: [0.0, 0.0, -1.0],
        },
        Quad {
            o: [lo[0], lo[1], hi[2]],
            u: ex,
            v: ey,
            n: [0.0, 0.0, 1.0],
        },
    ]
}

/// The closed L-shaped chair: profile in local (x, z), extruded along y. The profile is
/// cut into three rectangles (back below and above the seat height, seat) so that no
/// edge has a T-junction and the mesh is watertight.
fn chair_quads(width: f64, depth: f64, seat: f64, back: f64, thick: f64) -> Vec<Quad> {
    let (x0, x1, x2) = (-depth / 2.0, -depth / 2.0 + thick, depth / 2.0);
    let (z0, z1, z2) = (0.0, seat, back);
    let (y0, y1) = (-width / 2.0, width / 2.0);
    let ey = [0.0, width, 0.0];
    let mut q = Vec::new();
    // Side faces (y = y0 and y = y1): the three profile rectangles.
    for (xa, xb, za, zb) in [(x0, x1, z0, z1), (x0, x1, z1, z2), (x1, x2, z0, z1)] {
        let u = [xb - xa, 0.0, 0.0];
        let v = [0.0, 0.0, zb - za];
        q.push(Quad {
            o: [xa, y0, za],
            u,
            v,
            n: [0.0, -1.0, 0.0],
        });
        q.push(Quad {
            o: [xa, y1, za],
            u,
            v,
            n: [0.0, 1.0, 0.0],
        });
    }
    // Faces along the profile outline, each spanning the width.
    let strip = |a: [f64; 2], b: [f64; 2], n: [f64; 2]| Quad {
        o: [a[0], y0, a[1]],
        u: [b[0] - a[0], 0.0, b[1] - a[1]],
        v: ey,
        n: [n[0], 0.0, n[1]],
    };
    q.push(strip([x0, z0], [x1, z0], [0.0, -1.0])); // bottom under the back
    q.push(strip([x1, z0], [x2, z0], [0.0, -1.0])); // bottom under the seat
    q.push(strip([x2, z0], [x2, z1], [1.0, 0.0])); // seat front
    q.push(strip([x1, z1], [x2, z1], [0.0, 1.0])); // seat top
    q.push(strip([x1, z1], [x1, z2], [1.0, 0.0])); // back, front face
    q.push(strip([x0, z2], [x1, z2], [0.0, 1.0])); // back top
    q.push(strip([x0, z0], [x0, z1], [-1.0, 0.0])); // back face, lower
    q.push(strip([x0, z1], [x0, z2], [-1.0, 0.0])); // back face, upper
    q
}

/// A procedural texture, evaluated in the object's local frame (for the room surfaces,
/// whose local frames are world-aligned, that is world coordinates up to a shift).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Texture {
    /// Uniform.
    Plain,
    /// 3D checkerboard of cell `size`; dark cells are darkened by `contrast`.
    Checker {
        /// Cell size, metres.
        size: f64,
        /// Darkening of the dark cells, in [0, 1).
        contrast: f64,
    },
    /// Stripes across local `axis` (0 = x, 1 = y, 2 = z) with the given `period`.
    Stripes {
        /// Stripe period (one dark + one light stripe is two periods), metres.
        period: f64,
        /// Local axis the stripes vary along.
        axis: usize,
        /// Darkening of the dark stripes, in [0, 1).
        contrast: f64,
    },
}

impl Texture {
    fn factor(&self, p: [f64; 3]) -> f64 {
        // A small irrational offset keeps faces at round coordinates off cell borders.
        let cell = |x: f64, s: f64| ((x + 0.0137) / s).floor() as i64;
        match self {
            Texture::Plain => 1.0,
            Texture::Checker { size, contrast } => {
                let k = cell(p[0], *size) + cell(p[1], *size) + cell(p[2], *size);
                if k.rem_euclid(2) == 1 {
                    1.0 - contrast
                } else {
                    1.0
                }
            }
            Texture::Stripes {
                period,
                axis,
                contrast,
            } => {
                if cell(p[(*axis).min(2)], *period).rem_euclid(2) == 1 {
                    1.0 - contrast
                } else {
                    1.0
                }
            }
        }
    }
}

/// One object of the scene (room surfaces included): class, shape and pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectSpec {
    /// Object index = object id in `gt/views.safetensors`; mesh instance = index + 1.
    pub index: u32,
    /// Unique name, e.g. `floor`, `wall_east`, `chair_1`.
    pub name: String,
    /// NYU40 class id.
    pub class_id: u32,
    /// NYU40 class name.
    pub class_name: String,
    /// Whether this is a room surface (floor, ceiling, wall).
    pub room: bool,
    /// The geometry in the local frame.
    pub shape: ShapeSpec,
    /// World position of the local origin, metres.
    pub translation: [f64; 3],
    /// Rotation about the world z axis, radians. The world pose is
    /// `translation · Rz(yaw)`; the local frame's z is the world's z.
    pub yaw: f64,
    /// Base colour, sRGB 8 bit.
    pub color: [u8; 3],
    /// Procedural texture.
    pub texture: Texture,
}

impl ObjectSpec {
    /// The world pose of the local frame.
    pub fn pose(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(
                self.translation[0],
                self.translation[1],
                self.translation[2],
            ),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), self.yaw),
        )
    }

    /// The world rotation as a quaternion (w, x, y, z).
    pub fn rotation_wxyz(&self) -> [f64; 4] {
        let q = self.pose().rotation;
        [q.w, q.i, q.j, q.k]
    }
}

/// A ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Ray parameter of the hit in units of the direction's length: point = origin + t·dir.
    pub t: f64,
    /// Index of the object hit.
    pub object: u32,
    /// Unit surface normal at the hit, facing the ray's origin.
    pub normal: [f64; 3],
    /// The hit point, world coordinates.
    pub point: [f64; 3],
}

struct Placed {
    shape: SharedShape,
    iso: Isometry<f32>,
    pose: Isometry3<f64>,
    center: [f64; 3],
    radius: f64,
    /// Pose of the parry shape's own frame (the object pose times the base rotation).
    full: Isometry3<f64>,
    /// For the chair mesh (a BVH traversal): the local box, a cheap exact-miss test
    /// before the cast.
    cull_box: Option<([f64; 3], [f64; 3])>,
    /// Quadrics cast analytically in f64 (parry's GJK ray cast for capsules and cylinders
    /// is only accurate to about a millimetre).
    quadric: Option<Quadric>,
}

/// Shapes with a closed-form ray intersection, in the parry shape's own frame.
#[derive(Debug, Clone, Copy)]
enum Quadric {
    /// Ball of radius r at the origin.
    Ball(f64),
    /// Capsule: segment (−h, 0, 0)–(h, 0, 0), radius r.
    CapsuleX(f64, f64),
    /// Cylinder: axis y, |y| <= h, radius r.
    CylinderY(f64, f64),
}

/// Entry and exit parameters of a unit ray with a ball at `c` of radius `r`.
fn ball_interval(o: [f64; 3], d: [f64; 3], c: [f64; 3], r: f64) -> Option<(f64, f64)> {
    let oc = sub(o, c);
    let b = dot(oc, d);
    let cc = dot(oc, oc) - r * r;
    let disc = b * b - cc;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    // Numerically stable roots.
    let q = if b > 0.0 { -b - s } else { -b + s };
    let (t0, t1) = if q != 0.0 { (cc / q, q) } else { (-b, -b) };
    Some((t0.min(t1), t0.max(t1)))
}

/// Entry and exit of a unit ray with the infinite cylinder of radius r around the axis
/// `axis` (0 = x, 1 = y) through the origin; `None` if it misses. A ray parallel to the
/// axis gives an infinite interval when inside.
fn tube_interval(o: [f64; 3], d: [f64; 3], axis: usize, r: f64) -> Option<(f64, f64)> {
    let (i, j) = if axis == 0 { (1, 2) } else { (0, 2) };
    let a = d[i] * d[i] + d[j] * d[j];
    let b = o[i] * d[i] + o[j] * d[j];
    let c = o[i] * o[i] + o[j] * o[j] - r * r;
    if a < 1e-18 {
        return (c <= 0.0).then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let disc = b * b - a * c;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    let q = if b > 0.0 { -b - s } else { -b + s };
    let (t0, t1) = if q != 0.0 {
        (c / q, q / a)
    } else {
        (-b / a, -b / a)
    };
    Some((t0.min(t1), t0.max(t1)))
}

impl Quadric {
    /// First t >= 0 where the unit ray (local frame) enters the solid (0 if it starts
    /// inside), and the outward normal there.
    fn cast(self, o: [f64; 3], d: [f64; 3]) -> Option<(f64, [f64; 3])> {
        match self {
            Quadric::Ball(r) => {
                let (t0, t1) = ball_interval(o, d, [0.0; 3], r)?;
                if t1 < 0.0 {
                    return None;
                }
                let t = t0.max(0.0);
                Some((t, normalize(add(o, scale(d, t)))))
            }
            Quadric::CapsuleX(h, r) => {
                // The union of a finite tube and two end balls: the entry is the earliest
                // entry of the three (the tube's flat ends lie inside the balls).
                let mut best: Option<(f64, f64)> = None;
                let mut take = |iv: Option<(f64, f64)>| {
                    if let Some((t0, t1)) = iv {
                        if t1 >= 0.0 && best.is_none_or(|b| t0 < b.0) {
                            best = Some((t0, t1));
                        }
                    }
                };
                if let Some((t0, t1)) = tube_interval(o, d, 0, r) {
                    // Restrict the tube to |x| <= h.
                    let (s0, s1) = if d[0].abs() < 1e-18 {
                        if o[0].abs() <= h {
                            (f64::NEG_INFINITY, f64::INFINITY)
                        } else {
                            (1.0, -1.0)
                        }
                    } else {
                        let (a, b) = ((-h - o[0]) / d[0], (h - o[0]) / d[0]);
                        (a.min(b), a.max(b))
                    };
                    let (e0, e1) = (t0.max(s0), t1.min(s1));
                    if e0 <= e1 {
                        take(Some((e0, e1)));
                    }
                }
                take(ball_interval(o, d, [-h, 0.0, 0.0], r));
                take(ball_interval(o, d, [h, 0.0, 0.0], r));
                let (t0, _) = best?;
                let t = t0.max(0.0);
                let p = add(o, scale(d, t));
                let n = normalize([p[0] - p[0].clamp(-h, h), p[1], p[2]]);
                Some((t, n))
            }
            Quadric::CylinderY(h, r) => {
                let (t0, t1) = tube_interval(o, d, 1, r)?;
                let (s0, s1) = if d[1].abs() < 1e-18 {
                    if o[1].abs() > h {
                        return None;
                    }
                    (f64::NEG_INFINITY, f64::INFINITY)
                } else {
                    let (a, b) = ((-h - o[1]) / d[1], (h - o[1]) / d[1]);
                    (a.min(b), a.max(b))
                };
                let (e0, e1) = (t0.max(s0), t1.min(s1));
                if e0 > e1 || e1 < 0.0 {
                    return None;
                }
                let t = e0.max(0.0);
                let p = add(o, scale(d, t));
                let n = if s0 >= t0 {
                    [0.0, p[1].signum(), 0.0]
                } else {
                    normalize([p[0], 0.0, p[2]])
                };
                Some((t, n))
            }
        }
    }
}

impl Placed {
    /// Whether the ray (unit `d`) can hit the local box before `best`.
    fn box_may_hit(&self, o: [f64; 3], d: [f64; 3], best: f64) -> bool {
        let Some((lo, hi)) = &self.cull_box else {
            return true;
        };
        let (o, d) = self.to_local(o, d);
        let (mut t0, mut t1) = (0.0f64, best);
        for k in 0..3 {
            if d[k].abs() < 1e-12 {
                if o[k] < lo[k] || o[k] > hi[k] {
                    return false;
                }
                continue;
            }
            let (a, b) = ((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]);
            t0 = t0.max(a.min(b));
            t1 = t1.min(a.max(b));
            if t0 > t1 {
                return false;
            }
        }
        true
    }

    /// A world ray in the parry shape's frame.
    fn to_local(&self, o: [f64; 3], d: [f64; 3]) -> ([f64; 3], [f64; 3]) {
        let lo = self
            .full
            .inverse_transform_point(&Point3::new(o[0], o[1], o[2]));
        let ld = self
            .full
            .inverse_transform_vector(&Vector3::new(d[0], d[1], d[2]));
        ([lo.x, lo.y, lo.z], [ld.x, ld.y, ld.z])
    }

    /// Nearest hit (t along the unit world ray, world normal) before `best`.
    fn cast(&self, ray: &Ray, o: [f64; 3], d: [f64; 3], best: f64) -> Option<(f64, [f64; 3])> {
        if let Some(q) = self.quadric {
            let (lo, ld) = self.to_local(o, d);
            let (t, n) = q.cast(lo, ld)?;
            let n = self.full.transform_vector(&Vector3::new(n[0], n[1], n[2]));
            return (t < best).then_some((t, [n.x, n.y, n.z]));
        }
        let max_toi = if best.is_finite() {
            best as f32
        } else {
            f32::MAX
        };
        let inter = self
            .shape
            .cast_ray_and_get_normal(&self.iso, ray, max_toi, true)?;
        let t = f64::from(inter.time_of_impact);
        let n = inter.normal;
        (t < best).then_some((t, [f64::from(n.x), f64::from(n.y), f64::from(n.z)]))
    }
}

/// A built scene: the objects and their parry3d shapes, ready for ray casting.
pub struct Scene {
    /// Inner size of the room (x, y, z), metres; the room spans
    /// [−x/2, x/2] × [−y/2, y/2] × [0, z].
    pub room_size: [f64; 3],
    /// The objects: the six room surfaces first (floor, ceiling, four walls), then the
    /// objects on the floor.
    pub objects: Vec<ObjectSpec>,
    placed: Vec<Placed>,
    light: [f64; 3],
}

impl fmt::Debug for Scene {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Scene")
            .field("room_size", &self.room_size)
            .field("objects", &self.objects.len())
            .finish_non_exhaustive()
    }
}

/// The part of `gt/scene.json` that describes the geometry.
#[derive(Debug, Clone, Deserialize)]
struct Geometry {
    room: RoomJson,
    objects: Vec<ObjectSpec>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct RoomJson {
    pub size: [f64; 3],
    pub slab_thickness: f64,
}

impl Scene {
    /// Builds the shapes of a list of objects. Errors name the first invalid object.
    pub fn new(room_size: [f64; 3], objects: Vec<ObjectSpec>) -> Result<Scene> {
        let bad = |detail: String| SynthError::Scene {
            path: "<memory>".into(),
            detail,
        };
        let mut placed = Vec::with_capacity(objects.len());
        for (i, o) in objects.iter().enumerate() {
            if o.index as usize != i {
                return Err(bad(format!("object {i} has index {}", o.index)));
            }
            if !o.translation.iter().chain([&o.yaw]).all(|v| v.is_finite()) {
                return Err(bad(format!(
                    "object {i} ({}) has a non-finite pose",
                    o.name
                )));
            }
            let shape = o
                .shape
                .parry()
                .map_err(|e| bad(format!("object {i} ({}): {e}", o.name)))?;
            let pose = o.pose();
            let full =
                Isometry3::from_parts(pose.translation, pose.rotation * o.shape.base_rotation());
            let iso: Isometry<f32> = na::convert(full);
            let bs = shape.compute_bounding_sphere(&iso);
            let c = bs.center();
            let cull_box = matches!(o.shape, ShapeSpec::Chair { .. }).then(|| {
                let b = shape.compute_local_aabb();
                let pad = 1e-3;
                let lo = [b.mins.x, b.mins.y, b.mins.z].map(|v| f64::from(v) - pad);
                let hi = [b.maxs.x, b.maxs.y, b.maxs.z].map(|v| f64::from(v) + pad);
                (lo, hi)
            });
            // The f32-rounded dimensions parry uses, so both agree exactly.
            let f = |v: f64| f64::from(v as f32);
            let quadric = match o.shape {
                ShapeSpec::Ball { radius } => Some(Quadric::Ball(f(radius))),
                ShapeSpec::Capsule {
                    half_height,
                    radius,
                } => Some(Quadric::CapsuleX(f(half_height), f(radius))),
                ShapeSpec::Cylinder {
                    half_height,
                    radius,
                } => Some(Quadric::CylinderY(f(half_height), f(radius))),
                _ => None,
            };
            placed.push(Placed {
                full,
                cull_box,
                quadric,
                center: [f64::from(c.x), f64::from(c.y), f64::from(c.z)],
                radius: f64::from(bs.radius()) * 1.001 + 1e-4,
                shape,
                iso,
                pose,
            });
        }
        Ok(Scene {
            room_size,
            objects,
            placed,
            light: normalize(LIGHT),
        })
    }

    /// Generates the room and places `config.objects` objects by seeded rejection
    /// sampling (fewer if the floor is full).
    pub fn generate(config: &Config) -> Result<Scene> {
        let room = config.resolved_room();
        let mut objects = room_objects(room, config.seed);
        objects.extend(place_objects(config, room, objects.len() as u32));
        Scene::new(room, objects)
    }

    /// Rebuilds the scene from a `gt/scene.json` written by the generator.
    pub fn from_json(path: impl AsRef<Path>) -> Result<Scene> {
        let path = path.as_ref();
        let text =
            std::fs::read_to_string(path).map_err(crate::error::io_err(path, "cannot read"))?;
        Scene::from_json_str(&text).map_err(|e| match e {
            SynthError::Scene { detail, .. } => SynthError::Scene {
                path: path.display().to_string(),
                detail,
            },
            SynthError::Json { source, .. } => SynthError::Json {
                path: path.display().to_string(),
                source,
            },
            other => other,
        })
    }

    /// Rebuilds the scene from the text of a `gt/scene.json`.
    pub fn from_json_str(text: &str) -> Result<Scene> {
        let g: Geometry = serde_json::from_str(text).map_err(|source| SynthError::Json {
            path: "<memory>".into(),
            source,
        })?;
        Scene::new(g.room.size, g.objects)
    }

    pub(crate) fn room_json(&self) -> RoomJson {
        RoomJson {
            size: self.room_size,
            slab_thickness: SLAB,
        }
    }

    /// Number of objects (room surfaces included).
    pub fn len(&self) -> usize {
        self.objects.len()
    }

    /// Whether there are no objects.
    pub fn is_empty(&self) -> bool {
        self.objects.is_empty()
    }

    /// Nearest hit of the ray `origin + t·dir`, t >= 0 (dir need not be unit length; t is
    /// in units of its length). Shapes are solid: a ray starting inside one hits at t = 0.
    pub fn raycast(&self, origin: [f64; 3], dir: [f64; 3]) -> Option<Hit> {
        self.raycast_within(origin, dir, f64::INFINITY)
    }

    /// Nearest hit with t < `max_t` (in units of `dir`'s length).
    pub fn raycast_within(&self, origin: [f64; 3], dir: [f64; 3], max_t: f64) -> Option<Hit> {
        let len = norm(dir);
        if !(len > 0.0 && len.is_finite() && origin.iter().all(|v| v.is_finite())) {
            return None;
        }
        let d = scale(dir, 1.0 / len);
        let ray = Ray::new(
            Point::new(origin[0] as f32, origin[1] as f32, origin[2] as f32),
            Vector::new(d[0] as f32, d[1] as f32, d[2] as f32),
        );
        let mut best = max_t * len;
        let mut found: Option<(usize, [f64; 3])> = None;
        for (i, p) in self.placed.iter().enumerate() {
            let oc = sub(p.center, origin);
            let tca = dot(oc, d);
            let d2 = dot(oc, oc) - tca * tca;
            let r2 = p.radius * p.radius;
            if d2 > r2 {
                continue;
            }
            let thc = (r2 - d2).sqrt();
            if tca + thc < 0.0 || tca - thc > best || !p.box_may_hit(origin, d, best) {
                continue;
            }
            if let Some((t, n)) = p.cast(&ray, origin, d, best) {
                best = t;
                found = Some((i, n));
            }
        }
        let (i, mut n) = found?;
        let nl = norm(n);
        n = if nl > 0.0 && nl.is_finite() {
            scale(n, 1.0 / nl)
        } else {
            scale(d, -1.0)
        };
        if dot(n, d) > 0.0 {
            n = scale(n, -1.0);
        }
        Some(Hit {
            t: best / len,
            object: i as u32,
            normal: n,
            point: add(origin, scale(d, best)),
        })
    }

    /// Distance from a point to the nearest surface of any object (room surfaces
    /// included), from parry3d's exact point projections (f32 precision, ~1e-6 m).
    pub fn distance_to_surface(&self, p: [f64; 3]) -> f64 {
        let pt = Point3::new(p[0] as f32, p[1] as f32, p[2] as f32);
        self.placed
            .iter()
            .map(|o| {
                let proj = o.shape.project_point(&o.iso, &pt, false).point;
                let q = [f64::from(proj.x), f64::from(proj.y), f64::from(proj.z)];
                norm(sub(p, q))
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// The colour seen at a hit: base colour × texture × Lambert (fixed directional light
    /// plus ambient), 8-bit sRGB values (no gamma: the synthetic world is "already sRGB").
    pub fn shade(&self, hit: &Hit) -> [u8; 3] {
        let (o, p) = (
            &self.objects[hit.object as usize],
            &self.placed[hit.object as usize],
        );
        let local =
            p.pose
                .inverse_transform_point(&Point3::new(hit.point[0], hit.point[1], hit.point[2]));
        let tex = o.texture.factor([local.x, local.y, local.z]);
        let lambert = AMBIENT + (1.0 - AMBIENT) * dot(hit.normal, self.light).max(0.0);
        o.color
            .map(|c| (f64::from(c) * tex * lambert).round().clamp(0.0, 255.0) as u8)
    }

    pub(crate) fn pose(&self, i: usize) -> &Isometry3<f64> {
        &self.placed[i].pose
    }
}

/// The six room surfaces: floor, ceiling, walls east (+x), west (−x), north (+y),
/// south (−y). Slabs outside the room's inner box, so rays from inside hit their inner
/// faces.
fn room_objects(room: [f64; 3], seed: u64) -> Vec<ObjectSpec> {
    let [lx, ly, lz] = room;
    let (hx, hy, hz, t) = (lx / 2.0, ly / 2.0, lz / 2.0, SLAB / 2.0);
    let mut rng = Rng::new(&[seed, tag::LAYOUT, 0]);
    let mut wall_color = || {
        let j = rng.range(-12.0, 12.0);
        [
            (205.0 + j) as u8,
            (198.0 + j * 0.8) as u8,
            (182.0 + j * 0.5) as u8,
        ]
    };
    // (name, class, centre, half extents, colour, texture)
    type Slab = (&'static str, u32, [f64; 3], [f64; 3], [u8; 3], Texture);
    let slabs: [Slab; 6] = [
        (
            "floor",
            FLOOR,
            [0.0, 0.0, -t],
            [hx + SLAB, hy + SLAB, t],
            [170, 120, 80],
            Texture::Checker {
                size: 0.5,
                contrast: 0.35,
            },
        ),
        (
            "ceiling",
            CEILING,
            [0.0, 0.0, lz + t],
            [hx + SLAB, hy + SLAB, t],
            [238, 236, 230],
            Texture::Plain,
        ),
        (
            "wall_east",
            WALL,
            [hx + t, 0.0, hz],
            [t, hy + SLAB, hz + SLAB],
            wall_color(),
            Texture::Stripes {
                period: 0.4,
                axis: 1,
                contrast: 0.12,
            },
        ),
        (
            "wall_west",
            WALL,
            [-hx - t, 0.0, hz],
            [t, hy + SLAB, hz + SLAB],
            wall_color(),
            Texture::Stripes {
                period: 0.4,
                axis: 1,
                contrast: 0.12,
            },
        ),
        (
            "wall_north",
            WALL,
            [0.0, hy + t, hz],
            [hx + SLAB, t, hz + SLAB],
            wall_color(),
            Texture::Stripes {
                period: 0.4,
                axis: 0,
                contrast: 0.12,
            },
        ),
        (
            "wall_south",
            WALL,
            [0.0, -hy - t, hz],
            [hx + SLAB, t, hz + SLAB],
            wall_color(),
            Texture::Stripes {
                period: 0.4,
                axis: 0,
                contrast: 0.12,
            },
        ),
    ];
    slabs
        .into_iter()
        .enumerate()
        .map(
            |(i, (name, class_id, translation, half, color, texture))| ObjectSpec {
                index: i as u32,
                name: name.to_string(),
                class_id,
                class_name: profuse_formats::label_space::nyu40_name(class_id)
                    .unwrap_or("unknown")
                    .to_string(),
                room: true,
                shape: ShapeSpec::Cuboid { half_extents: half },
                translation,
                yaw: 0.0,
                color,
                texture,
            },
        )
        .collect()
}

/// Rounds to f32 precision so that the JSON round trip rebuilds identical shapes.
fn r32(v: f64) -> f64 {
    f64::from(v as f32)
}

fn sample_shape(class: u32, rng: &mut Rng) -> ShapeSpec {
    let mut u = |lo: f64, hi: f64| r32(rng.range(lo, hi));
    match class {
        CABINET => ShapeSpec::Cuboid {
            half_extents: [u(0.3, 0.6), u(0.22, 0.35), u(0.35, 0.6)],
        },
        BED => ShapeSpec::Cuboid {
            half_extents: [u(0.95, 1.1), u(0.7, 0.9), u(0.22, 0.3)],
        },
        CHAIR => ShapeSpec::Chair {
            width: u(0.45, 0.55),
            depth: u(0.45, 0.55),
            seat_height: u(0.42, 0.5),
            back_height: u(0.85, 1.0),
            back_thickness: u(0.07, 0.12),
        },
        SOFA => ShapeSpec::Capsule {
            half_height: u(0.55, 0.85),
            radius: u(0.33, 0.42),
        },
        TABLE => ShapeSpec::Cylinder {
            half_height: u(0.33, 0.4),
            radius: u(0.35, 0.55),
        },
        BOOKSHELF => ShapeSpec::Cuboid {
            half_extents: [u(0.35, 0.55), u(0.14, 0.2), u(0.75, 1.0)],
        },
        _ => ShapeSpec::Ball {
            radius: u(0.15, 0.28),
        },
    }
}

fn class_color(class: u32) -> [f64; 3] {
    match class {
        CABINET => [150.0, 100.0, 60.0],
        BED => [70.0, 110.0, 185.0],
        CHAIR => [200.0, 60.0, 50.0],
        SOFA => [60.0, 150.0, 80.0],
        TABLE => [195.0, 160.0, 95.0],
        BOOKSHELF => [125.0, 80.0, 145.0],
        LAMP => [245.0, 215.0, 70.0],
        _ => [128.0, 128.0, 128.0],
    }
}

fn sample_texture(rng: &mut Rng) -> Texture {
    match rng.below(5) {
        0 => Texture::Plain,
        1 | 2 => Texture::Checker {
            size: r32(rng.range(0.08, 0.2)),
            contrast: r32(rng.range(0.15, 0.3)),
        },
        _ => Texture::Stripes {
            period: r32(rng.range(0.06, 0.2)),
            axis: rng.below(3),
            contrast: r32(rng.range(0.15, 0.3)),
        },
    }
}

/// An oriented 2D box: centre, half sizes, yaw.
#[derive(Clone, Copy)]
struct Footprint {
    c: [f64; 2],
    h: [f64; 2],
    yaw: f64,
}

impl Footprint {
    fn axes(&self) -> [[f64; 2]; 2] {
        let (s, c) = self.yaw.sin_cos();
        [[c, s], [-s, c]]
    }

    fn corners(&self) -> [[f64; 2]; 4] {
        let [a, b] = self.axes();
        let mut out = [[0.0; 2]; 4];
        for (k, (sa, sb)) in [(1.0, 1.0), (1.0, -1.0), (-1.0, -1.0), (-1.0, 1.0)]
            .into_iter()
            .enumerate()
        {
            out[k] = [
                self.c[0] + sa * self.h[0] * a[0] + sb * self.h[1] * b[0],
                self.c[1] + sa * self.h[0] * a[1] + sb * self.h[1] * b[1],
            ];
        }
        out
    }

    /// Separating-axis test with `margin` added around both boxes.
    fn overlaps(&self, other: &Footprint, margin: f64) -> bool {
        let d = [other.c[0] - self.c[0], other.c[1] - self.c[1]];
        let (aa, ba) = (self.axes(), other.axes());
        for axis in aa.iter().chain(ba.iter()) {
            let proj = |f: &Footprint, ax: &[[f64; 2]; 2]| {
                f.h[0] * (ax[0][0] * axis[0] + ax[0][1] * axis[1]).abs()
                    + f.h[1] * (ax[1][0] * axis[0] + ax[1][1] * axis[1]).abs()
            };
            let dist = (d[0] * axis[0] + d[1] * axis[1]).abs();
            if dist > proj(self, &aa) + proj(other, &ba) + margin {
                return false;
            }
        }
        true
    }
}

/// Semi-axes of the ellipse that object footprints must stay inside (a fraction of the
/// camera orbit, so cameras never stand inside or right next to an object).
pub(crate) fn placement_ellipse(config: &Config, room: [f64; 3]) -> [f64; 2] {
    let k = 0.75 * config.orbit_frac;
    [k * room[0] / 2.0, k * room[1] / 2.0]
}

fn place_objects(config: &Config, room: [f64; 3], first_index: u32) -> Vec<ObjectSpec> {
    let mut rng = Rng::new(&[config.seed, tag::LAYOUT, 1]);
    // Classes: every furniture class once (shuffled), then random classes.
    let mut order = classes::FURNITURE.to_vec();
    for i in (1..order.len()).rev() {
        let j = rng.below(i + 1);
        order.swap(i, j);
    }
    let wanted: Vec<u32> = (0..config.objects)
        .map(|k| {
            if k < order.len() {
                order[k]
            } else {
                classes::FURNITURE[rng.below(classes::FURNITURE.len())]
            }
        })
        .collect();
    let mut candidates: Vec<(u32, ShapeSpec, [u8; 3], Texture)> = wanted
        .iter()
        .map(|&class| {
            let shape = sample_shape(class, &mut rng);
            let base = class_color(class);
            let color = base.map(|c| (c + rng.range(-25.0, 25.0)).round().clamp(0.0, 255.0) as u8);
            let texture = sample_texture(&mut rng);
            (class, shape, color, texture)
        })
        .collect();
    // Largest footprints first: rejection sampling succeeds more often.
    candidates.sort_by(|a, b| {
        let fa = a.1.footprint();
        let fb = b.1.footprint();
        (fb[0] * fb[1]).total_cmp(&(fa[0] * fa[1]))
    });
    let ell = placement_ellipse(config, room);
    let inside = |p: [f64; 2]| (p[0] / ell[0]).powi(2) + (p[1] / ell[1]).powi(2) <= 1.0;
    let mut placed: Vec<Footprint> = Vec::new();
    let mut out = Vec::new();
    let mut per_class = std::collections::BTreeMap::<u32, usize>::new();
    for (class, shape, color, texture) in candidates {
        // Up to 400 tries at full size, then at 85% and 70% of it; skipped if all fail.
        let mut spot = None;
        for shrink in [1.0, 0.85, 0.7] {
            let shape = shape.scaled(shrink);
            let h = shape.footprint();
            for _ in 0..400 {
                let f = Footprint {
                    c: [rng.range(-ell[0], ell[0]), rng.range(-ell[1], ell[1])],
                    h,
                    yaw: r32(rng.range(0.0, std::f64::consts::TAU)),
                };
                if f.corners().iter().all(|c| inside(*c))
                    && !placed.iter().any(|g| g.overlaps(&f, 0.12))
                {
                    spot = Some((f, shape));
                    break;
                }
            }
            if spot.is_some() {
                break;
            }
        }
        let Some((f, shape)) = spot else { continue };
        placed.push(f);
        let n = per_class.entry(class).or_default();
        let name = format!(
            "{}_{}",
            profuse_formats::label_space::nyu40_name(class).unwrap_or("object"),
            *n
        );
        *n += 1;
        out.push(ObjectSpec {
            index: first_index + out.len() as u32,
            name,
            class_id: class,
            class_name: profuse_formats::label_space::nyu40_name(class)
                .unwrap_or("unknown")
                .to_string(),
            room: false,
            translation: [r32(f.c[0]), r32(f.c[1]), shape.rest_height()],
            yaw: f.yaw,
            shape,
            color,
            texture,
        });
    }
    out
}

// Small vector helpers on [f64; 3].
pub(crate) fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub(crate) fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}
pub(crate) fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = norm(a);
    if n > 0.0 {
        scale(a, 1.0 / n)
    } else {
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(shape: ShapeSpec, translation: [f64; 3], yaw: f64) -> Scene {
        let o = ObjectSpec {
            index: 0,
            name: "x".into(),
            class_id: 3,
            class_name: "cabinet".into(),
            room: false,
            shape,
            translation,
            yaw,
            color: [100, 100, 100],
            texture: Texture::Plain,
        };
        match Scene::new([10.0, 10.0, 3.0], vec![o]) {
            Ok(s) => s,
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn cylinder_is_upright_and_exact() {
        let s = one(
            ShapeSpec::Cylinder {
                half_height: 0.4,
                radius: 0.5,
            },
            [0.0, 0.0, 0.4],
            0.3,
        );
        // From above: hits the top cap at z = 0.8.
        let h = s.raycast([0.1, 0.1, 3.0], [0.0, 0.0, -1.0]);
        let h = h.map(|h| (h.t, h.normal));
        assert!(
            matches!(h, Some((t, n)) if (t - 2.2).abs() < 1e-5 && (n[2] - 1.0).abs() < 1e-5),
            "{h:?}"
        );
        // From the side at height 0.2: hits the mantle at x = -0.5.
        let h = s.raycast([-3.0, 0.0, 0.2], [2.0, 0.0, 0.0]).map(|h| h.t);
        assert!(matches!(h, Some(t) if (t - 1.25).abs() < 1e-5), "{h:?}");
        assert!((s.distance_to_surface([0.0, 0.0, 1.8]) - 1.0).abs() < 1e-5);
        assert!((s.distance_to_surface([0.0, 0.0, 0.5]) - 0.3).abs() < 1e-5);
    }

    #[test]
    fn chair_mesh_is_closed_and_l_shaped() {
        let s = one(
            ShapeSpec::Chair {
                width: 0.5,
                depth: 0.5,
                seat_height: 0.45,
                back_height: 0.9,
                back_thickness: 0.1,
            },
            [0.0, 0.0, 0.0],
            0.0,
        );
        // Above the seat: hits z = 0.45; above the back: z = 0.9.
        let seat = s
            .raycast([0.1, 0.0, 2.0], [0.0, 0.0, -1.0])
            .map(|h| h.point[2]);
        let back = s
            .raycast([-0.2, 0.0, 2.0], [0.0, 0.0, -1.0])
            .map(|h| h.point[2]);
        assert!(
            matches!(seat, Some(z) if (z - 0.45).abs() < 1e-5),
            "{seat:?}"
        );
        assert!(
            matches!(back, Some(z) if (z - 0.9).abs() < 1e-5),
            "{back:?}"
        );
        // From the front at height 0.7: passes over the seat, hits the back's front face.
        let h = s
            .raycast([2.0, 0.0, 0.7], [-1.0, 0.0, 0.0])
            .map(|h| (h.point[0], h.normal[0]));
        assert!(
            matches!(h, Some((x, n)) if (x + 0.15).abs() < 1e-5 && n > 0.99),
            "{h:?}"
        );
        let Some(q) = (ShapeSpec::Chair {
            width: 0.5,
            depth: 0.5,
            seat_height: 0.45,
            back_height: 0.9,
            back_thickness: 0.1,
        })
        .quads() else {
            panic!("chair has quads")
        };
        // Closed: the outward-weighted face areas sum to zero.
        let mut sum = [0.0; 3];
        for quad in &q {
            let a = cross(quad.u, quad.v);
            let a = if dot(a, quad.n) < 0.0 {
                scale(a, -1.0)
            } else {
                a
            };
            sum = add(sum, a);
        }
        assert!(norm(sum) < 1e-12, "{sum:?}");
    }

    #[test]
    fn footprints_overlap_test() {
        let a = Footprint {
            c: [0.0, 0.0],
            h: [1.0, 0.5],
            yaw: 0.0,
        };
        let b = Footprint {
            c: [2.05, 0.0],
            h: [1.0, 0.5],
            yaw: 0.0,
        };
        assert!(!a.overlaps(&b, 0.0));
        assert!(a.overlaps(&b, 0.1));
        let c = Footprint {
            c: [1.6, 1.0],
            h: [0.5, 0.5],
            yaw: std::f64::consts::FRAC_PI_4,
        };
        assert!(!a.overlaps(&c, 0.0));
    }
}
